"""Who hears what the control loop publishes, in the API process: one protocol, one fan-out.

Theory of operation
-------------------
Every consumer of the loop's output is an :class:`~.backend_api.Observer` (four methods:
states, goal events, accepted commands, recorded events), added to the backend's
:class:`Observers` in the order they start::

    LoopBackend --> Observers --> Recorders    the flight recorder and daemon.record (below)
                              --> Requests     subscriptions, goal routing (every transport)
                              --> ZenohInterface (daemon.zenoh)
                              --> LiveView     Foxglove (daemon.foxglove)

All calls come in the asyncio thread, in that order; one observer's exception is logged and
the others still hear the message (a view or a recorder never stops a result reaching its
client). :class:`Recorders` is the observer that writes bags: the flight recorder, fed every
cycle through the loop's shared-memory ring (:mod:`.cyclering`, published states only without
it), and ``daemon.record``'s continuous recording. It also triggers the flight recorder on an
abort, a fault, a re-arm and the shutdown, and names the bag in the aborted result's details.

:func:`state_json` makes the loop's :class:`~.messages.State` the JSON snapshot they all get.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ...controller.config import ControllerConfig
from ...controller.goals import GoalFeedback, GoalResult, GoalStatus
from ...controller.joints import JointCommand
from ...controller.messages import JointTrajectory
from ...rec.continuous import ContinuousRecorder
from ...rec.flight import FlightRecorder
from ..channel.cyclering import READ_PERIOD_S, RING_S, CycleRing, remove_stale
from ..channel.messages import State
from ..settings import DaemonSettings
from .backend_api import Observer

__all__ = ["Observers", "Recorders", "state_json"]

log = logging.getLogger("jtc_hw.backend")

FLIGHT_AFTER_S = 1.0
"""The flight recorder's bags go on this long after their trigger (``jtc_hw.rec.flight``)."""


class Observers:
    """The observers of the loop's output, called in the order they were added."""

    def __init__(self) -> None:
        self._observers: list[Observer] = []

    def add(self, observer: Observer) -> None:
        """Also tell ``observer`` from now on (after those added before)."""
        self._observers.append(observer)

    def __bool__(self) -> bool:
        return bool(self._observers)

    # Each tells every observer through its ``Observer`` method ``on_<name>`` (which says what).

    def state(self, snapshot: dict[str, Any]) -> None:
        self._tell("on_state", snapshot)

    def goal_event(self, event: GoalResult | GoalFeedback) -> None:
        self._tell("on_goal_event", event)

    def command(self, traj: JointTrajectory, goal_id: int | None) -> None:
        self._tell("on_command", traj, goal_id)

    def record(self, event: dict[str, Any]) -> None:
        self._tell("on_record", event)

    def _tell(self, method: str, *args: Any) -> None:
        for observer in self._observers:
            try:
                getattr(observer, method)(*args)
            except Exception:
                # An observer (a view, a recorder) must never stop the loop's messages
                # reaching the others.
                log.exception("%s.%s failed; skipped", type(observer).__name__, method)


def _vector(a: Any) -> list[float | None] | None:
    if a is None:
        return None
    return [float(x) if np.isfinite(x) else None for x in np.asarray(a, dtype=float)]


def _command_json(command: JointCommand) -> dict[str, list[float | None] | None]:
    """The configured interfaces of a command (NaN, "nothing", as null)."""
    return {
        name: _vector(getattr(command, name))
        for name in ("positions", "velocities", "accelerations", "effort")
        if getattr(command, name) is not None
    }


def state_json(state: State, joint_names: Sequence[str]) -> dict[str, Any]:
    """The loop's state as the JSON snapshot observers get (the socket's ``state`` event)."""
    desired, error = state.desired, state.error
    return {
        "time_ns": state.time_ns,
        "joint_names": list(joint_names),
        "desired": {
            "positions": _vector(desired[0]),
            "velocities": _vector(desired[1]),
            "accelerations": _vector(desired[2]),
            "effort": _vector(desired[3]),
            "time_from_start": state.reference_time_from_start,
        },
        "actual": {
            "positions": _vector(state.positions),
            "velocities": _vector(state.velocities),
            "accelerations": _vector(state.accelerations),
            "time_from_start": state.feedback_time_from_start,
        },
        "error": {
            "positions": _vector(error[0]),
            "velocities": _vector(error[1]),
            "accelerations": _vector(error[2]),
        },
        "command": _command_json(state.command),
        "output": _command_json(state.output),
        "holding": state.holding,
        "active_goal": state.active_goal,
        "speed_scaling": {"factor": state.speed_scaling_factor,
                          "target": state.speed_scaling_target},
    }


