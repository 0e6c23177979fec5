"""Live view: the daemon's state served over the Foxglove WebSocket protocol (API process).

Theory of operation
-------------------
``daemon.foxglove: {port: 8765}`` starts a :class:`LiveView` next to the socket server. It
is an observer of what the loop sends to the API process (the backend calls it with every
state snapshot, goal event and accepted command, in the asyncio thread) plus a 1 Hz poll of
the status for ``/diagnostics``; the loop process knows nothing of it. An accepted command's
message (thousands of points) is built in a worker thread, off the goal's acceptance path.

The WebSocket server is the official ``foxglove-sdk`` (Python package ``foxglove``, extra
``jtc_hw[foxglove]``): it runs in the SDK's own native threads, and ``Channel.log`` only
queues a message for each subscribed client (``message_backlog_size`` of them; when a client
is slow the oldest data message is dropped, the protocol's way), so publishing never waits for
a client and never blocks the event loop. Nothing is serialised for a channel nobody
subscribes to (``has_sinks``).

Messages are JSON with a JSON schema per channel, shaped field for field like the ROS 2
message named as the schema (``sensor_msgs/msg/JointState``, ...), so that the same message
paths (``/joint_states.position[0]``) work in Foxglove on the live view and on a recorded bag.
Topics (``<c>`` is the controller's name)::

    /joint_states                sensor_msgs/msg/JointState                   measured
    /<c>/controller_state        control_msgs/msg/JointTrajectoryControllerState
    /<c>/joint_trajectory        trajectory_msgs/msg/JointTrajectory          accepted commands
    /<c>/goal_events             jtc_hw/msg/GoalEvent                         feedback, results
    /diagnostics                 diagnostic_msgs/msg/DiagnosticArray          loop, controller,
                                                                              hardware (1 Hz)

Times: the loop's clock is CLOCK_MONOTONIC (its deadline grid); it is mapped to wall time
once, when the live view starts, so stamps are consistent with each other and readable as
dates in Foxglove.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Final

import numpy as np

from ...controller.goals import GoalFeedback, GoalResult
from ...controller.messages import JointTrajectory, PointColumns
from ...errors import ConfigurationError

if TYPE_CHECKING:
    from ..settings import FoxgloveSettings

log = logging.getLogger("jtc_hw.liveview")

__all__ = [
    "BACKLOG_MESSAGES",
    "DIAGNOSTICS_PERIOD_S",
    "LiveView",
    "topics",
]

BACKLOG_MESSAGES: Final = 256
"""Messages queued per client; beyond that the oldest data message is dropped (a slow
client loses samples, never the daemon's time)."""
DIAGNOSTICS_PERIOD_S: Final = 1.0
"""Period of ``/diagnostics``."""

# DiagnosticStatus levels (diagnostic_msgs/msg/DiagnosticStatus).
OK: Final = 0
WARN: Final = 1
ERROR: Final = 2

INSTALL_HINT: Final = "pip install 'jtc_hw[foxglove]'"


def topics(controller: str) -> dict[str, str]:
    """The live view's topic per role (the names a recorded bag uses too)."""
    return {
        "joint_states": "/joint_states",
        "controller_state": f"/{controller}/controller_state",
        "joint_trajectory": f"/{controller}/joint_trajectory",
        "goal_events": f"/{controller}/goal_events",
        "diagnostics": "/diagnostics",
    }


# -- JSON schemas -----------------------------------------------------------------------------

_NUMBERS: Final = {"type": "array", "items": {"type": ["number", "null"]}}
_STRINGS: Final = {"type": "array", "items": {"type": "string"}}
_TIME: Final = {
    "type": "object",
    "properties": {"sec": {"type": "integer"}, "nanosec": {"type": "integer"}},
}
_HEADER: Final = {
    "type": "object",
    "properties": {"stamp": _TIME, "frame_id": {"type": "string"}},
}
_POINT: Final = {
    "type": "object",
    "properties": {
        "positions": _NUMBERS,
        "velocities": _NUMBERS,
        "accelerations": _NUMBERS,
        "effort": _NUMBERS,
        "time_from_start": _TIME,
    },
}


def _schema(title: str, properties: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    return title, {"title": title, "type": "object", "properties": properties}


SCHEMAS: Final[Mapping[str, tuple[str, dict[str, Any]]]] = {
    "joint_states": _schema("sensor_msgs/msg/JointState", {
        "header": _HEADER, "name": _STRINGS, "position": _NUMBERS, "velocity": _NUMBERS,
        "effort": _NUMBERS,
    }),
    "controller_state": _schema("control_msgs/msg/JointTrajectoryControllerState", {
        "header": _HEADER, "joint_names": _STRINGS, "reference": _POINT,
        "feedback": _POINT, "error": _POINT, "output": _POINT,
        "speed_scaling_factor": {"type": "number"},
    }),
    "joint_trajectory": _schema("trajectory_msgs/msg/JointTrajectory", {
        "header": _HEADER, "joint_names": _STRINGS,
        "points": {"type": "array", "items": _POINT},
    }),
    "goal_events": _schema("jtc_hw/msg/GoalEvent", {
        "header": _HEADER,
        "goal_id": {"type": "integer"},
        "event": {"enum": ["feedback", "result"]},
        "status": {"type": "string"},
        "error_code": {"type": "integer"},
        "error_string": {"type": "string"},
        "details": {"type": "string"},
        "joint_names": _STRINGS,
        "desired": _POINT,
        "actual": _POINT,
        "error": _POINT,
    }),
    "diagnostics": _schema("diagnostic_msgs/msg/DiagnosticArray", {
        "header": _HEADER,
        "status": {"type": "array", "items": {
            "type": "object",
            "properties": {
                "level": {"type": "integer"},
                "name": {"type": "string"},
                "message": {"type": "string"},
                "hardware_id": {"type": "string"},
                "values": {"type": "array", "items": {
                    "type": "object",
                    "properties": {"key": {"type": "string"}, "value": {"type": "string"}},
                }},
            },
        }},
    }),
}
"""Per role: the schema name (the ROS 2 type the JSON mirrors) and its JSON schema."""


# -- message builders (pure) ------------------------------------------------------------------


def ros_time(ns: int) -> dict[str, int]:
    """``builtin_interfaces/Time`` (or ``Duration``) of integer nanoseconds (floor division,
    so ``nanosec`` is always in ``[0, 1e9)`` as ROS requires, negative times included)."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def _header(wall_ns: int) -> dict[str, Any]:
    return {"stamp": ros_time(wall_ns), "frame_id": ""}


def _list(values: Any) -> list[Any]:
    return [] if values is None else list(values)


def _floats(values: Any) -> list[float | None]:
    """JSON numbers of an array; a non-finite value (NaN: "none") as null."""
    if values is None:
        return []
    return [float(x) if math.isfinite(x) else None for x in np.asarray(values, dtype=float)]


_POINT_FIELDS: Final = ("positions", "velocities", "accelerations", "effort")


def _point(part: Mapping[str, Any] | None, tfs_s: float | None = None) -> dict[str, Any]:
    part = part or {}
    return {**{name: _list(part.get(name)) for name in _POINT_FIELDS},
            "time_from_start": ros_time(round((tfs_s or 0.0) * 1e9))}


def _feedback_point(positions: Any, velocities: Any, accelerations: Any, tfs_ns: int
                    ) -> dict[str, Any]:
    return {"positions": _floats(positions), "velocities": _floats(velocities),
            "accelerations": _floats(accelerations), "effort": [],
            "time_from_start": ros_time(tfs_ns)}


def joint_state_message(snapshot: Mapping[str, Any], wall_ns: int) -> dict[str, Any]:
    """``sensor_msgs/msg/JointState`` of a state snapshot (the measured values)."""
    actual = snapshot["actual"]
    return {
        "header": _header(wall_ns),
        "name": list(snapshot["joint_names"]),
        "position": _list(actual.get("positions")),
        "velocity": _list(actual.get("velocities")),
        "effort": _list(actual.get("effort")),
    }


def controller_state_message(snapshot: Mapping[str, Any], wall_ns: int) -> dict[str, Any]:
    """``control_msgs/msg/JointTrajectoryControllerState`` of a state snapshot."""
    desired = snapshot["desired"]
    actual = snapshot["actual"]
    scaling = snapshot.get("speed_scaling") or {}
    return {
        "header": _header(wall_ns),
        "joint_names": list(snapshot["joint_names"]),
        "reference": _point(desired, desired.get("time_from_start")),
        "feedback": _point(actual, actual.get("time_from_start")),
        "error": _point(snapshot["error"]),
        "output": _point(snapshot.get("output") or snapshot.get("command")),
        "speed_scaling_factor": float(scaling.get("factor", 1.0)),
    }


def _trajectory_points(points: Any) -> list[dict[str, Any]]:
    if isinstance(points, PointColumns):
        columns = {name: points.values(name) for name in _POINT_FIELDS}
        out = []
        for i, t in enumerate(np.asarray(points.times_ns)):
            point: dict[str, Any] = {"time_from_start": ros_time(int(t))}
            for name, column in columns.items():
                if column is None or not column[1][i]:
                    point[name] = []
                else:
                    point[name] = _floats(column[0][i])
            out.append(point)
        return out
    return [
        {**{name: _floats(getattr(p, name)) for name in _POINT_FIELDS},
         "time_from_start": ros_time(p.time_from_start_ns)}
        for p in points
    ]


def trajectory_message(
    traj: JointTrajectory, start_wall_ns: int, goal_id: int | None
) -> dict[str, Any]:
    """``trajectory_msgs/msg/JointTrajectory`` of an accepted command; the header stamp is
    its start (0 when it started "now"); ``header.frame_id`` names the goal (``goal 3``) or
    ``topic`` for a topic command, so a plot can tell them apart."""
    return {
        "header": {
            "stamp": ros_time(start_wall_ns),
            "frame_id": "topic" if goal_id is None else f"goal {goal_id}",
        },
        "joint_names": list(traj.joint_names),
        "points": _trajectory_points(traj.points),
    }


def goal_event_message(
    event: GoalResult | GoalFeedback, joint_names: Sequence[str], wall_ns: int
) -> dict[str, Any]:
    """``jtc_hw/msg/GoalEvent`` (docs/foxglove.md): a result or a feedback of one goal."""
    message: dict[str, Any] = {"header": _header(wall_ns), "goal_id": event.goal_id}
    if isinstance(event, GoalResult):
        message.update(
            event="result",
            status=event.status.value,
            error_code=int(event.error_code),
            error_string=event.error_string,
            details=event.details,
        )
        return message
    desired, tfs_ns = event.desired, round(event.time_from_start * 1e9)
    message.update(
        event="feedback",
        status="executing",
        joint_names=list(joint_names),
        desired=_feedback_point(
            desired.positions, desired.velocities, desired.accelerations, tfs_ns),
        actual=_feedback_point(event.actual_positions, event.actual_velocities, None, tfs_ns),
        error=_feedback_point(*event.error[:3], 0),
    )
    return message


def _flatten(value: Any, prefix: str, out: list[dict[str, str]]) -> None:
    if isinstance(value, Mapping):
        for key, item in value.items():
            _flatten(item, f"{prefix}.{key}" if prefix else str(key), out)
    elif isinstance(value, float):
        out.append({"key": prefix, "value": f"{value:.6g}"})
    else:
        out.append({"key": prefix, "value": json.dumps(value) if isinstance(
            value, (list, tuple)) else str(value)})


def diagnostics_message(status: Mapping[str, Any], wall_ns: int) -> dict[str, Any]:
    """``diagnostic_msgs/msg/DiagnosticArray`` of the daemon's status: one entry for the
    loop (WARN while the API process is behind), one for the controller (ERROR with a fault)
    and one per hardware component (ERROR with a fault, WARN with ``warnings``), each with
    the status's values flattened to ``key: value`` (``counters.reads``, ...)."""
    entries: list[dict[str, Any]] = []

    def entry(level: int, name: str, message: str, hardware_id: str,
              source: Mapping[str, Any]) -> None:
        values: list[dict[str, str]] = []
        _flatten(source, "", values)
        entries.append({"level": level, "name": name, "message": message,
                        "hardware_id": hardware_id, "values": values})

    loop = status.get("loop")
    if isinstance(loop, Mapping):
        stalled = bool(loop.get("api_stalled"))
        entry(WARN if stalled else OK, "jtc_hw: loop",
              "API process behind" if stalled else "OK", "", loop)
    controller = status.get("controller")
    if isinstance(controller, Mapping):
        fault = controller.get("fault")
        entry(ERROR if fault else OK, "jtc_hw: controller", str(fault) if fault else (
            "holding" if controller.get("holding") else
            "active" if controller.get("active") else "inactive"), "", controller)
    hardware = status.get("hardware")
    components = hardware.get("components", []) if isinstance(hardware, Mapping) else []
    for component in components:
        if not isinstance(component, Mapping):
            continue
        fault = component.get("last_fault")
        warnings = component.get("warnings")
        message = str(fault) if fault else (
            "; ".join(map(str, warnings)) if isinstance(warnings, (list, tuple))
            else str(warnings) if warnings else str(component.get("state", "OK")))
        entry(ERROR if fault else WARN if warnings else OK,
              f"jtc_hw: hardware {component.get('name', '?')}", message,
              str(component.get("kind", "")), component)
    return {"header": _header(wall_ns), "status": entries}


# -- the server -------------------------------------------------------------------------------


class LiveView:
    """The Foxglove WebSocket server and its channels (one per topic), fed by the backend.

    Args:
        settings: ``daemon.foxglove``.
        controller: the controller's name (the topics' namespace).
        joint_names: the controller's joints.
        state_publish_rate: the rate the loop publishes state at (the default ``rate``).
        status: returns the daemon's status (polled for ``/diagnostics``).
    """

    def __init__(
        self,
        settings: FoxgloveSettings,
        controller: str,
        joint_names: Sequence[str],
        state_publish_rate: float,
        status: Callable[[], Mapping[str, Any]],
    ) -> None:
        self.settings = settings
        self.controller = controller
        self.joint_names = tuple(joint_names)
        self.topics = topics(controller)
        rate = settings.rate or state_publish_rate
        self._every_ns = 0 if rate >= state_publish_rate else round(1e9 / rate)
        self._last_state_ns: int | None = None
        self._status = status
        # The loop's clock (monotonic) to wall time, fixed once so stamps keep their spacing.
        self._wall_offset_ns = time.time_ns() - time.monotonic_ns()
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self._diagnostics: asyncio.Task[None] | None = None
        self._worker: ThreadPoolExecutor | None = None  # builds command messages (on_command)
        self.published = 0
        self.errors = 0

    @property
    def port(self) -> int:
        """The port the server listens on (the one chosen when ``port`` is 0)."""
        return int(self._server.port) if self._server is not None else self.settings.port

    def wall_ns(self, monotonic_ns: int) -> int:
        """A loop time (CLOCK_MONOTONIC ns) as wall time (ns since the epoch)."""
        return monotonic_ns + self._wall_offset_ns

    def start(self) -> None:
        """Create the channels and start the server.

        Raises:
            ConfigurationError: the ``foxglove`` package is missing (the message says what to
                install), or the address cannot be listened on.
        """
        try:
            import foxglove  # the optional extra (jtc_hw[foxglove])
        except ImportError:
            raise ConfigurationError(
                f"the live view needs the foxglove-sdk package: {INSTALL_HINT}, or remove "
                "daemon.foxglove",
                "daemon.foxglove",
            ) from None
        # A context of our own: channels of another LiveView (tests run several) or of the
        # user's code in the same process never mix with ours.
        # Kept: the SDK detaches the channels from sinks when the context is dropped.
        context = self._context = foxglove.Context()
        for role, topic in self.topics.items():
            name, schema = SCHEMAS[role]
            self._channels[role] = foxglove.Channel(
                topic,
                schema=foxglove.Schema(
                    name=name, encoding="jsonschema", data=json.dumps(schema).encode()
                ),
                message_encoding="json",
                context=context,
            )
        try:
            self._server = foxglove.start_server(
                name=f"jtc_hw {self.controller}",
                host=self.settings.host,
                port=self.settings.port,
                context=context,
                message_backlog_size=BACKLOG_MESSAGES,
            )
        except Exception as exc:  # the SDK raises its own error type for a bind failure
            raise ConfigurationError(
                f"cannot serve the live view on {self.settings.host}:{self.settings.port}: "
                f"{exc}; choose another port (0: any free one)",
                "daemon.foxglove.port",
                self.settings.port,
            ) from None
        self._diagnostics = asyncio.get_running_loop().create_task(self._poll_status())
        log.info("live view (Foxglove WebSocket) on ws://%s:%d", self.settings.host, self.port)

    async def close(self) -> None:
        """Stop publishing and close the server (idempotent)."""
        if self._diagnostics is not None:
            self._diagnostics.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._diagnostics
            self._diagnostics = None
        worker, self._worker = self._worker, None
        if worker is not None:  # the commands being published go first
            await asyncio.get_running_loop().run_in_executor(None, worker.shutdown)
        server, self._server = self._server, None
        if server is not None:
            # The SDK's stop joins its threads; keep the event loop free meanwhile.
            await asyncio.get_running_loop().run_in_executor(None, server.stop)

    # -- observer (called by the backend in the asyncio thread; never raises) ----------------

    def on_state(self, snapshot: dict[str, Any]) -> None:
        """Publish ``/joint_states`` and ``controller_state`` (at most at ``rate``)."""
        t = int(snapshot["time_ns"])
        if self._every_ns and self._last_state_ns is not None and (
            t - self._last_state_ns < self._every_ns
        ):
            return
        self._last_state_ns = t
        wall = self.wall_ns(t)
        self._publish("joint_states", joint_state_message, snapshot, wall, log_time=wall)
        self._publish("controller_state", controller_state_message, snapshot, wall,
                      log_time=wall)

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None:
        """Publish a goal's feedback or result on ``goal_events``."""
        wall = self.wall_ns(event.time_ns)
        self._publish("goal_events", goal_event_message, event, self.joint_names, wall,
                      log_time=wall)

    def on_command(self, traj: JointTrajectory, goal_id: int | None) -> None:
        """Publish an accepted command on ``joint_trajectory``, built in a worker thread.

        The backend calls this before the goal's ``accepted`` reply is sent: building a
        2,000-point goal's message took 10-40 ms and the SDK's encoding as much again, all of it
        added to the goal's acceptance (measured: loaded scenario's goals accepted in 104-236
        ms median with a viewer, 60-87 ms without; docs/benchmarks.md).
        """
        if not traj.points:
            return  # a stop: no trajectory to show
        channel = self._channels.get("joint_trajectory")
        if channel is None or self._server is None or not channel.has_sinks():
            return  # nobody listens: build nothing
        now = time.monotonic_ns()
        start = self.wall_ns(traj.start_time_ns) if traj.start_time_ns else 0
        if self._worker is None:
            self._worker = ThreadPoolExecutor(max_workers=1,
                                              thread_name_prefix="live-view-commands")
        self._worker.submit(self._publish, "joint_trajectory", trajectory_message, traj, start,
                            goal_id, log_time=self.wall_ns(now))

    def on_record(self, event: dict[str, Any]) -> None:
        """Nothing: results are on ``goal_events`` already."""

    def _publish(self, role: str, build: Callable[..., dict[str, Any]], *args: Any,
                 log_time: int) -> None:
        channel = self._channels.get(role)
        if channel is None or self._server is None or not channel.has_sinks():
            return  # nobody listens: build nothing
        try:
            channel.log(build(*args), log_time=log_time)
            self.published += 1
        except Exception:
            # An observer must never break the backend's dispatch of the loop's messages.
            self.errors += 1
            if self.errors <= 3:
                log.exception("live view: cannot publish on %s; skipped", role)

    async def _poll_status(self) -> None:
        while True:
            await asyncio.sleep(DIAGNOSTICS_PERIOD_S)
            try:
                status = self._status()
            except Exception:
                log.debug("live view: no status", exc_info=True)
                continue
            wall = time.time_ns()
            self._publish("diagnostics", diagnostics_message, status, wall, log_time=wall)
