"""MIT-mode motors emulated on a python-can bus.

Theory of operation
-------------------
:class:`MitBusEmulator` is a peer on a python-can bus (usually ``virtual``): it owns one
:class:`~jtc_hw.drivers.motor_model.Motor` per CAN id and one thread that receives frames,
decodes them with the shared codec (:mod:`jtc_hw.drivers.can.mit.codec`) and answers every
frame addressed to one of its motors with a state reply, as the firmware does:

* a set-point frame: the motor's physics is advanced to now under the previous set-point
  (``Motor.step_pd`` in motor mode, ``Motor.coast`` otherwise), then the new set-point is
  taken;
* ``FC`` enters motor mode (the PD starts from the set-point kp = kd = t = 0, i.e. free
  until the first set-point; a motor already in motor mode keeps its set-point: the
  mini-cheetah firmware only restarts its current loop), ``FD`` exits it (coasts), ``FE``
  makes the current position zero, ``FB`` clears a Damiao error (not one whose cause lasts).
  Out of motor mode a set-point is answered but not taken, as the firmware does.

Device-side timeout, per model. A Damiao motor (``"damiao"`` reply format) speaks the
register protocol on id ``0x7FF`` (:mod:`~jtc_hw.drivers.can.mit.codec`): reads of the
registers kept here, writes of ``TIMEOUT`` (register 9, RAM; answered with an echo). With a
timeout set, an enabled motor that receives no frame addressed to it (a set-point, a special
command or a register request) for that long disables itself (torque off: it coasts) and
reports state code ``0xD`` (communication lost) until ``FB`` clears it; ``FC`` is refused
meanwhile. The expiry takes effect at its exact modelled instant (last frame + timeout)
whenever the motor is next looked at (a frame, an inspection, :meth:`MitBusEmulator.
check_timeouts`), is recorded (:meth:`MitBusEmulator.timeout_expiries`,
:meth:`MitBusEmulator.wait_timeout_expiries`) and reported to ``on_event``. AK motors have no
timeout settable over CAN (the mini-cheetah firmware's "CAN Timeout" is set from its serial
setup menu, 0 = none by default): they keep executing their last set-point forever.
:meth:`MitBusEmulator.power_cycle` (and restarting ``jtc-hw emulate can``) brings motors back
out of motor mode, with no set-point and their registers as stored in flash
(``stored_timeout_s``; a timeout the host wrote in RAM is gone).

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
``"ak"`` reply has no fault field, so an AK "drive fault" is emulated as silence), bus-off
(an error frame with ``CAN_ERR_BUSOFF``, then silence until :meth:`MitBusEmulator.clear_bus_off`)
and a brown-out (:meth:`MitBusEmulator.brown_out`: a supply dip restarts the motor; it is
deaf and silent for a given time, then answers again out of motor mode -- a Damiao reply's
state nibble says ``0``, disabled; an AK reply carries no state and looks as before -- as the
firmware does after a power cycle).
"""

from __future__ import annotations

import errno
import heapq
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import can

from jtc_hw.hardware.timing import reduce_timer_slack

from ...motor_model import Motor, MotorParams
from ..bus import CAN_ERR_BUSOFF, wire_time_s
from ..emulation import PushSink, WakeEarly, attach_sink, clocks_now
from .codec import (
    DAMIAO_TIMEOUT_RID,
    DAMIAO_TIMEOUT_UNIT_S,
    MODEL_PRESETS,
    REGISTER_ID,
    REGISTER_READ,
    REGISTER_STORE,
    REGISTER_WRITE,
    MitCommand,
    MitLimits,
    MitReply,
    RegisterFrame,
    decode_command,
    decode_register_frame,
    encode_register_frame,
    encode_reply,
    special_command,
    timeout_register_value,
)

__all__ = ["EmulatorEvent", "MitBusEmulator"]

_IDLE_POLL_S = 0.05  # how often an idle emulator thread looks at its stop flag
COMMUNICATION_LOST = 0xD  # Damiao state code of an expired CAN timeout
_FREE = MitCommand(0.0, 0.0, 0.0, 0.0, 0.0)


class EmulatorEvent(NamedTuple):
    """A change of a motor's state: ``kind`` is ``"enabled"``, ``"disabled"``,
    ``"timeout"`` (its CAN timeout expired: it disabled itself) or ``"reset"`` (it restarted
    after a brown-out, out of motor mode); ``t`` is when, on the monotonic clock (the
    modelled instant, not when it was noticed)."""

    kind: str
    motor_id: int
    t: float


