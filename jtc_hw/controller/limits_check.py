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

What is checked is what the joints will follow: the reference from the splice time (the
lead-in from the current reference to the first point, then the points) to the end, and the
state kept past the end, for the joints the command names. A position that starts outside
the range (a robot switched on outside it) is not a violation as long as the trajectory goes
no further out than where it starts: otherwise no goal could bring it back.

Slowing down (``time_scaling: fit``): every time from the goal's start is multiplied by
``s >= 1``, velocities divided by ``s``, accelerations by ``s**2`` (jerks follow, by
``s**3``): the same path, traversed more slowly. For the points' own segments the extremes
scale exactly like that, so the smallest ``s`` is ``max(v / v_max, sqrt(a / a_max),
cbrt(j / j_max))``. The lead-in starts from the current reference's state, which does not
scale; when it still exceeds a limit after slowing, ``s`` grows by the remaining ratio and
the check runs again (a few rounds at most).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..errors import GoalRejected
from .interpolation import F64, SegmentKind
from .limits import JointLimits
from .trajectory import NS_PER_S, PreparedTrajectory, Trajectory

__all__ = [
    "AcceptedGoal",
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

INVALID_GOAL = -1

TOLERANCE = 1e-9
"""Relative slack on a limit: a value computed as the limit plus rounding is within it."""

_BISECTIONS = 30
"""Bisection steps for a bracketed root: the bracket shrinks by 2**-30 (1e-9 of a segment);
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


class AcceptedGoal(int):
    """A goal id that also carries how the goal was fitted to the joint limits.

    An ``int`` everywhere a goal id is expected (the daemon's backend returns it from
    ``send_goal``); ``time_scaling`` is the ``Plan``'s (None: checked as sent, or no limits).
    """

    time_scaling: TimeScaling | None

    def __new__(cls, goal_id: int, time_scaling: TimeScaling | None = None) -> AcceptedGoal:
        accepted = super().__new__(cls, goal_id)
        accepted.time_scaling = time_scaling
        return accepted

    def reply_fields(self) -> dict[str, float]:
        """The ``accepted`` reply's fields for it (:func:`scaling_fields`)."""
        return scaling_fields(self.time_scaling)


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


# --------------------------------------------------------------------------------------------
# Polynomials, vectorised: coefficients (N, d + 1), lowest degree first
# --------------------------------------------------------------------------------------------


def _derivative(coef: F64) -> F64:
    orders = np.arange(1, coef.shape[1], dtype=np.float64)
    out: F64 = coef[:, 1:] * orders
    return out


def _horner(coef: F64, t: F64) -> F64:
    """Each row's polynomial at that row's times ``t`` (N, C)."""
    out = np.broadcast_to(coef[:, -1:], t.shape).copy()
    for k in range(coef.shape[1] - 2, -1, -1):
        out *= t
        out += coef[:, k : k + 1]
    result: F64 = out
    return result


def _horner_1d(coef: F64, t: F64) -> F64:
    out = coef[:, -1].copy()
    for k in range(coef.shape[1] - 2, -1, -1):
        out *= t
        out += coef[:, k]
    result: F64 = out
    return result


def _quadratic_roots(c0: F64, c1: F64, c2: F64) -> F64:
    """Real roots (N, 2) of ``c0 + c1 t + c2 t**2`` (NaN where there is none); a linear or
    constant row gives its root or none. A negative discriminant gives the vertex instead:
    an extra sample, which can only find true values."""
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = np.maximum(c1 * c1 - 4.0 * c2 * c0, 0.0)
        q = -0.5 * (c1 + np.copysign(np.sqrt(disc), c1))
        quad = c2 != 0.0
        r1 = np.where(quad, q / c2, np.where(c1 != 0.0, -c0 / c1, np.nan))
        r2 = np.where(quad & (q != 0.0), c0 / q, np.nan)
    return np.stack((r1, r2), axis=1)


def _bracketed_roots(coef: F64, low: F64, high: F64, split: F64) -> F64:
    """Real roots in ``[low, high]`` of each row's polynomial, given the roots of its
    derivative (``split``, NaN for none): on each piece between them it is monotonic.

    Returns:
        (N, K + 1) roots, NaN where a piece has none.
    """
    n, k = split.shape
    inner = np.where(np.isnan(split), high[:, None], np.clip(split, low[:, None], high[:, None]))
    points = np.sort(np.concatenate((low[:, None], inner, high[:, None]), axis=1), axis=1)
    values = _horner(coef, points)
    a, b = points[:, :-1], points[:, 1:]
    fa, fb = values[:, :-1], values[:, 1:]
    roots = np.full((n, k + 1), np.nan)
    change = (b > a) & (np.sign(fa) * np.sign(fb) <= 0.0)
    rows, pieces = np.nonzero(change)
    if not rows.size:
        return roots
    lo, hi, flo = a[rows, pieces], b[rows, pieces], fa[rows, pieces]
    rising = flo < 0.0  # fa and fb differ in sign (or one is 0): the root is where it crosses
    c = coef[rows]
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        below = (_horner_1d(c, mid) < 0.0) == rising
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    roots[rows, pieces] = 0.5 * (lo + hi)
    return roots


def _roots(coef: F64, low: F64, high: F64, split: F64 | None) -> F64:
    """Real roots of polynomials of degree <= 4: closed form where the coefficients of degree
    3 and up are zero, else bracketed by ``split`` (the roots of the derivative)."""
    if coef.shape[1] < 3:  # linear (snap): pad to a quadratic with a zero leading term
        coef = np.concatenate((coef, np.zeros((coef.shape[0], 3 - coef.shape[1]))), axis=1)
    if coef.shape[1] == 3 or split is None:
        return _quadratic_roots(coef[:, 0], coef[:, 1], coef[:, 2])
    high_order = (coef[:, 3:] != 0.0).any(axis=1)
    out = np.full((coef.shape[0], split.shape[1] + 1), np.nan)
    low_rows = np.flatnonzero(~high_order)
    if low_rows.size:
        c = coef[low_rows]
        out[low_rows, :2] = _quadratic_roots(c[:, 0], c[:, 1], c[:, 2])
    rows = np.flatnonzero(high_order)
    if rows.size:
        out[rows] = _bracketed_roots(coef[rows], low[rows], high[rows], split[rows])
    return out


def _extreme_times(values: F64, candidates: F64) -> tuple[F64, F64, F64, F64]:
    """Per row: the minimum, the time of the minimum, the maximum, the time of the maximum."""
    rows = np.arange(values.shape[0])
    lo = values.argmin(axis=1)
    hi = values.argmax(axis=1)
    return values[rows, lo], candidates[rows, lo], values[rows, hi], candidates[rows, hi]


# --------------------------------------------------------------------------------------------
# The check
# --------------------------------------------------------------------------------------------


def check(
    reference: Trajectory,
    from_ns: int,
    table: LimitTable,
    joints: NDArray[np.intp],
    start_positions: F64,
) -> dict[str, Excess]:
    """The worst excess of each quantity over its limit, from ``from_ns`` on.

    Args:
        reference: the spliced reference.
        from_ns: the splice time (the lead-in's start); earlier segments are not checked.
        table: the limits.
        joints: the controller joint indices to check (the command's).
        start_positions: every joint's reference position at ``from_ns``: the position range
            is widened to include it (see the module docstring).

    Returns:
        By field, the worst excess beyond :data:`TOLERANCE`; empty when within every limit.
    """
    cols = table.columns(joints)
    if not cols.size:
        return {}
    breaks, blocks, origins, kinds, final = reference.pieces()
    first = int(breaks.searchsorted(from_ns, side="left"))
    segments = max(breaks.shape[0] - 1 - first, 0)
    k = cols.shape[0]
    n = segments * k
    b = blocks[first:][:, :, :, cols]  # (s, 4, 6, k)
    org = origins[first:][:, cols]
    t0 = (breaks[first:-1][:, None] - org).reshape(n) / NS_PER_S
    t1 = (breaks[first + 1 :][:, None] - org).reshape(n) / NS_PER_S
    hold = (kinds[first:][:, cols] == SegmentKind.HOLD).reshape(n)
    coef = np.moveaxis(b[:, 0], 1, 2).reshape(n, 6).copy()
    const = np.moveaxis(b[:, :3, 0], 1, 2).reshape(n, 3)  # held rows: p, v, a as stored
    coef[hold, 1:] = 0.0
    origin_ns = org.reshape(n)

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

    d1 = _derivative(coef)
    d2 = _derivative(d1)
    d3 = _derivative(d2)
    d4 = _derivative(d3)
    roots: dict[int, F64] = {}

    def roots_of(order: int) -> F64:
        """Roots of the ``order``-th derivative of P (1: velocity's, ... 4: snap's)."""
        if order not in roots:
            poly = (d1, d2, d3, d4)[order - 1]
            split = roots_of(order + 1) if poly.shape[1] > 3 else None
            roots[order] = _roots(poly, t0, t1, split)
        return roots[order]

    # (value polynomial, the order of the derivative whose roots hold its extremes)
    quantities = {"position": (coef, 1), "velocity": (d1, 2), "acceleration": (d2, 3),
                  "jerk": (d3, 4)}
    found: dict[str, Excess] = {}
    end_ns = int(breaks[-1])
    for name in _FIELDS:
        if not wanted[name]:
            continue
        values_min = np.full(k, np.inf)
        values_max = np.full(k, -np.inf)
        time_min = np.zeros(k, dtype=np.int64)
        time_max = np.zeros(k, dtype=np.int64)
        if n:
            poly, order = quantities[name]
            extra = roots_of(order)
            cand = np.concatenate((t0[:, None], t1[:, None], extra), axis=1)
            cand = np.where(np.isnan(cand), t0[:, None], np.clip(cand, t0[:, None], t1[:, None]))
            values = _horner(poly, cand)
            if name != "jerk":
                held = const[hold, _FIELDS.index(name)]
                values[hold] = held[:, None]
            else:
                values[hold] = 0.0
            vmin, tmin, vmax, tmax = _extreme_times(values, cand)
            vmin2, vmax2 = vmin.reshape(segments, k), vmax.reshape(segments, k)
            smin, smax = vmin2.argmin(axis=0), vmax2.argmax(axis=0)
            cols_k = np.arange(k)
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
