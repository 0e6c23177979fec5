"""What the request layer needs from a backend, and what a backend reports to its observers.

:class:`Backend` is implemented for real by :class:`jtc_hw.daemon.core.backend.LoopBackend` (the
control loop in its own process) and in tests by a small controller host. Everything that
consumes the loop's output is an :class:`Observer` (:mod:`jtc_hw.daemon.core.observers` draws
them).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

from ...controller.goals import GoalFeedback, GoalResult
from ...controller.limits_check import TimeScaling
from ...controller.messages import JointTrajectory
from ...controller.parameters import ParameterChange
from ...controller.tolerances import JointTolerance
from ...controller.trajectory import QueriedState

__all__ = ["Accepted", "Backend", "Observer"]


@dataclasses.dataclass(frozen=True, slots=True)
class Accepted:
    """An accepted action goal: its id, and how it was fitted to the joint limits.

    Attributes:
        goal_id: the goal's id (its events and results carry it).
        time_scaling: the uniform slow-down applied to fit the limits (``time_scaling: fit``),
            ``None`` when the goal runs as sent (checked, or no limits).
        duration_s: the last point's ``time_from_start`` after slowing, seconds; ``None``
            with ``time_scaling``.
    """

    goal_id: int
    time_scaling: float | None = None
    duration_s: float | None = None

    @classmethod
    def of(cls, goal_id: int, scaling: TimeScaling | None) -> Accepted:
        """The goal ``goal_id`` accepted with the plan's ``scaling`` (``None``: as sent)."""
        if scaling is None:
            return cls(goal_id)
        return cls(goal_id, scaling.factor, scaling.duration_s)


class Observer(Protocol):
    """What the backend reports to, in the asyncio loop's thread; each method returns at once
    (queue anything slow) and should not raise (an exception is logged and skipped)."""

    def on_state(self, snapshot: dict[str, Any]) -> None:
        """A JSON-able controller state snapshot, at ``state_publish_rate``."""

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None:
        """A goal's feedback or result."""

    def on_command(self, traj: JointTrajectory, goal_id: int | None) -> None:
        """An accepted command as the client sent it (a goal's trajectory, ``goal_id`` its
        id; a topic trajectory, ``goal_id`` None; no points: a stop), before its reply."""

    def on_record(self, event: dict[str, Any]) -> None:
        """A result, fault or re-arm as recordings keep it (``goal_events``' JSON,
        docs/recording.md)."""


class Backend(Protocol):
    """The control loop's host, as the server sees it.

    The synchronous methods are called from the asyncio loop and must return at once (no
    waiting on the control loop): answer from replicas and caches. The coroutines may wait on
    the control loop; only the requesting client waits for them. An unexpected exception
    becomes an ``internal`` error reply.
    """

    joint_names: tuple[str, ...]

    def now_ns(self) -> int:
        """The daemon's monotonic clock, in nanoseconds."""

    def hello(self) -> dict[str, Any]:
        """Facts for a new client (``update_rate``, ``state_publish_rate``, ...)."""

    def config_dict(self) -> dict[str, Any]:
        """The configuration in effect, JSON-able."""

    def status(self) -> dict[str, Any]:
        """Loop statistics, hardware and controller status, JSON-able."""

    async def send_goal(
        self,
        traj: JointTrajectory,
        path_tolerance: Sequence[JointTolerance],
        goal_tolerance: Sequence[JointTolerance],
        goal_time_tolerance: float,
        *,
        time_scaling: str | None = None,
    ) -> Accepted:
        """Accept an action goal: its id, and how it was fitted to the joint limits (the
        ``accepted`` reply then says so).

        Raises:
            GoalRejected: why it was refused, with the FollowJointTrajectory error code.
        """

    async def cancel_goal(self, goal_id: int) -> bool:
        """Request cancellation; False if ``goal_id`` is not executing.

        Raises:
            HardwareError: the control loop did not answer (an ``internal`` error reply).
        """

    async def send_trajectory(
        self, traj: JointTrajectory, *, time_scaling: str | None = None
    ) -> TimeScaling | None:
        """A topic trajectory (no points: stop); how it was fitted to the joint limits.

        Raises:
            GoalRejected: why it was refused.
        """

    def query_state(self, time_ns: int) -> QueriedState:
        """``query_state`` at ``time_ns`` (upstream's section 16: ``success`` only inside
        the reference).

        Raises:
            ControllerStateError: the controller is not active.
        """

    async def sim(self, component: str, freeze: bool | None, fault: str | None = None) -> None:
        """Freeze or release a simulated component's feedback (``None``: unchanged), or
        inject a latched read fault; returns once the loop did.

        Raises:
            ConfigurationError: no such simulated component.
            HardwareError: the component is not simulated hardware, or could not do it.
        """

    async def stop_motion(self) -> bool:
        """End any motion and hold the measured position: cancel the active goal (its result
        is ``canceled``) or stop a topic trajectory. Must not wait on anything but the loop.
        Returns False if there was nothing to stop (the controller is not active: stopped
        after a fault, or not started).

        Raises:
            HardwareError: the request could not reach the control loop.
        """

    async def set_speed_scaling(self, factor: float | None) -> dict[str, float]:
        """Set the speed scaling factor's target (``None``: resume, back to the factor before
        the pause); the control loop's controller ramps to it from its next cycle. Returns
        ``{"factor": in force now, "target": what it ramps to}``.

        Raises:
            ConfigurationError: not a number in ``[0, speed_scaling.max_scaling_factor]``.
            HardwareError: the request could not reach the control loop.
        """

    async def rearm(self) -> bool:
        """Leave a hardware fault: clear the devices' latched faults and hold the position;
        False if there was nothing to re-arm (the controller is running, no fault).

        Raises:
            HardwareError: re-arming failed (the controller stays stopped).
        """

    def get_parameters(self, names: Sequence[str] | None) -> dict[str, Any]:
        """Controller parameters in effect: ``{"parameters": {name: value}, "read_only":
        [name, ...]}`` (``controller.parameters.parameters_report``), all or ``names``.

        Raises:
            ConfigurationError: a name is not a parameter.
        """

    async def set_parameters(self, changes: Mapping[str, Any]) -> ParameterChange:
        """Check a change of controller parameters, have the control loop apply it, and
        return once it has (``config_dict`` and ``hello`` then show it).

        Raises:
            ConfigurationError: an unknown or read-only parameter, or a bad value (the
                configuration file's message); nothing changed.
            HardwareError: the control loop did not answer.
        """

    def add_observer(self, observer: Observer) -> None:
        """Also report to ``observer`` from now on (after those added before)."""
