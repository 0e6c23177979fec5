"""Path and goal tolerances: defaults from the configuration, per-goal overrides, checks.

A tolerance of 0 means "not checked". Per-goal values follow ``control_msgs/JointTolerance``:
``> 0`` sets the tolerance, ``0`` keeps the default, ``-1`` erases it (not checked); any other
negative value, a non-finite value or an unknown joint rejects the goal (upstream logs and falls
back to the defaults; we say why instead, see docs/behaviour.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..errors import GoalRejected
from .config import ControllerConfig
from .validation import INVALID_GOAL, INVALID_JOINTS

_ERASE = -1.0
_FIELDS = ("position", "velocity", "acceleration")


@dataclass(frozen=True)
class JointTolerance:
    """One joint's tolerance override (``control_msgs/JointTolerance``)."""

    name: str
    position: float = 0.0
    velocity: float = 0.0
    acceleration: float = 0.0


@dataclass(frozen=True, eq=False)
class SegmentTolerances:
    """Tolerances in effect for one command.

    Attributes:
        path: ``(3, n)`` position / velocity / acceleration tolerance while moving.
        goal: ``(3, n)`` the same at the end (velocity defaults to stopped_velocity_tolerance).
            The velocity and acceleration rows only bite where the controller computes that
            error (upstream 8.4: a velocity or effort command interface for velocity, an
            acceleration command interface for acceleration); elsewhere the error is 0.
        goal_time: seconds allowed past the end to get inside ``goal``; 0 waits forever.
        path_limit, goal_limit: ``path`` and ``goal`` with infinity where a tolerance is not
            checked: an error beyond its limit is a violation (:func:`exceeds`).
    """

    path: NDArray[np.float64]
    goal: NDArray[np.float64]
    goal_time: float
    path_limit: NDArray[np.float64] = field(init=False, repr=False)
    goal_limit: NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name, table in (("path_limit", self.path), ("goal_limit", self.goal)):
            object.__setattr__(self, name, np.where(table > 0.0, table, np.inf))

    @classmethod
    def from_config(cls, config: ControllerConfig) -> SegmentTolerances:
        """The defaults of the ``constraints`` parameters."""
        n = len(config.joints)
        path = np.zeros((3, n))
        goal = np.zeros((3, n))
        for i, joint in enumerate(config.joints):
            c = config.constraints.joints[joint]
            path[0, i] = c.trajectory
            goal[0, i] = c.goal
            goal[1, i] = config.constraints.stopped_velocity_tolerance
        return cls(path, goal, config.constraints.goal_time)

    def with_overrides(
        self,
        joints: Sequence[str],
        path_tolerance: Sequence[JointTolerance] = (),
        goal_tolerance: Sequence[JointTolerance] = (),
        goal_time_tolerance: float = 0.0,
    ) -> SegmentTolerances:
        """Apply a goal's tolerance overrides to these defaults.

        Raises:
            GoalRejected: an unknown or repeated joint, or an illegal value; the message names
                the list, the joint, the field and the value.
        """
        path = self.path.copy()
        goal = self.goal.copy()
        index = {name: i for i, name in enumerate(joints)}
        for label, table, overrides in (
            ("path_tolerance", path, path_tolerance),
            ("goal_tolerance", goal, goal_tolerance),
        ):
            seen: set[str] = set()
            for tol in overrides:
                if tol.name not in index:
                    raise GoalRejected(
                        f"{label}: joint '{tol.name}' is not a controller joint "
                        f"(controller joints: {', '.join(joints)})",
                        INVALID_JOINTS,
                    )
                if tol.name in seen:
                    raise GoalRejected(
                        f"{label}: joint '{tol.name}' is listed twice", INVALID_JOINTS
                    )
                seen.add(tol.name)
                for row, name in enumerate(_FIELDS):
                    value = getattr(tol, name)
                    where = f"{label}.{tol.name}.{name}"
                    table[row, index[tol.name]] = _resolve(
                        table[row, index[tol.name]], value, where
                    )
        goal_time = _resolve(self.goal_time, goal_time_tolerance, "goal_time_tolerance")
        return SegmentTolerances(path, goal, goal_time)


def _resolve(default: float, value: float, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise GoalRejected(f"{where}: expected a finite number, got {value!r}", INVALID_GOAL)
    if value > 0.0:
        return float(value)
    if value == 0.0:
        return default
    if abs(value - _ERASE) < 1e-7:
        return 0.0
    raise GoalRejected(
        f"{where}: {value!r} is not a tolerance; use > 0 to set it, 0 for the default, "
        "-1 to erase it",
        INVALID_GOAL,
    )


def exceeds(error: NDArray[np.float64], limit: NDArray[np.float64]) -> bool:
    """Whether any field of ``error`` (3, n) is beyond its ``limit`` (3, n; a tolerance's
    ``*_limit``): ``violated(...).any()`` in one comparison, the check of every cycle
    (``count_nonzero`` rather than ``any``: a third of its cost on a few values)."""
    return np.count_nonzero(np.abs(error) > limit) != 0


def violated(error: NDArray[np.float64], tolerance: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Per joint, whether any checked field of ``error`` (3, n) exceeds ``tolerance`` (3, n)."""
    bad: NDArray[np.bool_] = np.any((tolerance > 0.0) & (np.abs(error) > tolerance), axis=0)
    return bad
