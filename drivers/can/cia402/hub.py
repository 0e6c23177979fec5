"""The wire the emulated CiA 402 drives share: one :class:`Hub` per python-can bus object.

The drives on one bus object (:class:`~jtc_hw.drivers.can.cia402.emulator.Cia402DriveEmulator`)
share a hub as drives share a cable: one receive thread (or, in push mode, the sending peer's
thread) that dispatches every frame to them (SYNC, NMT and heartbeats to each in node-id order;
an RPDO or SDO to its node), one queue of answers released when the modelled wire
(``pace_bitrate``, :func:`~jtc_hw.drivers.can.bus.wire_time_s`) has carried them, and the
drives' time-driven work (heartbeat consumers, their own heartbeat, a stop in progress) run
when due. A hub knows a drive only as a :class:`HubDrive`: what it calls when a frame or a
deadline concerns that drive.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
import time
from typing import Protocol

import can
import canopen

from ..bus import wire_time_s
from ..emulation import PushSink, WakeEarly, attach_sink, clocks_now
from . import codec as c4

__all__ = ["Hub", "HubDrive"]

# The emulator's logger (its name from before drivers/can/ was split: log filters name it).
_log = logging.getLogger("jtc_hw.drivers.can.cia402_emulator")


class HubDrive(Protocol):
    """A drive on a hub: what the hub reads of it and calls when something concerns it."""

    bus: can.BusABC
    node_id: int
    pace_bitrate: int | None
    node: canopen.LocalNode

    def on_sync(self, now: float) -> None:
        """A SYNC arrived at ``now`` (monotonic)."""

    def on_nmt(self, command: int) -> None:
        """An NMT command for this node (or for all)."""

    def on_heartbeat(self, producer: int, state: int, at: float) -> None:
        """A heartbeat (or boot-up) of node ``producer`` crossed the bus at ``at``."""

    def on_frame(self, cob: int, data: bytes) -> bool:
        """A frame addressed to this node; False: canopen's SDO server takes it."""

    def on_time(self, now: float) -> float | None:
        """Due time-driven work; when the next is (None: none)."""


