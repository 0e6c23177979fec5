"""Check a ``JointTrajectory`` against the configuration and turn it into arrays.

Every rejection names the point, the joint, the field and the value, and says what would be
accepted. Codes follow ``control_msgs/FollowJointTrajectory``: joint problems are
``INVALID_JOINTS`` (-2), everything else here ``INVALID_GOAL`` (-1); a trajectory entirely in
the past is found when it is spliced (``OLD_HEADER_TIMESTAMP``, -3, see ``Trajectory.splice``).
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np

from ..errors import GoalRejected
from .config import ControllerConfig
from .trajectory import JointTrajectory, PreparedTrajectory

INVALID_GOAL = -1
INVALID_JOINTS = -2
_FIELDS = ("positions", "velocities", "accelerations", "effort")


def prepare(config: ControllerConfig, msg: Any) -> PreparedTrajectory:
    """Validate ``msg`` and return it in controller joint order.

    Args:
        config: the controller configuration (joints, partial goals, integration, interfaces).
        msg: a ``JointTrajectory`` with at least one point (an empty one is a stop request that
            the caller handles).

    Returns:
        The prepared trajectory.

    Raises:
        GoalRejected: with the precise reason and result code.
    """
    if not isinstance(msg, JointTrajectory):
        raise GoalRejected(f"expected a JointTrajectory, got {type(msg).__name__}")
    if not msg.points:
        raise GoalRejected("empty trajectory: it has no points")
    joint_index = _joint_columns(config, msg)
    k = len(msg.joint_names)
    if isinstance(msg.start_time_ns, bool) or msg.start_time_ns < 0:
        raise GoalRejected(
            f"start time {msg.start_time_ns} ns is negative; use 0 to start now or a time on "
            "the controller's clock"
        )
    m = len(msg.points)
    arrays = {name: np.full((m, k), np.nan) for name in _FIELDS}
    present: dict[str, list[bool]] = {name: [] for name in _FIELDS}
    times: list[int] = []
    for i, point in enumerate(msg.points):
        t = point.time_from_start_ns
        if t < 0:
            raise GoalRejected(
                f"point #{i}: time_from_start {t / 1e9:.9f} s is negative; it must be >= 0"
            )
        if times and t <= times[-1]:
            raise GoalRejected(
                f"point #{i}: time_from_start {t / 1e9:.9f} s is not after point #{i - 1} "
                f"({times[-1] / 1e9:.9f} s); times must be strictly increasing"
            )
        times.append(t)
        for name in _FIELDS:
            values = getattr(point, name)
            present[name].append(values is not None)
            if values is None:
                continue
            if len(values) != k:
                raise GoalRejected(
                    f"point #{i}: {name} has {len(values)} value(s) but joint_names has {k}; "
                    "give one value per joint or leave the field empty"
                )
            for j, value in enumerate(values):
                if isinstance(value, bool) or not isinstance(value, numbers.Real):
                    raise GoalRejected(
                        f"point #{i}: {name}[{j}] (joint '{msg.joint_names[j]}') is {value!r}, "
                        "not a number"
                    )
                if not math.isfinite(value):
                    raise GoalRejected(
                        f"point #{i}: {name}[{j}] (joint '{msg.joint_names[j]}') is "
                        f"{float(value)!r}; values must be finite"
                    )
            arrays[name][i] = values
        _check_point_fields(config, i, present, point_index=i)
    if any(present["effort"]) and not all(present["effort"]):
        missing = present["effort"].index(False)
        raise GoalRejected(
            f"point #{missing} has no effort while other points do; give effort at every "
            "point or at none"
        )
    if not config.allow_nonzero_velocity_at_trajectory_end and present["velocities"][-1]:
        last = arrays["velocities"][-1]
        for j, value in enumerate(last):
            if value != 0.0:
                raise GoalRejected(
                    f"point #{m - 1} (the last): velocity of joint '{msg.joint_names[j]}' is "
                    f"{float(value)!r}, must be 0 because "
                    "allow_nonzero_velocity_at_trajectory_end is false"
                )
    return PreparedTrajectory(
        joint_indices=joint_index,
        start_time_ns=int(msg.start_time_ns),
        times_ns=tuple(times),
        positions=arrays["positions"],
        velocities=arrays["velocities"],
        accelerations=arrays["accelerations"],
        effort=arrays["effort"],
        has_positions=tuple(present["positions"]),
        has_velocities=tuple(present["velocities"]),
        has_accelerations=tuple(present["accelerations"]),
        has_effort=tuple(present["effort"]),
    )


def _joint_columns(config: ControllerConfig, msg: JointTrajectory) -> np.ndarray[Any, Any]:
    names = msg.joint_names
    if not names:
        raise GoalRejected(
            "joint_names is empty; name the joints the points refer to", INVALID_JOINTS
        )
    index = {name: i for i, name in enumerate(config.joints)}
    seen: set[str] = set()
    cols = []
    for name in names:
        if not isinstance(name, str):
            raise GoalRejected(f"joint name {name!r} is not a string", INVALID_JOINTS)
        if name not in index:
            raise GoalRejected(
                f"joint '{name}' is not a controller joint (controller joints: "
                f"{', '.join(config.joints)})",
                INVALID_JOINTS,
            )
        if name in seen:
            raise GoalRejected(f"joint '{name}' appears twice in joint_names", INVALID_JOINTS)
        seen.add(name)
        cols.append(index[name])
    if len(names) != len(config.joints) and not config.allow_partial_joints_goal:
        missing = [j for j in config.joints if j not in seen]
        raise GoalRejected(
            f"joints {', '.join(missing)} missing from the trajectory; every controller joint "
            "must be given unless allow_partial_joints_goal is true",
            INVALID_JOINTS,
        )
    return np.asarray(cols, dtype=np.intp)


def _check_point_fields(
    config: ControllerConfig, i: int, present: dict[str, list[bool]], point_index: int
) -> None:
    has_p = present["positions"][i]
    has_v = present["velocities"][i]
    has_a = present["accelerations"][i]
    has_e = present["effort"][i]
    if has_e and "effort" not in config.command_interfaces:
        raise GoalRejected(
            f"point #{point_index}: effort is only used with the 'effort' command interface "
            f"(configured: {', '.join(config.command_interfaces)}); remove the effort field"
        )
    if not (has_p or has_v or has_a):
        raise GoalRejected(
            f"point #{point_index}: no positions, velocities or accelerations; a point needs "
            "positions (or, with allow_integration_in_goal_trajectories, velocities or "
            "accelerations)"
        )
    if not has_p:
        if config.interpolation_method == "none":
            raise GoalRejected(
                f"point #{point_index}: no positions; interpolation_method 'none' does not "
                "integrate derivatives, so every point needs positions"
            )
        if not config.allow_integration_in_goal_trajectories:
            raise GoalRejected(
                f"point #{point_index}: no positions; velocity- or acceleration-only points are "
                "accepted only with allow_integration_in_goal_trajectories: true"
            )
    elif has_a and not has_v:
        raise GoalRejected(
            f"point #{point_index}: accelerations without velocities; a quintic spline needs "
            "positions, velocities and accelerations (give velocities, or drop accelerations "
            "for linear interpolation)"
        )
