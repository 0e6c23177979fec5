"""The action server's bookkeeping: goal UUIDs, statuses, kept results, cancel requests (pure).

Theory of operation
-------------------
``rclcpp_action``'s server keeps, for every goal it accepted, its UUID, its acceptance stamp and
its status (``action_msgs/msg/GoalStatus``), and a finished goal's result until
``result_timeout`` (15 minutes by default) has passed since it ended, so that a client asking
``get_result`` late still has it. :class:`GoalBook` is that record for the ROS 2 transport
(``node.py``), with no I/O, no clock and no Zenoh: the transport passes times in and does what
the book answers (reply, publish, cancel through the request layer).

- A goal is :meth:`~GoalBook.accept`-ed with our goal id once the request layer accepted it;
  from then on the backend's events for that id are the goal's. Events of an id not accepted
  yet are :meth:`~GoalBook.hold`-en (bounded): the backend may tell its observers about a goal
  before the coroutine that sent it resumes (``jtc_hw.daemon.core.requests``, "Goal routing").
- ``get_result`` for a goal still running is parked (:meth:`~GoalBook.want_result`) and
  answered when the result comes (:meth:`~GoalBook.finish` returns who waits); for a UUID
  never seen (or forgotten) the answer is ``STATUS_UNKNOWN`` at once, as rclcpp_action does.
- ``cancel_goal`` follows ``rcl_action_process_cancel_request``: a zero UUID and a zero stamp
  cancel every goal; a zero UUID and a stamp, every goal accepted at or before it; a UUID, that
  goal (and, with a stamp, also those accepted at or before it). The return code:
  ``ERROR_UNKNOWN_GOAL_ID`` for a UUID never seen, ``ERROR_GOAL_TERMINATED`` for a goal that
  has its result, ``ERROR_REJECTED`` when nothing could be canceled, else ``ERROR_NONE``.
- Results are kept for :data:`RESULT_TIMEOUT_NS` after the goal ended, at most
  :data:`MAX_KEPT` finished goals (the oldest go first); the status array lists the running
  goals and the kept ones (at most :data:`MAX_STATUS` of those, the newest).
"""

from __future__ import annotations

import collections
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Final

__all__ = [
    "ABORTED",
    "ACCEPTED",
    "CANCELED",
    "CANCELING",
    "ERROR_GOAL_TERMINATED",
    "ERROR_NONE",
    "ERROR_REJECTED",
    "ERROR_UNKNOWN_GOAL_ID",
    "EXECUTING",
    "MAX_KEPT",
    "MAX_STATUS",
    "MAX_WAITING",
    "RESULT_TIMEOUT_NS",
    "SUCCEEDED",
    "UNKNOWN",
    "ZERO_UUID",
    "Goal",
    "GoalBook",
    "status_code",
]

# action_msgs/msg/GoalStatus
UNKNOWN: Final = 0
ACCEPTED: Final = 1
EXECUTING: Final = 2
CANCELING: Final = 3
SUCCEEDED: Final = 4
CANCELED: Final = 5
ABORTED: Final = 6
_TERMINAL: Final = frozenset({SUCCEEDED, CANCELED, ABORTED})

# action_msgs/srv/CancelGoal response codes
ERROR_NONE: Final = 0
ERROR_REJECTED: Final = 1
ERROR_UNKNOWN_GOAL_ID: Final = 2
ERROR_GOAL_TERMINATED: Final = 3

ZERO_UUID: Final = bytes(16)
RESULT_TIMEOUT_NS: Final = 15 * 60 * 10**9
"""rclcpp_action's default ``result_timeout``: how long a finished goal's result is kept."""
MAX_KEPT: Final = 256
"""Finished goals kept at most (beyond: the oldest is forgotten before its timeout)."""
MAX_STATUS: Final = 64
"""Finished goals listed in a status array at most (the newest)."""
MAX_WAITING: Final = 256
"""``get_result`` requests parked at once, over all goals (beyond: answered UNKNOWN)."""
EARLY_GOALS: Final = 64
"""Goal ids whose events are held until the goal is accepted here."""
EARLY_EVENTS: Final = 64
"""Events held per such goal (the last is always kept: it may be the result)."""

_STATUS_OF = {"succeeded": SUCCEEDED, "canceled": CANCELED, "aborted": ABORTED,
              "executing": EXECUTING, "canceling": CANCELING}


def status_code(status: Any) -> int:
    """``GoalStatus.status`` of our ``jtc_hw.controller.goals.GoalStatus`` (or its value)."""
    return _STATUS_OF.get(getattr(status, "value", status), UNKNOWN)


@dataclass(eq=False)
class Goal:
    """One goal as the action server knows it.

    Attributes:
        uuid: the client's 16-byte goal id.
        goal_id: ours (the request layer's).
        stamp_ns: when it was accepted, ROS time (the system clock), nanoseconds.
        status: its ``GoalStatus`` code.
        error_code, error_string: its result (once ``status`` is terminal).
        ended_ns: when the result came, ROS time.
        waiting: ``get_result`` requests parked until the result (the transport's objects).
    """

    uuid: bytes
    goal_id: int
    stamp_ns: int
    status: int = EXECUTING
    error_code: int = 0
    error_string: str = ""
    ended_ns: int | None = None
    waiting: list[Any] = field(default_factory=list)

    @property
    def terminal(self) -> bool:
        return self.status in _TERMINAL


