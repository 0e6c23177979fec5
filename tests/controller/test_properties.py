"""Property-based tests (hypothesis): trajectory sampling and splicing, and the goal lifecycle.

Part 1 builds random valid trajectories the way the controller does
(``Trajectory.constant(...).splice(now, prepare(config, msg), ...)``) and checks what
docs/behaviour.md promises: knots are hit exactly, the continuity each segment kind guarantees,
finite and pure sampling, replacement keeps the past, and continuous joints take the short way.

Part 2 drives the controller with random sequences of goals, cancels, topic trajectories,
cycles and re-activations against an ideal mirror on a simulated clock, and checks that every
accepted goal gets exactly one consistent result.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, note, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    rule,
)

from jtc_hw import (
    ControllerStateError,
    ErrorCode,
    GoalFeedback,
    GoalRejected,
    GoalResult,
    GoalStatus,
    JointTolerance,
    JointTrajectory,
    JointTrajectoryController,
    Trajectory,
    TrajectoryPoint,
    TrajectoryStopped,
)
from jtc_hw.controller.config import ControllerConfig
from jtc_hw.controller.interpolation import SegmentKind
from jtc_hw.controller.outcomes import DEACTIVATED
from jtc_hw.controller.planner import Plan
from jtc_hw.controller.trajectory import TrajectorySample, shortest_angular_distance
from jtc_hw.controller.validation import prepare
from jtc_hw.errors import StalePlan

from conftest import MS, Mirror, S, kinds_at, make_config

JOINTS = tuple(f"j{i}" for i in range(1, 7))
HOLD, LINEAR, CUBIC, QUINTIC = (int(k) for k in SegmentKind)
FIELDS = ("positions", "velocities", "accelerations", "effort")

# Which fields a point carries: p(ositions), v(elocities), a(ccelerations).
WITH_POSITIONS = ("p", "pv", "pva")
DERIVATIVES_ONLY = ("v", "a", "va")  # need allow_integration_in_goal_trajectories

FAST = settings(
    max_examples=120,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

value = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False, allow_subnormal=False)


def vec(k: int) -> st.SearchStrategy[list[float]]:
    return st.lists(value, min_size=k, max_size=k)


@cache
def traj_config(
    n: int, integrate: bool, effort: bool, partial: bool = False, method: str = "splines"
) -> ControllerConfig:
    return make_config(
        joints=JOINTS[:n],
        command_interfaces=("effort",) if effort else ("position",),
        allow_integration_in_goal_trajectories=integrate,
        allow_partial_joints_goal=partial,
        interpolation_method=method,
    )


@st.composite
def point_lists(
    draw: st.DrawFn, k: int, integrate: bool, effort: bool, min_ms: int
) -> list[TrajectoryPoint]:
    """1-8 points for k joints, strictly increasing times on a 1 ms grid in [min_ms, 5 s]."""
    m = draw(st.integers(1, 8))
    times = sorted(draw(st.sets(st.integers(min_ms, 5000), min_size=m, max_size=m)))
    allowed = WITH_POSITIONS + (DERIVATIVES_ONLY if integrate else ())
    if draw(st.booleans()):
        combos = [draw(st.sampled_from(allowed))] * m  # one field combination throughout
    else:
        combos = draw(st.lists(st.sampled_from(allowed), min_size=m, max_size=m))
    return [
        TrajectoryPoint(
            positions=draw(vec(k)) if "p" in c else None,
            velocities=draw(vec(k)) if "v" in c else None,
            accelerations=draw(vec(k)) if "a" in c else None,
            effort=draw(vec(k)) if effort else None,
            time_from_start_ns=t * MS,
        )
        for t, c in zip(times, combos)
    ]


@dataclass
class Scenario:
    config: ControllerConfig
    n: int
    base: Trajectory  # the state before the new command (a constant, possibly moving, state)
    start_state: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    now: int
    msg: JointTrajectory
    cols: np.ndarray  # controller index of each message column

    def build(self) -> Trajectory:
        return self.base.splice(
            self.now,
            prepare(self.config, self.msg),
            self.config.interpolation_method,
            np.array(self.config.wraparound),
        )

    @property
    def splice_at(self) -> int:
        return max(self.msg.start_time_ns or self.now, self.now)

    @property
    def knot_times(self) -> list[int]:
        start = self.msg.start_time_ns or self.now
        return [start + p.time_from_start_ns for p in self.msg.points]


@st.composite
def scenarios(draw: st.DrawFn, min_ms: int = 0, method: str = "splines") -> Scenario:
    n = draw(st.integers(1, 6))
    integrate = method == "splines" and draw(st.booleans())
    effort = draw(st.booleans())
    config = traj_config(n, integrate, effort, method=method)
    order = draw(st.permutations(JOINTS[:n]))
    points = draw(point_lists(n, integrate, effort, min_ms))
    now = draw(st.integers(0, 10**12))
    base_t = now - draw(st.integers(0, min(now, 10 * S)))
    start = draw(st.one_of(st.just(0), st.integers(now + 1, now + 3 * S)))
    p0, v0, a0 = (np.array(draw(vec(n))) for _ in range(3))
    e0 = np.array(draw(vec(n))) if effort else np.zeros(n)
    base = Trajectory.constant(base_t, p0, v0, a0, e0)
    cols = np.array([JOINTS.index(name) for name in order])
    return Scenario(
        config, n, base, (p0, v0, a0, e0), now, JointTrajectory(order, points, start), cols
    )


@dataclass
class Expected:
    """Knot values in message column order, integrated by Heun's method where not given."""

    pos: list[np.ndarray]
    vel: list[np.ndarray]
    acc: list[np.ndarray]
    has_v: list[bool]  # after integration (derivative-only points get a velocity)
    has_a: list[bool]


