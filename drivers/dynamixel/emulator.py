"""A bus of emulated Dynamixel X-series servos on a pseudo-terminal (Protocol 2.0).

Theory of operation
-------------------
:class:`DynamixelEmulator` opens a pty pair and serves the slave side (``/dev/pts/N``, or a
symlink to it) to any Protocol 2.0 host: the official SDK, our driver, a terminal tool. One thread
waits on the master side with ``select`` (so :meth:`~DynamixelEmulator.close` is prompt), feeds
the bytes to the shared :class:`~jtc_hw.drivers.dynamixel.packets.Decoder` and answers each
instruction packet as the addressed servos would (the pty, the serving thread, the pacing and
the command line's frame are :mod:`~jtc_hw.drivers.pty_emulator`'s, shared with the Feetech
emulator):

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
import dataclasses
import json
import math
import sys
import threading
import time
from collections.abc import Iterable, Mapping, Sequence

from .. import emulation_cli
from ..pty_emulator import (
    IDLE_STEP_S,
    PtyBusEmulator,
    bus_parser,
    corrupt_last_byte,
    faulted,
    run_emulator,
)
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
)
from .servo import EmulatedServo, WatchdogTrip

__all__ = ["DynamixelEmulator", "build_parser", "main", "parse_ids"]

#: CLEAR's fixed parameters (option 0x01 "clear multi-turn" and the "DXL" key + 0x22).
_CLEAR_MULTI_TURN = bytes((0x01, 0x44, 0x58, 0x4C, 0x22))

@dataclasses.dataclass
class _Reply:
    servo: EmulatedServo
    data: bytes


class DynamixelEmulator(PtyBusEmulator[Packet, EmulatedServo]):
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
        super().__init__(baud=baud, pace=pace, link=link, thread_name="dxl-emulator")
        self.reboot_time_s = reboot_time_s
        positions = dict(initial_positions or {})
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
        self._decoder = Decoder()

    # -- observation and faults ---------------------------------------------------------------

    def positions(self) -> dict[int, float]:
        """id -> Present Position in rad (``present_position * 2*pi / ticks_per_rev``), now."""
        with self._lock:
            self._step_servos(time.monotonic())
            return {s.id: self.model.ticks_to_rad(s.present_ticks()) for s in self._servos}

    def corrupt_crc(self, servo_id: int, count: int) -> None:
        """Servo ``servo_id`` sends its next ``count`` replies with a wrong CRC.

        Raises:
            KeyError: unknown servo.
        """
        self._corrupt_replies(servo_id, count)

    def raise_hardware_error(self, servo_id: int, bits: HardwareError) -> None:
        """Latch hardware error ``bits`` on servo ``servo_id`` until it is rebooted.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            s = self._servo_now(servo_id)
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
            s = self._servo_now(servo_id)
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
            s = self._servo_now(servo_id)
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
                # The serving thread steps the servos at least every IDLE_STEP_S and notifies
                # on every trip and stop; the bounded wait also steps them itself.
                self._changed.wait(min(remaining, 10 * IDLE_STEP_S))

    def last_instruction_s(self, servo_id: int) -> float:
        """When servo ``servo_id`` last received an instruction packet (its id or broadcast,
        good CRC, awake), ``time.monotonic()``.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            return self._servo(servo_id).last_instruction

    def _checksum_errors(self) -> tuple[str, int]:
        return "crc_errors", self._decoder.crc_errors

    @property
    def crc_errors(self) -> int:
        """Instruction packets received with a bad CRC."""
        return self._decoder.crc_errors

    # -- serving ------------------------------------------------------------------------------

    def describe(self) -> str:
        return f"{len(self._servos)} x {self.model.name}"

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
        else:
            self._hold_bus(first_byte, len(packet.raw))

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
        chunks: list[tuple[EmulatedServo, bytes]]
        if fast:
            chunks = []
            with self._lock:
                entries = [(r.servo.id, r.data[0], r.data[1:]) for r in fast]
                parts = fast_status_parts(entries)
                for r, part in zip(fast, parts, strict=True):
                    if r.servo.take_drop():
                        break
                    chunks.append((r.servo, part))
                if any([servo.take_corrupt() for servo, _ in chunks]):
                    servo, last = chunks[-1]
                    chunks[-1] = (servo, corrupt_last_byte(last))
        else:
            with self._lock:
                chunks = faulted((r.servo, r.data) for r in replies)
        with self._lock:
            timed = [(servo.return_delay_s() + servo.delay_s, data, servo.baud())
                     for servo, data in chunks]
        self._send(self._schedule(start, len(request.raw), bus_baud, timed))


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
    p = bus_parser("jtc-hw emulate dynamixel", "Emulated Dynamixel X-series servos (Protocol "
                   "2.0) on a pseudo-terminal.", model="XM430-W350", baud=4_000_000,
                   return_delay="500")
    p.add_argument(
        "--firmware",
        type=int,
        default=None,
        help=f"Firmware Version the servos report (default: the model's; below "
        f"{BUS_WATCHDOG_FIRMWARE}: no Bus Watchdog)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the emulator from the command line; 0 on a clean stop, 2 on bad options."""
    parser = build_parser()
    args = parser.parse_args(argv)

    def make(ids: list[int]) -> DynamixelEmulator:
        return DynamixelEmulator(
            ids,
            args.model,
            baud=args.baud,
            pace=args.pace,
            link=args.link,
            return_delay_us=args.return_delay_us,
            firmware_version=args.firmware,
        )

    reported: set[tuple[int, float]] = set()

    def report_trips(emulator: DynamixelEmulator) -> None:
        # One JSON line per Bus Watchdog trip once the servo is at rest, for a tool in another
        # process (times: CLOCK_MONOTONIC, shared by the machine's processes).
        for trip in emulator.watchdog_trips():
            key = (trip.servo_id, trip.expired_s)
            if trip.stopped_s is not None and key not in reported:
                reported.add(key)
                print("watchdog " + json.dumps(dataclasses.asdict(trip)), file=sys.stderr,
                      flush=True)

    return run_emulator(parser, args, make, valid_ids=range(253), tick=report_trips)


if __name__ == "__main__":
    sys.exit(main())
