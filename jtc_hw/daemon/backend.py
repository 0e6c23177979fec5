"""The API process's view of the control loop: planning, a replica reference, the loop process.

Theory of operation
-------------------
``LoopBackend`` starts the loop process (``jtc_hw.daemon.loop``) and implements the ``Backend``
interface the socket server uses. Goals are validated and fitted here, in a worker thread of
the API process, against a replica of the loop's reference (the loop reports every change, in
order). A fitted ``Plan`` is planned for a time a little ahead of now (``margin``) and sent to
the loop, which swaps it in at its next cycle if the reference has not changed meanwhile and
that cycle is not later than the planned time; otherwise it answers "stale" and we plan again
against the newer reference with a larger margin. ``query_state`` is answered from the replica
without involving the loop at all.

The loop's messages are read without blocking (:class:`~.pipe.Inbox`), whatever the loop has
written in part; plans and requests are written without blocking (:class:`~.pipe.PlanWriter`,
the rest when the pipe is writable), a request before what is left of a plan, so the event
loop never waits for the loop to read a plan of megabytes. A plan is made far enough ahead
for its transfer (a bounded amount per cycle), and after a large one the freed heap is given
back to the system (``malloc_trim``, in the planning thread).

The loop's death is a result, not a silence: when its process ends (its sentinel) without
having been asked to stop, every goal it accepted and has not finished (tracked here from
``committed`` to its result) gets one ``ABORTED`` result "control loop died: <how>" through
the listener, a goal being planned or committed is refused, the status
reports the fault, new goals and requests are refused with that reason, and
:meth:`LoopBackend.wait_exited` returns, so that the service exits non-zero (systemd restarts
it). Meanwhile the device-side watchdogs stop the motors.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import logging
import math
import multiprocessing
import os
import signal
import socket
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from multiprocessing.connection import Connection
from typing import Any, Protocol

import numpy as np

from ..controller.config import ControllerConfig
from ..controller.config_io import (
    ParameterChange,
    config_to_dict,
    parameters_report,
    set_parameters,
)
from ..controller.controller import Plan, Planner, in_trajectory_time
from ..controller.goals import (
    ErrorCode,
    GoalFeedback,
    GoalResult,
    GoalStatus,
    TrajectoryStopped,
)
from ..controller.joints import JointCommand
from ..controller.limits_check import TimeScaling
from ..controller.tolerances import JointTolerance
from ..controller.trajectory import (
    JointTrajectory,
    PointColumns,
    QueriedState,
    Trajectory,
    TrajectorySample,
)
from ..errors import (
    ControllerStateError,
    GoalRejected,
    HardwareError,
    JtcHwError,
)
from .backend_api import Accepted
from .cyclering import READ_PERIOD_S, RING_S, CycleRing, remove_stale
from .messages import (
    Cancel,
    Commit,
    Committed,
    Events,
    Exit,
    Failed,
    Fault,
    Log,
    LoopOp,
    Ready,
    Rearm,
    Reference,
    Reply,
    Request,
    SetParameters,
    SetSpeedScaling,
    Shutdown,
    Sim,
    Stale,
    State,
    Status,
    Stop,
)
from .pipe import Inbox, PlanWriter
from .robot import RobotConfig, joint_position_limits

log = logging.getLogger("jtc_hw.backend")

ATTEMPTS = 5
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
TRIM_AFTER_BYTES = 16 << 20
"""A plan or replaced reference this large makes the API process return freed memory to the
system afterwards (``realtime.release_freed_memory``, in the planning thread)."""
TRIM_DELAY_S = 0.5
"""After a large plan is committed: time for the request's decoded objects to go first."""
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


class Listener(Protocol):
    """Receives what the loop publishes (called in the asyncio thread)."""

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None: ...

    def on_state(self, snapshot: dict[str, Any]) -> None: ...


class Tap(Protocol):
    """Also receives what the loop publishes, and every accepted command (the live view, a
    recorder): called in the asyncio thread after the listener; must not block or raise."""

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None: ...

    def on_state(self, snapshot: dict[str, Any]) -> None: ...

    def on_command(self, traj: JointTrajectory, goal_id: int | None) -> None: ...


def _vector(a: Any) -> list[float | None] | None:
    if a is None:
        return None
    return [float(x) if np.isfinite(x) else None for x in np.asarray(a, dtype=float)]


def _command_json(command: JointCommand) -> dict[str, list[float | None] | None]:
    """The configured interfaces of a command (NaN, "nothing", as null)."""
    return {
        name: _vector(getattr(command, name))
        for name in ("positions", "velocities", "accelerations", "effort")
        if getattr(command, name) is not None
    }


