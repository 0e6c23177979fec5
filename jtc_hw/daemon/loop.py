"""The control loop process: read -> update -> write at absolute deadlines, nothing else.

Theory of operation
-------------------
The loop runs in its own process so that API work (parsing, fitting a 2,000-point goal,
serving clients) never shares an interpreter lock with it. It talks to the API process over
one duplex ``multiprocessing`` connection:

- in (framed by ``send_framed``, arrays out of band): ``("commit", plan_id, Plan)``,
  ``("request", request_id, op, args)``;
- out: ``("ready", info)``, ``("reference", version, trajectory_or_None, plan_id_or_None)``,
  ``("committed", plan_id, goal_id)``, ``("stale", plan_id, reason)``, ``("events", [...])``,
  ``("state", snapshot)``, ``("status", dict)``, ``("reply", request_id, ok, value)``,
  ``("log", level, message)``, ``("exit", code)``.

Every change of the controller's reference is reported, in order, so the API process keeps an
exact replica to plan against: a committed plan by its id (the API process made it), a hold by
value (a constant trajectory, a few bytes). The loop process has a single thread: after each
cycle it reads whatever has arrived, a bounded amount, without blocking (:class:`_Inbox`), and
the next cycle pops the completed messages.

One cycle at deadline ``t``: drain requests -> ``hardware.read(t)`` -> ``controller.update`` ->
``hardware.write`` -> report events; a state snapshot at ``state_publish_rate``, statistics at
2 Hz. The controller's clock is the deadline grid itself (exact multiples of the period); how
late the process woke is measured and published, never fed into the control law. Garbage
collection is disabled in the loop and run explicitly (generation 0) when a cycle has slack.
"""

from __future__ import annotations

import collections
import gc
import logging
import os
import pickle
import signal
import struct
import sys
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from ..controller.controller import JointTrajectoryController, Plan
from ..controller.goals import Event
from ..controller.joints import JointCommand, JointState
from ..errors import HardwareError, JtcHwError, StalePlan
from ..hardware import HardwareSet, LifecycleState
from .clock import Ticker
from .loopstats import LoopStats
from .robot import RobotConfig, create_hardware_set, load_robot

log = logging.getLogger("jtc_hw.loop")

STATUS_PERIOD_NS = 500_000_000
GC_SLACK_NS = 300_000  # run a gen-0 collection only with this much time left before the deadline


_FRAME = struct.Struct("<I")


def send_framed(conn: Connection, message: tuple[Any, ...]) -> None:
    """Send ``message`` with its arrays out of band (pickle protocol 5).

    A 2,000-point plan carries megabytes of coefficients. Pickled in band, unpickling copies
    them while holding the interpreter lock, which the loop thread then waits for. Out of band,
    each array travels as its own frame that the receiving thread reads with the lock released
    (``os.read``), and unpickling only wraps those bytes: no copy.
    """
    buffers: list[pickle.PickleBuffer] = []
    head = pickle.dumps(message, protocol=5, buffer_callback=buffers.append)
    conn.send_bytes(_FRAME.pack(len(buffers)) + head)
    for buffer in buffers:
        conn.send_bytes(buffer.raw())


def recv_framed(conn: Connection) -> Any:
    """Receive one message sent by ``send_framed``."""
    head = conn.recv_bytes()
    (count,) = _FRAME.unpack_from(head)
    buffers = [conn.recv_bytes() for _ in range(count)]
    return pickle.loads(memoryview(head)[_FRAME.size :], buffers=buffers)


_HEADER = struct.Struct("!i")
_LONG_HEADER = struct.Struct("!Q")


