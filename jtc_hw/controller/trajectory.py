"""Trajectory messages and the immutable reference trajectory the controller samples.

Theory of operation
-------------------
A ``JointTrajectory`` is what a client sends (``trajectory_msgs/JointTrajectory``): joint names,
points with ``time_from_start``, and a start time (the header stamp; 0 means "start now").

A ``Trajectory`` is what the controller follows: one piecewise polynomial per controller joint,
on a shared grid of integer-nanosecond breakpoints so that knots are hit exactly. It is built
once (``Trajectory.constant`` at activation, then ``splice`` for every new command) and never
changes afterwards; ``sample(t)`` is a pure function of ``t``.

``splice`` implements the reference's *trajectory replacement*:

1. keep the new points whose time (start + ``time_from_start``) is now or later; if none is
   left, reject (``OLD_HEADER_TIMESTAMP``) and leave the current trajectory untouched;
2. keep the current trajectory up to ``Ts = max(start, now)``;
3. bridge from the current trajectory's state at ``Ts`` (position, velocity, acceleration,
   effort) to the first kept point, then follow the kept points.

Joints absent from a partial goal keep following the current trajectory. Because the bridge
starts from the current *reference*, a new or replacing command never steps the command; its
smoothness is the continuity level that the first point's fields allow (linear: position,
cubic: velocity, quintic: acceleration).
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..errors import GoalRejected
from .interpolation import (
    F64,
    SegmentKind,
    constant_block,
    evaluate,
    kind_for,
    position_coefficients,
    segment_block,
)

NS_PER_S = 1_000_000_000
OLD_HEADER_TIMESTAMP = -3


def seconds_to_ns(seconds: float) -> int:
    """Convert seconds to integer nanoseconds, rounding to the nearest nanosecond.

    Raises:
        ValueError: ``seconds`` is not a finite number.
    """
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)):
        raise ValueError(f"expected a number of seconds, got {seconds!r}")
    if not math.isfinite(seconds):
        raise ValueError(f"expected a finite number of seconds, got {seconds!r}")
    if isinstance(seconds, int):
        return seconds * NS_PER_S
    return round(seconds * NS_PER_S)


Values = Sequence[float] | NDArray[np.floating[Any]]
"""A joint vector as accepted from users: a sequence of floats or a float numpy array."""


def _field(values: Values | None) -> tuple[float, ...] | None:
    if values is None:
        return None
    out = tuple(values)
    return out if out else None


@dataclass(frozen=True, init=False)
class TrajectoryPoint:
    """One waypoint (``trajectory_msgs/JointTrajectoryPoint``).

    Fields that are absent (``None`` or empty) are not used; which ones are present selects the
    interpolation (see ``Trajectory``). Values are in SI units in the order of the trajectory's
    ``joint_names``. Content is checked by the controller, not here.

    Args:
        time_from_start: seconds after the trajectory's start time (``time_from_start_ns`` gives
            it in integer nanoseconds instead).
    """

    time_from_start_ns: int
    positions: tuple[float, ...] | None
    velocities: tuple[float, ...] | None
    accelerations: tuple[float, ...] | None
    effort: tuple[float, ...] | None

    def __init__(
        self,
        time_from_start: float | None = None,
        positions: Values | None = None,
        velocities: Values | None = None,
        accelerations: Values | None = None,
        effort: Values | None = None,
        *,
        time_from_start_ns: int | None = None,
    ) -> None:
        if time_from_start_ns is None:
            time_from_start_ns = 0 if time_from_start is None else seconds_to_ns(time_from_start)
        object.__setattr__(self, "time_from_start_ns", int(time_from_start_ns))
        object.__setattr__(self, "positions", _field(positions))
        object.__setattr__(self, "velocities", _field(velocities))
        object.__setattr__(self, "accelerations", _field(accelerations))
        object.__setattr__(self, "effort", _field(effort))

    @property
    def time_from_start(self) -> float:
        """``time_from_start`` in seconds."""
        return self.time_from_start_ns / NS_PER_S


@dataclass(frozen=True, init=False)
class JointTrajectory:
    """A trajectory command (``trajectory_msgs/JointTrajectory``).

    Args:
        joint_names: names of the joints the point values refer to, in that order.
        points: the waypoints.
        start_time_ns: the header stamp, on the controller's clock, in nanoseconds; 0 means
            "start now" (when the controller receives it).
    """

    joint_names: tuple[str, ...]
    points: tuple[TrajectoryPoint, ...]
    start_time_ns: int

    def __init__(
        self,
        joint_names: Sequence[str],
        points: Sequence[TrajectoryPoint],
        start_time_ns: int = 0,
    ) -> None:
        object.__setattr__(self, "joint_names", tuple(joint_names))
        object.__setattr__(self, "points", tuple(points))
        object.__setattr__(self, "start_time_ns", int(start_time_ns))


@dataclass(frozen=True)
class PreparedTrajectory:
    """A validated trajectory in the controller's joint indexing (built by ``validation``).

    Missing fields are ``NaN`` rows; ``has_*`` say which fields each point carries.
    """

    joint_indices: NDArray[np.intp]
    start_time_ns: int
    times_ns: tuple[int, ...]
    positions: F64
    velocities: F64
    accelerations: F64
    effort: F64
    has_positions: tuple[bool, ...]
    has_velocities: tuple[bool, ...]
    has_accelerations: tuple[bool, ...]
    has_effort: tuple[bool, ...]


class TrajectorySample(NamedTuple):
    """Desired state of every controller joint at one time (arrays in controller joint order)."""

    positions: F64
    velocities: F64
    accelerations: F64
    effort: F64


def shortest_angular_distance(from_angle: F64, to_angle: F64) -> F64:
    """Signed angle in ``[-pi, pi)`` that takes ``from_angle`` to ``to_angle``."""
    d: F64 = np.mod(to_angle - from_angle + math.pi, 2.0 * math.pi) - math.pi
    return d


def _wrap_offset(start: F64, first: F64) -> F64:
    """Multiple of 2 pi to add to ``first`` so it lies within pi of ``start``.

    At exactly pi the motion keeps the direction of the raw difference, as upstream does.
    """
    raw = first - start
    dist = shortest_angular_distance(start, first)
    tie = np.abs(np.abs(dist) - math.pi) < 1e-9
    dist = np.where(tie, np.copysign(math.pi, raw), dist)
    offset: F64 = (start + dist) - first
    return offset


class _Knots(NamedTuple):
    pos: F64  # (m + 1, k): row 0 is the bridge start
    vel: F64
    acc: F64
    eff: F64
    has_v: list[bool]
    has_a: list[bool]


class _Piece(NamedTuple):
    block: F64  # (4, 6, n)
    origin: NDArray[np.int64]  # (n,)
    kind: NDArray[np.int8]  # (n,)


class Trajectory:
    """Immutable reference trajectory for all controller joints.

    ``sample(t)`` returns, for ``t`` in integer nanoseconds on the controller's clock:

    - before the first breakpoint: the state at the first breakpoint (nothing is extrapolated
      backwards);
    - inside a segment ``[t_i, t_i+1)``: the segment's polynomial; at a knot time exactly, the
      segment that *starts* there, so a knot's own values come back unrounded;
      linear segments give position and a constant velocity (acceleration 0), cubic and quintic
      give position, velocity and acceleration, method ``none`` gives the held point's values;
      effort is linear between points (held for ``none``);
    - at or after the last breakpoint: the last point's position and effort, held, with zero
      velocity and acceleration ("after the last waypoint is reached, its position is held").

    A trajectory with no segments (``constant``) returns its state at every time.
    """

    __slots__ = ("_breaks", "_blocks", "_origins", "_kinds", "_final", "n_joints")

    def __init__(
        self,
        breaks: list[int],
        blocks: F64,
        origins: NDArray[np.int64],
        kinds: NDArray[np.int8],
        final: F64,
    ) -> None:
        self._breaks = breaks
        self._blocks = blocks
        self._origins = origins
        self._kinds = kinds
        final = np.array(final, dtype=np.float64)
        final.setflags(write=False)
        self._final = final
        self.n_joints = final.shape[1]
        for array in (blocks, origins, kinds):
            array.setflags(write=False)

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def constant(
        cls,
        t_ns: int,
        positions: Sequence[float] | F64,
        velocities: Sequence[float] | F64 | None = None,
        accelerations: Sequence[float] | F64 | None = None,
        effort: Sequence[float] | F64 | None = None,
    ) -> Trajectory:
        """A trajectory that is the given state at every time (a hold when velocities are 0)."""
        p = np.asarray(positions, dtype=np.float64)
        zero = np.zeros_like(p)
        rows = [p] + [
            zero if v is None else np.asarray(v, dtype=np.float64)
            for v in (velocities, accelerations, effort)
        ]
        n = p.shape[0]
        return cls(
            [int(t_ns)],
            np.zeros((0, 4, 6, n)),
            np.zeros((0, n), dtype=np.int64),
            np.zeros((0, n), dtype=np.int8),
            np.stack(rows),
        )

    def splice(
        self,
        now_ns: int,
        new: PreparedTrajectory,
        interpolation_method: str = "splines",
        wraparound: NDArray[np.bool_] | None = None,
        keep_from_ns: int | None = None,
    ) -> Trajectory:
        """Combine this trajectory with a new command (the reference's trajectory replacement).

        Args:
            now_ns: the current time.
            new: the validated command.
            interpolation_method: ``"splines"`` or ``"none"``.
            wraparound: per controller joint, whether it is continuous; the new command's
                positions of such a joint are shifted by a multiple of 2 pi so that the first
                kept point is within pi of the current reference (no full turn, no step).
            keep_from_ns: the earliest time the result will be sampled, if before ``now_ns``
                (a plan made ahead of time and swapped in early); this trajectory is kept from
                there, so the result equals it on ``[keep_from_ns, max(start, now_ns))``.

        Returns:
            The new reference; ``self`` is unchanged.

        Raises:
            GoalRejected: every point of ``new`` lies before ``now_ns`` (``OLD_HEADER_TIMESTAMP``).
        """
        start = new.start_time_ns if new.start_time_ns != 0 else now_ns
        abs_times = [start + t for t in new.times_ns]
        keep = bisect_left(abs_times, now_ns)
        if keep == len(abs_times):
            late = (now_ns - abs_times[-1]) / NS_PER_S
            raise GoalRejected(
                f"all {len(abs_times)} point(s) lie in the past: the last one was due "
                f"{late:.6f} s before now (start time {start} ns + time_from_start "
                f"{new.times_ns[-1] / NS_PER_S:.6f} s); send a later start time or 0 for 'now'",
                OLD_HEADER_TIMESTAMP,
            )
        splice_at = max(start, now_ns)
        cols = new.joint_indices
        knot_times = [splice_at] + abs_times[keep:]
        knots = self._new_knots(new, keep, self.sample(splice_at), cols, knot_times, wraparound)
        keep_from = now_ns if keep_from_ns is None else min(keep_from_ns, now_ns)
        return self._combine(keep_from, splice_at, cols, knot_times, knots, interpolation_method)

    @staticmethod
    def _new_knots(
        new: PreparedTrajectory,
        keep: int,
        s0: TrajectorySample,
        cols: NDArray[np.intp],
        knot_times: list[int],
        wraparound: NDArray[np.bool_] | None,
    ) -> _Knots:
        """Knot values for the new joints: row 0 is the bridge start, then the kept points.

        Fills positions (and velocities) of derivative-only points by Heun's method, starting
        from the bridge state, and applies the wraparound offset.
        """
        m = len(knot_times) - 1
        k = cols.shape[0]
        pos = np.empty((m + 1, k))
        vel = np.zeros((m + 1, k))
        acc = np.zeros((m + 1, k))
        eff = np.zeros((m + 1, k))
        pos[0] = s0.positions[cols]
        vel[0] = s0.velocities[cols]
        acc[0] = s0.accelerations[cols]
        eff[0] = s0.effort[cols]
        has_v = [True]
        has_a = [True]
        given = new.positions[keep:].copy()
        if wraparound is not None and new.has_positions[keep]:
            wrap = wraparound[cols]
            if wrap.any():
                given += np.where(wrap, _wrap_offset(pos[0], given[0]), 0.0)
        for row in range(1, m + 1):
            src = keep + row - 1
            hv, ha = new.has_velocities[src], new.has_accelerations[src]
            if ha:
                acc[row] = new.accelerations[src]
            if hv:
                vel[row] = new.velocities[src]
            if new.has_effort[src]:
                eff[row] = new.effort[src]
            if new.has_positions[src]:
                pos[row] = given[row - 1]
            else:
                # Heun's method: trapezoidal integration of acceleration, then of velocity.
                dt = (knot_times[row] - knot_times[row - 1]) / NS_PER_S
                if not hv:
                    vel[row] = vel[row - 1] + (acc[row - 1] + acc[row]) * 0.5 * dt
                    hv = True
                pos[row] = pos[row - 1] + (vel[row - 1] + vel[row]) * 0.5 * dt
            has_v.append(hv)
            has_a.append(ha)
        return _Knots(pos, vel, acc, eff, has_v, has_a)

    def _combine(
        self,
        now_ns: int,
        splice_at: int,
        cols: NDArray[np.intp],
        knot_times: list[int],
        knots: _Knots,
        method: str,
    ) -> Trajectory:
        n = self.n_joints
        partial = cols.shape[0] != n
        pos, eff = knots.pos, knots.eff

        # Breakpoints: the current trajectory from the segment holding `now` up to the splice,
        # the new knots, and (partial goals) the current trajectory's later breakpoints.
        old = self._breaks
        first_old = max(bisect_right(old, now_ns) - 1, 0)
        grid = {b for b in old[first_old:] if b < splice_at}
        grid.update(knot_times)
        if partial:
            grid.update(b for b in old if b > splice_at)
        breaks = sorted(grid)

        segments = len(breaks) - 1
        blocks = np.zeros((segments, 4, 6, n))
        origins = np.zeros((segments, n), dtype=np.int64)
        kinds = np.zeros((segments, n), dtype=np.int8)
        others = np.setdiff1d(np.arange(n), cols) if partial else None
        for i in range(segments):
            t = breaks[i]
            if breaks[i + 1] <= splice_at:
                piece = self._piece_at(t)
                blocks[i], origins[i], kinds[i] = piece
                continue
            new_piece = self._new_piece(t, knot_times, knots, method)
            blocks[i][:, :, cols] = new_piece.block
            origins[i][cols] = new_piece.origin
            kinds[i][cols] = new_piece.kind
            if others is not None:
                piece = self._piece_at(t)
                blocks[i][:, :, others] = piece.block[:, :, others]
                origins[i][others] = piece.origin[others]
                kinds[i][others] = piece.kind[others]

        # Past the end every joint holds its last position and effort (joints a partial command
        # does not name hold the current trajectory's last values).
        final = self._final.copy() if partial else np.zeros((4, n))
        final[1:3] = 0.0
        final[0, cols] = pos[-1]
        final[3, cols] = eff[-1]
        return Trajectory(breaks, blocks, origins, kinds, final)

    @staticmethod
    def _new_piece(
        t: int,
        knot_times: list[int],
        knots: _Knots,
        method: str,
    ) -> _Piece:
        """The new joints' polynomial on the grid segment starting at ``t``."""
        pos, vel, acc, eff, has_v, has_a = knots
        k = pos.shape[1]
        # Index of the knot row that starts the segment containing t. A zero-length bridge
        # (first point due at the splice time) has two rows at the same time: take the later.
        row = bisect_right(knot_times, t) - 1
        if row >= len(knot_times) - 1:
            block = constant_block(pos[-1], np.zeros(k), np.zeros(k), eff[-1])
            return _Piece(block, np.full(k, t, dtype=np.int64), np.zeros(k, dtype=np.int8))
        t0, t1 = knot_times[row], knot_times[row + 1]
        origin = np.full(k, t0, dtype=np.int64)
        if method == "none":
            block = constant_block(pos[row], vel[row], acc[row], eff[row])
            return _Piece(block, origin, np.full(k, SegmentKind.HOLD, dtype=np.int8))
        kind = kind_for(has_v[row] and has_v[row + 1], has_a[row] and has_a[row + 1])
        duration = (t1 - t0) / NS_PER_S
        coeffs = position_coefficients(
            kind, duration, pos[row], vel[row], acc[row], pos[row + 1], vel[row + 1], acc[row + 1]
        )
        slope = (eff[row + 1] - eff[row]) / duration
        return _Piece(segment_block(coeffs, eff[row], slope), origin, np.full(k, kind, np.int8))

    def _piece_at(self, t: int) -> _Piece:
        """This trajectory's polynomial in effect at ``t`` (a constant after the end)."""
        n = self.n_joints
        if not self._blocks.shape[0] or t >= self._breaks[-1]:
            f = self._final
            return _Piece(
                constant_block(f[0], f[1], f[2], f[3]),
                np.full(n, t, dtype=np.int64),
                np.zeros(n, dtype=np.int8),
            )
        if t < self._breaks[0]:
            s = self.sample(t)
            return _Piece(
                constant_block(s.positions, s.velocities, s.accelerations, s.effort),
                np.full(n, t, dtype=np.int64),
                np.zeros(n, dtype=np.int8),
            )
        i = bisect_right(self._breaks, t) - 1
        return _Piece(self._blocks[i], self._origins[i], self._kinds[i])

    # -- queries ------------------------------------------------------------------------------

    @property
    def start_ns(self) -> int:
        """First breakpoint."""
        return self._breaks[0]

    @property
    def end_ns(self) -> int:
        """Last breakpoint: from here on the last point is held."""
        return self._breaks[-1]

    @property
    def breakpoints_ns(self) -> tuple[int, ...]:
        """All breakpoints (segment boundaries), ascending."""
        return tuple(self._breaks)

    def sample(self, t_ns: int) -> TrajectorySample:
        """Desired state at ``t_ns``; pure: the same time always gives the same answer.

        See the class docstring for the behaviour before the start, inside and past the end.
        """
        breaks = self._breaks
        if t_ns >= breaks[-1] or not self._blocks.shape[0]:
            f = self._final
            return TrajectorySample(f[0], f[1], f[2], f[3])
        i = bisect_right(breaks, t_ns) - 1
        if i < 0:
            i, t_ns = 0, breaks[0]
        tau = (t_ns - self._origins[i]) * 1e-9
        out = evaluate(self._blocks[i], tau)
        return TrajectorySample(out[0], out[1], out[2], out[3])

    def kinds_at(self, t_ns: int) -> NDArray[np.int8]:
        """Per joint, the ``SegmentKind`` in effect at ``t_ns`` (HOLD past the end)."""
        if not self._blocks.shape[0] or t_ns >= self._breaks[-1]:
            return np.zeros(self.n_joints, dtype=np.int8)
        i = max(bisect_right(self._breaks, t_ns) - 1, 0)
        kinds: NDArray[np.int8] = self._kinds[i].copy()
        return kinds
