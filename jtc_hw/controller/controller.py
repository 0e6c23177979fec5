"""The joint trajectory controller: goals, tolerances, outcomes and the control law.

Theory of operation
-------------------
The controller never reads a clock and does no I/O: every method takes the time (integer
nanoseconds on one monotonic clock) and ``update`` takes the measured state. It always follows
one immutable reference ``Trajectory``: at activation a hold at the start state, then every
accepted command is spliced into it (see ``Trajectory.splice``), and every stop re-anchors it
as a hold (or, with ``decelerate_on_cancel``, a decelerating stop ending in one).

One ``update(now, period, state)``:

1. apply a pending stop (cancel, empty topic trajectory): hold the measured position, or
   with ``decelerate_on_cancel`` follow a decelerating stop from the measured state
   (``stopping.py``);
2. sample the reference at ``now`` and compute the error, desired minus measured (shortest
   angle for continuous joints);
3. if a command is executing, check it *before* commanding anything: path tolerance while
   moving (and at the first sample, even if it is already the end), goal tolerance,
   ``goal_time`` and ``cmd_timeout`` once the look-ahead time ``now + 1/update_rate`` reaches
   the last point (upstream: success comes one period before the reference reaches it);
   decide success or abort; an abort holds the measured position (or starts the decelerating
   stop) in this same cycle;
4. compute the command: forwarded interfaces (position, velocity without PID, acceleration)
   take the reference at ``now + 1/update_rate`` -- a command written at cycle ``t`` is what
   the joints should reach by the next cycle; PID outputs (velocity alone, effort) act on the
   error measured now: ``u = k_ff v_d + effort_d + k_p e + k_i sum(e dt) + k_d (v_d - v)``;
5. return the command and the events (goal results, feedback at ``action_monitor_rate``).

Speed scaling (``set_speed_scaling``): the reference lives on trajectory time, which advances by
the elapsed clock time times a factor that ramps toward its target within the acceleration
limits; "now" above is that trajectory time (equal to the clock while the factor is 1), and the
velocities and accelerations sampled are those of the slowed motion (``v s``, ``a s^2 + v ds/dt``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..errors import (
    ConfigurationError,
    ControllerStateError,
    GoalRejected,
    HardwareError,
    StalePlan,
)
from .config import MAX_SCALING_CEILING, ControllerConfig
from .goals import (
    ErrorCode,
    Event,
    GoalFeedback,
    GoalHandle,
    GoalResult,
    GoalStatus,
    GoalTransition,
    TrajectoryStopped,
)
from .joints import JointCommand, JointState
from .limits_check import (
    FIT,
    REJECT,
    TIME_SCALING_MODES,
    TOLERANCE,
    LimitTable,
    TimeScaling,
    check,
    describe_excess,
    fit_factor,
    reject,
    scale_prepared,
)
from .messages import NS_PER_S, JointTrajectory, PreparedTrajectory
from .parameters import ParameterChange, get_parameters, read_only_differences, set_parameters
from .pid import Pid
from .stopping import (
    stop_decelerations,
    stop_duration_bound_s,
    stop_jerks,
    stop_trajectory,
    warm_up,
)
from .tolerances import JointTolerance, SegmentTolerances, violated
from .trajectory import QueriedState, Trajectory, TrajectorySample, shortest_angular_distance
from .validation import prepare

F64 = NDArray[np.float64]

PREEMPTED_BY_ACTION = "Current goal cancelled due to new incoming action."
PREEMPTED_BY_TOPIC = "Current goal cancelled due to new incoming trajectory on the topic interface."
STOPPED_BY_TOPIC = "Current goal cancelled: an empty trajectory on the topic interface stopped it."
CANCELED_ON_REQUEST = ""
"""Upstream's cancel result carries an empty ``error_string`` (section 9); what happened goes
to ``details`` (:data:`CANCELED_DETAILS`)."""
CANCELED_DETAILS = "canceled on request; holding the current position"
CANCELED_DECELERATING_DETAILS = "canceled on request; decelerating to a stop"
DEACTIVATED = "Current goal cancelled during deactivate transition."
SUCCEEDED = "Goal successfully reached!"
PATH_TOLERANCE_VIOLATED = "Aborted due to path tolerance violation"
GOAL_TIME_EXCEEDED = "Aborted due to goal_time_tolerance exceeding by {late_s} seconds"
"""Upstream's text; ``late_s`` formatted as C++ ``std::to_string(double)`` does (``%f``)."""


class ControllerState(NamedTuple):
    """The ``controller_state`` of one cycle (jtc_upstream_behaviour.md section 16).

    Attributes:
        time_ns: the cycle's time.
        reference: the desired state at ``time_ns`` (upstream's ``reference``).
        reference_time_from_start: seconds from the start of the trajectory being followed
            (the command's start time, or when the current hold began) to ``time_ns``.
        feedback: the measured state; velocities only with a velocity state interface,
            accelerations only with an acceleration state interface (else ``None``).
        feedback_time_from_start: seconds of the daemon's clock since that start (with speed
            scaling, ``reference_time_from_start`` is about this times the factor).
        error: ``(3, n)`` desired minus measured position / velocity / acceleration.
        output: what the command interfaces hold, read back with upstream's rule: refreshed
            only in a cycle whose command is finite on every configured command interface of
            every command joint, else the previous value is kept; ``None`` for an interface
            that is not configured, ``NaN`` for joints that are not command joints.
        speed_scaling_factor: the speed scaling factor in force this cycle (upstream's
            ``speed_scaling_factor``).
        speed_scaling_target: the factor it ramps toward (``set_speed_scaling``).
    """

    time_ns: int
    reference: TrajectorySample
    reference_time_from_start: float
    feedback: JointState
    feedback_time_from_start: float
    error: F64
    output: JointCommand
    speed_scaling_factor: float = 1.0
    speed_scaling_target: float = 1.0


class UpdateResult(NamedTuple):
    """What one cycle produced.

    Attributes:
        command: values to write; ``NaN`` entries mean "write nothing".
        events: goal results, feedback and stop notices, in the order they happened
            (including those caused by ``send_goal`` / ``cancel_goal`` since the last cycle).
        desired: the reference at ``now``.
        error: ``(3, n)`` desired minus measured position / velocity / acceleration.
        state: the cycle's controller state (``controller_state`` topic).
    """

    command: JointCommand
    events: tuple[Event, ...]
    desired: TrajectorySample
    error: F64
    state: ControllerState


@dataclass
class _Execution:
    """The command being monitored: an action goal, or a topic trajectory (goal is None)."""

    goal: GoalHandle | None
    tolerances: SegmentTolerances
    start_ns: int
    end_ns: int
    first_sample: bool = True
    next_feedback_ns: int = 0


class _Outcome(NamedTuple):
    transition: GoalTransition
    code: ErrorCode
    message: str
    hold_measured: bool
    details: str = ""


@dataclass(frozen=True, eq=False)
class Plan:
    """A command validated and fitted against one version of the reference, ready to commit.

    Attributes:
        goal: True for an action goal, False for a topic trajectory.
        reference: the spliced reference to follow once committed.
        base_version: the reference version it was spliced onto.
        planned_ns: the time it was planned for; committing later than this is refused
            (the splice would have started in the past, stepping the command).
        start_ns: the command's start time (header stamp, or ``planned_ns`` for "now").
        tolerances: the tolerances to monitor.
        valid_from_ns: the earliest commit time for which ``reference`` still equals the base
            reference up to ``planned_ns`` (committing earlier is refused).
    """

    goal: bool
    reference: Trajectory
    base_version: int
    planned_ns: int
    start_ns: int
    tolerances: SegmentTolerances
    valid_from_ns: int
    time_scaling: TimeScaling | None = None
    """With ``time_scaling`` ``fit`` in effect: the slow-down applied (1.0: none was needed)
    and the resulting duration; None when the goal was checked against the limits as sent."""