class _Inbox:
    """Messages from the API process, read by the loop thread itself, a bounded amount at a
    time, without ever blocking.

    A receiving thread would compete with the loop thread for the interpreter lock: measured,
    a thread receiving a 2.4 MB plan stretched cycles by milliseconds (each time the loop
    thread released the lock in a system call, the receiver took it for up to the switch
    interval). Here the loop process has one thread. :meth:`pump` reads what has arrived, at
    most ``budget`` bytes, straight into the buffer of the message being received
    (``MSG_DONTWAIT``: the connection stays blocking for sends), and completes messages in
    ``multiprocessing``'s wire format (a 4-byte length, or -1 and an 8-byte length) framed by
    :func:`send_framed`. A 2,000-point plan then arrives over a few cycles, each paying a
    bounded copy. The API process's send just waits meanwhile.
    """

    def __init__(self, conn: Connection, budget: int) -> None:
        import socket

        self._sock = socket.socket(fileno=os.dup(conn.fileno()))
        self._budget = budget
        self._queue: collections.deque[Any] = collections.deque()
        self.closed = False
        self._header = bytearray(_HEADER.size)
        self._body: bytearray | None = None  # the message being received, once its size is known
        self._view = memoryview(self._header)
        self._filled = 0
        self._long = False
        self._frame: list[bytearray] = []  # [head, buffers...] of the framed message so far
        self._frame_size = 0  # buffers the framed message has (from its head)

    def close(self) -> None:
        """Release the duplicated socket (the connection itself stays open)."""
        self._sock.close()

    def pump(self) -> None:
        """Read what has arrived, at most ``budget`` bytes; never blocks."""
        import socket

        budget = self._budget
        while budget > 0 and not self.closed:
            want = min(len(self._view) - self._filled, budget)
            try:
                got = self._sock.recv_into(self._view[self._filled:], want, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.closed = True
                return
            if got == 0:
                self.closed = True
                return
            budget -= got
            self._filled += got
            if self._filled == len(self._view):
                self._advance()

    def _advance(self) -> None:
        if self._body is None:
            if self._long:
                (size,) = _LONG_HEADER.unpack(self._header)
                self._long = False
            else:
                (size,) = _HEADER.unpack(self._header)
                if size == -1:
                    self._long = True
                    self._expect(bytearray(_LONG_HEADER.size), header=True)
                    return
            self._body = bytearray(size)
            self._expect(self._body)
            if size:
                return
        body, self._body = self._body, None
        self._expect(bytearray(_HEADER.size), header=True)
        self._message(body)

    def _expect(self, buffer: bytearray, header: bool = False) -> None:
        if header:
            self._header = buffer
        self._view = memoryview(buffer)
        self._filled = 0

    def _message(self, body: bytearray) -> None:
        if not self._frame:
            (self._frame_size,) = _FRAME.unpack_from(body)
        self._frame.append(body)
        if len(self._frame) == self._frame_size + 1:
            head, *buffers = self._frame
            self._frame = []
            self._queue.append(pickle.loads(memoryview(head)[_FRAME.size :], buffers=buffers))

    @property
    def waiting(self) -> int:
        """Completed messages not popped yet."""
        return len(self._queue)

    def pop(self) -> Any | None:
        try:
            return self._queue.popleft()
        except IndexError:
            return None


class ControlLoop:
    """Owns the hardware and the controller; one instance per loop process."""

    def __init__(self, robot: RobotConfig, conn: Connection) -> None:
        self.robot = robot
        self.conn = conn
        self.config = robot.controller
        self.period_ns = round(1e9 / self.config.update_rate)
        self.ctrl = JointTrajectoryController(self.config)
        self.hardware: HardwareSet = create_hardware_set(robot)
        self.stats = LoopStats(self.config.update_rate)
        self.state_every_ns = round(1e9 / self.config.state_publish_rate)
        self.fault: str | None = None
        self.running = True
        self._version_sent = -1
        self._committed_plan: int | None = None
        self._retired: collections.deque[tuple[Any, Any]] = collections.deque()
        self._next_state_ns = 0
        self._next_status_ns = 0
        self._last_state: JointState | None = None
        self._last_command: JointCommand | None = None
        self._shutdown_reason = "daemon stopping"

    # -- messaging ----------------------------------------------------------------------------

    def send(self, *message: Any) -> None:
        try:
            self.conn.send(message)
        except (OSError, EOFError):
            self.running = False  # the API process is gone: stop safely

    def _report_reference(self) -> None:
        version = self.ctrl.reference_version
        if version == self._version_sent:
            return
        if self._committed_plan is not None:
            self.send("reference", version, None, self._committed_plan)
            self._committed_plan = None
        else:
            self.send("reference", version, self.ctrl.reference, None)
        self._version_sent = version

    def _send_events(self, events: tuple[Event, ...]) -> None:
        if events:
            self.send("events", events)

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self, now_ns: int, *, recover: bool = False) -> None:
        """Configure and activate the hardware, activate the controller (no jump).

        With ``recover``, the hardware clears its latched faults (reboot, fault reset) between
        configuring and activating: the client's explicit re-arm request.
        """
        self.hardware.configure()
        if recover:
            self.hardware.recover()
        last = self.hardware.activate(now_ns)
        state = self.hardware.read(now_ns)
        self.ctrl.activate(now_ns, state, last)
        self._last_state = state

    def _enter_fault(self, now_ns: int, reason: str) -> None:
        self.fault = reason
        log.error("hardware fault: %s; controller stopped, hardware safe action applied", reason)
        self.send("log", logging.ERROR, f"hardware fault: {reason}")
        events: tuple[Event, ...] = ()
        if self.ctrl.active:
            events = self.ctrl.deactivate(now_ns, f"hardware fault: {reason}", abort=True)
        try:
            self.hardware.deactivate(now_ns)
        except JtcHwError as exc:
            log.error("safe action after the fault failed too: %s", exc)
        # The status (with the fault) goes before the goal's result, so that a client that
        # asks for the status on seeing the result finds the fault.
        self.send("status", self.status())
        self._send_events(events)

    def _rearm(self, now_ns: int) -> bool:
        if self.fault is None and self.ctrl.active:
            return False
        # Re-open the devices (a port may have gone away), clear latched faults, then seed
        # the command from the measured position: re-arming never jumps.
        hardware = self.hardware
        if hardware.state is LifecycleState.ACTIVE:
            try:
                hardware.deactivate(now_ns)
            except JtcHwError as exc:
                log.warning("re-arm: deactivating first failed: %s", exc)
        if hardware.state is LifecycleState.INACTIVE:
            try:
                hardware.cleanup()
            except JtcHwError as exc:
                log.warning("re-arm: releasing the devices first failed: %s", exc)
        try:
            self.start(now_ns, recover=True)
        except JtcHwError as exc:
            self.fault = f"re-arm failed: {exc}"
            log.error("%s", self.fault)
            self.send("status", self.status())
            if hardware.state is LifecycleState.ACTIVE:
                try:
                    hardware.deactivate(now_ns)
                except JtcHwError:
                    pass
            raise
        self.fault = None
        log.info("re-armed: holding the measured position")
        self.send("status", self.status())
        return True

    # -- requests -----------------------------------------------------------------------------

    def _handle(self, message: Any, now_ns: int) -> None:
        kind = message[0]
        if kind == "commit":
            _, plan_id, plan = message
            # Freeing megabytes of arrays (munmap) costs hundreds of microseconds: the plan and
            # the reference it replaces are released later, in a cycle's spare time.
            self._retired.append((plan, self.ctrl.reference if self.ctrl.active else None))
            self._commit(plan_id, plan, now_ns)
        elif kind == "request":
            _, request_id, op, args = message
            try:
                value = self._request(op, args, now_ns)
            except JtcHwError as exc:
                self.send("reply", request_id, False, (type(exc).__name__, str(exc)))
            else:
                self.send("reply", request_id, True, value)

    def _commit(self, plan_id: int, plan: Plan, now_ns: int) -> None:
        if self.fault is not None or not self.ctrl.active:
            self.send("stale", plan_id, f"not active: {self.fault or 'controller stopped'}")
            return
        try:
            goal_id = self.ctrl.commit(plan, now_ns)
        except StalePlan as exc:
            self.send("stale", plan_id, str(exc))
            return
        self._committed_plan = plan_id
        self._report_reference()
        self.send("committed", plan_id, goal_id)

    def _request(self, op: str, args: dict[str, Any], now_ns: int) -> Any:
        if op == "cancel":
            return self.ctrl.cancel_goal(int(args["goal_id"]))
        if op == "stop":
            self.ctrl.request_stop()
            return True
        if op == "sim":
            from ..hardware.mirror import MirrorHardware

            component = self.hardware.component(args["component"])
            if not isinstance(component, MirrorHardware):
                raise HardwareError(
                    f"component '{args['component']}' is {component.kind} hardware; only "
                    "simulated (mirror) components can be frozen"
                )
            if args.get("freeze") is not None:
                component.set_frozen(bool(args["freeze"]))
            if args.get("fault"):
                component.inject_fault(str(args["fault"]))
            return True
        if op == "rearm":
            done = self._rearm(now_ns)
            self._report_reference()
            return done
        if op == "shutdown":
            self._shutdown_reason = str(args.get("reason") or self._shutdown_reason)
            self.running = False
            return True
        raise JtcHwError(f"unknown loop request {op!r}")

    # -- the cycle ----------------------------------------------------------------------------

    def cycle(self, now_ns: int, period_ns: int, inbox: _Inbox) -> None:
        """One read -> update -> write at deadline ``now_ns``."""
        message = inbox.pop()
        while message is not None:
            self._handle(message, now_ns)
            message = inbox.pop()
        if self.fault is not None or not self.ctrl.active:
            return
        try:
            state = self.hardware.read(now_ns)
            out = self.ctrl.update(now_ns, period_ns, state)
            self.hardware.write(now_ns, out.command)
        except HardwareError as exc:
            self._enter_fault(now_ns, str(exc))
            self._report_reference()
            return
        self._report_reference()
        self._send_events(out.events)
        if now_ns >= self._next_state_ns:
            self._next_state_ns = now_ns + self.state_every_ns
            self.send(
                "state",
                (
                    now_ns,
                    np.stack(out.desired),
                    state.positions,
                    state.velocities,
                    out.error,
                    out.command,
                    self.ctrl.holding,
                    self.ctrl.active_goal,
                ),
            )

    def status(self) -> dict[str, Any]:
        return {
            "loop": self.stats.snapshot(),
            "hardware": self.hardware.status(),
            "controller": {
                "active": self.ctrl.active,
                "holding": self.ctrl.holding,
                "active_goal": self.ctrl.active_goal,
                "fault": self.fault,
                "reference_version": self.ctrl.reference_version,
            },
        }

    def run(self, inbox: _Inbox) -> None:
        """Cycle until asked to stop or the API process disappears."""
        ticker = Ticker(self.period_ns)
        clock = time.monotonic_ns
        gc.collect()
        gc.freeze()
        gc.disable()
        previous = None
        while self.running:
            deadline, woke, skipped = ticker.wait()
            period = self.period_ns if previous is None else deadline - previous
            previous = deadline
            self.cycle(deadline, period, inbox)
            done = clock()
            self.stats.record(woke - deadline, done - woke, skipped)
            if deadline >= self._next_status_ns:
                self._next_status_ns = deadline + STATUS_PERIOD_NS
                self.send("status", self.status())
            inbox.pump()
            if inbox.closed and not inbox.waiting:  # what arrived before the end goes first
                log.warning("the API process went away: stopping the loop safely")
                self._shutdown_reason = "daemon API process exited"
                self.running = False
            elif deadline + self.period_ns - clock() > GC_SLACK_NS:
                if self._retired:
                    self._retired.popleft()
                else:
                    gc.collect(0)
        self.shutdown(clock())

    def shutdown(self, now_ns: int) -> None:
        """Give the active goal its result, hold, apply the safe action, release hardware."""
        reason = self._shutdown_reason
        if self.ctrl.active:
            events = self.ctrl.deactivate(now_ns, f"{reason}: holding position")
            self._send_events(events)
        try:
            if self.fault is None:
                self.hardware.deactivate(now_ns)
            self.hardware.cleanup()
        except JtcHwError as exc:
            log.error("releasing the hardware failed: %s", exc)
        self.send("status", self.status())


