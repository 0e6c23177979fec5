"""Validation and fitting of commands outside the control loop: :class:`Planner` makes a
:class:`Plan` (a spliced reference, ready to commit) from a command and a reference version.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import GoalRejected
from .config import ControllerConfig
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
from .tolerances import JointTolerance, SegmentTolerances
from .trajectory import Trajectory
from .validation import prepare


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