FIT_ROUNDS = 8
"""Slow-down rounds before a goal whose lead-in keeps exceeding a limit is rejected: the
first round is exact for the points' segments, later ones only correct the lead-in."""


class Planner:
    """Validation and fitting of commands: a pure function of (reference, version, time, msg).

    The controller uses one internally; the daemon runs another in its API process against a
    replica of the loop's reference, so that parsing and fitting never run in the control loop
    (the loop only commits a ready ``Plan``).
    """

    def __init__(self, config: ControllerConfig) -> None:
        self.config = config
        self.joint_names = tuple(config.joints)
        self.wraparound = np.asarray(config.wraparound, dtype=bool)
        self.defaults = SegmentTolerances.from_config(config)
        self.limits = LimitTable.of(config.joints, config.limits)

    def plan_goal(
        self,
        reference: Trajectory,
        version: int,
        now_ns: int,
        trajectory: JointTrajectory,
        path_tolerance: Sequence[JointTolerance] = (),
        goal_tolerance: Sequence[JointTolerance] = (),
        goal_time_tolerance: float = 0.0,
        valid_from_ns: int | None = None,
        time_scaling: str | None = None,
    ) -> Plan:
        """Validate and fit an action goal (``valid_from_ns``: see ``Plan``; default ``now_ns``).

        Args:
            time_scaling: ``"reject"`` or ``"fit"`` (see ``limits_check``); None: the
                configuration's ``limits.time_scaling``.

        Raises:
            GoalRejected: invalid trajectory or tolerances, entirely in the past, beyond the
                joint limits (``reject``; with ``fit``: a position limit, or a lead-in that
                slowing cannot fix), or an unknown ``time_scaling``.
        """
        mode = self._mode(time_scaling)
        prepared = prepare(self.config, trajectory)
        tolerances = self.defaults.with_overrides(
            self.joint_names, path_tolerance, goal_tolerance, goal_time_tolerance
        )
        return self._plan(
            True, reference, version, now_ns, prepared, tolerances, valid_from_ns, mode
        )

    def plan_trajectory(
        self,
        reference: Trajectory,
        version: int,
        now_ns: int,
        trajectory: JointTrajectory,
        valid_from_ns: int | None = None,
        time_scaling: str | None = None,
    ) -> Plan:
        """Validate and fit a topic trajectory (non-empty; an empty one is a stop request).

        Args:
            time_scaling: as for ``plan_goal``.

        Raises:
            GoalRejected: invalid, entirely in the past, or beyond the joint limits (see
                ``plan_goal``).
        """
        mode = self._mode(time_scaling)
        prepared = prepare(self.config, trajectory)
        return self._plan(
            False, reference, version, now_ns, prepared, self.defaults, valid_from_ns, mode
        )

    def _mode(self, time_scaling: str | None) -> str:
        if time_scaling is None:
            return self.config.time_scaling
        if time_scaling not in TIME_SCALING_MODES:
            raise GoalRejected(
                f"time_scaling: {time_scaling!r} is not one of "
                f"{', '.join(repr(m) for m in TIME_SCALING_MODES)}"
            )
        return time_scaling

    def _plan(
        self,
        goal: bool,
        reference: Trajectory,
        version: int,
        now_ns: int,
        prepared: PreparedTrajectory,
        tolerances: SegmentTolerances,
        valid_from_ns: int | None,
        mode: str = REJECT,
    ) -> Plan:
        valid_from = now_ns if valid_from_ns is None else min(valid_from_ns, now_ns)
        new_ref = reference.splice(
            now_ns, prepared, self.config.interpolation_method, self.wraparound, valid_from
        )
        start = prepared.start_time_ns or now_ns
        scaling = None
        if self.limits is not None:
            new_ref, scaling = self._within_limits(
                reference, now_ns, prepared, new_ref, start, valid_from, mode
            )
        return Plan(goal, new_ref, version, now_ns, start, tolerances, valid_from, scaling)

    def _within_limits(
        self,
        reference: Trajectory,
        now_ns: int,
        prepared: PreparedTrajectory,
        spliced: Trajectory,
        start: int,
        valid_from: int,
        mode: str,
    ) -> tuple[Trajectory, TimeScaling | None]:
        """Check ``spliced`` (``prepared`` spliced into ``reference``) against the limits
        and, with ``fit``, slow ``prepared`` down until it is within them.

        Raises:
            GoalRejected: beyond a limit (see ``plan_goal``).
        """
        table = self.limits
        assert table is not None
        splice_at = max(start, now_ns)
        cols = prepared.joint_indices
        start_positions = spliced.sample(splice_at).positions
        factor = 1.0
        current, current_prepared = spliced, prepared
        for _round in range(FIT_ROUNDS + 1):
            found = check(current, splice_at, table, cols, start_positions)
            if not found:
                if mode != FIT:
                    return current, None
                duration = int(current_prepared.times_ns[-1]) / NS_PER_S
                return current, TimeScaling(factor, duration)
            first_due = start + int(current_prepared.times_ns[0])
            worst = found.get("position") or max(found.values(), key=lambda e: e.ratio)
            message = describe_excess(worst, table, start, first_due, current.end_ns)
            if "position" in found:
                raise reject(message)
            if mode != FIT:
                raise reject(
                    f"{message}; slow the trajectory down (its times by a factor of at least "
                    f'{fit_factor(found):.6g}), or send it with time_scaling "fit"'
                )
            # First round: exact for everything that scales (a lead-in from rest too). Later
            # rounds only correct a lead-in from a moving reference, whose start velocity does
            # not scale: its acceleration falls only like 1/s (jerk 1/s**2), so a step is
            # taken as if it did (lead_in=True): it may overshoot the smallest factor slightly.
            factor *= fit_factor(found, lead_in=_round > 0) * (1.0 + 4 * TOLERANCE)
            current_prepared = scale_prepared(prepared, factor)
            current = reference.splice(
                now_ns,
                current_prepared,
                self.config.interpolation_method,
                self.wraparound,
                valid_from,
            )
        raise reject(
            f"{message}, even slowed down by a factor of {factor:.6g}: the lead-in from the "
            "current reference's motion to the first point does not fit the limits; send a "
            "first point that continues the current motion, or wait for it to end"
        )


def in_trajectory_time(
    trajectory: JointTrajectory, now_ns: int, tau_ns: int, factor: float
) -> JointTrajectory:
    """``trajectory`` with its header stamp moved to trajectory time (speed scaling).

    With speed scaling the reference runs on trajectory time (``tau_ns`` at clock time
    ``now_ns``); as upstream (section 14.1 step 2) the stamp's distance from now is scaled by
    the factor in force, so at a steady factor the command starts at the stamp's clock time.
    A zero ("now") or negative stamp (refused by validation) is left as it is.
    """
    if (now_ns == tau_ns and factor == 1.0) or not isinstance(trajectory, JointTrajectory):
        return trajectory  # validation names what is wrong with a non-trajectory
    stamp = trajectory.start_time_ns
    if isinstance(stamp, bool) or not isinstance(stamp, int) or stamp <= 0:
        return trajectory
    moved = tau_ns + (stamp - now_ns if factor == 1.0 else round((stamp - now_ns) * factor))
    return JointTrajectory(trajectory.joint_names, trajectory.points, max(1, moved))


def _command_mask(config: ControllerConfig) -> NDArray[np.bool_] | None:
    """Which joints get commands: ``None`` for all of them (``command_joints`` empty, or as
    many as ``joints``: mapped by index, the names may differ), else the joints that
    ``command_joints`` names (a subset, mapped by name; the others are monitored only).
    jtc_upstream_behaviour.md sections 1 and 12."""
    command_joints = config.command_joints
    if not command_joints or len(command_joints) == len(config.joints):
        return None
    named = set(command_joints)
    return np.array([j in named for j in config.joints], dtype=bool)