QUIET_LOGGERS = {
    # python-can's socketcand client warns whenever TCP splits a frame across two reads,
    # which is normal and handled: at 1 kHz that would flood the journal.
    "can.interfaces.socketcand.socketcand": logging.ERROR,
}
"""Third-party loggers whose level the loop process raises."""

INBOX_BUDGET_PER_MS = 256 * 1024
"""Bytes the loop reads from the API process per cycle, per millisecond of period."""

LOOP_SWITCH_INTERVAL_S = 0.0001
"""The loop process's interpreter switch interval (``sys.setswitchinterval``), s."""


def loop_main(source: str | dict[str, Any], controller_name: str | None, conn: Connection) -> None:
    """Entry point of the loop process (``multiprocessing`` spawn target).

    Never raises: failures are reported as ``("exit", code)`` with a log line first.
    """
    # The API process coordinates shutdown; a terminal's Ctrl-C or systemd's SIGTERM to the
    # whole group must not kill the loop before the goal got its result and the robot holds.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for name, level in QUIET_LOGGERS.items():
        logging.getLogger(name).setLevel(level)
    # The inbox thread takes the interpreter lock whenever the loop thread releases it (in any
    # system call) and, receiving a large plan, keeps it for up to the switch interval, 5 ms by
    # default: measured, that made a 1 kHz loop skip deadlines under client load. A short
    # interval bounds that wait; it costs nothing while only one thread wants the lock.
    sys.setswitchinterval(LOOP_SWITCH_INTERVAL_S)
    code = 0
    try:
        robot = load_robot(source, controller_name)
        loop = ControlLoop(robot, conn)
        from ..hardware.timing import reduce_timer_slack
        from .realtime import apply_realtime, keep_freed_memory

        rt = robot.daemon.realtime
        for line in apply_realtime(rt.priority, rt.lock_memory, rt.cpu_affinity):
            loop.send("log", logging.INFO, line)
        loop.send("log", logging.INFO, reduce_timer_slack())
        loop.send("log", logging.INFO, keep_freed_memory())
        now = time.monotonic_ns()
        loop.start(now)
        loop._report_reference()  # before "ready": the API process plans against it at once
        loop.send(
            "ready",
            {
                "pid": os.getpid(),
                "t0_ns": now,
                "period_ns": loop.period_ns,
                "hardware": loop.hardware.status(),
            },
        )
        inbox = _Inbox(conn, INBOX_BUDGET_PER_MS * max(1, loop.period_ns // 1_000_000))
        try:
            loop.run(inbox)
        finally:
            inbox.close()
    except JtcHwError as exc:
        log.error("%s", exc)
        _send_quietly(conn, ("log", logging.ERROR, str(exc)))
        code = 2
    except Exception as exc:  # last resort: say what happened, never die silently
        log.exception("control loop crashed")
        _send_quietly(conn, ("log", logging.CRITICAL, f"control loop crashed: {exc!r}"))
        code = 3
    _send_quietly(conn, ("exit", code))


def _send_quietly(conn: Connection, message: tuple[Any, ...]) -> None:
    try:
        conn.send(message)
    except (OSError, EOFError):
        pass
