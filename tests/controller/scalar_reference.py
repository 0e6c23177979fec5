"""The scalar implementation of validation and splicing as it was before vectorising (oracle).

``jtc_hw.controller.validation.prepare`` and ``Trajectory.splice`` were per-point Python
(commit 1b167ed); they are now numpy over all points at once. This module keeps the per-point
code, unchanged but for names, so that ``test_vectorised.py`` can check that the vectorised code
gives bit-identical trajectories and the same rejections (message and code) on random input.
Not used by the package; do not "fix" it: it is the definition of the behaviour being kept.
Deliberate changes of behaviour since are made here too, marked with their issue: issue 11
(upstream's sections 4.3 step 6 and 4.6) keeps the last point's velocity and acceleration past
the end, and method ``none`` shows the next point; the last-point velocity rule counts
|v| <= FLT_EPSILON as zero (upstream's rule; it was ``!= 0``).
"""

from __future__ import annotations

import math
import numbers
from bisect import bisect_left, bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from jtc_hw.controller.config import ControllerConfig
from jtc_hw.controller.messages import JointTrajectory
from jtc_hw.controller.trajectory import TrajectorySample
from jtc_hw.errors import GoalRejected

F64 = NDArray[np.float64]
NS_PER_S = 1_000_000_000
OLD_HEADER_TIMESTAMP = -3
INVALID_GOAL = -1
INVALID_JOINTS = -2
_FIELDS = ("positions", "velocities", "accelerations", "effort")


# -- interpolation.py ---------------------------------------------------------------------------

class SegmentKind(IntEnum):
    """How a segment was interpolated (the value is the polynomial degree, 0 = held value)."""

    HOLD = 0
    LINEAR = 1
    CUBIC = 3
    QUINTIC = 5


def kind_for(has_velocity: bool, has_acceleration: bool) -> SegmentKind:
    """Choose the spline by the fields *both* ends carry, as the reference prescribes.

    Position only gives linear, position and velocity cubic, all three quintic. Acceleration
    without velocity cannot happen after integration (acceleration-only points get a velocity
    by Heun's method), so it falls back to linear.
    """
    if not has_velocity:
        return SegmentKind.LINEAR
    return SegmentKind.QUINTIC if has_acceleration else SegmentKind.CUBIC


def position_coefficients(
    kind: SegmentKind,
    duration_s: float,
    p0: F64,
    v0: F64,
    a0: F64,
    p1: F64,
    v1: F64,
    a1: F64,
) -> F64:
    """Coefficients ``(6, n)`` of the position polynomial joining two knots.

    Args:
        kind: linear, cubic or quintic (HOLD gives a constant ``p0``).
        duration_s: segment length in seconds; zero gives a constant ``p0`` (the segment is
            never sampled, see ``Trajectory``).
        p0, v0, a0: state at the start knot (ignored beyond what ``kind`` uses).
        p1, v1, a1: state at the end knot.

    Returns:
        Array ``c`` with ``p(tau) = sum(c[k] * tau**k)``.
    """
    c = np.zeros((6, p0.shape[0]))
    c[0] = p0
    if kind == SegmentKind.HOLD or duration_s <= 0.0:
        return c
    T = duration_s
    h = p1 - p0
    if kind == SegmentKind.LINEAR:
        c[1] = h / T
    elif kind == SegmentKind.CUBIC:
        c[1] = v0
        c[2] = (3.0 * h - (2.0 * v0 + v1) * T) / T**2
        c[3] = (-2.0 * h + (v0 + v1) * T) / T**3
    else:
        c[1] = v0
        c[2] = 0.5 * a0
        c[3] = (20.0 * h - (8.0 * v1 + 12.0 * v0) * T - (3.0 * a0 - a1) * T**2) / (2.0 * T**3)
        c[4] = (-30.0 * h + (14.0 * v1 + 16.0 * v0) * T + (3.0 * a0 - 2.0 * a1) * T**2) / (
            2.0 * T**4
        )
        c[5] = (12.0 * h - 6.0 * (v1 + v0) * T + (a1 - a0) * T**2) / (2.0 * T**5)
    return c


def segment_block(position: F64, effort0: F64, effort_slope: F64) -> F64:
    """Stack a position polynomial with its derivatives and a linear effort into ``(4, 6, n)``."""
    n = position.shape[1]
    block = np.zeros((4, 6, n))
    block[0] = position
    k = np.arange(1, 6, dtype=np.float64)[:, None]
    block[1, :5] = position[1:] * k
    block[2, :4] = block[1, 1:5] * k[:4]
    block[3, 0] = effort0
    block[3, 1] = effort_slope
    return block


