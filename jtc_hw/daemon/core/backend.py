"""The API process's view of the control loop: a replica reference, planning against it.

Theory of operation
-------------------
``LoopBackend`` implements the ``Backend`` interface the socket server uses, over the loop
process that :class:`~.supervision.LoopProcess` starts and speaks to. Goals are validated and
fitted here, in a worker thread of the API process, against a replica of the loop's reference
(the loop reports every change, in order: ``Reference``). A fitted ``Plan`` is planned for a
time a little ahead of now (``margin``) and sent to the loop, which swaps it in at its next
cycle if the reference has not changed meanwhile and that cycle is not later than the planned
time; otherwise it answers ``Stale`` and we plan again against the newer reference with a
larger margin. ``query_state`` is answered from the replica without involving the loop at
all. A plan is made far enough ahead for its transfer (a bounded amount per cycle), and after
a large one the freed heap is given back to the system (``malloc_trim``, in the planning
thread).

What the loop publishes goes to the backend's observers (:mod:`.observers`: the recorders, the
socket server, the live view, Zenoh), each goal's one result included: the goals the loop
accepted and has not finished are tracked here from ``Committed`` to their result, and if the
loop process dies, each gets one ``ABORTED`` result "control loop died: <how>".

The loop's States (at ``state_publish_rate``) come through the cycle ring, not its pipe: the
loop marks a cycle's row as a State (``CycleRing.write_state``) and a timer here reads them,
half a period after the deadline the next one is due, once the pipe's messages that came before
it have been taken (``LoopProcess.poll``), so they keep their order. Pickling and writing a
State to the pipe cost the loop about a third of its period's p99 (cold at 50 Hz, and the
write wakes this process up; decisions 49). Without shared memory for the ring, the loop
sends them through the pipe as before.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from ...api.events import result_event
from ...config.controller_file import config_to_dict
from ...controller.config import ControllerConfig
from ...controller.goals import ErrorCode, GoalResult, GoalStatus, TrajectoryStopped
from ...controller.limits_check import TimeScaling
from ...controller.messages import JointTrajectory, PointColumns
from ...controller.parameters import ParameterChange, parameters_report, set_parameters
from ...controller.planner import Plan, Planner, in_trajectory_time
from ...controller.tolerances import JointTolerance
from ...controller.trajectory import QueriedState, Trajectory, TrajectorySample
from ...errors import ControllerStateError, GoalRejected, HardwareError
from ..channel.messages import (
    Cancel,
    Committed,
    Events,
    Fault,
    LoopMessage,
    Ready,
    Rearm,
    Reference,
    SetParameters,
    SetSpeedScaling,
    Sim,
    Stale,
    State,
    Status,
    Stop,
)
from ..channel.pipe import Outgoing
from ..realtime import release_freed_memory
from ..robot import RobotConfig, joint_position_limits
from .backend_api import Accepted, Observer
from .observers import Observers, Recorders, state_json
from .supervision import LoopProcess

log = logging.getLogger("jtc_hw.backend")

ATTEMPTS = 5
TRIM_AFTER_BYTES = 16 << 20
"""A plan or replaced reference this large makes the API process return freed memory to the
system afterwards (``realtime.release_freed_memory``, in the planning thread)."""
STATE_READ_MIN_NS = 200_000
"""The States in the ring are read at most this often (a loop faster than 5 kHz, or late)."""
TRIM_DELAY_S = 1.0
"""The freed memory is returned once no large plan has come for this long: the request's
decoded objects have gone by then, and a stream of large goals (one a second) reuses the heap
instead of paying its page faults again at each plan (a 20,000-point plan took 29 ms instead of
15, its planning waiting behind the trim in the planning thread)."""


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


class LoopBackend:
    """Serves the socket server's requests against the loop process's replica."""

    def __init__(self, robot: RobotConfig, source: str | dict[str, Any]) -> None:
        self.robot = robot
        self.config: ControllerConfig = robot.controller
        self.joint_names = tuple(self.config.joints)
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
        self._status: dict[str, Any] = {}
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jtc-hw-plan")
        self._parameters_lock = asyncio.Lock()  # one change at a time, each from the last
        self._period_ns = round(1e9 / self.config.update_rate)
        self._margin_ns = max(5_000_000, 3 * self._period_ns)
        self._plan_ns_per_point = 2_000.0  # planning time per point, learnt from large plans
        self._active_goal: int | None = None
        self._open_goals: dict[int, None] = {}  # committed, no result yet (in commit order)
        self._trim: asyncio.TimerHandle | None = None  # a release of freed memory, scheduled
        self._state_timer: asyncio.TimerHandle | None = None  # the next read of the States
        self._state_next = 0  # the ring's next State to read
        self._state_misses = 0  # reads in a row that found none
        self._states_lost = 0  # States overwritten in the ring before they were read
        self.loop = LoopProcess(source, self.config.name, self._period_ns, self._dispatch,
                                self._loop_ended)
        """The loop process."""
        self.recorders = Recorders(robot.daemon, self.config, self.status)
        """The flight recorder and ``daemon.record`` (the first observer)."""
        self.observers = Observers()
        self.observers.add(self.recorders)

    # -- process ------------------------------------------------------------------------------

    async def start(self) -> Ready:
        """Make the recorders, spawn the loop process and wait until the hardware is active.

        Raises:
            HardwareError: the loop process failed to start (its log says why).
        """
        ready = await self.loop.start(self.recorders.start())
        if self.recorders.ring is not None:
            self._state_timer = asyncio.get_running_loop().call_soon(self._read_states)
        return ready

    def _read_states(self, again: bool = True) -> None:
        """Publish the States the loop marked in the cycle ring since the last call, after the
        loop's messages written before them; again when the next is due (module docstring),
        unless ``again`` is False (and then no more)."""
        ring = self.recorders.ring
        if self._state_timer is not None:
            self._state_timer.cancel()
        self._state_timer = None
        if ring is None:
            return
        states: list[State] = []
        try:
            self.loop.poll()
            states, self._state_next, lost = ring.read_states(self._state_next)
            self._states_lost += lost
            for state in states:
                self._on_state(state)
        except Exception:  # a programming error: said, and the States go on (the loop too)
            log.exception("publishing the control loop's states failed")
        if not again:
            return
        now = time.monotonic_ns()
        period = self._period_ns
        if states:
            # The next state cycle is the first deadline a state period after this one's;
            # half a period later the loop has written it.
            every = math.ceil(1e9 / self.config.state_publish_rate / period) * period
            due, self._state_misses = states[-1].time_ns + every + period // 2, 0
        else:  # late, or not cycling (faulted, stopping): look again, less often after three
            self._state_misses += 1
            due = now + (period if self._state_misses <= 3
                         else round(1e9 / self.config.state_publish_rate))
        self._state_timer = asyncio.get_running_loop().call_at(
            max(due, now + STATE_READ_MIN_NS) / 1e9, self._read_states)

    async def wait_exited(self) -> int:
        """As :meth:`LoopProcess.wait_exited`."""
        return await self.loop.wait_exited()

    async def stop(self, reason: str, record: bool = True) -> int:
        """Ask the loop to finish (goal result, hold, safe action) and wait for it to exit.

        ``record``: the flight recorder writes a ``shutdown`` bag (False for a start that
        failed: nothing ran, nothing to look at; a bag per failed start under a restarting
        service manager would push out the bags worth keeping)."""
        if not self.loop.started:
            self._read_states(again=False)
            self.recorders.close_ring()
            return 0
        if self.loop.running and record:
            self.recorders.trigger("shutdown", due=False)  # written by close()
        await self.loop.stop(reason)  # (the States of a decelerating stop go on meanwhile)
        self._read_states(again=False)  # the loop's last States
        self.recorders.read_ring(again=False)  # the loop's last cycles
        await self.recorders.close()
        self.recorders.close_ring()
        self.loop.close()
        if self._trim is not None:
            self._trim.cancel()
            self._trim = None
        # Waits for a plan or a memory release already running (milliseconds; the interpreter
        # would wait for it at exit anyway); queued ones are dropped: the loop has ended.
        self._executor.shutdown(wait=True, cancel_futures=True)
        return self.loop.exit_code or 0

    @property
    def alive(self) -> bool:
        """The loop process runs and is ready."""
        return self.loop.alive

    @property
    def death(self) -> str | None:
        """Why the loop process ended without being asked to ("control loop died: ...")."""
        return self.loop.death

    @property
    def exit_code(self) -> int | None:
        """The loop process's exit status, once known."""
        return self.loop.exit_code

    @property
    def info(self) -> Ready | None:
        """The loop's ``Ready`` (its pid, start time, period), once it is."""
        return self.loop.info

    @property
    def last_heard_ns(self) -> int:
        """When the loop's last message arrived (monotonic clock, ns)."""
        return self.loop.last_heard_ns

    # -- messages from the loop ---------------------------------------------------------------

    def _loop_ended(self, reason: str) -> None:
        """The loop process ended: exactly one result for every goal it accepted and did not
        finish."""
        now = self.now_ns()
        for goal_id in list(self._open_goals):
            self._finish_goal(GoalResult(goal_id, GoalStatus.ABORTED, ErrorCode.INVALID_GOAL,
                                         reason, now))
        self._active_goal = None

    def _dispatch(self, message: LoopMessage) -> None:
        """A message of the loop (after :class:`LoopProcess` took its part)."""
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
                        self.observers.goal_event(event)
            case Reference(version, trajectory, plan_id):
                replaced = self._ref
                if plan_id is not None:
                    self._ref = self._plans.pop(plan_id).reference
                else:
                    self._ref = trajectory
                self._version = version
                if replaced is not None and replaced.nbytes >= TRIM_AFTER_BYTES:
                    del replaced
                    self._release_memory(TRIM_DELAY_S)
            case Committed(_, goal_id):
                self._active_goal = goal_id
                if goal_id is not None:
                    self._open_goals[goal_id] = None
            case Stale(plan_id):
                self._plans.pop(plan_id, None)
            case Status(status):
                self._status = status
            case Fault():
                self.observers.record({"event": "fault", "text": message.text,
                                    "time_ns": time.monotonic_ns()})
                self.recorders.trigger("fault")
            case Ready(t0_ns=t0):
                initial = self.config.speed_scaling.initial_scaling_factor
                self._timebase = (t0, t0, initial, initial)  # activation: trajectory time = clock

    def _on_state(self, state: State) -> None:
        self._measured = (state.positions, state.velocities)
        self._timebase = (state.time_ns, state.trajectory_time_ns, state.speed_scaling_factor,
                          state.speed_scaling_target)
        if self.observers:
            self.observers.state(state_json(state, self.joint_names))

    def _finish_goal(self, result: GoalResult) -> None:
        if self.recorders.flight is not None:
            result = self.recorders.annotate(result)
            # As recordings keep it (``goal_events``' JSON): the socket's result event.
            self.observers.record(result_event(result))
        self._open_goals.pop(result.goal_id, None)
        if result.goal_id == self._active_goal:
            self._active_goal = None
        self.observers.goal_event(result)
        log.log(
            logging.ERROR if self.death else logging.INFO,
            "goal %d %s (%d): %s%s",
            result.goal_id,
            result.status.value,
            int(result.error_code),
            result.error_string,
            f": {result.details}" if result.details else "",
        )

    # -- Backend interface --------------------------------------------------------------------

    def add_observer(self, observer: Observer) -> None:
        """Also report states, goal events, accepted commands and records to ``observer``
        (after the recorders and the observers added before)."""
        self.observers.add(observer)

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
        info = self.loop.info
        status = dict(self._status, alive=self.alive, loop_pid=None if info is None else info.pid)
        if "controller" in status or self.death:
            controller = dict(status.get("controller", {}), active_goal=self._active_goal)
            if self.death:
                controller.update(active=False, holding=False, fault=self.death)
            status["controller"] = controller
        status.update(self.recorders.status())
        status["plan_memory"] = self.loop.plan_memory()
        status["states_lost"] = self._states_lost
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
        """Plan and commit an action goal (:meth:`Backend.send_goal`); ``time_scaling``
        ``"reject"`` or ``"fit"`` a goal beyond the joint limits (None: ``limits.time_scaling``).

        Raises:
            GoalRejected: invalid goal, beyond the joint limits, or the loop kept refusing the
                plan.
        """
        goal_id, plan = await self._plan_and_commit(
            traj,
            lambda t, ref, ver, now, valid_from: self._planner.plan_goal(
                ref, ver, now, t, path_tolerance, goal_tolerance, goal_time_tolerance,
                valid_from, time_scaling,
            ),
        )
        assert goal_id is not None
        return Accepted.of(goal_id, plan.time_scaling)

    async def send_trajectory(
        self, traj: JointTrajectory, *, time_scaling: str | None = None
    ) -> TimeScaling | None:
        """Plan and commit a topic trajectory; an empty one stops (:meth:`Backend.send_trajectory`).

        Raises:
            GoalRejected: invalid trajectory, beyond the joint limits, or not active.
        """
        if not traj.points:
            await self.loop.request(Stop())
            self.observers.command(traj, None)
            return None
        _, plan = await self._plan_and_commit(
            traj,
            lambda t, ref, ver, now, valid_from: self._planner.plan_trajectory(
                ref, ver, now, t, valid_from, time_scaling),
        )
        return plan.time_scaling

    async def stop_motion(self) -> bool:
        """End any motion and hold; False if the controller is not active (nothing to stop).

        Raises:
            HardwareError: the control loop is not running, or did not answer.
        """
        if not self.alive:
            raise HardwareError("the control loop is not running; nothing commands the motors")
        try:
            await self.loop.request(Stop())
        except GoalRejected:  # the loop's "not active": stopped after a fault, nothing moves
            return False
        return True

    async def cancel_goal(self, goal_id: int) -> bool:
        """Cancel the executing goal ``goal_id``; False if it is not executing."""
        return bool(await self.loop.request(Cancel(goal_id)))

    async def rearm(self) -> bool:
        """Leave a hardware fault (:meth:`Backend.rearm`): the loop re-opens the devices first,
        then clears their latched faults (``recover``) and holds the measured position."""
        rearmed = bool(await self.loop.request(Rearm()))
        if rearmed:
            self.observers.record({"event": "rearm",
                                "text": "re-armed: holding the measured position",
                                "time_ns": time.monotonic_ns()})
            self.recorders.trigger("rearm")
        return rearmed

    async def set_speed_scaling(self, factor: float | None) -> dict[str, float]:
        value: dict[str, float] = await self.loop.request(SetSpeedScaling(factor))
        if self._timebase is not None:
            t, tau, current, _ = self._timebase
            self._timebase = (t, tau, current, value["target"])
        return value

    def get_parameters(self, names: Sequence[str] | None) -> dict[str, Any]:
        return parameters_report(self.config, names)

    async def set_parameters(self, changes: Mapping[str, Any]) -> ParameterChange:
        """Check a change here, once (the configuration file's parser, in the planning
        thread), have the loop's controller switch to the result, then plan with it too.

        The loop gains the checked configuration itself (no second check in its process) and
        applies upstream's timing; goals planned after this returns get the new defaults and
        checks. Changes are serialised, each made from the configuration the previous left.

        Raises:
            ConfigurationError, HardwareError: as :meth:`Backend.set_parameters`; after a
                HardwareError the loop may or may not have applied the change
                (``get_parameters`` shows the API process's copy, unchanged).
            ControllerStateError: the control loop is not running.
        """
        async with self._parameters_lock:
            aio = asyncio.get_running_loop()
            change: ParameterChange = await aio.run_in_executor(
                self._executor, set_parameters, self.config, dict(changes)
            )
            await self.loop.request(SetParameters(change.config))
            self.config = change.config
            self._planner = Planner(change.config)
            return change

    async def sim(self, component: str, freeze: bool | None, fault: str | None = None) -> None:
        await self.loop.request(Sim(component, freeze, fault))

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

    def _release_memory(self, delay_s: float) -> None:
        """Return freed memory to the system in ``delay_s``, in the planning thread (it walks
        the heap: not in the event loop's thread); a pending release is put off to then: one
        release once large plans stop coming."""
        aio = asyncio.get_running_loop()
        if self._trim is not None:
            self._trim.cancel()

        def release() -> None:
            self._trim = None
            # RuntimeError: the executor was shut down, the daemon is stopping
            with contextlib.suppress(RuntimeError):
                aio.run_in_executor(self._executor, release_freed_memory)

        self._trim = aio.call_later(delay_s, release)

    def _transfer_ns(self, nbytes: int) -> int:
        """How much longer than a small plan one of ``nbytes`` takes to reach the loop, which
        reads a bounded amount of it per cycle (:class:`~.pipe.Inbox`) unless it comes in shared
        memory; the base margin covers the cycle a small plan waits for."""
        return self.loop.transfer_cycles(nbytes) * self._period_ns

    def _plan_and_share(
        self, plan_id: int, make: Callable[..., Plan], *args: Any
    ) -> tuple[Plan, Outgoing]:
        """In the planning thread: the plan, and its records for the loop (a large one copied
        into shared memory), in one hop from the event loop and back."""
        plan = make(*args)
        return plan, self.loop.prepare(plan_id, plan)

    async def _plan_and_commit(
        self, sent: JointTrajectory, make: Callable[..., Plan]
    ) -> tuple[int | None, Plan]:
        """Check ``sent`` against the position limits, plan it in trajectory time with
        ``make(trajectory, reference, version, now_ns, valid_from_ns)`` (in the planning
        thread) and commit the plan; once committed the observers see ``sent`` as the client
        sent it. Returns the plan's goal id (None: a topic trajectory) and the plan."""
        check_position_limits(sent, self._position_limits)
        traj = sent
        if self._timebase is not None:
            t, tau, factor, _ = self._timebase
            traj = in_trajectory_time(sent, t, tau, factor)
        points = len(traj.points)
        aio = asyncio.get_running_loop()
        # Plan far enough ahead for the plan to reach the loop: a 2,000-point plan is 2.4 MB,
        # several cycles of the loop's inbox budget.
        expected = Trajectory.nbytes_for(points + 1, len(self.joint_names))
        planning = round(2 * self._plan_ns_per_point * points)  # twice the usual: seldom late
        margin = self._margin_ns + planning + self._transfer_ns(expected)
        for _attempt in range(ATTEMPTS):
            refused = self.loop.refusal()
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
            plan_id = self.loop.next_id()
            try:
                plan, outgoing = await aio.run_in_executor(
                    self._executor, self._plan_and_share, plan_id, make, traj, ref, version,
                    *self._plan_times(planned, valid_from),
                )
            except OSError as exc:  # no shared memory to be had, or the loop ended meanwhile
                raise GoalRejected(
                    self.loop.refusal() or f"the plan could not be handed to the loop: {exc}"
                ) from None
            took = self.now_ns() - begin
            if points >= 100:  # fixed costs are noise by then
                self._plan_ns_per_point += 0.25 * (took / points - self._plan_ns_per_point)
            transfer = self._transfer_ns(plan.reference.nbytes)
            if self.now_ns() + transfer + self._margin_ns // 2 > planned:
                # Fitting and sending it take longer than the margin: plan later (without
                # sending a plan the loop would refuse as late).
                margin = max(2 * margin, took + transfer + self._margin_ns)
                outgoing.close()
                continue
            self._plans[plan_id] = plan
            try:
                reply = await self.loop.commit(plan_id, outgoing)
            except ControllerStateError as exc:  # the loop died before it answered
                raise GoalRejected(str(exc)) from None
            if plan.reference.nbytes >= TRIM_AFTER_BYTES:
                self._release_memory(TRIM_DELAY_S)  # the fitting's temporaries, the request
            match reply:
                case Committed(goal_id=goal_id):
                    self.observers.command(sent, goal_id)
                    return goal_id, plan
                case Stale(reason=reason) if reason.startswith("not active"):
                    raise GoalRejected(f"the controller is {reason}")
                case Stale(reason=reason):
                    margin = 2 * margin + took
                    log.debug("plan %d was stale (%s); planning again", plan_id, reason)
        raise GoalRejected(
            f"the control loop kept refusing the plan ({ATTEMPTS} attempts); the reference "
            "changes too often or planning is too slow for this goal's size"
        )


