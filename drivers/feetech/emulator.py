"""A bus of emulated Feetech servos (STS/SMS or SCS) on a pseudo-terminal.

Theory of operation
-------------------
:class:`FeetechEmulator` serves the slave side of a pty (``/dev/pts/N``, or a symlink to it)
to any host speaking Feetech's serial protocol: ``scservo_sdk`` (as LeRobot uses it), our
driver, a terminal tool. The pty, the serving thread, the wire-time pacing and the command
line's frame are :mod:`~jtc_hw.drivers.pty_emulator`'s (shared with the Dynamixel emulator);
this module decodes instruction packets with :class:`.codec.Decoder` and answers each as the
addressed servos (:class:`~jtc_hw.drivers.feetech.servo.EmulatedServo`) would::

    host:   FF FF | ID | LEN | INST   | PARAMS... | CHECKSUM
    servo:  FF FF | ID | LEN | STATUS | DATA...   | CHECKSUM    (after its return delay)

- PING, READ, WRITE, REG_WRITE + ACTION, SYNC_WRITE, and SYNC_READ on STS/SMS. A broadcast
  (id 0xFE) is obeyed by every servo and answered by none, except a broadcast PING (every
  STS/SMS servo answers, in id order) and SYNC_READ (each listed servo answers in the listed
  order, each after the previous one, as on a real bus; an id nobody has is skipped).
- SCS servos know no SYNC_READ and do not answer a broadcast PING (LeRobot ``feetech.py``:
  "'Sync Read' is not available with Feetech motors using Protocol 1", likewise "Broadcast
  Ping"): such a packet goes unanswered, as the real servos leave it.
- Response Status Level (8): 0 answers only PING and READ (and SYNC_READ), 1 everything (the
  STS memory table's description). The status byte is the servo's Status (65) bits.
- A packet with a bad checksum is not answered: the status byte has no checksum bit (bit 4 is
  unused, :class:`.codec.StatusError`), so a servo cannot say it; it is counted
  (``checksum_errors``). Instructions the servos do not know (Feetech's RESET / RECOVERY,
  which restore factory settings, among them) go unanswered too (emulator choice: the
  emulator never forgets its ids).
- A status answers from the id the instruction addressed, even when that instruction changed
  the servo's id (emulator choice); the next packets must use the new id.
- Timing: each reply waits the servo's Return Delay Time (7, 2 us units; factory 500 us) and,
  paced, the wire time at the servo's Baud Rate register (10 bits a byte). The command line
  paces by default (``--no-pace`` to answer as soon as due); the class does not unless
  ``pace=True``, for hosts in the same interpreter (tests).

Why the host's timeout matters here: the PyPI SDK allows the wire time of the expected status
bytes plus ``2 * LATENCY_TIMER + 2`` = 34 ms for a reply, measured with ``time.time()`` from
when ``writePort`` returned (``port_handler.py``), and LeRobot patches it to the wire time plus
50 ms (``patch_setPacketTimeout``; :mod:`.control_table` says what Feetech's own fix does). On a
pty nothing waits for a USB adapter, so the emulator's replies come well inside either
allowance when it is scheduled on time, which its SCHED_FIFO priority (the command line's
default) sees to on a busy host. The host's side is another matter: ``rxPacket`` checks the
deadline after an empty read and before reading again, so an SDK thread descheduled for longer
than the allowance reports ``COMM_RX_TIMEOUT`` for a reply that has arrived (seen once in ten
runs of the acceptance test with 50 ms, its test process normally scheduled beside busy ones).
A timeout against the emulator is therefore not proof that a servo was silent; what the
emulator did is in its counters and its protection events.

Faults for tests (all thread-safe): :meth:`~FeetechEmulator.set_silent`,
:meth:`~FeetechEmulator.drop_replies`, :meth:`~FeetechEmulator.delay_replies`,
:meth:`~FeetechEmulator.corrupt_checksum`, :meth:`~FeetechEmulator.block` (an obstacle: the
servo's torque builds until its overload protection), :meth:`~FeetechEmulator.set_temperature`
(overheat), :meth:`~FeetechEmulator.set_supply_voltage`,
:meth:`~FeetechEmulator.set_angle_fault` and :meth:`~FeetechEmulator.power_cycle` (what the
EPROM lock kept). A test plays the user's hand with :meth:`~FeetechEmulator.turn_by_hand` (a
servo with its torque off, as ``jtc-hw calibrate feetech`` asks the user to move them).
Protections entered are recorded with the emulator's clock
(:meth:`~FeetechEmulator.protection_events`, :meth:`~FeetechEmulator.wait_protection`); the
command line prints each as a JSON line ``protection {...}`` on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from collections.abc import Mapping, Sequence

from ..pty_emulator import PtyBusEmulator, bus_parser, faulted, run_emulator
from .codec import (
    BROADCAST_ID,
    Decoder,
    Instruction,
    Packet,
    StatusError,
    encode_status,
    parse_read,
    parse_sync_read,
    parse_sync_write,
    parse_write,
    status_error_text,
)
from .control_table import BAUD_RATES, EEPROM_END, model_by_name
from .servo import EmulatedServo, ProtectionEvent

__all__ = ["FeetechEmulator", "build_parser", "main"]

_Reply = tuple[EmulatedServo, bytes]
#: The instructions answered at Response Status Level 0.
_ALWAYS_ANSWERED = frozenset({Instruction.PING, Instruction.READ, Instruction.SYNC_READ})


class FeetechEmulator(PtyBusEmulator[Packet, EmulatedServo]):
    """One bus of emulated Feetech servos on a pseudo-terminal (see the module docstring).

    Args:
        ids: the servo ids (0..253), all of ``model``.
        model: the servo model's name (``control_table.MODELS``: STS3215, STS3250, SCS0009).
        baud: the servos' baud rate in bit/s (a value of ``control_table.BAUD_RATES``).
        pace: hold replies back so that requests and replies take their wire time.
        link: a path to create as a symlink to the pty slave (an existing symlink is replaced).
        initial_positions: id -> Present Position, steps (default: mid-range, 2048 or 512).
        return_delay_us: initial Return Delay Time, us (default: the servo's, 500 us).
        supply_v: the supply voltage the servos read (default: the model's nominal).

    Raises:
        ValueError: bad ids or baud rate.
        KeyError: unknown model (``UnknownModelError``).
    """

    def __init__(self, ids: Sequence[int], model: str = "STS3215", *, baud: int = 1_000_000,
                 pace: bool = False, link: str | None = None,
                 initial_positions: Mapping[int, int] | None = None,
                 return_delay_us: float | None = None, supply_v: float | None = None) -> None:
        ids = list(ids)
        if not ids or any(not 0 <= i < BROADCAST_ID for i in ids) or len(set(ids)) != len(ids):
            raise ValueError(f"ids must be distinct values in 0..253, got {ids}")
        values = {bps: v for v, bps in BAUD_RATES.items()}
        if baud not in values:
            raise ValueError(f"Feetech servos do not support {baud} bit/s; choose one of "
                             f"{sorted(values)}")
        self.model = model_by_name(model)
        super().__init__(baud=baud, pace=pace, link=link, thread_name="feetech-emulator")
        # Signalled (under the lock) when a servo enters a protection: wait_protection().
        self._changed = threading.Condition(self._lock)
        positions = dict(initial_positions or {})
        middle = (self.model.position_max + 1) // 2
        now = time.monotonic()
        self._servos = [
            EmulatedServo(self.model, i, positions.get(i, middle), now, supply_v,
                          self._changed.notify_all)
            for i in ids
        ]
        for s in self._servos:
            s.set("baud_rate", values[baud])
            if return_delay_us is not None:
                s.set("return_delay_time", max(0, min(254, round(return_delay_us / 2.0))))
            s.stored = bytes(s.memory[:EEPROM_END])  # the factory settings of this bus
        self._decoder = Decoder(status=False)

    def describe(self) -> str:
        return f"{len(self._servos)} x {self.model.name}"

    # -- observation ------------------------------------------------------------------------------

    def positions(self) -> dict[int, int]:
        """id -> Present Position, steps, now."""
        with self._lock:
            self._step_servos(time.monotonic())
            return {s.id: s.present_steps() for s in self._servos}

    def stored_register(self, servo_id: int, name: str) -> int:
        """What register ``name`` (EEPROM) of servo ``servo_id`` would read after a power cycle.

        Raises:
            KeyError: unknown servo or register.
        """
        with self._lock:
            return self._servo(servo_id).stored_value(name)

    def protection_events(self, since_s: float = -math.inf) -> list[ProtectionEvent]:
        """Every protection a servo entered at or after ``since_s`` (``time.monotonic()``)."""
        with self._lock:
            self._step_servos(time.monotonic())  # an overload due by now is recorded
            events = [e for s in self._servos for e in s.events if e.at_s >= since_s]
        return sorted(events, key=lambda e: (e.at_s, e.servo_id))

    def wait_protection(
        self, servo_id: int, error: StatusError, timeout_s: float, since_s: float = -math.inf
    ) -> ProtectionEvent:
        """Block until servo ``servo_id`` enters protection ``error`` (at or after ``since_s``);
        the first such event.

        Raises:
            KeyError: unknown servo.
            TimeoutError: it did not within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        with self._lock:
            s = self._servo(servo_id)
            while True:
                now = time.monotonic()
                s.step(now)
                for event in s.events:
                    if event.error & error and event.at_s >= since_s:
                        return event
                if now >= deadline:
                    raise TimeoutError(f"servo {servo_id} entered no {error!r} protection "
                                       f"within {timeout_s:g} s (events: {s.events})")
                self._changed.wait(min(deadline - now, 0.05))

    def _checksum_errors(self) -> tuple[str, int]:
        return "checksum_errors", self._decoder.checksum_errors

    # -- faults -----------------------------------------------------------------------------------

    def corrupt_checksum(self, servo_id: int, count: int) -> None:
        """Servo ``servo_id`` sends its next ``count`` replies with a wrong checksum.

        Raises:
            KeyError: unknown servo.
        """
        self._corrupt_replies(servo_id, count)

    def block(self, servo_id: int, blocked: bool = True) -> None:
        """An obstacle holds servo ``servo_id``'s shaft (or lets it go): a goal away from it
        makes the torque rise to its limit, and after Protection Time the overload protection
        switches the torque off (see the servo module).

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo_now(servo_id).blocked = bool(blocked)

    def set_temperature(self, servo_id: int, celsius: float) -> None:
        """Servo ``servo_id``'s temperature reads ``celsius`` from now on; above Max
        Temperature Limit (70 degC by default) it overheats and unloads.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo(servo_id).set_temperature(celsius, time.monotonic())

    def set_supply_voltage(self, servo_id: int, volts: float | None) -> None:
        """Servo ``servo_id``'s supply reads ``volts`` from now on (``None``: nominal).

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            s = self._servo(servo_id)
            s.set_supply(s.physics.nominal_voltage_v if volts is None else volts,
                         time.monotonic())

    def set_angle_fault(self, servo_id: int, fault: bool) -> None:
        """Servo ``servo_id``'s position sensor reports a fault (the angle bit) while ``fault``.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo_now(servo_id).set_angle_fault(fault)

    def power_cycle(self, servo_id: int) -> None:
        """Switch servo ``servo_id`` off and on: what the EPROM lock let it store survives.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo(servo_id).power_cycle(time.monotonic())

    def turn_by_hand(self, servo_id: int, shaft_steps: int) -> None:
        """Turn servo ``servo_id``'s shaft by hand to ``shaft_steps`` (what Present Position
        reads with no homing offset), at rest: the user's hand during a calibration.

        Raises:
            KeyError: unknown servo.
            RuntimeError: its torque is on: a hand cannot turn a servo holding its goal (switch
                the torque off first, as a calibration must).
        """
        with self._lock:
            s = self._servo_now(servo_id)
            if s.torque_on:
                raise RuntimeError(f"servo {servo_id} holds its position (torque on): switch "
                                   "its torque off before turning it by hand")
            s.motor.position = float(shaft_steps) * s.model.rad_per_step
            s.motor.velocity = 0.0
            s.motor.reset_reference()
            s.stale = True

    # -- serving ----------------------------------------------------------------------------------

    def _handle(self, packet: Packet, arrival: float, first_byte: float) -> None:
        with self._lock:
            self._step_servos(arrival)
            self._last_step = arrival
            if not packet.checksum_ok:
                replies: list[_Reply] = []
            else:
                self.packets_served += 1
                replies = self._dispatch(packet, arrival)
            self.errors_sent += sum(1 for _, data in replies if data[4])
            bus_baud = self._servo_baud(replies[0][0]) if replies else self._baud
            timed = [(s.return_delay_s() + s.delay_s, data, self._servo_baud(s))
                     for s, data in faulted(replies)]
        if replies:
            start = first_byte if self.pace else arrival
            self._send(self._schedule(start, len(packet.raw), bus_baud, timed))
        else:
            self._hold_bus(first_byte, len(packet.raw))

    def _servo_baud(self, s: EmulatedServo) -> int:
        return BAUD_RATES.get(s.get("baud_rate"), self._baud)

    def _dispatch(self, p: Packet, now: float) -> list[_Reply]:
        """Execute ``p``; the status packets to send, in order."""
        series = self.model.series
        inst, params = p.code, p.params
        broadcast = p.id == BROADCAST_ID
        targets = (sorted(self._servos, key=lambda s: s.id) if broadcast
                   else [s for s in self._servos if s.id == p.id])
        try:
            if inst == Instruction.SYNC_READ:
                if not (series.sync_read and broadcast):
                    return []
                address, length, ids = parse_sync_read(params)
                by_id = {s.id: s for s in self._servos}
                return [self._status(by_id[i], i, by_id[i].read(address, length))
                        for i in ids if i in by_id]
            if inst == Instruction.SYNC_WRITE:
                if broadcast:
                    address, _, items = parse_sync_write(params)
                    for servo_id, data in items:
                        for s in self._servos:
                            if s.id == servo_id:
                                s.write(address, data, now)
                return []
            if inst == Instruction.PING and broadcast and not series.broadcast_ping:
                return []
            replies = [self._single(s, inst, params, now) for s in targets]
        except ValueError:  # malformed parameters: nobody answers
            return []
        if broadcast and inst != Instruction.PING:
            return []
        return [r for r in replies if r is not None]

    def _single(self, s: EmulatedServo, inst: int, params: bytes, now: float) -> _Reply | None:
        """Execute a one-servo instruction; its status packet, or ``None`` for no answer."""
        servo_id, level = s.id, s.get("response_status_level")
        data = b""
        if inst == Instruction.PING:
            pass
        elif inst == Instruction.READ:
            address, length = parse_read(params)
            data = s.read(address, length)
        elif inst == Instruction.WRITE:
            address, payload = parse_write(params)
            s.write(address, payload, now)
        elif inst == Instruction.REG_WRITE:
            s.registered = parse_write(params)
        elif inst == Instruction.ACTION:
            if s.registered is not None:
                address, payload = s.registered
                s.registered = None
                s.write(address, payload, now)
        else:
            return None  # an instruction the servos do not know
        if level == 0 and inst not in _ALWAYS_ANSWERED:
            return None
        return self._status(s, servo_id, data)

    def _status(self, s: EmulatedServo, servo_id: int, data: bytes = b"") -> _Reply:
        s.refresh()
        return s, encode_status(servo_id, s.status, data)


# -- command line ---------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """The ``jtc-hw emulate feetech`` argument parser."""
    p = bus_parser("jtc-hw emulate feetech", "Emulated Feetech STS/SMS or SCS servos "
                   "(LeRobot's SO-100/SO-101 arm: six STS3215) on a pseudo-terminal.",
                   model="STS3215", baud=1_000_000, return_delay="500", paced=True)
    p.add_argument("--supply-v", type=float, default=None,
                   help="the supply voltage the servos read, V (default: the model's nominal)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the emulator from the command line; 0 on a clean stop, 2 on bad options."""
    parser = build_parser()
    args = parser.parse_args(argv)

    def make(ids: list[int]) -> FeetechEmulator:
        return FeetechEmulator(ids, args.model, baud=args.baud, pace=args.pace, link=args.link,
                               return_delay_us=args.return_delay_us, supply_v=args.supply_v)

    reported = 0

    def report_protections(emulator: FeetechEmulator) -> None:
        # One JSON line per protection entered, for a tool in another process (times:
        # CLOCK_MONOTONIC, shared by the machine's processes).
        nonlocal reported
        events = emulator.protection_events()
        for e in events[reported:]:
            line = {"servo_id": e.servo_id, "error": status_error_text(e.error),
                    "at_s": e.at_s, "torque_off": e.torque_off}
            print("protection " + json.dumps(line), file=sys.stderr, flush=True)
        reported = len(events)

    return run_emulator(parser, args, make, valid_ids=range(BROADCAST_ID),
                        tick=report_protections)


if __name__ == "__main__":
    sys.exit(main())
