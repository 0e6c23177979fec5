"""The control loop process: read -> update -> write at absolute deadlines, nothing else.

Theory of operation
-------------------
The loop runs in its own process so that API work (parsing, fitting a 2,000-point goal,
serving clients) never shares an interpreter lock with it. It talks to the API process over
one duplex ``multiprocessing`` connection, in the records :mod:`.messages` draws (in:
``Commit`` and ``Request``, framed by ``pipe.PlanWriter``; out: everything else).

Every change of the controller's reference is reported, in order, so the API process keeps an
exact replica to plan against: a committed plan by its id (the API process made it), a hold by
value (a constant trajectory, a few bytes). The loop process has a single thread: after each
cycle it reads whatever has arrived, a bounded amount, without blocking (:class:`~.pipe.Inbox`),
and the next cycle pops the completed messages. What it sends goes through a
:class:`~.outbox.Outbox`, written at the end of each cycle without ever blocking: the loop never
waits for the API process. If the API process stops reading for ``daemon.api_stall_s``, the loop
ends the active goal, holds and refuses new goals, cycling on, until the API process has read
the backlog (docs/safety.md, "API stall"). Before it configures any hardware, the loop process
locks every device its components drive (``HardwareInterface.devices()``, :mod:`.locks`): a
second daemon on the same hardware stops there, having sent nothing.

One cycle at deadline ``t``: drain requests -> ``hardware.read(t)`` -> ``controller.update`` ->
``hardware.write`` -> report events; a state snapshot at ``state_publish_rate`` (a slot of the
cycle ring; without one, pickled into the outbox and written by the next cycle), statistics at
2 Hz. After it, before ``t + period``: write the outbox, read the inbox (a bounded amount) and
handle what that completed at ``t`` (a plan committed, a request served, their answers written
at once), then free or collect in spare time. The controller's clock is the deadline grid;
how late the process woke is measured and published, never fed into the control law. Garbage
collection is disabled in the loop and run explicitly (generation 0) when a cycle has slack.

Shutdown (the ``shutdown`` request: SIGTERM, SIGINT): the active goal gets its result, the
controller is deactivated (velocity, acceleration and effort commands 0), the hardware applies
its safe action and is released. With ``constraints.decelerate_on_cancel`` the loop first keeps
cycling through the controller's decelerating stop until the joints are at rest (a cycle after
the one that wrote the rest command has read them, also when deadlines were skipped), at most the
stop's duration plus ``SHUTDOWN_STOP_MARGIN_S`` (and ``SHUTDOWN_STOP_MAX_S``), refusing new
goals meanwhile.
"""

from __future__ import annotations

