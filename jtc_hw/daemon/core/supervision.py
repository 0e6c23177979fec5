"""The loop process as the API process sees it: spawned, spoken to without waiting, watched.

Theory of operation
-------------------
:class:`LoopProcess` spawns the loop process (``jtc_hw.daemon.loop.cycle.loop_main``) on one duplex
pipe and waits for its ``Ready``. From then on it is the only one that talks to it:

- out: ``Commit`` and ``Request`` records (:mod:`.messages`), written without blocking by a
  :class:`~.pipe.PlanWriter` (a request before what is left of a plan, see :mod:`.pipe`);
- in: the loop's messages, read without blocking (:class:`~.pipe.Inbox`). It answers the
  futures waiting for a ``Committed``/``Stale`` or a ``Reply``/``Failed`` (a failure raised
  again as its own class), logs the loop's ``Log`` and ``Fault`` lines, and hands every
  message on to its owner (``on_message``: the backend's replica and observers).

The loop's death is a result, not a silence: when its process ends (its sentinel) without
having been asked to stop, :attr:`LoopProcess.death` says how ("control loop died: <how>"),
the owner is told (``on_ended``, before anything else: every goal the loop accepted gets its
one ``ABORTED`` result there), the requests and plans still waiting fail with that reason, new
ones are refused with it, and :meth:`LoopProcess.wait_exited` returns, so that the service
exits non-zero (systemd restarts it). Meanwhile the device-side watchdogs stop the motors.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import multiprocessing
import os
import signal
import socket
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from ...controller.planner import Plan
from ...errors import ControllerStateError, HardwareError, JtcHwError
from ..channel.messages import (
    Commit,
    Committed,
    Exit,
    Failed,
    Fault,
    Log,
    LoopMessage,
    LoopOp,
    Ready,
    Released,
    Reply,
    Request,
    Shutdown,
    Stale,
)
from ..channel.pipe import SHARED_MIN_BYTES, Inbox, Outgoing, PlanWriter, prepare
from ..channel.shared import IDLE_S, SHARED_AVAILABLE, SharedPool
from ..loop.cycle import INBOX_SPARE, inbox_budget, loop_main

__all__ = ["LoopProcess"]

log = logging.getLogger("jtc_hw.backend")

# The loop process's start (a spawned interpreter importing numpy and the drivers, then the
# hardware's configure and activate). JTC_HW_LOOP_START_TIMEOUT_S raises it where a machine
# is known to be far slower, as tools/vcan-hil's software-emulated VM (issue 15).
START_TIMEOUT_S = float(os.environ.get("JTC_HW_LOOP_START_TIMEOUT_S", "30"))
REQUEST_TIMEOUT_S = 5.0
REAP_TIMEOUT_S = 5.0
"""Bound on reaping the loop process once its sentinel says it ended (microseconds in practice)."""
READ_BUDGET_BYTES = 1 << 20
"""Bytes of the loop's messages read per wake-up of the event loop (more: it wakes again)."""
PIPE_READ_BYTES_PER_S = 1e9
"""A conservative rate of the loop's reads from the pipe (2 GB/s measured on a busy 2-core VM),
for planning far enough ahead of a large plan's arrival."""
PLAN_SEND_BUFFER_BYTES = 4 << 20
"""Socket send buffer asked for the pipe to the loop (the kernel caps it at ``wmem_max``)."""


def _grow_send_buffer(conn: Connection) -> int:
    """Ask for a larger send buffer on our end of the pipe to the loop; the one granted.

    The loop reads whatever has arrived once a cycle: with the default buffer (~208 kB) that
    is all a cycle gets of a plan, so a 2.4 MB plan takes a dozen cycles however large the
    loop's budget.

    Raises:
        OSError: the socket refused the option (not expected for a Unix socket).
    """
    sock = socket.socket(fileno=os.dup(conn.fileno()))
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, PLAN_SEND_BUFFER_BYTES)
        return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF))
    finally:
        sock.close()