def constant_block(position: F64, velocity: F64, acceleration: F64, effort: F64) -> F64:
    """A block that returns the given values unchanged at any ``tau`` (hold / method ``none``)."""
    n = position.shape[0]
    block = np.zeros((4, 6, n))
    block[0, 0] = position
    block[1, 0] = velocity
    block[2, 0] = acceleration
    block[3, 0] = effort
    return block


def evaluate(block: F64, tau: F64) -> F64:
    """Evaluate a ``(4, 6, n)`` block at per-joint ``tau`` (seconds); returns ``(4, n)``.

    Issue 24: the powers of ``tau`` are products (``t2 = tau * tau``, ``t3 = t2 * tau``,
    ``t4 = t2 * t2``, ``t5 = t4 * tau``), no longer ``tau ** k``: the package samples the
    loop's reference from one float that way, and both give the same bits. The values move by
    an ulp or two at most, the polynomials do not change."""
    t2 = tau * tau
    t4 = t2 * t2
    powers = np.stack((np.ones_like(tau), tau, t2, t2 * tau, t4, t4 * tau))
    result: F64 = (block * powers).sum(axis=1)
    return result


# -- trajectory.py ------------------------------------------------------------------------------


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
        pos, vel, acc, eff = knots.pos, knots.vel, knots.acc, knots.eff

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
        final[0, cols] = pos[-1]
        final[1, cols] = vel[-1]  # issue 11: the last point's velocity and acceleration kept
        final[2, cols] = acc[-1]
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
            block = constant_block(pos[-1], vel[-1], acc[-1], eff[-1])  # issue 11
            return _Piece(block, np.full(k, t, dtype=np.int64), np.zeros(k, dtype=np.int8))
        t0, t1 = knot_times[row], knot_times[row + 1]
        origin = np.full(k, t0, dtype=np.int64)
        if method == "none":
            shown = 0 if row == 0 else row + 1  # issue 11: the next point (row 0: lead-in)
            block = constant_block(pos[shown], vel[shown], acc[shown], eff[shown])
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


# -- validation.py ------------------------------------------------------------------------------


def prepare(config: ControllerConfig, msg: Any) -> PreparedTrajectory:
    """Validate ``msg`` and return it in controller joint order.

    Args:
        config: the controller configuration (joints, partial goals, integration, interfaces).
        msg: a ``JointTrajectory`` with at least one point (an empty one is a stop request that
            the caller handles).

    Returns:
        The prepared trajectory.

    Raises:
        GoalRejected: with the precise reason and result code.
    """
    if not isinstance(msg, JointTrajectory):
        raise GoalRejected(f"expected a JointTrajectory, got {type(msg).__name__}")
    if not msg.points:
        raise GoalRejected("empty trajectory: it has no points")
    joint_index = _joint_columns(config, msg)
    k = len(msg.joint_names)
    if isinstance(msg.start_time_ns, bool) or msg.start_time_ns < 0:
        raise GoalRejected(
            f"start time {msg.start_time_ns} ns is negative; use 0 to start now or a time on "
            "the controller's clock"
        )
    m = len(msg.points)
    arrays = {name: np.full((m, k), np.nan) for name in _FIELDS}
    present: dict[str, list[bool]] = {name: [] for name in _FIELDS}
    times: list[int] = []
    for i, point in enumerate(msg.points):
        t = point.time_from_start_ns
        if t < 0:
            raise GoalRejected(
                f"point #{i}: time_from_start {t / 1e9:.9f} s is negative; it must be >= 0"
            )
        if times and t <= times[-1]:
            raise GoalRejected(
                f"point #{i}: time_from_start {t / 1e9:.9f} s is not after point #{i - 1} "
                f"({times[-1] / 1e9:.9f} s); times must be strictly increasing"
            )
        times.append(t)
        for name in _FIELDS:
            values = getattr(point, name)
            present[name].append(values is not None)
            if values is None:
                continue
            if len(values) != k:
                raise GoalRejected(
                    f"point #{i}: {name} has {len(values)} value(s) but joint_names has {k}; "
                    "give one value per joint or leave the field empty"
                )
            for j, value in enumerate(values):
                if isinstance(value, bool) or not isinstance(value, numbers.Real):
                    raise GoalRejected(
                        f"point #{i}: {name}[{j}] (joint '{msg.joint_names[j]}') is {value!r}, "
                        "not a number"
                    )
                if not math.isfinite(value):
                    raise GoalRejected(
                        f"point #{i}: {name}[{j}] (joint '{msg.joint_names[j]}') is "
                        f"{float(value)!r}; values must be finite"
                    )
            arrays[name][i] = values
        _check_point_fields(config, i, present, point_index=i)
    if any(present["effort"]) and not all(present["effort"]):
        missing = present["effort"].index(False)
        raise GoalRejected(
            f"point #{missing} has no effort while other points do; give effort at every "
            "point or at none"
        )
    if not config.allow_nonzero_velocity_at_trajectory_end and present["velocities"][-1]:
        last = arrays["velocities"][-1]
        for j, value in enumerate(last):
            if abs(value) > 2.0**-23:  # issue 11 point 4: upstream's FLT_EPSILON
                raise GoalRejected(
                    f"point #{m - 1} (the last): velocity of joint '{msg.joint_names[j]}' is "
                    f"{float(value)!r}, must be 0 (|velocity| <= 1.1920929e-07, FLT_EPSILON) "
                    "because allow_nonzero_velocity_at_trajectory_end is false"
                )
    return PreparedTrajectory(
        joint_indices=joint_index,
        start_time_ns=int(msg.start_time_ns),
        times_ns=tuple(times),
        positions=arrays["positions"],
        velocities=arrays["velocities"],
        accelerations=arrays["accelerations"],
        effort=arrays["effort"],
        has_positions=tuple(present["positions"]),
        has_velocities=tuple(present["velocities"]),
        has_accelerations=tuple(present["accelerations"]),
        has_effort=tuple(present["effort"]),
    )