def check_position_limits(
    traj: JointTrajectory, limits: Mapping[str, tuple[float, float]]
) -> None:
    """Refuse a trajectory whose waypoint positions lie outside the hardware's
    ``position_limits`` (the drivers would clamp the command there, and the goal would then
    fail on its tolerances, or worse, press a joint into its end stop).

    Only the waypoints are checked (the splines between them are issue 12's joint limits);
    joints the controller does not know are left to the controller's own validation.

    Raises:
        GoalRejected: INVALID_GOAL naming the point, the joint, the position and the limits.
    """
    checked = [(k, name) for k, name in enumerate(traj.joint_names) if name in limits]
    if not checked or not traj.points:
        return
    points = traj.points
    if isinstance(points, PointColumns):
        column = points.values("positions")
        if column is None:
            return
        positions, present = column
    else:
        width = len(traj.joint_names)
        rows = [p.positions if p.positions is not None and len(p.positions) == width else None
                for p in points]
        present = np.array([row is not None for row in rows], dtype=bool)
        if not present.any():
            return
        positions = np.array([row if row is not None else (0.0,) * width for row in rows],
                             dtype=np.float64)
    columns = [k for k, _ in checked]
    low = np.array([limits[name][0] for _, name in checked])
    high = np.array([limits[name][1] for _, name in checked])
    values = positions[:, columns]
    bad = present[:, None] & ((values < low) | (values > high))
    if not bad.any():
        return
    i, j = (int(x) for x in np.argwhere(bad)[0])
    name = checked[j][1]
    raise GoalRejected(
        f"point {i}: joint '{name}' position {values[i, j]:g} rad is outside its "
        f"position_limits [{low[j]:g}, {high[j]:g}] (hardware configuration); send a "
        "trajectory within the limits",
        int(ErrorCode.INVALID_GOAL),
    )


FLIGHT_AFTER_S = 1.0
"""The flight recorder's bags go on this long after their trigger (``jtc_hw.rec.flight``)."""