class LoopProcess:
    """Starts, speaks to and watches the loop process.

    Args:
        source: the robot configuration (a path or a mapping), loaded again by the loop.
        controller_name: the controller to run.
        period_ns: the loop's period.
        on_message: every message of the loop, after this class has taken its part (answers
            resolved, log lines logged).
        on_ended: the loop process ended (the reason every open goal is aborted with).
    """

    def __init__(self, source: str | dict[str, Any], controller_name: str | None,
                 period_ns: int, on_message: Callable[[LoopMessage], None],
                 on_ended: Callable[[str], None]) -> None:
        self._source = source
        self._controller_name = controller_name
        self._period_ns = period_ns
        self._on_message = on_message
        self._on_ended = on_ended
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[Committed | Stale | Reply | Failed]] = {}
        self._ready: asyncio.Future[Ready] | None = None
        self._exited: asyncio.Future[int] | None = None
        self._conn: Connection | None = None
        self._process: multiprocessing.process.BaseProcess | None = None
        self._inbox: Inbox | None = None
        self._writer: PlanWriter | None = None
        self._pool: SharedPool | None = None  # the shared memory large plans travel in
        self._trim: asyncio.TimerHandle | None = None  # dropping its idle regions, pending
        self._writing = False  # waiting for the pipe to be writable (add_writer)
        self._stopping = False
        self._last_error: str | None = None  # the loop's last error log line
        # An error the loop logged before Ready: why the start fails, said by start()'s
        # exception (the daemon's "cannot start: ..."), logged here only if the start goes on.
        self._start_error: tuple[int, str] | None = None
        self.bytes_per_cycle = 1 << 18
        """What the loop reads of a plan per cycle (set by :meth:`start`)."""
        self.death: str | None = None
        """Why the loop process ended without being asked to ("control loop died: ...")."""
        self.last_heard_ns = 0
        self.info: Ready | None = None
        """The loop's ``Ready`` (its pid, start time, period), once it is."""
        self.exit_code: int | None = None

    # -- lifecycle ----------------------------------------------------------------------------

    async def start(self, ring_name: str | None) -> Ready:
        """Spawn the loop process and wait until the hardware is active.

        Args:
            ring_name: the cycle ring the loop writes every cycle into (None: none).

        Raises:
            HardwareError: the loop process failed to start (its log says why).
        """
        aio = asyncio.get_running_loop()
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe(duplex=True)
        self._conn = parent
        # What the loop reads of a plan per cycle: its budget, the time it may read for at a
        # conservative copy rate, and what the socket can hold (it reads what has arrived).
        reading_s = (1 - INBOX_SPARE - 0.1) * self._period_ns / 1e9  # minus the cycle itself
        self.bytes_per_cycle = min(
            _grow_send_buffer(parent),
            inbox_budget(self._period_ns),
            round(PIPE_READ_BYTES_PER_S * reading_s),
        )
        self._ready = aio.create_future()
        self._exited = aio.create_future()
        self._process = ctx.Process(
            target=loop_main,
            args=(self._source, self._controller_name, child, ring_name),
            name="jtc-hw-loop",
            daemon=True,
        )
        self._process.start()
        child.close()
        self._inbox = Inbox(parent, READ_BUDGET_BYTES, framed=False)
        self._writer = PlanWriter(parent)
        self._pool = SharedPool() if SHARED_AVAILABLE else None
        aio.add_reader(parent.fileno(), self._readable)
        aio.add_reader(self._process.sentinel, self._process_ended)
        waiters: set[asyncio.Future[Any]] = {self._ready, self._exited}
        done, _ = await asyncio.wait(
            waiters, timeout=START_TIMEOUT_S, return_when=asyncio.FIRST_COMPLETED
        )
        if self._ready in done:
            self.info = self._ready.result()
            return self.info
        if done and self._start_error is not None:
            # The loop exited; its last error says why (a busy device, a bad parameter), once:
            # in this exception, which the daemon logs.
            self._start_error = None
            raise HardwareError(self._last_error or "the control loop did not start")
        self._log_start_error()
        if done:
            raise HardwareError(self._last_error or "the control loop did not start (see the log "
                                "above)")
        raise HardwareError(
            f"the control loop did not become ready within {START_TIMEOUT_S:.0f} s"
        )

    def _log_start_error(self) -> None:
        """Log the error the loop reported while starting, if the start did not end with it."""
        if self._start_error is not None:
            level, text = self._start_error
            self._start_error = None
            log.log(level, "%s", text)

    @property
    def started(self) -> bool:
        """:meth:`start` has spawned the process."""
        return self._process is not None and self._exited is not None

    @property
    def alive(self) -> bool:
        """The loop process runs and is ready."""
        return (
            self._process is not None
            and self._process.is_alive()
            and self._exited is not None
            and not self._exited.done()
        )

    @property
    def running(self) -> bool:
        """Started and not seen to have ended."""
        return self._exited is not None and not self._exited.done()

    async def wait_exited(self) -> int:
        """Until the loop process has ended (asked to or not); its exit status.

        Raises:
            ControllerStateError: the loop was never started.
        """
        if self._exited is None:
            raise ControllerStateError("the control loop was never started")
        return await asyncio.shield(self._exited)

    async def stop(self, reason: str) -> None:
        """Ask the loop to finish (goal result, hold, safe action), wait for it to exit (or
        terminate it after 10 s and the decelerating stop's bound) and reap it."""
        if self._process is None or self._exited is None:
            return
        self._stopping = True
        if not self._exited.done():
            stopping_s = 0.0  # a decelerating stop the loop finishes first (its bound)
            try:
                reply = await self.request(Shutdown(reason))
                if isinstance(reply, float):
                    stopping_s = reply
            except JtcHwError as exc:
                log.warning("shutdown request: %s", exc)
            try:
                await asyncio.wait_for(asyncio.shield(self._exited), timeout=10.0 + stopping_s)
            except asyncio.TimeoutError:  # the builtin TimeoutError from 3.11 on
                log.error("the control loop did not stop within 10 s; terminating it")
                self._process.terminate()
        await asyncio.get_running_loop().run_in_executor(None, self._process.join, 5.0)
        if not self._exited.done():  # its sentinel was not seen (yet): settle the goals now
            self._loop_ended(self._process.exitcode)

    def close(self) -> None:
        """Stop watching the process and close the pipe (after :meth:`stop`)."""
        aio = asyncio.get_running_loop()
        if self._process is not None:
            with contextlib.suppress(ValueError, OSError):
                aio.remove_reader(self._process.sentinel)
        if self._conn is not None:
            with contextlib.suppress(ValueError, OSError):
                aio.remove_reader(self._conn.fileno())
            if self._inbox is not None:
                self._inbox.close()
                self._inbox = None
            if self._writer is not None:
                if self._writing:
                    with contextlib.suppress(ValueError, OSError):
                        aio.remove_writer(self._conn.fileno())
                    self._writing = False
                self._writer.close()
                self._writer = None
            self._conn.close()
            self._conn = None
        self._close_pool()

    def _close_pool(self) -> None:
        if self._trim is not None:
            self._trim.cancel()
            self._trim = None
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    def _released(self, tokens: tuple[int, ...]) -> None:
        """The loop unmapped these regions: reusable now; dropped if idle for ``IDLE_S``."""
        pool = self._pool
        if pool is None:
            return
        pool.released(tokens)
        if self._trim is None:
            aio = asyncio.get_running_loop()

            def trim() -> None:
                self._trim = None
                if self._pool is not pool:
                    return
                # Freeing tens of megabytes takes milliseconds: not in the event loop.
                # (RuntimeError: the executor was shut down, the daemon is stopping.)
                with contextlib.suppress(RuntimeError):
                    done = aio.run_in_executor(None, pool.trim)
                    done.add_done_callback(
                        lambda _: self._released(()) if pool.free_bytes else None
                    )

            self._trim = aio.call_later(IDLE_S, trim)

    # -- messages from the loop ---------------------------------------------------------------

    def poll(self) -> None:
        """Take what the loop has written so far, without waiting (as when its pipe is
        readable): the messages before a State read from the cycle ring go first."""
        self._readable()

    def _readable(self) -> None:
        inbox = self._inbox
        if inbox is None or self._conn is None:
            return
        inbox.pump()
        while (message := inbox.pop()) is not None:
            self._dispatch(message)
        if inbox.closed:
            # The end of the pipe: the process is ending. Its sentinel says when it has.
            asyncio.get_running_loop().remove_reader(self._conn.fileno())

    def _dispatch(self, message: LoopMessage) -> None:
        self.last_heard_ns = time.monotonic_ns()
        match message:
            case Committed(plan_id) | Stale(plan_id):
                self._answer(plan_id, message)
            case Reply(request_id) | Failed(request_id):
                self._answer(request_id, message)
            case Log(level, text):
                self._on_log(level, text)
            case Fault():
                self._on_log(logging.ERROR, message.text)
            case Ready():
                self._log_start_error()
                if self._ready is not None and not self._ready.done():
                    self._ready.set_result(message)
            case Released(tokens):
                self._released(tokens)
            case Exit(code):
                # The process is ending; its sentinel settles the goals (_process_ended).
                self.exit_code = code
        self._on_message(message)

    def _answer(self, waiter: int, message: Committed | Stale | Reply | Failed) -> None:
        """Resolve the future waiting for ``message`` (a plan's or a request's), if any."""
        future = self._waiting.pop(waiter, None)
        if future is not None and not future.done():
            future.set_result(message)

    def _on_log(self, level: int, text: str) -> None:
        """A log line of the loop: logged (before ``Ready``, an error is kept as the start's
        reason instead); an error is the loop's last."""
        if level >= logging.ERROR and self._ready is not None and not self._ready.done():
            self._log_start_error()  # an earlier one did not stop the start: say it
            self._start_error = (level, text)
        else:
            log.log(level, "%s", text)
        if level >= logging.ERROR:
            self._last_error = text

    def _process_ended(self) -> None:
        """The loop process has exited: take what it wrote before, then settle every goal."""
        aio = asyncio.get_running_loop()
        assert self._process is not None
        aio.remove_reader(self._process.sentinel)
        # Its descriptors (the sentinel) close a moment before it can be reaped: with a
        # timeout, join waits for that moment (blocking waitpid), where join(0) could miss it.
        self._process.join(REAP_TIMEOUT_S)
        code = self._process.exitcode
        inbox = self._inbox
        if inbox is not None and self._conn is not None and not inbox.closed:
            # Nothing more can arrive: read to the end (at most the socket's buffer).
            for _ in range(64):
                self._readable()
                if inbox.closed or self._inbox is None:
                    break
        self._loop_ended(code)

    def _loop_ended(self, code: int | None) -> None:
        asked = self._stopping and self.exit_code == 0
        if self.exit_code is None or code not in (0, None):
            self.exit_code = 3 if code is None else code
        if not asked:
            self.death = f"control loop died: {_describe_exit(code, self.exit_code)}"
            if self._last_error and self.exit_code > 0:
                self.death += f" ({self._last_error})"
            if self._ready is not None and self._ready.done():
                log.critical("%s; the device watchdogs stop the motors", self.death)
        reason = self.death or "control loop exited"
        # Exactly one result for every goal the loop accepted and did not finish.
        self._on_ended(reason)
        for future in self._waiting.values():
            if not future.done():
                future.set_exception(ControllerStateError(reason))
        self._waiting.clear()
        self._close_pool()  # nothing reads it any more
        if self._exited is not None and not self._exited.done():
            self._exited.set_result(self.exit_code)

    # -- messages to the loop -----------------------------------------------------------------

    def refusal(self) -> str | None:
        """Why nothing can be sent to the loop now, or ``None``."""
        if self.death:
            return f"{self.death}; the daemon is exiting (its service manager restarts it)"
        if self._conn is None or not self.alive:
            return "the control loop is not running"
        return None

    def plan_memory(self) -> dict[str, Any] | None:
        """The shared memory large plans travel in (``get_status``'s ``plan_memory``), or
        ``None`` when plans go through the pipe (no ``memfd`` on this system)."""
        return None if self._pool is None else self._pool.status()

    def transfer_cycles(self, nbytes: int) -> int:
        """Cycles a plan of ``nbytes`` takes to reach the loop beyond the one it waits for:
        none in shared memory, else the loop's read budget per cycle sets it."""
        if SHARED_AVAILABLE and nbytes >= SHARED_MIN_BYTES:
            return 0
        return -(-nbytes // self.bytes_per_cycle) - 1

    def next_id(self) -> int:
        """A new id for a plan or a request (one sequence: their answers share a table)."""
        return next(self._ids)

    def _send(self, message: Request | Outgoing) -> None:
        """Queue ``message`` for the loop (a request, or a plan :meth:`prepare` made ready:
        owned from now on), write what the pipe takes now, and the rest when it becomes
        writable (module docstring).

        Raises:
            ControllerStateError: the loop is not running (:meth:`refusal`), or just exited.
        """
        reason = self.refusal()
        if reason is not None:
            if isinstance(message, Outgoing):
                message.close()
            raise ControllerStateError(reason)
        writer = self._writer
        assert self._conn is not None and writer is not None
        writer.put(message)
        self._write()
        if writer.closed:
            # The loop is gone (its death is being reported by _process_ended).
            raise ControllerStateError(self.refusal() or "the control loop exited")

    def _write(self) -> None:
        writer, conn = self._writer, self._conn
        if writer is None or conn is None:
            return
        done = writer.flush() or writer.closed
        if done == (not self._writing):
            return
        aio = asyncio.get_running_loop()
        if done:
            aio.remove_writer(conn.fileno())
            self._writing = False
        else:
            aio.add_writer(conn.fileno(), self._write)
            self._writing = True

    async def request(self, op: LoopOp) -> Any:
        """Have the loop do ``op``; what it returns.

        Raises:
            JtcHwError: the loop's error (``Failed.exception``).
            HardwareError: the loop did not answer within ``REQUEST_TIMEOUT_S``.
            ControllerStateError: the loop is not running (or died meanwhile).
        """
        request_id = self.next_id()
        future = asyncio.get_running_loop().create_future()
        self._waiting[request_id] = future
        self._send(Request(request_id, op))
        try:
            answer = await asyncio.wait_for(future, REQUEST_TIMEOUT_S)
        except asyncio.TimeoutError:  # the builtin TimeoutError from 3.11 on
            self._waiting.pop(request_id, None)
            raise HardwareError(
                f"the control loop did not answer {op.name!r} within 5 s") from None
        match answer:
            case Reply(value=value):
                return value
            case Failed():
                raise answer.exception()
        raise HardwareError(f"the control loop answered {op.name!r} with {answer!r}")

    def prepare(self, plan_id: int, plan: Plan) -> Outgoing:
        """``plan`` (its id from :meth:`next_id`) made ready for :meth:`commit`: pickled, a
        large one's arrays copied into shared memory (milliseconds for tens of megabytes: call
        it in a worker thread). Thread-safe.

        Raises:
            OSError: no shared memory could be had (out of memory, or the loop ended).
        """
        return prepare(Commit(plan_id, plan), SHARED_MIN_BYTES, self._pool)

    async def commit(self, plan_id: int, outgoing: Outgoing) -> Committed | Stale:
        """Send the plan :meth:`prepare` made ready (owned from now on) and wait for the
        loop's answer.

        Raises:
            ControllerStateError: the loop is not running, or died before it answered.
            TimeoutError: no answer within ``REQUEST_TIMEOUT_S``.
        """
        future = asyncio.get_running_loop().create_future()
        self._waiting[plan_id] = future
        try:
            self._send(outgoing)
            answer = await asyncio.wait_for(future, REQUEST_TIMEOUT_S)
        except ControllerStateError:
            self._waiting.pop(plan_id, None)
            raise
        if not isinstance(answer, Committed | Stale):
            raise HardwareError(f"the control loop answered a plan with {answer!r}")
        return answer


def _describe_exit(code: int | None, status: int) -> str:
    """How a process ended, from its ``exitcode`` (negative: the signal that killed it)."""
    if code is not None and code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {status}"
