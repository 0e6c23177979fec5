"""The immutable reference trajectory the controller samples.

Theory of operation
-------------------
A ``JointTrajectory`` (:mod:`.messages`) is what a client sends.

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
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..errors import GoalRejected
from .interpolation import (
    F64,
    SegmentKind,
    constant_blocks,
    evaluate,
    evaluate_at,
    kinds_for,
    segment_blocks,
)
from .messages import NS_PER_S, PreparedTrajectory

OLD_HEADER_TIMESTAMP = -3


class TrajectorySample(NamedTuple):
    """Desired state of every controller joint at one time (arrays in controller joint order)."""

    positions: F64
    velocities: F64
    accelerations: F64
    effort: F64


BEFORE_START = "before_start"
INSIDE = "inside"
AFTER_END = "after_end"


class QueriedState(NamedTuple):
    """Answer of ``query_state`` (upstream's ``QueryTrajectoryState``, section 16).

    Attributes:
        positions, velocities, accelerations, effort: the values the answer carries (arrays in
            controller joint order), as ``TrajectorySample``.
        success: True only when the time lies inside the trajectory.
        where: ``"inside"``, ``"before_start"`` (before the time the reference was installed:
            the values are the current measured state) or ``"after_end"`` (at or after the last
            point: the values are the last point's).
    """

    positions: F64
    velocities: F64
    accelerations: F64
    effort: F64
    success: bool
    where: str


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
    times: NDArray[np.int64]  # (m + 1,): the splice time, then the kept points' times
    pos: F64  # (m + 1, k): row 0 is the bridge start
    vel: F64
    acc: F64
    eff: F64
    has_v: NDArray[np.bool_]  # (m + 1,)
    has_a: NDArray[np.bool_]


class _Pieces(NamedTuple):
    blocks: F64  # (s, 4, 6, n)
    origins: NDArray[np.int64]  # (s, n)
    kinds: NDArray[np.int8]  # (s, n)


def _slice(pieces: _Pieces, start: int, stop: int) -> _Pieces:
    """Segments ``[start, stop)`` of ``pieces``, as views."""
    return _Pieces(pieces.blocks[start:stop], pieces.origins[start:stop], pieces.kinds[start:stop])


def _reorder(knots: _Knots, cols: NDArray[np.intp], n: int) -> _Knots:
    """``knots`` of a command naming every joint (``cols``, a permutation), in the controller's
    joint order."""
    if (cols == np.arange(n)).all():
        return knots
    values = []
    for given in (knots.pos, knots.vel, knots.acc, knots.eff):
        ordered = np.empty_like(given)
        ordered[:, cols] = given
        values.append(ordered)
    return knots._replace(pos=values[0], vel=values[1], acc=values[2], eff=values[3])


MAX_TIME_NS = 2**63 - 1
"""The controller's clock range: times are int64 nanoseconds."""


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """``[start, stop)`` of each run of consecutive True values of a 1-D mask."""
    edges = np.diff(np.concatenate(([False], mask, [False])).astype(np.int8))
    starts = np.flatnonzero(edges == 1).tolist()
    return list(zip(starts, np.flatnonzero(edges == -1).tolist(), strict=True))


def _integrate(values: F64, increments: F64, mask: NDArray[np.bool_]) -> None:
    """``values[r] = values[r - 1] + increments[r]`` in place for every row ``r`` where ``mask``
    is True, in row order (row 0 is never masked).

    Each run of masked rows is one ``np.add.accumulate`` from the row before it: the same
    additions, in the same order, as a loop over the rows, so the same result to the bit.
    """
    for start, stop in _runs(mask):
        stacked = np.concatenate((values[start - 1 : start], increments[start:stop]))
        values[start:stop] = np.add.accumulate(stacked, axis=0)[1:]


def _seconds(durations_ns: NDArray[np.int64]) -> F64:
    """Durations in seconds, each the correctly rounded quotient ``ns / 1e9`` (exact integers
    below 2**53 ns, ~104 days, convert exactly; longer ones go through Python's ints)."""
    if durations_ns.size and int(np.abs(durations_ns).max()) >= 2**53:
        return np.array([d / NS_PER_S for d in durations_ns.tolist()], dtype=np.float64)
    seconds: F64 = durations_ns / NS_PER_S
    return seconds


class Trajectory:
    """Immutable reference trajectory for all controller joints.

    ``sample(t)`` returns, for ``t`` in integer nanoseconds on the controller's clock:

    - before ``state_before_ns`` (upstream's time of the state before the trajectory, section
      4.3 step 3 of the upstream reference): nothing, it raises ``ValueError``; the reference
      is not defined before it was installed;
    - inside a segment ``[t_i, t_i+1)``: the segment's polynomial; at a knot time exactly, the
      segment that *starts* there, so a knot's own values come back unrounded;
      linear segments give position and a constant velocity (acceleration 0), cubic and quintic
      give position, velocity and acceleration, method ``none`` gives the next point's values
      (upstream's section 4.6); effort is linear between points (held for ``none``);
    - at or after the last breakpoint: the last point as given (upstream's section 4.3 step 6):
      its position and effort, and its velocity and acceleration *kept* (0 where the point had
      none), until the controller replaces the reference.

    A trajectory with no segments (``constant``) returns its state at every time from
    ``state_before_ns`` on. ``query(t, current)`` answers upstream's ``query_state``.

    Its state is a few numpy arrays (the breakpoints too), so that pickling it -- a plan sent
    to the loop process -- moves them as whole buffers, whatever the number of segments.
    """

    __slots__ = (
        "_breaks",
        "_blocks",
        "_origins",
        "_kinds",
        "_final",
        "_start",
        "_end",
        "_last",
        "_memo",
        "_past_end",
        "n_joints",
        "state_before_ns",
    )

    def __init__(
        self,
        breaks: Sequence[int] | NDArray[np.int64],
        blocks: F64,
        origins: NDArray[np.int64],
        kinds: NDArray[np.int8],
        final: F64,
        state_before_ns: int | None = None,
    ) -> None:
        breaks_array = np.array(breaks, dtype=np.int64)
        self._breaks = breaks_array
        self._blocks = blocks
        self._origins = origins
        self._kinds = kinds
        final = np.array(final, dtype=np.float64)
        self._final = final
        self._start = int(breaks_array[0])
        self._end = int(breaks_array[-1])
        # The earliest time the trajectory is defined (default: its first breakpoint).
        self.state_before_ns = self._start if state_before_ns is None else int(state_before_ns)
        # The segment the last sample fell in, (start, end, index, origin): the loop samples
        # increasing times, mostly in the same segment, and comparing two ints is cheaper than
        # a search; ``origin`` is the segment's time origin (ns) when every joint has the same
        # (``_shared_origin``), else None. Replaced whole (one assignment), so threads
        # sampling at once each read a consistent one; it changes no answer. At first: an
        # empty segment just before the first, so that the first sample inside finds it as
        # "the next one".
        self._last: tuple[int, int, int, int | None] = (self._start, self._start, -1, None)
        # The last sample taken, (time, sample): the loop samples each cycle at ``now`` and
        # one period ahead, and the next cycle's ``now`` is mostly this cycle's "ahead". Its
        # arrays are read-only, as every sample is (the state past the end is ``_final``'s
        # rows), so handing the same one out twice is the same answer. Replaced whole.
        self._memo: tuple[int, TrajectorySample] | None = None
        # The sample at and past the end (``_final``'s rows), made at its first use: the same
        # every time, as a trajectory is immutable (an idle controller samples it twice a
        # cycle).
        self._past_end: TrajectorySample | None = None
        self.n_joints = final.shape[1]
        for array in (breaks_array, blocks, origins, kinds, final):
            array.setflags(write=False)

    def __getstate__(self) -> tuple[None, dict[str, Any]]:
        """Pickled without its memo and past-the-end sample (samples, not part of the
        trajectory: views that would be pickled as copies)."""
        state = {name: getattr(self, name) for name in self.__slots__}
        state["_memo"] = None
        state["_past_end"] = None
        return None, state

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
        """The new reference: this trajectory combined with a new command (the reference's
        trajectory replacement); ``self`` is unchanged.

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

        Raises:
            GoalRejected: every point of ``new`` lies before ``now_ns`` (``OLD_HEADER_TIMESTAMP``),
                or the last one lies beyond the clock's range (``MAX_TIME_NS``).
        """
        start = new.start_time_ns if new.start_time_ns != 0 else now_ns
        last = int(new.times_ns[-1])
        if start + last > MAX_TIME_NS:
            raise GoalRejected(
                f"the last point is due at start time {start} ns + time_from_start "
                f"{last / NS_PER_S:.6f} s, beyond the controller clock's range "
                f"({MAX_TIME_NS} ns); send an earlier start time or shorter times"
            )
        abs_times = new.times_ns + start
        keep = int(abs_times.searchsorted(now_ns, side="left"))
        if keep == abs_times.shape[0]:
            late = (now_ns - (start + last)) / NS_PER_S
            raise GoalRejected(
                f"all {abs_times.shape[0]} point(s) lie in the past: the last one was due "
                f"{late:.6f} s before now (start time {start} ns + time_from_start "
                f"{last / NS_PER_S:.6f} s); send a later start time or 0 for 'now'",
                OLD_HEADER_TIMESTAMP,
            )
        splice_at = max(start, now_ns)
        cols = new.joint_indices
        knot_times = np.concatenate((np.array([splice_at], dtype=np.int64), abs_times[keep:]))
        knots = self._new_knots(new, keep, self._sample(splice_at), cols, knot_times, wraparound)
        keep_from = now_ns if keep_from_ns is None else min(keep_from_ns, now_ns)
        return self._combine(keep_from, splice_at, cols, knots, interpolation_method)

    @staticmethod
    def _new_knots(
        new: PreparedTrajectory,
        keep: int,
        s0: TrajectorySample,
        cols: NDArray[np.intp],
        knot_times: NDArray[np.int64],
        wraparound: NDArray[np.bool_] | None,
    ) -> _Knots:
        """Knot values for the new joints: row 0 is the bridge start, then the kept points.

        Fills positions (and velocities) of derivative-only points by Heun's method, starting
        from the bridge state, and applies the wraparound offset.
        """
        m = knot_times.shape[0] - 1
        k = cols.shape[0]
        pos = np.empty((m + 1, k))
        vel = np.zeros((m + 1, k))
        acc = np.zeros((m + 1, k))
        eff = np.zeros((m + 1, k))
        pos[0] = s0.positions[cols]
        vel[0] = s0.velocities[cols]
        acc[0] = s0.accelerations[cols]
        eff[0] = s0.effort[cols]
        hp = np.concatenate(([True], new.has_positions[keep:]))
        hv = np.concatenate(([True], new.has_velocities[keep:]))
        ha = np.concatenate(([True], new.has_accelerations[keep:]))
        he = np.concatenate(([True], new.has_effort[keep:]))
        given = new.positions[keep:].copy()
        if wraparound is not None and new.has_positions[keep]:
            wrap = wraparound[cols]
            if wrap.any():
                given += np.where(wrap, _wrap_offset(pos[0], given[0]), 0.0)
        rows = np.flatnonzero(ha[1:]) + 1
        acc[rows] = new.accelerations[keep:][rows - 1]
        rows = np.flatnonzero(hv[1:]) + 1
        vel[rows] = new.velocities[keep:][rows - 1]
        rows = np.flatnonzero(he[1:]) + 1
        eff[rows] = new.effort[keep:][rows - 1]
        rows = np.flatnonzero(hp[1:]) + 1
        pos[rows] = given[rows - 1]
        if not hp.all():
            # Heun's method: trapezoidal integration of acceleration, then of velocity.
            # Row r integrates over [knot r-1, knot r]; row 0 (the bridge start) never does.
            dt = _seconds(np.diff(knot_times))[:, None]
            vel_rows = ~hp & ~hv
            if vel_rows.any():
                increments = np.zeros_like(acc)
                increments[1:] = (acc[:-1] + acc[1:]) * 0.5 * dt
                _integrate(vel, increments, vel_rows)
            increments = np.zeros_like(vel)
            increments[1:] = (vel[:-1] + vel[1:]) * 0.5 * dt
            _integrate(pos, increments, ~hp)
            hv = hv | ~hp
        return _Knots(knot_times, pos, vel, acc, eff, hv, ha)

    def _combine(
        self,
        now_ns: int,
        splice_at: int,
        cols: NDArray[np.intp],
        knots: _Knots,
        method: str,
    ) -> Trajectory:
        n = self.n_joints
        partial = cols.shape[0] != n
        knot_times = knots.times

        # Breakpoints: the current trajectory from the segment holding `now` up to the splice,
        # the new knots, and (partial goals) the current trajectory's later breakpoints.
        old = self._breaks
        first_old = max(int(old.searchsorted(now_ns, side="right")) - 1, 0)
        parts = [old[first_old:][old[first_old:] < splice_at], knot_times]
        if partial:
            parts.append(old[old > splice_at])
        breaks = np.unique(np.concatenate(parts))

        segments = breaks.shape[0] - 1
        starts = breaks[:-1]
        # Segments wholly before the splice keep this trajectory's polynomials; they come
        # first. The rest carry the new command (and, partial goals, the other joints' old).
        first_new = int(np.count_nonzero(breaks[1:] <= splice_at))
        out = _Pieces(
            np.zeros((segments, 4, 6, n)),
            np.zeros((segments, n), dtype=np.int64),
            np.zeros((segments, n), dtype=np.int8),
        )
        if first_new:
            self._pieces_at(starts[:first_new], _slice(out, 0, first_new))
        if first_new < segments:
            t = starts[first_new:]
            tail = _slice(out, first_new, segments)
            if partial:
                self._pieces_at(t, tail)
                new_pieces = self._new_pieces(t, knots, method)
                tail.blocks[..., cols] = new_pieces.blocks
                tail.origins[:, cols] = new_pieces.origins
                tail.kinds[:, cols] = new_pieces.kinds
            else:  # every joint: fit in the controller's joint order, straight into place
                self._new_pieces(t, _reorder(knots, cols, n), method, tail)

        # Past the end every joint is its last point as given, velocity and acceleration kept
        # (upstream section 4.3 step 6: a streaming client's last point keeps the joint moving
        # until the next one; cmd_timeout is the guard). Joints a partial command does not name
        # keep the current trajectory's last point.
        final = self._final.copy() if partial else np.zeros((4, n))
        final[0, cols] = knots.pos[-1]
        final[1, cols] = knots.vel[-1]
        final[2, cols] = knots.acc[-1]
        final[3, cols] = knots.eff[-1]
        # Not defined before the time this trajectory is kept from (nor before the one it
        # replaces was): sampling there fails, as upstream's before its state-before time.
        state_before = max(now_ns, self.state_before_ns)
        return Trajectory(breaks, out.blocks, out.origins, out.kinds, final, state_before)

    @staticmethod
    def _new_pieces(
        t: NDArray[np.int64], knots: _Knots, method: str, out: _Pieces | None = None
    ) -> _Pieces:
        """The new joints' polynomials on the grid segments starting at the times ``t``
        (ascending), written to ``out`` (all zeros) or to new arrays."""
        times, pos, vel, acc, eff = knots.times, knots.pos, knots.vel, knots.acc, knots.eff
        m = times.shape[0] - 1
        k = pos.shape[1]
        if out is None:
            out = _Pieces(
                np.zeros((t.shape[0], 4, 6, k)),
                np.zeros((t.shape[0], k), dtype=np.int64),
                np.zeros((t.shape[0], k), dtype=np.int8),
            )
        blocks, origins, kinds = out
        # Index of the knot row that starts the segment containing each t. A zero-length bridge
        # (first point due at the splice time) has two rows at the same time: take the later.
        row = times.searchsorted(t, side="right") - 1
        inside = int(np.count_nonzero(row < m))  # the segments before the last knot come first
        origins[inside:] = t[inside:, None]
        if inside < t.shape[0]:  # past the last knot: its values as given, velocity kept
            blocks[inside:, 0, 0] = pos[-1]
            blocks[inside:, 1, 0] = vel[-1]
            blocks[inside:, 2, 0] = acc[-1]
            blocks[inside:, 3, 0] = eff[-1]
        if not inside:
            return out
        r = row[:inside]
        origins[:inside] = times[r][:, None]
        if method == "none":
            # Upstream section 4.6: the state before during the lead-in (row 0), then during
            # the segment from point i (row i + 1) the raw *next* point i + 1 (row i + 2).
            shown = np.where(r == 0, 0, r + 1)
            constant_blocks(pos[shown], vel[shown], acc[shown], eff[shown], out=blocks[:inside])
            kinds[:inside] = SegmentKind.HOLD
            return out
        # Fit each knot segment in use once (a partial goal's grid can split one in several).
        split = bool((r[1:] == r[:-1]).any())
        used, where = np.unique(r, return_inverse=True) if split else (r, r)
        nxt = used + 1
        segment_kinds = kinds_for(
            knots.has_v[used] & knots.has_v[nxt], knots.has_a[used] & knots.has_a[nxt]
        )
        fitted = segment_blocks(
            segment_kinds,
            _seconds(times[nxt] - times[used]),
            (pos[used], vel[used], acc[used], eff[used]),
            (pos[nxt], vel[nxt], acc[nxt], eff[nxt]),
            out=None if split else blocks[:inside],
        )
        if split:
            blocks[:inside] = fitted[where]
            kinds[:inside] = segment_kinds[where, None]
        else:
            kinds[:inside] = segment_kinds[:, None]
        return out

    def _pieces_at(self, t: NDArray[np.int64], out: _Pieces) -> None:
        """This trajectory's polynomials in effect at the times ``t`` (constants after the end
        and before the start), written to ``out`` (all zeros)."""
        blocks, origins, kinds = out
        origins[:] = t[:, None]
        f = self._final
        if not self._blocks.shape[0]:
            blocks[:, :, 0] = f
            return
        after = t >= self._end
        blocks[after, :, 0] = f
        early = t < self._start
        if early.any():
            blocks[early, :, 0] = np.stack(self._sample(self._start))
        inside = np.flatnonzero(~after & ~early)
        if inside.size:
            i = self._breaks.searchsorted(t[inside], side="right") - 1
            blocks[inside] = self._blocks[i]
            origins[inside] = self._origins[i]
            kinds[inside] = self._kinds[i]

    # -- queries ------------------------------------------------------------------------------

    @property
    def start_ns(self) -> int:
        """First breakpoint."""
        return self._start

    @property
    def end_ns(self) -> int:
        """Last breakpoint: from here on the last point is held."""
        return self._end

    @property
    def nbytes(self) -> int:
        """Bytes of its arrays: what a copy of it (e.g. a plan sent to the loop) moves."""
        arrays = (self._breaks, self._blocks, self._origins, self._kinds, self._final)
        return sum(a.nbytes for a in arrays)

    @staticmethod
    def nbytes_for(segments: int, n_joints: int) -> int:
        """``nbytes`` of a trajectory of ``segments`` segments for ``n_joints`` joints (a
        command of ``m`` points gives about ``m + 1``, more when spliced into a partial one)."""
        per_segment = 8 + n_joints * (4 * 6 * 8 + 8 + 1)  # breakpoint; block, origin, kind
        return 8 + segments * per_segment + 4 * n_joints * 8  # last breakpoint, final state

    @property
    def breakpoints_ns(self) -> tuple[int, ...]:
        """All breakpoints (segment boundaries), ascending."""
        return tuple(self._breaks.tolist())

    def sample(self, t_ns: int) -> TrajectorySample:
        """Desired state at ``t_ns``; pure: the same time always gives the same answer.

        See the class docstring for the behaviour inside and past the end.

        Raises:
            ValueError: ``t_ns`` is before ``state_before_ns`` (upstream's sampling fails
                there, section 4.3 step 3).
        """
        if t_ns < self.state_before_ns:
            raise ValueError(
                f"cannot sample the trajectory at {t_ns} ns: it is defined from "
                f"{self.state_before_ns} ns (the time it was installed) on"
            )
        return self._sample(t_ns)

    def query(self, t_ns: int, current: TrajectorySample) -> QueriedState:
        """Upstream's ``query_state`` (section 16) on this trajectory; pure. The answer
        (:class:`QueriedState`) carries ``current``, the measured state, before
        ``state_before_ns``, and the last point's values at or after the last point.
        """
        if t_ns < self.state_before_ns:
            return QueriedState(*current, success=False, where=BEFORE_START)
        s = self._sample(t_ns)
        if t_ns >= self._end:
            return QueriedState(*s, success=False, where=AFTER_END)
        return QueriedState(*s, success=True, where=INSIDE)

    def _sample(self, t_ns: int) -> TrajectorySample:
        """``sample`` without the check of ``state_before_ns`` (before the first breakpoint:
        the state at it), for building trajectories."""
        if t_ns >= self._end or not self._blocks.shape[0]:
            past = self._past_end
            if past is None:
                f = self._final
                past = self._past_end = TrajectorySample(f[0], f[1], f[2], f[3])
            return past
        memo = self._memo
        if memo is not None and memo[0] == t_ns:
            return memo[1]
        asked = t_ns
        lo, hi, i, origin = self._last
        if not lo <= t_ns < hi:
            breaks = self._breaks
            # Mostly the next segment (points a period or so apart); else a search.
            following = int(breaks[i + 2]) if hi <= t_ns and i + 2 < breaks.shape[0] else hi
            if hi <= t_ns < following:
                i += 1
                origin = self._shared_origin(i)
                self._last = (hi, following, i, origin)
            else:
                i = int(breaks.searchsorted(t_ns, side="right")) - 1
                if i < 0:
                    i, t_ns = 0, self._start
                    origin = self._shared_origin(0)
                else:
                    origin = self._shared_origin(i)
                    self._last = (int(breaks[i]), int(breaks[i + 1]), i, origin)
        if origin is not None:
            out = evaluate_at(self._blocks[i], (t_ns - origin) * 1e-9)
        else:
            out = evaluate(self._blocks[i], (t_ns - self._origins[i]) * 1e-9)
        out.setflags(write=False)
        sample = TrajectorySample(out[0], out[1], out[2], out[3])
        self._memo = (asked, sample)
        return sample

    def _shared_origin(self, i: int) -> int | None:
        """Segment ``i``'s time origin (ns) if every joint has the same (a segment is built
        for all joints at once, except where a partial goal spliced some), else None."""
        row = self._origins[i].tolist()
        first: int = row[0]
        return first if row.count(first) == len(row) else None

    def pieces(
        self,
    ) -> tuple[NDArray[np.int64], F64, NDArray[np.int64], NDArray[np.int8], F64]:
        """Its arrays, read-only, for checks that read whole polynomials (``limits_check``):
        breakpoints ``(s + 1,)``, blocks ``(s, 4, 6, n)``, origins and kinds ``(s, n)``, and
        the state past the end ``(4, n)``."""
        return self._breaks, self._blocks, self._origins, self._kinds, self._final
