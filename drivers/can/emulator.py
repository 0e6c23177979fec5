"""MIT-mode motors emulated on a python-can bus, and the ``jtc-hw emulate can`` process.

Theory of operation
-------------------
:class:`MitBusEmulator` is a peer on a python-can bus (usually ``virtual``): it owns one
:class:`~jtc_hw.drivers.motor_model.Motor` per CAN id and one thread that receives frames,
decodes them with the shared codec (:mod:`jtc_hw.drivers.can.frames`) and answers every
frame addressed to one of its motors with a state reply, as the firmware does:

* a set-point frame: the motor's physics is advanced to now under the previous set-point
  (``Motor.step_pd`` in motor mode, ``Motor.coast`` otherwise), then the new set-point is
  taken;
* ``FC`` enters motor mode (the PD starts from the set-point kp = kd = t = 0, i.e. free
  until the first set-point), ``FD`` exits it (coasts), ``FE`` makes the current position
  zero, ``FB`` clears a Damiao error.

Wire-time pacing (``pace=True``): the emulator models the bus as one serial wire at
``bitrate``. A command occupies the wire from when it was sent (its python-can timestamp, not
when this thread got to it; or from when the wire frees up)
for :func:`~jtc_hw.drivers.can.bus.wire_time_s` of its bits; the reply follows it; the reply
is delivered only when its last bit would have arrived. Replies are computed when the command is
handled (before they are due) and kept in a due-time queue, so the thread sleeps only until
the next one is due, then only sends it; it wakes a little before (:class:`WakeEarly`) and spins the
rest, so that wake-up latency does not delay the release.

Fault injection (thread-safe setters): a silent motor, dropping the next N replies, delaying
replies, the drive temperature and a Damiao error code (``"damiao"`` reply format only: the
``"ak"`` reply has no fault field, so an AK "drive fault" is emulated as silence), and bus-off
(an error frame with ``CAN_ERR_BUSOFF``, then silence until :meth:`MitBusEmulator.clear_bus_off`).

``main(argv)`` runs emulators in a process, behind a socketcand server (default) so that other
processes reach them with python-can's stock ``socketcand`` interface, until SIGINT/SIGTERM.
With ``--one-thread`` the emulators start no threads (``start(push=True, thread=False)``; CiA
402 drives ``start(push=True)``): the server's single thread reads every client, the frames
reach the emulators in it, and it releases every bus's due replies (each emulator keeps its
own heap of due replies and its own wire, so the buses stay independent and concurrent). A
process serving several buses then keeps one busy thread: no interpreter lock to contend for,
no thread hand-over.
"""

from __future__ import annotations

import argparse
import heapq
import math
import signal
import sys
import threading
import time
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import can

from jtc_hw.hardware.timing import reduce_timer_slack

from ..motor_model import Motor, MotorParams
from .bus import CAN_ERR_BUSOFF, wire_time_s
from .emulation import PushSink, WakeEarly, attach_sink
from .frames import (
    MODEL_PRESETS,
    MitCommand,
    MitLimits,
    MitReply,
    decode_command,
    encode_reply,
    special_command,
)

__all__ = ["MitBusEmulator", "build_parser", "main", "parse_ids"]

_IDLE_POLL_S = 0.05  # how often an idle emulator thread looks at its stop flag


@dataclass
class _MotorSlot:
    motor: Motor
    limits: MitLimits
    enabled: bool = False
    command: MitCommand = MitCommand(0.0, 0.0, 0.0, 0.0, 0.0)
    t: float | None = None
    zero: float = 0.0
    silent: bool = False
    drop: int = 0
    delay_s: float = 0.0
    temperature: float = 30.0
    rotor_temperature: float = 30.0
    error_code: int = 0
    commands: int = 0
    replies: int = 0


