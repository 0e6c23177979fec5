"""What ends a command: upstream's result texts, the command being monitored, and the checks
that decide its outcome each cycle (path and goal tolerances, ``goal_time``, ``cmd_timeout``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from .goals import ErrorCode, GoalHandle, GoalTransition
from .joints import F64
from .messages import NS_PER_S
from .tolerances import SegmentTolerances, exceeds, violated

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


@dataclass
class Execution:
    """The command being monitored: an action goal, or a topic trajectory (goal is None)."""

    goal: GoalHandle | None
    tolerances: SegmentTolerances
    start_ns: int
    end_ns: int
    first_sample: bool = True
    next_feedback_ns: int = 0


class Outcome(NamedTuple):
    """How a command ends: its transition, code and texts, and whether to stop at once."""

    transition: GoalTransition
    code: ErrorCode
    message: str
    hold_measured: bool
    details: str = ""


def judge(
    now_ns: int,
    ahead_ns: int,
    ex: Execution,
    error: F64,
    cmd_timeout_ns: int,
    joint_names: tuple[str, ...],
) -> Outcome | None:
    """Whether the executing command ends this cycle (``now_ns``, look-ahead ``ahead_ns``,
    trajectory time), and how: path tolerance while moving, then goal tolerance, ``goal_time``
    and ``cmd_timeout`` (0: none) once the look-ahead reaches the last point."""
    tol = ex.tolerances
    # Upstream section 7 step 8: "before the last point" is judged on the look-ahead
    # sample, so success, goal checks and cmd_timeout start one period before the
    # reference reaches the last point (how late is still measured from now).
    before_end = ahead_ns < ex.end_ns
    first, ex.first_sample = ex.first_sample, False
    if before_end or first:
        if exceeds(error, tol.path_limit):
            bad = violated(error, tol.path)
            return Outcome(
                GoalTransition.ABORT,
                ErrorCode.PATH_TOLERANCE_VIOLATED,
                PATH_TOLERANCE_VIOLATED,
                True,
                describe_violation(joint_names, error, tol.path, bad),
            )
    if before_end:
        return None
    late_ns = now_ns - ex.end_ns
    if not exceeds(error, tol.goal_limit):
        if ex.goal is None and cmd_timeout_ns:
            # A topic trajectory never succeeds upstream (section 7 step 8e): it is watched
            # until cmd_timeout stops it, which is what ends a streamed motion whose last
            # point keeps a velocity (section 4.3 step 6) when its client falls silent.
            if late_ns > cmd_timeout_ns:
                return Outcome(
                    GoalTransition.ABORT,
                    ErrorCode.GOAL_TOLERANCE_VIOLATED,
                    f"Stopped due to command timeout: {late_ns / NS_PER_S:.6f} s past the "
                    f"last point (cmd_timeout {cmd_timeout_ns / NS_PER_S:g} s) with no "
                    "new command",
                    True,
                )
            return None
        return Outcome(GoalTransition.SUCCEED, ErrorCode.SUCCESSFUL, SUCCEEDED, False)
    outside = violated(error, tol.goal)
    if tol.goal_time > 0.0 and late_ns > round(tol.goal_time * NS_PER_S):
        return Outcome(
            GoalTransition.ABORT,
            ErrorCode.GOAL_TOLERANCE_VIOLATED,
            GOAL_TIME_EXCEEDED.format(late_s=f"{late_ns / NS_PER_S:f}"),
            True,
            describe_violation(joint_names, error, tol.goal, outside),
        )
    if cmd_timeout_ns and late_ns > cmd_timeout_ns:
        return Outcome(
            GoalTransition.ABORT,
            ErrorCode.GOAL_TOLERANCE_VIOLATED,
            f"Aborted due to command timeout: {late_ns / NS_PER_S:.6f} s past the last "
            f"point (cmd_timeout {cmd_timeout_ns / NS_PER_S:g} s) and still outside "
            "the goal tolerance",
            True,
            describe_violation(joint_names, error, tol.goal, outside),
        )
    return None

def describe_violation(
    joint_names: tuple[str, ...], error: F64, tolerance: F64, bad: NDArray[np.bool_]
) -> str:
    """Which joint's error exceeds which tolerance, for a result's ``details``."""
    parts = []
    for j in np.flatnonzero(bad):
        for row, name in enumerate(("position", "velocity", "acceleration")):
            t = tolerance[row, j]
            e = error[row, j]
            if t > 0.0 and abs(e) > t:
                parts.append(
                    f"joint '{joint_names[j]}' {name} error {e:+.6g} exceeds {t:.6g}"
                )
    return "; ".join(parts)
