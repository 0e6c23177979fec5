"""What the serial-bus emulators (Dynamixel, Feetech) share: a pseudo-terminal served by one
thread, replies paced to the wire, and the command line around them.

Theory of operation
-------------------
A serial servo bus is one wire shared by a host and its servos; an emulator stands in for the
servos on a pty pair. :class:`PtyBusEmulator` owns everything that does not depend on the
protocol::

    host (SDK, driver)                                 PtyBusEmulator
    opens /dev/pts/N  --- instruction bytes --->  master fd --select--> decoder.feed()
    (or the --link)                                                        |  packets
                      <--- status packets ----  _send(due)  <-- _handle(packet, arrival,
                                                                           first_byte)

- :meth:`~PtyBusEmulator.start` opens the pty in raw mode (no echo, no line discipline
  translating bytes such as 0x0D or 0x11), optionally symlinks it, and starts the serving
  thread; :meth:`~PtyBusEmulator.close` stops it promptly (the thread waits in ``select``
  with a short timeout and on an event) and removes the link if it still points at the pty.
- The serving thread feeds what arrives to the family's decoder (a
  :class:`~jtc_hw.drivers.framing.StreamBuffer` with ``feed``) and hands each packet to the
  subclass's :meth:`~PtyBusEmulator._handle` with two stamps: when its chunk arrived and when its
  first byte did (where a paced reply is timed from). A partial packet older than the servos'
  inter-byte timeout is dropped. While the bus is idle,
  :meth:`~PtyBusEmulator._step_servos` advances every servo (a :class:`BusServo`: its id, its
  ``step(now)``, its :class:`ReplyFaults`) every few milliseconds.
- Observation shared by the families: :meth:`~PtyBusEmulator.register` (a servo's register
  now), :meth:`~PtyBusEmulator.stats` (the counters) and the reply faults every servo has
  (:meth:`~PtyBusEmulator.set_silent`, :meth:`~PtyBusEmulator.drop_replies`,
  :meth:`~PtyBusEmulator.delay_replies`; a family names its checksum fault).
- Timing (:meth:`~PtyBusEmulator._schedule`, :meth:`~PtyBusEmulator._send`): a subclass computes
  a request's replies at once, then asks when each is due. Unpaced, a reply is due after its
  servo's return delay (and any injected delay); due replies are written together and waits
  under 0.2 ms are skipped (a host sharing the emulator's interpreter, as in tests, pays a thread
  switch for every wait). With ``pace=True`` the host sees the timing of a real bus, not of a
  pty (``time.monotonic``, 8N1: 10 bits per byte): a request starts on the wire when its first
  byte arrived, or when the bus is free if an earlier packet still holds it (a write nobody
  answers still takes its wire time: :meth:`~PtyBusEmulator._hold_bus`); each reply is written
  when its last byte would have arrived. Such a wait sleeps (with a 1 us timer slack asked for
  the serving thread) until ~100 us before the moment and spins the rest: this is a test device,
  and a sleep alone wakes 20-70 us late.

Command line (:func:`bus_parser`, :func:`run_emulator`): ``--ids --model --baud --pace
--link --stats --return-delay-us --priority``, the SCHED_FIFO priority asked for before any
thread starts (:mod:`~jtc_hw.drivers.emulation_cli`), the device path on stdout, then serving
until SIGINT/SIGTERM with the packet statistics on stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import select
import signal
import sys
import threading
import time
import tty
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Generic, Protocol, TypeVar

from jtc_hw.hardware.timing import reduce_timer_slack

from .emulation_cli import DEFAULT_PRIORITY, apply_priority, parse_ids

__all__ = [
    "BusServo",
    "FrameDecoder",
    "PtyBusEmulator",
    "ReplyFaults",
    "corrupt_last_byte",
    "faulted",
    "bus_parser",
    "run_emulator",
    "wire_time_s",
]

#: Physics advance period while the bus is idle, s.
IDLE_STEP_S = 0.005
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

P = TypeVar("P")
P_co = TypeVar("P_co", covariant=True)
_E = TypeVar("_E", bound="PtyBusEmulator[Any, Any]")
_S = TypeVar("_S", bound="ReplyFaults")
S = TypeVar("S", bound="BusServo")


def wire_time_s(n_bytes: int, baud: int) -> float:
    """Seconds ``n_bytes`` take on the wire at ``baud`` (8N1: 10 bits per byte)."""
    return n_bytes * 10.0 / baud


class ReplyFaults:
    """The reply faults a test injects into one emulated servo (:class:`BusServo` has them).

    Attributes:
        drop: how many of its next replies are left unsent.
        delay_s: how much later than its return delay it answers, s.
        corrupt: how many of its next replies are sent with a wrong checksum / CRC.
        silent: it answers nothing while set.
    """

    def __init__(self) -> None:
        self.drop = 0
        self.delay_s = 0.0
        self.corrupt = 0
        self.silent = False

    def take_drop(self) -> bool:
        """Whether this reply goes unsent (silent, or one of the replies to drop)."""
        if self.silent:
            return True
        if self.drop > 0:
            self.drop -= 1
            return True
        return False

    def take_corrupt(self) -> bool:
        """Whether this reply is sent corrupted (one of the replies to corrupt)."""
        if self.corrupt > 0:
            self.corrupt -= 1
            return True
        return False


class BusServo(ReplyFaults):
    """What the shared machinery needs of an emulated servo: its id, its clock, its faults."""

    @property
    def id(self) -> int:
        """The servo's present id."""
        raise NotImplementedError

    def step(self, now: float) -> None:
        """Advance the servo to ``now`` (``time.monotonic()``)."""
        raise NotImplementedError

    def value(self, name: str) -> int:
        """The value register ``name`` holds now (present registers brought up to date).

        Raises:
            KeyError: no such register.
        """
        raise NotImplementedError