class MitBusEmulator:
    """MIT-mode motors on one python-can bus (see the module docstring).

    Args:
        bus: the bus to answer on (the caller owns it and shuts it down after :meth:`stop`).
        ids: the motors' CAN ids (command arbitration ids; the id in replies).
        model: a :data:`~jtc_hw.drivers.can.frames.MODEL_PRESETS` name.
        limits: ranges overriding the model's.
        master_id: arbitration id of the replies.
        bitrate: bit/s, for pacing.
        pace: deliver replies no earlier than the wire would.
        motor_params: physics of every motor (default: torque / velocity limits from the
            model's ranges).
        initial_positions: ``{id: rad}``.

    Raises:
        ValueError: unknown model, or an id the reply format cannot carry.
    """

    def __init__(
        self,
        bus: can.BusABC,
        ids: Iterable[int],
        model: str = "AK80-9",
        *,
        limits: MitLimits | None = None,
        master_id: int = 0,
        bitrate: int = 1_000_000,
        pace: bool = False,
        motor_params: MotorParams | None = None,
        initial_positions: Mapping[int, float] | None = None,
    ) -> None:
        if limits is None:
            if model not in MODEL_PRESETS:
                raise ValueError(f"unknown MIT model {model!r}; known: {', '.join(MODEL_PRESETS)}")
            limits = MODEL_PRESETS[model]
        self.bus = bus
        self.limits = limits
        self.master_id = master_id
        self.bitrate = bitrate
        self.pace = pace
        # 0.5 ms sub-steps: semi-implicit Euler stays stable for the MIT gains' range on
        # the default inertia, at a quarter of the cost of the default 0.2 ms.
        params = motor_params or MotorParams(
            torque_limit=limits.t_max, velocity_limit=limits.v_max, max_step_s=0.0005
        )
        initial = dict(initial_positions or {})
        self._slots: dict[int, _MotorSlot] = {}
        for motor_id in ids:
            top = 0xFF if limits.reply == "ak" else 0x0F
            if not 1 <= motor_id <= min(top, 0x7FF):
                raise ValueError(f"motor id {motor_id} out of range 1..{top} for this model")
            self._slots[motor_id] = _MotorSlot(Motor(params, initial.get(motor_id, 0.0)), limits)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)  # push mode: a new earliest due reply
        self._push = False
        self._early = WakeEarly()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bus_off = False
        self._wire_free = 0.0
        self._due: list[tuple[float, int, can.Message]] = []
        self._seq = 0
        self.frames_received = 0
        self.replies_sent = 0
        self.tx_failures = 0
        self.error: BaseException | None = None

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self, push: bool = False, thread: bool = True) -> None:
        """Start answering (one daemon thread).

        Args:
            push: the bus is a python-can ``virtual`` bus whose frames should be handled in
                the sending peer's thread (see :meth:`_on_frame`), the thread only
                releasing the due replies: one thread hand-over less per frame. Used by
                ``jtc-hw emulate can`` behind its socketcand server.
            thread: ``False`` (push mode only): start no thread; the caller releases the
                due replies (:meth:`next_due`, :meth:`release_due`: a one-thread
                socketcand server's timer).

        Raises:
            ValueError: ``push`` with a bus that is not a python-can virtual bus, or no
                thread without ``push``.
        """
        if self._thread is not None:
            return
        if not thread and not push:
            raise ValueError("an emulator without a thread needs push mode")
        if push and not self._push:
            try:
                attach_sink(self.bus, PushSink(self._on_frame))
            except (AttributeError, ValueError) as exc:
                raise ValueError(f"push mode needs a python-can virtual bus ({exc})") from exc
            self._push = True
        self._stop.clear()
        if not thread:
            return
        self._thread = threading.Thread(target=self._run, name="mit-emulator", daemon=True)
        self._thread.start()

    def next_due(self) -> float | None:
        """The monotonic time the next reply is due (``None``: none pending)."""
        with self._lock:
            return self._due[0][0] if self._due else None

    def release_due(self, now: float) -> None:
        """Send every reply due at or before ``now`` (monotonic)."""
        self._deliver_due(now)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop answering and join the thread (the bus stays open)."""
        self._stop.set()
        with self._wake:
            self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def __enter__(self) -> MitBusEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- inspection ---------------------------------------------------------------------------

    @property
    def ids(self) -> tuple[int, ...]:
        """The emulated motor ids."""
        return tuple(self._slots)

    def position(self, motor_id: int) -> float:
        """The motor's position (rad, relative to its zero), physics advanced to now."""
        with self._lock:
            slot = self._slots[motor_id]
            self._advance(slot, time.monotonic())
            return slot.motor.position - slot.zero

    def enabled(self, motor_id: int) -> bool:
        """Whether the motor is in motor mode."""
        with self._lock:
            return self._slots[motor_id].enabled

    def last_command(self, motor_id: int) -> MitCommand:
        """The last set-point the motor decoded."""
        with self._lock:
            return self._slots[motor_id].command

    def commands(self, motor_id: int) -> int:
        """How many frames the motor received."""
        with self._lock:
            return self._slots[motor_id].commands

    def set_position(self, motor_id: int, position: float) -> None:
        """Move the joint (by hand), at rest."""
        with self._lock:
            slot = self._slots[motor_id]
            slot.motor.position = position + slot.zero
            slot.motor.velocity = 0.0
            slot.motor.reset_reference()

    # -- fault injection ----------------------------------------------------------------------

    def set_silent(self, motor_id: int, silent: bool = True) -> None:
        """The motor stops (or resumes) answering."""
        with self._lock:
            self._slots[motor_id].silent = silent

    def drop_replies(self, motor_id: int, count: int) -> None:
        """Drop the motor's next ``count`` replies."""
        with self._lock:
            self._slots[motor_id].drop = count

    def set_reply_delay(self, motor_id: int, delay_s: float) -> None:
        """Deliver the motor's replies ``delay_s`` late."""
        with self._lock:
            self._slots[motor_id].delay_s = delay_s

    def set_temperature(self, motor_id: int, degc: float) -> None:
        """The drive temperature reported (Damiao replies)."""
        with self._lock:
            self._slots[motor_id].temperature = degc

    def set_error(self, motor_id: int, code: int) -> None:
        """Raise a Damiao error code (8..14): the drive switches off and reports it; an AK
        motor, whose reply has no fault field, goes silent instead (0 clears either)."""
        with self._lock:
            slot = self._slots[motor_id]
            slot.error_code = code
            if code >= 8:
                slot.enabled = False
            if self.limits.reply == "ak":
                slot.silent = code >= 8

    def bus_off(self) -> None:
        """Send a bus-off error frame and go silent until :meth:`clear_bus_off`."""
        with self._lock:
            self._bus_off = True
        self.bus.send(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True,
                                  is_extended_id=True, data=bytes(8)))

    def clear_bus_off(self) -> None:
        """Answer again after :meth:`bus_off`."""
        with self._lock:
            self._bus_off = False

    # -- the thread ---------------------------------------------------------------------------

    def _run(self) -> None:
        if self.pace:
            # Replies are due at exact times: without this, Linux may wake us 50 us late.
            reduce_timer_slack()
        try:
            if self._push:
                self._release_loop()
                return
            while not self._stop.is_set():
                now = time.monotonic()
                self._deliver_due(now)
                with self._lock:
                    next_due = self._due[0][0] if self._due else None
                if next_due is not None and next_due - now <= self._early.early_s:
                    # The reply is ready; hold it until its modelled time (see WakeEarly).
                    self._early.spin_until(next_due)
                    continue
                timeout = min(_IDLE_POLL_S, _IDLE_POLL_S if next_due is None
                              else next_due - now - self._early.early_s)
                msg = self.bus.recv(timeout=timeout)
                if msg is not None:
                    self._handle(msg, self._sent_at(msg))
                elif next_due is not None:
                    self._early.observe(now + timeout, time.monotonic())
        except Exception as exc:  # noqa: BLE001 - reported through .error, test sees it
            self.error = exc

    def _release_loop(self) -> None:
        """Push mode: frames are handled by :meth:`_on_frame`; this thread only sends the
        replies at their due time."""
        while not self._stop.is_set():
            with self._wake:
                next_due = self._due[0][0] if self._due else None
                now = time.monotonic()
                wait = _IDLE_POLL_S if next_due is None else (
                    next_due - now - self._early.early_s)
                if wait > 0.0:
                    wait = min(wait, _IDLE_POLL_S)
                    if not self._wake.wait(wait) and next_due is not None:
                        self._early.observe(now + wait, time.monotonic())
                    continue
            assert next_due is not None
            self._early.spin_until(next_due)  # within WakeEarly.early_s of it
            self._deliver_due(time.monotonic())

    def _on_frame(self, msg: can.Message) -> None:
        """Push mode: a frame on the bus, handled in the sender's thread."""
        try:
            self._handle(msg, self._sent_at(msg))
        except Exception as exc:  # noqa: BLE001 - reported through .error, test sees it
            self.error = exc

    @staticmethod
    def _sent_at(msg: can.Message) -> float:
        """When the frame was sent, on the monotonic clock.

        python-can stamps received frames with the wall clock at the sender's ``send`` (virtual)
        or at reception by the interface (socketcan, socketcand): that is when the frame went on
        the wire, earlier than when this thread got to it. Only the frame's age is taken from
        the wall clock (bounded to [0, 50 ms], so a clock step cannot move it far).
        """
        now = time.monotonic()
        if not msg.timestamp:
            return now
        age = min(max(time.time() - msg.timestamp, 0.0), 0.05)
        return now - age

    def _deliver_due(self, now: float) -> None:
        while True:
            with self._lock:
                if not self._due or self._due[0][0] > now:
                    return
                _, _, reply = heapq.heappop(self._due)
            self._send(reply)

    def _advance(self, slot: _MotorSlot, now: float) -> None:
        if slot.t is not None and now > slot.t:
            dt = now - slot.t
            c = slot.command
            if slot.enabled:
                slot.motor.step_pd(dt, c.position + slot.zero, c.velocity, c.kp, c.kd, c.torque)
            else:
                slot.motor.coast(dt)
        slot.t = now

    def _handle(self, msg: can.Message, now: float) -> None:
        if msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame:
            return
        self.frames_received += 1
        with self._lock:
            slot = self._slots.get(msg.arbitration_id)
            if slot is None or len(msg.data) != 8:
                return
            self._advance(slot, now)
            slot.commands += 1
            kind = special_command(msg.data)
            if kind == "enter":
                if slot.error_code < 8:
                    slot.enabled = True
                    slot.command = MitCommand(slot.motor.position - slot.zero, 0.0, 0.0, 0.0, 0.0)
            elif kind == "exit":
                slot.enabled = False
            elif kind == "zero":
                slot.zero = slot.motor.position
            elif kind == "clear_error":
                slot.error_code = 0
            else:
                slot.command = decode_command(msg.data, self.limits)
            if self._bus_off or slot.silent:
                return
            if slot.drop > 0:
                slot.drop -= 1
                return
            reply = self._reply(msg.arbitration_id, slot)
            due = now
            if self.pace:
                start = max(now, self._wire_free)
                self._wire_free = start + wire_time_s((msg, reply), self.bitrate)
                due = self._wire_free
            due += slot.delay_s
            slot.replies += 1
            if due <= now:
                immediate = True
            else:
                immediate = False
                self._seq += 1
                heapq.heappush(self._due, (due, self._seq, reply))
                if self._push and self._due[0][1] == self._seq:
                    self._wake.notify()  # the release thread waits for a later one
        if immediate:
            self._send(reply)

    def _send(self, reply: can.Message) -> None:
        try:
            self.bus.send(reply, timeout=0.0)
        except can.CanOperationError:
            self.tx_failures += 1  # a full transmit queue: the frame is lost, as on a wire
        else:
            self.replies_sent += 1

    def _reply(self, motor_id: int, slot: _MotorSlot) -> can.Message:
        m = slot.motor
        state = MitReply(
            motor_id,
            m.position - slot.zero,
            m.velocity,
            m.torque if slot.enabled else 0.0,
            error_code=(slot.error_code if slot.error_code else (1 if slot.enabled else 0)),
            temperature=round(slot.temperature),
            rotor_temperature=round(slot.rotor_temperature),
        )
        return can.Message(arbitration_id=self.master_id, is_extended_id=False,
                           data=encode_reply(state, self.limits))