def expected_knots(sc: Scenario) -> Expected:
    """An independent Heun integration from the start state, as docs/behaviour.md describes."""
    p0, v0, a0, _ = sc.start_state
    pos, vel, acc = p0[sc.cols], v0[sc.cols], a0[sc.cols]
    t_prev = sc.splice_at
    out = Expected([], [], [], [], [])
    zero = np.zeros(len(sc.cols))
    for point, t in zip(sc.msg.points, sc.knot_times):
        dt = (t - t_prev) / S
        a = np.array(point.accelerations) if point.accelerations is not None else zero
        if point.velocities is not None:
            v = np.array(point.velocities)
        elif point.positions is None:
            v = vel + (acc + a) * 0.5 * dt
        else:
            v = zero  # missing velocity counts as 0
        p = np.array(point.positions) if point.positions is not None else pos + (vel + v) * 0.5 * dt
        out.pos.append(p)
        out.vel.append(v)
        out.acc.append(a)
        out.has_v.append(point.velocities is not None or point.positions is None)
        out.has_a.append(point.accelerations is not None)
        pos, vel, acc, t_prev = p, v, a, t
    return out


def kind_of(has_v: bool, has_a: bool) -> int:
    return LINEAR if not has_v else (QUINTIC if has_a else CUBIC)


def continuity_violations(
    traj: Trajectory, t: int, level: int, before: Trajectory | None = None
) -> list[str]:
    """Compare sample(t - 1) with sample(t) (1 ns apart) up to the derivative ``level`` allows.

    ``before``: the trajectory ``traj`` replaced, equal to it before ``t`` (a splice at ``t``):
    its sample gives the left side, since ``traj`` is not defined before it was installed; no
    left side at all (``t`` is where ``before`` starts too) gives no violation.

    A difference over 1 ns is the next derivative times 1e-9 s; the tolerance is twice that
    (the next derivative taken at both sides; jerk estimated over 1 us) plus float slack.
    """
    left_of = traj if before is None else before
    if t - 1 < left_of.state_before_ns:
        return []
    left, right = left_of.sample(t - 1), traj.sample(t)
    d = 1_000
    rows = [("positions", "velocities")]
    if level >= CUBIC:
        rows.append(("velocities", "accelerations"))
    out = []
    for field, deriv in rows:
        x_l, x_r = getattr(left, field), getattr(right, field)
        rate = np.maximum(np.abs(getattr(left, deriv)), np.abs(getattr(right, deriv)))
        tol = 1e-6 + 2e-9 * rate + 1e-12 * np.abs(x_r)
        if (np.abs(x_r - x_l) > tol).any():
            out.append(f"{field} jump at {t}: left {x_l}, right {x_r}, tol {tol}")
    if level >= QUINTIC:
        far_l = left_of.sample(max(t - 1 - d, left_of.state_before_ns))
        far_r = traj.sample(t + d)
        jerk = np.maximum(
            np.abs(left.accelerations - far_l.accelerations),
            np.abs(far_r.accelerations - right.accelerations),
        ) / (d * 1e-9)
        tol = 1e-6 + 2e-9 * jerk + 1e-12 * np.abs(right.accelerations)
        if (np.abs(right.accelerations - left.accelerations) > tol).any():
            out.append(
                f"accelerations jump at {t}: left {left.accelerations}, "
                f"right {right.accelerations}, tol {tol}"
            )
    return out


# -- 1a. knots are hit exactly -------------------------------------------------------------------


def assert_knot_accelerations(actual: Any, given: Any, where: str) -> None:
    """A knot's acceleration is the point's, exactly, except where half of it is subnormal:
    the quintic stores ``a / 2`` as its coefficient, and halving a value below
    ``2 * float_info.min`` drops its last bit (one ulp, ~5e-324), which ``2 * (a / 2)`` cannot
    restore."""
    given = np.asarray(given, dtype=float)
    halved_subnormal = np.abs(given) < 2 * np.finfo(float).tiny
    np.testing.assert_array_equal(actual[~halved_subnormal], given[~halved_subnormal], where)
    np.testing.assert_array_max_ulp(actual[halved_subnormal], given[halved_subnormal], maxulp=1)



@FAST
@given(sc=scenarios())
def test_samples_pass_through_every_waypoint(sc: Scenario) -> None:
    traj = sc.build()
    exp = expected_knots(sc)
    points, times, cols = sc.msg.points, sc.knot_times, sc.cols
    m = len(points)
    p0, v0, a0, e0 = sc.start_state

    # The bridge starts from the previous state exactly (unless the first point is due now).
    if times[0] > sc.splice_at:
        s = traj.sample(sc.splice_at)
        bridge = kind_of(exp.has_v[0], exp.has_a[0])
        assert (kinds_at(traj, sc.splice_at)[cols] == bridge).all()
        np.testing.assert_array_equal(s.positions, p0)
        np.testing.assert_array_equal(s.effort, e0)
        if bridge >= CUBIC:
            np.testing.assert_array_equal(s.velocities, v0)
        if bridge == QUINTIC:
            assert_knot_accelerations(s.accelerations, a0, "bridge start")

    for i, (point, t) in enumerate(zip(points, times)):
        s = traj.sample(t)
        pos, vel, acc = s.positions[cols], s.velocities[cols], s.accelerations[cols]
        if point.positions is not None:
            np.testing.assert_array_equal(pos, point.positions, err_msg=f"point {i}")
        else:
            np.testing.assert_allclose(pos, exp.pos[i], rtol=1e-9, atol=1e-9, err_msg=f"{i}")
        if point.effort is not None:
            np.testing.assert_array_equal(s.effort[cols], point.effort, err_msg=f"point {i}")
        if i == m - 1:  # the last point as given, its velocity and acceleration kept (issue 11)
            assert (kinds_at(traj, t) == HOLD).all()
            np.testing.assert_allclose(vel, exp.vel[i], rtol=1e-9, atol=1e-9)
            np.testing.assert_array_equal(acc, exp.acc[i])
            assert traj.end_ns == t
            continue
        kind = kind_of(exp.has_v[i] and exp.has_v[i + 1], exp.has_a[i] and exp.has_a[i + 1])
        assert (kinds_at(traj, t)[cols] == kind).all(), (i, kinds_at(traj, t), kind)
        if kind >= CUBIC:
            if point.velocities is not None:
                np.testing.assert_array_equal(vel, point.velocities, err_msg=f"point {i}")
            else:
                np.testing.assert_allclose(vel, exp.vel[i], rtol=1e-9, atol=1e-9)
        else:
            slope = (exp.pos[i + 1] - exp.pos[i]) / ((times[i + 1] - t) / S)
            np.testing.assert_allclose(vel, slope, rtol=1e-9, atol=1e-9, err_msg=f"point {i}")
            assert (acc == 0.0).all()
        if kind == QUINTIC:
            assert_knot_accelerations(acc, point.accelerations, f"point {i}")

    # After the end: the last point as given, not decaying (upstream section 4.3 step 6).
    last = traj.sample(times[-1] + 10**15)
    for mine, at_end in zip(last, traj.sample(times[-1]), strict=True):
        np.testing.assert_array_equal(mine, at_end)


