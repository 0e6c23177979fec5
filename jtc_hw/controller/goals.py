"""Goal lifecycle: one status enum and one transition table (every goal ends exactly once).

::

    EXECUTING --cancel requested--> CANCELING --hold applied--> CANCELED
    EXECUTING --succeed--> SUCCEEDED        EXECUTING / CANCELING --abort--> ABORTED
    EXECUTING / CANCELING --preempt--> CANCELED

Terminal states have no outgoing transition, so a second result for a goal is an error raised
where it would happen, not a message a client receives.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, IntEnum

import numpy as np
from numpy.typing import NDArray

from ..errors import ControllerStateError
from .trajectory import TrajectorySample


class ErrorCode(IntEnum):
    """``control_msgs/FollowJointTrajectory`` result codes."""

    SUCCESSFUL = 0
    INVALID_GOAL = -1
    INVALID_JOINTS = -2
    OLD_HEADER_TIMESTAMP = -3
    PATH_TOLERANCE_VIOLATED = -4
    GOAL_TOLERANCE_VIOLATED = -5


class GoalStatus(Enum):
    """Where a goal is in its life."""

    EXECUTING = "executing"
    CANCELING = "canceling"
    SUCCEEDED = "succeeded"
    ABORTED = "aborted"
    CANCELED = "canceled"

    @property
    def terminal(self) -> bool:
        """True once the goal has its result."""
        return self in (GoalStatus.SUCCEEDED, GoalStatus.ABORTED, GoalStatus.CANCELED)


class GoalTransition(Enum):
    """What can happen to a goal."""

    REQUEST_CANCEL = "request_cancel"
    CANCEL_DONE = "cancel_done"
    SUCCEED = "succeed"
    ABORT = "abort"
    PREEMPT = "preempt"


_S, _T = GoalStatus, GoalTransition
TRANSITIONS: dict[tuple[GoalStatus, GoalTransition], GoalStatus] = {
    (_S.EXECUTING, _T.REQUEST_CANCEL): _S.CANCELING,
    (_S.EXECUTING, _T.SUCCEED): _S.SUCCEEDED,
    (_S.EXECUTING, _T.ABORT): _S.ABORTED,
    (_S.EXECUTING, _T.PREEMPT): _S.CANCELED,
    (_S.CANCELING, _T.CANCEL_DONE): _S.CANCELED,
    (_S.CANCELING, _T.ABORT): _S.ABORTED,
    (_S.CANCELING, _T.PREEMPT): _S.CANCELED,
}


@dataclass(frozen=True)
class GoalResult:
    """The one result of an accepted goal.

    Attributes:
        error_string: upstream's text, exactly (e.g. "Aborted due to path tolerance
            violation"), so that clients comparing strings keep working.
        details: what upstream only logs: which joint broke which tolerance, by how much
            ("" when there is nothing to add).
    """

    goal_id: int
    status: GoalStatus
    error_code: ErrorCode
    error_string: str
    time_ns: int
    details: str = ""


@dataclass(frozen=True, eq=False)
class GoalFeedback:
    """Progress of the active goal (``FollowJointTrajectory`` feedback).

    Attributes:
        time_from_start: seconds since the goal's trajectory start time (negative while a
            future start time has not come).
        desired: the reference at ``time_ns``.
        actual_positions, actual_velocities: measured state (velocities ``None`` without a
            velocity state interface).
        error: ``(3, n)`` position / velocity / acceleration error, desired minus actual
            (position error wrapped for continuous joints).
    """

    goal_id: int
    time_ns: int
    time_from_start: float
    desired: TrajectorySample
    actual_positions: NDArray[np.float64]
    actual_velocities: NDArray[np.float64] | None
    error: NDArray[np.float64]


@dataclass(frozen=True)
class TrajectoryStopped:
    """A topic (fire-and-forget) trajectory was stopped by the controller; no goal to report to.

    ``reason`` and ``details`` are as a goal result's ``error_string`` and ``details``.
    """

    reason: str
    time_ns: int
    details: str = ""


Event = GoalResult | GoalFeedback | TrajectoryStopped


class GoalHandle:
    """An accepted goal's identity and status."""

    __slots__ = ("goal_id", "status")

    def __init__(self, goal_id: int) -> None:
        self.goal_id = goal_id
        self.status = GoalStatus.EXECUTING

    def transition(self, event: GoalTransition) -> GoalStatus:
        """Apply ``event``; returns the new status.

        Raises:
            ControllerStateError: the transition is not in the table (e.g. a second result).
        """
        new = TRANSITIONS.get((self.status, event))
        if new is None:
            raise ControllerStateError(
                f"goal {self.goal_id}: cannot {event.value} a goal that is {self.status.value}"
            )
        self.status = new
        return new