def corrupt_last_byte(data: bytes) -> bytes:
    """``data`` with its last byte (a checksum or a CRC's high byte) inverted."""
    return data[:-1] + bytes((data[-1] ^ 0xFF,))


def faulted(replies: Iterable[tuple[_S, bytes]]) -> list[tuple[_S, bytes]]:
    """The replies that are sent, in order, after each servo's injected faults."""
    out: list[tuple[_S, bytes]] = []
    for servo, data in replies:
        if servo.take_drop():
            continue
        out.append((servo, corrupt_last_byte(data) if servo.take_corrupt() else data))
    return out


class FrameDecoder(Protocol[P_co]):
    """What the serving thread needs of a family's packet decoder."""

    junk_bytes: int

    @property
    def pending(self) -> int: ...

    def reset(self) -> None: ...

    def feed(self, data: bytes) -> list[P_co]: ...


class PtyBusEmulator(Generic[P, S]):
    """One bus of emulated servos on a pseudo-terminal (see the module docstring).

    A subclass sets :attr:`_decoder` and :attr:`_servos` and implements :meth:`_handle`; it
    calls :meth:`_schedule` then :meth:`_send` to answer, :meth:`_hold_bus` for a packet nobody
    answers. :attr:`_lock` guards the servos: the serving thread takes it around
    :meth:`_step_servos`, and a subclass around its own dispatch.

    Args:
        baud: the bus's baud rate in bit/s, for pacing packets nobody answers.
        pace: hold replies back so that requests and replies take their wire time.
        link: a path to create as a symlink to the pty slave (an existing symlink is replaced).
        thread_name: the serving thread's name.
    """

    _decoder: FrameDecoder[P]
    _servos: list[S]

    def __init__(self, *, baud: int, pace: bool, link: str | None, thread_name: str) -> None:
        self.pace = pace
        self._baud = baud
        self._link = link
        self._thread_name = thread_name
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = -1
        self._slave = -1
        self._slave_path = ""
        # When the bus is next idle (the end of the last request or reply on the wire, paced
        # mode; the last reply's due time, unpaced).
        self._bus_free = 0.0
        self._last_step = 0.0  # when every servo was last stepped (idle stepping)
        self.packets_served = 0
        self.replies_sent = 0
        self.errors_sent = 0  # status packets carrying an error
        self.bytes_dropped = 0

    # -- what a family provides -----------------------------------------------------------------

    def _handle(self, packet: P, arrival: float, first_byte: float) -> None:
        """Step the physics to ``arrival``, execute ``packet`` and send its replies;
        ``first_byte``: when its first byte arrived (paced replies are timed from there)."""
        raise NotImplementedError

    def _step_servos(self, now: float) -> None:
        """Advance every servo to ``now`` (called with :attr:`_lock` held)."""
        for s in self._servos:
            s.step(now)

    def _checksum_errors(self) -> tuple[str, int]:
        """The family's name for requests received with a bad checksum or CRC, and their count."""
        raise NotImplementedError

    def stats(self) -> dict[str, int]:
        """Counters: packets served, replies sent, replies with an error status, requests with
        a bad checksum / CRC, junk bytes seen, reply bytes the pty could not take."""
        with self._lock:
            name, count = self._checksum_errors()
            return {
                "packets_served": self.packets_served,
                "replies_sent": self.replies_sent,
                "errors_sent": self.errors_sent,
                name: count,
                "junk_bytes": self._decoder.junk_bytes,
                "bytes_dropped": self.bytes_dropped,
            }

    def describe(self) -> str:
        """What is served, for the command line's banner (``"6 x STS3215"``)."""
        raise NotImplementedError

    def _servo(self, servo_id: int) -> S:
        """The servo ``servo_id``.

        Raises:
            KeyError: no such servo.
        """
        for s in self._servos:
            if s.id == servo_id:
                return s
        raise KeyError(f"no emulated servo with id {servo_id}")

    def _servo_now(self, servo_id: int) -> S:
        """The servo ``servo_id``, advanced to now (call it with :attr:`_lock` held).

        Raises:
            KeyError: no such servo.
        """
        s = self._servo(servo_id)
        s.step(time.monotonic())
        return s

    def register(self, servo_id: int, name: str) -> int:
        """The value of register ``name`` of servo ``servo_id`` now (present values refreshed).

        Raises:
            KeyError: unknown servo or register.
        """
        with self._lock:
            return self._servo_now(servo_id).value(name)

    # -- faults (thread-safe) -----------------------------------------------------------------

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

    def set_silent(self, servo_id: int, silent: bool) -> None:
        """Servo ``servo_id`` never answers (group reads included) while ``silent``.

        Raises:
            KeyError: unknown servo.
        """
        with self._lock:
            self._servo(servo_id).silent = bool(silent)

    def _corrupt_replies(self, servo_id: int, count: int) -> None:
        with self._lock:
            self._servo(servo_id).corrupt = max(0, int(count))

    # -- lifecycle --------------------------------------------------------------------------------

    def start(self: _E) -> _E:
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
        self._thread = threading.Thread(target=self._serve, name=self._thread_name, daemon=True)
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

    def __enter__(self: _E) -> _E:
        if self._thread is None:
            self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def device_path(self) -> str:
        """The path a host opens: the link if one was asked for, else ``/dev/pts/N``."""
        return self._link or self._slave_path

    @property
    def slave_path(self) -> str:
        """The pty slave's path (``/dev/pts/N``)."""
        return self._slave_path

    # -- serving ----------------------------------------------------------------------------------

    def _serve(self) -> None:
        reduce_timer_slack(_TIMER_SLACK_NS)  # best effort: else the spin absorbs the slack
        last_rx = time.monotonic()
        first_byte = last_rx  # when the first byte of the packet being received arrived
        while not self._stop.is_set():
            try:
                readable, _, _ = select.select([self._master], [], [], IDLE_STEP_S)
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
                        self._stop.wait(IDLE_STEP_S)
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
            # Physics runs once per request (in _handle); the idle bus only needs timers and
            # coasting motors to move on now and then.
            now = time.monotonic()
            if now - self._last_step >= IDLE_STEP_S:
                with self._lock:
                    self._step_servos(now)
                    self._last_step = now

    # -- output -----------------------------------------------------------------------------------

    def _schedule(
        self, start: float, request_bytes: int, request_baud: int,
        replies: Sequence[tuple[float, bytes, int]],
    ) -> list[tuple[float, bytes]]:
        """When each reply is due: ``[(time.monotonic() moment, bytes)]``, in order.

        Args:
            start: the request's first byte (paced) or its arrival (unpaced).
            request_bytes: the request's length, bytes.
            request_baud: the bus's baud rate while the request was sent, bit/s.
            replies: ``(delay before it, s; its bytes; its servo's baud rate)`` in the order the
                servos answer; the delay is the return delay plus any injected one.

        Also marks the bus busy until the last reply is due.
        """
        t = max(start, self._bus_free)
        if self.pace:
            t += wire_time_s(request_bytes, request_baud)
        due: list[tuple[float, bytes]] = []
        for delay_s, data, baud in replies:
            t += delay_s
            if self.pace:
                t += wire_time_s(len(data), baud)
            due.append((t, data))
        self._bus_free = t
        return due

    def _hold_bus(self, first_byte: float, n_bytes: int) -> None:
        """Paced: a packet nobody answers holds the bus for its wire time, so that a request
        right behind it (a Sync Read after a Sync Write) starts on the wire only after it."""
        if self.pace:
            start = max(first_byte, self._bus_free)
            self._bus_free = start + wire_time_s(n_bytes, self._baud)

    def _send(self, due: Sequence[tuple[float, bytes]]) -> None:
        """Write each reply when it is due (see the module docstring); returns early when the
        emulator is closed meanwhile."""
        if self.pace:
            for when, data in due:
                if self._wait_until(when):
                    return
                self._write([data])
            return
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


