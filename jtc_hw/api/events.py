"""The JSON forms of what the daemon sends and the client writes: goal and record events,
desired states, trajectories and tolerances (no I/O; :mod:`.framing` encodes them).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

from ..controller.goals import GoalFeedback, GoalResult
from ..controller.messages import FIELDS, NS_PER_S, JointTrajectory, TrajectoryPoint
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
