"""The controller stepped on a simulated clock against ideal mirror joints (no sleeps)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from jtc_hw import (
    ControllerStateError,
    ErrorCode,
    GoalFeedback,
    GoalRejected,
    GoalResult,
    GoalStatus,
    HardwareError,
    JointCommand,
    JointState,
    JointTolerance,
    JointTrajectory,
    JointTrajectoryController,
    TrajectoryPoint,
    TrajectoryStopped,
)
from jtc_hw.errors import StalePlan

from conftest import MS, Rig, S, make_config, pid_controller

NAMES = ("j1", "j2")


def traj(
    *points: tuple[float, list[float]], start_time_ns: int = 0, **fields: Any
) -> JointTrajectory:
    return JointTrajectory(
        NAMES, [TrajectoryPoint(t, p, **fields) for t, p in points], start_time_ns
    )


def constraints(traj_tol: float = 0.0, goal_tol: float = 0.0, **extra: Any) -> dict[str, Any]:
    c: dict[str, Any] = {j: {"trajectory": traj_tol, "goal": goal_tol} for j in NAMES}
    c.update(extra)
    return c


# -- lifecycle ----------------------------------------------------------------------------------


def test_calls_before_activation_are_refused() -> None:
    ctrl = JointTrajectoryController(make_config())
    with pytest.raises(ControllerStateError):
        ctrl.update(0, 10 * MS, JointState([0, 0], [0, 0]))
    with pytest.raises(GoalRejected, match="not active"):
        ctrl.send_goal(0, traj((1.0, [1, 1])))
    with pytest.raises(ControllerStateError):
        ctrl.query_state(0)


def test_activation_holds_measured_position_without_a_step() -> None:
    rig = Rig(make_config(), [0.3, -0.2])
    out = rig.step()
    np.testing.assert_array_equal(out.command.positions, [0.3, -0.2])
    assert rig.ctrl.holding


@pytest.mark.parametrize(
    ("flag", "last", "expected"),
    [
        (True, [0.5, 0.6], [0.5, 0.6]),  # restart: continue from the last command
        (True, [0.5, math.nan], [0.3, -0.2]),  # NaN = no value: measured state
        (False, [0.5, 0.6], [0.3, -0.2]),
    ],
)
def test_activation_with_last_command(flag: bool, last: list[float], expected: list[float]) -> None:
    config = make_config(set_last_command_interface_value_as_state_on_activation=flag)
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.3, -0.2], [0, 0]), JointCommand(positions=last))
    out = ctrl.update(0, 10 * MS, JointState([0.3, -0.2], [0, 0]))
    np.testing.assert_array_equal(out.command.positions, expected)


def test_start_without_holding_commands_nothing_until_a_trajectory() -> None:
    rig = Rig(make_config(start_with_holding=False), [0.1, 0.2])
    assert np.isnan(rig.step().command.positions).all()
    rig.ctrl.send_goal(rig.now, traj((1.0, [0.1, 0.2])))
    assert not np.isnan(rig.step().command.positions).any()


def test_reactivation_discards_the_old_goal_and_holds_the_new_position() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((2.0, [1.0, 1.0])))
    rig.step(50)
    events = rig.ctrl.deactivate(rig.now)
    (result,) = [e for e in events if isinstance(e, GoalResult)]
    assert (result.goal_id, result.status) == (gid, GoalStatus.ABORTED)  # upstream section 3
    rig.mirror.p = np.array([-0.4, 0.7])  # moved while inactive (e.g. torque off)
    rig.ctrl.activate(rig.now, rig.mirror.state())
    for _ in range(300):
        np.testing.assert_array_equal(rig.step().command.positions, [-0.4, 0.7])
    assert rig.results(gid) == []  # its one result came with deactivate


def test_fault_deactivation_aborts_with_reason() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((2.0, [1.0, 1.0])))
    rig.step(3)
    events = rig.ctrl.deactivate(rig.now, "servo 3 overheated")
    result = [e for e in events if isinstance(e, GoalResult)][0]
    assert (result.goal_id, result.status, result.error_string) == (
        gid,
        GoalStatus.ABORTED,
        "servo 3 overheated",
    )


def test_nan_state_is_never_taken_for_a_position() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    rig.step(10)
    before = rig.ctrl.reference
    with pytest.raises(HardwareError, match="j2"):
        rig.ctrl.update(rig.now, 10 * MS, JointState([0.1, math.nan], [0, 0]))
    assert rig.ctrl.reference is before


# -- execution and time base ------------------------------------------------------------------


def test_goal_succeeds_one_period_before_the_end_and_not_before() -> None:
    """Upstream section 7 step 8: success is judged on the look-ahead sample, one period
    before the reference reaches the last point (issue 11; it was at the end before)."""
    # The mirror measures velocity by backward difference, like an encoder: a cubic arriving
    # with zero velocity reads up to 0.06 rad/s at the last knot, inside this stopped tolerance.
    config = make_config(constraints=constraints(0.05, 0.01, stopped_velocity_tolerance=0.1))
    rig = Rig(config, [0.0, 0.0])
    points = ((0.5, [0.5, -0.5], [1.5, 0.0]), (1.0, [1.0, 0.0], [0.0, 0.0]))
    gid = rig.ctrl.send_goal(
        rig.now, JointTrajectory(NAMES, [TrajectoryPoint(t, p, v) for t, p, v in points])
    )
    end = rig.now + 1 * S
    while rig.now < end - 10 * MS:
        rig.step()
        assert rig.results(gid) == []  # success is never reported early
    rig.step()
    (result,) = rig.results(gid)
    assert (result.status, result.error_code, result.time_ns) == (
        GoalStatus.SUCCEEDED,
        ErrorCode.SUCCESSFUL,
        end - 10 * MS,
    )
    rig.step(100)
    assert rig.results(gid) == [result]
    np.testing.assert_allclose(rig.mirror.p, [1.0, 0.0])


def test_command_leads_by_one_period() -> None:
    """The command written at cycle t is the reference at t + T: an ideal joint tracks exactly."""
    rig = Rig(make_config(), [0.0, 0.0])
    rig.ctrl.send_goal(
        rig.now,
        traj(
            (
                0.5,
                [0.3, 0.1],
            ),
            (1.0, [1.0, -1.0]),
        ),
    )
    for _ in range(120):
        t = rig.now
        out = rig.step()
        np.testing.assert_allclose(out.error[0], 0.0, atol=1e-12)
        np.testing.assert_array_equal(
            out.command.positions, rig.ctrl.query_state(t + 10 * MS).positions
        )


def test_no_step_on_new_or_replacing_goal() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    rig.step(40)
    prev = rig.last.command.positions.copy()
    before = rig.ctrl.query_state(rig.now).positions.copy()
    rig.ctrl.send_goal(rig.now, traj((1.0, [-1.0, 0.5])))
    np.testing.assert_array_equal(rig.ctrl.query_state(rig.now).positions, before)
    out = rig.step()
    # The new command continues from the old reference: it moves by one period's travel at the
    # new segment's speed (1.4 rad/s here), not by a step towards the measured state.
    assert np.abs(out.command.positions - prev).max() == pytest.approx(0.014)


def test_future_start_time_holds_until_then() -> None:
    rig = Rig(make_config(constraints={"stopped_velocity_tolerance": 10.0}), [0.2, 0.2])
    start = rig.now + 1 * S
    gid = rig.ctrl.send_goal(rig.now, traj((0.5, [1.0, 1.0]), start_time_ns=start))
    while rig.now + 10 * MS < start:
        np.testing.assert_array_equal(rig.step().command.positions, [0.2, 0.2])
    rig.run_until(lambda out: bool(rig.results(gid)))
    # Decided one period before the end (upstream section 7 step 8; issue 11).
    assert rig.results(gid)[0].time_ns == start + 500 * MS - 10 * MS


def test_past_start_uses_time_from_start_not_its_sum() -> None:
    rig = Rig(make_config(constraints={"stopped_velocity_tolerance": 10.0}), [0.0, 0.0])
    pts = ((1.0, [0.1, 0.1]), (2.0, [0.2, 0.2]), (3.0, [0.3, 0.3]))
    # Last point due 1 s ago: rejected (summing 1+2+3 would wrongly put it 2 s in the future).
    with pytest.raises(GoalRejected) as info:
        rig.ctrl.send_goal(rig.now, traj(*pts, start_time_ns=rig.now - 4 * S))
    assert info.value.error_code == ErrorCode.OLD_HEADER_TIMESTAMP
    # Last point due in 0.5 s: accepted, and only that point remains to be reached.
    gid = rig.ctrl.send_goal(rig.now, traj(*pts, start_time_ns=rig.now - 2500 * MS))
    t0 = rig.now
    rig.run_until(lambda out: bool(rig.results(gid)))
    # Decided one period before the end (upstream section 7 step 8; issue 11).
    assert rig.results(gid)[0].time_ns == t0 + 500 * MS - 10 * MS


# -- preemption, cancel, topic ------------------------------------------------------------------


def test_preemption_cancels_the_previous_goal_once() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    a = rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    rig.step(10)
    b = rig.ctrl.send_goal(rig.now, traj((1.0, [0.0, 0.5])))
    rig.step()
    (ra,) = rig.results(a)
    assert (ra.status, ra.error_code) == (GoalStatus.CANCELED, ErrorCode.INVALID_GOAL)
    assert ra.error_string == "Current goal cancelled due to new incoming action."
    rig.run_until(lambda out: bool(rig.results(b)))
    assert [r.status for r in rig.results()] == [GoalStatus.CANCELED, GoalStatus.SUCCEEDED]


def test_cancel_holds_measured_position_and_reports_once() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    rig.step(30)
    assert rig.ctrl.cancel_goal(gid)
    assert not rig.ctrl.cancel_goal(gid)  # already canceling
    assert not rig.ctrl.cancel_goal(12345)
    measured = rig.mirror.p.copy()
    out = rig.step()
    (result,) = rig.results(gid)
    assert (result.status, result.error_code) == (GoalStatus.CANCELED, ErrorCode.SUCCESSFUL)
    np.testing.assert_array_equal(out.command.positions, measured)
    rig.step(50)
    np.testing.assert_array_equal(rig.mirror.p, measured)
    assert len(rig.results(gid)) == 1


def test_topic_trajectory_cancels_the_goal_and_executes() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    rig.step(5)
    rig.ctrl.send_trajectory(rig.now, traj((0.5, [-0.5, 0.5])))
    rig.step(100)
    (result,) = rig.results(gid)
    assert result.status is GoalStatus.CANCELED
    np.testing.assert_allclose(rig.mirror.p, [-0.5, 0.5])


def test_empty_topic_trajectory_stops_and_cancels_not_aborts() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    rig.step(30)
    rig.ctrl.send_trajectory(rig.now, JointTrajectory((), []))
    measured = rig.mirror.p.copy()
    rig.step(50)
    (result,) = rig.results(gid)
    assert result.status is GoalStatus.CANCELED
    np.testing.assert_array_equal(rig.mirror.p, measured)


def test_topic_path_violation_holds_and_reports() -> None:
    rig = Rig(make_config(constraints=constraints(0.05)), [0.0, 0.0])
    rig.mirror.frozen = True
    rig.ctrl.send_trajectory(rig.now, traj((1.0, [1.0, 1.0])))
    rig.run_until(lambda out: any(isinstance(e, TrajectoryStopped) for e in out.events))
    assert rig.ctrl.holding
    np.testing.assert_array_equal(rig.last.command.positions, [0.0, 0.0])


# -- tolerances ---------------------------------------------------------------------------------


def test_path_violation_aborts_and_the_violating_cycle_already_holds() -> None:
    rig = Rig(make_config(constraints=constraints(0.05, 0.01)), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((1.0, [0.0, 1.0])))
    rig.mirror.frozen = True  # feedback stops following
    out = rig.run_until(lambda out: bool(rig.results(gid)))
    (result,) = rig.results(gid)
    assert (result.status, result.error_code) == (
        GoalStatus.ABORTED,
        ErrorCode.PATH_TOLERANCE_VIOLATED,
    )
    assert result.error_string == "Aborted due to path tolerance violation"  # upstream's text
    assert "joint 'j2' position error" in result.details
    assert "j1" not in result.details
    np.testing.assert_array_equal(out.command.positions, [0.0, 0.0])  # no command past the check
    rig.mirror.frozen = False
    rig.step(50)
    np.testing.assert_array_equal(rig.mirror.p, [0.0, 0.0])  # holds


def test_first_point_at_zero_is_checked() -> None:
    rig = Rig(make_config(constraints=constraints(0.1)), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((0.0, [1.0, 0.0])))
    out = rig.step()
    (result,) = rig.results(gid)
    assert result.error_code == ErrorCode.PATH_TOLERANCE_VIOLATED
    np.testing.assert_array_equal(out.command.positions, [0.0, 0.0])  # the jump never went out


def test_goal_time_tolerance_aborts_after_it_and_not_before() -> None:
    rig = Rig(make_config(constraints=constraints(0.0, 0.01, goal_time=0.2)), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((0.5, [0.5, 0.5])))
    end = rig.now + 500 * MS
    rig.step(20)
    rig.mirror.frozen = True
    while rig.now <= end + 200 * MS:
        rig.step()
        assert rig.results(gid) == []
    rig.step()
    (result,) = rig.results(gid)
    assert result.error_code == ErrorCode.GOAL_TOLERANCE_VIOLATED
    assert "goal_time_tolerance" in result.error_string


def test_goal_time_zero_waits_for_the_goal() -> None:
    rig = Rig(make_config(constraints=constraints(0.0, 0.01)), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((0.5, [0.5, 0.5])))
    rig.step(20)
    rig.mirror.frozen = True
    rig.step(500)  # 5 s past the end, still outside: keeps waiting
    assert rig.results(gid) == []
    rig.mirror.frozen = False
    rig.step(3)  # the joint jumps to the goal, then reads stopped one cycle later
    assert rig.results(gid)[0].status is GoalStatus.SUCCEEDED


def test_no_success_while_passing_through_the_goal_at_speed() -> None:
    # With a velocity command interface (upstream computes the velocity error only then; a
    # position-only one succeeds here: test_results.py).
    ctrl = JointTrajectoryController(
        make_config(
            command_interfaces=("position", "velocity"), constraints=constraints(0.0, 0.01)
        )
    )
    ctrl.activate(0, JointState([0.0, 0.0], [0, 0]))
    gid = ctrl.send_goal(0, traj((0.1, [0.5, 0.5])))
    at_goal_moving = JointState([0.5, 0.5], [0.8, 0.0])
    out = ctrl.update(200 * MS, 10 * MS, at_goal_moving)
    assert [e for e in out.events if isinstance(e, GoalResult)] == []
    out = ctrl.update(210 * MS, 10 * MS, JointState([0.5, 0.5], [0.005, 0.0]))
    assert [e.goal_id for e in out.events if isinstance(e, GoalResult)] == [gid]


@pytest.mark.parametrize(
    ("override", "aborts"),
    [(0.0, True), (-1.0, False), (0.5, False), (0.01, True)],
)
def test_path_tolerance_overrides(override: float, aborts: bool) -> None:
    rig = Rig(make_config(constraints=constraints(0.05)), [0.0, 0.0])
    tol = [JointTolerance("j1", position=override), JointTolerance("j2", position=override)]
    gid = rig.ctrl.send_goal(rig.now, traj((1.0, [0.2, 0.2])), path_tolerance=tol)
    rig.mirror.frozen = True
    rig.step(80)  # reference reaches ~0.18 rad away from the frozen joint
    codes = [r.error_code for r in rig.results(gid)]
    assert codes == ([ErrorCode.PATH_TOLERANCE_VIOLATED] if aborts else [])


@pytest.mark.parametrize(
    ("tolerance", "message"),
    [
        (JointTolerance("nope", position=0.1), "'nope' is not a controller joint"),
        (JointTolerance("j1", position=-2.0), "path_tolerance.j1.position"),
        (JointTolerance("j1", velocity=math.nan), "finite"),
    ],
)
def test_invalid_tolerances_reject_the_goal(tolerance: JointTolerance, message: str) -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    with pytest.raises(GoalRejected, match=message):
        rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])), path_tolerance=[tolerance])
    with pytest.raises(GoalRejected, match="goal_time_tolerance"):
        rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])), goal_time_tolerance=-3.0)
    assert rig.ctrl.holding


def test_goal_tolerance_override_and_goal_time_override() -> None:
    rig = Rig(make_config(constraints=constraints(0.0, 0.001)), [0.0, 0.0])
    gid = rig.ctrl.send_goal(
        rig.now,
        traj((0.2, [0.3, 0.3])),
        goal_tolerance=[JointTolerance("j1", position=0.5), JointTolerance("j2", position=0.5)],
        goal_time_tolerance=0.1,
    )
    rig.mirror.frozen = True
    rig.step(21)
    (result,) = rig.results(gid)
    assert result.status is GoalStatus.SUCCEEDED  # 0.3 away, inside the overridden 0.5


def test_cmd_timeout_aborts_a_goal_stuck_outside_its_tolerance() -> None:
    rig = Rig(make_config(constraints=constraints(0.0, 0.01), cmd_timeout=0.3), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((0.5, [0.5, 0.5])))
    rig.step(10)
    rig.mirror.frozen = True
    end = rig.now + 400 * MS
    out = rig.run_until(lambda out: bool(rig.results(gid)))
    (result,) = rig.results(gid)
    assert result.status is GoalStatus.ABORTED and "command timeout" in result.error_string
    assert result.time_ns > end + 300 * MS
    np.testing.assert_array_equal(out.command.positions, rig.mirror.p)


def test_cmd_timeout_not_greater_than_goal_time_is_ignored() -> None:
    config = make_config(constraints=constraints(0.0, 0.01, goal_time=0.5), cmd_timeout=0.3)
    rig = Rig(config, [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((0.2, [0.5, 0.5])))
    rig.mirror.frozen = True
    rig.run_until(lambda out: bool(rig.results(gid)))
    assert "goal_time_tolerance" in rig.results(gid)[0].error_string


def test_feedback_at_action_monitor_rate() -> None:
    rig = Rig(make_config(action_monitor_rate=20.0), [0.0, 0.0])
    start = rig.now
    gid = rig.ctrl.send_goal(rig.now, traj((2.0, [1.0, 1.0])))
    rig.step(100)
    feedback = [e for e in rig.events if isinstance(e, GoalFeedback)]
    assert len(feedback) == 20
    assert {f.goal_id for f in feedback} == {gid}
    f = feedback[3]
    assert f.time_ns == start + 150 * MS
    assert f.time_from_start == pytest.approx(0.15)
    np.testing.assert_array_equal(f.desired.positions, rig.ctrl.query_state(f.time_ns).positions)
    assert f.error.shape == (3, 2)


def test_query_state_has_no_side_effects() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    later = rig.ctrl.query_state(rig.now + 500 * MS)
    assert later.positions[0] == pytest.approx(0.5)
    rig.ctrl.query_state(rig.now + 100 * S)
    out = rig.step()
    np.testing.assert_allclose(out.command.positions, [0.01, 0.01])


# -- control laws -------------------------------------------------------------------------------


def test_pid_proportional() -> None:
    ctrl = pid_controller(p=10.0)
    out = ctrl.update(0, 10 * MS, JointState([-0.1], [0.0]))  # hold 0, at -0.1: e = +0.1
    assert out.command.effort[0] == pytest.approx(1.0)


def test_pid_integral_accumulates_and_clamps() -> None:
    ctrl = pid_controller(i=2.0, i_clamp=0.05)
    outs = [ctrl.update(k * 10 * MS, 10 * MS, JointState([-0.1], [0.0])) for k in range(1, 6)]
    # k_i * e * dt = 2 * 0.1 * 0.01 = 0.002 per cycle, contributing from the next call on
    # (control_toolbox: the integral lags one call)
    assert [o.command.effort[0] for o in outs[:3]] == pytest.approx([0.0, 0.002, 0.004])
    for k in range(6, 100):
        out = ctrl.update(k * 10 * MS, 10 * MS, JointState([-0.1], [0.0]))
    assert out.command.effort[0] == pytest.approx(0.05)


def test_pid_integral_with_zero_clamp_is_off() -> None:
    ctrl = pid_controller(i=2.0, i_clamp=0.0)
    for k in range(1, 20):
        out = ctrl.update(k * 10 * MS, 10 * MS, JointState([-0.1], [0.0]))
    assert out.command.effort[0] == 0.0


def test_pid_derivative_on_velocity_error() -> None:
    ctrl = pid_controller(d=3.0)
    out = ctrl.update(0, 10 * MS, JointState([0.0], [0.2]))  # v_d = 0, v = 0.2
    assert out.command.effort[0] == pytest.approx(-0.6)


def test_pid_velocity_feed_forward_and_effort_feed_forward() -> None:
    ctrl = pid_controller(ff_velocity_scale=2.0)
    ctrl.send_goal(
        0,
        JointTrajectory(
            ("j",),
            [TrajectoryPoint(1.0, [1.0], [1.0], effort=[5.0])],
        ),
    )
    t = 500 * MS
    d = ctrl.query_state(t)
    ahead = ctrl.query_state(t + 10 * MS)  # feed-forward from the look-ahead sample
    out = ctrl.update(t, 10 * MS, JointState(d.positions, d.velocities))
    assert out.command.effort[0] == pytest.approx(2.0 * ahead.velocities[0] + ahead.effort[0])


def test_velocity_only_uses_pid_and_stops_after_cancel() -> None:
    ctrl = pid_controller("velocity", p=5.0, i=1.0, i_clamp=1.0, ff_velocity_scale=1.0)
    gid = ctrl.send_goal(0, JointTrajectory(("j",), [TrajectoryPoint(2.0, [1.0])]))
    state = JointState([0.0], [0.0])
    for k in range(50):
        out = ctrl.update(k * 10 * MS, 10 * MS, state)
        state = JointState(
            state.positions + out.command.velocities * 0.01 * 0.5, out.command.velocities
        )
    assert abs(out.command.velocities[0]) > 0.1
    ctrl.cancel_goal(gid)
    out = ctrl.update(50 * 10 * MS, 10 * MS, JointState(state.positions, [0.0]))
    assert out.command.velocities[0] == 0.0  # no integral, no feed-forward: motion stops


def test_effort_joint_stops_pushing_after_abort() -> None:
    config = make_config(
        joints=("j",),
        command_interfaces=("effort",),
        gains={"j": {"p": 5.0, "i": 10.0, "i_clamp": 2.0}},
        constraints={"j": {"trajectory": 0.5}},
    )
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.0], [0.0]))
    gid = ctrl.send_goal(0, JointTrajectory(("j",), [TrajectoryPoint(1.0, [1.0])]))
    stuck = JointState([0.0], [0.0])  # the joint is blocked
    k = 0
    results: list[Any] = []
    while not results:
        out = ctrl.update(k * 10 * MS, 10 * MS, stuck)
        results = [e for e in out.events if isinstance(e, GoalResult)]
        k += 1
        if k == 40:
            assert out.command.effort[0] > 2.0  # integral wound up while pushing
    assert results[0].goal_id == gid
    assert results[0].error_code == ErrorCode.PATH_TOLERANCE_VIOLATED
    assert out.command.effort[0] == 0.0  # the aborting cycle already stops pushing
    for _ in range(10):
        k += 1
        assert ctrl.update(k * 10 * MS, 10 * MS, stuck).command.effort[0] == 0.0


def test_leaving_a_fault_rearms_without_a_jump() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((2.0, [1.0, 1.0])))
    rig.step(50)
    events = rig.ctrl.deactivate(rig.now, "servo 2: no status packet")
    assert [e.status for e in events if isinstance(e, GoalResult)] == [GoalStatus.ABORTED]
    rig.mirror.p = rig.mirror.p - 0.05  # sagged while faulted
    rig.ctrl.activate(rig.now, rig.mirror.state(), JointCommand(positions=[math.nan] * 2))
    measured = rig.mirror.p.copy()
    np.testing.assert_array_equal(rig.step().command.positions, measured)
    assert rig.results(gid) == []


def test_acceleration_interface_forwards_desired_acceleration() -> None:
    config = make_config(command_interfaces=("position", "velocity", "acceleration"))
    rig = Rig(config, [0.0, 0.0])
    rig.ctrl.send_goal(
        rig.now,
        JointTrajectory(NAMES, [TrajectoryPoint(1.0, [1.0, -1.0], [0.0, 0.0], [0.0, 0.0])]),
    )
    t = rig.now
    out = rig.step()
    ahead = rig.ctrl.query_state(t + 10 * MS)
    np.testing.assert_array_equal(out.command.accelerations, ahead.accelerations)
    np.testing.assert_array_equal(out.command.velocities, ahead.velocities)
    assert out.command.accelerations[0] > 0.0


def test_forward_velocity_after_success_is_kept() -> None:
    """Upstream sections 4.3 step 6 and 11.2: the success hold is the last point as given, its
    velocity re-commanded (issue 11; this test asserted 0 before)."""
    config = make_config(
        joints=("j",),
        command_interfaces=("position", "velocity"),
        allow_nonzero_velocity_at_trajectory_end=True,
        constraints={"stopped_velocity_tolerance": 10.0},
    )
    rig = Rig(config, [0.0])
    gid = rig.ctrl.send_goal(rig.now, JointTrajectory(("j",), [TrajectoryPoint(0.5, [0.5], [1.0])]))
    rig.run_until(lambda out: bool(rig.results(gid)))
    for _ in range(50):
        rig.step()
        assert rig.last.command.velocities[0] == 1.0
        assert rig.last.command.positions[0] == 0.5


def test_open_loop_holds_last_command_on_abort() -> None:
    config = make_config(open_loop_control=True, constraints=constraints(0.05))
    rig = Rig(config, [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    rig.mirror.frozen = True
    rig.run_until(lambda out: bool(rig.results(gid)))
    held = rig.last.command.positions
    assert held[0] > 0.04  # the last commanded position, not the frozen measured 0.0


# -- continuous joints --------------------------------------------------------------------------


def test_wraparound_error_is_the_short_angle() -> None:
    config = make_config(gains={"j1": {"angle_wraparound": True}})
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([3.1, 3.1], [0, 0]))
    out = ctrl.update(0, 10 * MS, JointState([-3.1, -3.1], [0, 0]))
    assert out.error[0, 0] == pytest.approx(6.2 - 2 * math.pi)
    assert out.error[0, 1] == pytest.approx(6.2)


def test_success_at_goal_plus_a_turn_only_for_continuous_joints() -> None:
    config = make_config(gains={"j1": {"angle_wraparound": True}}, constraints=constraints(0, 0.01))
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.0, 0.0], [0, 0]))
    gid = ctrl.send_goal(0, traj((0.1, [1.0, 1.0])))
    out = ctrl.update(S, 10 * MS, JointState([1.0 + 2 * math.pi, 1.0 + 2 * math.pi], [0, 0]))
    assert [e for e in out.events if isinstance(e, GoalResult)] == []  # j2 is a turn away
    out = ctrl.update(S + 10 * MS, 10 * MS, JointState([1.0 + 2 * math.pi, 1.0], [0, 0]))
    assert [e.goal_id for e in out.events if isinstance(e, GoalResult)] == [gid]


def test_continuous_joint_never_spins_a_full_turn() -> None:
    config = make_config(gains={"j1": {"angle_wraparound": True}, "j2": {"angle_wraparound": True}})
    rig = Rig(config, [3.0, -3.0])
    gid = rig.ctrl.send_goal(rig.now, traj((1.0, [-3.0, 3.0])))
    travel = 0.0
    start = rig.mirror.p.copy()
    while not rig.results(gid):
        rig.step()
        travel = max(travel, float(np.abs(rig.mirror.p - start).max()))
    assert travel == pytest.approx(2 * math.pi - 6.0)


# -- plan / commit (how the daemon keeps fitting out of the loop) -------------------------------


def test_plan_then_commit_equals_send_goal() -> None:
    a, b = Rig(make_config(), [0.0, 0.0]), Rig(make_config(), [0.0, 0.0])
    msg = traj((0.5, [0.3, 0.1]), (1.0, [1.0, -1.0]))
    a.ctrl.send_goal(a.now, msg)
    plan = b.ctrl.plan_goal(b.now, msg)
    assert b.ctrl.commit(plan, b.now) == 1
    for _ in range(120):
        np.testing.assert_array_equal(a.step().command.positions, b.step().command.positions)


def test_commit_refuses_a_plan_made_on_an_older_reference() -> None:
    rig = Rig(make_config(constraints=constraints(0.05)), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    plan = rig.ctrl.plan_goal(rig.now + 50 * MS, traj((1.0, [0.0, 0.0])))
    rig.ctrl.cancel_goal(gid)
    rig.step()  # the cancel re-anchors the reference: the plan's base is gone
    with pytest.raises(StalePlan, match="version"):
        rig.ctrl.commit(plan, rig.now)
    assert rig.ctrl.holding and len(rig.results(gid)) == 1


def test_commit_refuses_a_late_plan() -> None:
    rig = Rig(make_config(), [0.0, 0.0])
    plan = rig.ctrl.plan_goal(rig.now, traj((1.0, [1.0, 1.0])))
    with pytest.raises(StalePlan, match="late"):
        rig.ctrl.commit(plan, rig.now + 1)
    assert rig.ctrl.commit(plan, rig.now) == 1  # on time it still fits


def test_plan_for_a_later_cycle_keeps_the_reference_until_then() -> None:
    rig = Rig(make_config(), [0.2, 0.2])
    planned = rig.now + 30 * MS
    plan = rig.ctrl.plan_goal(planned, traj((0.5, [1.0, 1.0])), valid_from_ns=rig.now)
    rig.ctrl.commit(plan, rig.now)
    for _ in range(3):
        np.testing.assert_array_equal(rig.step().command.positions, [0.2, 0.2])
    assert rig.step().command.positions[0] > 0.2


def test_plan_committed_early_on_a_moving_reference_does_not_step() -> None:
    """A plan made for a later cycle and swapped in early keeps following the old motion."""
    rig = Rig(make_config(), [0.0, 0.0])
    # Moving at 1 rad/s with a knot every 50 ms, so knots lie between commit and planned time.
    knots = [(0.05 * k, [0.05 * k, -0.05 * k]) for k in range(1, 41)]
    rig.ctrl.send_goal(rig.now, traj(*knots))
    rig.step(20)
    early = 150 * MS
    plan = rig.ctrl.plan_goal(
        rig.now + early, traj((1.0, [0.0, 0.0])), valid_from_ns=rig.now - 10 * MS
    )
    with pytest.raises(StalePlan, match="before the plan's validity"):
        rig.ctrl.commit(plan, rig.now - 20 * MS)
    rig.ctrl.commit(plan, rig.now)
    previous = rig.last.command.positions.copy()
    for _ in range(40):  # across the planned splice time
        out = rig.step()
        assert np.abs(out.command.positions - previous).max() <= 0.011  # <= 1.1 rad/s * 10 ms
        previous = out.command.positions.copy()
