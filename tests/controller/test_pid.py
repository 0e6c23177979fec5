"""Issue 11, part C: upstream's control law, command joints, activation seeding and controller
state (sections 1, 3, 12 and 16 of ../shared/reference/jtc_upstream_behaviour.md).

Every test drives the pure controller on a simulated clock: ``update(now, period, state)``.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
import pytest

from jtc_hw import (
    ConfigurationError,
    ErrorCode,
    GoalResult,
    JointCommand,
    JointState,
    JointTrajectory,
    JointTrajectoryController,
    TrajectoryPoint,
)
from jtc_hw.controller.pid import Pid

from conftest import MS, S, make_config, pid_controller

PERIOD = 10 * MS


# -- 10. the PID law ----------------------------------------------------------------------------


def test_integral_contribution_lags_one_call() -> None:
    """Section 12: the integral accumulated by a call only contributes from the next call."""
    ctrl = pid_controller(i=2.0, i_clamp=1.0)
    off = JointState([-0.1], [0.0])  # hold at 0, measured -0.1: e = +0.1
    first = ctrl.update(PERIOD, PERIOD, off).command.effort[0]
    second = ctrl.update(2 * PERIOD, PERIOD, off).command.effort[0]
    assert first == 0.0
    assert second == pytest.approx(2.0 * 0.1 * 0.01)


def test_zero_dt_returns_the_previous_output_and_changes_nothing() -> None:
    """Section 12: ``dt == 0`` returns the previous output, with no state change."""
    ctrl = pid_controller(p=10.0, i=5.0, i_clamp=1.0)
    u1 = ctrl.update(PERIOD, PERIOD, JointState([-0.1], [0.0])).command.effort[0]
    # A different error at dt = 0: the same output, and the integral did not move.
    u0 = ctrl.update(PERIOD, 0, JointState([-0.3], [0.0])).command.effort[0]
    assert u0 == u1 == pytest.approx(1.0)
    u2 = ctrl.update(2 * PERIOD, PERIOD, JointState([-0.1], [0.0])).command.effort[0]
    assert u2 == pytest.approx(1.0 + 5.0 * 0.1 * 0.01)  # one step of integral, not two


def test_non_finite_error_gives_nan_and_leaves_the_integral() -> None:
    """Section 12: a non-finite error (here the velocity error) gives NaN, no state change."""
    ctrl = pid_controller(p=1.0, i=2.0, i_clamp=1.0)
    off = JointState([-0.1], [0.0])
    ctrl.update(PERIOD, PERIOD, off)
    for k in range(2, 12):
        out = ctrl.update(k * PERIOD, PERIOD, JointState([-0.1], [math.nan]))
        assert math.isnan(out.command.effort[0])
    u = ctrl.update(12 * PERIOD, PERIOD, off).command.effort[0]
    assert u == pytest.approx(0.1 + 2.0 * 0.1 * 0.01)  # the NaN cycles integrated nothing


def test_integral_clamp_and_deadband_as_control_toolbox() -> None:
    """Section 12: I is clamped to [i_min, i_max] after each update; no integration while
    ``|e| <= error_deadband`` (with 0, only an exact zero stops it); output clamp excludes I's
    future contribution."""
    pid = Pid(
        np.array([0.0, 0.0]),
        np.array([1.0, 1.0]),
        np.array([0.0, 0.0]),
        np.array([0.05, 0.05]),
        error_deadband=np.array([0.0, 0.5]),
    )
    e = np.array([1.0, 0.5])  # joint 1 exactly at its deadband: not integrated
    outs = [pid.compute(e, np.zeros(2), 0.01)[0] for _ in range(8)]
    assert outs[:4] == pytest.approx([0.0, 0.01, 0.02, 0.03])
    assert outs[-1] == pytest.approx(0.05)  # clamped to i_max
    assert pid.i_term[1] == 0.0
    clamped = Pid(
        np.array([10.0]), np.zeros(1), np.zeros(1), np.zeros(1), u_min=-1.0, u_max=2.0
    )
    assert clamped.compute(np.array([1.0]), np.zeros(1), 0.01)[0] == 2.0
    assert clamped.compute(np.array([-1.0]), np.zeros(1), 0.01)[0] == -1.0


# -- 9. feed-forward timing ---------------------------------------------------------------------


def varying_goal(ctrl: JointTrajectoryController, **effort: Any) -> None:
    """A cubic from rest to 1 rad/s (and a linear effort ramp): they change every cycle."""
    ctrl.send_goal(0, JointTrajectory(("j",), [TrajectoryPoint(1.0, [0.5], [1.0], **effort)]))


def test_velocity_feed_forward_comes_from_the_look_ahead_sample() -> None:
    """Section 12: with the closed-loop adapter, ``u = ff * command_next.v + PID(e at
    traj_time)``; command_next is sampled one period ahead."""
    ctrl = pid_controller("velocity", p=3.0, ff_velocity_scale=0.5)
    varying_goal(ctrl)
    t = 500 * MS
    desired = ctrl.query_state(t)
    ahead = ctrl.query_state(t + PERIOD)
    assert ahead.velocities[0] != pytest.approx(desired.velocities[0])
    measured = desired.positions[0] - 0.02  # position error 0.02 at traj_time
    out = ctrl.update(t, PERIOD, JointState([measured], [desired.velocities[0]]))
    expected = 0.5 * ahead.velocities[0] + 3.0 * 0.02
    assert out.command.velocities[0] == pytest.approx(expected, rel=1e-12)


def test_effort_feed_forward_comes_from_the_look_ahead_sample() -> None:
    """Section 12: effort-only: ``u = ff * command_next.v + command_next.effort + PID``."""
    ctrl = pid_controller("effort", d=2.0, ff_velocity_scale=1.5)
    varying_goal(ctrl, effort=[4.0])
    t = 500 * MS
    desired = ctrl.query_state(t)
    ahead = ctrl.query_state(t + PERIOD)
    assert ahead.effort[0] != pytest.approx(desired.effort[0])
    out = ctrl.update(t, PERIOD, JointState(desired.positions, desired.velocities - 0.1))
    expected = 1.5 * ahead.velocities[0] + ahead.effort[0] + 2.0 * 0.1
    assert out.command.effort[0] == pytest.approx(expected, rel=1e-12)


# -- 11. command_joints -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("command_joints", "message"),
    [
        (["j1", "j2", "j3", "j4"], "command_joints: has 4 names but joints has only 3"),
        (["j1", "x"], "command_joints: names [x], which is not in joints (j1, j2, j3)"),
    ],
)
def test_command_joints_longer_or_not_a_subset_is_refused(
    command_joints: list[str], message: str
) -> None:
    """Section 1: longer than joints, or shorter and not a subset, fails to configure."""
    with pytest.raises(ConfigurationError, match=re.escape(message)):
        make_config(joints=("j1", "j2", "j3"), command_joints=command_joints)


def test_command_joints_subset_commands_only_those_and_monitors_the_others() -> None:
    """Sections 1 and 12: a subset is mapped by name; commands go to those joints only (NaN,
    "write nothing", for the others), the others are still checked against tolerances."""
    config = make_config(
        joints=("j1", "j2", "j3"),
        command_joints=["j3", "j1"],
        constraints={"j2": {"trajectory": 0.05}},
    )
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.0, 0.0, 0.0], [0.0] * 3))
    gid = ctrl.send_goal(
        0, JointTrajectory(("j1", "j2", "j3"), [TrajectoryPoint(1.0, [1.0, 1.0, -1.0])])
    )
    out = ctrl.update(0, PERIOD, JointState([0.0] * 3, [0.0] * 3))
    positions = out.command.positions
    assert positions[0] > 0.0 and positions[2] < 0.0 and math.isnan(positions[1])
    # j2 is not commanded, so it does not follow: its path tolerance aborts the goal.
    results: list[GoalResult] = []
    p = np.zeros(3)
    for k in range(1, 100):
        out = ctrl.update(k * PERIOD, PERIOD, JointState(p, [0.0] * 3))
        p = np.where(np.isnan(out.command.positions), p, out.command.positions)
        results += [e for e in out.events if isinstance(e, GoalResult)]
        if results:
            break
    assert [(r.goal_id, r.error_code) for r in results] == [
        (gid, ErrorCode.PATH_TOLERANCE_VIOLATED)
    ]
    assert p[1] == 0.0 and p[0] > 0.0


def test_command_joints_with_other_names_map_by_index() -> None:
    """Section 1: as many command joints as joints, other names (a chain): by index."""
    config = make_config(joints=("j1", "j2"), command_joints=["c1", "c2"])
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.25, -0.5], [0.0, 0.0]))
    out = ctrl.update(0, PERIOD, JointState([0.25, -0.5], [0.0, 0.0]))
    np.testing.assert_array_equal(out.command.positions, [0.25, -0.5])


# -- 12. activation -----------------------------------------------------------------------------


def test_activation_seeds_position_velocity_and_acceleration_from_commands() -> None:
    """Section 3 step 4: each command type whose values are all finite replaces that field of
    the current and last-commanded state; one NaN makes that type the measured one."""
    config = make_config(
        command_interfaces=("position", "velocity", "acceleration"),
        state_interfaces=("position", "velocity", "acceleration"),
    )
    ctrl = JointTrajectoryController(config)
    measured = JointState([0.3, -0.2], [0.01, 0.02], [0.1, 0.2])
    ctrl.activate(
        0,
        measured,
        JointCommand(positions=[0.5, 0.6], velocities=[1.0, -1.0], accelerations=[0.0, math.nan]),
    )
    seeded = ctrl.last_commanded_state
    np.testing.assert_array_equal(seeded.positions, [0.5, 0.6])
    np.testing.assert_array_equal(seeded.velocities, [1.0, -1.0])
    np.testing.assert_array_equal(seeded.accelerations, [0.1, 0.2])  # NaN: measured
    # The hold is at the seeded positions, at rest (section 11.1).
    out = ctrl.update(0, PERIOD, measured)
    np.testing.assert_array_equal(out.command.positions, [0.5, 0.6])
    np.testing.assert_array_equal(out.command.velocities, [0.0, 0.0])


def test_activation_does_not_seed_with_a_subset_of_command_joints() -> None:
    """Section 3 step 4: seeding needs ``len(command_joints) == dof``."""
    config = make_config(joints=("j1", "j2"), command_joints=["j2"])
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.3, -0.2], [0.0, 0.0]), JointCommand(positions=[0.5, 0.6]))
    out = ctrl.update(0, PERIOD, JointState([0.3, -0.2], [0.0, 0.0]))
    assert math.isnan(out.command.positions[0])
    assert out.command.positions[1] == -0.2
    np.testing.assert_array_equal(ctrl.last_commanded_state.positions, [0.3, -0.2])


# -- 13. controller state -----------------------------------------------------------------------


def test_state_reference_and_feedback_carry_time_from_start() -> None:
    """Section 16: reference and feedback tfs = time - start of the trajectory followed."""
    ctrl = pid_controller("position")
    t0 = 3 * S
    ctrl.update(t0 - PERIOD, PERIOD, JointState([0.0], [0.0]))
    ctrl.send_goal(t0, JointTrajectory(("j",), [TrajectoryPoint(1.0, [1.0])]))
    state = ctrl.update(t0 + 250 * MS, PERIOD, JointState([0.0], [0.0])).state
    assert state.reference_time_from_start == pytest.approx(0.25)
    assert state.feedback_time_from_start == pytest.approx(0.25)
    assert state.time_ns == t0 + 250 * MS
    np.testing.assert_array_equal(
        state.reference.positions, ctrl.query_state(t0 + 250 * MS).positions
    )


def test_state_feedback_accelerations_follow_the_state_interfaces() -> None:
    """Section 16: feedback accelerations only with an acceleration state interface."""
    measured = JointState([0.0, 0.0], [0.1, 0.2], [0.3, 0.4])
    with_acc = JointTrajectoryController(
        make_config(
            command_interfaces=("position", "velocity", "acceleration"),
            state_interfaces=("position", "velocity", "acceleration"),
        )
    )
    with_acc.activate(0, measured)
    feedback = with_acc.update(0, PERIOD, measured).state.feedback
    np.testing.assert_array_equal(feedback.accelerations, [0.3, 0.4])
    np.testing.assert_array_equal(feedback.velocities, [0.1, 0.2])
    without = JointTrajectoryController(make_config(state_interfaces=("position",)))
    without.activate(0, measured)
    feedback = without.update(0, PERIOD, measured).state.feedback
    assert feedback.velocities is None and feedback.accelerations is None


def test_state_output_is_read_back_with_the_refresh_rule() -> None:
    """Section 16: output is refreshed only when every configured command interface of every
    command joint is finite; otherwise the previous value is kept. Unconfigured interfaces
    are empty, joints that are not command joints NaN."""
    config = make_config(
        joints=("j1", "j2", "j3"),
        command_joints=["j1", "j3"],
        command_interfaces=("position", "velocity"),
        start_with_holding=False,
    )
    ctrl = JointTrajectoryController(config)
    here = JointState([0.1, 0.2, 0.3], [0.0] * 3)
    ctrl.activate(0, here, JointCommand(positions=[1.0, 2.0, 3.0], velocities=[0.0] * 3))
    out = ctrl.update(0, PERIOD, here)
    assert np.isnan(out.command.positions).all()  # nothing commanded yet
    output = out.state.output  # kept: what the interfaces held at activation
    np.testing.assert_array_equal(output.positions, [1.0, math.nan, 3.0])
    assert output.accelerations is None and output.effort is None
    ctrl.send_goal(PERIOD, JointTrajectory(("j1", "j2", "j3"), [TrajectoryPoint(1.0, [0.5] * 3)]))
    out = ctrl.update(PERIOD, PERIOD, here)
    np.testing.assert_array_equal(out.state.output.positions, out.command.positions)
    assert math.isnan(out.state.output.positions[1])
    assert not math.isnan(out.state.output.positions[0])
