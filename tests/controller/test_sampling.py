"""Issue 11, points 1, 2, 3 and 5: sampling and decision timing as upstream's controller does.

Every test drives the pure controller on a simulated clock (``Rig``: ideal mirrored joints)
and names the section of ``../shared/reference/jtc_upstream_behaviour.md`` it checks.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from jtc_hw import (
    ErrorCode,
    GoalResult,
    GoalStatus,
    JointState,
    JointTrajectory,
    JointTrajectoryController,
    TrajectoryPoint,
    TrajectoryStopped,
)
from jtc_hw.controller.parameters import explain

from conftest import MS, Rig, S, make_config

NAMES = ("j1", "j2")


def streaming_config(**params: Any) -> Any:
    """Position and velocity commands (a velocity interface a servoing client drives)."""
    params.setdefault("command_interfaces", ("position", "velocity"))
    params.setdefault("allow_nonzero_velocity_at_trajectory_end", True)
    return make_config(joints=("j",), **params)


# -- point 1: after the last point ----------------------------------------------------------------


def test_streamed_last_point_keeps_its_velocity_until_cmd_timeout() -> None:
    """Section 4.3 step 6: past the last point the reference is that point as given, its
    velocity kept, so a servoing client's joint keeps moving between messages; section 7 step
    8a / 8e: cmd_timeout (a topic trajectory never succeeds) is what stops it."""
    # Inside the goal tolerance after the end: only cmd_timeout ends it (not a "success").
    config = streaming_config(cmd_timeout=0.2, constraints={"stopped_velocity_tolerance": 10.0})
    rig = Rig(config, [0.0])
    period = rig.period
    for k in range(3):  # a client publishing one point 50 ms ahead, every 40 ms
        rig.ctrl.send_trajectory(
            rig.now, JointTrajectory(("j",), [TrajectoryPoint(0.05, [0.05 * (k + 1)], [1.0])])
        )
        rig.step(4)
    end = rig.now + 10 * MS  # the last message's point is due 50 ms after it was sent
    # Between the last point and cmd_timeout the command keeps the point's velocity.
    while rig.now <= end + 200 * MS - period:
        out = rig.step()
        if rig.now - period >= end:
            assert out.command.velocities[0] == 1.0
            assert out.command.positions[0] == pytest.approx(0.15)
        assert not [e for e in rig.events if isinstance(e, TrajectoryStopped)]
    rig.run_until(lambda out: any(isinstance(e, TrajectoryStopped) for e in out.events))
    (stopped,) = [e for e in rig.events if isinstance(e, TrajectoryStopped)]
    assert "cmd_timeout 0.2 s" in stopped.reason
    assert end + 200 * MS < stopped.time_ns <= end + 200 * MS + period
    out = rig.step()
    assert out.command.velocities[0] == 0.0  # the hold: zero velocity
    assert rig.ctrl.holding


def test_without_cmd_timeout_nothing_stops_a_kept_velocity_and_check_warns() -> None:
    """Section 4.3 step 6: with cmd_timeout 0 the kept velocity is commanded until the next
    command; ``explain`` (``jtc-hw check``) warns about exactly that configuration."""
    config = streaming_config()
    rig = Rig(config, [0.0])
    rig.ctrl.send_trajectory(rig.now, JointTrajectory(("j",), [TrajectoryPoint(0.1, [0.1], [0.5])]))
    for _ in range(500):  # 5 s after a 0.1 s trajectory
        out = rig.step()
    assert out.command.velocities[0] == 0.5
    warning = "a trajectory ending with a velocity keeps the joints moving"
    assert any(warning in w for w in explain(config))
    assert not any(warning in w for w in explain(streaming_config(cmd_timeout=0.5)))
    assert not any(
        warning in w for w in explain(streaming_config(command_interfaces=("position",)))
    )
    assert not any(
        warning in w
        for w in explain(streaming_config(allow_nonzero_velocity_at_trajectory_end=False))
    )
    # A cmd_timeout that is ignored (not above goal_time) is no guard: still warned.
    ignored = streaming_config(cmd_timeout=0.2, constraints={"goal_time": 0.5})
    assert any(warning in w for w in explain(ignored))


def test_a_new_command_starts_from_the_kept_velocity() -> None:
    """Section 4.3 step 6: the kept velocity is part of the reference, so the next streamed
    point is spliced from it (the joint does not stop between messages)."""
    rig = Rig(streaming_config(), [0.0])
    rig.ctrl.send_trajectory(
        rig.now, JointTrajectory(("j",), [TrajectoryPoint(0.05, [0.05], [1.0])])
    )
    rig.step(8)  # 30 ms past the point
    assert rig.ctrl.query_state(rig.now).velocities[0] == 1.0
    rig.ctrl.send_trajectory(
        rig.now, JointTrajectory(("j",), [TrajectoryPoint(0.05, [0.1], [1.0])])
    )
    np.testing.assert_array_equal(rig.ctrl.query_state(rig.now).velocities, [1.0])


# -- point 2: sampling outside the trajectory and query_state ------------------------------------


def test_query_state_succeeds_only_inside_the_trajectory() -> None:
    """Section 16 query_state: success false while holding and at or after the last point
    (carrying the last point's values), true strictly inside; section 4.3 step 3: before the
    reference's start, success false carrying the current (measured) state."""
    rig = Rig(make_config(), [0.3, -0.2])
    t0 = rig.now
    rig.step()
    held = rig.ctrl.query_state(rig.now)  # a hold is one point: always "after its end"
    assert (held.success, held.where) == (False, "after_end")
    np.testing.assert_array_equal(held.positions, [0.3, -0.2])
    start = rig.now
    rig.ctrl.send_goal(start, JointTrajectory(NAMES, [TrajectoryPoint(1.0, [1.0, 1.0])]))
    inside = rig.ctrl.query_state(start + 500 * MS)
    assert (inside.success, inside.where) == (True, "inside")
    np.testing.assert_allclose(inside.positions, [0.65, 0.4])
    for t in (start + S, start + 5 * S):
        end = rig.ctrl.query_state(t)
        assert (end.success, end.where) == (False, "after_end")
        np.testing.assert_array_equal(end.positions, [1.0, 1.0])
    measured = JointState([0.31, -0.19], [0.25, -0.5])
    rig.ctrl.update(rig.now, rig.period, measured)
    before = rig.ctrl.query_state(t0 - S)
    assert (before.success, before.where) == (False, "before_start")
    np.testing.assert_array_equal(before.positions, [0.31, -0.19])
    np.testing.assert_array_equal(before.velocities, [0.25, -0.5])


def test_a_cycle_before_the_reference_starts_commands_nothing() -> None:
    """Section 4.3 step 3: sampling before the state-before time fails, so a cycle there (a
    clock that went back) decides and commands nothing (``NaN``: write nothing)."""
    ctrl = JointTrajectoryController(make_config())
    ctrl.activate(10 * S, JointState([0.3, -0.2], [0.0, 0.0]))
    ctrl.send_goal(10 * S, JointTrajectory(NAMES, [TrajectoryPoint(0.01, [5.0, 5.0])]))
    out = ctrl.update(10 * S - 10 * MS, 10 * MS, JointState([0.3, -0.2], [0.0, 0.0]))
    assert np.isnan(out.command.positions).all()
    assert out.events == ()
    np.testing.assert_array_equal(out.desired.positions, [0.3, -0.2])
    with pytest.raises(ValueError, match="defined from 10000000000 ns"):
        ctrl.reference.sample(10 * S - 1)


# -- point 3: interpolation none -----------------------------------------------------------------


def test_none_commands_the_next_point_during_each_segment() -> None:
    """Section 4.6: with ``interpolation_method: none`` the reference is the state before
    during the lead-in, then point i + 1 during segment i (so point 0 is never output), then
    the last point."""
    rig = Rig(make_config(interpolation_method="none"), [0.0, 0.0])
    start = rig.now
    points = [(0.1, [1.0, -1.0]), (0.2, [2.0, -2.0]), (0.3, [3.0, -3.0])]
    gid = rig.ctrl.send_goal(
        start, JointTrajectory(NAMES, [TrajectoryPoint(t, p) for t, p in points])
    )
    seen = []
    while not rig.results(gid):
        t = rig.now
        rig.step()
        seen.append((t - start, rig.ctrl.query_state(t).positions.tolist()))
    expected = {
        0: [0.0, 0.0],
        50 * MS: [0.0, 0.0],
        100 * MS: [2.0, -2.0],
        150 * MS: [2.0, -2.0],
        200 * MS: [3.0, -3.0],
        250 * MS: [3.0, -3.0],
    }
    for t, positions in seen:
        if t in expected:
            assert positions == expected[t], t
    assert all(p != [1.0, -1.0] for _, p in seen)  # point 0 is never the reference
    np.testing.assert_array_equal(rig.mirror.p, [3.0, -3.0])


# -- point 5: decision timing ---------------------------------------------------------------------


@pytest.mark.parametrize("rate", [100.0, 250.0])
def test_success_is_decided_when_the_look_ahead_reaches_the_last_point(rate: float) -> None:
    """Section 7 step 8: "before the last point" is judged on the look-ahead sample
    (traj_time + period): the goal succeeds at the first cycle whose look-ahead reaches the
    last point, one period before the reference does (here the end, 1.005 s, is not on the
    cycle grid)."""
    rig = Rig(
        make_config(update_rate=rate, constraints={"stopped_velocity_tolerance": 10.0}), [0.0, 0.0]
    )
    start = rig.now
    gid = rig.ctrl.send_goal(start, JointTrajectory(NAMES, [TrajectoryPoint(1.005, [1.0, 1.0])]))
    rig.run_until(lambda out: bool(rig.results(gid)))
    (result,) = rig.results(gid)
    assert result.status is GoalStatus.SUCCEEDED
    end = start + 1005 * MS
    assert result.time_ns < end <= result.time_ns + rig.period  # its look-ahead reached it
    assert rig.ctrl.query_state(result.time_ns).success  # the reference had not


def test_goal_tolerance_not_path_tolerance_in_the_last_period() -> None:
    """Section 7 step 8b: from the cycle whose look-ahead reaches the last point the goal
    tolerance is checked, no longer the path tolerance: a joint outside the path tolerance
    there is not a path violation (old behaviour) but, with goal_time exceeded, a goal-time
    abort."""
    c = {j: {"trajectory": 0.05, "goal": 0.01} for j in NAMES}
    c["goal_time"] = 0.001
    rig = Rig(make_config(constraints=c), [0.0, 0.0])
    start = rig.now
    gid = rig.ctrl.send_goal(start, JointTrajectory(NAMES, [TrajectoryPoint(1.0, [1.0, 1.0])]))
    while rig.now < start + 1 * S - rig.period:
        rig.step()
    assert rig.results(gid) == []
    rig.mirror.frozen = True
    rig.mirror.p = np.array([0.5, 0.5])  # far outside both tolerances, in the last period
    out = rig.step()  # now = end - period: look-ahead at the end
    assert [e for e in out.events if isinstance(e, GoalResult)] == []  # goal_time not yet over
    rig.run_until(lambda out: bool(rig.results(gid)))
    (result,) = rig.results(gid)
    assert result.status is GoalStatus.ABORTED
    assert result.error_code is ErrorCode.GOAL_TOLERANCE_VIOLATED  # not a path violation
