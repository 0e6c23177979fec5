"""Goals against joint limits: the exact extremes of the splines, and the uniform slow-down.

Theory of operation
-------------------
A spliced reference (``Trajectory``) is one polynomial of degree <= 5 per joint and grid
segment, so its extremes are exact and cheap to find: a quantity's extreme on a segment lies
at an end of the segment or at a root of its derivative. With ``P`` the position polynomial:

- jerk ``P'''`` (degree 2): extremes at the ends and the root of ``P''''`` (linear);
- acceleration ``P''`` (degree 3): the ends and the roots of ``P'''`` (quadratic formula);
- velocity ``P'`` (degree 4): the ends and the roots of ``P''``: a cubic, whose roots are
  bracketed by the roots of ``P'''`` (between two consecutive roots of its derivative a
  polynomial is monotonic, so it has at most one root there, found by bisection);
- position ``P``: the ends and the roots of ``P'`` (a quartic), bracketed by those of ``P''``.

Linear and cubic segments have zero high coefficients and use the closed forms only; every
step runs on all segments and joints at once (numpy). A bisected root is a few ulps of the
segment away from the true one, and a quantity is flat at its extremum, so the value found
is the extreme to rounding. Held segments (method ``none``, the state past a joint's last
point) are constants: their stored velocity and acceleration are checked as they are.

What is checked (the reference from the splice time, lead-in included, and the state kept
past the end, for the joints the command names; a position starting outside its range may go
no further out) and how ``time_scaling: fit`` slows a goal down (:func:`fit_factor`,
:func:`scale_prepared`, rounds in ``Planner``) are in docs/behaviour.md, "Joint limits".
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..config.limits import JointLimits
from ..errors import GoalRejected
from .interpolation import F64, SegmentKind
from .messages import NS_PER_S, PreparedTrajectory
from .trajectory import Trajectory
from .validation import INVALID_GOAL

__all__ = [
    "FIT",
    "REJECT",
    "TIME_SCALING_MODES",
    "Excess",
    "LimitTable",
    "TimeScaling",
    "check",
    "describe_excess",
    "fit_factor",
    "scale_prepared",
    "scaling_fields",
]

REJECT = "reject"
FIT = "fit"
TIME_SCALING_MODES = (REJECT, FIT)
"""``time_scaling`` values: reject a goal beyond the limits, or slow it down to fit them."""

TOLERANCE = 1e-9
"""Relative slack on a limit: a value computed as the limit plus rounding is within it."""

_BISECTIONS = 24
"""Bisection steps for a bracketed root: the bracket shrinks by 2**-24 (6e-8 of a segment);
the quantity is flat at its extremum, so the value's error is far below that."""

_FIELDS = ("position", "velocity", "acceleration", "jerk")
_EXPONENT = {"velocity": 1.0, "acceleration": 2.0, "jerk": 3.0}


class TimeScaling(NamedTuple):
    """How a goal was fitted to the limits (``time_scaling: fit``).

    Attributes:
        factor: the uniform slow-down ``s >= 1`` (1.0: it fitted as sent).
        duration_s: the last point's ``time_from_start`` after slowing, seconds.
    """

    factor: float
    duration_s: float


def scaling_fields(scaling: TimeScaling | None) -> dict[str, float]:
    """``time_scale`` and ``duration_s`` of a reply when ``fit`` was in effect, else none."""
    if scaling is None:
        return {}
    return {"time_scale": scaling.factor, "duration_s": scaling.duration_s}


class Excess(NamedTuple):
    """The worst excess of one quantity over its limit.

    Attributes:
        field: ``position``, ``velocity``, ``acceleration`` or ``jerk``.
        joint: the joint's index in the controller's joints.
        time_ns: when (controller clock; the end time for the state kept past the end).
        value: the value there (signed).
        limit: the bound it exceeds (for position the end of the range it leaves).
        ratio: ``|value| / limit`` (infinite for position: no slow-down fixes it).
    """

    field: str
    joint: int
    time_ns: int
    value: float
    limit: float
    ratio: float


