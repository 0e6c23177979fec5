"""Write what the daemon publishes as a rosbag2 directory with MCAP storage (``rosbags``).

Theory of operation
-------------------
A ``BagRecorder`` is fed the socket's messages as plain dicts (``state`` events, one per
``state_publish_rate`` tick of the loop; ``get_status`` replies; goal events; accepted commands)
or the rows of the loop's cycle ring, and writes each as the ROS 2 message a ROS user expects on
the topic of the same name (:func:`topics`; what each holds: docs/recording.md, "Topics and
message types"): ``/joint_states``, ``controller_state`` (control_msgs' current definition),
``goal_events`` (one JSON object each), the action's goal status, ``/rosout`` (each result's,
fault's and re-arm's text, at the level a ROS console shows it) and ``/diagnostics``.

Timestamps: the daemon clock (CLOCK_MONOTONIC of the loop's deadlines, ``time_ns``) is mapped to
wall time once, with the offset measured when the recording starts (``clock_offset_ns``), so
consecutive messages keep the loop's exact spacing. The offset is stored in the bag's
``metadata.yaml`` (``custom_data: jtc_hw.clock_offset_ns``) so a reader can recover daemon times.

A full disk: the bag keeps what was written before it, readable. Three things make that
possible. The ``.mcap`` file is written unbuffered, so every write reaches the file system (or
fails) when rosbags makes it, and the offset after the last complete chunk is known (``_safe``).
Chunks are closed every :data:`CHUNK_BYTES` (rosbags' own is 1 MiB), which bounds what a retry
needs. And a reserve file of :data:`RESERVE_BYTES` (growing with the chunk index that the summary
will hold) is allocated next to the ``.mcap`` when the bag is created. When a write fails
(``OSError``: ENOSPC, EIO, EFBIG...), the recorder deletes the reserve, cuts the ``.mcap`` back to
the last complete chunk, writes the failed chunk again, then the MCAP summary and
``metadata.yaml``, and raises :class:`RecordingFailed`: one line saying what failed, where, and
how many messages the bag holds. Every later call is a no-op (the bag is closed). Without
room even then, the chunk is dropped or the bag is left without its summary, and the message
says so.

``rosbags`` is imported lazily: without it ``BagRecorder`` raises ``RecordingUnavailable`` with
the install hint.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..errors import ConfigurationError, JtcHwError


class CycleRowLayout(Protocol):
    """Where each value sits in a row of the loop's cycle ring: what a recording reads of
    ``jtc_hw.daemon.channel.cyclering.CycleLayout``, which satisfies it. Said here rather than
    imported: the recordings are a layer below the daemon that uses them
    (``pyproject.toml``'s contracts)."""

    @property
    def width(self) -> int: ...

    def column(self, name: str) -> int: ...

    def block(self, name: str) -> slice: ...

    def times(self, rows: Any) -> Any: ...


RECORD_HINT = "recording needs the rosbags library: pip install 'jtc_hw[record]'"

CONTROLLER_STATE_TYPE = "control_msgs/msg/JointTrajectoryControllerState"

# control_msgs' current definition (ros-controls/control_msgs, after the deprecated
# desired/actual fields were removed and speed_scaling_factor was added). rosbags' stores do not
# ship control_msgs, so it is registered from this text.
CONTROLLER_STATE_MSG = """\
std_msgs/Header header
string[] joint_names
trajectory_msgs/JointTrajectoryPoint reference
trajectory_msgs/JointTrajectoryPoint feedback
trajectory_msgs/JointTrajectoryPoint error
trajectory_msgs/JointTrajectoryPoint output
string[] multi_dof_joint_names
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_reference
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_feedback
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_error
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_output
float64 speed_scaling_factor
"""

CLOCK_OFFSET_KEY = "jtc_hw.clock_offset_ns"
TOLERANCES_KEY = "jtc_hw.tolerances"
"""``custom_data`` key: JSON ``{joint: {"path": x, "goal": y}}``, the configured constraints
(``constraints.<joint>.trajectory`` / ``.goal``; 0: not checked) when the recording started."""

DIAGNOSTIC_OK, DIAGNOSTIC_WARN, DIAGNOSTIC_ERROR = 0, 1, 2

LOG_NAME = "jtc_hw"
"""``rcl_interfaces/msg/Log.name`` of the recorded results, faults and re-arms."""

GOAL_STATUS_CODES = {"succeeded": 4, "canceled": 5, "aborted": 6}
"""``action_msgs/msg/GoalStatus`` codes of the socket's result statuses (STATUS_SUCCEEDED,
STATUS_CANCELED, STATUS_ABORTED); another status is STATUS_UNKNOWN (0)."""

LOG_LEVELS = {"succeeded": 20, "canceled": 30, "aborted": 40, "fault": 40, "rearm": 20}
"""``rcl_interfaces/msg/Log`` levels (INFO 20, WARN 30, ERROR 40) by result status or event."""


CHUNK_BYTES = 64 * 1024
"""An MCAP chunk is written once it holds this much: the most rows a full disk can cost (when
even the reserve cannot take the chunk again), and part of what the reserve holds."""

RESERVE_BYTES = 256 * 1024
"""Space set aside when a bag is created, freed to finish it when the disk fills: a chunk
written again, the schemas, the MCAP summary and ``metadata.yaml`` (a few tens of kB)."""

RESERVE_PER_CHUNK = 256
"""Bytes the reserve grows by per chunk written (its entry in the summary's chunk index)."""

RESERVE_NAME = ".jtc_hw-reserve"
"""The reserve's file name, in the bag directory while it is written."""


class RecordingUnavailable(ConfigurationError):
    """The optional recording library is not installed (the CLI exits 2 with the hint)."""


class RecordingFailed(JtcHwError):
    """Writing a bag failed (a full disk...); it was closed with what was written before, and
    the message says so in one line. ``jtc-hw record`` exits 4; the daemon stops recording."""


class _UnbufferedFile:
    """The ``.mcap`` file without a write buffer: a write reaches the file system or raises
    before the next begins (a short write is completed), so the file's length is always known.
    Stands in for the buffered file rosbags opens (``write``, ``tell``, ``close``)."""

    def __init__(self, raw: Any) -> None:
        self._raw = raw

    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        done = 0
        while done < len(view):
            done += self._raw.write(view[done:])
        return done

    def tell(self) -> int:
        return int(self._raw.tell())

    def truncate(self, size: int) -> None:
        self._raw.truncate(size)
        self._raw.seek(size)

    def close(self) -> None:
        self._raw.close()


def topics(controller: str) -> dict[str, str]:
    """The recording's topics and their ROS 2 message types, for a controller name."""
    return {
        "/joint_states": "sensor_msgs/msg/JointState",
        f"/{controller}/controller_state": CONTROLLER_STATE_TYPE,
        f"/{controller}/goal_events": "std_msgs/msg/String",
        f"/{controller}/follow_joint_trajectory/_action/status": "action_msgs/msg/GoalStatusArray",
        "/rosout": "rcl_interfaces/msg/Log",
        "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    }


def typestore() -> Any:
    """rosbags' ROS 2 Jazzy type store with ``control_msgs/msg/JointTrajectoryControllerState``.

    Raises:
        RecordingUnavailable: rosbags is not installed.
    """
    try:  # rosbags is an optional extra (jtc_hw[record])
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ImportError as exc:
        raise RecordingUnavailable(RECORD_HINT) from exc
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(CONTROLLER_STATE_MSG, CONTROLLER_STATE_TYPE))
    return store


_POINT_FIELDS = ("positions", "velocities", "accelerations", "effort")
"""The value fields of a ``JointTrajectoryPoint``."""


def _floats(values: Sequence[float | None] | None) -> Any:
    """A float64 array for a message field; the socket's ``null`` (no value) becomes NaN."""
    if not values:
        return np.zeros(0, dtype=np.float64)
    return np.array([math.nan if v is None else v for v in values], dtype=np.float64)


def tolerances_from_constraints(constraints: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """``{joint: {"path", "goal"}}`` from the controller's ``constraints`` as ``get_config``
    gives them (upstream names: ``<joint>: {trajectory, goal}``)."""
    return {
        joint: {"path": float(values.get("trajectory", 0.0)),
                "goal": float(values.get("goal", 0.0))}
        for joint, values in constraints.items() if isinstance(values, Mapping)
    }


class BagRecorder:
    """Writes the daemon's messages into one rosbag2/MCAP directory (see the module docstring).

    Args:
        path: the bag directory to create; it must not exist.
        controller: the controller's name, the namespace of its topics.
        clock_offset_ns: wall time minus daemon clock, measured once.
        tolerances: the configured tolerances per joint (``tolerances_from_constraints``),
            stored in the metadata for ``jtc-hw plot``'s band.
    """

    def __init__(self, path: str | Path, controller: str, clock_offset_ns: int,
                 tolerances: Mapping[str, Mapping[str, float]] | None = None) -> None:
        """Create the bag directory and its connections.

        Raises:
            RecordingUnavailable: rosbags is not installed.
            FileExistsError: the directory exists (rosbag2 never writes into an existing one).
        """
        self._store = typestore()
        from rosbags.rosbag2 import StoragePlugin, Writer  # the optional extra; typestore checked

        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists: give a new directory name for the bag")
        self.controller = controller
        self.offset_ns = clock_offset_ns
        self.counts: dict[str, int] = {}
        self._writer = Writer(self.path, version=8, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._closed = False
        self._failure: str | None = None
        self._storage: Any = None  # rosbags' MCAP writer, when its file could be taken over
        self._reserve: int | None = None  # the reserve's descriptor
        self._reserved = 0
        self._safe = 0  # the .mcap's length after the last complete chunk
        self._chunks = 0
        try:
            self._take_over_storage()
            self._reserve = os.open(self.path / RESERVE_NAME,
                                    os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
            self._grow_reserve(RESERVE_BYTES)
        except OSError as exc:
            self._salvage(exc, "creating")
        self._writer.set_custom_data(CLOCK_OFFSET_KEY, str(clock_offset_ns))
        if tolerances:
            self._writer.set_custom_data(TOLERANCES_KEY, json.dumps(
                {joint: dict(values) for joint, values in tolerances.items()}, sort_keys=True))
        self._connections = {
            topic: self._writer.add_connection(topic, msgtype, typestore=self._store)
            for topic, msgtype in topics(controller).items()
        }
        self._last_goal: Any = None
        self._command_connection: Any = None  # created with the first command

    # -- a full disk (see the module docstring) ------------------------------------------------

    def _take_over_storage(self) -> None:
        """Swap rosbags' buffered ``.mcap`` file for an unbuffered one; without the attributes
        this relies on (another rosbags version), the bag is written as rosbags does, and a
        full disk leaves it without its summary."""
        storage: Any = self._writer.storage  # rosbags' McapWriter
        bio = getattr(storage, "bio", None)
        chunk = getattr(storage, "chunk", None)
        if bio is None or chunk is None or not hasattr(storage, "close_chunk"):
            return
        bio.flush()
        storage.bio = _UnbufferedFile(bio.detach())
        self._storage = storage
        self._safe = storage.bio.tell()

    def _grow_reserve(self, size: int) -> None:
        if self._reserve is not None and size > self._reserved:
            os.posix_fallocate(self._reserve, 0, size)
            self._reserved = size

    def _release_reserve(self) -> None:
        if self._reserve is not None:
            os.close(self._reserve)
            self._reserve = None
            (self.path / RESERVE_NAME).unlink(missing_ok=True)

    def _close_chunk(self) -> None:
        """Write the pending chunk (if any); ``_safe`` is the file's length before it."""
        storage = self._storage
        if storage is None or not storage.chunk.bio.tell():
            return
        self._safe = storage.bio.tell()
        storage.close_chunk()
        self._safe = storage.bio.tell()
        self._chunks += 1
        self._grow_reserve(RESERVE_BYTES + RESERVE_PER_CHUNK * self._chunks)

    def _guard(self, what: str, action: Callable[[], None]) -> None:
        """Run ``action``; an ``OSError`` closes the bag with what it holds and raises
        :class:`RecordingFailed`."""
        if self._failure is not None:
            return
        try:
            action()
        except OSError as exc:
            self._salvage(exc, what)

    def _salvage(self, exc: OSError, what: str) -> None:
        """Finish the bag after ``exc`` in the room the reserve leaves (see the module docstring).

        Raises:
            RecordingFailed: always; one line: what failed, where, what the bag holds.
        """
        self._closed = True
        reason = exc.strerror or str(exc)
        self._release_reserve()
        storage, kept, lost = self._storage, "", ""
        try:
            if storage is not None:
                storage.bio.truncate(self._safe)  # the failed write's partial bytes
                try:
                    self._close_chunk()
                except OSError:
                    storage.bio.truncate(self._safe)
                    storage.chunk = type(storage.chunk)(2**63 - 1, 0, type(storage.chunk.bio)(),
                                                       type(storage.chunk.msgs)(list))
                    lost = f"; the last {CHUNK_BYTES // 1024} kB of rows are lost"
            self._writer.close()
            kept = "it is closed and readable"
        except Exception as again:  # noqa: BLE001 - no room even now: leave what is on disk
            with contextlib.suppress(Exception):  # the file is closed either way
                self._writer.abort()
            kept = (f"it could not be finished ({getattr(again, 'strerror', None) or again}): "
                    "the .mcap has no summary or metadata.yaml")
        count = sum(self.counts.values())
        self._failure = (f"writing the bag {self.path} failed while {what}: {reason}; {kept}, "
                         f"with {count} messages{lost}")
        raise RecordingFailed(self._failure) from None

    @property
    def failure(self) -> str | None:
        """Why the bag was closed early (:class:`RecordingFailed`'s message), or None."""
        return self._failure

    def _time(self, kind: str, t_ns: int) -> Any:
        """A ``builtin_interfaces/msg/<kind>`` (``Time`` or ``Duration``) of ``t_ns``."""
        return self._store.types[f"builtin_interfaces/msg/{kind}"](
            sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)

    def _stamp(self, time_ns: int) -> Any:
        return self._time("Time", time_ns + self.offset_ns)

    def _header(self, time_ns: int) -> Any:
        Header = self._store.types["std_msgs/msg/Header"]
        return Header(stamp=self._stamp(time_ns), frame_id="")

    def _write(self, topic: str, time_ns: int, message: Any) -> None:
        """Serialise and write one message.

        Raises:
            RecordingFailed: the file system refused it (see :meth:`_salvage`).
        """
        if self._closed:
            return
        connection = self._connections[topic]
        data = self._store.serialize_cdr(message, connection.msgtype)

        def write() -> None:
            self._writer.write(connection, time_ns + self.offset_ns, data)
            self.counts[topic] = self.counts.get(topic, 0) + 1
            if self._storage is not None and self._storage.chunk.bio.tell() >= CHUNK_BYTES:
                self._close_chunk()

        self._guard(f"writing {topic}", write)

    def _trajectory_point(self, values: Sequence[Any], time_from_start: Any) -> Any:
        """A ``JointTrajectoryPoint`` of the arrays of :data:`_POINT_FIELDS`, in that order."""
        return self._store.types["trajectory_msgs/msg/JointTrajectoryPoint"](
            **dict(zip(_POINT_FIELDS, values, strict=True)), time_from_start=time_from_start)

    def _point(self, values: Mapping[str, Any] | None) -> Any:
        values = values or {}
        t = values.get("time_from_start") or 0.0
        return self._trajectory_point([_floats(values.get(name)) for name in _POINT_FIELDS],
                                      self._time("Duration", round(t * 1e9)))

    def _multi_dof_point(self) -> Any:
        Point = self._store.types["trajectory_msgs/msg/MultiDOFJointTrajectoryPoint"]
        return Point(transforms=[], velocities=[], accelerations=[],
                     time_from_start=self._time("Duration", 0))

    def _state(self, time_ns: int, names: list[str], reference: Any, feedback: Any,
               error: Any, output: Any, scaling: float) -> None:
        """``/joint_states`` (the feedback) and ``controller_state`` of a state or a cycle."""
        types = self._store.types
        self._write("/joint_states", time_ns, types["sensor_msgs/msg/JointState"](
            header=self._header(time_ns), name=names, position=feedback.positions,
            velocity=feedback.velocities, effort=feedback.effort))
        empty = self._multi_dof_point()
        self._write(f"/{self.controller}/controller_state", time_ns, types[CONTROLLER_STATE_TYPE](
            header=self._header(time_ns), joint_names=names,
            reference=reference, feedback=feedback, error=error, output=output,
            multi_dof_joint_names=[],
            multi_dof_reference=empty, multi_dof_feedback=empty,
            multi_dof_error=empty, multi_dof_output=empty,
            speed_scaling_factor=scaling,
        ))

    def state(self, event: Mapping[str, Any]) -> None:
        """Record one ``state`` event: ``/joint_states``, ``controller_state``, goal changes."""
        time_ns = int(event["time_ns"])
        scaling = (event.get("speed_scaling") or {}).get("factor", 1.0)
        self._state(time_ns, list(event["joint_names"]), self._point(event.get("desired")),
                    self._point(event.get("actual")), self._point(event.get("error")),
                    self._point(event.get("output") or event.get("command")),
                    float(1.0 if scaling is None else scaling))
        self._goal_change(event.get("active_goal"), time_ns)

    def cycle(self, layout: CycleRowLayout, row: Any, names: Sequence[str]) -> None:
        """Record one cycle's row of the loop's cycle ring (``jtc_hw.daemon.channel.cyclering``):
        ``/joint_states``, ``controller_state`` and goal changes, as :meth:`state` does for a
        published state. A per-joint block that is all NaN (an interface not configured, no
        reference while faulted) is recorded as an empty array, as ROS leaves such fields."""
        time_ns = int(row[layout.column("time_ns"):layout.column("time_ns") + 1]
                      .view(np.int64)[0])

        def block(name: str) -> Any:
            values = row[layout.block(name)]
            return values if not np.isnan(values).all() else np.zeros(0, dtype=np.float64)

        empty = np.zeros(0, dtype=np.float64)

        def point(prefix: str, t: float, effort: bool = True) -> Any:
            values = [block(f"{prefix}_{name}") for name in _POINT_FIELDS[:3]]
            return self._trajectory_point(
                [*values, block(f"{prefix}_effort") if effort else empty],
                self._time("Duration", 0 if math.isnan(t) else round(t * 1e9)))

        ref_t = float(row[layout.column("reference_time_from_start")])
        fb_t = float(row[layout.column("feedback_time_from_start")])
        feedback = point("measured", fb_t, effort=False)
        reference = point("reference", ref_t)

        def difference(name: str) -> Any:
            a, b = getattr(reference, name), getattr(feedback, name)
            return a - b if len(a) and len(a) == len(b) else empty

        error = self._trajectory_point([*map(difference, _POINT_FIELDS[:3]), empty],
                                       reference.time_from_start)
        scaling = float(row[layout.column("speed_scaling")])
        self._state(time_ns, list(names), reference, feedback, error, point("output", ref_t),
                    1.0 if math.isnan(scaling) else scaling)
        raw_goal = float(row[layout.column("active_goal")])
        self._goal_change(None if math.isnan(raw_goal) else int(raw_goal), time_ns)

    def _goal_change(self, goal: Any, time_ns: int) -> None:
        """``goal_started`` / ``goal_ended`` events when the active goal changes."""
        if goal != self._last_goal:
            if self._last_goal is not None:
                self.goal_event({"event": "goal_ended", "goal_id": self._last_goal,
                                 "time_ns": time_ns})
            if goal is not None:
                self.goal_event({"event": "goal_started", "goal_id": goal, "time_ns": time_ns})
            self._last_goal = goal

    def command(self, trajectory: Any, time_ns: int) -> None:
        """Record an accepted command (a ``JointTrajectory``: joint_names, points with
        ``time_from_start_ns`` and value tuples, ``start_time_ns``) received at ``time_ns`` on
        ``/<controller>/joint_trajectory``. Its header stamp is the command's start time on the
        wall clock, or 0 for "start now", as in ROS."""
        topic = f"/{self.controller}/joint_trajectory"
        if self._command_connection is None:
            self._command_connection = self._writer.add_connection(
                topic, "trajectory_msgs/msg/JointTrajectory", typestore=self._store)
            self._connections[topic] = self._command_connection
        types = self._store.types
        Header = types["std_msgs/msg/Header"]
        Message = types["trajectory_msgs/msg/JointTrajectory"]
        points = [
            self._trajectory_point([_floats(getattr(point, name)) for name in _POINT_FIELDS],
                                   self._time("Duration", int(point.time_from_start_ns)))
            for point in trajectory.points
        ]
        start = int(trajectory.start_time_ns)
        header = Header(stamp=self._time("Time", start + self.offset_ns if start else 0),
                        frame_id="")
        self._write(topic, time_ns, Message(
            header=header, joint_names=list(trajectory.joint_names), points=points))

    def goal_event(self, event: Mapping[str, Any]) -> None:
        """Record a goal event (``result``, ``fault``, ``rearm``, ``goal_started``...) as JSON
        text on ``goal_events``; a result's status also on the action's status topic, and a
        result's, fault's or re-arm's text on ``/rosout``."""
        time_ns = int(event["time_ns"])
        String = self._store.types["std_msgs/msg/String"]
        self._write(f"/{self.controller}/goal_events", time_ns,
                    String(data=json.dumps(dict(event), sort_keys=True, allow_nan=False)))
        kind = event.get("event")
        if kind == "result":
            status = str(event.get("status", ""))
            self._goal_status(int(event["goal_id"]), status, time_ns)
            text = ": ".join([f"goal {event['goal_id']} {status} ({event.get('error_code', 0)})"]
                             + [str(event[k]) for k in ("error_string", "details")
                                if event.get(k)])
            self._log(LOG_LEVELS.get(status, 30), text, time_ns)
        elif kind in ("fault", "rearm"):
            self._log(LOG_LEVELS[str(kind)], str(event.get("text") or kind), time_ns)

    def _goal_status(self, goal_id: int, status: str, time_ns: int) -> None:
        """A ``GoalStatusArray`` holding the one goal that just finished (a ROS action server
        lists every goal it tracks; a bag reader wants the change). The goal's UUID is its id,
        big-endian in the last 8 bytes."""
        types = self._store.types
        uuid = np.frombuffer(bytes(8) + goal_id.to_bytes(8, "big", signed=False), np.uint8)
        info = types["action_msgs/msg/GoalInfo"](
            goal_id=types["unique_identifier_msgs/msg/UUID"](uuid=uuid.copy()),
            stamp=self._stamp(time_ns))
        entry = types["action_msgs/msg/GoalStatus"](
            goal_info=info, status=GOAL_STATUS_CODES.get(status, 0))
        self._write(f"/{self.controller}/follow_joint_trajectory/_action/status", time_ns,
                    types["action_msgs/msg/GoalStatusArray"](status_list=[entry]))

    def _log(self, level: int, text: str, time_ns: int) -> None:
        Log = self._store.types["rcl_interfaces/msg/Log"]
        self._write("/rosout", time_ns, Log(
            stamp=self._stamp(time_ns), level=level, name=LOG_NAME, msg=text, file="",
            function="", line=0))

    def diagnostics(self, status: Mapping[str, Any], time_ns: int) -> None:
        """Record a ``get_status`` reply as a ``DiagnosticArray`` (loop, controller, hardware)."""
        types = self._store.types
        Status = types["diagnostic_msgs/msg/DiagnosticStatus"]
        Array = types["diagnostic_msgs/msg/DiagnosticArray"]
        entries = []
        loop = status.get("loop") or {}
        entries.append(Status(level=DIAGNOSTIC_OK, name="jtc_hw: loop", message="",
                              hardware_id="", values=self._key_values(loop)))
        controller = status.get("controller") or {}
        fault = controller.get("fault")
        entries.append(Status(
            level=DIAGNOSTIC_ERROR if fault else DIAGNOSTIC_OK, name="jtc_hw: controller",
            message=str(fault or ""), hardware_id="", values=self._key_values(controller)))
        hardware = status.get("hardware") or {}
        components = hardware.items() if isinstance(hardware, Mapping) else enumerate(hardware)
        for name, component in components:
            info = component if isinstance(component, Mapping) else {"value": component}
            error = info.get("fault") or info.get("error")
            entries.append(Status(
                level=DIAGNOSTIC_ERROR if error else DIAGNOSTIC_OK, name=f"jtc_hw: {name}",
                message=str(error or ""), hardware_id=str(name),
                values=self._key_values(info)))
        self._write("/diagnostics", time_ns, Array(header=self._header(time_ns), status=entries))

    def _key_values(self, values: Mapping[str, Any], prefix: str = "") -> list[Any]:
        """Scalars of a nested mapping as ``KeyValue``s with dotted keys (lists as JSON)."""
        KeyValue = self._store.types["diagnostic_msgs/msg/KeyValue"]
        out = []
        for key, value in values.items():
            name = f"{prefix}{key}"
            if isinstance(value, Mapping):
                out.extend(self._key_values(value, f"{name}."))
            else:
                text = value if isinstance(value, str) else json.dumps(value, default=str)
                out.append(KeyValue(key=name, value=text))
        return out

    def close(self) -> None:
        """Finish the bag (writes ``metadata.yaml`` and the MCAP summary); a no-op once closed
        (also after :class:`RecordingFailed`).

        Raises:
            RecordingFailed: the file system refused the last chunk or the summary (the bag is
                closed with the rows before, see :meth:`_salvage`).
        """
        if self._closed:
            return

        def finish() -> None:
            self._close_chunk()
            self._writer.close()  # without room for it, _salvage frees the reserve and retries
            self._closed = True
            self._release_reserve()

        self._guard("closing it", finish)
