"""Goals are checked against the hardware's ``position_limits`` when they are accepted."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jtc_hw import GoalRejected, JointTrajectory, TrajectoryPoint
from jtc_hw.controller.messages import PointColumns
from jtc_hw.daemon.core.backend import check_position_limits
from jtc_hw.daemon.robot import joint_position_limits, load_robot

LIMITS = {"a": (-1.0, 1.0), "c": (0.0, math.inf)}


def test_waypoints_within_the_limits_pass() -> None:
    traj = JointTrajectory(["a", "b", "c"], [TrajectoryPoint(1.0, [0.5, 99.0, 0.0]),
                                             TrajectoryPoint(2.0, [-1.0, -99.0, 1e3])])
    check_position_limits(traj, LIMITS)


@pytest.mark.parametrize("columns", [False, True])
def test_the_first_waypoint_outside_names_point_joint_value_and_limits(columns: bool) -> None:
    rows = [[0.0, 5.0, 0.1], [0.9, 0.0, 0.2], [0.2, 0.0, -0.5], [1.5, 0.0, 0.0]]
    if columns:
        points: object = PointColumns([1, 2, 3, 4], positions=np.array(rows))
    else:
        points = [TrajectoryPoint(t + 1.0, row) for t, row in enumerate(rows)]
    traj = JointTrajectory(["a", "b", "c"], points)  # type: ignore[arg-type]
    with pytest.raises(GoalRejected) as caught:
        check_position_limits(traj, LIMITS)
    assert caught.value.error_code == -1
    assert str(caught.value).startswith(
        "point 2: joint 'c' position -0.5 rad is outside its position_limits [0, inf]")


def test_points_without_positions_and_unknown_joints_are_left_to_validation() -> None:
    check_position_limits(JointTrajectory(["a"], [TrajectoryPoint(1.0, None, [9.0])]), LIMITS)
    check_position_limits(JointTrajectory(["x"], [TrajectoryPoint(1.0, [9.0])]), LIMITS)
    check_position_limits(JointTrajectory(["a"], []), LIMITS)


def test_the_limits_come_from_the_hardware_configuration() -> None:
    robot = load_robot({
        "joints": ["j1", "j2", "j3"], "command_interfaces": ["position"],
        "state_interfaces": ["position"], "update_rate": 100.0,
        "hardware": [{"name": "arm", "kind": "mirror", "joints": ["j1", "j2", "j3"],
                      "params": {"position_limits": {"j1": [-0.5, 0.5], "j3": [-math.inf, 2.0]}}}],
    })
    assert joint_position_limits(robot) == {"j1": (-0.5, 0.5), "j3": (-math.inf, 2.0)}