@dataclass(frozen=True)
class LimitTable:
    """The configured limits as arrays in the controller's joint order (``inf``: unlimited).

    Attributes:
        names: the controller's joints.
        low, high: the position range.
        velocity, acceleration, jerk: the maximum magnitudes.
    """

    names: tuple[str, ...]
    low: F64
    high: F64
    velocity: F64
    acceleration: F64
    jerk: F64

    @classmethod
    def of(cls, joints: Sequence[str], limits: Mapping[str, JointLimits]) -> LimitTable | None:
        """The table for ``joints``; None when no joint has a position, velocity,
        acceleration or jerk limit (nothing to check)."""
        n = len(joints)
        low, high = np.full(n, -np.inf), np.full(n, np.inf)
        bounds = {name: np.full(n, np.inf) for name in _FIELDS[1:]}
        for i, joint in enumerate(joints):
            lim = limits.get(joint)
            if lim is None:
                continue
            if lim.position is not None:
                low[i], high[i] = lim.position
            for name, values in bounds.items():
                bound = getattr(lim, name)
                if bound is not None:
                    values[i] = bound
        if np.isinf(low).all() and np.isinf(high).all() and all(
            np.isinf(v).all() for v in bounds.values()
        ):
            return None
        return cls(tuple(joints), low, high, **bounds)

    def columns(self, joints: NDArray[np.intp]) -> NDArray[np.intp]:
        """Those of ``joints`` that have any limit."""
        limited = (
            np.isfinite(self.low) | np.isfinite(self.high) | np.isfinite(self.velocity)
            | np.isfinite(self.acceleration) | np.isfinite(self.jerk)
        )
        cols: NDArray[np.intp] = joints[limited[joints]]
        return cols


# -- Polynomials, vectorised ----------------------------------------------------------------------
# A polynomial is a list of coefficient arrays (one value per row), lowest degree first; its length
# is the highest degree any row uses, plus one.

Poly = list[F64]


def _derivative(poly: Poly) -> Poly:
    return [poly[k] * float(k) for k in range(1, len(poly))]


def _evaluate(poly: Poly, t: F64) -> F64:
    """Horner's scheme, row by row (``t``: one time per row)."""
    if not poly:
        return np.zeros_like(t)
    out = poly[-1] * np.ones_like(t) if len(poly) == 1 else poly[-1] * t
    if len(poly) == 1:
        return out
    for k in range(len(poly) - 2, 0, -1):
        out += poly[k]
        out *= t
    out += poly[0]
    return out


