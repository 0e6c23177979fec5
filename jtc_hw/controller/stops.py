"""Stops: requested (an empty topic trajectory, a cancel, an abort, the daemon's shutdown) and
applied by the next ``update``: a hold of the measured position, or with
``decelerate_on_cancel`` a decelerating stop (its trajectory: :mod:`.stopping`).

A mixin of :class:`~.controller.JointTrajectoryController`, which sets the state declared here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeGuard

import numpy as np

from .goals import ErrorCode, GoalTransition
from .joints import F64, JointState
from .outcomes import CANCELED_ON_REQUEST, STOPPED_BY_TOPIC, Execution
from .pid import Pid
from .speed_scaling import SpeedScaling
from .stopping import stop_duration_bound_s, stop_trajectory
from .trajectory import Trajectory


class Stops(SpeedScaling):
    """The stop methods of the controller (module docstring)."""

    _execution: Execution | None
    _pending_stop: GoalTransition | None
    _stop_reason: str
    _stop_decel: F64 | None
    _stop_jerk: F64
    _has_acc_state: bool
    _last_command_positions: F64
    _pid: Pid
    _commanding: bool
    _require_active_for_commands: Callable[[], None]
    _set_reference: Callable[..., None]
    _finish: Callable[..., None]

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
        """
        v = state.velocities
        if self._stop_decel is None or not self._usable(v):
            return 0.0
        a = state.accelerations if self._has_acc_state else None
        if not self._usable(a):
            a = np.zeros(self._n)
        return stop_duration_bound_s(v, a, self._stop_decel, self._stop_jerk)

    def _usable(self, values: F64 | None) -> TypeGuard[F64]:
        """Whether ``values`` are measured values of every joint, all finite."""
        return values is not None and values.shape == (self._n,) and bool(np.isfinite(values).all())

    def _request_stop(self, transition: GoalTransition, reason: str) -> None:
        self._pending_stop = transition
        self._stop_reason = reason

    def _apply_stop(self, now_ns: int, state: JointState, positions: F64) -> None:
        transition, self._pending_stop = self._pending_stop, None
        ex, self._execution = self._execution, None
        if ex is not None and ex.goal is not None and transition is not None:
            if transition is GoalTransition.CANCEL_DONE:
                self._finish(ex.goal, transition, ErrorCode.SUCCESSFUL, CANCELED_ON_REQUEST,
                             now_ns, self._stop_reason)
            else:
                self._finish(ex.goal, transition, ErrorCode.INVALID_GOAL, self._stop_reason, now_ns)
        self._stop(now_ns, state, positions)
        self._commanding = True

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
        """
        velocities = state.velocities
        if self._stop_decel is None or not self._usable(velocities):
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