class JointTrajectoryController:
    """ROS 2 ``joint_trajectory_controller`` semantics, with time and state injected.

    Example::

        ctrl = JointTrajectoryController(load_config("robot.yaml"))
        ctrl.activate(now_ns, JointState(positions))
        goal_id = ctrl.send_goal(now_ns, JointTrajectory(names, points))
        out = ctrl.update(now_ns, period_ns, JointState(positions, velocities))
        write(out.command); handle(out.events)
    """

    def __init__(self, config: ControllerConfig) -> None:
        self.config = config
        self.joint_names = tuple(config.joints)
        n = len(self.joint_names)
        self._n = n
        self._wrap = np.asarray(config.wraparound, dtype=bool)
        self._any_wrap = bool(self._wrap.any())
        gains = [config.gains[j] for j in self.joint_names]
        self._pid = Pid(
            np.array([g.p for g in gains]),
            np.array([g.i for g in gains]),
            np.array([g.d for g in gains]),
            np.array([g.i_clamp for g in gains]),
        )
        self._ff = np.array([g.ff_velocity_scale for g in gains])
        cmd = config.command_interfaces
        self._cmd_pos = "position" in cmd
        self._cmd_vel = "velocity" in cmd
        self._cmd_acc = "acceleration" in cmd
        self._cmd_eff = "effort" in cmd
        self._use_pid = config.use_pid
        self._has_vel_state = "velocity" in config.state_interfaces
        self._has_acc_state = "acceleration" in config.state_interfaces
        self._cmd_mask = _command_mask(config)
        self._cmd_fields = (self._cmd_pos, self._cmd_vel, self._cmd_acc, self._cmd_eff)
        # Which errors exist (upstream 8.4): a velocity error only where velocity is commanded
        # (velocity or effort), an acceleration error only where acceleration is; otherwise 0,
        # so e.g. stopped_velocity_tolerance never blocks a position-commanded goal.
        self._vel_error = self._has_vel_state and (self._cmd_vel or self._cmd_eff)
        self._acc_error = self._has_acc_state and self._cmd_acc
        self._lookahead_ns = round(NS_PER_S / config.update_rate)
        self._feedback_ns = round(NS_PER_S / config.action_monitor_rate)
        self._cmd_timeout_ns = round(config.effective_cmd_timeout * NS_PER_S)
        # Decelerating stops (stopping.py): None when every stop is a plain hold.
        self._stop_decel = stop_decelerations(config)
        self._stop_jerk = stop_jerks(config)
        self._stop_ref: Trajectory | None = None  # the decelerating stop being followed
        if self._stop_decel is not None:
            # The first stop must not pay numpy's first-call costs inside a control cycle
            # (measured: several ms in a fresh loop process, enough to skip deadlines).
            warm_up(n)
        self._planner = Planner(config)
        self.last_time_scaling: TimeScaling | None = None
        """How the last accepted command was fitted to the joint limits (``Plan``)."""
        self._version = 0
        self._active = False
        self._ref = Trajectory.constant(0, np.zeros(n))
        self._execution: _Execution | None = None
        self._pending_stop: GoalTransition | None = None
        self._stop_reason = ""
        self._commanding = True
        self._events: list[Event] = []
        self._next_goal_id = 1
        self._last_command_positions = np.zeros(n)
        self._last_command_velocities: F64 | None = None
        self._last_command_accelerations: F64 | None = None
        self._measured = JointState(np.zeros(n))  # the last state read (query_state)
        self._nan = np.full(n, np.nan)
        self._nan.setflags(write=False)
        self._output = self._nan_command()
        self._ref_start_ns = 0
        # Speed scaling (upstream section 13): the reference is sampled at trajectory time
        # ``_tau_ns``, which advances by the elapsed time times the factor; ``_wall_ns`` is the
        # clock time it was last advanced to.
        self._tau_ns = 0
        self._wall_ns = 0
        self._timebase_started = False
        self._ref_start_wall_ns = 0
        initial = config.speed_scaling.initial_scaling_factor
        self._scale = initial
        self._scale_target = initial
        self._scale_rate = 0.0  # d(factor)/dt in force since _wall_ns, 1/s
        self._ramp_target = initial  # what _scale_rate aims at (the target may change since)
        self._resume_scale = initial if initial > 0.0 else 1.0
        self._set_ramp_bounds(config)

    # -- lifecycle ----------------------------------------------------------------------------

    @property
    def active(self) -> bool:
        """Whether ``activate`` was called and ``deactivate`` not since."""
        return self._active

    @property
    def active_goal(self) -> int | None:
        """The id of the goal being executed, if any."""
        ex = self._execution
        return ex.goal.goal_id if ex is not None and ex.goal is not None else None

    @property
    def holding(self) -> bool:
        """True when no command is being executed (holding a position)."""
        return self._execution is None

    def activate(
        self, now_ns: int, state: JointState, last_command: JointCommand | None = None
    ) -> None:
        """Start: hold the start state, with no jump.

        The start state is the measured one, except -- when
        ``set_last_command_interface_value_as_state_on_activation`` is true and every joint is
        a command joint -- for each of position, velocity and acceleration whose command
        interface is configured and whose ``last_command`` values are all finite: that field
        is the last command (jtc_upstream_behaviour.md section 3 step 4; a single NaN, "no
        value", makes that field the measured one). The hold is at the start positions with
        zero velocity; the start state is also the last commanded state
        (``last_commanded_state``) and ``last_command`` the first ``output`` of the
        controller state. Any trajectory or goal from an earlier activation is gone; PID
        integrators start at zero.

        Raises:
            ControllerStateError: already active.
            HardwareError: the measured positions are missing or not finite.
        """
        if self._active:
            raise ControllerStateError("activate: the controller is already active")
        positions = self._checked_positions(state)
        seed = (
            last_command
            if self.config.set_last_command_interface_value_as_state_on_activation
            and self._cmd_mask is None
            else None
        )
        start = self._seeded(seed, "positions", self._cmd_pos, positions)
        assert start is not None
        velocities = self._seeded(
            seed, "velocities", self._cmd_vel, state.velocities if self._has_vel_state else None
        )
        accelerations = self._seeded(
            seed,
            "accelerations",
            self._cmd_acc,
            state.accelerations if self._has_acc_state else None,
        )
        # Trajectory time starts at the clock and then never jumps, across re-activations too
        # (the daemon's API process extrapolates it to plan).
        self._tau_ns = self._traj_time(now_ns) if self._timebase_started else now_ns
        self._timebase_started = True
        self._wall_ns = now_ns
        initial = self.config.speed_scaling.initial_scaling_factor
        self._scale = self._scale_target = initial
        self._scale_rate = 0.0
        self._set_reference(Trajectory.constant(self._tau_ns, start))
        self._measured = state
        self._last_command_positions = start.copy()
        self._last_command_velocities = velocities
        self._last_command_accelerations = accelerations
        self._output = self._nan_command()
        if last_command is not None:
            self._refresh_output(last_command)
        self._execution = None
        self._pending_stop = None
        self._stop_ref = None
        self._pid.reset()
        self._commanding = self.config.start_with_holding
        # Upstream resolves cmd_timeout in on_activate only: a runtime change waits for it.
        self._cmd_timeout_ns = round(self.config.effective_cmd_timeout * NS_PER_S)
        self._active = True

    def _seeded(
        self, last_command: JointCommand | None, name: str, configured: bool, measured: F64 | None
    ) -> F64 | None:
        """One field of the activation state: the last command's if usable, else measured."""
        values = getattr(last_command, name) if last_command is not None else None
        if (
            configured
            and values is not None
            and values.shape == (self._n,)
            and bool(np.isfinite(values).all())
        ):
            return np.array(values, dtype=np.float64)
        return None if measured is None else np.array(measured, dtype=np.float64)

    @property
    def last_commanded_state(self) -> JointState:
        """Upstream's ``last_commanded_state``: the state last commanded (the look-ahead sample
        of the last cycle, in every joint), or the activation state before the first cycle.
        Velocities and accelerations are ``None`` where nothing gave them."""
        return JointState(
            self._last_command_positions,
            self._last_command_velocities,
            self._last_command_accelerations,
        )

    def deactivate(self, now_ns: int, reason: str | None = None) -> tuple[Event, ...]:
        """Stop, as upstream's ``on_deactivate``: the active goal ends ``ABORTED`` with
        ``INVALID_GOAL`` (-1) and no more commands are produced.

        The caller writes :attr:`deactivation_command` to the hardware once (velocity,
        acceleration and effort 0, position left as it is), as upstream writes it into the
        command interfaces before they are released.

        Args:
            now_ns: the time, stamped on the result.
            reason: the result's ``error_string`` (default: upstream's deactivation message;
                the daemon names the fault or the shutdown).

        Returns:
            The events not yet delivered, ending with the goal's result if one was active.

        Raises:
            ControllerStateError: not active.
        """
        if not self._active:
            raise ControllerStateError("deactivate: the controller is not active")
        ex = self._execution
        if ex is not None and ex.goal is not None:
            self._finish(
                ex.goal, GoalTransition.ABORT, ErrorCode.INVALID_GOAL, reason or DEACTIVATED, now_ns
            )
        self._execution = None
        self._pending_stop = None
        self._active = False
        events, self._events = tuple(self._events), []
        return events

    @property
    def deactivation_command(self) -> JointCommand:
        """What upstream's ``on_deactivate`` writes: 0 to every velocity, acceleration and
        effort command interface, and the position command unchanged (``NaN``: write nothing,
        the device keeps its position target).

        A velocity-commanded joint would otherwise keep turning at its last command until the
        driver's own safe action (or watchdog) stops it. Joints outside a ``command_joints``
        subset get ``NaN`` everywhere: the controller never commands them.
        """
        zeros = np.zeros(self._n)
        if self._cmd_mask is not None:
            zeros[~self._cmd_mask] = np.nan  # joints outside command_joints: write nothing
        return JointCommand(
            self._nan if self._cmd_pos else None,
            zeros if self._cmd_vel else None,
            zeros if self._cmd_acc else None,
            zeros if self._cmd_eff else None,
        )

    # -- commands -----------------------------------------------------------------------------

    def send_goal(
        self,
        now_ns: int,
        trajectory: JointTrajectory,
        path_tolerance: Sequence[JointTolerance] = (),
        goal_tolerance: Sequence[JointTolerance] = (),
        goal_time_tolerance: float = 0.0,
        *,
        time_scaling: str | None = None,
    ) -> int:
        """Accept an action goal (``follow_joint_trajectory``) or raise why not.

        On acceptance the trajectory is spliced into the reference and the previous goal, if
        any, is canceled (its result is delivered with the next ``update``).

        Args:
            time_scaling: a goal beyond the joint limits is rejected (``"reject"``) or slowed
                down to fit them (``"fit"``); None: ``config.time_scaling``. With ``fit``,
                ``last_time_scaling`` then says the factor and the new duration.

        Returns:
            The goal id; its result arrives exactly once among ``update``/``deactivate`` events.

        Raises:
            GoalRejected: inactive controller, invalid trajectory or tolerances, a trajectory
                entirely in the past, or beyond the joint limits; the reference is unchanged.
        """
        plan = self.plan_goal(
            now_ns,
            trajectory,
            path_tolerance,
            goal_tolerance,
            goal_time_tolerance,
            time_scaling=time_scaling,
        )
        goal_id = self.commit(plan, now_ns)
        assert goal_id is not None
        self.last_time_scaling = plan.time_scaling
        return goal_id

    def send_trajectory(
        self, now_ns: int, trajectory: JointTrajectory, *, time_scaling: str | None = None
    ) -> None:
        """Fire-and-forget trajectory (the ``joint_trajectory`` topic).

        An empty trajectory (no points) stops: the measured position is held from the next
        cycle and an active goal is canceled. Otherwise the trajectory is spliced in, an active
        goal is canceled, and the default path tolerances and ``goal_time`` are monitored
        (a violation holds the position and emits ``TrajectoryStopped``).

        Args:
            time_scaling: as for ``send_goal``.

        Raises:
            GoalRejected: inactive controller, invalid or entirely past trajectory, or beyond
                the joint limits.
        """
        if isinstance(trajectory, JointTrajectory) and not trajectory.points:
            self.request_stop()
            return
        plan = self.plan_trajectory(now_ns, trajectory, time_scaling=time_scaling)
        self.commit(plan, now_ns)
        self.last_time_scaling = plan.time_scaling

    def plan_goal(
        self,
        now_ns: int,
        trajectory: JointTrajectory,
        path_tolerance: Sequence[JointTolerance] = (),
        goal_tolerance: Sequence[JointTolerance] = (),
        goal_time_tolerance: float = 0.0,
        valid_from_ns: int | None = None,
        *,
        time_scaling: str | None = None,
    ) -> Plan:
        """First half of ``send_goal``: validate and fit against the current reference
        (``Plan.time_scaling`` says how a ``fit`` goal was slowed).

        Raises:
            GoalRejected: see ``send_goal``.
        """
        self._require_active_for_commands()
        tau = self._traj_time(now_ns)
        return self._planner.plan_goal(
            self._ref,
            self._version,
            tau,
            in_trajectory_time(trajectory, now_ns, tau, self._scale),
            path_tolerance,
            goal_tolerance,
            goal_time_tolerance,
            None if valid_from_ns is None else self._traj_time(valid_from_ns),
            time_scaling,
        )

    def plan_trajectory(
        self, now_ns: int, trajectory: JointTrajectory, *, time_scaling: str | None = None
    ) -> Plan:
        """First half of ``send_trajectory`` for a non-empty trajectory.

        Raises:
            GoalRejected: see ``send_trajectory``.
        """
        self._require_active_for_commands()
        tau = self._traj_time(now_ns)
        return self._planner.plan_trajectory(
            self._ref,
            self._version,
            tau,
            in_trajectory_time(trajectory, now_ns, tau, self._scale),
            time_scaling=time_scaling,
        )

    def commit(self, plan: Plan, now_ns: int) -> int | None:
        """Second half: swap in a planned reference (O(1), no fitting).

        The plan's times are trajectory times (:attr:`trajectory_time_ns`; equal to the clock
        while the speed scaling factor has always been 1); ``now_ns`` is the clock's.

        Returns:
            The goal id for a goal plan, None for a topic plan.

        Raises:
            GoalRejected: the controller is not active.
            StalePlan: the reference changed since the plan was made (a stop, an abort or
                another command), or ``now_ns`` is past the time it was planned for.
        """
        self._require_active_for_commands()
        wall_ns, now_ns = now_ns, self._traj_time(now_ns)
        if plan.base_version != self._version:
            raise StalePlan(
                f"planned against reference version {plan.base_version}, current is {self._version}"
            )
        if now_ns < plan.valid_from_ns:
            raise StalePlan(
                f"committed at {now_ns} ns, before the plan's validity ({plan.valid_from_ns} ns)"
            )
        if now_ns > plan.planned_ns:
            raise StalePlan(
                f"planned for {plan.planned_ns} ns, committed late at {now_ns} ns "
                f"({(now_ns - plan.planned_ns) / 1e6:.3f} ms)"
            )
        handle = None
        if plan.goal:
            self._preempt(PREEMPTED_BY_ACTION, wall_ns)
            handle = GoalHandle(self._next_goal_id)
            self._next_goal_id += 1
        else:
            self._preempt(PREEMPTED_BY_TOPIC, wall_ns)
        self._set_reference(plan.reference, plan.start_ns)
        self._execution = _Execution(handle, plan.tolerances, plan.start_ns, plan.reference.end_ns)
        self._commanding = True
        return None if handle is None else handle.goal_id

    def request_stop(self) -> None:
        """Stop as an empty topic trajectory does: hold the measured position from the next
        cycle (or decelerate to rest, see :meth:`stop`; a decelerating stop under way goes on
        unchanged); an active goal ends ``CANCELED``.

        Raises:
            GoalRejected: the controller is not active.
        """
        self._require_active_for_commands()
        if self._execution is None and self.stopping_until_ns is not None:
            return  # a decelerating stop is under way: it goes on unchanged
        self._request_stop(GoalTransition.PREEMPT, STOPPED_BY_TOPIC)

    def abort(self, reason: str) -> None:
        """Abort what is executing: from the next ``update``, hold the measured position; an
        active goal ends ``ABORTED`` with ``reason`` (a topic trajectory just stops). For a
        fault outside the controller and the hardware, where the controller stays active
        (e.g. nobody reads the goal's feedback and result). Nothing happens while holding.

        Raises:
            GoalRejected: the controller is not active.
        """
        self._require_active_for_commands()
        if self._execution is not None:
            self._request_stop(GoalTransition.ABORT, reason)

    def stop(self, reason: str) -> None:
        """Bring the joints to rest from the next ``update``, whatever is executing: the
        decelerating stop when ``constraints.decelerate_on_cancel`` applies (see
        :attr:`decelerates`), else a hold of the measured position. An active goal ends
        ``ABORTED`` (``INVALID_GOAL``) with ``reason``. A decelerating stop already under way
        goes on unchanged. For the daemon's shutdown, which then waits for
        :attr:`stopping_until_ns` before deactivating.

        Raises:
            GoalRejected: the controller is not active.
        """
        self._require_active_for_commands()
        if self._execution is None and self.stopping_until_ns is not None:
            return
        self._request_stop(GoalTransition.ABORT, reason)

    @property
    def decelerates(self) -> bool:
        """Whether stops decelerate (``decelerate_on_cancel`` and its preconditions hold)
        rather than hold on the spot."""
        return self._stop_decel is not None

    @property
    def stop_pending(self) -> bool:
        """Whether a stop was requested that the next ``update`` applies."""
        return self._pending_stop is not None

    @property
    def stopping_until_ns(self) -> int | None:
        """While the reference is a decelerating stop: the time its last joint comes to rest
        (it holds from then on); ``None`` otherwise."""
        if not self._following_stop:
            return None
        assert self._stop_ref is not None
        # Trajectory time to the clock: the stop runs at the clock's pace from ``_tau_ns``.
        return self._wall_ns + (self._stop_ref.end_ns - self._tau_ns)

    def stop_duration_s(self, state: JointState) -> float:
        """At least as long as a decelerating stop started from ``state`` lasts (0 if stops
        hold or ``state`` has no usable velocities; without an acceleration state, the
        acceleration is taken as 0): the daemon's bound for waiting on one. Cheap: no
        trajectory is built.

        Raises:
            Nothing.
        """
        v = state.velocities
        if self._stop_decel is None or v is None or v.shape != (self._n,):
            return 0.0
        if not np.isfinite(v).all():
            return 0.0
        a = state.accelerations if self._has_acc_state else None
        if a is None or a.shape != (self._n,) or not np.isfinite(a).all():
            a = np.zeros(self._n)
        return stop_duration_bound_s(v, a, self._stop_decel, self._stop_jerk)

    @property
    def reference_version(self) -> int:
        """Increments every time the reference changes (activation, commit, stop, abort)."""
        return self._version

    def cancel_goal(self, goal_id: int) -> bool:
        """Request cancellation; the goal ends ``CANCELED`` at the next ``update``, which holds
        the measured position.

        Returns:
            False if ``goal_id`` is not the executing goal (unknown, finished or canceling).
        """
        ex = self._execution
        if ex is None or ex.goal is None or ex.goal.goal_id != goal_id:
            return False
        if ex.goal.status is not GoalStatus.EXECUTING:
            return False
        ex.goal.transition(GoalTransition.REQUEST_CANCEL)
        details = CANCELED_DETAILS if self._stop_decel is None else CANCELED_DECELERATING_DETAILS
        self._request_stop(GoalTransition.CANCEL_DONE, details)
        return True

    def query_state(self, t_ns: int) -> QueriedState:
        """The ``query_state`` service (upstream's section 16): the desired state at ``t_ns``.

        ``success`` is True only strictly inside the reference; before the time it was
        installed the answer carries the last measured state, at or after its last point the
        last point's values (``where`` says which). Unlike upstream's, it has no side effects.

        Raises:
            ControllerStateError: the controller is not active.
        """
        if not self._active:
            raise ControllerStateError("query_state: the controller is not active")
        m = self._measured
        zero = np.zeros(self._n)
        current = TrajectorySample(
            m.positions,
            zero if m.velocities is None else m.velocities,
            zero if m.accelerations is None else m.accelerations,
            zero,
        )
        return self._ref.query(self._traj_time(t_ns), current)

    @property
    def reference(self) -> Trajectory:
        """The trajectory being followed (immutable), in trajectory time
        (:attr:`trajectory_time_ns`)."""
        return self._ref

    # -- speed scaling ------------------------------------------------------------------------

    def set_speed_scaling(self, factor: float) -> None:
        """Set the speed scaling factor's target: the trajectory time advances by the elapsed
        time times the factor (1: as planned, 0.5: half speed, 0: paused; above 1, where
        ``speed_scaling.max_scaling_factor`` allows it: faster).

        The factor ramps toward the target from the next ``update``, as fast as the
        acceleration limits allow (``config.limits``; a joint's acceleration
        ``a s^2 + v ds/dt`` stays within its limit), and for joints without one at
        ``1 / speed_scaling.ramp_time`` per second; velocity and acceleration commands and
        feed-forwards are scaled with it. It holds across goals; ``activate`` resets it to
        ``speed_scaling.initial_scaling_factor``.

        Example::

            ctrl.set_speed_scaling(0.0)   # pause smoothly
            ctrl.resume_speed_scaling()   # back to the factor before the pause

        Raises:
            ConfigurationError: ``factor`` is not a number in ``[0, max_scaling_factor]``
                (upstream's ``[0, 1]`` by default); the message names the range.
        """
        most = self.config.speed_scaling.max_scaling_factor
        if (
            isinstance(factor, bool)
            or not isinstance(factor, (int, float))
            or not 0.0 <= factor <= most  # False for NaN
        ):
            wider = (
                f"; speed_scaling.max_scaling_factor allows up to {MAX_SCALING_CEILING:g}"
                if most < MAX_SCALING_CEILING
                else ""
            )
            raise ConfigurationError(
                f"the speed scaling factor must be a number in [0, {most:g}] (1: full speed, "
                f"0: pause{wider}), got {factor!r}",
                "factor",
                factor,
            )
        self._scale_target = float(factor)
        if factor > 0.0:
            self._resume_scale = float(factor)

    def resume_speed_scaling(self) -> float:
        """Ramp back to the last non-zero factor set (the one before a pause; initially
        ``initial_scaling_factor``, or 1 if that is 0).

        Returns:
            The target it ramps to.
        """
        self._scale_target = self._resume_scale
        return self._resume_scale

    @property
    def speed_scaling_factor(self) -> float:
        """The speed scaling factor in force (it ramps toward :attr:`speed_scaling_target`)."""
        return self._scale

    @property
    def speed_scaling_target(self) -> float:
        """The factor the speed scaling ramps toward (``set_speed_scaling``)."""
        return self._scale_target

    @property
    def trajectory_time_ns(self) -> int:
        """The trajectory time of the last cycle: where the reference is sampled. It equals the
        clock while the factor has been 1 throughout; below 1 it falls behind the clock."""
        return self._tau_ns

    def _traj_time(self, wall_ns: int) -> int:
        """The trajectory time at clock time ``wall_ns``, at the factor in force."""
        elapsed = wall_ns - self._wall_ns
        if elapsed == 0:
            return self._tau_ns
        scale = 1.0 if self._following_stop else self._scale
        return self._tau_ns + (elapsed if scale == 1.0 else round(elapsed * scale))

    @property
    def _following_stop(self) -> bool:
        """Whether the reference is a decelerating stop: it runs on the clock, not slowed by
        the speed scaling factor, so that the joints decelerate at the configured rate from
        the velocity they were measured at, whatever the factor (0 included)."""
        ref = self._stop_ref
        return ref is not None and ref is self._ref

    def _advance(self, now_ns: int) -> int:
        """Move the trajectory time (and the ramping factor) to clock time ``now_ns``."""
        elapsed = now_ns - self._wall_ns
        if elapsed == 0:
            return self._tau_ns
        self._tau_ns = self._traj_time(now_ns)
        self._wall_ns = now_ns
        rate = self._scale_rate
        if rate != 0.0 and elapsed > 0:
            target = self._ramp_target
            scale = self._scale + rate * (elapsed / NS_PER_S)
            # The rate was chosen to land on the target; rounding must not overshoot it.
            if (rate > 0.0 and scale >= target - 1e-12) or (rate < 0.0 and scale <= target + 1e-12):
                scale = target
            self._scale = max(scale, 0.0)
        return self._tau_ns

    def _set_ramp_bounds(self, config: ControllerConfig) -> None:
        """What bounds the factor's ramp: per joint with one, its acceleration limit; a ramp
        time for the joints without (``speed_scaling.ramp_time``, 0: no bound)."""
        limited = [
            i
            for i, j in enumerate(self.joint_names)
            if j in config.limits and config.limits[j].acceleration is not None
        ]
        self._acc_index: NDArray[np.intp] | None = (
            np.array(limited, dtype=np.intp) if limited else None
        )
        self._acc_limit = np.array(
            [config.limits[self.joint_names[i]].acceleration for i in limited], dtype=np.float64
        )
        ramp_time = config.speed_scaling.ramp_time
        self._default_ramp_rate = (
            1.0 / ramp_time if ramp_time > 0.0 and len(limited) < self._n else math.inf
        )

    def _ramp(
        self, ahead: TrajectorySample | None, here: TrajectorySample | None = None
    ) -> None:
        """Choose the factor's rate of change for the coming period (``_scale_rate``).

        The fastest change toward the target that keeps every joint with an acceleration
        limit within it, on the reference at the look-ahead time ``ahead``: the joint's
        acceleration is ``a s^2 + v ds/dt``, so ``|ds/dt| <= (A - |a| s^2) / |v|`` keeps it
        within ``A`` whatever the signs (0 when the reference alone already uses the whole
        limit: the factor waits); a joint at rest does not bound it. Joints without a limit
        bound it by the ramp time. With ``here`` (the reference at the cycle's own trajectory
        time), the larger speed and acceleration of the two samples count: the period's
        velocity step is taken between them, and a trajectory slowing down (or one paused,
        whose time stands still) has a larger speed at ``here`` than at ``ahead``.
        """
        scale, target = self._scale, self._scale_target
        if scale == target:
            self._scale_rate = 0.0
            return
        direction = 1.0 if target > scale else -1.0
        self._ramp_target = target
        bound = self._default_ramp_rate
        index = self._acc_index
        if index is not None and ahead is not None:
            speed = np.abs(ahead.velocities[index])
            acc = np.abs(ahead.accelerations[index])
            if here is not None:
                speed = np.maximum(speed, np.abs(here.velocities[index]))
                acc = np.maximum(acc, np.abs(here.accelerations[index]))
            moving = speed > 1e-9
            if moving.any():
                room = self._acc_limit - acc * (scale * scale)
                bound = min(bound, float((np.maximum(room, 0.0)[moving] / speed[moving]).min()))
        period_s = self._lookahead_ns / NS_PER_S
        self._scale_rate = direction * min(bound, abs(target - scale) / period_s)

    def _scaled(self, sample: TrajectorySample) -> TrajectorySample:
        """``sample`` (a reference sample in trajectory time) as the joints move on the clock:
        velocities times the factor, accelerations ``a s^2 + v ds/dt``; positions and effort
        as they are."""
        scale, rate = self._scale, self._scale_rate
        if (scale == 1.0 and rate == 0.0) or self._following_stop:
            return sample
        v = sample.velocities
        return TrajectorySample(
            sample.positions, v * scale, sample.accelerations * (scale * scale) + v * rate,
            sample.effort,
        )

    # -- runtime parameters -------------------------------------------------------------------

    def get_parameters(self, names: Iterable[str] | None = None) -> dict[str, Any]:
        """Parameter values by ROS-style name (``gains.<joint>.p``): all, or ``names``.

        Raises:
            ConfigurationError: a name is not a parameter of this controller.
        """
        return get_parameters(self.config, names)

    def set_parameters(self, changes: Mapping[str, Any]) -> ParameterChange:
        """Change parameters while running, with upstream's timing (``ParameterChange.effects``):
        gains from the next ``update``; default tolerances, ``goal_time`` and the goal checks
        (``allow_*``) from the next command, the running one keeping its own; ``cmd_timeout``
        and the activation settings at the next ``activate``.

        Example::

            ctrl.set_parameters({"gains.j1.p": 12.0, "constraints.goal_time": 0.5})

        Raises:
            ConfigurationError: an unknown or read-only parameter, or a value the
                configuration file would refuse (the same message); nothing changed.
        """
        change = set_parameters(self.config, changes)
        self.apply_parameters(change.config)
        return change

    def apply_parameters(self, config: ControllerConfig) -> None:
        """Switch to ``config``, a checked configuration differing from the current one only in
        parameters that may change at runtime (``set_parameters`` made elsewhere, e.g. by the
        daemon's API process); same timing as ``set_parameters``.

        Raises:
            ConfigurationError: ``config`` changes read-only parameters (named); nothing changed.
        """
        fixed = read_only_differences(self.config, config)
        if fixed:
            raise ConfigurationError(
                f"read-only parameters differ: {', '.join(fixed)}; they cannot change while "
                "the controller runs"
            )
        self.config = config
        self._planner = Planner(config)  # defaults and checks for the next command
        self._set_ramp_bounds(config)
        gains = [config.gains[j] for j in self.joint_names]
        self._pid.set_gains(
            np.array([g.p for g in gains]),
            np.array([g.i for g in gains]),
            np.array([g.d for g in gains]),
            np.array([g.i_clamp for g in gains]),
        )
        self._ff = np.array([g.ff_velocity_scale for g in gains])
        self._stop_decel = stop_decelerations(config)
        self._stop_jerk = stop_jerks(config)

    # -- the cycle ----------------------------------------------------------------------------

    def update(self, now_ns: int, period_ns: int, state: JointState) -> UpdateResult:
        """One control cycle; see the module docstring for the order of decisions.

        Args:
            now_ns: this cycle's time.
            period_ns: time since the previous cycle (PID integration step).
            state: measured state at ``now_ns``.

        Raises:
            ControllerStateError: the controller is not active.
            HardwareError: the state has missing or non-finite positions (a failed read must
                never be taken for a position); nothing is commanded.
        """
        if not self._active:
            raise ControllerStateError("update: the controller is not active")
        positions = self._checked_positions(state)
        self._measured = state
        # Speed scaling (upstream section 13): the reference is sampled, and tolerances, goal
        # time and cmd_timeout judged, in trajectory time.
        tau = self._advance(now_ns)
        if self._pending_stop is not None:
            self._apply_stop(now_ns, state, positions)
        if tau < self._ref.state_before_ns:
            return self._before_reference(now_ns, state, positions)
        desired = self._scaled(self._ref.sample(tau))
        error = self._error(desired, state, positions)
        # The look-ahead time (upstream section 7 step 7: one nominal period ahead, unscaled):
        # decisions judge "before the last point" on it.
        ahead_ns = tau + self._lookahead_ns
        ex = self._execution
        if ex is not None:
            outcome = self._check(tau, ahead_ns, ex, error)
            if outcome is not None:
                self._conclude(now_ns, ex, outcome, state, positions)
                if outcome.hold_measured:
                    desired = self._scaled(self._ref.sample(tau))
                    error = self._error(desired, state, positions)
            elif ex.goal is not None and now_ns >= ex.next_feedback_ns:
                ex.next_feedback_ns = now_ns + self._feedback_ns
                self._events.append(
                    GoalFeedback(
                        ex.goal.goal_id,
                        now_ns,
                        (tau - ex.start_ns) / NS_PER_S,
                        desired,
                        positions,
                        state.velocities,
                        error,
                    )
                )
        command = self._control(tau, period_ns, desired, error)
        return self._result(now_ns, tau, command, desired, error, state, positions)

    # -- internals ----------------------------------------------------------------------------

    def _result(
        self,
        now_ns: int,
        tau_ns: int,
        command: JointCommand,
        desired: TrajectorySample,
        error: F64,
        state: JointState,
        positions: F64,
    ) -> UpdateResult:
        """The cycle's result: its command, the events queued since the last one and the
        controller state (section 16: feedback velocities and accelerations only with their
        state interfaces)."""
        events, self._events = tuple(self._events), []
        feedback = state
        if (state.velocities is not None and not self._has_vel_state) or (
            state.accelerations is not None and not self._has_acc_state
        ):
            feedback = JointState(
                positions,
                state.velocities if self._has_vel_state else None,
                state.accelerations if self._has_acc_state else None,
            )
        controller_state = ControllerState(
            now_ns,
            desired,
            (tau_ns - self._ref_start_ns) / NS_PER_S,
            feedback,
            (now_ns - self._ref_start_wall_ns) / NS_PER_S,
            error,
            self._output,
            self._scale,
            self._scale_target,
        )
        return UpdateResult(command, events, desired, error, controller_state)

    def _before_reference(self, now_ns: int, state: JointState, positions: F64) -> UpdateResult:
        """A cycle before the reference's ``state_before_ns`` (a clock that went back): upstream
        samples nothing there (section 4.3 step 3), so nothing is decided or commanded; the
        desired state reported is the reference's first."""
        desired = self._ref.sample(self._ref.state_before_ns)
        error = self._error(desired, state, positions)
        return self._result(
            now_ns, self._tau_ns, self._nan_command(), desired, error, state, positions
        )

    def _checked_positions(self, state: JointState) -> F64:
        positions = state.positions
        if positions.shape != (self._n,):
            raise HardwareError(
                f"state has {positions.shape} positions, expected {self._n} "
                f"({', '.join(self.joint_names)})"
            )
        if not np.isfinite(positions).all():
            bad = [self.joint_names[i] for i in np.flatnonzero(~np.isfinite(positions))]
            raise HardwareError(
                f"state position of joint(s) {', '.join(bad)} is not finite; check the "
                "hardware read"
            )
        return positions

    def _error(self, desired: TrajectorySample, state: JointState, positions: F64) -> F64:
        error = np.zeros((3, self._n))
        if self._any_wrap:
            error[0] = np.where(
                self._wrap,
                shortest_angular_distance(positions, desired.positions),
                desired.positions - positions,
            )
        else:
            error[0] = desired.positions - positions
        if self._vel_error and state.velocities is not None:
            error[1] = desired.velocities - state.velocities
        if self._acc_error and state.accelerations is not None:
            error[2] = desired.accelerations - state.accelerations
        return error

    def _check(self, now_ns: int, ahead_ns: int, ex: _Execution, error: F64) -> _Outcome | None:
        tol = ex.tolerances
        # Upstream section 7 step 8: "before the last point" is judged on the look-ahead
        # sample, so success, goal checks and cmd_timeout start one period before the
        # reference reaches the last point (how late is still measured from now).
        before_end = ahead_ns < ex.end_ns
        first, ex.first_sample = ex.first_sample, False
        if before_end or first:
            bad = violated(error, tol.path)
            if bad.any():
                return _Outcome(
                    GoalTransition.ABORT,
                    ErrorCode.PATH_TOLERANCE_VIOLATED,
                    PATH_TOLERANCE_VIOLATED,
                    True,
                    self._describe(error, tol.path, bad),
                )
        if before_end:
            return None
        outside = violated(error, tol.goal)
        late_ns = now_ns - ex.end_ns
        if not outside.any():
            if ex.goal is None and self._cmd_timeout_ns:
                # A topic trajectory never succeeds upstream (section 7 step 8e): it is watched
                # until cmd_timeout stops it, which is what ends a streamed motion whose last
                # point keeps a velocity (section 4.3 step 6) when its client falls silent.
                if late_ns > self._cmd_timeout_ns:
                    return _Outcome(
                        GoalTransition.ABORT,
                        ErrorCode.GOAL_TOLERANCE_VIOLATED,
                        f"Stopped due to command timeout: {late_ns / NS_PER_S:.6f} s past the "
                        f"last point (cmd_timeout {self._cmd_timeout_ns / NS_PER_S:g} s) with no "
                        "new command",
                        True,
                    )
                return None
            return _Outcome(GoalTransition.SUCCEED, ErrorCode.SUCCESSFUL, SUCCEEDED, False)
        if tol.goal_time > 0.0 and late_ns > round(tol.goal_time * NS_PER_S):
            return _Outcome(
                GoalTransition.ABORT,
                ErrorCode.GOAL_TOLERANCE_VIOLATED,
                GOAL_TIME_EXCEEDED.format(late_s=f"{late_ns / NS_PER_S:f}"),
                True,
                self._describe(error, tol.goal, outside),
            )
        if self._cmd_timeout_ns and late_ns > self._cmd_timeout_ns:
            return _Outcome(
                GoalTransition.ABORT,
                ErrorCode.GOAL_TOLERANCE_VIOLATED,
                f"Aborted due to command timeout: {late_ns / NS_PER_S:.6f} s past the last "
                f"point (cmd_timeout {self._cmd_timeout_ns / NS_PER_S:g} s) and still outside "
                "the goal tolerance",
                True,
                self._describe(error, tol.goal, outside),
            )
        return None

    def _describe(self, error: F64, tolerance: F64, bad: NDArray[np.bool_]) -> str:
        parts = []
        for j in np.flatnonzero(bad):
            for row, name in enumerate(("position", "velocity", "acceleration")):
                t = tolerance[row, j]
                e = error[row, j]
                if t > 0.0 and abs(e) > t:
                    parts.append(
                        f"joint '{self.joint_names[j]}' {name} error {e:+.6g} exceeds {t:.6g}"
                    )
        return "; ".join(parts)

    def _conclude(
        self, now_ns: int, ex: _Execution, outcome: _Outcome, state: JointState, positions: F64
    ) -> None:
        self._execution = None
        if ex.goal is not None:
            self._finish(
                ex.goal, outcome.transition, outcome.code, outcome.message, now_ns, outcome.details
            )
        elif outcome.transition is GoalTransition.ABORT:
            self._events.append(TrajectoryStopped(outcome.message, now_ns, outcome.details))
        if outcome.hold_measured:
            self._stop(now_ns, state, positions)

    def _finish(
        self,
        goal: GoalHandle,
        transition: GoalTransition,
        code: ErrorCode,
        message: str,
        now_ns: int,
        details: str = "",
    ) -> None:
        status = goal.transition(transition)
        self._events.append(GoalResult(goal.goal_id, status, code, message, now_ns, details))

    def _hold(self, now_ns: int, positions: F64) -> None:
        """Hold the measured position (open loop: the last commanded one), zero velocity."""
        hold = self._last_command_positions if self.config.open_loop_control else positions
        # The reference runs on trajectory time (speed scaling): the hold starts there.
        self._set_reference(Trajectory.constant(self._traj_time(now_ns), hold.copy()))
        self._pid.reset()

    def _stop(self, now_ns: int, state: JointState, positions: F64) -> None:
        """Bring the joints to rest: the decelerating stop when it is configured and the
        measured velocities are usable (jtc_upstream_behaviour.md section 11.3), else the hold.

        As upstream, the stop starts from the measured position and velocity; its starting
        acceleration (used only by a jerk-limited joint) is the measured one with an
        acceleration state interface, else the reference's at ``now_ns``.

        Raises:
            Nothing.
        """
        velocities = state.velocities
        if (
            self._stop_decel is None
            or velocities is None
            or velocities.shape != (self._n,)
            or not np.isfinite(velocities).all()
        ):
            self._hold(now_ns, positions)
            return
        # The reference runs on trajectory time (speed scaling): the stop starts there, and
        # is then followed at the clock's pace (``_following_stop``).
        tau = self._traj_time(now_ns)
        accelerations = state.accelerations if self._has_acc_state else None
        if accelerations is None or accelerations.shape != (self._n,):
            accelerations = (
                self._scaled(self._ref.sample(tau)).accelerations
                if tau >= self._ref.state_before_ns
                else np.zeros(self._n)
            )
        accelerations = np.where(np.isfinite(accelerations), accelerations, 0.0)
        stop = stop_trajectory(
            tau, positions, velocities, accelerations, self._stop_decel, self._stop_jerk
        )
        self._set_reference(stop)
        self._stop_ref = stop
        self._pid.reset()

    def _set_reference(self, reference: Trajectory, start_ns: int | None = None) -> None:
        """Follow ``reference`` from now on; ``start_ns``: its start time for the state's
        ``time_from_start`` (default: its first breakpoint, the time a hold begins)."""
        self._ref = reference
        self._ref_start_ns = reference.start_ns if start_ns is None else start_ns
        # The same start on the clock (for the feedback's time_from_start).
        self._ref_start_wall_ns = self._wall_ns + (self._ref_start_ns - self._tau_ns)
        self._version += 1

    def _nan_command(self) -> JointCommand:
        nan = self._nan
        return JointCommand(*(nan if on else None for on in self._cmd_fields))

    def _refresh_output(self, command: JointCommand) -> None:
        """Upstream's read-back rule for the state's ``output`` (section 16): take ``command``
        only if every configured interface holds a finite value for every command joint.
        Joints that are not command joints read NaN."""
        mask = self._cmd_mask
        fields = (command.positions, command.velocities, command.accelerations, command.effort)
        exact = True  # ``command`` has exactly the configured fields, NaN off command joints
        for on, values in zip(self._cmd_fields, fields, strict=True):
            if not on:
                exact = exact and values is None
                continue
            if values is None or values.shape != (self._n,):
                return
            if not np.isfinite(values if mask is None else values[mask]).all():
                return
            if mask is not None and not np.isnan(values[~mask]).all():
                exact = False
        if exact:
            self._output = command
            return
        self._output = JointCommand(
            *(
                None if not on or f is None else f if mask is None else np.where(mask, f, np.nan)
                for on, f in zip(self._cmd_fields, fields, strict=True)
            )
        )

    def _require_active_for_commands(self) -> None:
        if not self._active:
            raise GoalRejected("the controller is not active; commands are accepted once it is")

    def _preempt(self, message: str, now_ns: int) -> None:
        ex = self._execution
        if ex is not None and ex.goal is not None:
            if ex.goal.status is GoalStatus.CANCELING:
                self._finish(
                    ex.goal,
                    GoalTransition.PREEMPT,
                    ErrorCode.SUCCESSFUL,
                    CANCELED_ON_REQUEST,
                    now_ns,
                    CANCELED_DETAILS,
                )
            else:
                self._finish(
                    ex.goal, GoalTransition.PREEMPT, ErrorCode.INVALID_GOAL, message, now_ns
                )
        self._execution = None
        self._pending_stop = None

    def _request_stop(self, transition: GoalTransition, reason: str) -> None:
        self._pending_stop = transition
        self._stop_reason = reason

    def _apply_stop(self, now_ns: int, state: JointState, positions: F64) -> None:
        transition, self._pending_stop = self._pending_stop, None
        ex, self._execution = self._execution, None
        if ex is not None and ex.goal is not None and transition is not None:
            code = (
                ErrorCode.SUCCESSFUL
                if transition is GoalTransition.CANCEL_DONE
                else ErrorCode.INVALID_GOAL
            )
            if transition is GoalTransition.CANCEL_DONE:
                self._finish(
                    ex.goal, transition, code, CANCELED_ON_REQUEST, now_ns, self._stop_reason
                )
            else:
                self._finish(ex.goal, transition, code, self._stop_reason, now_ns)
        self._stop(now_ns, state, positions)
        self._commanding = True

    def _control(
        self, tau_ns: int, period_ns: int, desired: TrajectorySample, error: F64
    ) -> JointCommand:
        if not self._commanding:
            if self._scale != self._scale_target:
                self._ramp(None)
            return self._nan_command()
        # Upstream (jtc_upstream_behaviour.md section 12): forwarded commands and the
        # closed-loop feed-forward (velocity, and effort for effort-only) come from the sample
        # one period ahead; the PID acts on the error at ``now`` (``desired``). Beyond
        # upstream, speed scaling applies to every interface: the sample's velocity and
        # acceleration are those of the slowed time (``_scaled``), with the factor's rate for
        # the coming period chosen first (``_ramp``).
        ahead = self._ref.sample(tau_ns + self._lookahead_ns)
        if self._scale != self._scale_target or self._scale_rate != 0.0:
            self._ramp(ahead, self._ref.sample(tau_ns))
        ahead = self._scaled(ahead)
        pid_out: F64 | None = None
        if self._use_pid:
            pid_out = self._ff * ahead.velocities + self._pid.compute(
                error[0], error[1], period_ns / NS_PER_S
            )
        position = velocity = acceleration = effort = None
        if self._cmd_pos:
            position = ahead.positions
        if self._cmd_vel:
            velocity = pid_out if pid_out is not None else ahead.velocities
        if self._cmd_acc:
            acceleration = ahead.accelerations
        if self._cmd_eff:
            assert pid_out is not None
            effort = pid_out + ahead.effort
        # Upstream's last_commanded_state is the look-ahead sample in every joint (also the
        # ones that are only monitored): open-loop holds start from it.
        self._last_command_positions = ahead.positions
        self._last_command_velocities = ahead.velocities
        self._last_command_accelerations = ahead.accelerations
        mask = self._cmd_mask
        if mask is not None:
            # Commands go to command joints only; NaN ("write nothing") for monitored joints.
            position, velocity, acceleration, effort = (
                None if f is None else np.where(mask, f, np.nan)
                for f in (position, velocity, acceleration, effort)
            )
        command = JointCommand(position, velocity, acceleration, effort)
        self._refresh_output(command)
        return command