# -- 1b. continuity at the knots -------------------------------------------------------------------


@FAST
@given(sc=scenarios())
def test_continuity_at_interior_knots_matches_segment_kind(sc: Scenario) -> None:
    traj = sc.build()
    times = sc.knot_times
    problems = []
    # The splice: the bridge leaves the previous state with the continuity its kind allows.
    if times[0] > sc.splice_at:
        level = int(kinds_at(traj, sc.splice_at).min())
        problems += continuity_violations(traj, sc.splice_at, level, sc.base)
    for t in times[:-1]:
        if t == sc.splice_at:
            continue  # a first point due at the splice time: no lead-in, a jump is allowed
        level = int(min(kinds_at(traj, t - 1).min(), kinds_at(traj, t).min()))
        assert level in (LINEAR, CUBIC, QUINTIC)
        problems += continuity_violations(traj, t, level)
    # The last knot: position is continuous (the velocity becomes the last point's there).
    if times[-1] > sc.splice_at:
        problems += continuity_violations(traj, times[-1], LINEAR)
    assert not problems, problems


# -- 1c. always finite -----------------------------------------------------------------------------

probe_times = st.lists(
    st.one_of(
        st.integers(-(2**62), 2**62),
        st.integers(0, 10**12 + 10 * S),
    ),
    max_size=20,
)