class LoopBackend:
    """Runs the loop process and serves the socket server's requests."""

    def __init__(self, robot: RobotConfig, source: str | dict[str, Any]) -> None:
        self.robot = robot
        self.config: ControllerConfig = robot.controller
        self.joint_names = tuple(self.config.joints)
        self._source = source
        self._planner = Planner(self.config)
        self._position_limits = joint_position_limits(robot)
        self._ref: Trajectory | None = None
        # The last measured positions and velocities the loop published (query_state carries
        # them before the reference's start, as upstream's current state).
        self._measured: tuple[Any, Any] | None = None
        # Speed scaling: (clock ns, trajectory time ns, factor, target) of the loop's latest
        # state; the reference (and so every plan) is in trajectory time.
        self._timebase: tuple[int, int, float, float] | None = None
        self._version = -1
        self._plans: dict[int, Plan] = {}
        self._waiting: dict[int, asyncio.Future[Committed | Stale | Reply | Failed]] = {}
        self._ids = itertools.count(1)
        self._listener: Listener | None = None
        self._taps: list[Tap] = []
        self._status: dict[str, Any] = {}
        self._ready: asyncio.Future[Ready] | None = None
        self._exited: asyncio.Future[int] | None = None
        self._conn: Connection | None = None
        self._process: multiprocessing.process.BaseProcess | None = None
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jtc-hw-plan")
        self._parameters_lock = asyncio.Lock()  # one change at a time, each from the last
        self._period_ns = round(1e9 / self.config.update_rate)
        self._margin_ns = max(5_000_000, 3 * self._period_ns)
        self._bytes_per_cycle = 1 << 18  # what the loop reads of a plan per cycle (start())
        self._plan_ns_per_point = 2_000.0  # planning time per point, learnt from large plans
        self._active_goal: int | None = None
        self._open_goals: dict[int, None] = {}  # committed, no result yet (in commit order)
        self._inbox: Inbox | None = None
        self._writer: PlanWriter | None = None
        self._writing = False  # waiting for the pipe to be writable (add_writer)
        self._trim: asyncio.TimerHandle | None = None  # a release of freed memory, scheduled
        self._stopping = False
        self._last_error: str | None = None  # the loop's last error log line
        # An error the loop logged before "ready": why the start fails, said by start()'s
        # exception (the daemon's "cannot start: ..."), logged here only if the start goes on.
        self._start_error: tuple[int, str] | None = None
        self.death: str | None = None
        """Why the loop process ended without being asked to ("control loop died: ...")."""
        self.last_heard_ns = 0
        self.info: Ready | None = None
        """The loop's ``Ready`` (its pid, start time, period), once it is."""
        self.exit_code: int | None = None
        self.flight: Any = None
        """The flight recorder (``jtc_hw.rec.flight.FlightRecorder``), made by ``start``."""
        self.recording: Any = None
        """``daemon.record``'s recorder (``jtc_hw.rec.continuous``), made by ``start``."""
        self._ring: CycleRing | None = None  # every cycle's row, from the loop (start)
        self._ring_next = 0  # the ring's next row to copy
        self._ring_timer: asyncio.TimerHandle | None = None

    # -- process ------------------------------------------------------------------------------

    async def start(self) -> Ready:
        """Spawn the loop process and wait until the hardware is active.

        Raises:
            HardwareError: the loop process failed to start (its log says why).
        """
        from ..rec.flight import FlightRecorder
        from .loop import INBOX_SPARE, inbox_budget, loop_main

        d = self.robot.daemon
        tolerances = {joint: {"path": c.trajectory, "goal": c.goal}
                      for joint, c in self.config.constraints.joints.items()}
        self.flight = FlightRecorder(d.flight_recorder_dir, d.flight_recorder_s,
                                     d.flight_recorder_keep, self.config.name, tolerances,
                                     cycle_rate_hz=self.config.update_rate,
                                     joint_names=self.joint_names)
        if self.flight.available:
            # Every cycle's row, for the flight recorder (see .cyclering): created here, the
            # owner, and removed by _close once the loop has ended.
            for name in remove_stale():
                log.info("removed %s, the cycle ring of a daemon that was killed", name)
            try:
                self._ring = CycleRing.create(
                    len(self.joint_names), max(64, math.ceil(RING_S * self.config.update_rate)))
            except OSError as exc:
                log.warning("flight recorder: no shared memory for every cycle (%s); it keeps "
                            "the published states instead", exc)
                self.flight.cycle_rate_hz = None
        if d.record is not None:
            from ..rec.continuous import ContinuousRecorder

            self.recording = ContinuousRecorder(d.record, self.config.name, self.status,
                                                tolerances)
        aio = asyncio.get_running_loop()
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe(duplex=True)
        self._conn = parent
        # What the loop reads of a plan per cycle: its budget, the time it may read for at a
        # conservative copy rate, and what the socket can hold (it reads what has arrived).
        reading_s = (1 - INBOX_SPARE - 0.1) * self._period_ns / 1e9  # minus the cycle itself
        self._bytes_per_cycle = min(
            _grow_send_buffer(parent),
            inbox_budget(self._period_ns),
            round(PIPE_READ_BYTES_PER_S * reading_s),
        )
        self._ready = aio.create_future()
        self._exited = aio.create_future()
        self._process = ctx.Process(
            target=loop_main,
            args=(self._source, self.config.name, child,
                  None if self._ring is None else self._ring.name),
            name="jtc-hw-loop",
            daemon=True,
        )
        self._process.start()
        child.close()
        self._inbox = Inbox(parent, READ_BUDGET_BYTES, framed=False)
        self._writer = PlanWriter(parent)
        aio.add_reader(parent.fileno(), self._readable)
        aio.add_reader(self._process.sentinel, self._process_ended)
        if self._ring is not None:
            self._ring_timer = aio.call_later(READ_PERIOD_S, self._read_ring)
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

    async def wait_exited(self) -> int:
        """Until the loop process has ended (asked to or not); its exit status.

        Raises:
            ControllerStateError: the loop was never started.
        """
        if self._exited is None:
            raise ControllerStateError("the control loop was never started")
        return await asyncio.shield(self._exited)

    async def stop(self, reason: str, record: bool = True) -> int:
        """Ask the loop to finish (goal result, hold, safe action) and wait for it to exit.

        ``record``: the flight recorder writes a ``shutdown`` bag (False for a start that
        failed: nothing ran, nothing to look at; a bag per failed start under a restarting
        service manager would push out the bags worth keeping)."""
        if self._process is None or self._exited is None:
            self._close_ring()
            return 0
        self._stopping = True
        if self.flight is not None and not self._exited.done() and record:
            self.flight.trigger("shutdown")
        if not self._exited.done():
            stopping_s = 0.0  # a decelerating stop the loop finishes first (its bound)
            try:
                reply = await self._request(Shutdown(reason))
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
        self._read_ring(again=False)  # the loop's last cycles
        if self.flight is not None:  # the shutdown's bag, with what came after the trigger
            await asyncio.get_running_loop().run_in_executor(None, self.flight.close)
        if self.recording is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.recording.close)
        self._close()
        return self.exit_code or 0

    def _read_ring(self, again: bool = True) -> None:
        """Copy the cycles the loop wrote since the last time into the flight recorder;
        again in ``READ_PERIOD_S`` unless ``again`` is False."""
        ring = self._ring
        if ring is None:
            return
        rows, self._ring_next, lost = ring.read(self._ring_next)
        if self.flight is not None:
            self.flight.on_cycles(rows, ring.layout, lost)
        if again and self._ring_timer is not None:
            self._ring_timer = asyncio.get_running_loop().call_later(
                READ_PERIOD_S, self._read_ring)

    def _close_ring(self) -> None:
        """Stop reading the cycle ring and remove it (the loop process has ended)."""
        if self._ring_timer is not None:
            self._ring_timer.cancel()
            self._ring_timer = None
        if self._ring is not None:
            self._ring.close()
            self._ring = None

    def _close(self) -> None:
        aio = asyncio.get_running_loop()
        self._close_ring()
        if self._process is not None:
            try:
                aio.remove_reader(self._process.sentinel)
            except (ValueError, OSError):
                pass
        if self._conn is not None:
            try:
                aio.remove_reader(self._conn.fileno())
            except (ValueError, OSError):
                pass
            if self._inbox is not None:
                self._inbox.close()
                self._inbox = None
            if self._writer is not None:
                if self._writing:
                    try:
                        aio.remove_writer(self._conn.fileno())
                    except (ValueError, OSError):
                        pass
                    self._writing = False
                self._writer.close()
                self._writer = None
            self._conn.close()
            self._conn = None
        if self._trim is not None:
            self._trim.cancel()
            self._trim = None
        self._executor.shutdown(wait=False)

    @property
    def alive(self) -> bool:
        """The loop process runs and is ready."""
        return (
            self._process is not None
            and self._process.is_alive()
            and self._exited is not None
            and not self._exited.done()
        )

    # -- messages from the loop ---------------------------------------------------------------

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
        now = self.now_ns()
        for goal_id in list(self._open_goals):
            self._finish_goal(GoalResult(goal_id, GoalStatus.ABORTED, ErrorCode.INVALID_GOAL,
                                         reason, now))
        self._active_goal = None
        self._fail_waiting(reason)
        if self._exited is not None and not self._exited.done():
            self._exited.set_result(self.exit_code)

    def _dispatch(self, message: Any) -> None:
        self.last_heard_ns = time.monotonic_ns()
        match message:
            case State():
                self._on_state(message)
            case Events(events):
                for event in events:
                    if isinstance(event, TrajectoryStopped):
                        log.warning("topic trajectory stopped: %s%s", event.reason,
                                    f": {event.details}" if event.details else "")
                    elif isinstance(event, GoalResult):
                        self._finish_goal(event)
                    else:
                        if self._listener is not None:
                            self._listener.on_goal_event(event)
                        self._tap("on_goal_event", event)
            case Reference(version, trajectory, plan_id):
                replaced = self._ref
                if plan_id is not None:
                    self._ref = self._plans.pop(plan_id).reference
                else:
                    self._ref = trajectory
                self._version = version
                if replaced is not None and replaced.nbytes >= TRIM_AFTER_BYTES:
                    del replaced
                    self._release_memory(0.0)
            case Committed(plan_id, goal_id):
                self._active_goal = goal_id
                if goal_id is not None:
                    self._open_goals[goal_id] = None
                self._answer(plan_id, message)
            case Stale(plan_id):
                self._answer(plan_id, message)
                self._plans.pop(plan_id, None)
            case Reply(request_id) | Failed(request_id):
                self._answer(request_id, message)
            case Status(status):
                self._status = status
            case Log(level, text):
                self._on_log(level, text)
            case Fault():
                self._on_log(logging.ERROR, message.text)
                self._record_event({"event": "fault", "text": message.text,
                                    "time_ns": time.monotonic_ns()})
                if self.flight is not None:
                    self._flight_trigger("fault")
            case Ready(t0_ns=t0):
                self._log_start_error()
                initial = self.config.speed_scaling.initial_scaling_factor
                self._timebase = (t0, t0, initial, initial)  # activation: trajectory time = clock
                if self._ready is not None and not self._ready.done():
                    self._ready.set_result(message)
            case Exit(code):
                # The process is ending; its sentinel settles the goals (_process_ended).
                self.exit_code = code

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

    def _on_state(self, state: State) -> None:
        self._measured = (state.positions, state.velocities)
        self._timebase = (state.time_ns, state.trajectory_time_ns, state.speed_scaling_factor,
                          state.speed_scaling_target)
        if (
            self._listener is not None
            or self._taps
            or self.flight is not None
            or self.recording is not None
        ):
            snapshot = self._snapshot(state)
            if self.flight is not None and self._ring is None:
                self.flight.on_state(snapshot)  # (with the ring, it has every cycle)
            if self.recording is not None:
                self.recording.on_state(snapshot)
            if self._listener is not None:
                self._listener.on_state(snapshot)
            self._tap("on_state", snapshot)

    def _snapshot(self, state: State) -> dict[str, Any]:
        desired, error = state.desired, state.error
        return {
            "time_ns": state.time_ns,
            "joint_names": list(self.joint_names),
            "desired": {
                "positions": _vector(desired[0]),
                "velocities": _vector(desired[1]),
                "accelerations": _vector(desired[2]),
                "effort": _vector(desired[3]),
                "time_from_start": state.reference_time_from_start,
            },
            "actual": {
                "positions": _vector(state.positions),
                "velocities": _vector(state.velocities),
                "accelerations": _vector(state.accelerations),
                "time_from_start": state.feedback_time_from_start,
            },
            "error": {
                "positions": _vector(error[0]),
                "velocities": _vector(error[1]),
                "accelerations": _vector(error[2]),
            },
            "command": _command_json(state.command),
            "output": _command_json(state.output),
            "holding": state.holding,
            "active_goal": state.active_goal,
            "speed_scaling": {"factor": state.speed_scaling_factor,
                              "target": state.speed_scaling_target},
        }

    def _finish_goal(self, result: GoalResult) -> None:
        if self.flight is not None:
            result = self._flight_result(result)
        self._open_goals.pop(result.goal_id, None)
        if result.goal_id == self._active_goal:
            self._active_goal = None
        if self._listener is not None:
            self._listener.on_goal_event(result)
        self._tap("on_goal_event", result)
        log.log(
            logging.ERROR if self.death else logging.INFO,
            "goal %d %s (%d): %s%s",
            result.goal_id,
            result.status.value,
            int(result.error_code),
            result.error_string,
            f": {result.details}" if result.details else "",
        )

    def _record_command(self, traj: JointTrajectory, goal_id: int | None = None) -> None:
        """An accepted command, as received, for ``/<controller>/joint_trajectory`` (converted
        to a message in the recorders' worker threads: a large goal costs the event loop
        nothing here), and for the socket's subscribers of commands (``jtc-hw record``)."""
        on_command = getattr(self._listener, "on_command", None)
        if on_command is not None:
            try:
                on_command(traj, goal_id)
            except Exception:  # a listener must never fail a goal that the loop accepted
                log.exception("sending an accepted command to the subscribers failed")
        now = time.monotonic_ns()
        if self.flight is not None:
            self.flight.on_command(traj, now)
        if self.recording is not None:
            self.recording.on_command(traj, now)

    def _flight_trigger(self, reason: str, now_ns: int | None = None) -> str | None:
        """Trigger the flight recorder; a timer writes the bag a second later even if no state
        comes (a faulted loop publishes none)."""
        path: str | None = self.flight.trigger(reason, now_ns)
        if path is not None:
            asyncio.get_running_loop().call_later(FLIGHT_AFTER_S + 0.05, self._flight_due)
        return path

    def _flight_due(self) -> None:
        """A trigger's second has passed: take the cycles written since the last read of the
        ring (up to 100 ms of them), then let the flight recorder write what is due."""
        self._read_ring(again=False)
        if self.flight is not None:
            self.flight.poll(time.monotonic_ns())

    def _flight_result(self, result: GoalResult) -> GoalResult:
        """Record the result; an abort triggers the flight recorder and its details name the
        bag (``flight recorder: PATH``)."""
        path = None
        if result.status is GoalStatus.ABORTED:
            path = self._flight_trigger("aborted", result.time_ns)
            if path is not None:
                note = f"flight recorder: {path}"
                result = dataclasses.replace(
                    result, details=f"{result.details}; {note}" if result.details else note)
        event = {
            "event": "result", "goal_id": result.goal_id, "status": result.status.value,
            "error_code": int(result.error_code), "error_string": result.error_string,
            "details": result.details, "time_ns": result.time_ns,
        }
        self._record_event(event)
        return result

    def _record_event(self, event: dict[str, Any]) -> None:
        """A result, fault or re-arm (``goal_events``' JSON, docs/recording.md) for the
        recorders: the flight recorder, ``daemon.record`` and the socket's subscribers of
        commands (``jtc-hw record``)."""
        if self.flight is not None:
            self.flight.on_event(event)
        if self.recording is not None:
            self.recording.on_event(event)
        on_record = getattr(self._listener, "on_record", None)
        if on_record is not None:
            try:
                on_record(event)
            except Exception:  # a listener must never fail the loop's bookkeeping
                log.exception("sending a recorded event to the subscribers failed")

    def _fail_waiting(self, reason: str) -> None:
        for future in self._waiting.values():
            if not future.done():
                future.set_exception(ControllerStateError(reason))
        self._waiting.clear()

    # -- Backend interface --------------------------------------------------------------------

    def set_listener(self, listener: Listener) -> None:
        """Where goal events and state snapshots go."""
        self._listener = listener

    def add_tap(self, tap: Tap) -> None:
        """Also send state snapshots, goal events and accepted commands to ``tap``."""
        self._taps.append(tap)

    def _tap(self, method: str, *args: Any) -> None:
        for tap in self._taps:
            try:
                getattr(tap, method)(*args)
            except Exception:
                # A tap (a view, a recorder) must never stop the loop's messages reaching
                # the clients.
                log.exception("%s.%s failed; skipped", type(tap).__name__, method)

    def now_ns(self) -> int:
        """The daemon's clock (CLOCK_MONOTONIC, shared by both processes)."""
        return time.monotonic_ns()

    def hello(self) -> dict[str, Any]:
        """Static facts for a new client."""
        return {
            "joint_names": list(self.joint_names),
            "update_rate": self.config.update_rate,
            "state_publish_rate": self.config.state_publish_rate,
            "action_monitor_rate": self.config.action_monitor_rate,
            "now_ns": self.now_ns(),
        }

    def config_dict(self) -> dict[str, Any]:
        """The controller configuration in its plain form, plus hardware and daemon sections."""
        return {
            "controller": config_to_dict(self.config),
            "hardware": [
                {"name": h.name, "kind": h.kind, "joints": list(h.joints)}
                for h in self.robot.hardware
            ],
        }

    def status(self) -> dict[str, Any]:
        """The loop's statistics and hardware status (refreshed at 2 Hz); the active goal is
        tracked from commits and results, so it is current. ``alive``: the loop process runs;
        ``loop_pid``: its pid; after its death, ``controller.fault`` says how it died."""
        status = dict(self._status, alive=self.alive,
                      loop_pid=None if self.info is None else self.info.pid)
        if "controller" in status or self.death:
            controller = dict(status.get("controller", {}), active_goal=self._active_goal)
            if self.death:
                controller.update(active=False, holding=False, fault=self.death)
            status["controller"] = controller
        if self.flight is not None:
            status["flight_recorder"] = self.flight.status()
        if self.recording is not None:
            status["recording"] = {"file": str(self.recording.path),
                                   "errors": self.recording.errors,
                                   "stopped": self.recording.stopped}
        return status

    def query_state(self, time_ns: int) -> QueriedState:
        """``query_state`` at ``time_ns`` from the replica reference (see
        ``JointTrajectoryController.query_state``); before the reference's start it carries
        the last published measured state (before any: the reference's first state).

        Raises:
            ControllerStateError: the loop has not reported a reference yet.
        """
        ref = self._ref
        if ref is None:
            raise ControllerStateError("the controller is not active yet")
        first = ref.sample(ref.state_before_ns)
        current = first
        if self._measured is not None:
            positions, velocities = self._measured
            zero = np.zeros(len(self.joint_names))
            current = TrajectorySample(
                np.asarray(positions, dtype=np.float64),
                zero if velocities is None else np.asarray(velocities, dtype=np.float64),
                zero,
                zero,
            )
        return ref.query(self._trajectory_time(time_ns), current)

    async def send_goal(
        self,
        traj: JointTrajectory,
        path_tolerance: Sequence[JointTolerance] = (),
        goal_tolerance: Sequence[JointTolerance] = (),
        goal_time_tolerance: float = 0.0,
        *,
        time_scaling: str | None = None,
    ) -> Accepted:
        """Plan and commit an action goal.

        Args:
            time_scaling: ``"reject"`` or ``"fit"`` a goal beyond the joint limits (None:
                ``limits.time_scaling``).

        Returns:
            The goal's id, and how it was fitted to the joint limits.

        Raises:
            GoalRejected: invalid goal, beyond the joint limits, or the loop kept refusing the
                plan.
        """
        check_position_limits(traj, self._position_limits)
        sent = traj  # as the client sent it (the taps see it so: stamped on the clock)
        traj = self._stamp_in_trajectory_time(traj)
        made: list[Plan] = []  # the last plan made is the one committed

        def make(ref: Trajectory, ver: int, now: int, valid_from: int) -> Plan:
            plan = self._planner.plan_goal(
                ref,
                ver,
                now,
                traj,
                path_tolerance,
                goal_tolerance,
                goal_time_tolerance,
                valid_from,
                time_scaling,
            )
            made.append(plan)
            return plan

        goal_id = await self._plan_and_commit(make, len(traj.points))
        assert goal_id is not None
        self._tap("on_command", sent, goal_id)
        self._record_command(sent, goal_id)
        return Accepted.of(goal_id, made[-1].time_scaling)

    async def send_trajectory(
        self, traj: JointTrajectory, *, time_scaling: str | None = None
    ) -> TimeScaling | None:
        """Plan and commit a topic trajectory; an empty one stops.

        Args:
            time_scaling: as for ``send_goal``.

        Returns:
            How it was fitted to the joint limits (None: as sent, or a stop).

        Raises:
            GoalRejected: invalid trajectory, beyond the joint limits, or not active.
        """
        if not traj.points:
            await self._request(Stop())
            self._record_command(traj)
            return None
        check_position_limits(traj, self._position_limits)
        sent = traj
        traj = self._stamp_in_trajectory_time(traj)
        made: list[Plan] = []

        def make(ref: Trajectory, ver: int, now: int, valid_from: int) -> Plan:
            plan = self._planner.plan_trajectory(ref, ver, now, traj, valid_from, time_scaling)
            made.append(plan)
            return plan

        await self._plan_and_commit(make, len(traj.points))
        self._tap("on_command", sent, None)
        self._record_command(sent)
        return made[-1].time_scaling

    async def stop_motion(self) -> bool:
        """End any motion and hold; False if the controller is not active (nothing to stop).

        Raises:
            HardwareError: the control loop is not running, or did not answer.
        """
        if not self.alive:
            raise HardwareError("the control loop is not running; nothing commands the motors")
        try:
            await self._request(Stop())
        except GoalRejected:  # the loop's "not active": stopped after a fault, nothing moves
            return False
        return True

    async def cancel_goal(self, goal_id: int) -> bool:
        """Cancel the executing goal ``goal_id``; False if it is not executing."""
        return bool(await self._request(Cancel(goal_id)))

    async def rearm(self) -> bool:
        """Leave a hardware fault: re-open the devices, clear their latched faults
        (``recover``) and hold the measured position.

        Raises:
            HardwareError: re-arming failed (the controller stays stopped).

        Returns:
            False if there was nothing to re-arm (no fault, the controller is running).
        """
        rearmed = bool(await self._request(Rearm()))
        if rearmed:
            self._record_event({"event": "rearm",
                                "text": "re-armed: holding the measured position",
                                "time_ns": time.monotonic_ns()})
            if self.flight is not None:
                self._flight_trigger("rearm")
        return rearmed

    async def set_speed_scaling(self, factor: float | None) -> dict[str, float]:
        """Set the speed scaling factor's target in the loop's controller (``None``: resume,
        back to the factor before the pause); it ramps there from the loop's next cycle.

        Returns:
            ``{"factor": in force now, "target": what it ramps to}``.

        Raises:
            ConfigurationError: not a number in ``[0, speed_scaling.max_scaling_factor]``.
            HardwareError: the control loop did not answer.
        """
        value: dict[str, float] = await self._request(SetSpeedScaling(factor))
        if self._timebase is not None:
            t, tau, current, _ = self._timebase
            self._timebase = (t, tau, current, value["target"])
        return value

    def get_parameters(self, names: Sequence[str] | None) -> dict[str, Any]:
        """Controller parameters in effect (``config_io.parameters_report``).

        Raises:
            ConfigurationError: a name is not a parameter.
        """
        return parameters_report(self.config, names)

    async def set_parameters(self, changes: Mapping[str, Any]) -> ParameterChange:
        """Check a change here, once (the configuration file's parser, in the planning
        thread), have the loop's controller switch to the result, then plan with it too.

        The loop gains the checked configuration itself (no second check in its process) and
        applies upstream's timing; goals planned after this returns get the new defaults and
        checks. Changes are serialised, each made from the configuration the previous left.

        Raises:
            ConfigurationError: an unknown or read-only parameter or a bad value; nothing
                changed.
            ControllerStateError: the control loop is not running.
            HardwareError: the control loop did not answer (it may or may not have applied
                the change; ``get_parameters`` shows the API process's copy, unchanged).
        """
        async with self._parameters_lock:
            aio = asyncio.get_running_loop()
            change: ParameterChange = await aio.run_in_executor(
                self._executor, set_parameters, self.config, dict(changes)
            )
            await self._request(SetParameters(change.config))
            self.config = change.config
            self._planner = Planner(change.config)
            return change

    async def sim(self, component: str, freeze: bool | None, fault: str | None = None) -> None:
        """Freeze or release a simulated component's feedback; returns once the loop did.

        Raises:
            ConfigurationError: no component of that name.
            HardwareError: the component is not simulated hardware.
        """
        await self._request(Sim(component, freeze, fault))

    # -- internals ----------------------------------------------------------------------------

    def _trajectory_time(self, wall_ns: int) -> int:
        """Trajectory time at clock time ``wall_ns``, extrapolated from the loop's last state
        at the factor then in force (exact while the factor has always been 1)."""
        if self._timebase is None:
            return wall_ns
        t, tau, factor, _ = self._timebase
        return tau + (wall_ns - t if factor == 1.0 else round((wall_ns - t) * factor))

    def _plan_times(self, planned_ns: int, valid_from_ns: int) -> tuple[int, int]:
        """A plan's planned and valid-from times (clock) in trajectory time, bounding where
        the loop's trajectory time can be when the plan arrives: at most the last known one
        advanced at the larger of the factor and its target, at least the last known one."""
        if self._timebase is None:
            return planned_ns, valid_from_ns
        t, tau, factor, target = self._timebase
        fastest = max(factor, target)
        if fastest == 1.0 and t == tau:
            return planned_ns, valid_from_ns  # never scaled: trajectory time is the clock
        planned = tau + round((planned_ns - t) * fastest)
        return planned, min(tau, tau + round((valid_from_ns - t) * min(factor, target)))

    def _stamp_in_trajectory_time(self, traj: JointTrajectory) -> JointTrajectory:
        if self._timebase is None:
            return traj
        t, tau, factor, _ = self._timebase
        return in_trajectory_time(traj, t, tau, factor)

    def _refusal(self) -> str | None:
        """Why nothing can be sent to the loop now, or ``None``."""
        if self.death:
            return f"{self.death}; the daemon is exiting (its service manager restarts it)"
        if self._conn is None or not self.alive:
            return "the control loop is not running"
        return None

    def _send(self, message: Commit | Request, bulk: bool = False) -> None:
        """Queue ``message`` for the loop and write what the pipe takes now; the rest is written
        when it becomes writable (the event loop never waits for the loop to read a plan).
        A request (not ``bulk``) goes before what is left of a plan being written."""
        reason = self._refusal()
        if reason is not None:
            raise ControllerStateError(reason)
        writer = self._writer
        assert self._conn is not None and writer is not None
        writer.put(message, bulk)
        self._write()
        if writer.closed:
            # The loop is gone (its death is being reported by _process_ended).
            raise ControllerStateError(self._refusal() or "the control loop exited")

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

    async def _request(self, op: LoopOp) -> Any:
        """Have the loop do ``op``; what it returns.

        Raises:
            JtcHwError: the loop's error (``Failed.exception``).
            HardwareError: the loop did not answer within ``REQUEST_TIMEOUT_S``.
            ControllerStateError: the loop is not running (or died meanwhile).
        """
        request_id = next(self._ids)
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

    def _release_memory(self, delay_s: float) -> None:
        """Return freed memory to the system in ``delay_s``, in the planning thread (it walks
        the heap: not in the event loop's thread); one pending release covers them all."""
        if self._trim is not None:
            return
        from .realtime import release_freed_memory

        aio = asyncio.get_running_loop()

        def release() -> None:
            self._trim = None
            try:
                aio.run_in_executor(self._executor, release_freed_memory)
            except RuntimeError:  # the executor was shut down: the daemon is stopping
                pass

        self._trim = aio.call_later(delay_s, release)

    def _transfer_ns(self, nbytes: int) -> int:
        """How much longer than a small plan one of ``nbytes`` takes to reach the loop, which
        reads a bounded amount of it per cycle (:class:`~.pipe.Inbox`); the base margin covers
        the cycle a small plan waits for."""
        return (-(-nbytes // self._bytes_per_cycle) - 1) * self._period_ns

    async def _plan_and_commit(self, make: Any, points: int) -> int | None:
        aio = asyncio.get_running_loop()
        # Plan far enough ahead for the plan to reach the loop: a 2,000-point plan is 2.4 MB,
        # several cycles of the loop's inbox budget.
        expected = Trajectory.nbytes_for(points + 1, len(self.joint_names))
        planning = round(2 * self._plan_ns_per_point * points)  # twice the usual: seldom late
        margin = self._margin_ns + planning + self._transfer_ns(expected)
        for _attempt in range(ATTEMPTS):
            refused = self._refusal()
            if refused is not None:
                raise GoalRejected(refused)
            if self._ref is None:
                raise GoalRejected("the controller is not active yet")
            ref, version = self._ref, self._version
            begin = self.now_ns()
            planned = begin + margin
            # The loop may commit as soon as the plan arrives, at a cycle whose deadline can lie
            # up to a period before now: keep the current reference from there.
            valid_from = begin - 2 * self._period_ns
            plan: Plan = await aio.run_in_executor(
                self._executor, make, ref, version, *self._plan_times(planned, valid_from)
            )
            took = self.now_ns() - begin
            if points >= 100:  # fixed costs are noise by then
                self._plan_ns_per_point += 0.25 * (took / points - self._plan_ns_per_point)
            transfer = self._transfer_ns(plan.reference.nbytes)
            if self.now_ns() + transfer + self._margin_ns // 2 > planned:
                # Fitting and sending it take longer than the margin: plan later (without
                # sending a plan the loop would refuse as late).
                margin = max(2 * margin, took + transfer + self._margin_ns)
                continue
            plan_id = next(self._ids)
            self._plans[plan_id] = plan
            future = aio.create_future()
            self._waiting[plan_id] = future
            try:
                self._send(Commit(plan_id, plan), bulk=True)
                reply = await asyncio.wait_for(future, REQUEST_TIMEOUT_S)
            except ControllerStateError as exc:  # the loop died before it answered
                self._waiting.pop(plan_id, None)
                raise GoalRejected(str(exc)) from None
            if plan.reference.nbytes >= TRIM_AFTER_BYTES:
                self._release_memory(TRIM_DELAY_S)  # the fitting's temporaries, the request
            match reply:
                case Committed(goal_id=goal_id):
                    return goal_id
                case Stale(reason=reason) if reason.startswith("not active"):
                    raise GoalRejected(f"the controller is {reason}")
                case Stale(reason=reason):
                    margin = 2 * margin + took
                    log.debug("plan %d was stale (%s); planning again", plan_id, reason)
                case _:
                    raise HardwareError(f"the control loop answered a plan with {reply!r}")
        raise GoalRejected(
            f"the control loop kept refusing the plan ({ATTEMPTS} attempts); the reference "
            "changes too often or planning is too slow for this goal's size"
        )


def _describe_exit(code: int | None, status: int) -> str:
    """How a process ended, from its ``exitcode`` (negative: the signal that killed it)."""
    if code is not None and code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {status}"