class Recorders:
    """The observer writing bags (module docstring).

    Args:
        daemon: the daemon's settings (``flight_recorder_*``, ``record``).
        config: the controller's configuration (its name, rate, tolerances).
        status: the daemon's status, for the recordings' diagnostics.
    """

    def __init__(self, daemon: DaemonSettings, config: ControllerConfig,
                 status: Callable[[], dict[str, Any]]) -> None:
        self._daemon = daemon
        self._config = config
        self._status = status
        self.flight: FlightRecorder | None = None
        """The flight recorder, made by :meth:`start`."""
        self.recording: ContinuousRecorder | None = None
        """``daemon.record``'s recorder, made by :meth:`start`."""
        self._ring: CycleRing | None = None  # every cycle's row, from the loop
        self._ring_next = 0  # the ring's next row to copy
        self._ring_timer: asyncio.TimerHandle | None = None

    def start(self) -> str | None:
        """Make the recorders and the cycle ring; the ring's name for the loop (None: none).

        Raises:
            OSError: ``daemon.record``'s directory cannot be created.
            RecordingUnavailable: ``daemon.record`` is set and rosbags is not installed.
        """
        d, config = self._daemon, self._config
        joint_names = tuple(config.joints)
        tolerances = {joint: {"path": c.trajectory, "goal": c.goal}
                      for joint, c in config.constraints.joints.items()}
        self.flight = FlightRecorder(d.flight_recorder_dir, d.flight_recorder_s,
                                     d.flight_recorder_keep, config.name, tolerances,
                                     cycle_rate_hz=config.update_rate,
                                     joint_names=joint_names)
        # Every cycle's row, for the flight recorder, and the published states (see
        # .cyclering): created here, the owner, and removed by close_ring once the loop has
        # ended.
        for name in remove_stale():
            log.info("removed %s, the cycle ring of a daemon that was killed", name)
        try:
            self._ring = CycleRing.create(
                len(joint_names), max(64, math.ceil(RING_S * config.update_rate)))
        except OSError as exc:
            log.warning("no shared memory for the control loop's cycles (%s): its states come "
                        "through its pipe, and the flight recorder keeps those", exc)
            self.flight.cycle_rate_hz = None
        if d.record is not None:
            self.recording = ContinuousRecorder(d.record, config.name, self._status, tolerances)
        if self._ring is None:
            return None
        if self.flight.available:
            self._ring_timer = asyncio.get_running_loop().call_later(
                READ_PERIOD_S, self.read_ring)
        return self._ring.name

    @property
    def ring(self) -> CycleRing | None:
        """The cycle ring (None: none, or removed)."""
        return self._ring

    # -- Observer ----------------------------------------------------------------------------

    def on_state(self, snapshot: dict[str, Any]) -> None:
        if self.flight is not None and self._ring is None:
            self.flight.on_state(snapshot)  # (with the ring, it has every cycle)
        if self.recording is not None:
            self.recording.on_state(snapshot)

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None:
        """Nothing: results reach the recorders as records (:meth:`on_record`)."""

    def on_command(self, traj: JointTrajectory, goal_id: int | None) -> None:
        """For ``/<controller>/joint_trajectory`` (converted to a message in the recorders'
        worker threads: a large goal costs the event loop nothing here)."""
        now = time.monotonic_ns()
        if self.flight is not None:
            self.flight.on_command(traj, now)
        if self.recording is not None:
            self.recording.on_command(traj, now)

    def on_record(self, event: dict[str, Any]) -> None:
        if self.flight is not None:
            self.flight.on_event(event)
        if self.recording is not None:
            self.recording.on_event(event)

    # -- the flight recorder -----------------------------------------------------------------

    def trigger(self, reason: str, now_ns: int | None = None, *, due: bool = True
                ) -> str | None:
        """Trigger the flight recorder (if made); its path (None: none). With ``due``, a timer
        writes the bag a second later even if no state comes (a faulted loop publishes none);
        without, :meth:`close` writes it (the shutdown)."""
        if self.flight is None:
            return None
        path = self.flight.trigger(reason, now_ns)
        if path is not None and due:
            asyncio.get_running_loop().call_later(FLIGHT_AFTER_S + 0.05, self._flight_due)
        return path

    def annotate(self, result: GoalResult) -> GoalResult:
        """An abort triggers the flight recorder and its details name the bag
        (``flight recorder: PATH``)."""
        if result.status is not GoalStatus.ABORTED:
            return result
        path = self.trigger("aborted", result.time_ns)
        if path is None:
            return result
        note = f"flight recorder: {path}"
        return dataclasses.replace(
            result, details=f"{result.details}; {note}" if result.details else note)

    def _flight_due(self) -> None:
        """A trigger's second has passed: take the cycles written since the last read of the
        ring (up to 100 ms of them), then let the flight recorder write what is due."""
        self.read_ring(again=False)
        if self.flight is not None:
            self.flight.poll(time.monotonic_ns())

    def read_ring(self, again: bool = True) -> None:
        """Copy the cycles the loop wrote since the last time into the flight recorder;
        again in ``READ_PERIOD_S`` unless ``again`` is False."""
        ring = self._ring
        if ring is None or self.flight is None or not self.flight.available:
            return
        rows, self._ring_next, lost = ring.read(self._ring_next)
        if self.flight is not None:
            self.flight.on_cycles(rows, ring.layout, lost)
        if again and self._ring_timer is not None:
            self._ring_timer = asyncio.get_running_loop().call_later(
                READ_PERIOD_S, self.read_ring)

    def close_ring(self) -> None:
        """Stop reading the cycle ring and remove it (the loop process has ended)."""
        if self._ring_timer is not None:
            self._ring_timer.cancel()
            self._ring_timer = None
        if self._ring is not None:
            self._ring.close()
            self._ring = None

    async def close(self) -> None:
        """Write the flight recorder's pending bags and finish the recording (in threads)."""
        aio = asyncio.get_running_loop()
        if self.flight is not None:  # the shutdown's bag, with what came after the trigger
            await aio.run_in_executor(None, self.flight.close)
        if self.recording is not None:
            await aio.run_in_executor(None, self.recording.close)

    def status(self) -> dict[str, Any]:
        """The status sections ``flight_recorder`` and ``recording`` (of those made)."""
        sections: dict[str, Any] = {}
        if self.flight is not None:
            sections["flight_recorder"] = self.flight.status()
        if self.recording is not None:
            sections["recording"] = {"file": str(self.recording.path),
                                     "errors": self.recording.errors,
                                     "stopped": self.recording.stopped}
        return sections
