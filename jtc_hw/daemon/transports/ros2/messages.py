"""Our states, goal events and answers as ROS 2 messages (CDR), and the small requests decoded.

Theory of operation
-------------------
What the transport publishes and replies is built here with the distro's rosbags type store
(``types.RosTypes``) and serialized by rosbags: a message is made with :func:`make`, which
fills every field the distro's definition has from the values given by name and leaves the
others at their zero (so one builder serves Humble's ``controller_state`` with
``desired``/``actual`` and Jazzy's with ``reference``/``feedback`` and
``speed_scaling_factor``: the values are offered under both names). The large inputs (a goal,
a ``joint_trajectory`` sample) are decoded by ``cdr`` without a Python object per number; the
small ones (cancel, get_result, query_state, speed scaling: a few fixed-size fields) by rosbags
here, each failure a ``CdrError``.

Stamps are ROS time: the system clock, as upstream's nodes stamp with their node clock.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from typing import Any, Final

import numpy as np

from ....controller.goals import GoalFeedback
from ....controller.trajectory import QueriedState
from .cdr import CdrError

__all__ = ["Messages", "make", "ros_time"]

CDR_LE: Final = b"\x00\x01\x00\x00"
"""The encapsulation header: CDR, little-endian."""
_SEND_GOAL_RESPONSE: Final = struct.Struct("<4s?3xiI")
"""``bool accepted`` then ``builtin_interfaces/Time stamp`` (int32 aligned to 4 in the body)."""
SMALL_REQUEST_BYTES: Final = 4096
"""The longest cancel / get_result / query_state / speed-scaling payload decoded."""

JOINT_STATE: Final = "sensor_msgs/msg/JointState"
CONTROLLER_STATE: Final = "control_msgs/msg/JointTrajectoryControllerState"
TRAJECTORY: Final = "trajectory_msgs/msg/JointTrajectory"
SPEED_SCALING: Final = "control_msgs/msg/SpeedScalingFactor"
STATUS_ARRAY: Final = "action_msgs/msg/GoalStatusArray"
ACTION: Final = "control_msgs/action/FollowJointTrajectory"
FEEDBACK_MESSAGE: Final = f"{ACTION}_FeedbackMessage"
SEND_GOAL: Final = f"{ACTION}_SendGoal"
GET_RESULT: Final = f"{ACTION}_GetResult"
CANCEL_GOAL: Final = "action_msgs/srv/CancelGoal"
QUERY_STATE: Final = "control_msgs/srv/QueryTrajectoryState"
GET_PARAMETERS: Final = "rcl_interfaces/srv/GetParameters"
SET_PARAMETERS: Final = "rcl_interfaces/srv/SetParameters"
LIST_PARAMETERS: Final = "rcl_interfaces/srv/ListParameters"
PARAMETER_VALUE: Final = "rcl_interfaces/msg/ParameterValue"


def ros_time(ns: int) -> dict[str, int]:
    """``builtin_interfaces/Time`` fields of nanoseconds since the epoch."""
    return {"sec": ns // 10**9, "nanosec": ns % 10**9}


def _zero(store: Any, node: tuple[Any, Any]) -> Any:
    kind, spec = node
    kind = int(kind)
    if kind == 1:  # BASE
        name = spec[0]
        if name == "string":
            return ""
        if name == "bool":
            return False
        return 0.0 if name.startswith("float") else 0
    if kind == 2:  # NAME
        return make(store, spec)
    if kind == 3:  # ARRAY
        inner, length = spec
        if int(inner[0]) == 1 and inner[1][0] != "string":
            return np.zeros(length, dtype=_DTYPES.get(inner[1][0], np.float64))
        return [_zero(store, inner) for _ in range(length)]
    inner = spec[0]  # SEQUENCE
    if int(inner[0]) == 1 and inner[1][0] != "string":
        return np.zeros(0, dtype=_DTYPES.get(inner[1][0], np.float64))
    return []


_DTYPES: Final = {"float64": np.float64, "float32": np.float32, "uint8": np.uint8,
                  "int8": np.int8, "int16": np.int16, "uint16": np.uint16, "int32": np.int32,
                  "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
                  "byte": np.uint8, "char": np.uint8}


def make(store: Any, typename: str, **values: Any) -> Any:
    """A message of ``typename`` with the given fields (those the type does not have are
    ignored), every other field at its zero; a mapping value for a message field is made
    into that message the same way.

    Raises:
        KeyError: ``typename`` is not in the store.
    """
    _, fields = store.fielddefs[typename]
    args = {}
    for name, node in fields:
        if name in values:
            value = values[name]
            if isinstance(value, Mapping) and int(node[0]) == 2:
                value = make(store, node[1], **value)
            args[name] = value
        else:
            args[name] = _zero(store, node)
    return store.types[typename](**args)


def _f64(values: Any) -> np.ndarray:
    """A float64 array of a JSON vector (None entries: NaN) or of an array; None: empty."""
    if values is None:
        return np.zeros(0)
    return np.array([math.nan if v is None else v for v in values], dtype=np.float64)


def _duration(seconds: float | None) -> dict[str, int]:
    ns = 0 if seconds is None or not math.isfinite(seconds) else round(seconds * 1e9)
    return {"sec": ns // 10**9, "nanosec": ns % 10**9}


class Messages:
    """The messages of one transport: its distro's types, its joints (module docstring).

    Args:
        types: the distro's ``RosTypes``.
        joint_names: the controller's joints, in order.
    """

    def __init__(self, types: Any, joint_names: Sequence[str]) -> None:
        self.types = types
        self.store = types.typestore
        self.joint_names = list(joint_names)

    def _cdr(self, msg: Any, typename: str) -> bytes:
        return bytes(self.store.serialize_cdr(msg, typename))

    # -- topics -------------------------------------------------------------------------------

    def joint_state(self, snapshot: Mapping[str, Any], stamp_ns: int) -> bytes:
        """``/joint_states`` from a state snapshot (observers' ``state_json``): the measured
        positions and velocities, NaN where a joint has none (as joint_state_broadcaster
        fills a missing interface), effort NaN."""
        actual = snapshot["actual"]
        n = len(self.joint_names)
        velocity = _f64(actual.get("velocities")) if actual.get("velocities") else np.full(
            n, math.nan)
        msg = make(self.store, JOINT_STATE,
                   header={"stamp": ros_time(stamp_ns), "frame_id": ""},
                   name=self.joint_names, position=_f64(actual["positions"]),
                   velocity=velocity, effort=np.full(n, math.nan))
        return self._cdr(msg, JOINT_STATE)

    def _point(self, values: Mapping[str, Any] | None, **extra: Any) -> dict[str, Any]:
        values = values or {}
        return {"positions": _f64(values.get("positions")),
                "velocities": _f64(values.get("velocities")),
                "accelerations": _f64(values.get("accelerations")),
                "effort": _f64(values.get("effort")), **extra}

    def controller_state(self, snapshot: Mapping[str, Any], stamp_ns: int) -> bytes:
        """``/<controller>/controller_state`` in the distro's fields (module docstring)."""
        desired = snapshot["desired"]
        reference = self._point(desired, time_from_start=_duration(desired.get(
            "time_from_start")))
        actual = snapshot["actual"]
        feedback = self._point(actual, time_from_start=_duration(actual.get("time_from_start")))
        error = self._point(snapshot["error"])
        output = self._point(snapshot.get("output"))
        speed = (snapshot.get("speed_scaling") or {}).get("factor", 1.0)
        msg = make(self.store, CONTROLLER_STATE,
                   header={"stamp": ros_time(stamp_ns), "frame_id": ""},
                   joint_names=self.joint_names, reference=reference, desired=reference,
                   feedback=feedback, actual=feedback, error=error, output=output,
                   speed_scaling_factor=float(speed))
        return self._cdr(msg, CONTROLLER_STATE)

    def feedback(self, uuid: bytes, event: GoalFeedback, stamp_ns: int) -> bytes:
        """The action's ``FeedbackMessage`` of a goal's feedback."""
        d = event.desired
        desired = {"positions": np.asarray(d.positions, np.float64),
                   "velocities": np.asarray(d.velocities, np.float64),
                   "accelerations": np.asarray(d.accelerations, np.float64),
                   "effort": np.zeros(0),
                   "time_from_start": _duration(event.time_from_start)}
        velocities = event.actual_velocities
        actual = {"positions": np.asarray(event.actual_positions, np.float64),
                  "velocities": np.zeros(0) if velocities is None
                  else np.asarray(velocities, np.float64),
                  "time_from_start": _duration(event.time_from_start)}
        err = np.asarray(event.error, np.float64)
        error = {"positions": err[0].copy(), "velocities": err[1].copy(),
                 "accelerations": err[2].copy(),
                 "time_from_start": _duration(event.time_from_start)}
        feedback = {"header": {"stamp": ros_time(stamp_ns), "frame_id": ""},
                    "joint_names": self.joint_names, "desired": desired, "actual": actual,
                    "error": error}
        msg = make(self.store, FEEDBACK_MESSAGE, goal_id={"uuid": np.frombuffer(
            uuid, np.uint8).copy()}, feedback=feedback)
        return self._cdr(msg, FEEDBACK_MESSAGE)

    def status_array(self, goals: Sequence[Any]) -> bytes:
        """``_action/status``: ``GoalStatusArray`` of the book's goals."""
        store = self.store
        items = [make(store, "action_msgs/msg/GoalStatus", status=g.status,
                      goal_info={"goal_id": {"uuid": np.frombuffer(g.uuid, np.uint8).copy()},
                                 "stamp": ros_time(g.stamp_ns)})
                 for g in goals]
        return self._cdr(make(store, STATUS_ARRAY, status_list=items), STATUS_ARRAY)

    # -- replies ------------------------------------------------------------------------------

    def send_goal_response(self, accepted: bool, stamp_ns: int) -> bytes:
        """``SendGoal``'s response, written directly: it is on every goal's acceptance path
        (the same bytes as rosbags' serializer: tests/daemon/ros2/test_node_books.py)."""
        sec, nanosec = divmod(stamp_ns, 10**9)
        return _SEND_GOAL_RESPONSE.pack(CDR_LE, accepted, sec, nanosec)

    def get_result_response(self, status: int, error_code: int, error_string: str) -> bytes:
        name = f"{GET_RESULT}_Response"
        return self._cdr(make(self.store, name, status=status, result={
            "error_code": error_code, "error_string": error_string}), name)

    def cancel_response(self, code: int, goals: Sequence[Any]) -> bytes:
        name = f"{CANCEL_GOAL}_Response"
        infos = [make(self.store, "action_msgs/msg/GoalInfo",
                      goal_id={"uuid": np.frombuffer(g.uuid, np.uint8).copy()},
                      stamp=ros_time(g.stamp_ns)) for g in goals]
        return self._cdr(make(self.store, name, return_code=code, goals_canceling=infos), name)

    def query_state_response(self, queried: QueriedState | None, message: str) -> bytes:
        """``QueryTrajectoryState``'s response; ``queried`` None: failure with ``message``."""
        name = f"{QUERY_STATE}_Response"
        if queried is None:
            msg = make(self.store, name, success=False, message=message)
        else:
            msg = make(self.store, name, success=bool(queried.success), message=message,
                       name=self.joint_names,
                       position=np.asarray(queried.positions, np.float64),
                       velocity=np.asarray(queried.velocities, np.float64),
                       acceleration=np.asarray(queried.accelerations, np.float64))
        return self._cdr(msg, name)

    def response(self, service: str, **fields: Any) -> bytes:
        """The response of ``service`` (``pkg/srv/Name``) with ``fields`` (:func:`make`)."""
        name = f"{service}_Response"
        return self._cdr(make(self.store, name, **fields), name)

    # -- small requests -----------------------------------------------------------------------

    def decode(self, data: bytes, typename: str) -> Any:
        """A small request or sample of ``typename`` (at most :data:`SMALL_REQUEST_BYTES`).

        Raises:
            CdrError: not such a message, or longer.
        """
        return self._decode(data, typename)

    def _decode(self, data: bytes, typename: str) -> Any:
        if len(data) > SMALL_REQUEST_BYTES:
            raise CdrError(f"{typename}: {len(data)} bytes, more than this request can "
                               "hold")
        try:
            return self.store.deserialize_cdr(data, typename)
        except Exception as exc:  # rosbags' own errors, struct's, IndexError...
            raise CdrError(f"{typename}: {type(exc).__name__}: {exc}") from None

    def cancel_request(self, data: bytes) -> tuple[bytes, int]:
        """(UUID, stamp in ns) of a ``CancelGoal`` request.

        Raises:
            CdrError: not such a request.
        """
        msg = self._decode(data, f"{CANCEL_GOAL}_Request")
        info = msg.goal_info
        return bytes(info.goal_id.uuid), int(info.stamp.sec) * 10**9 + int(info.stamp.nanosec)

    def get_result_request(self, data: bytes) -> bytes:
        """The UUID of a ``GetResult`` request.

        Raises:
            CdrError: not such a request.
        """
        return bytes(self._decode(data, f"{GET_RESULT}_Request").goal_id.uuid)

    def query_state_request(self, data: bytes) -> int:
        """The ROS time (ns) a ``QueryTrajectoryState`` request asks about.

        Raises:
            CdrError: not such a request.
        """
        t = self._decode(data, f"{QUERY_STATE}_Request").time
        return int(t.sec) * 10**9 + int(t.nanosec)

    def speed_scaling(self, data: bytes) -> float:
        """The factor of a ``SpeedScalingFactor`` sample.

        Raises:
            CdrError: not such a message.
        """
        return float(self._decode(data, SPEED_SCALING).factor)
