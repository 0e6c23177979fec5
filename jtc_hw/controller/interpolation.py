"""Polynomial segments between two knots, vectorised across joints (pure math, no state).

Every segment is stored as the coefficients of a quintic in ``tau`` (seconds since the segment's
time origin); linear and cubic segments are quintics whose higher coefficients are zero. This
keeps sampling one code path whatever the interpolation, and makes the knot values exact: at
``tau = 0`` the position is the stored coefficient itself.

Every function works on ``m`` segments at once (a leading axis), so that fitting a goal is a
few array operations whatever its number of points.

Coefficient layout used throughout the package: ``(4, 6, n_joints)`` per segment, rows
``position, velocity, acceleration, effort``; column ``k`` multiplies ``tau**k``. The velocity and
acceleration rows are the derivatives of the position row, precomputed so that one multiply-add
evaluates all four quantities.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I8 = NDArray[np.int8]


class SegmentKind(IntEnum):
    """How a segment was interpolated (the value is the polynomial degree, 0 = held value)."""

    HOLD = 0
    LINEAR = 1
    CUBIC = 3
    QUINTIC = 5


def kinds_for(has_velocity: NDArray[np.bool_], has_acceleration: NDArray[np.bool_]) -> I8:
    """Per segment, the spline chosen by the fields *both* ends carry, as the reference
    prescribes (arguments: per segment, whether both ends carry that field).

    Position only gives linear, position and velocity cubic, all three quintic. Acceleration
    without velocity cannot happen after integration (acceleration-only points get a velocity
    by Heun's method), so it falls back to linear.
    """
    kinds: I8 = np.where(
        has_velocity,
        np.where(has_acceleration, SegmentKind.QUINTIC, SegmentKind.CUBIC),
        SegmentKind.LINEAR,
    ).astype(np.int8)
    return kinds


def _power(durations_s: F64, exponent: int) -> F64:
    """``durations_s ** exponent`` element by element with Python's float power (the C
    library's ``pow``): numpy's vectorised power may differ in the last bit depending on the
    CPU's instruction set, and a fitted trajectory must not depend on the machine."""
    return np.array([d**exponent for d in durations_s.tolist()], dtype=np.float64)


_DISTINCT_MIN = 256
"""From this many segments, :func:`_powers` looks for repeated durations first."""


def _powers(durations_s: F64, exponents: tuple[int, ...]) -> list[F64]:
    """:func:`_power` of ``durations_s`` for each of ``exponents``, each distinct duration
    raised once: a goal sampled at a fixed rate has a handful of distinct durations, and one
    Python ``pow`` per segment and exponent was a fifth of fitting 20,000 points. The same
    ``pow`` of the same value: the same bits."""
    if durations_s.shape[0] >= _DISTINCT_MIN:
        distinct, where = np.unique(durations_s, return_inverse=True)
        if 4 * distinct.shape[0] <= durations_s.shape[0]:
            return [_power(distinct, e)[where] for e in exponents]
    return [_power(durations_s, e) for e in exponents]


def _rows(mask: NDArray[np.bool_]) -> slice | NDArray[np.intp] | None:
    """The rows where ``mask`` holds: a slice when it is all of them (a view, no copy)."""
    if mask.all():
        return slice(None)
    rows = np.flatnonzero(mask)
    return rows if rows.size else None


_ORDERS = np.arange(1, 6, dtype=np.float64)[:, None]


def segment_blocks(
    kinds: I8,
    durations_s: F64,
    start: tuple[F64, F64, F64, F64],
    end: tuple[F64, F64, F64, F64],
    out: F64 | None = None,
) -> F64:
    """Blocks ``(m, 4, 6, n)`` of ``m`` segments, each joining two knots.

    Row 0 of a block is the position polynomial of the segment's kind (``c`` with
    ``p(tau) = sum(c[k] * tau**k)``), rows 1 and 2 its derivatives, row 3 the effort, linear
    from one knot to the next.

    Args:
        kinds: ``(m,)`` linear, cubic or quintic per segment.
        durations_s: ``(m,)`` segment lengths in seconds; zero gives a constant position and
            effort (such a segment is never sampled, see ``Trajectory``).
        start: ``(m, n)`` position, velocity, acceleration and effort at the start knots (the
            derivatives are ignored beyond what the kind uses).
        end: the same at the end knots.
        out: where to write the blocks, all zeros (default: a new array).
    """
    p0, v0, a0, e0 = start
    p1, v1, a1, e1 = end
    m, n = p0.shape
    blocks = np.zeros((m, 4, 6, n)) if out is None else out
    c = blocks[:, 0]  # the position coefficients, written in place
    c[:, 0] = p0
    moving = durations_s > 0.0
    rows = _rows(moving & (kinds == SegmentKind.LINEAR))
    if rows is not None:
        T = durations_s[rows, None]
        c[rows, 1] = (p1[rows] - p0[rows]) / T
    rows = _rows(moving & (kinds == SegmentKind.CUBIC))
    if rows is not None:
        d = durations_s[rows]
        T = d[:, None]
        T2, T3 = (x[:, None] for x in _powers(d, (2, 3)))
        h, v0r, v1r = p1[rows] - p0[rows], v0[rows], v1[rows]
        c[rows, 1] = v0r
        c[rows, 2] = (3.0 * h - (2.0 * v0r + v1r) * T) / T2
        c[rows, 3] = (-2.0 * h + (v0r + v1r) * T) / T3
    rows = _rows(moving & (kinds == SegmentKind.QUINTIC))
    if rows is not None:
        d = durations_s[rows]
        T = d[:, None]
        T2, T3, T4, T5 = (x[:, None] for x in _powers(d, (2, 3, 4, 5)))
        h, v0r, v1r, a0r, a1r = p1[rows] - p0[rows], v0[rows], v1[rows], a0[rows], a1[rows]
        c[rows, 1] = v0r
        c[rows, 2] = 0.5 * a0r
        c[rows, 3] = (20.0 * h - (8.0 * v1r + 12.0 * v0r) * T - (3.0 * a0r - a1r) * T2) / (
            2.0 * T3
        )
        c[rows, 4] = (
            -30.0 * h + (14.0 * v1r + 16.0 * v0r) * T + (3.0 * a0r - 2.0 * a1r) * T2
        ) / (2.0 * T4)
        c[rows, 5] = (12.0 * h - 6.0 * (v1r + v0r) * T + (a1r - a0r) * T2) / (2.0 * T5)
    blocks[:, 1, :5] = c[:, 1:] * _ORDERS
    blocks[:, 2, :4] = blocks[:, 1, 1:5] * _ORDERS[:4]
    blocks[:, 3, 0] = e0
    rows = _rows(moving)
    if rows is not None:
        blocks[rows, 3, 1] = (e1[rows] - e0[rows]) / durations_s[rows, None]
    return blocks


def constant_blocks(
    position: F64, velocity: F64, acceleration: F64, effort: F64, out: F64 | None = None
) -> F64:
    """Blocks ``(m, 4, 6, n)`` that return the given ``(m, n)`` values unchanged at any ``tau``
    (holds, method ``none``); ``out``: where to write them, all zeros (default: a new array)."""
    m, n = position.shape
    blocks = np.zeros((m, 4, 6, n)) if out is None else out
    blocks[:, 0, 0] = position
    blocks[:, 1, 0] = velocity
    blocks[:, 2, 0] = acceleration
    blocks[:, 3, 0] = effort
    return blocks


def evaluate(block: F64, tau: F64) -> F64:
    """Evaluate a ``(4, 6, n)`` block at per-joint ``tau`` (seconds); returns ``(4, n)``.

    The powers of ``tau`` are products (``t2 = tau * tau``, ``t3 = t2 * tau``, ``t4 = t2 * t2``,
    ``t5 = t4 * tau``), as :func:`evaluate_at` computes them from one float: where the two
    meet (joints sharing a time origin, sampled either way), they give the same bits."""
    powers = np.empty((6, tau.shape[0]))
    powers[0] = 1.0
    powers[1] = tau
    np.multiply(tau, tau, out=powers[2])
    np.multiply(powers[2], tau, out=powers[3])
    np.multiply(powers[2], powers[2], out=powers[4])
    np.multiply(powers[4], tau, out=powers[5])
    result: F64 = (block * powers).sum(axis=1)
    return result


def evaluate_at(block: F64, tau: float) -> F64:
    """:func:`evaluate` where every joint has the same ``tau`` (seconds), the loop's sample of
    every cycle: six float products instead of six array operations, the same values."""
    t2 = tau * tau
    t4 = t2 * t2
    powers = np.array((1.0, tau, t2, t2 * tau, t4, t4 * tau))[:, None]
    result: F64 = (block * powers).sum(axis=1)
    return result
