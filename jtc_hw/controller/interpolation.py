"""Polynomial segments between two knots, vectorised across joints (pure math, no state).

Every segment is stored as the coefficients of a quintic in ``tau`` (seconds since the segment's
time origin); linear and cubic segments are quintics whose higher coefficients are zero. This
keeps sampling one code path whatever the interpolation, and makes the knot values exact: at
``tau = 0`` the position is the stored coefficient itself.

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


_EXPONENTS = np.arange(6, dtype=np.float64)[:, None]


def evaluate(block: F64, tau: F64) -> F64:
    """Evaluate a ``(4, 6, n)`` block at per-joint ``tau`` (seconds); returns ``(4, n)``."""
    powers = tau[None, :] ** _EXPONENTS
    result: F64 = (block * powers).sum(axis=1)
    return result