@dataclass
class _MotorSlot:
    motor_id: int
    motor: Motor
    limits: MitLimits
    enabled: bool = False
    command: MitCommand = _FREE
    t: float | None = None
    zero: float = 0.0
    silent: bool = False
    drop: int = 0
    delay_s: float = 0.0
    temperature: float = 30.0
    rotor_temperature: float = 30.0
    error_code: int = 0
    persistent_error: bool = False
    commands: int = 0
    replies: int = 0
    # Damiao: registers in RAM, their stored (flash) values, the CAN timeout they set.
    registers: dict[int, int | float] = field(default_factory=dict)
    flash: dict[int, int | float] = field(default_factory=dict)
    timeout_s: float = 0.0
    last_rx: float | None = None
    expiries: list[float] = field(default_factory=list)
    # A brown-out: unpowered (deaf, silent, coasting) until this instant, then restarted.
    off_until: float | None = None
    restarts: list[float] = field(default_factory=list)
    first_replies: list[float] = field(default_factory=list)  # the first after each restart
    awaiting_reply: bool = False


class MitBusEmulator:
    """MIT-mode motors on one python-can bus (see the module docstring).

    Args:
        bus: the bus to answer on (the caller owns it and shuts it down after :meth:`stop`).
        ids: the motors' CAN ids (command arbitration ids; the id in replies).
        model: a :data:`~jtc_hw.drivers.can.mit.codec.MODEL_PRESETS` name.
        limits: ranges overriding the model's.
        master_id: arbitration id of the replies.
        bitrate: bit/s, for pacing.
        pace: deliver replies no earlier than the wire would.
        motor_params: physics of every motor (default: torque / velocity limits from the
            model's ranges).
        initial_positions: ``{id: rad}``.
        stored_timeout_s: Damiao: the CAN timeout stored in the motors' flash, which they
            power up with (0: none; the host sets its own in RAM).
        on_event: called with every :class:`EmulatorEvent` (a motor enabled, disabled, or
            its CAN timeout expired), outside the emulator's lock, in the thread that caused
            it or noticed it (:meth:`check_timeouts`).

    Raises:
        ValueError: unknown model, an id the reply format cannot carry, or a stored timeout
            for a model without one.
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
        stored_timeout_s: float = 0.0,
        on_event: Callable[[EmulatorEvent], None] | None = None,
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
        # Only Damiao firmware has a CAN timeout settable over CAN (register 9); an AK
        # motor's (mini-cheetah firmware) is set from its serial setup menu, not modelled.
        self.has_timeout = limits.reply == "damiao"
        if stored_timeout_s and not self.has_timeout:
            raise ValueError("only Damiao motors have a CAN timeout register")
        stored = timeout_register_value(stored_timeout_s)
        self._slots: dict[int, _MotorSlot] = {}
        for motor_id in ids:
            top = 0xFF if limits.reply == "ak" else 0x0F
            if not 1 <= motor_id <= min(top, 0x7FF):
                raise ValueError(f"motor id {motor_id} out of range 1..{top} for this model")
            slot = _MotorSlot(motor_id, Motor(params, initial.get(motor_id, 0.0)), limits)
            if self.has_timeout:
                slot.flash = {7: master_id, 8: motor_id, DAMIAO_TIMEOUT_RID: stored,
                              10: 1, 21: limits.p_max, 22: limits.v_max, 23: limits.t_max}
                self._load_flash(slot)
            self._slots[motor_id] = slot
        self._on_event = on_event
        self._events: list[EmulatorEvent] = []  # to emit once the lock is released
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
            position = slot.motor.position - slot.zero
        self._emit()
        return position

    def enabled(self, motor_id: int) -> bool:
        """Whether the motor is in motor mode (its CAN timeout evaluated to now)."""
        with self._lock:
            slot = self._slots[motor_id]
            self._advance(slot, time.monotonic())
            enabled = slot.enabled
        self._emit()
        return enabled

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

    def error_code(self, motor_id: int) -> int:
        """The motor's latched Damiao error code (0: none), timeouts evaluated to now."""
        self.check_timeouts()
        with self._lock:
            return self._slots[motor_id].error_code

    def timeout_s(self, motor_id: int) -> float:
        """The CAN timeout the motor runs with (its ``TIMEOUT`` register), s; 0: none."""
        with self._lock:
            return self._slots[motor_id].timeout_s

    def check_timeouts(self, now: float | None = None) -> None:
        """Bring every motor to ``now`` (default: the monotonic clock): a CAN timeout that
        has expired meanwhile takes effect, at its exact modelled instant, and is reported
        to ``on_event``. Expiry needs no frame to notice it: any inspection calls this."""
        when = time.monotonic() if now is None else now
        with self._lock:
            for slot in self._slots.values():
                self._advance(slot, when)
        self._emit()

    def timeout_expiries(self) -> list[tuple[int, float]]:
        """Every CAN timeout expiry so far, ``(motor id, monotonic time)``, oldest first.

        The time is the modelled instant the motor disabled itself: its last frame's arrival
        plus its timeout (timeouts are first brought up to date, :meth:`check_timeouts`).
        """
        self.check_timeouts()
        with self._lock:
            return sorted(((motor_id, t) for motor_id, slot in self._slots.items()
                           for t in slot.expiries), key=lambda item: item[1])

    def wait_timeout_expiries(
        self, ids: Iterable[int] | None = None, since: float = 0.0, timeout_s: float = 5.0
    ) -> dict[int, float]:
        """Wait until each motor of ``ids`` (default: all) has disabled itself on its CAN
        timeout at or after ``since`` (monotonic); the first such instant per motor.

        The wait sleeps until the earliest modelled expiry, then looks again (a frame may
        have pushed it back): what a benchmark of "daemon failure -> motors stopped" needs,
        ``since`` being the failure's time.

        Raises:
            TimeoutError: not every motor's timeout expired within ``timeout_s``.
        """
        wanted = set(self._slots if ids is None else ids)
        end = time.monotonic() + timeout_s
        while True:
            found: dict[int, float] = {}
            for motor_id, t in self.timeout_expiries():
                if motor_id in wanted and t >= since and motor_id not in found:
                    found[motor_id] = t
            now = time.monotonic()
            if len(found) == len(wanted):
                return found
            if now >= end:
                missing = sorted(wanted - set(found))
                raise TimeoutError(f"the CAN timeout of motors {missing} did not expire "
                                   f"within {timeout_s} s")
            with self._lock:
                deadlines = [d for motor_id in wanted - set(found)
                             if (d := self._deadline(self._slots[motor_id])) is not None]
            # Until the earliest modelled expiry (a little after, so it has passed), or
            # another look soon if none is armed (a frame may still arm one).
            wake = min(deadlines, default=now + _IDLE_POLL_S) + 1e-4
            time.sleep(max(0.0, min(wake, end) - now))

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

    def set_error(self, motor_id: int, code: int, persistent: bool = False) -> None:
        """Raise a Damiao error code (8..14): the drive switches off and reports it; an AK
        motor, whose reply has no fault field, goes silent instead (0 clears either).

        Args:
            motor_id: the motor.
            code: the error code; 0 clears it (and ends a persistent one).
            persistent: the cause lasts (e.g. a supply below the under-voltage limit): ``FB``
                does not clear it, so the motor refuses to enable until ``set_error(id, 0)``.
        """
        with self._lock:
            slot = self._slots[motor_id]
            self._advance(slot, time.monotonic())
            slot.error_code = code
            slot.persistent_error = persistent and code >= 8
            if code >= 8:
                self._set_enabled(slot, False, time.monotonic())
            if self.limits.reply == "ak":
                slot.silent = code >= 8
        self._emit()

    def power_cycle(self, motor_id: int | None = None) -> None:
        """Switch the motor (default: every motor) off and on again: it comes back out of
        motor mode, with no set-point, no latched error (a persistent cause stays) and its
        registers as stored in flash (a CAN timeout set in RAM is gone); its position and
        zero (stored) are kept."""
        now = time.monotonic()
        with self._lock:
            for key in self._slots if motor_id is None else (motor_id,):
                slot = self._slots[key]
                self._advance(slot, now)
                self._restart(slot, now)
        self._emit()

    def _restart(self, slot: _MotorSlot, t: float) -> None:
        """The firmware starting up at ``t``: see :meth:`power_cycle`. Under the lock."""
        self._set_enabled(slot, False, t)
        slot.command = _FREE
        if not slot.persistent_error:
            slot.error_code = 0
        self._load_flash(slot)
        slot.last_rx = None

    def brown_out(self, motor_id: int, off_s: float) -> None:
        """A supply dip: the motor loses power now (torque off: it coasts; it hears and
        answers nothing) and restarts ``off_s`` later as after a power cycle
        (:meth:`power_cycle`): out of motor mode, answering "disabled" (Damiao state ``0``;
        an AK reply has no state and looks as before).

        The restart takes effect at its modelled instant whenever the motor is next looked at
        (a frame, an inspection); it is recorded (:meth:`restarts`), reported to ``on_event``
        as ``"reset"``, and the instant of the first reply after it is recorded
        (:meth:`first_replies_after_reset`).

        Raises:
            ValueError: ``off_s`` is not positive.
        """
        if not off_s > 0.0:
            raise ValueError(f"a brown-out lasts a positive time, got {off_s!r} s")
        now = time.monotonic()
        with self._lock:
            slot = self._slots[motor_id]
            self._advance(slot, now)
            self._set_enabled(slot, False, now)
            slot.off_until = now + off_s
        self._emit()

    def restarts(self, motor_id: int) -> list[float]:
        """The instants (monotonic) the motor restarted after a brown-out, oldest first."""
        self.check_timeouts()
        with self._lock:
            return list(self._slots[motor_id].restarts)

    def first_replies_after_reset(self, motor_id: int) -> list[float]:
        """When (monotonic) the motor's first reply after each restart went on the bus."""
        with self._lock:
            return list(self._slots[motor_id].first_replies)

    def bus_off(self) -> None:
        """Send a bus-off error frame and go silent until :meth:`clear_bus_off`.

        The error frame goes first: a controller going bus-off reports it as it stops, so
        the peer never sees the silence without the reason. Silent first, a caller
        descheduled between the two (a busy host) let the driver's ``feedback_timeout``
        expire before the frame came, and the bus-off read as silent motors (issue 22).
        """
        self.bus.send(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True,
                                  is_extended_id=True, data=bytes(8)))
        with self._lock:
            self._bus_off = True

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
                try:
                    msg = self.bus.recv(timeout=timeout)
                except can.CanOperationError as exc:
                    if exc.error_code != errno.ENETDOWN:
                        raise
                    # SocketCAN: the network device shared with the driver went down (`ip
                    # link set vcan0 down`); motors on a wire would not notice: keep
                    # listening, frames come again once it is up.
                    continue
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
        now, wall = clocks_now()
        if not msg.timestamp:
            return now
        age = min(max(wall - msg.timestamp, 0.0), 0.05)
        return now - age

    def _deliver_due(self, now: float) -> None:
        while True:
            with self._lock:
                if not self._due or self._due[0][0] > now:
                    return
                _, _, reply = heapq.heappop(self._due)
            self._send(reply)

    def _advance(self, slot: _MotorSlot, now: float) -> None:
        """Run the motor's physics up to ``now``; an expired CAN timeout takes effect at its
        modelled instant (PD until then, coasting after), as does the restart after a
        brown-out. Under the lock."""
        if slot.off_until is not None and slot.off_until <= now:
            restart = slot.off_until
            if slot.t is not None and restart > slot.t:
                self._step(slot, restart)  # coasting while unpowered
            slot.off_until = None
            self._restart(slot, restart)
            slot.restarts.append(restart)
            slot.awaiting_reply = True
            self._events.append(EmulatorEvent("reset", slot.motor_id, restart))
        if slot.t is not None and now > slot.t:
            deadline = self._deadline(slot)
            if deadline is not None and deadline < now:
                self._step(slot, max(deadline, slot.t))
                slot.expiries.append(deadline)
                slot.error_code = COMMUNICATION_LOST
                self._events.append(EmulatorEvent("timeout", slot.motor_id, deadline))
                self._set_enabled(slot, False, deadline)
            self._step(slot, now)
        elif slot.t is None:
            slot.t = now
        # (A frame stamped earlier than the physics already ran is applied now: time does not
        # run backwards, nothing is integrated twice.)

    def _step(self, slot: _MotorSlot, until: float) -> None:
        assert slot.t is not None
        dt = until - slot.t
        if dt > 0.0:
            c = slot.command
            if slot.enabled:
                slot.motor.step_pd(dt, c.position + slot.zero, c.velocity, c.kp, c.kd, c.torque)
            else:
                slot.motor.coast(dt)
            slot.t = until

    @staticmethod
    def _deadline(slot: _MotorSlot) -> float | None:
        """When the motor's CAN timeout expires if no frame comes (``None``: not armed)."""
        if slot.enabled and slot.timeout_s > 0.0 and slot.last_rx is not None:
            return slot.last_rx + slot.timeout_s
        return None

    def _set_enabled(self, slot: _MotorSlot, enabled: bool, t: float) -> None:
        if slot.enabled != enabled:
            slot.enabled = enabled
            kind = "enabled" if enabled else "disabled"
            self._events.append(EmulatorEvent(kind, slot.motor_id, t))

    def _emit(self) -> None:
        """Hand the pending events to ``on_event``, outside the lock."""
        if not self._events:
            return
        with self._lock:
            events, self._events = self._events, []
        if self._on_event is not None:
            for event in events:
                self._on_event(event)

    @staticmethod
    def _load_flash(slot: _MotorSlot) -> None:
        slot.registers = dict(slot.flash)
        counts = int(slot.registers.get(DAMIAO_TIMEOUT_RID, 0))
        slot.timeout_s = counts * DAMIAO_TIMEOUT_UNIT_S

    def _handle(self, msg: can.Message, now: float) -> None:
        if msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame:
            return
        self.frames_received += 1
        with self._lock:
            reply = self._answer(msg, now)
        self._emit()
        if reply is not None:
            self._send(reply)

    def _answer(self, msg: can.Message, now: float) -> can.Message | None:
        """Apply one frame; the reply to send now (``None``: none, or queued). Under the lock."""
        if len(msg.data) != 8:
            return None
        register = msg.arbitration_id == REGISTER_ID and self.has_timeout
        motor_id = msg.data[0] | (msg.data[1] << 8) if register else msg.arbitration_id
        slot = self._slots.get(motor_id)
        if slot is None:
            return None
        self._advance(slot, now)
        if slot.off_until is not None:
            return None  # unpowered: hears nothing
        slot.last_rx = now  # any frame addressed to the motor feeds its CAN timeout
        slot.commands += 1
        if register:
            data = self._register(slot, msg.data)
        else:
            self._command(slot, msg.data, now)
            data = self._state(motor_id, slot)
        if data is None or self._bus_off or slot.silent:
            return None
        if slot.drop > 0:
            slot.drop -= 1
            return None
        reply = can.Message(arbitration_id=self.master_id, is_extended_id=False, data=data)
        due = now
        if self.pace:
            start = max(now, self._wire_free)
            self._wire_free = start + wire_time_s((msg, reply), self.bitrate)
            due = self._wire_free
        due += slot.delay_s
        slot.replies += 1
        if slot.awaiting_reply:
            slot.awaiting_reply = False
            slot.first_replies.append(due)
        if due <= now:
            return reply
        self._seq += 1
        heapq.heappush(self._due, (due, self._seq, reply))
        if self._push and self._due[0][1] == self._seq:
            self._wake.notify()  # the release thread waits for a later one
        return None

    def _command(self, slot: _MotorSlot, data: bytes | bytearray, now: float) -> None:
        """A frame on the motor's own id, as the mini-cheetah firmware handles it."""
        kind = special_command(data)
        if kind == "enter":
            # Re-entering while enabled only restarts the current loop: the set-point
            # stays. From rest the motor starts free (kp = kd = t = 0) until a set-point.
            if slot.error_code < 8 and not slot.enabled:
                slot.command = MitCommand(slot.motor.position - slot.zero, 0.0, 0.0, 0.0, 0.0)
                self._set_enabled(slot, True, now)
        elif kind == "exit":
            self._set_enabled(slot, False, now)
        elif kind == "zero":
            slot.zero = slot.motor.position
        elif kind == "clear_error":
            if not slot.persistent_error:
                slot.error_code = 0
        elif slot.enabled:
            slot.command = decode_command(data, self.limits)
        # A set-point out of motor mode is answered but not taken (the firmware unpacks
        # commands in motor mode only).

    def _register(self, slot: _MotorSlot, data: bytes | bytearray) -> bytes | None:
        """A Damiao register request: the reply's bytes, or ``None`` (not answered).

        Modelled: reads of the registers the emulator keeps (MST_ID, ESC_ID, TIMEOUT,
        CTRL_MODE, PMAX, VMAX, TMAX), writes of TIMEOUT (echoed; in RAM) and store (to
        flash, while disabled, unanswered). Other requests are not answered.
        """
        try:
            frame = decode_register_frame(data)
        except ValueError:
            return None
        if frame.command == REGISTER_READ and frame.rid in slot.registers:
            value = slot.registers[frame.rid]
            return encode_register_frame(RegisterFrame(frame.motor_id, REGISTER_READ,
                                                       frame.rid, value))
        if frame.command == REGISTER_WRITE and frame.rid == DAMIAO_TIMEOUT_RID:
            assert isinstance(frame.value, int)
            slot.registers[frame.rid] = frame.value
            slot.timeout_s = frame.value * DAMIAO_TIMEOUT_UNIT_S
            return encode_register_frame(frame)
        if frame.command == REGISTER_STORE and not slot.enabled:
            slot.flash = dict(slot.registers)
        return None

    def _send(self, reply: can.Message) -> None:
        try:
            self.bus.send(reply, timeout=0.0)
        except can.CanOperationError:
            self.tx_failures += 1  # a full transmit queue: the frame is lost, as on a wire
        else:
            self.replies_sent += 1

    def _state(self, motor_id: int, slot: _MotorSlot) -> bytes:
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
        return encode_reply(state, self.limits)
