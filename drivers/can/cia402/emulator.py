"""An emulated CiA 402 servo drive on a python-can bus: a peer speaking real CANopen.

Theory of operation
-------------------
Each :class:`Cia402DriveEmulator` is one node: its object dictionary is the shipped EDS
(``jtc_hw_drive.eds``) served by canopen's :class:`~canopen.LocalNode` SDO server; this module
adds what canopen's local node does not do: NMT (boot-up message, pre-operational /
operational / stopped, reset communication restoring the PDO parameters), the CiA 402 state
machine (:data:`~jtc_hw.drivers.can.cia402.codec.DRIVE_TRANSITIONS`), synchronous PDOs and
the physics of the joint (:class:`~jtc_hw.drivers.motor_model.Motor`).

Emulators given the same ``bus`` object share one receive thread (a *hub*,
:mod:`~jtc_hw.drivers.can.cia402.hub`), as drives share a wire; emulators on different bus
objects (e.g. one virtual bus each, same channel) run their own. On every SYNC (COB-ID
0x080), in node-id order, each operational drive

1. advances the motor to the SYNC's receive stamp (the drive's servo loop ran on while the
   hub's thread waited; at most 2 s since the previous step), with
   the set-points in force (CSP: ``Motor.step_position`` toward the target position; CSV:
   ``Motor.step_velocity``; otherwise it coasts);
2. applies the RPDOs received since the previous SYNC (synchronous RPDOs take effect at the
   SYNC): the controlword drives the state machine, the targets become the new set-points;
3. answers with its synchronous TPDOs, built from the mapping currently in its object
   dictionary (so a host that did not configure the mapping gets what it asked for).

With ``pace_bitrate`` the hub models the wire: every frame seen or sent occupies the bus for
its stuffed bit time (:func:`~jtc_hw.drivers.can.bus.wire_time_s`), and answers are released
no earlier than the bus would have carried them. Fault injection: :meth:`inject_fault`
(latched drive fault, e.g. 0x4310 over-temperature, cleared by a fault reset),
:meth:`set_silent`, :meth:`drop_tpdos`, :meth:`set_tpdo_delay`, :meth:`refuse_enable`,
:meth:`refuse_mode`, :meth:`lose_enable` (an enable input that opens once enabled),
:meth:`inject_bus_off` (an error frame, then silence).

Losing the master (CiA 301 heartbeat, CiA 402 abort connection): each used 0x1016 entry
watches one producer from its first heartbeat after the entry was written (a boot-up of the
producer restarts that); with no heartbeat for the consumer time the drive sends EMCY 0x8130
(error register 0x11, the lost node id in byte 3), monitoring stops until the next heartbeat,
and 0x6007 applies: quick stop (from Operation Enabled: the 0x605A ramp, 0x6085 or 0x6084 or
the torque limit, then Switch On Disabled or, 0x605A 5..8, holding in Quick Stop Active),
fault (Fault Reaction Active with the 0x605E ramp, then Fault), Disable Voltage (coasting,
Switch On Disabled) or nothing. 0x1017 makes the drive produce its own heartbeat. A stop the
drive performs by itself runs without SYNCs: the hub also does time-driven work (consumer
deadlines, own heartbeat, a stop in progress stepped every millisecond), in its thread or, in
push mode, through ``next_due`` / ``release_due``. Each heartbeat event is recorded
(:class:`WatchdogTrip`: last heartbeat, detection and stop times on ``time.monotonic()``,
reaction, states), see :attr:`~Cia402DriveEmulator.watchdog_trips` and
:meth:`~Cia402DriveEmulator.wait_watchdog_stop`. Not modelled: 0x1029 (the drive stays in its
NMT state after a heartbeat event), life guarding, abort connection on entering NMT Stopped
(a bus-off silences the heartbeat, so the consumer reacts after its time).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError

from ...motor_model import Motor, MotorParams
from ..bus import CAN_ERR_BUSOFF
from . import codec as c4
from .hub import Hub

__all__ = ["DEFAULT_EDS", "Cia402DriveEmulator", "NmtState", "WatchdogTrip"]

# A logger name is public (log filters name it): the one from before drivers/can/ was split.
_log = logging.getLogger("jtc_hw.drivers.can.cia402_emulator")

DEFAULT_EDS: Path = c4.DEFAULT_EDS
"""The EDS of the emulated drive (shipped with the package)."""

_COMM_RANGE = range(0x1000, 0x2000)
_RPDO_COMM, _RPDO_MAP, _TPDO_COMM, _TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
_PDO_PARAM_RANGE = range(0x1400, 0x1C00)
_SUPPORTED_MODES = (int(c4.Mode.CYCLIC_SYNC_POSITION), int(c4.Mode.CYCLIC_SYNC_VELOCITY))
_ABORT_VALUE_RANGE = 0x06090030
_ABORT_STATE = 0x08000022  # data cannot be transferred because of the present device state
_ABORT_INCOMPATIBLE = 0x06040043  # general parameter incompatibility (CiA 301 for 0x1016)
_STOPPED_RAD_S = 1e-3  # |velocity| below this: the motor is at rest (a stop is complete)
_AUTONOMOUS_STEP_S = 0.001  # physics step while the drive stops by itself (no SYNC needed)
_MAX_GAP_S = 2.0  # longest interval the physics catches up on when the master fell silent
_POWERED = (c4.State.READY_TO_SWITCH_ON, c4.State.SWITCHED_ON, c4.State.OPERATION_ENABLED,
            c4.State.QUICK_STOP_ACTIVE)
_REACTION_CODES = {
    c4.ABORT_CONNECTION_OPTION: range(0, 4),
    c4.QUICK_STOP_OPTION: range(0, 9),
    c4.FAULT_REACTION_OPTION: range(0, 5),
}


_Layouts = tuple[dict[int, c4.PdoLayout], list[tuple[int, c4.PdoLayout, int]]]
"""(RPDO cob id -> layout, [(TPDO cob id, layout, transmission type)])."""


NmtState = c4.NmtState
"""NMT states (the values a heartbeat carries); defined in the codec."""


@dataclass(frozen=True)
class WatchdogTrip:
    """One heartbeat event of a drive: its consumer's producer fell silent. Times are
    ``time.monotonic()`` (CLOCK_MONOTONIC: comparable across processes of one machine).

    Attributes:
        producer: node id whose heartbeat was lost (the master's).
        consumer_time_s: the consumer heartbeat time of the entry that expired, s.
        last_heartbeat_at: when the producer's last heartbeat arrived.
        detected_at: when the consumer time ran out (the heartbeat event; EMCY 0x8130 sent).
        reaction: the 0x6007 abort connection option code applied.
        state_before: the drive's state when the event happened.
        velocity_at_detection: motor velocity when the event happened, rad/s.
        stopped_at: when the motor came to rest (|velocity| < 1e-3 rad/s); None while it
            still moves (or if the reaction was "no action").
        state_after: the drive's state when the motor came to rest.
        position_at_stop: motor position at rest, rad.
    """

    producer: int
    consumer_time_s: float
    last_heartbeat_at: float
    detected_at: float
    reaction: c4.AbortConnection
    state_before: c4.State
    velocity_at_detection: float
    stopped_at: float | None = None
    state_after: c4.State | None = None
    position_at_stop: float | None = None


@dataclass
class _Consumer:
    """One 0x1016 entry: the producer it watches and whether monitoring has started."""

    producer: int
    time_s: float
    armed: bool = False
    deadline: float = 0.0
    last_at: float = 0.0


@dataclass
class _Stop:
    """A stop the drive performs by itself (quick stop, fault reaction, power off): how, and
    the state it enters once the motor is at rest (None: stays where it is)."""

    ramp: c4.Ramp
    final: c4.State | None


class Cia402DriveEmulator:
    """One emulated CiA 402 drive (see the module docstring).

    Args:
        bus: the python-can bus it listens and talks on (not closed by :meth:`stop`).
        node_id: CANopen node id, 1..127.
        pace_bitrate: model the wire at this bit rate (bit/s); None: frames are instant.
            Emulators sharing a bus object share the first one's setting.
        counts_per_revolution: position counts per motor revolution.
        motor_params: physics of the motor (output side of the drive's own units).
        initial_position: motor position at start, rad.
        eds: the object dictionary (default: the shipped EDS).
        rated_torque: N*m that 0x6077 = 1000 stands for (default: the motor's torque limit).

    Raises:
        ValueError: node id out of range.
    """

    def __init__(
        self,
        bus: can.BusABC,
        node_id: int,
        *,
        pace_bitrate: int | None = None,
        counts_per_revolution: int = 131072,
        motor_params: MotorParams | None = None,
        initial_position: float = 0.0,
        eds: str | Path | None = None,
        rated_torque: float | None = None,
    ) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id must be 1..127, got {node_id!r}")
        self.bus = bus
        self.node_id = node_id
        self.pace_bitrate = pace_bitrate
        self.counts_per_revolution = int(counts_per_revolution)
        self.motor = Motor(motor_params, initial_position)
        self.rated_torque = rated_torque or self.motor.params.torque_limit or 1.0
        self.node = canopen.LocalNode(node_id, str(eds or DEFAULT_EDS))
        # canopen's callback registration is untyped.
        register: Any = self.node
        register.add_read_callback(self._od_read)
        register.add_write_callback(self._od_write)
        # The heartbeat producer (0x1017) is this module's, paced and silenced with the other
        # frames and carrying the emulated NMT state; canopen's slave would start a python-can
        # periodic thread of its own on a write.
        if register.nmt.on_write in register._write_callbacks:
            register._write_callbacks.remove(register.nmt.on_write)
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self.nmt_state = NmtState.INITIALISING
        self.state = c4.State.SWITCH_ON_DISABLED
        self.mode = 0
        self.mode_display = 0
        self.controlword = 0
        self.target_position = 0
        self.target_velocity = 0
        self.error_code = 0
        self.error_register = 0
        self._fault_persistent = False
        self._last_step: float | None = None  # time the physics was last advanced to
        self._sync_count = 0
        self._pending_rpdo: dict[int, bytes] = {}
        self._layout_cache: _Layouts | None = None
        self._silent = False
        self._drop = 0
        self._tpdo_delay_s = 0.0
        self._refuse_enable = False
        self._refuse_mode = False
        self._lose_enable: tuple[int, int | None] | None = None
        self._enabled_at_sync = 0
        self._emcy_pending: bytes | None = None
        self.syncs_seen = 0
        self.tpdos_sent = 0
        self.rpdos_applied = 0
        self.enable_jump_counts: int | None = None
        self._consumers: dict[int, _Consumer] = {}
        self._producer_s = 0.0
        self._next_beat = 0.0
        self._stopping: _Stop | None = None
        self._hold_at: float | None = None
        self._trips: list[WatchdogTrip] = []
        self._beats: deque[float] = deque(maxlen=64)  # when it produced its heartbeats
        self._open_trip: int | None = None  # index of the trip whose stop is not complete
        self.heartbeats_seen = 0
        self._hub: Hub | None = None
        self._load_comm_objects()

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self, push: bool = False) -> None:
        """Join the bus and boot: send the boot-up message and enter pre-operational.

        Args:
            push: (first drive on the bus object) the bus is a python-can ``virtual`` bus
                whose frames are handled in the sending peer's thread and no thread is
                started: the caller releases the due frames (:meth:`timer`'s
                ``next_due`` / ``release_due``; a one-thread socketcand server's timer).

        Raises:
            ValueError: another emulator with this node id is on the same bus object, or
                ``push`` with a bus that is not a python-can virtual bus.
            RuntimeError: already started.
        """
        if self._hub is not None:
            raise RuntimeError(f"drive {self.node_id} already started")
        self._hub = Hub.join(self, push)
        self._boot()

    def timer(self) -> Any:
        """The object releasing this drive's bus's due frames (``next_due(): float | None``,
        ``release_due(now)``), shared by the drives on the bus object; started drives only.

        Raises:
            RuntimeError: not started.
        """
        if self._hub is None:
            raise RuntimeError(f"drive {self.node_id} not started")
        return self._hub

    def stop(self) -> None:
        """Leave the bus (its thread stops with the last drive on it). Idempotent."""
        hub, self._hub = self._hub, None
        if hub is not None:
            hub.leave(self)

    def __enter__(self) -> Cia402DriveEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def error(self) -> BaseException | None:
        """The exception that stopped the receive thread, if any."""
        return None if self._hub is None else self._hub.error

    # -- observation ----------------------------------------------------------------------------

    @property
    def state(self) -> c4.State:
        """The CiA 402 state the drive is in (setting it wakes :meth:`wait_state`)."""
        return self._state

    @state.setter
    def state(self, state: c4.State) -> None:
        with self._changed:
            self._state = state
            self._changed.notify_all()

    def wait_state(self, state: c4.State, timeout_s: float) -> bool:
        """Wait until the drive is in ``state``; False if it is not within ``timeout_s``."""
        with self._changed:
            return self._changed.wait_for(lambda: self._state is state, timeout_s)

    @property
    def position_counts(self) -> int:
        """Position actual, counts."""
        return round(self.motor.position * self.counts_per_revolution / c4.TWO_PI)

    @property
    def velocity_counts(self) -> int:
        """Velocity actual, counts/s."""
        return round(self.motor.velocity * self.counts_per_revolution / c4.TWO_PI)

    @property
    def statusword(self) -> int:
        """The statusword the drive reports now."""
        following = self.state is c4.State.OPERATION_ENABLED
        return c4.encode_statusword(
            self.state,
            voltage_enabled=self.state is not c4.State.SWITCH_ON_DISABLED,
            following=following,
        )

    @property
    def watchdog_trips(self) -> list[WatchdogTrip]:
        """Every heartbeat event of this drive so far, oldest first."""
        with self._lock:
            return list(self._trips)

    @property
    def heartbeats_produced(self) -> list[float]:
        """When (``time.monotonic()``) this drive produced its last heartbeats (0x1017), oldest
        first, at most 64: the drive's own clock, which sets the producer time; the frames'
        receive stamps add however late the host ran the hub's thread after that."""
        with self._lock:
            return list(self._beats)

    @property
    def heartbeat_consumers(self) -> dict[int, tuple[int, float, bool]]:
        """The used 0x1016 entries: sub-index -> (producer node id, consumer time in s,
        monitoring: armed by a heartbeat since the entry was written)."""
        with self._lock:
            return {sub: (c.producer, c.time_s, c.armed) for sub, c in self._consumers.items()}

    def wait_watchdog_stop(self, timeout_s: float, since: int = 0) -> WatchdogTrip | None:
        """Wait until the stop of a heartbeat event is complete (the motor at rest).

        Args:
            timeout_s: how long to wait at most, s.
            since: ignore the first ``since`` trips (those of :attr:`watchdog_trips` already
                seen).

        Returns:
            The first trip from index ``since`` whose stop is complete; None if there is none
            within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                for trip in self._trips[since:]:
                    if trip.stopped_at is not None:
                        return trip
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    return None
                self._changed.wait(remaining)

    # -- fault injection ------------------------------------------------------------------------

    def inject_fault(self, error_code: int = 0x4310, *, persistent: bool = False) -> None:
        """Latch a drive fault with ``error_code`` in 0x603F and an EMCY message: Fault
        Reaction Active (the motor stopped as 0x605E says), then Fault, torque off. A fault
        reset clears it unless ``persistent`` (the condition is still there), until
        :meth:`clear_condition`."""
        with self._lock:
            self._fault_persistent = persistent
            self._begin_fault_reaction(error_code, time.monotonic())
            self._emcy_pending = c4.encode_emcy(self.error_code, self.error_register)

    def clear_condition(self) -> None:
        """The cause of a persistent fault is gone: the next fault reset succeeds."""
        with self._lock:
            self._fault_persistent = False

    def set_silent(self, silent: bool) -> None:
        """A silent drive receives but never transmits (power loss of its CAN transceiver)."""
        self._silent = bool(silent)

    def drop_tpdos(self, syncs: int) -> None:
        """Do not answer the next ``syncs`` SYNCs (the state still advances)."""
        self._drop = max(0, int(syncs))

    def set_tpdo_delay(self, delay_s: float) -> None:
        """Send the TPDOs ``delay_s`` after the SYNC (late answers)."""
        self._tpdo_delay_s = max(0.0, float(delay_s))

    def refuse_enable(self, refuse: bool) -> None:
        """Ignore Enable Operation (stays Switched On): a failed transition for the host."""
        self._refuse_enable = bool(refuse)

    def lose_enable(self, after_syncs: int | None, fault_code: int | None = 0x5441) -> None:
        """An enable input (STO) that opens ``after_syncs`` SYNCs after the drive entered
        Operation Enabled, each time: with ``fault_code`` the drive faults with it (0x5441
        enable input off), without it drops to Switch On Disabled. None: the input stays
        closed."""
        with self._lock:
            self._lose_enable = None if after_syncs is None else (max(1, after_syncs), fault_code)

    def refuse_mode(self, refuse: bool) -> None:
        """Accept writes to 0x6060 but keep the display 0x6061 (a failed mode switch)."""
        self._refuse_mode = bool(refuse)

    def inject_bus_off(self) -> None:
        """Put an error frame reporting bus-off on the bus, then keep every drive of this
        bus object silent until :meth:`clear_bus_off`."""
        hub = self._hub
        if hub is None:
            return
        frame = can.Message(
            arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, is_extended_id=False,
            data=bytes(8),
        )
        hub.transmit(frame)
        hub.bus_off = True

    def clear_bus_off(self) -> None:
        """The bus recovered (every drive of this bus object talks again)."""
        if self._hub is not None:
            self._hub.bus_off = False

    # -- NMT ------------------------------------------------------------------------------------

    def _boot(self) -> None:
        self.nmt_state = NmtState.INITIALISING
        self._pending_rpdo.clear()
        self._layout_cache = None
        self._send(c4.bootup_cob_id(self.node_id), b"\x00", force=True)
        self.nmt_state = NmtState.PRE_OPERATIONAL
        if self._producer_s > 0.0:  # its heartbeats follow the boot-up
            self._set_producer(round(self._producer_s * 1000.0), time.monotonic())

    def on_nmt(self, command: int) -> None:
        with self._lock:
            if command == c4.NMT_START:
                self.nmt_state = NmtState.OPERATIONAL
                if self._stopping is None:
                    self._last_step = None
            elif command == c4.NMT_STOP:
                self.nmt_state = NmtState.STOPPED
            elif command == c4.NMT_ENTER_PRE_OPERATIONAL:
                self.nmt_state = NmtState.PRE_OPERATIONAL
            elif command in (c4.NMT_RESET_NODE, c4.NMT_RESET_COMMUNICATION):
                for index in [i for i in self.node.data_store if i in _COMM_RANGE]:
                    del self.node.data_store[index]
                if command == c4.NMT_RESET_NODE:
                    self.node.data_store.clear()
                    self.state = c4.State.SWITCH_ON_DISABLED
                    self.mode = self.mode_display = 0
                    self._stopping = None
                    if not self._fault_persistent:
                        self.error_code = self.error_register = 0
                    else:
                        self.state = c4.State.FAULT
                # The heartbeat consumer and producer go back to their (stored) defaults.
                self._load_comm_objects()
                self._boot()

    # -- object dictionary ------------------------------------------------------------------------

    def _live(self, index: int) -> int | None:
        if index == c4.ERROR_REGISTER:
            return self.error_register
        return self._snapshot().get(index)

    def _snapshot(self) -> dict[int, int]:
        """The live value of every mappable object now."""
        return {
            c4.STATUSWORD: self.statusword,
            c4.CONTROLWORD: self.controlword,
            c4.POSITION_ACTUAL: self.position_counts,
            c4.VELOCITY_ACTUAL: self.velocity_counts,
            c4.TORQUE_ACTUAL: round(1000.0 * self.motor.torque / self.rated_torque),
            c4.ERROR_CODE: self.error_code,
            c4.MODES_OF_OPERATION: self.mode,
            c4.MODES_OF_OPERATION_DISPLAY: self.mode_display,
            c4.TARGET_POSITION: self.target_position,
            c4.TARGET_VELOCITY: self.target_velocity,
        }

    def _od_read(self, index: int, subindex: int, od: Any) -> int | None:
        return self._live(index)

    def _od_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index == c4.CONSUMER_HEARTBEAT_TIME:
            with self._lock:
                self._write_consumer(subindex, int.from_bytes(data[:4], "little"))
            return
        if index == c4.PRODUCER_HEARTBEAT_TIME:
            with self._lock:
                self._set_producer(int.from_bytes(data[:2], "little"), time.monotonic())
            return
        if index in _REACTION_CODES:
            if int.from_bytes(data[:2], "little", signed=True) not in _REACTION_CODES[index]:
                raise SdoAbortedError(_ABORT_VALUE_RANGE)
            return
        if index in _PDO_PARAM_RANGE:
            if self.nmt_state == NmtState.OPERATIONAL and index >= _RPDO_MAP:
                pass  # real drives may refuse; accepting keeps hosts that remap live working
            self._layout_cache = None
            return
        if index in c4.OBJECTS:
            bits, signed = c4.OBJECTS[index]
            value = int.from_bytes(data[: bits // 8], "little", signed=signed)
            with self._lock:
                if index == c4.MODES_OF_OPERATION:
                    if value not in _SUPPORTED_MODES:
                        raise SdoAbortedError(_ABORT_VALUE_RANGE)
                    self.mode = value
                    if not self._refuse_mode:
                        self.mode_display = value
                elif index == c4.CONTROLWORD:
                    self._apply_controlword(value)
                elif index == c4.TARGET_POSITION:
                    self.target_position = value
                elif index == c4.TARGET_VELOCITY:
                    self.target_velocity = value
                else:
                    raise SdoAbortedError(_ABORT_STATE)

    def _u32(self, index: int, subindex: int) -> int:
        return int.from_bytes(self.node.get_data(index, subindex), "little")

    def _layouts(self) -> _Layouts:
        """(RPDO cob id -> layout, [(TPDO cob id, layout, transmission type)]) from the OD."""
        if self._layout_cache is not None:
            return self._layout_cache
        rpdos: dict[int, c4.PdoLayout] = {}
        tpdos: list[tuple[int, c4.PdoLayout, int]] = []
        for comm, mapping, is_rx in ((_RPDO_COMM, _RPDO_MAP, True), (_TPDO_COMM, _TPDO_MAP, False)):
            for n in range(4):
                if comm + n not in self.node.object_dictionary:
                    continue
                cob = self._u32(comm + n, 1)
                if cob & 0x80000000:
                    continue  # not valid
                ttype = int.from_bytes(self.node.get_data(comm + n, 2), "little")
                count = int.from_bytes(self.node.get_data(mapping + n, 0), "little")
                entries = []
                for sub in range(1, count + 1):
                    index, subindex, bits = c4.decode_mapping(self._u32(mapping + n, sub))
                    signed = c4.OBJECTS.get(index, (bits, False))[1]
                    entries.append(c4.PdoEntry(index, subindex, bits, signed))
                layout = c4.PdoLayout(tuple(entries))
                if is_rx:
                    rpdos[cob & 0x7FF] = layout
                else:
                    tpdos.append((cob & 0x7FF, layout, ttype))
        self._layout_cache = (rpdos, tpdos)
        return self._layout_cache

    # -- heartbeat consumer (0x1016) and producer (0x1017) -------------------------------------

    def _load_comm_objects(self) -> None:
        """The consumer entries and the producer time from the object dictionary (after a
        boot or a reset communication: the stored or default values)."""
        self._consumers.clear()
        od = self.node.object_dictionary
        if c4.CONSUMER_HEARTBEAT_TIME in od:
            count = int.from_bytes(self.node.get_data(c4.CONSUMER_HEARTBEAT_TIME, 0), "little")
            for sub in range(1, count + 1):
                self._write_consumer(sub, self._u32(c4.CONSUMER_HEARTBEAT_TIME, sub))
        self._producer_s = 0.0
        if c4.PRODUCER_HEARTBEAT_TIME in od:
            ms = int.from_bytes(self.node.get_data(c4.PRODUCER_HEARTBEAT_TIME, 0), "little")
            self._set_producer(ms, time.monotonic())

    def _write_consumer(self, sub: int, value: int) -> None:
        """A 0x1016 entry is written: monitoring of that producer restarts, and begins with
        its next heartbeat (CiA 301: the producer's state is unknown until then).

        Raises:
            SdoAbortedError: another used entry watches the same node id (0x06040043).
        """
        entry = c4.decode_consumer_entry(value)
        if entry is None:
            self._consumers.pop(sub, None)
            return
        producer, time_ms = entry
        for other, consumer in self._consumers.items():
            if other != sub and consumer.producer == producer:
                raise SdoAbortedError(_ABORT_INCOMPATIBLE)
        self._consumers[sub] = _Consumer(producer, time_ms / 1000.0)

    def _set_producer(self, time_ms: int, now: float) -> None:
        self._producer_s = time_ms / 1000.0
        if self._producer_s > 0.0:
            self._next_beat = now + self._producer_s
            self._wake_at(self._next_beat)

    def on_heartbeat(self, producer: int, state: int, at: float) -> None:
        """A heartbeat (or boot-up) of ``producer`` crossed the bus at ``at`` (monotonic)."""
        with self._lock:
            for consumer in self._consumers.values():
                if consumer.producer != producer:
                    continue
                if state == NmtState.INITIALISING:
                    # A boot-up: the producer restarted; watch it again from its next heartbeat.
                    consumer.armed = False
                    continue
                self.heartbeats_seen += 1
                consumer.last_at = max(consumer.last_at, at)
                consumer.deadline = consumer.last_at + consumer.time_s
                if not consumer.armed:
                    consumer.armed = True
                    self._wake_at(consumer.deadline)

    def _wake_at(self, when: float) -> None:
        hub = self._hub
        if hub is not None:
            hub.wake_at(when)

    def on_time(self, now: float) -> float | None:
        """Time-driven work (the hub calls it when due): expired consumers, this drive's own
        heartbeat, a stop in progress. The time of the next such work (None: none)."""
        with self._lock:
            for consumer in self._consumers.values():
                if consumer.armed and now >= consumer.deadline:
                    self._heartbeat_event(consumer, now)
            if self._producer_s > 0.0 and now >= self._next_beat:
                if self.nmt_state != NmtState.INITIALISING:
                    self._send(c4.bootup_cob_id(self.node_id), c4.encode_heartbeat(self.nmt_state))
                    self._beats.append(now)
                self._next_beat = now + self._producer_s
            if self._stopping is not None:
                self._advance(now)
            wake: float | None = None
            for consumer in self._consumers.values():
                if consumer.armed and (wake is None or consumer.deadline < wake):
                    wake = consumer.deadline
            if self._producer_s > 0.0 and (wake is None or self._next_beat < wake):
                wake = self._next_beat
            if self._stopping is not None:
                step = now + _AUTONOMOUS_STEP_S
                wake = step if wake is None else min(wake, step)
            return wake

    def _heartbeat_event(self, consumer: _Consumer, now: float) -> None:
        """The consumer time ran out: EMCY 0x8130 and the 0x6007 abort connection reaction.
        Monitoring stops until the producer's next heartbeat."""
        consumer.armed = False
        # The drive's own loop ran on with the set-points in force until now.
        self._advance(now)
        reaction = c4.AbortConnection(self._option(c4.ABORT_CONNECTION_OPTION))
        trip = WatchdogTrip(
            producer=consumer.producer, consumer_time_s=consumer.time_s,
            last_heartbeat_at=consumer.last_at, detected_at=now, reaction=reaction,
            state_before=self.state, velocity_at_detection=self.motor.velocity,
        )
        self._trips.append(trip)
        self.error_register |= c4.ERROR_REGISTER_GENERIC | c4.ERROR_REGISTER_COMMUNICATION
        # Manufacturer-specific byte: the node id whose heartbeat was lost.
        emcy = c4.encode_emcy(c4.EMCY_HEARTBEAT, self.error_register, bytes((consumer.producer,)))
        self._send(c4.emcy_cob_id(self.node_id), emcy)
        _log.warning("drive %d: heartbeat of node %d lost (%.0f ms): %s", self.node_id,
                     consumer.producer, consumer.time_s * 1e3, reaction.name.lower())
        if reaction is c4.AbortConnection.NO_ACTION:
            self._changed.notify_all()
            return
        self._open_trip = len(self._trips) - 1
        state = self.state
        if reaction is c4.AbortConnection.FAULT:
            self._begin_fault_reaction(c4.EMCY_HEARTBEAT, now)
        else:
            self.error_code = c4.EMCY_HEARTBEAT
            if reaction is c4.AbortConnection.QUICK_STOP and state is c4.State.OPERATION_ENABLED:
                self._begin_quick_stop(now)
            elif state in _POWERED:
                # Disable Voltage, or Quick Stop from a state without a quick stop (7, 10):
                # Switch On Disabled, the power stage off.
                self.state = c4.State.SWITCH_ON_DISABLED
        if self._stopping is None:
            self._stopping = _Stop(c4.Ramp.COAST, None)  # to see when it is at rest
            self._last_step = now
        self._advance(now)

    # -- stops the drive performs by itself -------------------------------------------------------

    def _option(self, index: int) -> int:
        """An option code (INTEGER16) or deceleration (UNSIGNED32) from the object dictionary."""
        data = self.node.get_data(index, 0)
        return int.from_bytes(data, "little", signed=len(data) == 2)

    def _begin_quick_stop(self, now: float) -> None:
        """Transition 11 (quick stop command or abort connection): as 0x605A says."""
        ramp, stays = c4.quick_stop_reaction(self._option(c4.QUICK_STOP_OPTION))
        if ramp is c4.Ramp.COAST:
            self.state = c4.State.SWITCH_ON_DISABLED  # "disable drive function": at once
            self._stopping = _Stop(ramp, None)
        else:
            self.state = c4.State.QUICK_STOP_ACTIVE
            self._stopping = _Stop(
                ramp, c4.State.QUICK_STOP_ACTIVE if stays else c4.State.SWITCH_ON_DISABLED
            )
        self._start_autonomous(now)

    def _begin_fault_reaction(self, error_code: int, now: float) -> None:
        """Transition 13: Fault Reaction Active (the stop 0x605E says), then Fault (14)."""
        self.error_code = error_code & 0xFFFF
        self.error_register |= c4.ERROR_REGISTER_GENERIC
        if error_code == c4.EMCY_HEARTBEAT:
            self.error_register |= c4.ERROR_REGISTER_COMMUNICATION
        if self.state in (c4.State.FAULT, c4.State.FAULT_REACTION_ACTIVE):
            return
        ramp = c4.fault_reaction(self._option(c4.FAULT_REACTION_OPTION))
        powered = self.state in (c4.State.OPERATION_ENABLED, c4.State.QUICK_STOP_ACTIVE)
        self.state = c4.State.FAULT_REACTION_ACTIVE
        # A drive whose power stage is off can only let the motor coast.
        self._stopping = _Stop(ramp if powered else c4.Ramp.COAST, c4.State.FAULT)
        self._start_autonomous(now)

    def _start_autonomous(self, now: float) -> None:
        if self._last_step is None:
            self._last_step = now
        self._wake_at(now + _AUTONOMOUS_STEP_S)

    def _deceleration(self, ramp: c4.Ramp) -> float:
        """The ramp's deceleration, motor rad/s^2 (0: none, the torque limit stops it)."""
        if ramp is c4.Ramp.SLOW_DOWN:
            counts = self._option(c4.PROFILE_DECELERATION)
        elif ramp is c4.Ramp.QUICK_STOP:
            counts = self._option(c4.QUICK_STOP_DECELERATION)
        else:
            return 0.0  # current / voltage limit: as hard as the drive can
        return counts * c4.TWO_PI / self.counts_per_revolution

    def _stopped(self, now: float) -> None:
        """The motor of a stop in progress is at rest."""
        stop, self._stopping = self._stopping, None
        if stop is not None and stop.final is not None:
            self.state = stop.final
        if self.state is c4.State.QUICK_STOP_ACTIVE:
            self._hold_at = self.motor.position
        if self._open_trip is not None:
            index, self._open_trip = self._open_trip, None
            self._trips[index] = replace(
                self._trips[index], stopped_at=now, state_after=self.state,
                position_at_stop=self.motor.position,
            )
        self._changed.notify_all()

    # -- PDO and the state machine --------------------------------------------------------------

    def on_frame(self, cob: int, data: bytes) -> bool:
        """A frame addressed to this node: True if taken here (an RPDO) or dropped (a silent
        drive); False for frames that are not (SDO: canopen's server answers them)."""
        if self._silent:
            return True
        if self.nmt_state != NmtState.OPERATIONAL:
            return False
        rpdos = self._layouts()[0]
        if cob not in rpdos:
            return False
        self._pending_rpdo[cob] = data
        return True

    def _apply_controlword(self, controlword: int) -> None:
        previous, self.controlword = self.controlword, controlword
        state = self.state
        if state is c4.State.FAULT:
            rising = controlword & c4.CW_FAULT_RESET and not previous & c4.CW_FAULT_RESET
            if rising and not self._fault_persistent:
                self.error_code = self.error_register = 0
                self.state = c4.State.SWITCH_ON_DISABLED
            return
        if state is c4.State.FAULT_REACTION_ACTIVE:
            return
        command = c4.decode_controlword(controlword)
        if command is c4.Command.FAULT_RESET:
            return  # no fault to reset; the drive ignores the rest of the word
        if state is c4.State.QUICK_STOP_ACTIVE and command is c4.Command.ENABLE_OPERATION and (
            self._stopping is not None or not c4.quick_stop_reaction(
                self._option(c4.QUICK_STOP_OPTION))[1]
        ):
            return  # transition 16 exists only at rest with 0x605A 5..8
        new = c4.expected_after(state, command)
        if new is state:
            return
        if new is c4.State.OPERATION_ENABLED:
            if self._refuse_enable:
                return
            # Record how far the first set-point is from where the joint stands: a host
            # that does not seed the target from the actual position makes the joint jump.
            self.enable_jump_counts = self.target_position - self.position_counts
            self.motor.reset_reference()
            self.error_code = self.error_register = 0  # nothing stops it any more
            self._stopping = None
            self._enabled_at_sync = self._sync_count
        elif new is c4.State.QUICK_STOP_ACTIVE:
            self._begin_quick_stop(time.monotonic())
            return
        elif self._stopping is not None:
            # Out of Quick Stop Active by Disable Voltage (12): the power stage goes off.
            self._stopping = _Stop(c4.Ramp.COAST, None)
        self.state = new

    def _advance(self, now: float, cap: float = _MAX_GAP_S) -> None:
        """Advance the physics to ``now`` (at most ``cap`` seconds at once; a ``now`` the
        physics has already passed, e.g. a SYNC's stamp after a time-driven step, is a no-op).
        """
        last = self._last_step
        if last is not None and now <= last:
            return
        self._last_step = now
        if last is not None:
            self._step_physics(min(now - last, cap), now)

    def _step_physics(self, dt: float, now: float) -> None:
        if dt <= 0.0:
            return
        stop = self._stopping
        if stop is not None:
            if stop.ramp is c4.Ramp.COAST:
                self.motor.coast(dt)
            else:
                self.motor.step_velocity(dt, 0.0, self._deceleration(stop.ramp))
            if abs(self.motor.velocity) < _STOPPED_RAD_S:
                self._stopped(now)
            return
        state = self.state
        if state is c4.State.OPERATION_ENABLED:
            if self.mode_display == c4.Mode.CYCLIC_SYNC_POSITION:
                goal = self.target_position * c4.TWO_PI / self.counts_per_revolution
                self.motor.step_position(dt, goal)
                return
            if self.mode_display == c4.Mode.CYCLIC_SYNC_VELOCITY:
                speed = self.target_velocity * c4.TWO_PI / self.counts_per_revolution
                self.motor.step_velocity(dt, speed)
                return
        elif state is c4.State.QUICK_STOP_ACTIVE:
            # At rest with 0x605A 5..8: the drive holds the position it stopped at.
            if self._hold_at is None:
                self._hold_at = self.motor.position
            self.motor.step_position(dt, self._hold_at)
            return
        self.motor.coast(dt)

    def on_sync(self, now: float) -> None:
        with self._lock:
            if self.nmt_state != NmtState.OPERATIONAL:
                return
            self.syncs_seen += 1
            self._sync_count += 1
            self._advance(now)
            if self.state is c4.State.FAULT_REACTION_ACTIVE and self._stopping is None:
                self.state = c4.State.FAULT
            lose = self._lose_enable
            if (lose is not None and self.state is c4.State.OPERATION_ENABLED
                    and self._sync_count - self._enabled_at_sync >= lose[0]):
                if lose[1] is None:
                    self.state = c4.State.SWITCH_ON_DISABLED
                    self._stopping = _Stop(c4.Ramp.COAST, None)
                    self._start_autonomous(now)
                else:
                    self._begin_fault_reaction(lose[1], now)
                    self._emcy_pending = c4.encode_emcy(self.error_code, self.error_register)
            rpdos, tpdos = self._layouts()
            for cob, data in self._pending_rpdo.items():
                layout = rpdos.get(cob)
                if layout is None or len(data) != layout.size:
                    continue
                values = layout.decode(data)
                self.rpdos_applied += 1
                # Targets first: an Enable Operation in the same PDO must see its set-point.
                ordered = sorted(
                    zip(layout.entries, values, strict=True),
                    key=lambda ev: ev[0].index == c4.CONTROLWORD,
                )
                for entry, value in ordered:
                    if entry.index == c4.CONTROLWORD:
                        self._apply_controlword(value)
                    elif entry.index == c4.TARGET_POSITION:
                        self.target_position = value
                    elif entry.index == c4.TARGET_VELOCITY:
                        self.target_velocity = value
            self._pending_rpdo.clear()
            if self._emcy_pending is not None:
                self._send(c4.emcy_cob_id(self.node_id), self._emcy_pending)
                self._emcy_pending = None
            if self._drop > 0:
                self._drop -= 1
                return
            live = self._snapshot()
            for cob, layout, ttype in tpdos:
                if not 1 <= ttype <= 240 or self._sync_count % ttype:
                    continue
                sample = [live.get(e.index, 0) for e in layout.entries]
                self._send(cob, layout.encode(*sample), delay_s=self._tpdo_delay_s)
                self.tpdos_sent += 1

    def _send(self, cob: int, data: bytes, *, delay_s: float = 0.0, force: bool = False) -> None:
        hub = self._hub
        if hub is None or (self._silent and not force) or (hub.bus_off and not force):
            return
        hub.transmit(
            can.Message(arbitration_id=cob, data=data, is_extended_id=False), delay_s
        )