# --------------------------------------------------------------------------------------------
# The process: `jtc-hw emulate can`
# --------------------------------------------------------------------------------------------


def parse_ids(text: str) -> list[int]:
    """``"1-6"``, ``"1,3,5"``, ``"1-3,7"`` -> ids.

    Raises:
        ValueError: not of that form.
    """
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            low, high = (int(x, 0) for x in part.split("-", 1))
            if high < low:
                raise ValueError(f"empty id range {part!r}")
            ids.extend(range(low, high + 1))
        elif part:
            ids.append(int(part, 0))
    if not ids or len(set(ids)) != len(ids):
        raise ValueError(f"expected distinct ids like 1-6 or 1,2,3, got {text!r}")
    return ids


def build_parser() -> argparse.ArgumentParser:
    """The ``jtc-hw emulate can`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="jtc-hw emulate can",
        description="Emulate CAN motors (MIT mode or CiA 402 drives) and serve them over "
        "socketcand on 127.0.0.1 (or on an in-process python-can virtual bus).",
    )
    parser.add_argument("--protocol", choices=("mit", "cia402"), default="mit")
    parser.add_argument("--ids", action="append", default=None,
                        help="motor ids / node ids, e.g. 1-6 (repeat once per --channel)")
    parser.add_argument("--model", default="AK80-9",
                        help=f"MIT motor model: {', '.join(MODEL_PRESETS)}")
    parser.add_argument("--bitrate", type=int, default=1_000_000)
    parser.add_argument("--pace", action="store_true",
                        help="deliver replies no earlier than the wire at --bitrate would")
    parser.add_argument("--socketcand-port", type=int, default=0,
                        help="TCP port of the socketcand server (0: any free port)")
    parser.add_argument("--interface", choices=("socketcand", "virtual"), default="socketcand",
                        help="socketcand: serve over TCP; virtual: in-process bus only")
    parser.add_argument("--channel", action="append", default=None,
                        help="bus channel name (repeatable; default can0)")
    parser.add_argument("--one-thread", action="store_true",
                        help="socketcand: serve every channel, and release every emulator's "
                        "replies, from one thread (no threads of the emulators' own)")
    parser.add_argument("--master-id", type=lambda s: int(s, 0), default=0,
                        help="MIT reply arbitration id")
    return parser


def _pairs(
    channels: Sequence[str] | None, ids: Sequence[str] | None
) -> list[tuple[str, list[int]]]:
    channels = list(channels or ["can0"])
    id_texts = list(ids or ["1-6"])
    if len(id_texts) == 1 and len(channels) > 1:
        every = parse_ids(id_texts[0])
        per = math.ceil(len(every) / len(channels))
        return [(ch, every[i * per:(i + 1) * per]) for i, ch in enumerate(channels)]
    if len(id_texts) != len(channels):
        raise ValueError("give one --ids per --channel (or a single --ids to split evenly)")
    return [(ch, parse_ids(t)) for ch, t in zip(channels, id_texts, strict=True)]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the emulators until SIGINT/SIGTERM; print one line saying how to connect.

    Returns:
        The exit status (0; 2 for bad arguments or a missing CiA 402 emulator).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        pairs = _pairs(args.channel, args.ids)
    except ValueError as exc:
        parser.error(str(exc))
    if args.protocol == "mit" and args.model not in MODEL_PRESETS:
        parser.error(f"unknown --model {args.model!r}; known: {', '.join(MODEL_PRESETS)}")
    factory: Any = None
    if args.protocol == "cia402":
        try:
            from .cia402_emulator import Cia402DriveEmulator
        except ImportError as exc:
            print(f"jtc-hw emulate can: the CiA 402 emulator is not available ({exc}); "
                  "it lives in jtc_hw.drivers.can.cia402_emulator", file=sys.stderr)
            return 2
        factory = Cia402DriveEmulator

    tag = uuid.uuid4().hex[:8]
    virtual = {ch: (ch if args.interface == "virtual" else f"emu-{tag}-{ch}") for ch, _ in pairs}
    buses: list[can.BusABC] = []
    emulators: list[Any] = []
    server = None
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        for ch, ids in pairs:
            if args.protocol == "mit":
                bus = can.Bus(interface="virtual", channel=virtual[ch])
                buses.append(bus)
                emulators.append(MitBusEmulator(bus, ids, args.model, bitrate=args.bitrate,
                                                pace=args.pace, master_id=args.master_id))
            else:
                # One bus object per channel: its drives share one receive thread and one
                # modelled wire, as drives on one cable do.
                bus = can.Bus(interface="virtual", channel=virtual[ch])
                buses.append(bus)
                pace = args.bitrate if args.pace else None
                # 0.5 ms physics sub-steps, as for the MIT motors (a quarter of the default's
                # CPU, stable at these gains).
                physics = MotorParams(max_step_s=0.0005)
                emulators.extend(factory(bus, node, pace_bitrate=pace, motor_params=physics)
                                 for node in ids)
        one_thread = args.one_thread and args.interface == "socketcand"
        timers: list[Any] = []
        for emulator in emulators:
            if args.protocol == "mit" and args.interface == "socketcand":
                # Nothing else in this process uses the bus: frames from the socketcand
                # clients are handled in the server's reading thread (no hand-over).
                emulator.start(push=True, thread=not one_thread)
                timers.append(emulator)
            elif one_thread:
                emulator.start(push=True)
                if all(emulator.timer() is not t for t in timers):
                    timers.append(emulator.timer())  # one per bus: its drives share it
            else:
                emulator.start()
        if args.interface == "socketcand":
            from .socketcand import SocketcandServer

            server = SocketcandServer(port=args.socketcand_port, channels=virtual,
                                      timers=timers if one_thread else None)
            server.start()
            print(f"interface=socketcand host={server.host} port={server.port} "
                  f"channel={','.join(virtual)}", flush=True)
        else:
            print(f"interface=virtual channel={','.join(virtual)}", flush=True)
        stop.wait()
    finally:
        if server is not None:
            server.stop()
        for emulator in emulators:
            emulator.stop()
        for bus in buses:
            bus.shutdown()
    return 0


if __name__ == "__main__":  # pragma: no cover - `python -m jtc_hw.drivers.can.emulator`
    sys.exit(main())