@FAST
@given(sc=scenarios(), extra=probe_times)
def test_samples_are_always_finite(sc: Scenario, extra: list[int]) -> None:
    traj = sc.build()
    times = sc.knot_times
    probes = list(extra) + [sc.now, sc.splice_at, times[-1] + 10**15, 2**62, -(2**62), 0]
    for t in times:
        probes += [t - 1, t, t + 1]
    for a, b in zip([sc.splice_at] + times, times):
        probes += [a + (b - a) // 3, (a + b) // 2]
    for t in probes:
        if t < traj.state_before_ns:  # not defined before it is installed (issue 11)
            with pytest.raises(ValueError, match="defined from"):
                traj.sample(t)
            continue
        s = traj.sample(t)
        for field in FIELDS:
            assert np.isfinite(getattr(s, field)).all(), (t, field, s)
            assert getattr(s, field).shape == (sc.n,)


# -- 1d. sample is pure ----------------------------------------------------------------------------


def snapshot(s: TrajectorySample) -> tuple[bytes, ...]:
    return tuple(np.ascontiguousarray(getattr(s, f)).tobytes() for f in FIELDS)


@FAST
@given(sc=scenarios(), data=st.data())
def test_sample_is_pure(sc: Scenario, data: st.DataObject) -> None:
    traj = sc.build()
    times = sc.knot_times
    probes = [sc.now - 5, sc.splice_at, times[-1] + 1] + [t + d for t in times for d in (-1, 0)]
    probes += data.draw(st.lists(st.integers(sc.now - S, times[-1] + S), max_size=15))
    probes = [t for t in probes if t >= traj.state_before_ns]  # defined from there (issue 11)
    first = {t: snapshot(traj.sample(t)) for t in probes}
    kinds = {t: kinds_at(traj, t).tobytes() for t in probes}
    # Mutating what sample returned must not leak into later samples (writes may be refused).
    for t in probes:
        s = traj.sample(t)
        for f in FIELDS:
            try:
                getattr(s, f)[...] = 12345.0
            except ValueError:
                pass
    for t in data.draw(st.permutations(probes)) + list(reversed(probes)):
        assert snapshot(traj.sample(t)) == first[t], t
        assert kinds_at(traj, t).tobytes() == kinds[t], t


# -- 1e. replacement keeps the past ----------------------------------------------------------------


@dataclass
class Replacement:
    config: ControllerConfig
    first: Trajectory
    now2: int
    msg: JointTrajectory
    cols: np.ndarray


@st.composite
def replacements(draw: st.DrawFn) -> Replacement:
    n = draw(st.integers(1, 6))
    integrate, effort, partial = draw(st.booleans()), draw(st.booleans()), draw(st.booleans())
    config = traj_config(n, integrate, effort, partial)
    wrap = np.array(config.wraparound)
    now1 = draw(st.integers(10 * S, 10**12))
    start_a = draw(st.one_of(st.just(0), st.integers(now1 + 1, now1 + 3 * S)))
    p0, v0, a0 = (draw(vec(n)) for _ in range(3))
    base = Trajectory.constant(now1, p0, v0, a0, draw(vec(n)) if effort else None)
    msg_a = JointTrajectory(
        draw(st.permutations(JOINTS[:n])), draw(point_lists(n, integrate, effort, 1)), start_a
    )
    first = base.splice(now1, prepare(config, msg_a), "splines", wrap)
    now2 = now1 + draw(st.integers(0, first.end_ns - now1 + 2 * S))
    names = draw(st.permutations(JOINTS[:n]))
    if partial:
        names = names[: draw(st.integers(1, n))]
    start_b = draw(
        st.one_of(
            st.just(0),
            st.integers(now2 + 1, now2 + 3 * S),
            st.integers(max(now2 - 3 * S, 1), now2),  # in the past: earlier points dropped
        )
    )
    msg_b = JointTrajectory(names, draw(point_lists(len(names), integrate, effort, 1)), start_b)
    cols = np.array([JOINTS.index(name) for name in names])
    return Replacement(config, first, now2, msg_b, cols)


@FAST
@given(rp=replacements(), data=st.data())
def test_replacement_keeps_the_current_trajectory_until_the_splice(
    rp: Replacement, data: st.DataObject
) -> None:
    first, now2, msg, cols = rp.first, rp.now2, rp.msg, rp.cols
    start = msg.start_time_ns or now2
    abs_times = [start + p.time_from_start_ns for p in msg.points]
    prepared = prepare(rp.config, msg)
    if abs_times[-1] < now2:
        with pytest.raises(GoalRejected) as info:
            first.splice(now2, prepared, "splines", np.array(rp.config.wraparound))
        assert info.value.error_code == ErrorCode.OLD_HEADER_TIMESTAMP
        return
    second = first.splice(now2, prepared, "splines", np.array(rp.config.wraparound))
    ts = max(start, now2)
    note(f"splice at {ts}, first ends {first.end_ns}, second ends {second.end_ns}")

    # Identical before the splice time (from now on: the controller never samples the past).
    before = [now2, ts - 1] + data.draw(st.lists(st.integers(now2, ts), max_size=10))
    for t in before:
        if now2 <= t < ts:
            for f in FIELDS:
                np.testing.assert_array_equal(
                    getattr(second.sample(t), f), getattr(first.sample(t), f), err_msg=f"{f}@{t}"
                )

    kept = [t for t in abs_times if t >= now2]
    if kept[0] > ts:  # a bridge: it starts from the current reference, in position continuously
        np.testing.assert_array_equal(second.sample(ts).positions, first.sample(ts).positions)
        kind = kinds_at(second, ts)
        cubic = cols[kind[cols] >= CUBIC]
        np.testing.assert_array_equal(
            second.sample(ts).velocities[cubic], first.sample(ts).velocities[cubic]
        )
        problems = continuity_violations(second, ts, LINEAR, first)
        assert not problems, problems

    # The last point of the new command is reached and held.
    last = msg.points[-1]
    if last.positions is not None:
        np.testing.assert_array_equal(second.sample(abs_times[-1]).positions[cols], last.positions)
    # The combined trajectory ends with the latest joint.
    others = np.setdiff1d(np.arange(first.n_joints), cols)
    expected_end = abs_times[-1]
    if others.size and first.end_ns > ts:
        expected_end = max(expected_end, first.end_ns)
    assert second.end_ns == expected_end

    # Partial goals: joints not named keep following the current trajectory, to the end.
    if others.size:
        probes = [now2, ts, first.end_ns, second.end_ns, second.end_ns + 10**12]
        probes += [t + d for t in first.breakpoints_ns + second.breakpoints_ns for d in (-1, 0)]
        probes += data.draw(st.lists(st.integers(now2, second.end_ns + S), max_size=10))
        for t in probes:
            if t < now2:
                continue
            a, b = first.sample(t), second.sample(t)
            for f in FIELDS:
                np.testing.assert_array_equal(
                    getattr(b, f)[others], getattr(a, f)[others], err_msg=f"{f}@{t}"
                )


# -- 1f. continuous joints take the short way ------------------------------------------------------


@FAST
@given(
    n=st.integers(1, 3),
    data=st.data(),
    now=st.integers(0, 10**12),
    t1_ms=st.integers(1, 5000),
)
def test_wraparound_lead_in_never_moves_more_than_pi(
    n: int, data: st.DataObject, now: int, t1_ms: int
) -> None:
    wrap = data.draw(st.lists(st.booleans(), min_size=n, max_size=n).filter(any))
    config = make_config(
        joints=JOINTS[:n],
        gains={j: {"angle_wraparound": True} for j, w in zip(JOINTS, wrap) if w},
    )
    assert list(config.wraparound) == wrap
    angle = st.floats(-1e3, 1e3, allow_nan=False)
    start_p = np.array(data.draw(st.lists(angle, min_size=n, max_size=n)))
    start_v = np.array(data.draw(vec(n)))
    target = data.draw(
        st.lists(
            st.one_of(st.floats(-1e6, 1e6), st.sampled_from([math.pi, -math.pi, 3 * math.pi])),
            min_size=n,
            max_size=n,
        )
    )
    start_time = data.draw(st.one_of(st.just(0), st.integers(now + 1, now + 3 * S)))
    base = Trajectory.constant(now, start_p, start_v)
    msg = JointTrajectory(
        JOINTS[:n], [TrajectoryPoint(positions=target, time_from_start_ns=t1_ms * MS)], start_time
    )
    traj = base.splice(now, prepare(config, msg), "splines", np.array(config.wraparound))
    ts = max(start_time or now, now)
    t1 = ts + t1_ms * MS
    w = np.array(wrap)
    np.testing.assert_array_equal(traj.sample(ts).positions, start_p)  # no step
    probes = [ts, ts + 1, t1 - 1, t1, t1 + S] + data.draw(
        st.lists(st.integers(ts, t1), max_size=20)
    )
    for t in probes:
        travel = np.abs(traj.sample(t).positions - start_p)[w]
        assert (travel <= math.pi + 1e-9).all(), (t, travel)
    end = traj.sample(t1).positions
    # A continuous joint ends at the target angle (modulo whole turns), the others exactly on it.
    assert (np.abs(shortest_angular_distance(end[w], np.array(target)[w])) < 1e-6).all()
    np.testing.assert_array_equal(end[~w], np.array(target)[~w])


# -- interpolation_method none: a zero-order hold --------------------------------------------------


@FAST
@given(sc=scenarios(method="none"))
def test_none_method_gives_the_next_point(sc: Scenario) -> None:
    """Upstream section 4.6 (issue 11): the state before during the lead-in, point i + 1 from
    point i's time to point i + 1's, the last point after the end."""
    traj = sc.build()
    times, cols = sc.knot_times, sc.cols
    p0 = sc.start_state[0]
    if times[0] > sc.splice_at:
        for t in (sc.splice_at, (sc.splice_at + times[0]) // 2, times[0] - 1):
            np.testing.assert_array_equal(traj.sample(t).positions, p0)
    points = sc.msg.points
    for i in range(len(points)):
        nxt = times[i + 1] if i + 1 < len(times) else times[i] + 10 * S
        shown = points[min(i + 1, len(points) - 1)]
        for t in (times[i], (times[i] + nxt) // 2, nxt - 1):
            if t < traj.state_before_ns:  # a point due before the splice was dropped
                continue
            np.testing.assert_array_equal(traj.sample(t).positions[cols], shown.positions)


# == 2. Goal lifecycle ============================================================================

NAMES = ("j1", "j2")
PERIOD = 10 * MS
TOL_VALUES = (0.0, -1.0, 0.002, 0.02, 0.2)
THEN = st.one_of(st.just(0), st.integers(1, 150))  # cycles to run after an operation


@dataclass
class Command:
    goal: bool  # an action goal, else a topic trajectory
    msg: JointTrajectory
    path: list[JointTolerance]
    goal_tol: list[JointTolerance]
    goal_time: float
    expect: int | None  # the rejection code it must get; None: it must be accepted


class GoalLifecycle(RuleBasedStateMachine):
    """Random operations on a controller with an ideal mirror; every accepted goal ends once."""

    @initialize(
        holding=st.booleans(),
        iface=st.sampled_from(["position", "position+velocity", "velocity", "effort"]),
        traj_tol=st.sampled_from([0.0, 0.05, 0.3]),
        goal_tol=st.sampled_from([0.0, 0.01]),
        goal_time=st.sampled_from([0.0, 0.3]),
        cmd_timeout=st.sampled_from([0.0, 0.5]),
        partial=st.booleans(),
        integrate=st.booleans(),
        method=st.sampled_from(["splines", "splines", "none"]),
        wrap=st.booleans(),
        open_loop=st.booleans(),
        start=st.lists(st.floats(-3, 3), min_size=2, max_size=2),
    )
    def setup(
        self,
        holding: bool,
        iface: str,
        traj_tol: float,
        goal_tol: float,
        goal_time: float,
        cmd_timeout: float,
        partial: bool,
        integrate: bool,
        method: str,
        wrap: bool,
        open_loop: bool,
        start: list[float],
    ) -> None:
        gains: dict[str, dict[str, Any]] = {j: {} for j in NAMES}
        for j in NAMES:
            if iface == "effort":
                gains[j].update(p=100.0, d=20.0)
            elif iface == "velocity":
                gains[j].update(p=20.0, ff_velocity_scale=1.0)
        if wrap:
            gains["j1"]["angle_wraparound"] = True
        constraints: dict[str, Any] = {j: {"trajectory": traj_tol, "goal": goal_tol} for j in NAMES}
        constraints.update(goal_time=goal_time, stopped_velocity_tolerance=0.05)
        self.config = make_config(
            joints=NAMES,
            command_interfaces=tuple(iface.split("+")),
            start_with_holding=holding,
            constraints=constraints,
            cmd_timeout=cmd_timeout,
            allow_partial_joints_goal=partial,
            allow_integration_in_goal_trajectories=integrate,
            interpolation_method=method,
            open_loop_control=open_loop,
            gains=gains,
        )
        self.ctrl = JointTrajectoryController(self.config)
        self.mirror = Mirror(start)
        self.now = 10 * S
        self.ctrl.activate(self.now, self.mirror.state())
        self.commanding = holding  # whether commands must be finite (else all NaN)
        self.accepted: dict[int, int] = {}  # goal id -> time accepted
        self.path_checked: dict[int, bool] = {}  # goal id -> any path tolerance in force
        self.timed: dict[int, bool] = {}  # goal id -> a goal time or command timeout in force
        self.results: dict[int, GoalResult] = {}
        self.cancel_requested: set[int] = set()
        # id -> the (status, codes) its result must have, once an operation decided it
        self.decided: dict[int, tuple[GoalStatus, set[int]]] = {}
        self.fault_reason: dict[int, str] = {}  # ids active at a deactivation: its message
        self.last_accepted: int | None = None
        self.plans: list[tuple[Command, Plan]] = []
        self.last_ref = (self.ctrl.reference, self.ctrl.reference_version)

    # -- helpers ----------------------------------------------------------------------------------

    def _outstanding(self) -> set[int]:
        return set(self.accepted) - set(self.results)

    def _process(self, events: tuple[Any, ...]) -> None:
        for e in events:
            if isinstance(e, GoalResult):
                gid = e.goal_id
                assert gid in self.accepted, f"result for a goal never accepted: {e}"
                assert gid not in self.results, f"second result {e} after {self.results[gid]}"
                assert self.accepted[gid] <= e.time_ns <= self.now, e
                assert e.status.terminal, e
                code = int(e.error_code)
                if e.status is GoalStatus.SUCCEEDED:
                    assert code == ErrorCode.SUCCESSFUL, e
                elif e.status is GoalStatus.ABORTED:
                    assert code in (-4, -5, -1) and e.error_string, e
                    if code == -1:
                        assert e.error_string == self.fault_reason.get(gid), e
                    if code == -4:
                        assert self.path_checked[gid], e
                    if code == -5:  # late: needs a goal time or a command timeout
                        assert self.timed[gid], e
                else:
                    assert code in (0, -1), e
                    if code == 0:
                        assert gid in self.cancel_requested, e
                if code == 0:
                    assert e.status in (GoalStatus.SUCCEEDED, GoalStatus.CANCELED), e
                if gid in self.cancel_requested and gid not in self.fault_reason:
                    assert e.status is GoalStatus.CANCELED, e
                if gid in self.fault_reason:
                    assert e.status is GoalStatus.ABORTED, e
                if gid in self.decided:
                    status, codes = self.decided[gid]
                    assert e.status is status and code in codes, e
                event(f"result {e.status.name} {code}")
                self.results[gid] = e
            elif isinstance(e, GoalFeedback):
                assert e.goal_id in self.accepted and e.goal_id not in self.results, e
            else:
                assert isinstance(e, TrajectoryStopped), e

    def _expect_preemption(self) -> None:
        """The active goal, if any, is about to be preempted by a new command."""
        gid = self.ctrl.active_goal
        if gid is not None:
            code = 0 if gid in self.cancel_requested else -1
            self.decided[gid] = (GoalStatus.CANCELED, {code})

    def _trajectory(
        self, data: st.DataObject, allow_past: bool
    ) -> tuple[JointTrajectory, int | None]:
        """A trajectory and the rejection code it must get (None: it must be accepted)."""
        config = self.config
        names = list(data.draw(st.permutations(NAMES)))
        if config.allow_partial_joints_goal and data.draw(st.booleans()):
            names = names[:1]
        k = len(names)
        m = data.draw(st.integers(1, 3))
        times = sorted(data.draw(st.sets(st.integers(1, 150), min_size=m, max_size=m)))
        if data.draw(st.integers(0, 9)) == 0:
            times[0] = 0  # no lead-in: a jump the path tolerance may refuse
        combos = ["p", "pv"]
        if config.allow_integration_in_goal_trajectories and config.interpolation_method != "none":
            combos += ["v", "va"]
        small = st.lists(st.floats(-1.0, 1.0), min_size=k, max_size=k)
        points = []
        for t in times:
            c = data.draw(st.sampled_from(combos))
            points.append(
                TrajectoryPoint(
                    positions=data.draw(small) if "p" in c else None,
                    velocities=data.draw(small) if "v" in c else None,
                    accelerations=data.draw(small) if "a" in c else None,
                    time_from_start_ns=t * 10 * MS,
                )
            )
        when = data.draw(
            st.sampled_from(["now", "now", "future", "past"] if allow_past else ["now"])
        )
        start = {
            "now": 0,
            "future": self.now + data.draw(st.integers(1, 1000)) * MS,
            "past": self.now - data.draw(st.integers(0, 3000)) * MS,
        }[when]
        expect: int | None = None
        if start and start + points[-1].time_from_start_ns < self.now:
            expect = ErrorCode.OLD_HEADER_TIMESTAMP
        defect = data.draw(
            st.sampled_from(["none"] * 18 + ["joint", "dup", "time", "nan", "len", "neg"])
        )
        if defect == "joint":
            names[0], expect = "nope", ErrorCode.INVALID_JOINTS
        elif defect == "dup" and k == 2:
            names[1], expect = names[0], ErrorCode.INVALID_JOINTS
        elif defect == "time" and m > 1:
            p = points[1]
            points[1] = TrajectoryPoint(
                positions=p.positions,
                velocities=p.velocities,
                accelerations=p.accelerations,
                time_from_start_ns=points[0].time_from_start_ns,
            )
            expect = ErrorCode.INVALID_GOAL
        elif defect == "nan":
            points[-1] = TrajectoryPoint(
                positions=[math.nan] * k, time_from_start_ns=times[-1] * 10 * MS
            )
            expect = ErrorCode.INVALID_GOAL
        elif defect == "len":
            points[0] = TrajectoryPoint(
                positions=[0.0] * (k + 1), time_from_start_ns=times[0] * 10 * MS
            )
            expect = ErrorCode.INVALID_GOAL
        elif defect == "neg":
            start, expect = -1, ErrorCode.INVALID_GOAL
        return JointTrajectory(names, points, start), expect

    def _command(self, data: st.DataObject, goal: bool) -> Command:
        """A random goal (with tolerance overrides) or topic trajectory, and its fate."""
        msg, expect = self._trajectory(data, allow_past=self.ctrl.active)
        if not goal:
            return Command(False, msg, [], [], 0.0, expect)
        tol = st.builds(JointTolerance, st.sampled_from(NAMES), st.sampled_from(TOL_VALUES))
        path = data.draw(st.lists(tol, max_size=2, unique_by=lambda t: t.name))
        goal_tol = data.draw(st.lists(tol, max_size=2, unique_by=lambda t: t.name))
        goal_time = data.draw(st.sampled_from([0.0, 0.0, 0.2, -1.0]))
        if expect is None or expect == ErrorCode.OLD_HEADER_TIMESTAMP:
            bad = data.draw(st.sampled_from(["none"] * 15 + ["value", "joint", "goal_time"]))
            if bad == "value":
                path = [JointTolerance(NAMES[0], position=-2.0)]
                expect = ErrorCode.INVALID_GOAL
            elif bad == "joint":
                goal_tol = [JointTolerance("nope", position=0.1)]
                expect = ErrorCode.INVALID_JOINTS
            elif bad == "goal_time":
                goal_time, expect = math.inf, ErrorCode.INVALID_GOAL
        return Command(True, msg, path, goal_tol, goal_time, expect)

    def _snapshot(self) -> tuple[Any, ...]:
        c = self.ctrl
        return (c.active, c.active_goal, id(c.reference), c.reference_version, c.holding)

    def _rejected(self, cmd: Command, rejected: GoalRejected, before: tuple[Any, ...]) -> None:
        event(f"{'goal' if cmd.goal else 'topic'} rejected {rejected.error_code}")
        assert cmd.expect is not None, f"valid command rejected: {rejected}"
        assert rejected.error_code == cmd.expect, (rejected.error_code, cmd.expect, rejected)
        assert self._snapshot() == before, "a rejected command changed the controller"

    def _accepted(self, cmd: Command, gid: int | None) -> None:
        assert cmd.expect is None, f"command accepted, expected rejection {cmd.expect}"
        self.commanding = True
        if not cmd.goal:
            assert gid is None and self.ctrl.active_goal is None
            return
        assert gid is not None and gid not in self.accepted and gid == self.ctrl.active_goal
        self.accepted[gid] = self.now
        self.last_accepted = gid
        defaults = self.config.constraints.joints
        in_force = {j: defaults[j].trajectory for j in NAMES}
        for t in cmd.path:
            if t.position == -1.0:
                in_force[t.name] = 0.0
            elif t.position > 0.0:
                in_force[t.name] = t.position
        self.path_checked[gid] = any(v > 0.0 for v in in_force.values())
        goal_time = {0.0: self.config.constraints.goal_time, -1.0: 0.0}.get(
            cmd.goal_time, cmd.goal_time
        )
        self.timed[gid] = goal_time > 0.0 or self.config.effective_cmd_timeout > 0.0

    def _plan(self, cmd: Command) -> Plan:
        if cmd.goal:
            return self.ctrl.plan_goal(self.now, cmd.msg, cmd.path, cmd.goal_tol, cmd.goal_time)
        return self.ctrl.plan_trajectory(self.now, cmd.msg)

    # -- rules ------------------------------------------------------------------------------------

    @rule(data=st.data(), then=THEN)
    def accept_or_reject_goal(self, data: st.DataObject, then: int) -> None:
        """send_goal: valid, invalid, past or future start, random tolerance overrides."""
        self._send(self._command(data, goal=True))
        self._run(then)

    @rule(data=st.data(), then=THEN)
    def topic_trajectory(self, data: st.DataObject, then: int) -> None:
        """send_trajectory: the topic interface; an empty one stops."""
        if self.ctrl.active and data.draw(st.integers(0, 3)) == 0:
            note(f"send_trajectory at {self.now}: empty")
            gid = self.ctrl.active_goal
            if gid is not None:  # stopped: CANCELED (never ABORTED), at the next cycle
                self.decided[gid] = (GoalStatus.CANCELED, {-1})
            self.ctrl.send_trajectory(self.now, JointTrajectory((), []))
            self.commanding = True
        else:
            self._send(self._command(data, goal=False))
        self._run(then)

    def _send(self, cmd: Command) -> None:
        note(f"send at {self.now}: {cmd}")
        if not self.ctrl.active:
            with pytest.raises(GoalRejected, match="not active"):
                if cmd.goal:
                    self.ctrl.send_goal(self.now, cmd.msg)
                else:
                    self.ctrl.send_trajectory(self.now, cmd.msg)
            return
        before = self._snapshot()
        if cmd.expect is None:
            self._expect_preemption()
        try:
            if cmd.goal:
                gid = self.ctrl.send_goal(self.now, cmd.msg, cmd.path, cmd.goal_tol, cmd.goal_time)
            else:
                self.ctrl.send_trajectory(self.now, cmd.msg)
                gid = None
        except GoalRejected as rejected:
            self._rejected(cmd, rejected, before)
            return
        self._accepted(cmd, gid)

    @rule(data=st.data(), goal=st.booleans(), then=THEN)
    def plan(self, data: st.DataObject, goal: bool, then: int) -> None:
        """plan_goal / plan_trajectory (the daemon's first half): changes nothing."""
        cmd = self._command(data, goal)
        note(f"plan at {self.now}: {cmd}")
        if not self.ctrl.active:
            with pytest.raises(GoalRejected, match="not active"):
                self._plan(cmd)
        else:
            before = self._snapshot()
            try:
                plan = self._plan(cmd)
            except GoalRejected as rejected:
                self._rejected(cmd, rejected, before)
            else:
                assert cmd.expect is None, f"plan made, expected rejection {cmd.expect}"
                assert self._snapshot() == before, "planning changed the controller"
                then_what = data.draw(st.sampled_from(["commit", "race", "keep"]))
                if then_what == "race":  # another client's command is committed first
                    other = self._command(data, goal=data.draw(st.booleans()))
                    try:
                        other_plan = self._plan(other)
                    except GoalRejected as rejected:
                        self._rejected(other, rejected, before)
                    else:
                        self._commit(other, other_plan)  # the first plan is now stale
                if then_what == "keep":
                    self.plans = [*self.plans[-3:], (cmd, plan)]
                else:
                    self._commit(cmd, plan)
        self._run(then)

    @rule(data=st.data(), then=THEN)
    def commit(self, data: st.DataObject, then: int) -> None:
        """commit a plan: refused (StalePlan) once the reference changed or its time passed."""
        if self.plans:
            self._commit(*self.plans.pop(data.draw(st.integers(0, len(self.plans) - 1))))
        self._run(then)

    def _commit(self, cmd: Command, plan: Plan) -> None:
        before = self._snapshot()
        stale = plan.base_version != self.ctrl.reference_version or self.now > plan.planned_ns
        note(f"commit at {self.now} of a plan for {plan.planned_ns}: stale={stale}")
        event(f"commit: {'inactive' if not self.ctrl.active else 'stale' if stale else 'ok'}")
        if not self.ctrl.active:
            with pytest.raises(GoalRejected, match="not active"):
                self.ctrl.commit(plan, self.now)
        elif stale:
            with pytest.raises(StalePlan):
                self.ctrl.commit(plan, self.now)
            assert self._snapshot() == before, "a stale plan changed the controller"
        else:
            self._expect_preemption()
            self._accepted(cmd, self.ctrl.commit(plan, self.now))

    @rule(data=st.data(), then=THEN)
    def cancel(self, data: st.DataObject, then: int) -> None:
        """cancel_goal of the active, a finished, a rejected or an unknown id."""
        self._cancel(data)
        self._run(then)

    def _cancel(self, data: st.DataObject) -> None:
        choices: list[st.SearchStrategy[int]] = [st.integers(-2, 50)]  # unknown or rejected
        if self.accepted:
            choices.append(st.sampled_from(sorted(self.accepted)))  # finished ones included
        if self.ctrl.active_goal is not None:
            choices += [st.just(self.ctrl.active_goal)] * 2
        gid = data.draw(st.one_of(choices))
        expected = (
            self.ctrl.active and gid == self.ctrl.active_goal and gid not in self.cancel_requested
        )
        note(f"cancel {gid} at {self.now} -> {expected}")
        assert self.ctrl.cancel_goal(gid) == expected
        if expected:
            assert not self.ctrl.cancel_goal(gid)  # already canceling
            self.cancel_requested.add(gid)
            # Ends CANCELED with code 0 at the next cycle (this overrides a pending stop by an
            # empty topic trajectory), unless preempted or deactivated first.
            self.decided[gid] = (GoalStatus.CANCELED, {0})

    @rule(cycles=st.integers(1, 150))
    def advance(self, cycles: int) -> None:
        """update() for some cycles on the simulated clock, the mirror following."""
        self._run(cycles)

    def _run(self, cycles: int) -> None:
        if not cycles:
            return
        if not self.ctrl.active:
            with pytest.raises(ControllerStateError):
                self.ctrl.update(self.now, PERIOD, self.mirror.state())
            self.now += cycles * PERIOD
            return
        event(f"update; executing goal: {self.ctrl.active_goal is not None}")
        for _ in range(cycles):
            topic_running = not self.ctrl.holding and self.ctrl.active_goal is None
            out = self.ctrl.update(self.now, PERIOD, self.mirror.state())
            self._process(out.events)
            stopped = [e for e in out.events if isinstance(e, TrajectoryStopped)]
            assert not stopped or topic_running, stopped  # only a topic trajectory is "stopped"
            for f in FIELDS:
                values = getattr(out.command, f)
                if values is None:
                    continue
                if self.commanding:
                    assert np.isfinite(values).all(), (self.now, f, values)
                else:
                    assert np.isnan(values).all(), (self.now, f, values)
            assert np.isfinite(out.desired.positions).all()
            outstanding = self._outstanding()
            active = self.ctrl.active_goal
            # At most one goal executes, and every other accepted goal has had its result.
            assert outstanding == ({active} if active is not None else set()), (outstanding, active)
            self._check_version()
            self.mirror.apply(out.command, PERIOD / S)
            self.now += PERIOD

    @rule(frozen=st.booleans(), then=THEN)
    def freeze(self, frozen: bool, then: int) -> None:
        """Freeze the mirror (the joints stop following: path tolerances abort) or unfreeze."""
        self.mirror.frozen = frozen
        self._run(then)

    @rule(kick=st.floats(-0.5, 0.5), then=THEN)
    def disturb(self, kick: float, then: int) -> None:
        """Push joint j1 (measured position jumps)."""
        self.mirror.p = self.mirror.p + np.array([kick, 0.0])
        self._run(then)

    @rule(gap=st.integers(1, 2 * S))
    def clock_jump(self, gap: int) -> None:
        self.now += gap  # cycles skipped: the controller only sees the times it is given

    @rule(fault=st.booleans(), reactivate=st.integers(0, 3))
    def deactivate_activate(self, fault: bool, reactivate: int) -> None:
        """Deactivate (for a fault when ``fault``) and activate again, now or at the next
        call."""
        if not self.ctrl.active:
            with pytest.raises(ControllerStateError):
                self.ctrl.deactivate(self.now)
            self._activate()
            return
        gid = self.ctrl.active_goal
        self._deactivate(fault)
        assert not self.ctrl.cancel_goal(gid if gid is not None else 1)
        if reactivate:  # else stay inactive until the next call
            self._activate()

    def _deactivate(self, fault: bool) -> None:
        """The active goal ends now, ABORTED (-1) as upstream, with the fault's reason or
        upstream's deactivation message (even while a cancel is pending)."""
        reason = "servo overheated" if fault else None
        gid = self.ctrl.active_goal
        if gid is not None:
            self.fault_reason[gid] = reason or DEACTIVATED
            self.decided[gid] = (GoalStatus.ABORTED, {-1})
        self._process(self.ctrl.deactivate(self.now, reason))
        assert not self._outstanding(), self._outstanding()
        assert self.ctrl.active_goal is None and not self.ctrl.active

    def _activate(self) -> None:
        self.ctrl.activate(self.now, self.mirror.state())
        self.commanding = self.config.start_with_holding
        assert self.ctrl.holding and self.ctrl.active_goal is None

    # -- invariants -------------------------------------------------------------------------------

    def _check_version(self) -> None:
        ref, version = self.ctrl.reference, self.ctrl.reference_version
        old_ref, old_version = self.last_ref
        if ref is not old_ref:  # every change of reference is a new version (plans go stale)
            assert version > old_version, (version, old_version)
        self.last_ref = (ref, version)

    @invariant()
    def reference_changes_bump_the_version(self) -> None:
        self._check_version()

    @invariant()
    def only_the_newest_goal_can_execute(self) -> None:
        active = self.ctrl.active_goal
        assert active is None or (active == self.last_accepted and active not in self.results)

    def teardown(self) -> None:
        if not hasattr(self, "ctrl") or sys.exc_info()[0] is not None:
            return  # a step failed: that error is the one to report
        if self.ctrl.active:
            self._deactivate(fault=False)
        assert not self._outstanding(), f"goals without a result: {self._outstanding()}"


GoalLifecycle.TestCase.settings = settings(
    max_examples=120,
    stateful_step_count=40,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
test_goal_lifecycle = GoalLifecycle.TestCase