# -- command line ---------------------------------------------------------------------------------


def bus_parser(
    prog: str, description: str, *, model: str, baud: int, return_delay: str,
    paced: bool = False,
) -> argparse.ArgumentParser:
    """An emulator's argument parser with the options every serial-bus emulator takes: ``--ids
    --model --baud --pace --link --stats --return-delay-us --priority`` (a family adds its own
    after them).

    Args:
        prog: the command (``"jtc-hw emulate feetech"``).
        description: what it serves, for ``--help``.
        model: the default ``--model``.
        baud: the default ``--baud``, bit/s.
        return_delay: the servo's factory return delay, in words (``"500"``), for the help.
        paced: pace by default (then ``--no-pace`` turns it off).
    """
    p = argparse.ArgumentParser(prog=prog, description=description + " Prints the device "
                                "path, then serves until SIGINT/SIGTERM.")
    p.add_argument("--ids", default="1", help="servo ids, e.g. 1-6 or 1,2,5-7 (default 1)")
    p.add_argument("--model", default=model, help=f"servo model (default {model})")
    p.add_argument("--baud", type=int, default=baud,
                   help=f"servo baud rate, bit/s (default {baud})")
    pace_help = "hold replies back to the wire time of a real bus at that baud rate"
    if paced:
        p.add_argument("--pace", action=argparse.BooleanOptionalAction, default=True,
                       help=pace_help + " (default; --no-pace: as soon as they are due)")
    else:
        p.add_argument("--pace", action="store_true", help=pace_help)
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
        "--return-delay-us",
        type=float,
        default=None,
        help=f"Return Delay Time in us (default: the servo's, {return_delay})",
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


