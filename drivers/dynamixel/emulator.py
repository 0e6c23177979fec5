"""A bus of emulated Dynamixel X-series servos on a pseudo-terminal (Protocol 2.0).

Theory of operation
-------------------
:class:`DynamixelEmulator` opens a pty pair and serves the slave side (``/dev/pts/N``, or a
symlink to it) to any Protocol 2.0 host: the official SDK, our driver, a terminal tool. One thread
waits on the master side with ``select`` (so :meth:`~DynamixelEmulator.close` is prompt), feeds
the bytes to the shared :class:`~jtc_hw.drivers.dynamixel.packets.Decoder` and answers each
instruction packet as the addressed servos would:

- PING, READ, WRITE, REG_WRITE, ACTION, REBOOT, CLEAR (multi-turn), SYNC_READ, SYNC_WRITE,
  BULK_READ, BULK_WRITE, FAST_SYNC_READ, FAST_BULK_READ; FACTORY_RESET is refused with a
  "result fail" status (the emulator never forgets its ids). Broadcast (id 0xFE) where the
  protocol allows it: PING (every servo answers, in id order), WRITE, REG_WRITE, ACTION, REBOOT,
  CLEAR and the group instructions. A packet with a bad CRC addressed to one servo gets a
  "CRC error" status.
- Status Return Level (0: PING only, 1: PING and reads, 2: everything) and the Return Delay Time
  (register value * 2 us, waited before each reply). In group reads the servos answer in the
  requested order, each after the previous one, as on a real bus. Fast Sync/Bulk Read answers
  with one status packet written in per-servo pieces; a servo that does not answer (silent,
  dropping or rebooting) truncates it there, as the next servo would be waiting for it.
- Unpaced, replies that are already due are written together and waits under 0.2 ms are
  skipped: when the host shares the emulator's interpreter (tests), every wait costs it a thread
  switch.
- With ``pace=True`` the host sees the timing of a real bus, not of a pty (``time.monotonic``,
  10 bits per byte at the servo's Baud Rate register). A request starts on the wire when its
  first byte arrived, or when the bus is free if a previous packet still holds it (a Sync Write
  takes its wire time even though nobody answers it). Its replies are computed at once; each is
  then written when its last byte would have arrived: request start + request wire time + for
  each reply in turn the servo's return delay (and injected delay) and the reply's wire time.
  The wait sleeps (with a 1 us timer slack asked for the serving thread) until ~100 us before
  that moment and spins the rest: this is a test device, and a sleep alone wakes 20-70 us late.

Each servo (:class:`~jtc_hw.drivers.dynamixel.servo.EmulatedServo`) keeps its control table,
drives one motor model and has a Bus Watchdog as the e-Manual describes them: writes, operating
modes, the register <-> shaft mapping and the watchdog's rules are in that module's docstring.
Each Bus Watchdog trip is recorded as a :class:`~jtc_hw.drivers.dynamixel.servo.WatchdogTrip`:
:meth:`~DynamixelEmulator.watchdog_trips` and :meth:`~DynamixelEmulator.wait_watchdog_stopped`;
the command line prints one JSON line per trip.

Faults for tests (all thread-safe): :meth:`~DynamixelEmulator.drop_replies`,
:meth:`~DynamixelEmulator.delay_replies`, :meth:`~DynamixelEmulator.corrupt_crc`,
:meth:`~DynamixelEmulator.set_silent`, :meth:`~DynamixelEmulator.raise_hardware_error` (latched
until REBOOT: alert bit in every status, torque off, torque cannot be enabled),
:meth:`~DynamixelEmulator.fail_next_torque_on` (a fault found on energising the motor) and
:meth:`~DynamixelEmulator.set_firmware_version`.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import json
import math
import os
import select
import signal
import sys
import threading
import time
import tty
from collections.abc import Iterable, Mapping, Sequence
from types import TracebackType

from jtc_hw.hardware.timing import reduce_timer_slack

from .. import emulation_cli
from ..emulation_cli import DEFAULT_PRIORITY, realtime_priority
from .control_table import BUS_WATCHDOG_FIRMWARE, HardwareError, model_by_name
from .packets import (
    BROADCAST_ID,
    Decoder,
    ErrorNumber,
    Instruction,
    Packet,
    encode_status,
    fast_status_parts,
    parse_bulk_read,
    parse_bulk_write,
    parse_sync_read,
    parse_sync_write,
    wire_time_s,
)
from .servo import EmulatedServo, WatchdogTrip

__all__ = ["DynamixelEmulator", "build_parser", "main", "parse_ids"]

#: Physics advance period while the bus is idle, s.
_IDLE_STEP_S = 0.005
#: Unpaced: waits shorter than this are skipped (sleeping that briefly is not accurate), s.
_MIN_WAIT_S = 0.0002
#: Paced: the last part of a wait is spun rather than slept (a sleep wakes ~20-35 us late even
#: with a 1 us timer slack on this kind of machine), s.
_SPIN_S = 0.0001
#: Paced waits longer than this sleep on the stop event so that close() stays prompt, s.
_PROMPT_WAIT_S = 0.002
#: Timer slack asked for the serving thread (Linux ``PR_SET_TIMERSLACK``; default 50 us), ns.
_TIMER_SLACK_NS = 1000
#: A partial packet older than this is dropped (the servos' inter-byte timeout), s.
_PARTIAL_TIMEOUT_S = 0.1
#: CLEAR's fixed parameters (option 0x01 "clear multi-turn" and the "DXL" key + 0x22).
_CLEAR_MULTI_TURN = bytes((0x01, 0x44, 0x58, 0x4C, 0x22))

@dataclasses.dataclass
class _Reply:
    servo: EmulatedServo
    data: bytes


class DynamixelEmulator:
    """One bus of emulated servos on a pseudo-terminal (see the module docstring).

    Args:
        ids: the servo ids (1..252), all of ``model``.
        model: the servo model's name (see ``control_table.MODELS``).
        baud: the servos' baud rate in bit/s (a value of ``BAUD_RATES``); used for pacing.
        pace: hold replies back so that requests and replies take their wire time.
        link: a path to create as a symlink to the pty slave (an existing symlink is replaced).
        initial_positions: id -> shaft position, rad (default pi: tick 2048, mid-range).
        return_delay_us: initial Return Delay Time, us (default: the model's, 500 us).
        reboot_time_s: how long a servo stays silent after REBOOT.
        firmware_version: the Firmware Version every servo reports (default: the model's);
            below :data:`BUS_WATCHDOG_FIRMWARE` the servos have no Bus Watchdog.

    Raises:
        ValueError: bad ids, baud rate or firmware version.
        KeyError: unknown model (``UnknownModelError``).
    """

    def __init__(
        self,
        ids: Sequence[int],
        model: str = "XM430-W350",
        *,
        baud: int = 4_000_000,
        pace: bool = False,
        link: str | None = None,
        initial_positions: Mapping[int, float] | None = None,
        return_delay_us: float | None = None,
        reboot_time_s: float = 0.05,
        firmware_version: int | None = None,
    ) -> None:
        ids = list(ids)
        if not ids or any(not 0 <= i <= 252 for i in ids) or len(set(ids)) != len(ids):
            raise ValueError(f"ids must be distinct values in 0..252, got {ids}")
        self.model = model_by_name(model)
        values = {bps: v for v, bps in self.model.baud_rates.items()}
        if baud not in values:
            raise ValueError(
                f"{self.model.name} does not support {baud} bit/s; choose one of {sorted(values)}"
            )
        self.pace = pace
        self.reboot_time_s = reboot_time_s
        self._link = link
        positions = dict(initial_positions or {})
        self._lock = threading.Lock()
        # Signalled (under the lock) when a servo's Bus Watchdog trips or the servo comes to
        # rest after a trip: wait_watchdog_stopped() blocks on it.
        self._changed = threading.Condition(self._lock)
        self._servos = [
            EmulatedServo(self.model, i, positions.get(i, math.pi), values[baud],
                   self._changed.notify_all)
            for i in ids
        ]
        if return_delay_us is not None:
            value = max(0, min(254, round(return_delay_us / 2.0)))
            for s in self._servos:
                s.set("return_delay_time", value)
        if firmware_version is not None:
            for s in self._servos:
                s.set_firmware(firmware_version)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = -1
        self._slave = -1
        self._slave_path = ""
        self._decoder = Decoder()
        self._baud = baud
        # When the bus is next idle (the end of the last request or reply on the wire, paced
        # mode; the last reply's due time, unpaced).
        self._bus_free = 0.0
        self._last_step = 0.0  # when every servo was last stepped (idle stepping)
        self.packets_served = 0
        self.replies_sent = 0
        self.bytes_dropped = 0
        self.errors_sent = 0

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> DynamixelEmulator:
        """Open the pty (and the link) and start serving.

        Raises:
            RuntimeError: already started.
            OSError: the pty or the link cannot be created.
            FileExistsError: ``link`` exists and is not a symlink.
        """
        if self._thread is not None:
            raise RuntimeError("the emulator is already started")
        self._master, self._slave = os.openpty()
        try:
            # Raw mode: no echo, no line discipline translating bytes such as 0x0D or 0x11.
            tty.setraw(self._slave)
            os.set_blocking(self._master, False)
            self._slave_path = os.ttyname(self._slave)
            if self._link:
                if os.path.islink(self._link):
                    os.unlink(self._link)
                elif os.path.exists(self._link):
                    raise FileExistsError(f"{self._link} exists and is not a symlink")
                os.symlink(self._slave_path, self._link)
        except BaseException:
            os.close(self._master)
            os.close(self._slave)
            self._master = self._slave = -1
            raise
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="dxl-emulator", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving, join the thread, close the pty and remove the link (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1
        if self._link and os.path.islink(self._link):
            with contextlib.suppress(OSError):
                if os.readlink(self._link) == self._slave_path:
                    os.unlink(self._link)

    def __enter__(self) -> DynamixelEmulator:
        if self._thread is None:
            self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    @property
    def device_path(self) -> str:
        """The path a host opens: the link if one was asked for, else ``/dev/pts/N``."""
        return self._link or self._slave_path

    @property
    def slave_path(self) -> str:
        """The pty slave's path (``/dev/pts/N``)."""
        return self._slave_path

    # -- observation and faults ---------------------------------------------------------------

    def _servo(self, servo_id: int) -> EmulatedServo:
        for s in self._servos:
            if s.id == servo_id:
                return s
        raise KeyError(f"no emulated servo with id {servo_id}")

    def positions(self) -> dict[int, float]:
        """id -> Present Position in rad (``present_position * 2*pi / ticks_per_rev``), now."""
        with self._lock:
            now = time.monotonic()
            out = {}
            for s in self._servos:
                s.step(now)
                out[s.id] = self.model.ticks_to_rad(s.present_ticks())
            return out

    def register(self, servo_id: int, name: str) -> int:
        """The value of register ``name`` of servo ``servo_id`` (present values refreshed).

        Raises:
            KeyError: unknown servo or register.
        """
        with self._lock:
            s = self._servo(servo_id)
            s.step(time.monotonic())
            s.sync_present()
            self.model.register(name)
            return s.get(name)

    def drop_replies(self, servo_id: int, count: int) -> None:
        """Servo ``servo_id`` leaves its next ``count`` replies unsent.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo(servo_id).drop = max(0, int(count))

    def delay_replies(self, servo_id: int, seconds: float) -> None:
        """Servo ``servo_id`` answers ``seconds`` late (0 to stop).

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo(servo_id).delay_s = max(0.0, float(seconds))

    def corrupt_crc(self, servo_id: int, count: int) -> None:
        """Servo ``servo_id`` sends its next ``count`` replies with a wrong CRC.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo(servo_id).corrupt = max(0, int(count))

    def set_silent(self, servo_id: int, silent: bool) -> None:
        """Servo ``servo_id`` never answers (group reads included) while ``silent``.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo(servo_id).silent = bool(silent)

    def raise_hardware_error(self, servo_id: int, bits: HardwareError) -> None:
        """Latch hardware error ``bits`` on servo ``servo_id`` until it is rebooted.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            s = self._servo(servo_id)
            s.step(time.monotonic())
            s.set("hardware_error_status", s.get("hardware_error_status") | int(bits))
            s.set("torque_enable", 0)

    def set_temperature(self, servo_id: int, celsius: float) -> None:
        """Servo ``servo_id``'s internal temperature reads ``celsius`` from now on.

        As the e-Manual documents: above the Temperature Limit (31) the Overheating Error bit
        of Hardware Error Status is set; with that bit in Shutdown (63, default) the torque goes
        off and the error stays latched until a reboot. Cooling down clears nothing latched.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            s = self._servo(servo_id)
            s.step(time.monotonic())
            s.temperature_c = float(celsius)
            s.stale = True
            if round(celsius) > s.get("temperature_limit"):
                s.detect(HardwareError.OVERHEATING)

    def set_input_voltage(self, servo_id: int, volts: float | None) -> None:
        """Servo ``servo_id``'s supply reads ``volts`` from now on (``None``: the model's
        nominal voltage).

        Outside Min/Max Voltage Limit (32, 34) the Input Voltage Error bit is set; it shuts
        the servo down only if Shutdown (63) holds that bit (not by default), and then stays
        latched until a reboot; otherwise it clears when the supply is back within the limits.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            s = self._servo(servo_id)
            s.step(time.monotonic())
            s.voltage_v = None if volts is None else float(volts)
            s.stale = True
            tenths = round((s.model.nominal_voltage_v if volts is None else volts) * 10.0)
            bit = int(HardwareError.INPUT_VOLTAGE)
            if not s.get("min_voltage_limit") <= tenths <= s.get("max_voltage_limit"):
                s.detect(HardwareError.INPUT_VOLTAGE)
            elif not s.get("shutdown") & bit:
                s.set("hardware_error_status", s.get("hardware_error_status") & ~bit)

    def set_firmware_version(self, servo_id: int, version: int) -> None:
        """Servo ``servo_id`` reports Firmware Version ``version`` (below
        :data:`BUS_WATCHDOG_FIRMWARE`: no Bus Watchdog, and a write to it gets the access error).

        Raises:
            KeyError: unknown servo.
            ValueError: ``version`` outside 0..255.
        """
        with self._lock:
            self._servo(servo_id).set_firmware(version)

    def fail_next_torque_on(self, servo_id: int, bits: HardwareError) -> None:
        """The next time servo ``servo_id``'s torque is switched on, it finds hardware error
        ``bits`` at once (e.g. a shorted winding: electrical shock): the write is acknowledged
        (with the alert bit), then the error is latched and the torque is off again.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo(servo_id).torque_on_fault = int(bits)

    # -- Bus Watchdog records -------------------------------------------------------------------

    def watchdog_trips(self, since_s: float = -math.inf) -> list[WatchdogTrip]:
        """Every Bus Watchdog expiry at or after ``since_s`` (``time.monotonic()``), in order.

        The record survives clearing the register and rebooting; a trip still braking has
        ``stopped_s`` ``None``.
        """
        with self._lock:
            now = time.monotonic()
            for s in self._servos:
                s.step(now)  # an expiry due by now is recorded even if nothing stepped yet
            trips = [t for s in self._servos for t in s.trips if t.expired_s >= since_s]
        return sorted(trips, key=lambda t: (t.expired_s, t.servo_id))

    def wait_watchdog_stopped(
        self, ids: Iterable[int], timeout_s: float, since_s: float = -math.inf
    ) -> dict[int, WatchdogTrip]:
        """Block until each servo of ``ids`` has a trip at or after ``since_s`` that ended at
        rest; its first such trip per servo.

        This is what a benchmark of "daemon failure -> servos stopped" reads: take
        ``since_s`` and the failure moment from ``time.monotonic()``, then ``stopped_s`` minus
        the failure moment per servo.

        Raises:
            KeyError: unknown servo.
            TimeoutError: not every servo stopped within ``timeout_s`` (the message names them).
        """
        wanted = list(ids)
        deadline = time.monotonic() + timeout_s
        with self._lock:
            servos = [self._servo(i) for i in wanted]
            while True:
                now = time.monotonic()
                found: dict[int, WatchdogTrip] = {}
                for s in servos:
                    s.step(now)
                    trip = next((t for t in s.trips
                                 if t.expired_s >= since_s and t.stopped_s is not None), None)
                    if trip is not None:
                        found[s.id] = trip
                if len(found) == len(servos):
                    return found
                remaining = deadline - now
                if remaining <= 0.0:
                    missing = [i for i in wanted if i not in found]
                    raise TimeoutError(
                        f"servos {missing} did not stop on their Bus Watchdog within "
                        f"{timeout_s:g} s (trips: {[t for s in servos for t in s.trips]})"
                    )
                # The serving thread steps the servos at least every _IDLE_STEP_S and notifies
                # on every trip and stop; the bounded wait also steps them itself.
                self._changed.wait(min(remaining, 10 * _IDLE_STEP_S))

    def last_instruction_s(self, servo_id: int) -> float:
        """When servo ``servo_id`` last received an instruction packet (its id or broadcast,
        good CRC, awake), ``time.monotonic()``.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            return self._servo(servo_id).last_instruction

    def stats(self) -> dict[str, int]:
        """Counters: packets served, replies sent, CRC errors and junk bytes seen, ..."""
        with self._lock:
            return {
                "packets_served": self.packets_served,
                "replies_sent": self.replies_sent,
                "errors_sent": self.errors_sent,
                "crc_errors": self._decoder.crc_errors,
                "junk_bytes": self._decoder.junk_bytes,
                "bytes_dropped": self.bytes_dropped,
            }

    @property
    def crc_errors(self) -> int:
        """Instruction packets received with a bad CRC."""
        return self._decoder.crc_errors

    # -- serving ------------------------------------------------------------------------------

    def _serve(self) -> None:
        reduce_timer_slack(_TIMER_SLACK_NS)  # best effort: else the spin absorbs the slack
        last_rx = time.monotonic()
        first_byte = last_rx  # when the first byte of the packet being received arrived
        while not self._stop.is_set():
            try:
                readable, _, _ = select.select([self._master], [], [], _IDLE_STEP_S)
            except (OSError, ValueError):
                return
            now = time.monotonic()
            if readable:
                try:
                    data = os.read(self._master, 4096)
                except BlockingIOError:
                    data = b""
                except OSError as exc:
                    if exc.errno == errno.EIO:  # no slave open (cannot happen: we hold one)
                        self._stop.wait(_IDLE_STEP_S)
                        continue
                    return
                if data:
                    if self._decoder.pending and now - last_rx > _PARTIAL_TIMEOUT_S:
                        self._decoder.reset()
                    if not self._decoder.pending:
                        first_byte = now
                    last_rx = now
                    arrival = now
                    for packet in self._decoder.feed(data):
                        self._handle(packet, arrival, first_byte)
                        # Further packets of this chunk began on the wire with it at the
                        # latest (pacing queues them behind the previous one anyway).
                        first_byte = now
                        arrival = time.monotonic()
            # Physics runs once per request (in _handle); the idle bus only needs the watchdog
            # and the coasting motors to move on now and then.
            now = time.monotonic()
            if now - self._last_step >= _IDLE_STEP_S:
                with self._lock:
                    for s in self._servos:
                        s.step(now)
                    self._last_step = now

    def _handle(self, packet: Packet, arrival: float, first_byte: float) -> None:
        """Step the physics to ``arrival``, execute ``packet`` and send its replies.

        ``first_byte`` is when the packet's first byte arrived: paced replies are timed from
        there (or from when the bus is free, if later).
        """
        with self._lock:
            instruction = packet.crc_ok and not packet.is_status
            for s in self._servos:
                s.step(arrival)
                # The Bus Watchdog counts the instruction packets a servo receives: those
                # addressed to it and broadcast ones (every group instruction is broadcast, so
                # a Sync Write feeds the watchdog of every servo on the bus, as on real ones).
                if (
                    instruction
                    and (packet.id == s.id or packet.id == BROADCAST_ID)
                    and s.rebooting_until <= arrival
                ):
                    s.heard(arrival)
            self._last_step = arrival
            replies, fast = self._dispatch(packet, arrival)
            if replies or fast:
                self.packets_served += 1
            elif packet.crc_ok and not packet.is_status:
                self.packets_served += 1
        if replies or fast:
            self._transmit(packet, replies, fast, first_byte if self.pace else arrival)
        elif self.pace:
            # No reply, but the packet held the bus for its wire time: a request right behind
            # it (a Sync Read after a Sync Write) starts on the wire only after it.
            start = max(first_byte, self._bus_free)
            self._bus_free = start + wire_time_s(len(packet.raw), self._baud)

    def _awake(self, now: float) -> list[EmulatedServo]:
        return [s for s in self._servos if s.rebooting_until <= now]

    def _status(self, s: EmulatedServo, error: int, data: bytes = b"") -> _Reply:
        if error:
            self.errors_sent += 1
        return _Reply(s, encode_status(s.id, error | s.error_byte, data))

    def _dispatch(self, p: Packet, now: float) -> tuple[list[_Reply], list[_Reply]]:
        """Apply ``p``; return ``(status packets, fast status blocks)`` to send, in order."""
        if p.is_status:
            return [], []
        awake = self._awake(now)
        targets = [s for s in awake if s.id == p.id]
        if not p.crc_ok:
            if targets and p.instruction not in _GROUP:
                return [self._status(targets[0], ErrorNumber.CRC)], []
            return [], []
        inst, params = p.instruction, p.params
        broadcast = p.id == BROADCAST_ID
        if broadcast:
            targets = sorted(awake, key=lambda s: s.id)
        if inst == Instruction.PING:
            return [self._status(s, 0, bytes(s.table[0:2] + s.table[6:7])) for s in targets], []
        if inst in _GROUP:
            if not broadcast:
                return [], []
            return self._group(inst, params, now)
        if not targets:
            return [], []
        replies: list[_Reply] = []
        for s in targets:
            level = s.get("status_return_level")  # before the instruction may change it
            error, data = self._single(s, inst, params, broadcast, now)
            if broadcast or error < 0:
                continue
            if level == 2 or (level == 1 and inst == Instruction.READ):
                replies.append(self._status(s, error, data))
        return replies, []

    def _single(
        self, s: EmulatedServo, inst: int, params: bytes, broadcast: bool, now: float
    ) -> tuple[int, bytes]:
        """Execute a one-servo instruction; ``(error, data)``, error -1 for no reply."""
        if inst == Instruction.READ:
            if broadcast or len(params) != 4:
                return (-1 if broadcast else ErrorNumber.DATA_LENGTH), b""
            address, length = params[0] | params[1] << 8, params[2] | params[3] << 8
            if address + length > len(s.table) or length == 0:
                return ErrorNumber.ACCESS, b""
            s.refresh()
            return 0, bytes(s.table[address : address + length])
        if inst in (Instruction.WRITE, Instruction.REG_WRITE):
            if len(params) < 3:
                return ErrorNumber.DATA_LENGTH, b""
            address, data = params[0] | params[1] << 8, bytes(params[2:])
            error = s.check_write(address, data)
            if not error:
                if inst == Instruction.WRITE:
                    s.apply_write(address, data)
                else:
                    s.registered = (address, data)
                    s.set("registered_instruction", 1)
            return error, b""
        if inst == Instruction.ACTION:
            if s.registered is None:
                return ErrorNumber.INSTRUCTION, b""
            address, data = s.registered
            s.registered = None
            s.set("registered_instruction", 0)
            return s.write(address, data), b""
        if inst == Instruction.REBOOT:
            s.reboot(now, self.reboot_time_s)
            return 0, b""
        if inst == Instruction.CLEAR:
            if bytes(params) != _CLEAR_MULTI_TURN:
                return ErrorNumber.DATA_RANGE, b""
            s.refresh()
            if s.get("moving"):
                return ErrorNumber.RESULT_FAIL, b""
            s.clear_multi_turn()
            return 0, b""
        if inst == Instruction.FACTORY_RESET:
            return ErrorNumber.RESULT_FAIL, b""
        return ErrorNumber.INSTRUCTION, b""

    def _group(self, inst: int, params: bytes, now: float) -> tuple[list[_Reply], list[_Reply]]:
        awake = {s.id: s for s in self._awake(now)}
        try:
            if inst in (Instruction.SYNC_WRITE, Instruction.BULK_WRITE):
                if inst == Instruction.SYNC_WRITE:
                    address, _, items = parse_sync_write(params)
                    writes = [(i, address, d) for i, d in items]
                else:
                    writes = parse_bulk_write(params)
                for servo_id, address, data in writes:
                    if servo_id in awake:
                        awake[servo_id].write(address, data)
                return [], []
            if inst in (Instruction.SYNC_READ, Instruction.FAST_SYNC_READ):
                address, length, ids = parse_sync_read(params)
                reads = [(i, address, length) for i in ids]
            else:
                reads = [(e.id, e.address, e.length) for e in parse_bulk_read(params)]
        except ValueError:
            return [], []
        fast = inst in (Instruction.FAST_SYNC_READ, Instruction.FAST_BULK_READ)
        replies: list[_Reply] = []
        for servo_id, address, length in reads:
            s = awake.get(servo_id)
            if s is None or s.get("status_return_level") == 0:
                if fast:
                    break  # the following servos would wait for this one forever
                continue
            if address + length > len(s.table) or length == 0:
                error, data = int(ErrorNumber.ACCESS), bytes(length)
            else:
                s.refresh()
                error, data = 0, bytes(s.table[address : address + length])
            if fast:
                replies.append(_Reply(s, bytes((error | s.error_byte,)) + data))
            else:
                replies.append(self._status(s, error, data))
        if fast:
            return [], replies
        return replies, []

    # -- output -------------------------------------------------------------------------------

    def _transmit(
        self, request: Packet, replies: list[_Reply], fast: list[_Reply], start: float
    ) -> None:
        """Send the replies in order, each after its servo's delays (and wire time).

        Paced, the replies are computed at once and each is written when its last byte would
        arrive on a real bus: ``start`` (the request's first byte, or when the bus is free) +
        the request's wire time + for each reply in turn its return delay and wire time.
        """
        with self._lock:  # register reads go through the servos' decoded-value caches
            bus_baud = replies[0].servo.baud() if replies else fast[0].servo.baud()
        t = max(start, self._bus_free)
        if self.pace:
            t += wire_time_s(len(request.raw), bus_baud)
        chunks: list[tuple[EmulatedServo, bytes]]
        if fast:
            chunks = []
            with self._lock:
                entries = [(r.servo.id, r.data[0], r.data[1:]) for r in fast]
                parts = fast_status_parts(entries)
                for r, part in zip(fast, parts, strict=True):
                    if self._consume_drop(r.servo):
                        break
                    chunks.append((r.servo, part))
                if any([self._consume_corrupt(servo) for servo, _ in chunks]):
                    servo, last = chunks[-1]
                    chunks[-1] = (servo, last[:-1] + bytes((last[-1] ^ 0xFF,)))
        else:
            chunks = []
            with self._lock:
                for r in replies:
                    if self._consume_drop(r.servo):
                        continue
                    data = r.data
                    if self._consume_corrupt(r.servo):
                        data = data[:-1] + bytes((data[-1] ^ 0xFF,))
                    chunks.append((r.servo, data))
        due: list[tuple[float, bytes]] = []
        with self._lock:
            for servo, data in chunks:
                t += servo.return_delay_s() + servo.delay_s
                if self.pace:
                    t += wire_time_s(len(data), servo.baud())
                due.append((t, data))
        self._bus_free = t
        if self.pace:
            for when, data in due:
                if self._wait_until(when):
                    return
                self._write([data])
            return
        # Unpaced, replies already due are written together: every wait costs the host a
        # thread switch when it shares our interpreter (tests), so waits shorter than
        # _MIN_WAIT_S are skipped.
        pending: list[bytes] = []
        for when, data in due:
            remaining = when - time.monotonic()
            if remaining > _MIN_WAIT_S:
                if pending:
                    self._write(pending)
                    pending = []
                if self._stop.wait(remaining):
                    return
            pending.append(data)
        if pending:
            self._write(pending)

    def _wait_until(self, deadline: float) -> bool:
        """Wait until ``time.monotonic()`` reaches ``deadline``; ``True`` if stopped meanwhile.

        Sleeps (on the stop event when long, else in ``select``) until _SPIN_S before the
        deadline, then spins: a test device's pacing, bounded to ~_SPIN_S of busy waiting.
        """
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= _SPIN_S:
                break
            if remaining > _PROMPT_WAIT_S:
                if self._stop.wait(remaining - _SPIN_S):
                    return True
            else:
                select.select([], [], [], remaining - _SPIN_S)
        while time.monotonic() < deadline:
            pass
        return self._stop.is_set()

    def _consume_drop(self, s: EmulatedServo) -> bool:
        if s.silent:
            return True
        if s.drop > 0:
            s.drop -= 1
            return True
        return False

    def _consume_corrupt(self, s: EmulatedServo) -> bool:
        if s.corrupt > 0:
            s.corrupt -= 1
            return True
        return False

    def _write(self, replies: list[bytes]) -> None:
        data = b"".join(replies)
        try:
            written = os.write(self._master, data)
        except BlockingIOError:
            written = 0  # nobody reads the slave and its buffer is full: the bytes are lost
        except OSError:
            return
        self.bytes_dropped += len(data) - written
        if written:
            self.replies_sent += len(replies)


_GROUP = frozenset(
    {
        Instruction.SYNC_READ,
        Instruction.SYNC_WRITE,
        Instruction.FAST_SYNC_READ,
        Instruction.BULK_READ,
        Instruction.BULK_WRITE,
        Instruction.FAST_BULK_READ,
    }
)


# -- command line ---------------------------------------------------------------------------------


def parse_ids(text: str) -> list[int]:
    """``"1-6"``, ``"1,3,5"``, ``"1-3,7"`` -> a list of ids (the emulators' shared syntax).

    Raises:
        ValueError: malformed text, ids out of 0..252 or duplicated.
    """
    return emulation_cli.parse_ids(text, valid=range(253))


def build_parser() -> argparse.ArgumentParser:
    """The ``jtc-hw emulate dynamixel`` argument parser."""
    p = argparse.ArgumentParser(
        prog="jtc-hw emulate dynamixel",
        description="Emulated Dynamixel X-series servos (Protocol 2.0) on a pseudo-terminal. "
        "Prints the device path, then serves until SIGINT/SIGTERM.",
    )
    p.add_argument("--ids", default="1", help="servo ids, e.g. 1-6 or 1,2,5-7 (default 1)")
    p.add_argument("--model", default="XM430-W350", help="servo model (default XM430-W350)")
    p.add_argument(
        "--baud", type=int, default=4_000_000, help="servo baud rate, bit/s (default 4000000)"
    )
    p.add_argument(
        "--pace",
        action="store_true",
        help="hold replies back to the wire time of a real bus at that baud rate",
    )
    p.add_argument("--link", default=None, help="also create this symlink to the pty")
    p.add_argument(
        "--stats",
        choices=("live", "exit"),
        default="live",
        help="packet statistics on stderr: live (a line whenever they changed, at most 5 a "
        "second; the default) or exit (one line when it stops: a terminal that shows "
        "something else meanwhile, such as the demo's progress bar, stays readable)",
    )
    p.add_argument(
        "--firmware",
        type=int,
        default=None,
        help=f"Firmware Version the servos report (default: the model's; below "
        f"{BUS_WATCHDOG_FIRMWARE}: no Bus Watchdog)",
    )
    p.add_argument(
        "--return-delay-us",
        type=float,
        default=None,
        help="Return Delay Time in us (default: the servo's, 500)",
    )
    p.add_argument(
        "--priority",
        type=int,
        default=None,
        metavar="N",
        help=f"SCHED_FIFO priority of the process, 1..99, 0: normal scheduling (default: "
        f"{DEFAULT_PRIORITY} where permitted, so that a busy host does not delay the replies "
        "as it would never delay real servos)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the emulator from the command line; 0 on a clean stop, 2 on bad options."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.priority is not None and not 0 <= args.priority <= 99:
        parser.error(f"--priority must be 0..99, got {args.priority}")
    # Before the serving thread starts: it inherits the policy. A normally scheduled emulator
    # missed the daemon's 20 ms ping at configure on a busy machine (issue 22).
    refused = realtime_priority(DEFAULT_PRIORITY if args.priority is None else args.priority,
                                whole_process=True)
    if refused is not None and args.priority is not None:  # asked for: say it was not given
        print(f"jtc-hw emulate dynamixel: {refused}", file=sys.stderr)
    try:
        ids = parse_ids(args.ids)
        emulator = DynamixelEmulator(
            ids,
            args.model,
            baud=args.baud,
            pace=args.pace,
            link=args.link,
            return_delay_us=args.return_delay_us,
            firmware_version=args.firmware,
        )
    except (ValueError, KeyError) as exc:
        print(f"jtc-hw emulate dynamixel: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with emulator:
            print(emulator.device_path, flush=True)
            print(
                f"serving {len(ids)} x {emulator.model.name} (ids {args.ids}) at {args.baud} "
                f"bit/s{' paced' if args.pace else ''} on {emulator.slave_path}",
                file=sys.stderr,
                flush=True,
            )
            last: dict[str, int] = {}
            reported: set[tuple[int, float]] = set()
            while not stop.wait(0.2):
                stats = emulator.stats()
                if stats != last and args.stats == "live":
                    print(
                        " ".join(f"{k}={v}" for k, v in stats.items()), file=sys.stderr, flush=True
                    )
                    last = stats
                # One JSON line per Bus Watchdog trip once the servo is at rest, for a tool in
                # another process (times: CLOCK_MONOTONIC, shared by the machine's processes).
                for trip in emulator.watchdog_trips():
                    key = (trip.servo_id, trip.expired_s)
                    if trip.stopped_s is not None and key not in reported:
                        reported.add(key)
                        print("watchdog " + json.dumps(dataclasses.asdict(trip)),
                              file=sys.stderr, flush=True)
            if args.stats == "exit":
                print(" ".join(f"{k}={v}" for k, v in emulator.stats().items()),
                      file=sys.stderr, flush=True)
    except OSError as exc:
        print(f"jtc-hw emulate dynamixel: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


if __name__ == "__main__":
    sys.exit(main())