def _joint_columns(config: ControllerConfig, msg: JointTrajectory) -> np.ndarray[Any, Any]:
    names = msg.joint_names
    if not names:
        raise GoalRejected(
            "joint_names is empty; name the joints the points refer to", INVALID_JOINTS
        )
    index = {name: i for i, name in enumerate(config.joints)}
    seen: set[str] = set()
    cols = []
    for name in names:
        if not isinstance(name, str):
            raise GoalRejected(f"joint name {name!r} is not a string", INVALID_JOINTS)
        if name not in index:
            raise GoalRejected(
                f"joint '{name}' is not a controller joint (controller joints: "
                f"{', '.join(config.joints)})",
                INVALID_JOINTS,
            )
        if name in seen:
            raise GoalRejected(f"joint '{name}' appears twice in joint_names", INVALID_JOINTS)
        seen.add(name)
        cols.append(index[name])
    if len(names) != len(config.joints) and not config.allow_partial_joints_goal:
        missing = [j for j in config.joints if j not in seen]
        raise GoalRejected(
            f"joints {', '.join(missing)} missing from the trajectory; every controller joint "
            "must be given unless allow_partial_joints_goal is true",
            INVALID_JOINTS,
        )
    return np.asarray(cols, dtype=np.intp)


def _check_point_fields(
    config: ControllerConfig, i: int, present: dict[str, list[bool]], point_index: int
) -> None:
    has_p = present["positions"][i]
    has_v = present["velocities"][i]
    has_a = present["accelerations"][i]
    has_e = present["effort"][i]
    if has_e and "effort" not in config.command_interfaces:
        raise GoalRejected(
            f"point #{point_index}: effort is only used with the 'effort' command interface "
            f"(configured: {', '.join(config.command_interfaces)}); remove the effort field"
        )
    if not (has_p or has_v or has_a):
        raise GoalRejected(
            f"point #{point_index}: no positions, velocities or accelerations; a point needs "
            "positions (or, with allow_integration_in_goal_trajectories, velocities or "
            "accelerations)"
        )
    if not has_p:
        if config.interpolation_method == "none":
            raise GoalRejected(
                f"point #{point_index}: no positions; interpolation_method 'none' does not "
                "integrate derivatives, so every point needs positions"
            )
        if not config.allow_integration_in_goal_trajectories:
            raise GoalRejected(
                f"point #{point_index}: no positions; velocity- or acceleration-only points are "
                "accepted only with allow_integration_in_goal_trajectories: true"
            )
    elif has_a and not has_v:
        raise GoalRejected(
            f"point #{point_index}: accelerations without velocities; a quintic spline needs "
            "positions, velocities and accelerations (give velocities, or drop accelerations "
            "for linear interpolation)"
        )
