"""Decelerating stops: the reference that brings every joint to rest instead of a hold.

Theory of operation
-------------------
Upstream's ``constraints.decelerate_on_cancel`` (jtc_upstream_behaviour.md section 11.3)
replaces the hold of a stop (cancel, path and goal-time aborts, ``cmd_timeout``, topic stops)
by a trajectory that decelerates each joint from its *measured* position and velocity at
``max_deceleration_on_cancel`` until it is at rest, then holds there; without its
preconditions (:func:`stop_unavailable_reason`) a stop is the plain hold.

Upstream stores the stop as one waypoint per update period; here the same curve is stored
exactly, as its few polynomial pieces (one per phase per joint, on the trajectory's shared
breakpoint grid), so that building it inside the control cycle stays cheap. Beyond upstream, a
joint with a jerk limit stops along an S-curve computed in closed form (:func:`stop_phases`).
See docs/behaviour.md, "Stopping", for the preconditions, the derived deceleration and the
cost.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .config import ControllerConfig
from .interpolation import F64, SegmentKind
from .messages import NS_PER_S
from .trajectory import Trajectory
from .validation import FLT_EPSILON

__all__ = [
    "DERIVED_STOP_TIME_S",
    "FLT_EPSILON",
    "Phase",
    "stop_decelerations",
    "stop_duration_bound_s",
    "stop_jerks",
    "stop_phases",
    "stop_trajectory",
    "stop_unavailable_reason",
    "warm_up",
]

DERIVED_STOP_TIME_S = 0.5
"""With a velocity limit but neither ``max_deceleration_on_cancel`` nor an acceleration limit,
the derived deceleration stops the joint from its velocity limit in this many seconds
(deceleration = velocity limit / 0.5 s)."""


class Phase(NamedTuple):
    """One constant-jerk piece of a joint's stop, from ``start_s`` to ``end_s`` after the stop
    began, with the state at ``start_s`` (position, velocity, acceleration) and its jerk."""

    start_s: float
    end_s: float
    position: float
    velocity: float
    acceleration: float
    jerk: float


def stop_decelerations(config: ControllerConfig) -> F64 | None:
    """Per joint (``joints`` order), the deceleration of a decelerating stop, or ``None`` when
    stops are plain holds (:func:`stop_unavailable_reason` says why).

    A joint's deceleration is its ``constraints.<joint>.max_deceleration_on_cancel`` when it
    is > 0; otherwise it is derived from its limits: the acceleration limit if there is one,
    else the velocity limit / :data:`DERIVED_STOP_TIME_S`.
    """
    if stop_unavailable_reason(config) is not None:
        return None
    return np.array([_deceleration(config, j) for j in config.joints])


def stop_jerks(config: ControllerConfig) -> F64:
    """Per joint, the jerk limit bounding its stop (``inf`` where there is none)."""
    jerks = []
    for joint in config.joints:
        limits = config.limits.get(joint)
        jerk = None if limits is None else limits.jerk
        jerks.append(math.inf if jerk is None else float(jerk))
    return np.array(jerks)


def _deceleration(config: ControllerConfig, joint: str) -> float:
    explicit = config.constraints.joints[joint].max_deceleration_on_cancel
    if explicit > 0.0:
        return explicit
    limits = config.limits.get(joint)
    if limits is None:
        return 0.0
    if limits.acceleration is not None:
        return float(limits.acceleration)
    if limits.velocity is not None:
        return float(limits.velocity) / DERIVED_STOP_TIME_S
    return 0.0


def stop_unavailable_reason(config: ControllerConfig) -> str | None:
    """Why stops are plain holds with this configuration, or ``None`` if they decelerate.

    Upstream's preconditions (section 11.3): the option, a velocity state interface, and for
    every joint a deceleration > 0 (given or derived) and a velocity limit > 0 where one is
    configured (``check_joint_limits`` guarantees that).
    """
    if not config.constraints.decelerate_on_cancel:
        return "constraints.decelerate_on_cancel is false"
    if "velocity" not in config.state_interfaces:
        return (
            "a decelerating stop starts from the measured velocity: add 'velocity' to "
            "state_interfaces"
        )
    missing = [j for j in config.joints if _deceleration(config, j) <= 0.0]
    if missing:
        return (
            f"joint(s) {', '.join(missing)} have no deceleration: set "
            "constraints.<joint>.max_deceleration_on_cancel, or give limits.<joint>.acceleration "
            "or limits.<joint>.velocity to derive one"
        )
    return None


def _advance(phase: Phase, dt: float) -> tuple[float, float, float]:
    """Position, velocity and acceleration ``dt`` seconds into ``phase``."""
    j = phase.jerk
    a = phase.acceleration
    v = phase.velocity
    return (
        phase.position + v * dt + 0.5 * a * dt * dt + j * dt * dt * dt / 6.0,
        v + a * dt + 0.5 * j * dt * dt,
        a + j * dt,
    )


def stop_phases(
    position: float, velocity: float, acceleration: float, deceleration: float, jerk: float
) -> tuple[list[Phase], float]:
    """One joint's stop, in closed form: its moving phases in time order (none when already at
    rest) and the position it rests at.

    Without a jerk limit (``jerk`` infinite) this is upstream's profile: the acceleration is
    ``-dir * deceleration`` from the start (``acceleration`` is ignored) until the velocity is
    0 at ``|v0| / deceleration``; nothing moves if ``|v0| <= FLT_EPSILON``.

    With a jerk limit ``J`` and ``A = deceleration``: the starting acceleration is clamped to
    ``[-A, A]``; ``dir`` is the sign of the velocity the joint would reach if its acceleration
    went to 0 at once at ``J`` (``v0 + a0 |a0| / (2 J)``), so a joint already braking hard
    towards rest is not made to overshoot. In that direction (``v``, ``a`` the starting values
    times ``dir``), the velocity still to lose after ramping is ``R = v + a^2 / (2 J)``; the
    acceleration ramps at ``-J`` from ``a`` to ``-a_peak``, holds ``-a_peak`` for ``t2``, and
    ramps back to 0 at ``+J``, with ``a_peak = sqrt(J R)`` and ``t2 = 0`` when that is at most
    ``A``, else ``a_peak = A`` and ``t2 = (R - A^2 / J) / A``.

    Args:
        position, velocity, acceleration: the state the stop starts from.
        deceleration: the largest ``|acceleration|`` of the stop, > 0.
        jerk: the largest ``|jerk|``, > 0, or ``inf``.
    """
    big_a = deceleration
    if math.isinf(jerk):
        if abs(velocity) <= FLT_EPSILON:
            return [], position
        direction = 1.0 if velocity >= 0.0 else -1.0
        t_stop = abs(velocity) / big_a
        rest = position + direction * velocity * velocity / (2.0 * big_a)
        return [Phase(0.0, t_stop, position, velocity, -direction * big_a, 0.0)], rest
    a0 = min(max(acceleration, -big_a), big_a)
    if abs(velocity) <= FLT_EPSILON and abs(a0) <= FLT_EPSILON:
        return [], position
    direction = 1.0 if velocity + a0 * abs(a0) / (2.0 * jerk) >= 0.0 else -1.0
    v = direction * velocity
    a = direction * a0
    remaining = max(v + a * a / (2.0 * jerk), 0.0)
    if remaining <= big_a * big_a / jerk:
        peak = math.sqrt(jerk * remaining)
        t2 = 0.0
    else:
        peak = big_a
        t2 = (remaining - big_a * big_a / jerk) / big_a
    durations = ((a + peak) / jerk, t2, peak / jerk)
    jerks = (-direction * jerk, 0.0, direction * jerk)
    phases: list[Phase] = []
    state = (position, velocity, a0)
    t = 0.0
    for duration, j in zip(durations, jerks, strict=True):
        if duration <= 0.0:
            continue
        phase = Phase(t, t + duration, state[0], state[1], state[2], j)
        phases.append(phase)
        state = _advance(phase, duration)
        t += duration
    return phases, state[0]


def stop_trajectory(
    now_ns: int,
    positions: F64,
    velocities: F64,
    accelerations: F64,
    decelerations: F64,
    jerks: F64,
) -> Trajectory:
    """The reference that stops every joint, decelerating, from the given state at ``now_ns``.

    Each joint follows :func:`stop_phases` (computed here for all joints at once, with the same
    formulas); once at rest it holds its rest position with zero velocity and acceleration,
    and so does the trajectory after its last breakpoint. The breakpoints are the union of the
    joints' phase boundaries (at most three per joint), each joint's pieces keeping their own
    time origin.

    Args:
        now_ns: when the stop starts (its first breakpoint; it is not defined before).
        positions, velocities, accelerations: the state it starts from, per joint.
        decelerations: per joint, > 0 (:func:`stop_decelerations`).
        jerks: per joint, > 0 or ``inf`` (:func:`stop_jerks`).
    """
    n = positions.shape[0]
    p0 = np.asarray(positions, dtype=np.float64)
    v0 = np.asarray(velocities, dtype=np.float64)
    big_a = np.asarray(decelerations, dtype=np.float64)
    jerk = np.asarray(jerks, dtype=np.float64)
    limited = np.isfinite(jerk)
    safe_jerk = np.where(limited, jerk, 1.0)  # no inf arithmetic for the unlimited joints
    a0 = np.clip(np.asarray(accelerations, dtype=np.float64), -big_a, big_a)
    a0 = np.where(limited, a0, 0.0)
    # Direction: the velocity's sign; with a jerk limit, that of the velocity reached if the
    # acceleration went to 0 at once at the jerk limit (see stop_phases).
    reached = v0 + np.where(limited, a0 * np.abs(a0) / (2.0 * safe_jerk), 0.0)
    direction = np.where(reached >= 0.0, 1.0, -1.0)
    moving = np.where(
        limited,
        (np.abs(v0) > FLT_EPSILON) | (np.abs(a0) > FLT_EPSILON),
        np.abs(v0) > FLT_EPSILON,
    )
    v = direction * v0
    a = direction * a0
    remaining = np.maximum(v + a * a / (2.0 * safe_jerk), 0.0)
    short = remaining <= big_a * big_a / safe_jerk
    peak = np.where(short, np.sqrt(safe_jerk * remaining), big_a)
    t2_jerk = np.where(short, 0.0, (remaining - big_a * big_a / safe_jerk) / big_a)
    # Phase durations: ramp to -peak, constant -peak, ramp back to 0 (jerk-limited); a single
    # constant-deceleration phase of |v0| / A otherwise (upstream).
    zero = np.zeros(n)
    d1 = np.where(limited, (a + peak) / safe_jerk, 0.0)
    d2 = np.where(limited, t2_jerk, np.abs(v0) / big_a)
    d3 = np.where(limited, peak / safe_jerk, 0.0)
    d1, d2, d3 = (np.where(moving, d, 0.0) for d in (d1, d2, d3))
    j1 = np.where(limited, -direction * safe_jerk, 0.0)
    j3 = np.where(limited, direction * safe_jerk, 0.0)
    # State at the start of each phase (phase 2 starts at -dir * peak, or -dir * A unlimited).
    a_start = np.where(limited, a0, -direction * big_a)
    p1, v1, acc1 = _advance_all(p0, v0, a_start, j1, d1)
    acc1 = np.where(limited, np.where(d1 > 0.0, acc1, a_start), -direction * big_a)
    p2, v2, acc2 = _advance_all(p1, v1, acc1, zero, d2)
    p3 = _advance_all(p2, v2, acc2, j3, d3)[0]
    # Upstream's hold point for the constant deceleration; the S-curve's end otherwise.
    rest = np.where(limited, p3, p0 + direction * v0 * v0 / (2.0 * big_a))
    rest = np.where(moving, rest, p0)
    # Phase boundaries in ns (cumulative, each rounded once): b1 <= b2 <= b3.
    b1 = now_ns + np.round(d1 * NS_PER_S).astype(np.int64)
    b2 = now_ns + np.round((d1 + d2) * NS_PER_S).astype(np.int64)
    b3 = now_ns + np.round((d1 + d2 + d3) * NS_PER_S).astype(np.int64)
    grid = np.unique(np.concatenate(([now_ns], b1, b2, b3)))
    if grid.shape[0] == 1:
        return Trajectory.constant(now_ns, rest)
    starts = grid[:-1]
    # Per segment and joint: which phase it lies in (0, 1, 2; 3 = at rest). A zero-length
    # phase has equal boundaries and is skipped.
    phase = (
        (starts[:, None] >= b1[None, :]).astype(np.intp)
        + (starts[:, None] >= b2[None, :])
        + (starts[:, None] >= b3[None, :])
    )
    cols = np.arange(n)
    table_p = np.stack((p0, p1, p2, rest))
    table_v = np.stack((v0, v1, v2, zero))
    table_a = np.stack((a_start, acc1, acc2, zero))
    table_j = np.stack((j1, zero, j3, zero))
    table_o = np.stack((np.full(n, now_ns, dtype=np.int64), b1, b2, b3))
    pp, vv, aa, jj = (t[phase, cols] for t in (table_p, table_v, table_a, table_j))
    segments = starts.shape[0]
    blocks = np.zeros((segments, 4, 6, n))
    blocks[:, 0, 0] = pp
    blocks[:, 0, 1] = vv
    blocks[:, 0, 2] = 0.5 * aa
    blocks[:, 0, 3] = jj / 6.0
    blocks[:, 1, 0] = vv
    blocks[:, 1, 1] = aa
    blocks[:, 1, 2] = 0.5 * jj
    blocks[:, 2, 0] = aa
    blocks[:, 2, 1] = jj
    origins = table_o[phase, cols]
    kinds = np.where(phase < 3, SegmentKind.CUBIC, SegmentKind.HOLD).astype(np.int8)
    final = np.zeros((4, n))
    final[0] = rest
    return Trajectory(grid, blocks, origins, kinds, final, now_ns)


def _advance_all(p: F64, v: F64, a: F64, j: F64, dt: F64) -> tuple[F64, F64, F64]:
    """Position, velocity and acceleration ``dt`` into constant-jerk pieces (per joint)."""
    dt2 = dt * dt
    return (
        p + v * dt + 0.5 * a * dt2 + j * dt2 * dt / 6.0,
        v + a * dt + 0.5 * j * dt2,
        a + j * dt,
    )


def stop_duration_bound_s(
    velocities: F64, accelerations: F64, decelerations: F64, jerks: F64
) -> float:
    """An upper bound of how long the stop from this state lasts, in seconds, without
    building it: ``|v| / A`` per joint, plus ``2 (A + |a|) / J`` with a jerk limit (the
    S-curve's ramps; see :func:`stop_phases`), the largest over the joints.
    """
    v = np.abs(np.asarray(velocities, dtype=np.float64))
    a = np.minimum(np.abs(np.asarray(accelerations, dtype=np.float64)), decelerations)
    ramps = np.where(np.isfinite(jerks), 2.0 * (decelerations + a) / np.where(
        np.isfinite(jerks), jerks, 1.0), 0.0)
    return float(np.max(v / decelerations + ramps, initial=0.0))


def warm_up(n_joints: int) -> None:
    """Build and sample a throw-away stop of ``n_joints`` joints (jerk-limited and not), so
    that the first real one, built inside a control cycle, does not pay numpy's first-call
    costs.
    """
    ones = np.ones(n_joints)
    jerks = np.where(np.arange(n_joints) % 2 == 0, np.inf, 10.0)
    stop = stop_trajectory(0, ones, ones, ones, ones, jerks)
    stop.sample(1)
    stop.sample(stop.end_ns)
