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

Speed scaling (:mod:`.speed_scaling`): "now" above is trajectory time, which advances by the
elapsed clock time times a ramping factor (the clock while it is 1); the velocities and
accelerations sampled are those of the slowed motion (``v s``, ``a s^2 + v ds/dt``).

The class is one object in several modules: commands, the lifecycle and the cycle here; the
planning in :mod:`.planner`, the decisions in :mod:`.outcomes`, and as mixins (their methods
called directly, no indirection per cycle) :mod:`.speed_scaling`, :mod:`.stops` and
:mod:`.control_law`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import (
    ConfigurationError,
    ControllerStateError,
    GoalRejected,
    HardwareError,
    StalePlan,
)
from .config import ControllerConfig
from .control_law import ControlLaw
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
from .joints import F64, JointCommand, JointState, all_finite
from .limits_check import TimeScaling
from .messages import NS_PER_S, JointTrajectory
from .outcomes import (
    CANCELED_DECELERATING_DETAILS,
    CANCELED_DETAILS,
    CANCELED_ON_REQUEST,
    DEACTIVATED,
    PREEMPTED_BY_ACTION,
    PREEMPTED_BY_TOPIC,
    Execution,
    Outcome,
    judge,
)
from .parameters import ParameterChange, get_parameters, read_only_differences, set_parameters
from .pid import Pid
from .planner import Plan, Planner, in_trajectory_time
from .results import ControllerState, UpdateResult
from .stopping import stop_decelerations, stop_jerks, warm_up
from .stops import Stops
from .tolerances import JointTolerance
from .trajectory import QueriedState, Trajectory, TrajectorySample, shortest_angular_distance


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


class JointTrajectoryController(ControlLaw, Stops):
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
        *pid_gains, self._ff = self._gains(config)
        self._pid = Pid(*pid_gains)
        cmd = config.command_interfaces
        self._cmd_fields = self._cmd_pos, self._cmd_vel, self._cmd_acc, self._cmd_eff = (
            "position" in cmd, "velocity" in cmd, "acceleration" in cmd, "effort" in cmd)
        self._use_pid = config.use_pid
        self._has_vel_state = "velocity" in config.state_interfaces
        self._has_acc_state = "acceleration" in config.state_interfaces
        self._cmd_mask = _command_mask(config)
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
        self._execution: Execution | None = None
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
        # Speed scaling (upstream section 13; :mod:`.speed_scaling` declares this state).
        self._tau_ns = 0
        self._wall_ns = 0
        self._timebase_started = False
        self._ref_start_wall_ns = 0
        initial = config.speed_scaling.initial_scaling_factor
        self._scale = initial
        self._scale_target = initial
        self._scale_rate = 0.0  # d(factor)/dt in force since _wall_ns, 1/s
        self._ramp_target = initial  # what _scale_rate aims at (the target may change since)
        self._scale_jump = False
        self._resume_scale = initial if initial > 0.0 else 1.0
        self._scale_request = initial
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

        The start state is the measured one, except that with
        ``set_last_command_interface_value_as_state_on_activation`` and every joint a command
        joint, each commanded field of ``last_command`` that is finite for every joint takes
        its place (docs/behaviour.md, "Activation and commands"). The hold is at the start
        positions with zero velocity; the start state is also ``last_commanded_state`` and
        ``last_command`` the first ``output`` of the controller state. Any trajectory or goal
        from an earlier activation is gone; PID integrators start at zero.

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
        self._scale = self._scale_target = self._scale_request = initial
        self._scale_rate = 0.0
        self._scale_jump = False
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

        Returns the events not yet delivered, ending with the goal's result if one was active.

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
        any, is canceled (its result is delivered with the next ``update``). Returns the goal
        id; its result arrives exactly once among ``update``/``deactivate`` events.

        Args:
            time_scaling: a goal beyond the joint limits is rejected (``"reject"``) or slowed
                down to fit them (``"fit"``); None: ``config.time_scaling``. With ``fit``,
                ``last_time_scaling`` then says the factor and the new duration.

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
        (``Plan.time_scaling`` says how a ``fit`` goal was slowed); raises as ``send_goal`` does."""
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
        """First half of ``send_trajectory`` for a non-empty trajectory; raises as it does."""
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
        """Second half: swap in a planned reference (O(1), no fitting); the goal id for a goal
        plan, None for a topic plan.

        The plan's times are trajectory times (:attr:`trajectory_time_ns`; equal to the clock
        while the speed scaling factor has always been 1); ``now_ns`` is the clock's.

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
        self._execution = Execution(handle, plan.tolerances, plan.start_ns, plan.reference.end_ns)
        self._commanding = True
        return None if handle is None else handle.goal_id

    @property
    def reference_version(self) -> int:
        """Increments every time the reference changes (activation, commit, stop, abort)."""
        return self._version

    def cancel_goal(self, goal_id: int) -> bool:
        """Request cancellation; the goal ends ``CANCELED`` at the next ``update``, which holds
        the measured position. Returns False if ``goal_id`` is not the executing goal
        (unknown, finished or canceling)."""
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
        *pid_gains, self._ff = self._gains(config)
        self._pid.set_gains(*pid_gains)
        self._stop_decel = stop_decelerations(config)
        self._stop_jerk = stop_jerks(config)

    def _gains(self, config: ControllerConfig) -> list[F64]:
        """Per joint: p, i, d, i_clamp and the velocity feed-forward scale."""
        gains = [config.gains[j] for j in self.joint_names]
        fields = ("p", "i", "d", "i_clamp", "ff_velocity_scale")
        return [np.array([getattr(g, f) for g in gains]) for f in fields]

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
            outcome = judge(tau, ahead_ns, ex, error, self._cmd_timeout_ns, self.joint_names)
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
        if not all_finite(positions):
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
            np.subtract(desired.positions, positions, out=error[0])
        if self._vel_error and state.velocities is not None:
            np.subtract(desired.velocities, state.velocities, out=error[1])
        if self._acc_error and state.accelerations is not None:
            np.subtract(desired.accelerations, state.accelerations, out=error[2])
        return error

    def _conclude(
        self, now_ns: int, ex: Execution, outcome: Outcome, state: JointState, positions: F64
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

    def _set_reference(self, reference: Trajectory, start_ns: int | None = None) -> None:
        """Follow ``reference`` from now on; ``start_ns``: its start time for the state's
        ``time_from_start`` (default: its first breakpoint, the time a hold begins)."""
        self._ref = reference
        self._ref_start_ns = reference.start_ns if start_ns is None else start_ns
        # The same start on the clock (for the feedback's time_from_start).
        self._ref_start_wall_ns = self._wall_ns + (self._ref_start_ns - self._tau_ns)
        self._version += 1

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
