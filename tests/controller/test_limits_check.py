"""Goals against the joint limits (issue 12 part A): the splines' extremes, reject and fit.

Everything runs on the simulated clock (``Rig``); the reference the controller follows is
sampled densely to confirm what the analytic check claims.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jtc_hw import GoalResult, GoalStatus, JointTrajectory, TrajectoryPoint
from jtc_hw.controller.limits_check import LimitTable, check
from jtc_hw.controller.planner import Planner
from jtc_hw.controller.trajectory import Trajectory
from jtc_hw.errors import GoalRejected

from conftest import MS, Rig, S, make_config


def dense(ref: Trajectory, t0: int, t1: int, step: int = MS // 4) -> dict[str, np.ndarray]:
    """The reference sampled every ``step`` ns on ``[t0, t1]`` and 1 ns before each
    breakpoint (a segment's end value, where a cubic's acceleration peaks), jerk by finite
    differences."""
    ends = [b - 1 for b in ref.breakpoints_ns if t0 < b <= t1]
    times = sorted({*range(t0, t1 + 1, step), *ends})
    samples = [ref.sample(t) for t in times]
    acc = np.array([s.accelerations for s in samples])
    dt = np.diff(times)[:, None] / S
    return {
        "position": np.array([s.positions for s in samples]),
        "velocity": np.array([s.velocities for s in samples]),
        "acceleration": acc,
        "jerk": np.diff(acc, axis=0) / dt,
    }


def overshooting_goal() -> JointTrajectory:
    """Every waypoint's velocity is 0.9 or less, but the cubic lead-in from rest to
    (0.9 rad, 0.9 rad/s) in 1 s peaks at 1.2 rad/s at t = 2/3 s."""
    return JointTrajectory(
        ["j1", "j2"],
        [
            TrajectoryPoint(1.0, [0.9, 0.0], [0.9, 0.0]),
            TrajectoryPoint(2.0, [1.0, 0.0], [0.0, 0.0]),
        ],
    )


def test_a_spline_overshooting_a_velocity_limit_between_waypoints_is_rejected() -> None:
    rig = Rig(make_config(limits={"j1": {"velocity": 1.0}}), [0.0, 0.0])
    before = rig.ctrl.reference
    with pytest.raises(GoalRejected) as rejected:
        rig.ctrl.send_goal(rig.now, overshooting_goal())
    message = str(rejected.value)
    assert rejected.value.error_code == -1
    assert "'j1'" in message and "velocity limit" in message
    assert "t = 0.666667 s" in message  # the cubic's peak, not a waypoint
    assert "|velocity| 1.2 > 1" in message and "limits.j1.velocity" in message
    assert 'time_scaling "fit"' in message and "at least 1.2" in message
    assert rig.ctrl.reference is before  # nothing changed


def test_fit_slows_by_the_reported_factor_and_stays_within_the_limits() -> None:
    rig = Rig(
        make_config(limits={"j1": {"velocity": 1.0, "acceleration": 2.0}}),
        [0.0, 0.0],
    )
    start = rig.now
    goal_id = rig.ctrl.send_goal(start, overshooting_goal(), time_scaling="fit")
    scaling = rig.ctrl.last_time_scaling
    assert scaling is not None
    # Scale-invariant (the lead-in starts at rest): v / s <= 1 and a / s**2 <= 2; the
    # acceleration at the start, 3.6 rad/s**2, binds: s = sqrt(1.8).
    assert scaling.factor == pytest.approx(math.sqrt(1.8), rel=1e-6)
    assert scaling.duration_s == pytest.approx(2.0 * scaling.factor, rel=1e-6)
    ref = rig.ctrl.reference
    assert ref.end_ns - start == pytest.approx(scaling.duration_s * S, abs=2)
    seen = dense(ref, start, ref.end_ns)
    assert np.abs(seen["velocity"][:, 0]).max() <= 1.0 + 1e-9
    assert np.abs(seen["acceleration"][:, 0]).max() <= 2.0 + 1e-9
    # The smallest factor: the binding limit is reached, not merely respected.
    assert np.abs(seen["acceleration"][:, 0]).max() == pytest.approx(2.0, rel=1e-6)
    # The path is unchanged: the same waypoints, reached at the scaled times.
    p = ref.sample(start + round(scaling.factor * S)).positions
    assert p[0] == pytest.approx(0.9, abs=1e-6)
    rig.run_until(lambda _: rig.results(goal_id), limit_s=10)
    assert rig.results(goal_id)[0].status is GoalStatus.SUCCEEDED


def test_the_parameter_makes_fit_the_default_and_a_goal_can_still_ask_for_reject() -> None:
    rig = Rig(make_config(limits={"time_scaling": "fit", "j1": {"velocity": 1.0}}), [0.0, 0.0])
    rig.ctrl.send_goal(rig.now, overshooting_goal())
    assert rig.ctrl.last_time_scaling is not None
    assert rig.ctrl.last_time_scaling.factor == pytest.approx(1.2, rel=1e-6)
    with pytest.raises(GoalRejected, match="velocity limit"):
        rig.ctrl.send_goal(rig.now, overshooting_goal(), time_scaling="reject")
    with pytest.raises(GoalRejected, match="time_scaling: 'fast' is not one of"):
        rig.ctrl.send_goal(rig.now, overshooting_goal(), time_scaling="fast")


def test_a_fitting_goal_with_fit_reports_a_factor_of_one_and_without_fit_nothing() -> None:
    rig = Rig(make_config(limits={"j1": {"velocity": 5.0}}), [0.0, 0.0])
    rig.ctrl.send_goal(rig.now, overshooting_goal(), time_scaling="fit")
    assert rig.ctrl.last_time_scaling == (1.0, 2.0)
    rig.ctrl.send_goal(rig.now, overshooting_goal())
    assert rig.ctrl.last_time_scaling is None


def test_the_position_range_is_checked_on_the_spline_and_fit_cannot_fix_it() -> None:
    # Waypoints inside [-1, 1]; the cubic through (0.95, 0.5 rad/s) overshoots 1 on its way
    # to (0.9, 0) after it.
    rig = Rig(make_config(limits={"j2": {"position": [-1.0, 1.0]}}), [0.0, 0.0])
    goal = JointTrajectory(
        ["j1", "j2"],
        [
            TrajectoryPoint(1.0, [0.0, 0.95], [0.0, 0.5]),
            TrajectoryPoint(2.0, [0.0, 0.9], [0.0, 0.0]),
        ],
    )
    for mode in ("reject", "fit"):
        with pytest.raises(GoalRejected) as rejected:
            rig.ctrl.send_goal(rig.now, goal, time_scaling=mode)
        message = str(rejected.value)
        assert "'j2' leaves its position range [-1, 1]" in message
        assert "limits.j2.position" in message and "slowing down cannot change the path" in message
    within = JointTrajectory(["j1", "j2"], [TrajectoryPoint(1.0, [0.0, 0.95], [0.0, 0.0])])
    rig.ctrl.send_goal(rig.now, within)


def test_a_joint_outside_its_range_may_be_brought_back_but_not_further_out() -> None:
    rig = Rig(make_config(limits={"j1": {"position": [-1.0, 1.0]}}), [1.5, 0.0])
    back = JointTrajectory(["j1", "j2"], [TrajectoryPoint(2.0, [0.5, 0.0])])
    rig.ctrl.send_goal(rig.now, back)
    rig2 = Rig(make_config(limits={"j1": {"position": [-1.0, 1.0]}}), [1.5, 0.0])
    out = JointTrajectory(["j1", "j2"], [TrajectoryPoint(2.0, [1.6, 0.0])])
    with pytest.raises(GoalRejected, match=r"position 1\.6 > 1"):
        rig2.ctrl.send_goal(rig2.now, out)


def test_the_velocity_kept_past_the_end_is_checked() -> None:
    rig = Rig(make_config(limits={"j1": {"velocity": 1.0}}), [0.0, 0.0])
    goal = JointTrajectory(["j1", "j2"], [TrajectoryPoint(10.0, [1.0, 0.0], [1.5, 0.0])])
    with pytest.raises(GoalRejected, match="past the last point"):
        rig.ctrl.send_goal(rig.now, goal)


def test_jerk_of_quintic_segments_and_fit_by_its_cube_root() -> None:
    limits = {"j1": {"jerk": 10.0}}
    rig = Rig(make_config(limits=limits), [0.0, 0.0])
    goal = JointTrajectory(
        ["j1", "j2"], [TrajectoryPoint(1.0, [1.0, 0.0], [0.0, 0.0], [0.0, 0.0])]
    )
    # Rest to rest in 1 s, quintic: jerk 60 h / T**3 at both ends.
    with pytest.raises(GoalRejected, match=r"\|jerk\| 60 > 10"):
        rig.ctrl.send_goal(rig.now, goal)
    start = rig.now
    rig.ctrl.send_goal(start, goal, time_scaling="fit")
    scaling = rig.ctrl.last_time_scaling
    assert scaling is not None and scaling.factor == pytest.approx(6.0 ** (1 / 3), rel=1e-6)
    seen = dense(rig.ctrl.reference, start, rig.ctrl.reference.end_ns, step=MS // 8)
    assert np.abs(seen["jerk"][:, 0]).max() <= 10.0 * (1 + 1e-3)


def test_a_moving_lead_in_is_fitted_in_a_few_rounds() -> None:
    """Replacing a running goal: the lead-in starts with the current velocity, which does
    not scale, so the factor is found in more than one round; the result still fits."""
    cfg = make_config(limits={"j1": {"velocity": 1.0, "acceleration": 4.0}})
    rig = Rig(cfg, [0.0, 0.0])
    rig.ctrl.send_goal(
        rig.now, JointTrajectory(["j1", "j2"], [TrajectoryPoint(4.0, [2.0, 0.0], [0.0, 0.0])])
    )
    rig.step(150)
    assert abs(rig.ctrl.reference.sample(rig.now).velocities[0]) > 0.5
    back = JointTrajectory(["j1", "j2"], [TrajectoryPoint(0.3, [0.0, 0.0], [0.0, 0.0])])
    start = rig.now
    rig.ctrl.send_goal(start, back, time_scaling="fit")
    scaling = rig.ctrl.last_time_scaling
    assert scaling is not None and scaling.factor > 1.0
    seen = dense(rig.ctrl.reference, start, rig.ctrl.reference.end_ns)
    assert np.abs(seen["velocity"][:, 0]).max() <= 1.0 + 1e-9
    assert np.abs(seen["acceleration"][:, 0]).max() <= 4.0 + 1e-9


def test_method_none_checks_the_held_values() -> None:
    cfg = make_config(interpolation_method="none", limits={"j1": {"velocity": 1.0}})
    rig = Rig(cfg, [0.0, 0.0])
    goal = JointTrajectory(
        ["j1", "j2"],
        [
            TrajectoryPoint(1.0, [1.0, 0.0], [0.0, 0.0]),
            TrajectoryPoint(2.0, [2.0, 0.0], [2.0, 0.0]),  # held from point 1 on (section 4.6)
            TrajectoryPoint(3.0, [3.0, 0.0], [0.0, 0.0]),
        ],
    )
    with pytest.raises(GoalRejected, match=r"\|velocity\| 2 > 1"):
        rig.ctrl.send_goal(rig.now, goal)
    rig.ctrl.send_goal(rig.now, goal, time_scaling="fit")
    assert rig.ctrl.last_time_scaling is not None
    assert rig.ctrl.last_time_scaling.factor == pytest.approx(2.0, rel=1e-6)


def test_topic_trajectories_and_partial_goals_are_checked_for_the_joints_they_name() -> None:
    cfg = make_config(
        allow_partial_joints_goal=True,
        limits={"j1": {"velocity": 1.0}, "j2": {"velocity": 1.0}},
    )
    rig = Rig(cfg, [0.0, 0.0])
    fast = JointTrajectory(["j2"], [TrajectoryPoint(0.5, [1.0])])  # linear: 2 rad/s
    with pytest.raises(GoalRejected, match="'j2' exceeds its velocity limit"):
        rig.ctrl.send_trajectory(rig.now, fast)
    rig.ctrl.send_trajectory(rig.now, fast, time_scaling="fit")
    assert rig.ctrl.last_time_scaling is not None
    assert rig.ctrl.last_time_scaling.factor == pytest.approx(2.0, rel=1e-6)


def test_no_limits_no_check() -> None:
    planner = Planner(make_config(limits={"j1": {"effort": 3.0}}))
    assert planner.limits is None  # effort alone: nothing a trajectory's shape can exceed


# --------------------------------------------------------------------------------------------
# Property: the analytic extremes are the sampled ones, and fit always fits
# --------------------------------------------------------------------------------------------

values = st.floats(-2.0, 2.0, allow_nan=False)


@st.composite
def goals(draw: Any) -> tuple[list[TrajectoryPoint], str]:
    fields = draw(st.sampled_from(["p", "pv", "pva"]))
    m = draw(st.integers(1, 4))
    t = 0
    points = []
    for _ in range(m):
        t += draw(st.integers(50, 800)) * MS
        pos = [draw(values), draw(values)]
        vel = [draw(values), draw(values)] if "v" in fields else None
        acc = [4 * draw(values), 4 * draw(values)] if "a" in fields else None
        points.append(TrajectoryPoint(None, pos, vel, acc, time_from_start_ns=t))
    return points, fields


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(goal=goals())
def test_property_the_check_agrees_with_dense_sampling_and_fit_fits(
    goal: tuple[list[TrajectoryPoint], str],
) -> None:
    points, _fields = goal
    limits = {"velocity": 1.5, "acceleration": 6.0, "jerk": 80.0}
    cfg = make_config(limits={"j1": limits, "j2": limits})
    rig = Rig(cfg, [0.0, 0.0])
    traj = JointTrajectory(["j1", "j2"], points)
    start = rig.now
    # What the goal would follow, unchecked, sampled densely.
    unchecked = Planner(make_config()).plan_goal(rig.ctrl.reference, 0, start, traj).reference
    seen = dense(unchecked, start, unchecked.end_ns, step=MS // 2)
    table = LimitTable.of(cfg.joints, cfg.limits)
    assert table is not None
    found = check(unchecked, start, table, np.arange(2), np.zeros(2))
    for name in ("velocity", "acceleration"):  # jerk steps at knots blur differences
        peak = float(np.abs(seen[name]).max())
        if name in found:  # the true extreme: at least what sampling saw, hardly more
            value = abs(found[name].value)
            assert peak * (1 - 1e-9) - 1e-9 <= value <= peak * 1.01 + 1e-3
        else:
            assert peak <= limits[name] * (1 + 1e-6), f"{name}: sampled {peak}, not found"
    try:
        rig.ctrl.send_goal(start, traj, time_scaling="fit")
    except GoalRejected as exc:  # only a lead-in that slowing cannot fix may remain
        assert "even slowed down" in str(exc)
        return
    scaling = rig.ctrl.last_time_scaling
    assert scaling is not None and scaling.factor >= 1.0
    ref = rig.ctrl.reference
    fitted = dense(ref, start, ref.end_ns, step=MS // 2)
    assert np.abs(fitted["velocity"]).max() <= limits["velocity"] * (1 + 1e-6)
    assert np.abs(fitted["acceleration"]).max() <= limits["acceleration"] * (1 + 1e-6)
    assert not check(ref, start, table, np.arange(2), np.zeros(2))
    if scaling.factor > 1.0:  # the smallest factor: with limits 1 % lower it would not fit
        tighter = LimitTable(
            table.names, table.low, table.high, table.velocity * 0.99,
            table.acceleration * 0.99, table.jerk * 0.99,
        )
        assert check(ref, start, tighter, np.arange(2), np.zeros(2))


def test_a_fit_goal_runs_to_success_within_the_limits_on_the_simulated_clock() -> None:
    cfg = make_config(
        limits={"time_scaling": "fit", "j1": {"velocity": 0.5, "acceleration": 1.0}},
        constraints={"goal_time": 1.0},
    )
    rig = Rig(cfg, [0.0, 0.0])
    goal = JointTrajectory(
        ["j1", "j2"],
        [TrajectoryPoint(0.5, [0.5, 0.1], [1.0, 0.0]), TrajectoryPoint(1.0, [1.0, 0.2])],
    )
    goal_id = rig.ctrl.send_goal(rig.now, goal)
    commanded = []
    while not rig.results(goal_id):
        out = rig.step()
        commanded.append(out.desired.velocities[0])
    result = rig.results(goal_id)[0]
    assert isinstance(result, GoalResult) and result.status is GoalStatus.SUCCEEDED
    assert max(abs(v) for v in commanded) <= 0.5 + 1e-9