class Hub:
    """One receive thread per bus object, dispatching to the drives on it."""

    _lock = threading.Lock()
    _hubs: dict[int, Hub] = {}

    def __init__(self, bus: can.BusABC, pace_bitrate: int | None) -> None:
        self.bus = bus
        self.pace_bitrate = pace_bitrate
        self.network = canopen.Network(bus)  # no notifier: the hub thread feeds it
        self.drives: dict[int, HubDrive] = {}
        self.free_at = 0.0  # monotonic time the modelled wire becomes idle
        self._wire_cache: dict[tuple[int, bool, bytes], float] = {}
        self.bus_off = False
        self._pending: list[tuple[float, int, can.Message]] = []
        self._answer_at: float | None = None  # while answering a SYNC: when it ended
        self._early = WakeEarly()
        self._seq = itertools.count()
        self._send_lock = threading.Lock()
        self._wake: float | None = None  # when a drive has time-driven work (see _tick)
        self._wake_lock = threading.Lock()  # drives may ask from another thread (injection)
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"cia402-emulator-{bus.channel_info}", daemon=True
        )
        self.error: BaseException | None = None

    @classmethod
    def join(cls, drive: HubDrive, push: bool = False) -> Hub:
        with cls._lock:
            hub = cls._hubs.get(id(drive.bus))
            if hub is None:
                hub = cls(drive.bus, drive.pace_bitrate)
                if push:
                    try:
                        attach_sink(drive.bus, PushSink(hub._on_pushed))
                    except (AttributeError, ValueError) as exc:
                        raise ValueError(
                            f"push mode needs a python-can virtual bus ({exc})") from exc
                cls._hubs[id(drive.bus)] = hub
                start = not push
            else:
                start = False
            if drive.node_id in hub.drives:
                raise ValueError(f"node id {drive.node_id} already emulated on this bus")
            hub.drives[drive.node_id] = drive
            hub.network[drive.node_id] = drive.node
            # The emulator does NMT itself (canopen's slave sends no boot-up on a reset).
            hub.network.unsubscribe(0, drive.node.nmt.on_command)
            if start:
                hub._thread.start()
            return hub

    def leave(self, drive: HubDrive) -> None:
        with self._lock:
            self.drives.pop(drive.node_id, None)
            if drive.node_id in self.network:
                # LocalNode.remove_network unsubscribes its NMT handler, taken off in join().
                self.network.subscribe(0, drive.node.nmt.on_command)
                del self.network[drive.node_id]
            last = not self.drives
            if last:
                self._hubs.pop(id(self.bus), None)
        if last:
            self._stop.set()
            if self._thread.is_alive() and self._thread is not threading.current_thread():
                self._thread.join(timeout=5.0)

    # -- transmission ---------------------------------------------------------------------------

    def _occupy(self, msg: can.Message, now: float) -> float:
        """Put ``msg`` on the modelled wire; the time its transmission ends."""
        if self.pace_bitrate is None:
            return now
        key = (int(msg.arbitration_id), bool(msg.is_extended_id), bytes(msg.data))
        duration = self._wire_cache.get(key)
        if duration is None:
            # The exact stuffed length costs ~30 us of Python per frame; frames repeat (a
            # drive at rest sends the same TPDOs every cycle), so remember them.
            if len(self._wire_cache) > 4096:
                self._wire_cache.clear()
            duration = self._wire_cache[key] = wire_time_s((msg,), self.pace_bitrate)
        self.free_at = max(self.free_at, now) + duration
        return self.free_at

    def transmit(self, msg: can.Message, delay_s: float = 0.0) -> None:
        """Queue ``msg`` for sending when the modelled wire has carried it (and ``delay_s``).

        An answer to a SYNC is ready when the SYNC's last bit has crossed the wire (a drive
        reacts in microseconds), not when this thread got round to the SYNC: it queues from
        the SYNC's end.
        """
        start = time.monotonic() if self._answer_at is None else self._answer_at
        due = self._occupy(msg, start + delay_s)
        heapq.heappush(self._pending, (due, next(self._seq), msg))

    def _send_due(self) -> float | None:
        """Send what is due; the time until the next pending frame (None: nothing pending)."""
        while self._pending:
            due = self._pending[0][0]
            now = time.monotonic()
            if due > now:
                return due - now
            _, _, msg = heapq.heappop(self._pending)
            if self.bus_off and not msg.is_error_frame:
                continue
            try:
                with self.network.send_lock:
                    self.bus.send(msg)
            except can.CanError as exc:
                _log.warning("emulator: sending %s failed: %s", msg, exc)
        return None

    # -- time-driven work -----------------------------------------------------------------------

    def wake_at(self, when: float) -> None:
        """A drive has time-driven work at ``when`` (monotonic): a heartbeat consumer's
        deadline, its own heartbeat, a stop it performs by itself."""
        with self._wake_lock:
            wake = self._wake
            if wake is None or when < wake:
                self._wake = when

    def _tick(self, now: float) -> None:
        """Run the drives' time-driven work that is due, and note when the next is."""
        with self._wake_lock:
            self._wake = None  # what the drives ask for from here on is merged in
        for node_id in sorted(self.drives):
            when = self.drives[node_id].on_time(now)
            if when is not None:
                self.wake_at(when)

    # -- reception ------------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                wait = self._send_due()
                wake = self._wake
                if wake is not None and time.monotonic() >= wake:
                    # Frames that arrived meanwhile first (a heartbeat among them resets a
                    # consumer), so that a stall of this thread is not taken for a silent
                    # master: their arrival time is the bus's receive stamp.
                    while (msg := self.bus.recv(timeout=0.0)) is not None:
                        self._on_message(msg)
                    self._tick(time.monotonic())
                    continue
                early = self._early.early_s if self.pace_bitrate is not None else 0.0
                if wait is not None and wait <= early:
                    # The frame is ready; hold it until its modelled time (see WakeEarly).
                    self._early.spin_until(time.monotonic() + wait)
                    continue
                timeout = 0.05 if wait is None else min(wait - early, 0.05)
                if wake is not None:
                    timeout = max(0.0, min(timeout, wake - time.monotonic()))
                asked = time.monotonic()
                msg = self.bus.recv(timeout=timeout)
                if msg is None:
                    if wait is not None:
                        self._early.observe(asked + timeout, time.monotonic())
                    continue
                self._on_message(msg)
        except Exception as exc:  # noqa: BLE001 - reported by the drives' `error`
            if not self._stop.is_set():
                _log.exception("CiA 402 emulator hub stopped")
                self.error = exc

    def _on_message(self, msg: can.Message) -> None:
        """A frame on the bus: occupies the modelled wire, then reaches the drives."""
        if msg.is_error_frame:
            return
        now, wall = clocks_now()
        # The frame took the wire when it was sent (its receive stamp on a virtual bus, wall
        # clock), not when this thread got round to it.
        sent = msg.timestamp - (wall - now) if msg.timestamp else now
        end = self._occupy(msg, min(now, max(sent, now - 0.01)))
        if msg.arbitration_id == c4.SYNC_COB_ID and not msg.is_extended_id:
            self._answer_at = end if self.pace_bitrate is not None else None
        try:
            self._dispatch(msg)
        finally:
            self._answer_at = None

    def _on_pushed(self, msg: can.Message) -> None:
        """Push mode: a frame another peer sent, handled in its thread."""
        try:
            self._on_message(msg)
        except Exception as exc:  # noqa: BLE001 - reported by the drives' `error`
            _log.exception("CiA 402 emulator hub failed")
            self.error = exc

    def next_due(self) -> float | None:
        """Push mode: the monotonic time the next frame or time-driven work is due
        (``None``: nothing pending)."""
        due = self._pending[0][0] if self._pending else None
        wake = self._wake
        if wake is not None and (due is None or wake < due):
            return wake
        return due

    def release_due(self, now: float) -> None:
        """Push mode: run the due time-driven work, then send every frame that is due
        (``now`` is read again per frame)."""
        wake = self._wake
        if wake is not None and now >= wake:
            self._tick(now)
        self._send_due()

    def _dispatch(self, msg: can.Message) -> None:
        if self.bus_off:
            return
        cob = int(msg.arbitration_id)
        data = bytes(msg.data)
        now, wall = clocks_now()
        # When the frame crossed the bus (its receive stamp, wall clock), not when this
        # thread got round to it: a drive's servo loop runs on while this thread waits.
        at = now - max(0.0, wall - msg.timestamp) if msg.timestamp else now
        if cob == c4.SYNC_COB_ID:
            for node_id in sorted(self.drives):
                self.drives[node_id].on_sync(at)
                # Drives work in parallel: what the wire could already carry goes out while
                # the next drive's physics is computed.
                self._send_due()
        elif cob == 0:
            try:
                command, target = c4.decode_nmt(data)
            except Exception:  # noqa: BLE001 - a malformed NMT frame is ignored, as nodes do
                return
            for node_id in sorted(self.drives):
                if target in (0, node_id):
                    self.drives[node_id].on_nmt(command)
        elif (beat := c4.decode_heartbeat(cob, data)) is not None:
            for node_id in sorted(self.drives):
                self.drives[node_id].on_heartbeat(beat[0], beat[1], at)
        else:
            drive = self.drives.get(cob & 0x7F)
            if drive is not None and drive.on_frame(cob, data):
                return
            self.network.notify(cob, bytearray(data), msg.timestamp)
