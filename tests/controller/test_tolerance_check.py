"""The cycle's one-comparison tolerance check against the per-field rule it stands for.

``exceeds(error, limit)`` must say exactly what ``violated(error, tolerance).any()`` says: a
field is checked only where its tolerance is above 0, and its error violates it when
``|error| > tolerance`` (NaN never does, infinity always does on a checked field).
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from jtc_hw.controller.tolerances import SegmentTolerances, exceeds, violated

N = 4
VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 0.1, -0.1, 1e-300, np.inf, -np.inf, np.nan]),
)


@settings(max_examples=500, deadline=None)
@given(
    error=arrays(np.float64, (3, N), elements=VALUES),
    path=arrays(np.float64, (3, N), elements=st.sampled_from([0.0, 0.1, 1.0, 1e-300, 5.0])),
    goal=arrays(np.float64, (3, N), elements=st.sampled_from([0.0, 0.1, 1.0, 1e-300, 5.0])),
)
def test_exceeds_is_violated_any(error: np.ndarray, path: np.ndarray, goal: np.ndarray) -> None:
    tol = SegmentTolerances(path, goal, 0.0)
    assert exceeds(error, tol.path_limit) == bool(violated(error, tol.path).any())
    assert exceeds(error, tol.goal_limit) == bool(violated(error, tol.goal).any())


def test_limits_follow_overrides() -> None:
    base = SegmentTolerances(np.full((3, 1), 0.5), np.zeros((3, 1)), 0.0)
    erased = base.with_overrides(["j"], path_tolerance=[], goal_tolerance=[])
    assert np.array_equal(erased.path_limit, base.path_limit)
    assert np.isinf(erased.goal_limit).all()
    assert exceeds(np.array([[0.6], [0.0], [0.0]]), base.path_limit)
    assert not exceeds(np.array([[0.4], [0.0], [0.0]]), base.path_limit)
