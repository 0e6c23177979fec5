"""Issue 11, part B: validation epsilon, result strings, which errors exist, deactivation.

Each test names the section of ``../shared/reference/jtc_upstream_behaviour.md`` it checks; the
controller is stepped on a simulated clock (``update(now, period, state)`` called here).
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
import pytest

from jtc_hw import (
    ErrorCode,
    GoalRejected,
    GoalResult,
    GoalStatus,
    JointState,
    JointTolerance,
    JointTrajectory,
    JointTrajectoryController,
    TrajectoryPoint,
    TrajectoryStopped,
)
from jtc_hw.controller.validation import FLT_EPSILON

from conftest import MS, Rig, S, make_config

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


# -- point 6: result strings are upstream's, the details apart ---------------------------------


def test_path_violation_error_string_is_upstreams_and_details_name_the_joint() -> None:
    """Section 7 step 8d: "Aborted due to path tolerance violation", exactly; which joint broke
    which tolerance goes to ``details``."""
    rig = Rig(make_config(constraints=constraints(0.05)), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, goal(1.0, [0.0, 1.0]))
    rig.mirror.frozen = True
    rig.run_until(lambda out: bool(rig.results(gid)))
    (result,) = rig.results(gid)
    assert (result.status, result.error_code) == (
        GoalStatus.ABORTED,
        ErrorCode.PATH_TOLERANCE_VIOLATED,
    )
    assert result.error_string == "Aborted due to path tolerance violation"
    assert re.fullmatch(r"joint 'j2' position error \+0\.0\d+ exceeds 0\.05", result.details)


def test_goal_time_error_string_is_upstreams_with_the_lateness_as_to_string() -> None:
    """Section 7 step 8d: "Aborted due to goal_time_tolerance exceeding by <s> seconds", <s>
    formatted as std::to_string(double) (six decimals); details name the joint."""
    rig = Rig(make_config(constraints=constraints(0.0, 0.01, goal_time=0.2)), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, goal(0.5, [0.5, 0.0]))
    end = rig.now + 500 * MS
    rig.mirror.frozen = True
    rig.run_until(lambda out: bool(rig.results(gid)))
    (result,) = rig.results(gid)
    assert result.error_code == ErrorCode.GOAL_TOLERANCE_VIOLATED
    late_s = (result.time_ns - end) / S
    assert late_s > 0.2
    assert result.error_string == (
        f"Aborted due to goal_time_tolerance exceeding by {late_s:.6f} seconds"
    )
    assert result.details.startswith("joint 'j1' position error") and "j2" not in result.details


def test_success_error_string_is_upstreams_without_details() -> None:
    """Section 7 step 8d: "Goal successfully reached!", nothing in ``details``."""
    rig = Rig(make_config(constraints=constraints(0.05, 0.01)), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, goal(0.3, [0.2, 0.1]))
    rig.run_until(lambda out: bool(rig.results(gid)))
    (result,) = rig.results(gid)
    assert (result.status, result.error_string, result.details) == (
        GoalStatus.SUCCEEDED,
        "Goal successfully reached!",
        "",
    )


def test_cmd_timeout_message_keeps_the_joint_details_apart() -> None:
    """Section 8.6 (decided deviation: cmd_timeout ends a goal with a result): its message says
    what timed out; the joints outside the goal tolerance are in ``details``."""
    config = make_config(constraints=constraints(0.0, 0.01), cmd_timeout=0.3)
    rig = Rig(config, [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, goal(0.5, [0.5, 0.5]))
    rig.mirror.frozen = True
    rig.run_until(lambda out: bool(rig.results(gid)))
    (result,) = rig.results(gid)
    assert result.error_string.startswith("Aborted due to command timeout: ")
    assert "joint" not in result.error_string
    assert "joint 'j1' position error" in result.details
    assert "joint 'j2' position error" in result.details


def test_topic_trajectory_stop_carries_the_same_text_and_details() -> None:
    """Section 7 step 8e: a topic trajectory has no result; its stop notice carries the same
    reason as a goal would and the details apart."""
    rig = Rig(make_config(constraints=constraints(0.05)), [0.0, 0.0])
    rig.mirror.frozen = True
    rig.ctrl.send_trajectory(rig.now, goal(1.0, [1.0, 0.0]))
    rig.run_until(lambda out: any(isinstance(e, TrajectoryStopped) for e in out.events))
    (stopped,) = [e for e in rig.events if isinstance(e, TrajectoryStopped)]
    assert stopped.reason == "Aborted due to path tolerance violation"
    assert stopped.details.startswith("joint 'j1' position error")


# -- point 7: which errors exist ---------------------------------------------------------------


def test_dynamixel_velocity_count_at_rest_does_not_block_a_position_goal() -> None:
    """Section 8.4: with a position command interface the velocity error is not computed, so
    stopped_velocity_tolerance (0.01 rad/s) cannot keep a goal from succeeding. A Dynamixel
    reports velocity in counts of 0.229 rpm (0.024 rad/s): a servo at rest reading one count
    used to make the goal wait forever (goal_time 0)."""
    one_count = 0.229 * 2 * math.pi / 60  # rad/s
    assert one_count > 0.01
    ctrl = JointTrajectoryController(make_config(constraints=constraints(0.0, 0.01)))
    assert ctrl.config.constraints.stopped_velocity_tolerance == 0.01
    assert ctrl.config.constraints.goal_time == 0.0
    ctrl.activate(0, JointState([0.0, 0.0], [0.0, 0.0]))
    gid = ctrl.send_goal(0, goal(0.2, [0.5, -0.5]))
    at_rest = JointState([0.5, -0.5], [one_count, -one_count])
    found: list[GoalResult] = []
    for k in range(1, 31):  # 0.3 s: past the end, never finishing before the fix
        out = ctrl.update(k * PERIOD, PERIOD, at_rest)
        assert out.error[1].tolist() == [0.0, 0.0]  # no velocity error exists
        found += results(out.events)
    assert [(r.goal_id, r.status) for r in found] == [(gid, GoalStatus.SUCCEEDED)]


def test_velocity_error_exists_with_a_velocity_command_interface() -> None:
    """Section 8.4: velocity state and a velocity command interface: the velocity error is
    computed and stopped_velocity_tolerance holds the goal back while the joint moves."""
    config = make_config(
        command_interfaces=("position", "velocity"), constraints=constraints(0.0, 0.01)
    )
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.0, 0.0], [0.0, 0.0]))
    gid = ctrl.send_goal(0, goal(0.2, [0.5, -0.5]))
    drifting = JointState([0.5, -0.5], [0.024, 0.0])
    out = ctrl.update(300 * MS, PERIOD, drifting)
    assert out.error[1].tolist() == [-0.024, 0.0]
    assert results(out.events) == []
    out = ctrl.update(310 * MS, PERIOD, JointState([0.5, -0.5], [0.005, 0.0]))
    assert [r.goal_id for r in results(out.events)] == [gid]


@pytest.mark.parametrize(
    ("command_interfaces", "computed"),
    [
        (("position",), False),
        (("position", "velocity"), False),
        (("position", "velocity", "acceleration"), True),
    ],
)
def test_acceleration_error_needs_an_acceleration_command_interface(
    command_interfaces: tuple[str, ...], computed: bool
) -> None:
    """Section 8.4: the acceleration error only with an acceleration state interface and an
    acceleration command interface; otherwise it stays 0 and an acceleration goal tolerance
    never triggers."""
    config = make_config(
        command_interfaces=command_interfaces,
        state_interfaces=("position", "velocity", "acceleration"),
        constraints=constraints(0.0, 0.01),
    )
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.0, 0.0], [0.0, 0.0], [0.0, 0.0]))
    gid = ctrl.send_goal(
        0,
        goal(0.2, [0.5, -0.5]),
        goal_tolerance=[JointTolerance("j1", acceleration=0.1)],
    )
    shaking = JointState([0.5, -0.5], [0.0, 0.0], [5.0, 0.0])
    out = ctrl.update(300 * MS, PERIOD, shaking)
    assert out.error[2].tolist() == ([-5.0, 0.0] if computed else [0.0, 0.0])
    assert [r.goal_id for r in results(out.events)] == ([] if computed else [gid])


# -- point 8: deactivation ---------------------------------------------------------------------


def test_deactivation_aborts_the_goal_with_invalid_goal() -> None:
    """Sections 3 and 9: deactivating aborts the active goal, INVALID_GOAL (-1), upstream's
    message."""
    rig = Rig(make_config(), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, goal(2.0, [1.0, 1.0]))
    rig.step(20)
    (result,) = results(rig.ctrl.deactivate(rig.now))
    assert (result.goal_id, result.status, result.error_code, result.error_string) == (
        gid,
        GoalStatus.ABORTED,
        ErrorCode.INVALID_GOAL,
        "Current goal cancelled during deactivate transition.",
    )


def test_deactivation_while_a_cancel_is_pending_aborts_too() -> None:
    """Section 3: the goal still executing (its cancel not yet applied) ends ABORTED, and only
    once."""
    rig = Rig(make_config(), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, goal(2.0, [1.0, 1.0]))
    rig.step(5)
    assert rig.ctrl.cancel_goal(gid)
    (result,) = results(rig.ctrl.deactivate(rig.now, "daemon stopping: holding position"))
    assert (result.status, result.error_code, result.error_string) == (
        GoalStatus.ABORTED,
        ErrorCode.INVALID_GOAL,
        "daemon stopping: holding position",
    )


@pytest.mark.parametrize(
    "command_interfaces",
    [
        ("position",),
        ("position", "velocity"),
        ("position", "velocity", "acceleration"),
        ("velocity",),
        ("effort",),
    ],
)
def test_deactivation_command_zeroes_velocity_acceleration_and_effort(
    command_interfaces: tuple[str, ...],
) -> None:
    """Section 3 (deactivate): velocity, acceleration and effort commands are written 0, the
    position command is left as it is (NaN: "write nothing")."""
    config = make_config(command_interfaces=command_interfaces, gains={
        j: {"p": 1.0} for j in NAMES
    })
    rig = Rig(config, [0.0, 0.0])
    rig.ctrl.send_goal(rig.now, goal(1.0, [1.0, -1.0]))
    moving = rig.step(30).command
    rig.ctrl.deactivate(rig.now)
    cmd = rig.ctrl.deactivation_command
    for name, interface in (
        ("velocities", "velocity"),
        ("accelerations", "acceleration"),
        ("effort", "effort"),
    ):
        values = getattr(cmd, name)
        if interface in command_interfaces:
            assert values.tolist() == [0.0, 0.0], name
            assert np.abs(getattr(moving, name)).max() > 0.0 or name == "accelerations"
        else:
            assert values is None, name
    if "position" in command_interfaces:
        assert np.isnan(cmd.positions).all()
    else:
        assert cmd.positions is None


def test_deactivation_command_leaves_joints_outside_command_joints_alone() -> None:
    """Sections 3 and 12: the deactivation command goes to command joints only; a joint that
    is only monitored (outside a ``command_joints`` subset) gets NaN ("write nothing")."""
    config = make_config(command_interfaces=("velocity",), command_joints=["j2"], gains={
        j: {"p": 1.0} for j in NAMES
    })
    rig = Rig(config, [0.0, 0.0])
    rig.ctrl.send_goal(rig.now, goal(1.0, [1.0, -1.0]))
    rig.step(30)
    rig.ctrl.deactivate(rig.now)
    velocities = rig.ctrl.deactivation_command.velocities
    assert velocities is not None
    assert math.isnan(velocities[0])
    assert velocities[1] == 0.0


def test_cancel_result_has_upstreams_empty_error_string() -> None:
    """Section 9 (cancel request): the goal ends CANCELED with error_code 0 and an empty
    error_string, as upstream's; what happened is in ``details``."""
    rig = Rig(make_config(), [0.0, 0.0])
    gid = rig.ctrl.send_goal(rig.now, goal(1.0, [1.0, -1.0]))
    rig.step(10)
    assert rig.ctrl.cancel_goal(gid)
    rig.step(2)
    (result,) = rig.results(gid)
    assert result.status is GoalStatus.CANCELED
    assert result.error_code == ErrorCode.SUCCESSFUL
    assert result.error_string == ""
    assert "canceled on request" in result.details
