"""The JSON forms of what the daemon sends and the client writes: goal and record events,
desired states, trajectories and tolerances (no I/O; :mod:`.framing` encodes them).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from itertools import chain
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..controller.goals import GoalFeedback, GoalResult
from ..controller.messages import (
    FIELDS,
    NS_PER_S,
    JointTrajectory,
    PointColumns,
    TrajectoryPoint,
)
from ..controller.tolerances import JointTolerance
from ..controller.trajectory import QueriedState, TrajectorySample


def sample_to_json(sample: TrajectorySample | QueriedState) -> dict[str, Any]:
    """A desired state as ``{positions, velocities, accelerations, effort}`` arrays."""
    return {
        "positions": sample.positions,
        "velocities": sample.velocities,
        "accelerations": sample.accelerations,
        "effort": sample.effort,
    }


def result_event(result: GoalResult) -> dict[str, Any]:
    """The ``result`` event of a goal: ``error_string`` is upstream's text, ``details`` what
    we add (which joint broke which tolerance; ``""`` when nothing).
    """
    return {
        "event": "result",
        "goal_id": result.goal_id,
        "status": result.status.value,
        "error_code": int(result.error_code),
        "error_string": result.error_string,
        "details": result.details,
        "time_ns": result.time_ns,
    }


def feedback_event(feedback: GoalFeedback, joint_names: Sequence[str]) -> dict[str, Any]:
    """The ``feedback`` event of a goal (``actual.velocities`` is null without a reading)."""
    error = feedback.error
    return {
        "event": "feedback",
        "goal_id": feedback.goal_id,
        "time_ns": feedback.time_ns,
        "time_from_start": feedback.time_from_start,
        "joint_names": list(joint_names),
        "desired": sample_to_json(feedback.desired),
        "actual": {
            "positions": feedback.actual_positions,
            "velocities": feedback.actual_velocities,
        },
        "error": {
            "positions": error[0],
            "velocities": error[1],
            "accelerations": error[2],
        },
    }


def command_event(trajectory: JointTrajectory, goal_id: int | None,
                  time_ns: int) -> dict[str, Any]:
    """The ``command`` event: a command the daemon accepted at ``time_ns`` (daemon clock), as
    received (``trajectory_to_json``; ``start_time_ns`` absent: "start now"); ``goal_id`` null
    for a topic trajectory (an empty one: a stop).
    """
    return {"event": "command", "time_ns": time_ns, "goal_id": goal_id,
            "trajectory": trajectory_to_json(trajectory)}


def record_event(event: Mapping[str, Any]) -> dict[str, Any]:
    """The ``record`` event: a goal's result, a hardware fault or a re-arm, as the bags'
    ``goal_events`` hold it (``{"event": "result" | "fault" | "rearm", ..., "time_ns"}``,
    docs/recording.md), for connections subscribed with ``commands`` (``jtc-hw record``).
    """
    return {"event": "record", "record": dict(event)}


def trajectory_from_json(obj: Mapping[str, Any]) -> JointTrajectory:
    """A ``JointTrajectory`` back from ``trajectory_to_json``'s form (a ``command`` event's
    ``trajectory``; ``start_in`` is not resolved: give ``start_time_ns``).

    Raises:
        KeyError, TypeError, ValueError: not that form.
    """
    return JointTrajectory(
        obj["joint_names"],
        [TrajectoryPoint(float(p["time_from_start"]), p.get("positions"), p.get("velocities"),
                         p.get("accelerations"), p.get("effort")) for p in obj["points"]],
        int(obj.get("start_time_ns", 0)),
    )


def trajectory_to_json(
    trajectory: JointTrajectory, start_in: float | None = None
) -> dict[str, Any]:
    """The wire form of a ``JointTrajectory`` (for clients).

    ``start_time_ns`` is written when non-zero; ``start_in`` instead, when given.

    Raises:
        ValueError: both a non-zero ``start_time_ns`` and ``start_in``.
    """
    if start_in is not None and trajectory.start_time_ns:
        raise ValueError("give either a trajectory start_time_ns or start_in, not both")
    points = []
    for p in trajectory.points:
        point: dict[str, Any] = {"time_from_start": p.time_from_start_ns / NS_PER_S}
        for name in FIELDS:
            values = getattr(p, name)
            if values is not None:
                point[name] = list(values)
        points.append(point)
    out: dict[str, Any] = {"joint_names": list(trajectory.joint_names), "points": points}
    if start_in is not None:
        out["start_in"] = start_in
    elif trajectory.start_time_ns:
        out["start_time_ns"] = trajectory.start_time_ns
    return out


def tolerances_to_json(tolerances: Sequence[JointTolerance]) -> list[dict[str, Any]]:
    """The wire form of tolerance overrides."""
    return [dataclasses.asdict(t) for t in tolerances]  # name, position, velocity, acceleration


BINARY_MIN_POINTS = 100
"""Trajectories of this many points or more go as binary frames to a daemon that speaks
protocol version 2 (docs/protocol.md, "Binary frames"): below it JSON costs little."""
_NUMBERS = frozenset({float, int, np.float64, np.float32, np.int64, np.int32})
"""Number types a client's points may hold (the JSON encoder takes numpy's too); not bool."""
_POINT_KEYS = frozenset({"time_from_start", *FIELDS})


def trajectory_columns(
    trajectory: JointTrajectory | Mapping[str, Any],
    start_in: float | None = None,
    min_points: int = BINARY_MIN_POINTS,
) -> tuple[dict[str, Any], NDArray[np.float64], list[str]] | None:
    """A trajectory as a binary frame's parts: its wire form without ``points``, the points as
    an ``(m, columns)`` float64 array and the column names (docs/protocol.md, "Binary frames").

    ``None`` when it must go as JSON: fewer than ``min_points`` points, or points
    that are not regular (a field only some points carry, a vector not one value per joint, a
    value that is not a number, an unknown key): the daemon then names the problem as it does
    for JSON.

    Raises:
        ValueError: both a non-zero ``start_time_ns`` and ``start_in`` (as
            ``trajectory_to_json``).
    """
    if isinstance(trajectory, JointTrajectory):
        if len(trajectory.points) < max(1, min_points):
            return None
        head = trajectory_to_json(JointTrajectory(trajectory.joint_names, (),
                                                  trajectory.start_time_ns), start_in)
        del head["points"]
        table = _columns_of_points(trajectory.points, len(trajectory.joint_names))
    else:
        points = trajectory.get("points")
        names = trajectory.get("joint_names")
        if not isinstance(points, list) or len(points) < max(1, min_points):
            return None
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            return None
        head = {key: value for key, value in trajectory.items() if key != "points"}
        if start_in is not None:
            if "start_time_ns" in head:
                raise ValueError("give either the trajectory's start_time_ns or start_in")
            head["start_in"] = start_in
        table = _columns_of_mappings(points, len(names))
    if table is None:
        return None
    values, fields = table
    names = list(head["joint_names"])
    return head, values, ["time_from_start", *(f"{f}.{j}" for f in fields for j in names)]


def _columns_of_points(
    points: Sequence[TrajectoryPoint], k: int
) -> tuple[NDArray[np.float64], list[str]] | None:
    if isinstance(points, PointColumns):
        blocks, fields = [points.times_ns / NS_PER_S], []
        for name in FIELDS:
            given = points.values(name)
            if given is None:
                continue
            values, present = given
            if not present.all() or values.shape[1] != k:
                return None
            blocks.append(values)
            fields.append(name)
        return np.column_stack(blocks), fields
    first = points[0]
    fields = [name for name in FIELDS if getattr(first, name) is not None]
    rows = []
    for p in points:
        row = [p.time_from_start_ns / NS_PER_S]
        for name in FIELDS:
            vector = getattr(p, name)
            if (vector is None) != (name not in fields) or (vector is not None and
                                                             len(vector) != k):
                return None
            if vector is not None:
                row.extend(vector)
        rows.append(row)
    return np.array(rows, dtype=np.float64), fields


def _columns_of_mappings(
    points: list[Any], k: int
) -> tuple[NDArray[np.float64], list[str]] | None:
    if not all(isinstance(p, Mapping) for p in points):
        return None
    keys = set(points[0])
    if "time_from_start" not in keys or not keys <= _POINT_KEYS:
        return None
    fields = [name for name in FIELDS if name in keys]
    if any(set(p) != keys for p in points):
        return None
    times = [p["time_from_start"] for p in points]
    if not _NUMBERS.issuperset(map(type, times)):
        return None
    blocks = [np.array(times, dtype=np.float64)[:, None]]
    for name in fields:
        column = [p[name] for p in points]
        if not all(type(v) in (list, tuple) and len(v) == k for v in column):
            return None
        if not _NUMBERS.issuperset(map(type, chain.from_iterable(column))):
            return None
        blocks.append(np.array(column, dtype=np.float64).reshape(len(points), k))
    return np.hstack(blocks), fields