class GoalBook:
    """Every goal of one action server (module docstring)."""

    def __init__(self) -> None:
        self._by_uuid: dict[bytes, Goal] = {}
        self._by_id: dict[int, Goal] = {}
        self._finished: collections.OrderedDict[bytes, None] = collections.OrderedDict()
        self._early: collections.OrderedDict[int, list[Any]] = collections.OrderedDict()
        self._waiting = 0

    # -- goals --------------------------------------------------------------------------------

    def known(self, uuid: bytes) -> bool:
        """Whether a goal with this UUID is running or its result is kept."""
        return uuid in self._by_uuid

    def get(self, uuid: bytes) -> Goal | None:
        return self._by_uuid.get(uuid)

    def by_id(self, goal_id: int) -> Goal | None:
        """The goal of our id ``goal_id``, if it is ours and known."""
        return self._by_id.get(goal_id)

    def accept(self, uuid: bytes, goal_id: int, stamp_ns: int) -> tuple[Goal, list[Any]]:
        """Record an accepted goal (status EXECUTING: upstream executes at once); also the
        events of ``goal_id`` held so far, to be handled now in their order.

        Raises:
            ValueError: the UUID is in use (the transport rejects such a goal first).
        """
        if uuid in self._by_uuid:
            raise ValueError("goal UUID already in use")
        goal = Goal(uuid, goal_id, stamp_ns)
        self._by_uuid[uuid] = goal
        self._by_id[goal_id] = goal
        return goal, self._early.pop(goal_id, [])

    def hold(self, goal_id: int, event: Any) -> None:
        """Keep an event of a goal id not (yet) accepted here, bounded (module docstring)."""
        events = self._early.get(goal_id)
        if events is None:
            if len(self._early) >= EARLY_GOALS:
                self._early.popitem(last=False)
            events = self._early[goal_id] = []
        if len(events) >= EARLY_EVENTS:
            events.pop(-2 if len(events) > 1 else -1)
        events.append(event)

    def forget_held(self, goal_id: int) -> None:
        """Drop held events of ``goal_id`` (it is not ours: another transport's)."""
        self._early.pop(goal_id, None)

    def canceling(self, goal: Goal) -> None:
        """``goal``'s cancel was accepted (status CANCELING)."""
        if not goal.terminal:
            goal.status = CANCELING

    def finish(self, goal_id: int, status: int, error_code: int, error_string: str,
               now_ns: int) -> Goal | None:
        """The result of ``goal_id`` came: the goal (its ``waiting`` requests to answer, then
        cleared by the caller with :meth:`answered`), None if it is not ours. A second result
        for the same goal is ignored (None)."""
        goal = self._by_id.get(goal_id)
        if goal is None or goal.terminal:
            return None
        goal.status = status
        goal.error_code = error_code
        goal.error_string = error_string
        goal.ended_ns = now_ns
        self._finished[goal.uuid] = None
        while len(self._finished) > MAX_KEPT:
            self._forget(next(iter(self._finished)))
        return goal

    def answered(self, goal: Goal) -> list[Any]:
        """Take the parked ``get_result`` requests of ``goal``."""
        waiting, goal.waiting = goal.waiting, []
        self._waiting -= len(waiting)
        return waiting

    def want_result(self, uuid: bytes, request: Any) -> bool:
        """Park a ``get_result`` request on the running goal ``uuid``; False when the goal is
        not running (unknown, forgotten or finished: answer now, :meth:`get`) or when
        :data:`MAX_WAITING` are parked already (answer ``STATUS_UNKNOWN``)."""
        goal = self._by_uuid.get(uuid)
        if goal is None or goal.terminal or self._waiting >= MAX_WAITING:
            return False
        goal.waiting.append(request)
        self._waiting += 1
        return True

    def expire(self, now_ns: int) -> int:
        """Forget results older than :data:`RESULT_TIMEOUT_NS`; how many were."""
        expired = 0
        while self._finished:
            uuid = next(iter(self._finished))
            ended = self._by_uuid[uuid].ended_ns or 0
            if now_ns - ended < RESULT_TIMEOUT_NS:
                break
            self._forget(uuid)
            expired += 1
        return expired

    def _forget(self, uuid: bytes) -> None:
        self._finished.pop(uuid, None)
        goal = self._by_uuid.pop(uuid, None)
        if goal is not None:
            self._by_id.pop(goal.goal_id, None)

    # -- cancel -------------------------------------------------------------------------------

    def cancel_targets(self, uuid: bytes, stamp_ns: int) -> tuple[int, list[Goal]]:
        """The goals a ``cancel_goal`` request names that can be canceled, and the return code
        if none of them turns out to be (module docstring). With goals listed the transport
        cancels each, and answers ``ERROR_NONE`` with those that were, ``ERROR_REJECTED``
        (or this code, when more specific) when none was."""
        goals = list(self._by_uuid.values())
        code = ERROR_REJECTED
        if uuid == ZERO_UUID:
            chosen: Iterable[Goal] = (g for g in goals if stamp_ns == 0 or g.stamp_ns <= stamp_ns)
        else:
            named = self._by_uuid.get(uuid)
            if named is None:
                code = ERROR_UNKNOWN_GOAL_ID
            elif named.terminal:
                code = ERROR_GOAL_TERMINATED
            chosen = (g for g in goals
                      if g is named or (stamp_ns != 0 and g.stamp_ns <= stamp_ns))
        return code, [g for g in chosen if not g.terminal]

    # -- status -------------------------------------------------------------------------------

    def status_list(self) -> list[Goal]:
        """The goals of a status array: running ones, then the newest kept results, in order
        of acceptance."""
        running = [g for g in self._by_uuid.values() if not g.terminal]
        kept = [self._by_uuid[u] for u in list(self._finished)[-MAX_STATUS:]]
        return sorted(running + kept, key=lambda g: (g.stamp_ns, g.goal_id))

    @property
    def running(self) -> int:
        return sum(1 for g in self._by_uuid.values() if not g.terminal)

    @property
    def kept(self) -> int:
        return len(self._finished)

    @property
    def waiting(self) -> int:
        return self._waiting
