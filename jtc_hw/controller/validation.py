"""Check a ``JointTrajectory`` against the configuration and turn it into arrays.

Every rejection names the point, the joint, the field and the value, and says what would be
accepted. Codes follow ``control_msgs/FollowJointTrajectory``: joint problems are
``INVALID_JOINTS`` (-2), everything else here ``INVALID_GOAL`` (-1); a trajectory entirely in
the past is found when it is spliced (``OLD_HEADER_TIMESTAMP``, -3, see ``Trajectory.splice``).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from itertools import chain, repeat
from operator import attrgetter, is_not
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import GoalRejected
from .config import ControllerConfig
from .interpolation import F64
from .messages import FIELDS, JointTrajectory, PointColumns, PreparedTrajectory, TrajectoryPoint
from .trajectory import MAX_TIME_NS

INVALID_GOAL = -1
INVALID_JOINTS = -2
FLT_EPSILON = 2.0**-23
"""C's ``FLT_EPSILON`` (1.1920929e-07, exactly 2**-23): upstream counts a last-point velocity
as non-zero only above it, so a "stopped" velocity with rounding noise is not rejected."""


def prepare(config: ControllerConfig, msg: Any) -> PreparedTrajectory:
    """Validate ``msg`` and return it in controller joint order.

    The checks run on whole arrays (one numpy operation per check for all points); only when
    one fails, or the points are irregular (mixed lengths, values that are not plain numbers),
    are they walked one by one, to name the first offending point, field and value.

    Args:
        config: the controller configuration (joints, partial goals, integration, interfaces).
        msg: a ``JointTrajectory`` with at least one point (an empty one is a stop request that
            the caller handles).

    Raises:
        GoalRejected: with the precise reason and result code.
    """
    if not isinstance(msg, JointTrajectory):
        raise GoalRejected(f"expected a JointTrajectory, got {type(msg).__name__}")
    if not msg.points:
        raise GoalRejected("empty trajectory: it has no points")
    joint_index = _joint_columns(config, msg)
    if isinstance(msg.start_time_ns, bool) or msg.start_time_ns < 0:
        raise GoalRejected(
            f"start time {msg.start_time_ns} ns is negative; use 0 to start now or a time on "
            "the controller's clock"
        )
    columns = _columns(msg.points, len(msg.joint_names))
    if columns is not None:
        prepared = _checked(config, joint_index, msg.start_time_ns, *columns)
        if prepared is not None:
            return prepared
    return _prepare_points(config, msg, joint_index)


_Columns = tuple[NDArray[np.int64], dict[str, tuple[F64, NDArray[np.bool_]]]]
_PLAIN_NUMBERS = frozenset({float, int, np.float64})
_TIME = attrgetter("time_from_start_ns")
"""Value types converted to float64 exactly as the per-point path converts them."""


def _columns(points: Sequence[TrajectoryPoint], k: int) -> _Columns | None:
    """Times and, per field present anywhere, ``(m, k)`` values and ``(m,)`` presence; None when
    the points do not make regular arrays of plain numbers (the per-point path says why)."""
    fields: dict[str, tuple[F64, NDArray[np.bool_]]] = {}
    if isinstance(points, PointColumns):
        for name in FIELDS:
            column = points.values(name)
            if column is not None:
                if column[0].shape[1] != k:
                    return None
                fields[name] = column
        return points.times_ns, fields
    m = len(points)
    try:
        times = np.fromiter(map(_TIME, points), dtype=np.int64, count=m)
    except OverflowError:  # beyond the clock's range
        return None
    for name in FIELDS:
        given_at: list[tuple[float, ...] | None] = list(map(attrgetter(name), points))
        present = np.fromiter(map(is_not, given_at, repeat(None)), dtype=np.bool_, count=m)
        if not present.any():
            continue
        rows = [v for v in given_at if v is not None]
        if not _PLAIN_NUMBERS.issuperset(map(type, chain.from_iterable(rows))):
            return None
        try:
            given: F64 = np.array(rows, dtype=np.float64)
        except (ValueError, OverflowError):  # mixed lengths; an integer beyond float64
            return None
        if given.shape != (len(rows), k):
            return None
        values: F64 = np.full((m, k), np.nan)
        values[present] = given
        fields[name] = (values, present)
    return times, fields


def _checked(
    config: ControllerConfig,
    joint_index: NDArray[np.intp],
    start_time_ns: int,
    times: NDArray[np.int64],
    fields: dict[str, tuple[F64, NDArray[np.bool_]]],
) -> PreparedTrajectory | None:
    """Every check of ``_prepare_points`` on whole arrays; None if any fails."""
    m, k = times.shape[0], joint_index.shape[0]
    if times[0] < 0 or (m > 1 and not bool((np.diff(times) > 0).all())):
        return None
    arrays: dict[str, F64] = {}
    present: dict[str, NDArray[np.bool_]] = {}
    for name in FIELDS:
        if name not in fields:
            arrays[name] = np.full((m, k), np.nan)
            present[name] = np.zeros(m, dtype=bool)
            continue
        values, mask = fields[name]
        if not np.isfinite(values[mask]).all():
            return None
        arrays[name] = np.where(mask[:, None], values, np.nan)
        present[name] = mask
    has_p, has_v, has_a, has_e = (present[name] for name in FIELDS)
    if has_e.any() and ("effort" not in config.command_interfaces or not has_e.all()):
        return None
    if not (has_p | has_v | has_a).all() or (has_p & has_a & ~has_v).any():
        return None
    if not has_p.all() and (
        config.interpolation_method == "none" or not config.allow_integration_in_goal_trajectories
    ):
        return None
    if (
        not config.allow_nonzero_velocity_at_trajectory_end
        and has_v[-1]
        and bool((np.abs(arrays["velocities"][-1]) > FLT_EPSILON).any())
    ):
        return None
    for name in FIELDS:
        arrays[name].setflags(write=False)
        present[name].setflags(write=False)
    return _prepared(joint_index, start_time_ns, times, arrays, present)


def _prepare_points(
    config: ControllerConfig, msg: JointTrajectory, joint_index: NDArray[np.intp]
) -> PreparedTrajectory:
    """Point by point: raises ``GoalRejected`` naming the first problem, in point order."""
    k = len(msg.joint_names)
    m = len(msg.points)
    arrays = {name: np.full((m, k), np.nan) for name in FIELDS}
    present: dict[str, list[bool]] = {name: [] for name in FIELDS}
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
        if t > MAX_TIME_NS:
            raise GoalRejected(
                f"point #{i}: time_from_start {t / 1e9:.9f} s is beyond the controller clock's "
                f"range ({MAX_TIME_NS} ns); give times of at most {MAX_TIME_NS / 1e9:.0f} s"
            )
        times.append(t)
        for name in FIELDS:
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
        _check_point_fields(config, i, present)
    if any(present["effort"]) and not all(present["effort"]):
        missing = present["effort"].index(False)
        raise GoalRejected(
            f"point #{missing} has no effort while other points do; give effort at every "
            "point or at none"
        )
    if not config.allow_nonzero_velocity_at_trajectory_end and present["velocities"][-1]:
        last = arrays["velocities"][-1]
        for j, value in enumerate(last):
            if abs(value) > FLT_EPSILON:
                raise GoalRejected(
                    f"point #{m - 1} (the last): velocity of joint '{msg.joint_names[j]}' is "
                    f"{float(value)!r}, must be 0 (|velocity| <= {FLT_EPSILON:.8g}, FLT_EPSILON) "
                    "because allow_nonzero_velocity_at_trajectory_end is false"
                )
    flags = {name: np.array(present[name], dtype=bool) for name in FIELDS}
    return _prepared(joint_index, msg.start_time_ns, np.array(times, dtype=np.int64), arrays, flags)


def _prepared(
    joint_index: NDArray[np.intp],
    start_time_ns: int,
    times: NDArray[np.int64],
    arrays: Mapping[str, F64],
    flags: Mapping[str, NDArray[np.bool_]],
) -> PreparedTrajectory:
    """The values and ``has_*`` flags, per name of :data:`FIELDS`, as a PreparedTrajectory."""
    positions, velocities, accelerations, effort = (arrays[name] for name in FIELDS)
    has_p, has_v, has_a, has_e = (flags[name] for name in FIELDS)
    return PreparedTrajectory(joint_index, int(start_time_ns), times, positions, velocities,
                              accelerations, effort, has_p, has_v, has_a, has_e)


def _joint_columns(config: ControllerConfig, msg: JointTrajectory) -> NDArray[np.intp]:
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


def _check_point_fields(config: ControllerConfig, i: int, present: dict[str, list[bool]]) -> None:
    has_p, has_v, has_a, has_e = (present[name][i] for name in FIELDS)
    if has_e and "effort" not in config.command_interfaces:
        raise GoalRejected(
            f"point #{i}: effort is only used with the 'effort' command interface "
            f"(configured: {', '.join(config.command_interfaces)}); remove the effort field"
        )
    if not (has_p or has_v or has_a):
        raise GoalRejected(
            f"point #{i}: no positions, velocities or accelerations; a point needs "
            "positions (or, with allow_integration_in_goal_trajectories, velocities or "
            "accelerations)"
        )
    if not has_p:
        if config.interpolation_method == "none":
            raise GoalRejected(
                f"point #{i}: no positions; interpolation_method 'none' does not "
                "integrate derivatives, so every point needs positions"
            )
        if not config.allow_integration_in_goal_trajectories:
            raise GoalRejected(
                f"point #{i}: no positions; velocity- or acceleration-only points are "
                "accepted only with allow_integration_in_goal_trajectories: true"
            )
    elif has_a and not has_v:
        raise GoalRejected(
            f"point #{i}: accelerations without velocities; a quintic spline needs "
            "positions, velocities and accelerations (give velocities, or drop accelerations "
            "for linear interpolation)"
        )
