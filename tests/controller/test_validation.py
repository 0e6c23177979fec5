"""Every rejection reason names what is wrong, where, and carries the right result code."""

from __future__ import annotations

import math
from typing import Any

import pytest

from jtc_hw import ErrorCode, GoalRejected, JointState, JointTrajectory, JointTrajectoryController
from jtc_hw import TrajectoryPoint as P

from conftest import make_config

J = ("j1", "j2")


def reject(msg: Any, code: ErrorCode = ErrorCode.INVALID_GOAL, **params: Any) -> str:
    ctrl = JointTrajectoryController(make_config(**params))
    ctrl.activate(0, JointState([0.0, 0.0], [0.0, 0.0]))
    reference = ctrl.reference
    with pytest.raises(GoalRejected) as info:
        ctrl.send_goal(0, msg)
    assert info.value.error_code == code
    assert ctrl.reference is reference and ctrl.holding  # nothing changed
    return info.value.reason


def test_accepts_a_valid_goal() -> None:
    ctrl = JointTrajectoryController(make_config())
    ctrl.activate(0, JointState([0.0, 0.0], [0.0, 0.0]))
    assert ctrl.send_goal(0, JointTrajectory(J, [P(1.0, [1, 2])])) == 1


def test_empty_trajectory() -> None:
    assert "no points" in reject(JointTrajectory(J, []))


def test_not_a_trajectory() -> None:
    assert "expected a JointTrajectory" in reject({"joint_names": J})


def test_empty_joint_names() -> None:
    assert "joint_names is empty" in reject(
        JointTrajectory((), [P(1.0, [])]), ErrorCode.INVALID_JOINTS
    )


def test_unknown_joint() -> None:
    r = reject(JointTrajectory(("j1", "elbow"), [P(1.0, [1, 2])]), ErrorCode.INVALID_JOINTS)
    assert "'elbow' is not a controller joint" in r and "j1, j2" in r


def test_duplicate_joint() -> None:
    r = reject(JointTrajectory(("j1", "j1"), [P(1.0, [1, 2])]), ErrorCode.INVALID_JOINTS)
    assert "'j1' appears twice" in r


def test_missing_joint_without_partial_goals() -> None:
    r = reject(JointTrajectory(("j1",), [P(1.0, [1])]), ErrorCode.INVALID_JOINTS)
    assert "j2 missing" in r and "allow_partial_joints_goal" in r


def test_partial_goal_allowed() -> None:
    ctrl = JointTrajectoryController(make_config(allow_partial_joints_goal=True))
    ctrl.activate(0, JointState([0.0, 0.0], [0.0, 0.0]))
    ctrl.send_goal(0, JointTrajectory(("j2",), [P(1.0, [1])]))


@pytest.mark.parametrize("field", ["positions", "velocities", "accelerations"])
def test_size_mismatch(field: str) -> None:
    values: dict[str, Any] = {"positions": [0, 0], "velocities": [0, 0], "accelerations": [0, 0]}
    values[field] = [1, 2, 3]
    r = reject(JointTrajectory(J, [P(1.0, [0, 0]), P(2.0, **values)]))
    assert f"point #1: {field} has 3 value(s) but joint_names has 2" in r


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite(bad: float) -> None:
    r = reject(JointTrajectory(J, [P(1.0, [0, 0], [0, bad])]))
    assert "point #0: velocities[1] (joint 'j2')" in r and "finite" in r


def test_not_a_number() -> None:
    r = reject(JointTrajectory(J, [P(1.0, [0, "x"])]))  # type: ignore[list-item]
    assert "positions[1] (joint 'j2') is 'x', not a number" in r


def test_non_finite_time_is_refused_when_built() -> None:
    with pytest.raises(ValueError, match="finite"):
        P(math.nan, [0, 0])


def test_times_not_strictly_increasing() -> None:
    r = reject(JointTrajectory(J, [P(1.0, [0, 0]), P(1.0, [1, 1])]))
    assert "point #1: time_from_start 1.000000000 s is not after point #0" in r


def test_negative_time() -> None:
    assert "negative" in reject(JointTrajectory(J, [P(-0.5, [0, 0])]))


def test_negative_start_time() -> None:
    assert "start time -5 ns is negative" in reject(JointTrajectory(J, [P(1.0, [0, 0])], -5))


def test_effort_without_effort_interface() -> None:
    r = reject(JointTrajectory(J, [P(1.0, [0, 0], effort=[1, 1])]))
    assert "effort is only used with the 'effort' command interface" in r


def test_effort_at_some_points_only() -> None:
    r = reject(
        JointTrajectory(J, [P(1.0, [0, 0], effort=[1, 1]), P(2.0, [0, 0])]),
        command_interfaces=("effort",),
    )
    assert "point #1 has no effort" in r


def test_velocity_only_without_integration() -> None:
    r = reject(JointTrajectory(J, [P(1.0, velocities=[1, 1])]))
    assert "allow_integration_in_goal_trajectories" in r


def test_no_fields_at_all() -> None:
    r = reject(JointTrajectory(J, [P(1.0)]), allow_integration_in_goal_trajectories=True)
    assert "no positions, velocities or accelerations" in r


def test_none_method_needs_positions() -> None:
    r = reject(
        JointTrajectory(J, [P(1.0, velocities=[1, 1])]),
        allow_integration_in_goal_trajectories=True,
        interpolation_method="none",
    )
    assert "'none' does not integrate" in r


def test_accelerations_without_velocities() -> None:
    r = reject(JointTrajectory(J, [P(1.0, [0, 0], accelerations=[1, 1])]))
    assert "accelerations without velocities" in r


def test_nonzero_final_velocity_when_forbidden() -> None:
    r = reject(
        JointTrajectory(J, [P(1.0, [0, 0], [0, 0]), P(2.0, [1, 1], [0, 0.25])]),
        allow_nonzero_velocity_at_trajectory_end=False,
    )
    assert "velocity of joint 'j2' is 0.25, must be 0" in r


def test_entirely_in_the_past() -> None:
    ctrl = JointTrajectoryController(make_config())
    ctrl.activate(10_000_000_000, JointState([0.0, 0.0], [0.0, 0.0]))
    with pytest.raises(GoalRejected) as info:
        ctrl.send_goal(10_000_000_000, JointTrajectory(J, [P(1.0, [0, 0])], 1_000_000_000))
    assert info.value.error_code == ErrorCode.OLD_HEADER_TIMESTAMP
    assert "lie in the past" in info.value.reason