def run_emulator(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    make: Callable[[list[int]], _E],
    *,
    valid_ids: range,
    tick: Callable[[_E], None] | None = None,
) -> int:
    """Serve the emulator ``make(ids)`` builds until SIGINT/SIGTERM (``jtc-hw emulate ...``).

    Asks for the real-time priority before any thread starts (they inherit it: a normally
    scheduled emulator missed the daemon's 20 ms ping at configure on a busy machine, issue 22),
    prints the device path on stdout and a banner on stderr, then the statistics as ``--stats``
    says; ``tick`` runs every 0.2 s meanwhile (e.g. to print events).

    Returns:
        0 on a clean stop, 2 on bad ids or options ``make`` refuses (``ValueError``,
        ``KeyError``) or a pty that cannot be opened; ``--priority`` out of range exits with
        ``parser.error``.
    """
    prog = parser.prog
    apply_priority(parser, args.priority)
    try:
        ids = parse_ids(args.ids, valid=valid_ids)
        emulator = make(ids)
    except (ValueError, KeyError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    def stats_line() -> None:
        print(" ".join(f"{k}={v}" for k, v in emulator.stats().items()), file=sys.stderr,
              flush=True)

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with emulator:
            print(emulator.device_path, flush=True)
            print(
                f"serving {emulator.describe()} (ids {args.ids}) at {args.baud} "
                f"bit/s{' paced' if args.pace else ''} on {emulator.slave_path}",
                file=sys.stderr,
                flush=True,
            )
            last: dict[str, int] = {}
            while not stop.wait(0.2):
                stats = emulator.stats()
                if stats != last and args.stats == "live":
                    stats_line()
                    last = stats
                if tick is not None:
                    tick(emulator)
            if args.stats == "exit":
                stats_line()
    except OSError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
