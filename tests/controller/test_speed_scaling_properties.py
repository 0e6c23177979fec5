"""Property: random speed scaling changes during a goal (issue 12 part C).

Whatever factors in [0, 1] are set, whenever, on whichever forwarded command interfaces: the
reference the joints are given never changes velocity faster than the acceleration limits
allow, the factor moves monotonically toward each target without overshooting it, the joints
stay within the path tolerance, and once the factor is back at 1 the goal ends with exactly
one result, at the goal's last point (the path is not changed, only the time along it).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_speed_scaling import ACCEL, INTERFACES, NAMES, PATH_TOL, Run, goal

from jtc_hw import GoalStatus
from jtc_hw.config.limits import JointLimits

from conftest import make_config

FORWARDED = ["position", "position_velocity", "position_velocity_acceleration"]


@settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    interfaces=st.sampled_from(FORWARDED),
    changes=st.lists(
        st.tuples(
            st.integers(min_value=0, max_value=60),  # cycles before the change
            st.floats(min_value=0.0, max_value=1.0, allow_nan=False),
        ),
        min_size=1,
        max_size=8,
    ),
)
def test_random_factor_changes_keep_the_limits_and_one_result(
    interfaces: str, changes: list[tuple[int, float]]
) -> None:
    cfg = make_config(
        NAMES,
        constraints={
            "goal_time": 1.0,
            **{j: {"trajectory": PATH_TOL, "goal": 0.01} for j in NAMES},
        },
        **INTERFACES[interfaces],
    )
    cfg = dataclasses.replace(
        cfg, limits={j: JointLimits(acceleration=a) for j, a in ACCEL.items()}
    )
    run = Run(cfg)
    gid = run.ctrl.send_goal(run.now, goal())
    dt = run.period / 1e9
    bound = np.array([ACCEL[j] for j in NAMES]) * dt * 1.02 + 1e-12
    factors: list[float] = []
    targets: list[float] = []
    for wait, factor in [*changes, (0, 1.0)]:
        for _ in range(wait):
            out = run.step()
            factors.append(out.state.speed_scaling_factor)
            targets.append(out.state.speed_scaling_target)
        run.ctrl.set_speed_scaling(factor)
    run.until(lambda out: bool(run.results()), limit_s=30.0)
    for _ in range(20):
        run.step()
    steps = np.abs(np.diff(np.array(run.desired_v), axis=0))
    assert (steps <= bound).all(), steps.max(axis=0)
    assert all(0.0 <= f <= 1.0 for f in factors)
    for f0, f1, t in zip(factors, factors[1:], targets[1:], strict=False):
        # Toward the target in force at f1's cycle (set before that update: upstream, it is in
        # force from the next update), never past it.
        assert (f1 - f0) * (t - f0) >= 0.0
        assert min(f0, t) - 1e-12 <= f1 <= max(f0, t) + 1e-12
    errors = np.array([np.abs(s.error[0]) for s in run.states])
    assert (errors <= PATH_TOL).all(), errors.max()
    results = run.results()
    assert len(results) == 1 and results[0].goal_id == gid
    assert results[0].status is GoalStatus.SUCCEEDED
    np.testing.assert_allclose(run.mirror.p, [1.0, -0.5], atol=0.01)
