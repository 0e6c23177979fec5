"""Issue 11, part B: validation epsilon, result strings, which errors exist, deactivation.

Each test names the section of ``../shared/reference/jtc_upstream_behaviour.md`` it checks; the
controller is stepped on a simulated clock (``update(now, period, state)`` called here).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from jtc_hw import (
    ErrorCode,
    GoalRejected,
    GoalResult,
    GoalStatus,
    JointState,
    JointTrajectory,
    JointTrajectoryController,
    TrajectoryPoint,
)
from jtc_hw.controller.validation import FLT_EPSILON

from conftest import MS, Rig, make_config

NAMES = ("j1", "j2")
PERIOD = 10 * MS


def goal(t: float, positions: list[float], **fields: Any) -> JointTrajectory:
    return JointTrajectory(NAMES, [TrajectoryPoint(t, positions, **fields)])


def constraints(path: float = 0.0, goal_tol: float = 0.0, **extra: Any) -> dict[str, Any]:
    c: dict[str, Any] = {j: {"trajectory": path, "goal": goal_tol} for j in NAMES}
    c.update(extra)
    return c


def results(events: Any) -> list[GoalResult]:
    return [e for e in events if isinstance(e, GoalResult)]


# -- point 4: the last point's velocity, FLT_EPSILON -----------------------------------------


def test_flt_epsilon_is_upstreams() -> None:
    """Section 5 rule 5: FLT_EPSILON is C's, the float32 machine epsilon."""
    assert FLT_EPSILON == float(np.finfo(np.float32).eps)
    assert f"{FLT_EPSILON:.8g}" == "1.1920929e-07"


@pytest.mark.parametrize("path", ["columns", "per point"])
def test_last_velocity_within_flt_epsilon_counts_as_zero(path: str) -> None:
    """Section 5 rule 5: with allow_nonzero_velocity_at_trajectory_end false, a last-point
    velocity is non-zero only when |v| > FLT_EPSILON; rounding noise below it is accepted and
    the goal runs to success.

    ``per point``: a numpy float32 value makes the points irregular, so validation walks them
    one by one instead of checking whole columns; both paths apply the same rule.
    """
    config = make_config(
        allow_nonzero_velocity_at_trajectory_end=False, constraints=constraints(0.0, 0.01)
    )
    rig = Rig(config, [0.0, 0.0])
    tiny: list[Any] = [1e-7, -FLT_EPSILON]
    if path == "per point":
        tiny[0] = np.float32(1e-7)
    gid = rig.ctrl.send_goal(rig.now, goal(0.5, [0.3, -0.2], velocities=tiny))
    rig.run_until(lambda out: bool(rig.results(gid)), limit_s=2.0)
    assert rig.results(gid)[0].status is GoalStatus.SUCCEEDED


@pytest.mark.parametrize("value", [2.0**-23 * 1.0000001, 1.2e-7, -1e-6, 0.25])
def test_last_velocity_above_flt_epsilon_is_rejected(value: float) -> None:
    """Section 5 rule 5: |v| > FLT_EPSILON rejects the goal (INVALID_GOAL), naming the joint,
    the value and the limit."""
    ctrl = JointTrajectoryController(make_config(allow_nonzero_velocity_at_trajectory_end=False))
    ctrl.activate(0, JointState([0.0, 0.0], [0.0, 0.0]))
    with pytest.raises(GoalRejected) as info:
        ctrl.send_goal(0, goal(0.5, [0.3, -0.2], velocities=[0.0, value]))
    assert info.value.error_code == ErrorCode.INVALID_GOAL
    message = str(info.value)
    assert f"velocity of joint 'j2' is {value!r}, must be 0" in message
    assert "1.1920929e-07" in message and "allow_nonzero_velocity_at_trajectory_end" in message