import collections
import contextlib
import gc
import logging
import math
import os
import signal
import sys
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from ...controller.controller import JointTrajectoryController
from ...controller.goals import Event
from ...controller.joints import JointCommand, JointState
from ...controller.planner import Plan
from ...errors import HardwareError, JtcHwError, StalePlan
from ...hardware import HardwareSet, LifecycleState
from ...hardware.mirror import MirrorHardware
from ...hardware.timing import reduce_timer_slack
from ..channel.cyclering import CycleRing
from ..channel.messages import (
    Cancel,
    Commit,
    Committed,
    Events,
    Exit,
    Failed,
    Fault,
    Log,
    LoopMessage,
    LoopOp,
    Ready,
    Rearm,
    Reference,
    Released,
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
from ..channel.pipe import Inbox
from ..locks import DeviceLock, lock_devices
from ..logs import quiet_third_party_loggers
from ..realtime import (
    apply_realtime,
    disable_huge_pages,
    keep_freed_memory,
    set_process_name,
)
from ..robot import RobotConfig, create_hardware_set, load_robot
from .clock import Ticker
from .outbox import Outbox
from .phases import PhaseRecorder
from .stats import LoopStats

log = logging.getLogger("jtc_hw.loop")

STATUS_PERIOD_NS = 500_000_000
GC_SLACK_NS = 300_000  # run a gen-0 collection only with this much time left before the deadline
OUTBOX_CAPACITY_BYTES = 1 << 20
"""Ordered bytes the loop keeps for a stalled API process before it ends the active goal
(beyond what the socket buffers; about 200 kB on Linux). Each cycle queues a few hundred bytes
of ordered messages at most (a goal's feedback at ``action_monitor_rate``), so ``api_stall_s``
normally ends the goal long before this bound."""
EXIT_DRAIN_S = 5.0
"""How long the ending loop waits for the API process to take its last messages."""
SHUTDOWN_STOP_MARGIN_S = 0.5
"""With ``constraints.decelerate_on_cancel``, a shutdown waits for the decelerating stop: at
most the stop's duration (as the last measured velocities give it) plus this margin, which
covers a velocity that grew in the cycle before the stop began."""
SHUTDOWN_STOP_MAX_S = 5.0
"""...and never longer than this, so that the daemon exits well within systemd's
``TimeoutStopSec=10``; a longer stop is cut short there by the deactivation and the hardware's
safe action, as without decelerating stops."""


class ControlLoop:
    """Owns the hardware and the controller; one instance per loop process."""

    def __init__(self, robot: RobotConfig, outbox: Outbox, ring: CycleRing | None = None
                 ) -> None:
        self.robot = robot
        self.outbox = outbox
        self.ring = ring
        """Every cycle's row goes here (the flight recorder's full-rate feed), if given."""
        self.config = robot.controller
        self.period_ns = round(1e9 / self.config.update_rate)
        self.ctrl = JointTrajectoryController(self.config)
        self.hardware: HardwareSet = create_hardware_set(robot)
        joint_index = {joint: i for i, joint in enumerate(self.hardware.joints)}
        self._component_joints = [
            np.array([joint_index[j] for j in comp.joints], dtype=np.intp)
            for comp in self.hardware.components
        ]
        # Upstream's speed scaling interfaces (docs/behaviour.md, "Speed scaling"): the
        # factor read from a component's scalar state interface before each update, the one
        # asked for written to its scalar command interface before each write.
        scaling = self.config.speed_scaling
        self._scaling_state = (self.hardware.scalar_interface(scaling.state_interface, "state")
                               if scaling.state_interface else None)
        self._scaling_command = (
            self.hardware.scalar_interface(scaling.command_interface, "command")
            if scaling.command_interface else None)
        self.stats = LoopStats(self.config.update_rate)
        self.state_every_ns = round(1e9 / self.config.state_publish_rate)
        self.fault: str | None = None
        self.fault_cause: str | None = None
        """The hardware fault that stopped the controller, kept while re-arms fail (``fault``
        then says why the last re-arm failed): what a successful re-arm recovered from."""
        self.running = True
        self._version_sent = -1
        self._committed_plan: int | None = None
        self._retired: collections.deque[tuple[Any, Any]] = collections.deque()
        self._next_state_ns = 0
        self._state_cycle = False  # this cycle published a State (serve_outbox)
        self._next_status_ns = 0
        self._last_state: JointState | None = None
        self._shutdown_reason = "daemon stopping"
        self._stopping_until_ns: int | None = None  # a shutdown waiting for its stop: the cap
        self._rest_written_ns: int | None = None  # that stop's cycle writing the rest command
        self._stop_seen_ns = 0  # that stop's last cycle (its start, before the first)
        self._stop_skipped = 0  # deadlines the loop skipped during that stop
        self.inbox_spare_ns = round(INBOX_SPARE * self.period_ns)
        self.api_stall_ns = round(robot.daemon.api_stall_s * 1e9)
        self.api_stalled = False
        self.api_stalls = 0
        self.locks: list[DeviceLock] = []
        self.collect_garbage = gc.collect
        self.phases: PhaseRecorder | None = None
        """Set before :meth:`run` to time each phase of the period (``phases.PHASES_ENV``)."""

    # -- messaging ----------------------------------------------------------------------------

    def send(self, message: LoopMessage) -> None:
        """Queue an ordered message (never dropped); written at the end of the cycle.

        Raises:
            pickle.PicklingError: the message cannot be pickled (a programming error).
        """
        self.outbox.put(message)

    def publish(self, message: State | Status) -> None:
        """Queue a droppable message (``State``, the periodic ``Status``): while the API
        process lags, a newer one of the same class replaces it.

        Raises:
            pickle.PicklingError: the message cannot be pickled (a programming error).
        """
        self.outbox.put(message, key=type(message))

    def _report_reference(self) -> None:
        version = self.ctrl.reference_version
        if version == self._version_sent:
            return
        if self._committed_plan is not None:
            self.send(Reference(version, None, self._committed_plan))
            self._committed_plan = None
        else:
            self.send(Reference(version, self.ctrl.reference, None))
        self._version_sent = version

    def _send_events(self, events: tuple[Event, ...]) -> None:
        if events:
            self.send(Events(events))

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
        self.fault = self.fault_cause = reason
        log.error("hardware fault: %s; controller stopped, hardware safe action applied", reason)
        self.send(Fault(reason))
        events: tuple[Event, ...] = ()
        if self.ctrl.active:
            events = self.ctrl.deactivate(now_ns, f"hardware fault: {reason}")
            self._write_deactivation_command(now_ns)
        try:
            self.hardware.deactivate(now_ns)
        except JtcHwError as exc:
            log.error("safe action after the fault failed too: %s", exc)
        # The status (with the fault) goes before the goal's result, so that a client that
        # asks for the status on seeing the result finds the fault.
        self.send(Status(self.status()))
        self._send_events(events)

    def _write_deactivation_command(self, now_ns: int) -> None:
        """Write the controller's deactivation command (velocity, acceleration and effort 0,
        position unchanged) once, before the hardware's safe action, as upstream's
        ``on_deactivate`` leaves it in the command interfaces for the next write.

        Only components that are active and have not faulted get it: upstream's controller
        manager no longer writes to a component in error. Never raises: a failed write is
        logged; the safe action follows anyway."""
        command = self.ctrl.deactivation_command
        if command.velocities is None and command.accelerations is None and command.effort is None:
            return  # position only: nothing changes ("write nothing")
        for comp, index in zip(self.hardware.components, self._component_joints, strict=True):
            if comp.state is not LifecycleState.ACTIVE or comp.last_fault is not None:
                continue
            part = JointCommand(
                *(None if v is None else v[index] for v in (
                    command.positions, command.velocities, command.accelerations, command.effort
                ))
            )
            try:
                comp.write(now_ns, part)
            except JtcHwError as exc:
                log.warning("%s: writing the deactivation command (velocity, acceleration and "
                            "effort 0) failed: %s", comp.name, exc)

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
            self.send(Status(self.status()))
            if hardware.state is LifecycleState.ACTIVE:
                with contextlib.suppress(JtcHwError):
                    hardware.deactivate(now_ns)
            raise
        self.fault = self.fault_cause = None
        log.info("re-armed: holding the measured position")
        self.send(Status(self.status()))
        return True

    # -- requests -----------------------------------------------------------------------------

    def _handle(self, message: Commit | Request, now_ns: int) -> None:
        match message:
            case Commit(plan_id, plan):
                # Freeing megabytes of arrays (munmap) costs hundreds of microseconds: the plan
                # and the reference it replaces are released later, in a cycle's spare time.
                self._retired.append((plan, self.ctrl.reference if self.ctrl.active else None))
                self._commit(plan_id, plan, now_ns)
            case Request(request_id, op):
                try:
                    value = self._request(op, now_ns)
                except JtcHwError as exc:
                    self.send(Failed.of(request_id, exc))
                else:
                    self.send(Reply(request_id, value))

    def _commit(self, plan_id: int, plan: Plan, now_ns: int) -> None:
        if self.fault is not None or not self.ctrl.active:
            self.send(Stale(plan_id, f"not active: {self.fault or 'controller stopped'}"))
            return
        if self._stopping_until_ns is not None:
            self.send(Stale(plan_id, f"not active: {self._shutdown_reason}"))
            return
        if self.api_stalled:
            # Its feedback and result could not be delivered either.
            self.send(Stale(
                plan_id,
                "not active: the daemon's API process has not yet read the control loop's "
                "backlog; retry once it has",
            ))
            return
        try:
            goal_id = self.ctrl.commit(plan, now_ns)
        except StalePlan as exc:
            self.send(Stale(plan_id, str(exc)))
            return
        self._committed_plan = plan_id
        self._report_reference()
        self.send(Committed(plan_id, goal_id))

    def _request(self, op: LoopOp, now_ns: int) -> Any:
        match op:
            case Cancel(goal_id):
                return self.ctrl.cancel_goal(int(goal_id))
            case Stop():
                self.ctrl.request_stop()
                return True
            case Sim(name, freeze, fault):
                component = self.hardware.component(name)
                if not isinstance(component, MirrorHardware):
                    raise HardwareError(
                        f"component '{name}' is {component.kind} hardware; only "
                        "simulated (mirror) components can be frozen"
                    )
                if freeze is not None:
                    component.set_frozen(bool(freeze))
                if fault:
                    component.inject_fault(str(fault))
                return True
            case SetParameters(config):
                # Checked by the API process; the controller refuses read-only differences.
                self.ctrl.apply_parameters(config)
                self.config = config
                self.state_every_ns = round(1e9 / config.state_publish_rate)
                self._next_state_ns = min(self._next_state_ns, now_ns + self.state_every_ns)
                return True
            case SetSpeedScaling(factor):
                if factor is None:
                    self.ctrl.resume_speed_scaling()
                else:
                    self.ctrl.set_speed_scaling(factor)
                # The target asked for: with a state interface the hardware's factor is the
                # controller's target, and this the factor it is asked to take.
                return {
                    "factor": self.ctrl.speed_scaling_factor,
                    "target": self.ctrl.speed_scaling_request,
                }
            case Rearm():
                done = self._rearm(now_ns)
                self._report_reference()
                return done
            case Shutdown(reason):
                self._shutdown_reason = str(reason or self._shutdown_reason)
                return self._begin_shutdown(now_ns)
        raise JtcHwError(f"unknown loop request {op!r}")

    def _begin_shutdown(self, now_ns: int) -> bool | float:
        """Stop cycling now (True), or -- with decelerating stops -- once the joints are at rest
        (the longest it keeps cycling, in seconds: the API process waits that much longer for
        it to exit). Never raises: the controller is active whenever ``stop`` is asked of it."""
        if self._stopping_until_ns is not None:
            return (self._stopping_until_ns - now_ns) / 1e9
        if self.fault is not None or not self.ctrl.active or not self.ctrl.decelerates:
            self.running = False
            return True
        state = self._last_state
        duration_s = 0.0 if state is None else self.ctrl.stop_duration_s(state)
        bound_s = min(duration_s + SHUTDOWN_STOP_MARGIN_S, SHUTDOWN_STOP_MAX_S)
        self.ctrl.stop(f"{self._shutdown_reason}: decelerating to a stop")
        self._stopping_until_ns = now_ns + round(bound_s * 1e9)
        self._stop_seen_ns = now_ns
        log.info("%s: decelerating to a stop (at most %.3f s)", self._shutdown_reason, bound_s)
        return bound_s

    def _shutdown_stop_done(self, now_ns: int) -> bool:
        """Whether a shutdown waiting for its decelerating stop can end the loop now: the stop
        has ended (a cycle after its end has read the joints at rest), the controller or
        hardware stopped otherwise, or the bound has passed."""
        cap = self._stopping_until_ns
        if cap is None or self.fault is not None or not self.ctrl.active:
            return True
        self._stop_skipped += max(0, (now_ns - self._stop_seen_ns) // self.period_ns - 1)
        self._stop_seen_ns = now_ns
        if now_ns >= cap:
            # The bound is the stop's own duration plus a margin: a loop the host starved
            # gets here. The shutdown holds where the joints are, and says so with the count.
            log.warning("%s: the decelerating stop had not ended by its bound; holding where "
                        "the joints are (%d deadlines skipped since the stop began)",
                        self._shutdown_reason, self._stop_skipped)
            return True
        if self.ctrl.stop_pending:
            return False
        end = self.ctrl.stopping_until_ns
        if end is None:
            return True
        # One cycle past the end: the cycle at or after it wrote the rest command, and the
        # next read the joints at rest. Counted in cycles, not time: after a skipped deadline
        # the first cycle past ``end + period`` is the one writing it (a busy host ended the
        # loop before the joints were read at rest: issue 22).
        if now_ns < end:
            return False
        if self._rest_written_ns is None:
            self._rest_written_ns = now_ns
            return False
        return now_ns > self._rest_written_ns

    # -- the cycle ----------------------------------------------------------------------------

    def handle_inbox(self, inbox: Inbox, now_ns: int) -> bool:
        """Handle every completed message, in order, at deadline ``now_ns``; whether there was
        any."""
        message = inbox.pop()
        if message is None:
            return False
        while message is not None:
            self._handle(message, now_ns)
            message = inbox.pop()
        return True

    def cycle(self, now_ns: int, period_ns: int, inbox: Inbox) -> None:
        """One read -> update -> write at deadline ``now_ns``."""
        self.handle_inbox(inbox, now_ns)
        if self.fault is not None or not self.ctrl.active:
            if self.fault is not None:
                self._monitor(now_ns)
            return
        try:
            state = self.hardware.read(now_ns)
            if self._scaling_state is not None:
                component, name = self._scaling_state
                self.ctrl.set_speed_scaling_state(component.scalar_state(name))
            out = self.ctrl.update(now_ns, period_ns, state)
            if self._scaling_command is not None:
                component, name = self._scaling_command
                component.set_scalar_command(name, self.ctrl.speed_scaling_request)
            self.hardware.write(now_ns, out.command)
            self._last_state = state
        except HardwareError as exc:
            self._enter_fault(now_ns, str(exc))
            self._report_reference()
            return
        self._report_reference()
        self._send_events(out.events)
        ring = self.ring
        if ring is not None:
            cs = out.state
            ring.write(now_ns, self.ctrl.active_goal, self.ctrl.holding, False,
                       cs.speed_scaling_factor, cs.reference_time_from_start,
                       cs.feedback_time_from_start, cs.feedback, out.desired, cs.output)
        if now_ns >= self._next_state_ns:
            self._next_state_ns = now_ns + self.state_every_ns
            cs = out.state
            if ring is not None:
                # The row just written is the State: the API process reads it from the ring
                # at state_publish_rate. Nothing to pickle, nothing to write to it, no wake-up.
                ring.write_state(out.error, out.command, cs.output, cs.feedback,
                                 cs.speed_scaling_target, self.ctrl.trajectory_time_ns)
                return
            # Without the ring (no shared memory): pickled now, written by the next cycle.
            self._state_cycle = True
            self.publish(State(
                now_ns, np.stack(out.desired), state.positions, cs.feedback.velocities,
                out.error, out.command, self.ctrl.holding, self.ctrl.active_goal,
                cs.reference_time_from_start, cs.feedback_time_from_start,
                cs.feedback.accelerations, cs.output, cs.speed_scaling_factor,
                cs.speed_scaling_target, self.ctrl.trajectory_time_ns))

    def _monitor(self, now_ns: int) -> None:
        """While faulted: what the hardware can read without commanding anything (its motors'
        health, the joints' positions, see ``HardwareInterface.monitor``), so that the status
        and the cycle ring (the flight recorder's second after the fault) stay current."""
        measured = self.hardware.monitor(now_ns)
        ring = self.ring
        if ring is not None and measured is not None:
            ring.write(now_ns, None, False, True, self.ctrl.speed_scaling_factor, math.nan,
                       math.nan, measured, None, None)

    def status(self) -> dict[str, Any]:
        """The loop's statistics (``outbox``: how its messages to the API process fare, see
        :meth:`Outbox.snapshot`; ``api_stalls``: goals ended because the API process stopped
        reading; ``api_stalled``: it has not caught up since), hardware and controller."""
        return {
            "loop": {
                **self.stats.snapshot(),
                "outbox": self.outbox.snapshot(),
                "api_stalls": self.api_stalls,
                "api_stalled": self.api_stalled,
            },
            "hardware": self.hardware.status(),
            "controller": {
                "active": self.ctrl.active,
                "holding": self.ctrl.holding,
                "active_goal": self.ctrl.active_goal,
                "fault": self.fault,
                "fault_cause": self.fault_cause,
                "reference_version": self.ctrl.reference_version,
                "speed_scaling": {
                    "factor": self.ctrl.speed_scaling_factor,
                    "target": self.ctrl.speed_scaling_target,
                },
            },
        }

    def serve_outbox(self, now_ns: int) -> None:
        """Write the cycle's messages without blocking; end the active goal if the API process
        has not taken an ordered message for ``api_stall_s`` (or the backlog overflows). Never
        raises: an API process that has gone away stops the loop (``running``)."""
        outbox = self.outbox
        if self._state_cycle:
            # Pickling the State is this cycle's extra work; writing it waits for the next
            # (the period's p99), unless an ordered message (an event, a reply) waits behind
            # it, or the next cycle publishes a State too (it would replace this one unsent).
            self._state_cycle = False
            if outbox.oldest_ns() is None and self.state_every_ns >= 2 * self.period_ns:
                return
        outbox.flush()
        if outbox.closed:
            log.warning("the API process went away: stopping the loop safely")
            self._shutdown_reason = "daemon API process exited"
            self.running = False
            return
        oldest = outbox.oldest_ns()
        if oldest is None:
            if self.api_stalled:
                self.api_stalled = False
                log.warning("the API process has read the backlog: serving goals again")
            return
        waited_ns = now_ns - oldest
        if self.api_stalled or (waited_ns <= self.api_stall_ns and not outbox.overflow):
            return
        self.api_stalled = True
        self.api_stalls += 1
        reason = (
            f"the daemon's API process has not read the control loop's messages for "
            f"{waited_ns / 1e9:.2f} s (daemon.api_stall_s: {self.api_stall_ns / 1e9:g} s)"
            + ("" if not outbox.overflow else f", {outbox.ordered_bytes} bytes waiting")
            + ": holding position"
        )
        log.error("%s; goals are refused until it catches up", reason)
        if self.ctrl.active and not self.ctrl.holding:
            self.ctrl.abort(reason)  # the result waits in the outbox, in order

    def after_cycle(self, deadline_ns: int, inbox: Inbox) -> None:
        """After the cycle at ``deadline_ns``: write the outbox, read the inbox (its budget at
        most, and not once ``inbox_spare_ns`` is all that is left of the period) and handle
        what that completed at ``deadline_ns``, writing the answers at once.

        Handling it now rather than at the next cycle commits a plan (or serves a stop) a
        period earlier. Committing at a deadline whose sample was already taken changes
        nothing the joints got: a plan keeps the reference it replaces from its
        ``valid_from_ns`` up to its planned time.
        """
        self.serve_outbox(deadline_ns)
        inbox.pump(deadline_ns + self.period_ns - self.inbox_spare_ns)
        if self.handle_inbox(inbox, deadline_ns):
            self.serve_outbox(deadline_ns)  # Committed, the Reply: now, not a period later

    def run(self, inbox: Inbox) -> None:
        """Cycle until asked to stop or the API process disappears."""
        ticker = Ticker(self.period_ns)
        if self.phases is not None:
            self.phases.instrument(self, ticker, inbox)
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
            if self._stopping_until_ns is not None and self._shutdown_stop_done(deadline):
                self.running = False
            if deadline >= self._next_status_ns:
                self._next_status_ns = deadline + STATUS_PERIOD_NS
                self.publish(Status(self.status()))
            self.after_cycle(deadline, inbox)
            if inbox.closed and not inbox.waiting:  # what arrived before the end goes first
                log.warning("the API process went away: stopping the loop safely")
                self._shutdown_reason = "daemon API process exited"
                self.running = False
            elif deadline + self.period_ns - clock() > GC_SLACK_NS:
                if self._retired:
                    self._retired.popleft()
                elif inbox.release():
                    if inbox.released:  # shared memory unmapped: its pool may reuse it
                        self.send(Released(tuple(inbox.released)))
                        inbox.released.clear()
                else:
                    self.collect_garbage(0)
            # The cost is the whole period's work, wake-up to sleep: the cycle, the status,
            # the outbox, the inbox and the spare-time step (the status shows the cycles
            # before this one).
            self.stats.record(woke - deadline, clock() - woke, skipped)
        self.shutdown(clock())

    def shutdown(self, now_ns: int) -> None:
        """Give the active goal its result, hold, apply the safe action, release hardware.

        With decelerating stops, a requested shutdown (``_begin_shutdown``) comes here once
        the joints are at rest; the goal already has its result then."""
        reason = self._shutdown_reason
        if self.ctrl.active:
            events = self.ctrl.deactivate(now_ns, f"{reason}: holding position")
            self._write_deactivation_command(now_ns)
            self._send_events(events)
        try:
            if self.fault is None:
                self.hardware.deactivate(now_ns)
            self.hardware.cleanup()
        except JtcHwError as exc:
            log.error("releasing the hardware failed: %s", exc)
        self.send(Status(self.status()))


QUIET_LOGGERS = {
    # python-can's socketcand client warns whenever TCP splits a frame across two reads,
    # which is normal and handled: at 1 kHz that would flood the journal.
    "can.interfaces.socketcand.socketcand": logging.ERROR,
}
"""Third-party loggers whose level the loop process raises."""

INBOX_BUDGET_PER_MS = 1280 * 1024
"""Bytes the loop reads from the API process per cycle at most, per millisecond of period
(500 Hz: 2.5 MiB, a 2,000-point plan in one cycle when time allows, see ``INBOX_SPARE``)."""

INBOX_SPARE = 0.4
"""Share of the period the loop never spends reading its inbox: it stops reading once only
this much is left before the next deadline (each read is at most ``pipe.CHUNK_BYTES``, ~0.1 ms),
so that reading never makes it late."""


def inbox_budget(period_ns: int) -> int:
    """Bytes the loop reads from the API process per cycle, for a loop of ``period_ns``."""
    return INBOX_BUDGET_PER_MS * max(1, period_ns // 1_000_000)

LOOP_SWITCH_INTERVAL_S = 0.0001
"""The loop process's interpreter switch interval (``sys.setswitchinterval``), s."""


LOOP_PROCESS_NAME = "jtc-hw-loop"
"""The loop process's name in ``ps``/``top``/``/proc/<pid>/comm``."""


def loop_main(source: str | dict[str, Any], controller_name: str | None, conn: Connection,
              ring_name: str | None = None) -> None:
    """Entry point of the loop process (``multiprocessing`` spawn target).

    ``ring_name``: the API process's :class:`~.cyclering.CycleRing` to write every cycle into
    (None: none).

    Never raises: failures are reported as ``Exit(code)`` with a ``Log`` line first.
    """
    # The API process coordinates shutdown; a terminal's Ctrl-C or systemd's SIGTERM to the
    # whole group must not kill the loop before the goal got its result and the robot holds.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    set_process_name(LOOP_PROCESS_NAME)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for name, level in QUIET_LOGGERS.items():
        logging.getLogger(name).setLevel(level)
    quiet_third_party_loggers()  # canopen's INFO lines unless jtc-hw -v
    # Any thread would take the interpreter lock whenever the loop thread releases it (in any
    # system call) and keep it for up to the switch interval, 5 ms by default: measured, a
    # receiving thread made a 1 kHz loop skip deadlines under client load. There is none now
    # (the inbox is read by the loop thread); a short interval still bounds what a library's
    # helper thread could cost, and costs nothing while only one thread wants the lock.
    sys.setswitchinterval(LOOP_SWITCH_INTERVAL_S)
    outbox = Outbox(conn, OUTBOX_CAPACITY_BYTES)
    code = 0
    last_words: str | None = None  # the failure, logged by the API process (here if it cannot)
    loop: ControlLoop | None = None
    ring: CycleRing | None = None
    try:
        robot = load_robot(source, controller_name)
        ring = None if ring_name is None else CycleRing.attach(ring_name)
        loop = ControlLoop(robot, outbox, ring)  # creates the components: no I/O yet
        loop.phases = PhaseRecorder.from_env()  # bench/loop_jitter.py --breakdown
        # One daemon per hardware: before anything is sent to a device. The owner recorded is
        # the daemon (our parent), the process a user would stop.
        loop.locks = lock_devices(
            [name for component in loop.hardware.components for name in component.devices()],
            config=robot.source_path or "configuration given as a mapping",
            pid=os.getppid(),
        )
        rt = robot.daemon.realtime
        for line in (*apply_realtime(rt.priority, rt.lock_memory, rt.cpu_affinity),
                     reduce_timer_slack(), keep_freed_memory(), disable_huge_pages()):
            loop.send(Log(logging.INFO, line))
        now = time.monotonic_ns()
        loop.start(now)
        loop._report_reference()  # before Ready: the API process plans against it at once
        loop.send(Ready(os.getpid(), now, loop.period_ns, loop.hardware.status()))
        outbox.drain(EXIT_DRAIN_S)  # not cycling yet: waiting is harmless
        inbox = Inbox(conn, inbox_budget(loop.period_ns))
        try:
            loop.run(inbox)
        finally:
            inbox.close()
    except JtcHwError as exc:
        # Said once, by the API process (its log, or its "cannot start: ..." line): logging
        # it here as well printed a missing serial port three times, from three modules.
        last_words = str(exc)
        outbox.put(Log(logging.ERROR, last_words))
        code = 2
    except Exception as exc:  # last resort: say what happened, never die silently
        log.exception("control loop crashed")
        outbox.put(Log(logging.CRITICAL, f"control loop crashed: {exc!r}"))
        code = 3
    finally:
        if loop is not None and code:
            _safe_action(loop)
        if loop is not None:
            for lock in loop.locks:
                lock.release()
            loop.ring = None
            if loop.phases is not None:
                loop.phases.close()
        if ring is not None:
            ring.close()
    outbox.put(Exit(code))
    if not outbox.drain(EXIT_DRAIN_S):
        if last_words is not None:
            log.error("%s", last_words)  # nobody else will say it
        if not outbox.closed:
            log.error("the API process did not take the loop's last messages within %g s",
                      EXIT_DRAIN_S)
    outbox.close()


def _safe_action(loop: ControlLoop) -> None:
    """After a failure: the hardware's safe action and release, if it was still running (no
    I/O for components never configured)."""
    try:
        loop.hardware.shutdown(time.monotonic_ns())
    except Exception as exc:  # noqa: BLE001 - reported; the process ends anyway
        log.error("the safe action after the crash failed: %s", exc)