def _quadratic_roots(poly: Poly) -> list[F64]:
    """Real roots (two arrays, NaN where there is none) of a polynomial of degree <= 2 per
    row; a linear row gives its root, a constant row none. A negative discriminant gives the
    vertex instead: an extra sample, which can only find true values."""
    if len(poly) < 2:
        return []
    c0, c1 = poly[0], poly[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        if len(poly) == 2:
            return [np.where(c1 != 0.0, -c0 / c1, np.nan)]
        c2 = poly[2]
        disc = np.maximum(c1 * c1 - 4.0 * c2 * c0, 0.0)
        q = -0.5 * (c1 + np.copysign(np.sqrt(disc), c1))
        quad = c2 != 0.0
        r1 = np.where(quad, q / c2, np.where(c1 != 0.0, -c0 / c1, np.nan))
        r2 = np.where(quad & (q != 0.0), c0 / q, np.nan)
    return [r1, r2]


def _bracketed_roots(poly: Poly, low: F64, high: F64, split: list[F64]) -> list[F64]:
    """Real roots in ``[low, high]`` of each row's polynomial, given the roots of its
    derivative (``split``, NaN for none): between two of them it is monotonic, so it has at
    most one root there, found by bisection: ``len(split) + 1`` arrays of roots, NaN where a
    piece has none."""
    inner = [np.where(np.isnan(r), high, np.clip(r, low, high)) for r in split]
    points = np.sort(np.stack((low, *inner, high), axis=1), axis=1)
    values = np.stack([_evaluate(poly, points[:, i]) for i in range(points.shape[1])], axis=1)
    a, b = points[:, :-1], points[:, 1:]
    fa, fb = values[:, :-1], values[:, 1:]
    roots = np.full(a.shape, np.nan)
    change = (b > a) & (np.sign(fa) * np.sign(fb) <= 0.0)
    rows, pieces = np.nonzero(change)
    if rows.size:
        lo, hi = a[rows, pieces], b[rows, pieces]
        rising = fa[rows, pieces] < 0.0  # the root is where it crosses zero
        sub = [c[rows] for c in poly]
        for _ in range(_BISECTIONS):
            mid = 0.5 * (lo + hi)
            below = (_evaluate(sub, mid) < 0.0) == rising
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        roots[rows, pieces] = 0.5 * (lo + hi)
    return list(roots.T)


def _roots(poly: Poly, low: F64, high: F64, split: list[F64] | None) -> list[F64]:
    """Real roots of polynomials of degree <= 4: closed form for the rows whose coefficients
    of degree 3 and up are zero, bracketed by ``split`` (the derivative's roots) for the
    others."""
    if len(poly) <= 3 or split is None:
        return _quadratic_roots(poly)
    high_order = np.zeros(low.shape, dtype=bool)
    for c in poly[3:]:
        high_order |= c != 0.0
    out = [np.full(low.shape, np.nan) for _ in range(len(split) + 1)]
    closed = _quadratic_roots(poly[:3])
    if high_order.any():
        rows = np.flatnonzero(high_order)
        for i, r in enumerate(closed):
            out[i] = np.where(high_order, np.nan, r)
        bracketed = _bracketed_roots(
            [c[rows] for c in poly], low[rows], high[rows], [r[rows] for r in split]
        )
        for i, r in enumerate(bracketed):
            out[i][rows] = r
        return out
    return closed


# -- The check ------------------------------------------------------------------------------------


def check(
    reference: Trajectory,
    from_ns: int,
    table: LimitTable,
    joints: NDArray[np.intp],
    start_positions: F64,
) -> dict[str, Excess]:
    """The worst excess of each quantity over its limit, from ``from_ns`` on: by field, beyond
    :data:`TOLERANCE`; empty when within every limit.

    Args:
        reference: the spliced reference.
        from_ns: the splice time (the lead-in's start); earlier segments are not checked.
        table: the limits.
        joints: the controller joint indices to check (the command's).
        start_positions: every joint's reference position at ``from_ns``: the position range
            is widened to include it (see the module docstring).
    """
    cols = table.columns(joints)
    if not cols.size:
        return {}
    breaks, blocks, origins, kinds, final = reference.pieces()
    first = int(breaks.searchsorted(from_ns, side="left"))
    segments = max(breaks.shape[0] - 1 - first, 0)
    k = cols.shape[0]
    n = segments * k
    every = k == blocks.shape[3] and bool((cols == np.arange(k)).all())
    pick = slice(None) if every else cols  # all joints: views, no copies

    def rows(values: NDArray[Any]) -> NDArray[Any]:
        """(segments, joints) of the checked segments and columns, flattened."""
        flat: NDArray[Any] = np.ascontiguousarray(values[first:][:, pick]).reshape(n)
        return flat

    org = origins[first:][:, pick]
    t0 = ((breaks[first:-1][:, None] - org) / NS_PER_S).reshape(n)
    t1 = ((breaks[first + 1 :][:, None] - org) / NS_PER_S).reshape(n)
    origin_ns = org.reshape(n)
    hold = rows(kinds) == SegmentKind.HOLD
    any_hold = bool(hold.any())
    degree = 0  # the highest power any checked row uses
    position: Poly = []
    for power in range(6):
        c = rows(blocks[:, 0, power])
        if power and any_hold:
            c = np.where(hold, 0.0, c)  # held rows: the stored values, below
        position.append(c)
        if power and c.any():
            degree = power
    position = position[: degree + 1]
    velocity = _derivative(position)
    acceleration = _derivative(velocity)
    jerk = _derivative(acceleration)
    snap = _derivative(jerk)
    if any_hold:  # held rows are constants as stored (method none, past a joint's end)
        for poly, row in ((velocity, 1), (acceleration, 2)):
            stored = np.where(hold, rows(blocks[:, row, 0]), 0.0)
            if poly:
                poly[0] = np.where(hold, stored, poly[0])
            else:
                poly.append(stored)

    low = np.minimum(table.low[cols], start_positions[cols])
    high = np.maximum(table.high[cols], start_positions[cols])
    bound = {
        "velocity": table.velocity[cols],
        "acceleration": table.acceleration[cols],
        "jerk": table.jerk[cols],
    }
    wanted = {
        "position": bool(np.isfinite(low).any() or np.isfinite(high).any()),
        **{name: bool(np.isfinite(v).any()) for name, v in bound.items()},
    }
    # The roots of each derivative (by order: 1 is the velocity's), each found between those
    # of the next one.
    chain = {1: velocity, 2: acceleration, 3: jerk, 4: snap}
    roots: dict[int, list[F64]] = {}

    def roots_of(order: int) -> list[F64]:
        if order not in roots:
            poly = chain[order]
            split = roots_of(order + 1) if len(poly) > 3 else None
            roots[order] = _roots(poly, t0, t1, split)
        return roots[order]

    quantities = {
        "position": (position, 1),
        "velocity": (velocity, 2),
        "acceleration": (acceleration, 3),
        "jerk": (jerk, 4),
    }
    found: dict[str, Excess] = {}
    end_ns = int(breaks[-1])
    cols_k = np.arange(k)
    for name in _FIELDS:
        if not wanted[name]:
            continue
        values_min = np.full(k, np.inf)
        values_max = np.full(k, -np.inf)
        time_min = np.zeros(k, dtype=np.int64)
        time_max = np.zeros(k, dtype=np.int64)
        if n:
            poly, order = quantities[name]
            vmin = vmax = _evaluate(poly, t0)
            tmin = tmax = t0
            for candidate in [t1, *roots_of(order)]:
                inside = ~np.isnan(candidate)
                t = np.where(inside, np.clip(candidate, t0, t1), t0)
                value = _evaluate(poly, t)
                lower, higher = value < vmin, value > vmax
                vmin, tmin = np.where(lower, value, vmin), np.where(lower, t, tmin)
                vmax, tmax = np.where(higher, value, vmax), np.where(higher, t, tmax)
            vmin2, vmax2 = vmin.reshape(segments, k), vmax.reshape(segments, k)
            smin, smax = vmin2.argmin(axis=0), vmax2.argmax(axis=0)
            values_min = vmin2[smin, cols_k]
            values_max = vmax2[smax, cols_k]
            at_min = smin * k + cols_k
            at_max = smax * k + cols_k
            time_min = origin_ns[at_min] + np.round(tmin[at_min] * NS_PER_S).astype(np.int64)
            time_max = origin_ns[at_max] + np.round(tmax[at_max] * NS_PER_S).astype(np.int64)
        if name != "jerk":  # the state kept past the end (position and effort as given)
            kept = final[_FIELDS.index(name), cols]
            later_min, later_max = kept < values_min, kept > values_max
            values_min = np.where(later_min, kept, values_min)
            values_max = np.where(later_max, kept, values_max)
            time_min = np.where(later_min, end_ns, time_min)
            time_max = np.where(later_max, end_ns, time_max)
        excess = _worst(name, cols, values_min, time_min, values_max, time_max, low, high, bound)
        if excess is not None:
            found[name] = excess
    return found


def _worst(
    name: str,
    cols: NDArray[np.intp],
    values_min: F64,
    time_min: NDArray[np.int64],
    values_max: F64,
    time_max: NDArray[np.int64],
    low: F64,
    high: F64,
    bound: Mapping[str, F64],
) -> Excess | None:
    if name == "position":
        slack_low = TOLERANCE * np.maximum(1.0, np.abs(low))
        slack_high = TOLERANCE * np.maximum(1.0, np.abs(high))
        below = (low - values_min) - slack_low
        above = (values_max - high) - slack_high
        worst_below, worst_above = below.max(), above.max()
        if max(worst_below, worst_above) <= 0.0:
            return None
        if worst_above >= worst_below:
            i = int(above.argmax())
            return Excess(name, int(cols[i]), int(time_max[i]), float(values_max[i]),
                          float(high[i]), math.inf)
        i = int(below.argmax())
        return Excess(name, int(cols[i]), int(time_min[i]), float(values_min[i]),
                      float(low[i]), math.inf)
    limit = bound[name]
    magnitude = np.maximum(values_max, -values_min)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(np.isfinite(limit), magnitude / limit, 0.0)
    i = int(ratio.argmax())
    if not ratio[i] > 1.0 + TOLERANCE:
        return None
    positive = values_max[i] >= -values_min[i]
    return Excess(
        name,
        int(cols[i]),
        int(time_max[i] if positive else time_min[i]),
        float(values_max[i] if positive else values_min[i]),
        float(limit[i]),
        float(ratio[i]),
    )


def fit_factor(excesses: Mapping[str, Excess], *, lead_in: bool = False) -> float:
    """The smallest uniform slow-down that brings the scale-invariant parts within the
    velocity, acceleration and jerk limits (``max(r_v, sqrt(r_a), cbrt(r_j))``, at least 1).

    Args:
        excesses: what :func:`check` found.
        lead_in: the excess is in a lead-in from a moving reference, whose acceleration and
            jerk fall only like ``1/s`` and ``1/s**2``: ``max(r_v, r_a, sqrt(r_j))``.
    """
    factor = 1.0
    for name, excess in excesses.items():
        if name in _EXPONENT:
            exponent = _EXPONENT[name] - 1.0 if lead_in and name != "velocity" else _EXPONENT[name]
            factor = max(factor, excess.ratio ** (1.0 / exponent))
    return factor


def scale_prepared(prepared: PreparedTrajectory, factor: float) -> PreparedTrajectory:
    """``prepared`` slowed uniformly by ``factor``: times from its start multiplied (rounded to
    the nanosecond), velocities divided by it, accelerations by its square; the positions and
    efforts unchanged."""
    times = np.round(prepared.times_ns.astype(np.float64) * factor).astype(np.int64)
    return replace(
        prepared,
        times_ns=times,
        velocities=prepared.velocities / factor,
        accelerations=prepared.accelerations / (factor * factor),
    )


_UNITS = {"velocity": "per second", "acceleration": "per second squared",
          "jerk": "per second cubed"}


def describe_excess(
    excess: Excess, table: LimitTable, start_ns: int, first_point_ns: int, end_ns: int
) -> str:
    """The rejection's message: the joint, the time from the goal's start, the value against
    the limit (and where the limit comes from).

    Args:
        excess: what was found.
        table: the limits (for the joint's name).
        start_ns: the goal's start time.
        first_point_ns: when the first kept point is due (before it: the lead-in).
        end_ns: the trajectory's end (from there on: the state kept past the end).
    """
    joint = table.names[excess.joint]
    t = (excess.time_ns - start_ns) / NS_PER_S
    if excess.time_ns >= end_ns and excess.field != "position":
        where = f"past the last point (t = {t:.6g} s from the goal's start, the velocity and " \
            "acceleration the last point gives are kept)"
    elif excess.time_ns < first_point_ns:
        where = f"at t = {t:.6g} s from the goal's start, in the lead-in from the current " \
            "reference to the first point"
    else:
        where = f"at t = {t:.6g} s from the goal's start"
    if excess.field == "position":
        low, high = table.low[excess.joint], table.high[excess.joint]
        side = ">" if excess.value > excess.limit else "<"
        return (
            f"joint {joint!r} leaves its position range [{low:g}, {high:g}] {where}: position "
            f"{excess.value:.6g} {side} {excess.limit:g} (limits.{joint}.position); slowing "
            "down cannot change the path: move the points (or their velocities) inside the "
            "range"
        )
    return (
        f"joint {joint!r} exceeds its {excess.field} limit {where}: |{excess.field}| "
        f"{abs(excess.value):.6g} > {excess.limit:g} {_UNITS[excess.field]} "
        f"(limits.{joint}.{excess.field})"
    )


def reject(message: str) -> GoalRejected:
    """A ``GoalRejected`` (INVALID_GOAL) with ``message``."""
    return GoalRejected(message, INVALID_GOAL)
