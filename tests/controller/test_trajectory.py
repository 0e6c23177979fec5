"""Trajectory sampling and replacement, including the reference's visualized examples.

The reference samples trajectories defined on a 0.5 s grid every 10 ms; we do the same and check
what each interpolation returns and the continuity it guarantees at the knots.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from jtc_hw import GoalRejected, JointTrajectory, Trajectory, TrajectoryPoint
from jtc_hw.controller.config import ControllerConfig
from jtc_hw.controller.goals import ErrorCode
from jtc_hw.controller.interpolation import SegmentKind, evaluate
from jtc_hw.controller.validation import prepare

from conftest import MS, S, frange, kinds_at, make_config

T0 = 7 * S
GRID = [0.5, 1.0, 1.5, 2.0]
POS = [1.0, 2.0, 1.5, 0.5]
VEL = [1.0, 0.5, -1.0, 0.0]
ACC = [0.5, -1.0, 0.0, 1.0]


def one_joint(**params: Any) -> ControllerConfig:
    params.setdefault("allow_integration_in_goal_trajectories", True)
    return make_config(joints=("j",), **params)


def build(
    config: ControllerConfig,
    points: list[TrajectoryPoint],
    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
    now: int = T0,
    start_time_ns: int = 0,
    base: Trajectory | None = None,
) -> Trajectory:
    names = config.joints
    if base is None:
        n = len(names)
        base = Trajectory.constant(now, [start[0]] * n, [start[1]] * n, [start[2]] * n)
    msg = JointTrajectory(names, points, start_time_ns)
    return base.splice(
        now, prepare(config, msg), config.interpolation_method, np.array(config.wraparound)
    )


def pts(
    pos: list[float] | None = None,
    vel: list[float] | None = None,
    acc: list[float] | None = None,
    times: list[float] = GRID,
) -> list[TrajectoryPoint]:
    return [
        TrajectoryPoint(
            t,
            None if pos is None else [pos[i]],
            None if vel is None else [vel[i]],
            None if acc is None else [acc[i]],
        )
        for i, t in enumerate(times)
    ]


def samples(traj: Trajectory, end_s: float = 2.5) -> list[tuple[int, Any]]:
    return [(t, traj.sample(t)) for t in frange(T0, T0 + round(end_s * S), 10 * MS)]


def jumps(traj: Trajectory, knot_times: list[int]) -> np.ndarray:
    """|right - left| of position, velocity, acceleration at each knot (left = 1 ns before)."""
    out = []
    for t in knot_times:
        left, right = traj.sample(t - 1), traj.sample(t)
        out.append(
            [
                abs(right.positions[0] - left.positions[0]),
                abs(right.velocities[0] - left.velocities[0]),
                abs(right.accelerations[0] - left.accelerations[0]),
            ]
        )
    return np.array(out)


KNOTS = [T0 + round(t * S) for t in GRID]
INNER = KNOTS[:-1]  # the last knot ends the motion: the hold after it has zero velocity


def test_linear_when_only_positions_given() -> None:
    traj = build(one_joint(), pts(pos=POS))
    for t, p in zip(KNOTS, POS):
        assert traj.sample(t).positions[0] == p  # exact at the knots
    # Between knots: straight line, constant velocity, zero acceleration.
    s = traj.sample(T0 + 750 * MS)
    assert s.positions[0] == pytest.approx(1.5)
    assert s.velocities[0] == pytest.approx(2.0)
    assert s.accelerations[0] == 0.0
    assert kinds_at(traj, T0 + 750 * MS)[0] == SegmentKind.LINEAR
    j = jumps(traj, INNER)
    assert j[:, 0].max() < 1e-6  # C0
    assert j[:, 1].max() > 0.5  # velocity is not continuous: linear only guarantees C0
    for _, s in samples(traj):
        assert np.isfinite(s.positions).all() and np.isfinite(s.velocities).all()


def test_cubic_when_positions_and_velocities_given() -> None:
    traj = build(one_joint(), pts(pos=POS, vel=VEL))
    for t, p, v in zip(KNOTS, POS, VEL):
        s = traj.sample(t)
        assert (s.positions[0], s.velocities[0]) == (p, v)
    assert kinds_at(traj, T0 + 600 * MS)[0] == SegmentKind.CUBIC
    j = jumps(traj, INNER)
    assert j[:, :2].max() < 1e-6  # C1
    assert j[:, 2].max() > 0.1  # acceleration is not continuous for cubic


def test_quintic_when_positions_velocities_accelerations_given() -> None:
    traj = build(one_joint(), pts(pos=POS, vel=VEL, acc=ACC))
    for t, p, v, a in zip(INNER, POS, VEL, ACC):
        s = traj.sample(t)
        assert (s.positions[0], s.velocities[0], s.accelerations[0]) == (p, v, a)
    assert traj.sample(KNOTS[-1]).positions[0] == POS[-1]  # then held
    assert kinds_at(traj, T0 + 600 * MS)[0] == SegmentKind.QUINTIC
    assert jumps(traj, INNER).max() < 1e-6  # C2


def heun(start_p: float, vel: list[float], acc: list[float] | None) -> tuple[list, list]:
    p, v, a, t = start_p, 0.0, 0.0, 0.0
    ps, vs = [], []
    for i, tk in enumerate(GRID):
        dt = tk - t
        ak = acc[i] if acc is not None else 0.0
        vk = vel[i] if vel is not None else v + (a + ak) * 0.5 * dt
        p = p + (v + vk) * 0.5 * dt
        ps.append(p)
        vs.append(vk)
        v, a, t = vk, ak, tk
    return ps, vs


def test_velocity_only_integrates_by_heun_and_equals_position_velocity_input() -> None:
    config = one_joint()
    from_vel = build(config, pts(vel=VEL))
    ps, _ = heun(0.0, VEL, None)
    explicit = build(config, pts(pos=ps, vel=VEL))
    for (_, a), (_, b) in zip(samples(from_vel), samples(explicit)):
        np.testing.assert_allclose(a.positions, b.positions, atol=1e-12)
        np.testing.assert_allclose(a.velocities, b.velocities, atol=1e-12)
    assert jumps(from_vel, INNER)[:, :2].max() < 1e-6  # cubic: C1


def test_acceleration_only_integrates_by_heun_and_equals_full_input() -> None:
    config = one_joint()
    from_acc = build(config, pts(acc=ACC))
    ps, vs = heun(0.0, None, ACC)  # type: ignore[arg-type]
    explicit = build(config, pts(pos=ps, vel=vs, acc=ACC))
    for (_, a), (_, b) in zip(samples(from_acc), samples(explicit)):
        np.testing.assert_allclose(a.positions, b.positions, atol=1e-12)
    assert kinds_at(from_acc, T0 + 600 * MS)[0] == SegmentKind.QUINTIC
    assert jumps(from_acc, INNER).max() < 1e-6  # C2


def test_velocity_and_acceleration_only_is_quintic() -> None:
    traj = build(one_joint(), pts(vel=VEL, acc=ACC))
    assert kinds_at(traj, T0 + 600 * MS)[0] == SegmentKind.QUINTIC
    assert jumps(traj, INNER).max() < 1e-6


def test_nonzero_initial_point_is_the_lead_in_start() -> None:
    traj = build(one_joint(), pts(pos=POS, vel=VEL, acc=ACC), start=(-1.0, 0.5, 0.0))
    s = traj.sample(T0)
    assert (s.positions[0], s.velocities[0], s.accelerations[0]) == (-1.0, 0.5, 0.0)
    assert jumps(traj, INNER).max() < 1e-6  # smooth from the initial point on


def test_first_point_at_zero_means_no_lead_in() -> None:
    times = [0.0, 0.5, 1.0, 1.5]
    traj = build(one_joint(), pts(pos=POS, vel=VEL, acc=ACC, times=times), start=(-1.0, 0, 0))
    s = traj.sample(T0)
    assert (s.positions[0], s.velocities[0], s.accelerations[0]) == (POS[0], VEL[0], ACC[0])
    assert traj.breakpoints_ns[0] == T0


def test_inconsistent_points_splines_overshoot_none_returns_given_points() -> None:
    pos, vel, acc = [1.0, 1.0, 0.0, 0.0], [3.0, -3.0, 3.0, 0.0], [0.0, 0.0, 0.0, 0.0]
    spline = build(one_joint(), pts(pos=pos, vel=vel, acc=acc))
    none = build(one_joint(interpolation_method="none"), pts(pos=pos, vel=vel, acc=acc))
    spline_p = [s.positions[0] for _, s in samples(spline)]
    assert max(spline_p) > 1.2  # overshoots to honour the velocities
    none_p = {s.positions[0] for _, s in samples(none)}
    assert none_p <= {0.0, 1.0}  # only the initial point and the given points


def test_none_method_gives_the_next_point() -> None:
    """Upstream section 4.6: the state before during the lead-in, the raw point i + 1 during
    segment i (already at point 0's own time), the last point after the end (issue 11; this
    test asserted a zero-order hold before)."""
    traj = build(
        one_joint(interpolation_method="none", allow_nonzero_velocity_at_trajectory_end=True),
        pts(pos=POS, vel=VEL[:3] + [0.5], acc=ACC),
        start=(0.25, 0.0, 0.0),
    )
    for probe in (T0, T0 + 100 * MS, KNOTS[0] - 1):  # lead-in: the state before
        s = traj.sample(probe)
        assert (s.positions[0], s.velocities[0], s.accelerations[0]) == (0.25, 0.0, 0.0)
    for i, t in enumerate(KNOTS[:-1]):
        for probe in (t, t + 250 * MS, KNOTS[i + 1] - 1):
            s = traj.sample(probe)
            expected = (POS[i + 1], [*VEL[:3], 0.5][i + 1], ACC[i + 1])
            assert (s.positions[0], s.velocities[0], s.accelerations[0]) == expected
    for probe in (KNOTS[-1], KNOTS[-1] + 10 * S):
        s = traj.sample(probe)
        assert (s.positions[0], s.velocities[0], s.accelerations[0]) == (POS[-1], 0.5, ACC[-1])


def test_after_last_point_keeps_its_velocity_and_acceleration() -> None:
    """Upstream section 4.3 step 6: past the end the reference is the last point as given, its
    velocity and acceleration kept, not decaying (issue 11; this test asserted a zero-velocity
    hold before)."""
    traj = build(
        one_joint(allow_nonzero_velocity_at_trajectory_end=True),
        pts(pos=POS, vel=VEL[:3] + [2.0], acc=ACC[:3] + [-0.5]),
    )
    for t in (KNOTS[-1], KNOTS[-1] + 1, KNOTS[-1] + 100 * S):
        s = traj.sample(t)
        assert (s.positions[0], s.velocities[0], s.accelerations[0]) == (POS[-1], 2.0, -0.5)
    assert traj.end_ns == KNOTS[-1]


def test_after_last_point_absent_fields_are_zero() -> None:
    """Upstream section 4.3 step 6: absent velocities and accelerations of the last point are
    0 past the end (a linear last segment's slope does not carry over)."""
    traj = build(one_joint(), pts(pos=POS))
    assert traj.sample(KNOTS[-1] - 1).velocities[0] != 0.0
    s = traj.sample(KNOTS[-1] + 5 * S)
    assert (s.positions[0], s.velocities[0], s.accelerations[0]) == (POS[-1], 0.0, 0.0)


def test_sampling_before_the_state_before_time_fails() -> None:
    """Upstream section 4.3 step 3: sampling before the time of the state before the
    trajectory fails (issue 11; this test expected the start state before)."""
    traj = build(one_joint(), pts(pos=POS), start=(0.25, 0.0, 0.0))
    assert traj.state_before_ns == T0
    assert traj.sample(T0).positions[0] == 0.25
    for t in (T0 - 1, T0 - 5 * S):
        with pytest.raises(ValueError, match=f"at {t} ns: it is defined from {T0} ns"):
            traj.sample(t)


def test_sample_is_pure() -> None:
    traj = build(one_joint(), pts(pos=POS, vel=VEL, acc=ACC))
    times = [t for t, _ in samples(traj)]
    forward = [traj.sample(t).positions[0] for t in times]
    rng = np.random.default_rng(1)
    order = rng.permutation(len(times))
    shuffled = {times[i]: traj.sample(times[i]).positions[0] for i in order}
    assert forward == [shuffled[t] for t in times]


def test_each_sample_is_its_segment_polynomial_whatever_the_order_of_times() -> None:
    """``sample`` remembers the segment and the sample of its last call (the loop samples at
    now and a period ahead, segment after segment): every order of times -- the next segment,
    a skip, a breakpoint exactly, backwards, the same time twice -- gives each time's own
    segment polynomial, to the bit, in read-only arrays."""
    times_s = [0.01 * k for k in range(1, 41)]
    traj = build(
        one_joint(),
        pts(pos=[math.sin(t) for t in times_s], vel=[math.cos(t) for t in times_s],
            times=times_s),
    )
    breaks, blocks, origins, _, _ = traj.pieces()
    end = int(breaks[-1])
    rng = np.random.default_rng(24)
    walk = [int(b) for b in breaks[:-1]]  # every breakpoint exactly, in order
    walk += list(range(T0, end, 7 * MS))  # segment after segment, and skips
    walk += [int(t) for t in rng.integers(T0, end, 200)]  # anywhere, backwards too
    walk += [walk[-1], walk[-1], int(breaks[5]) - 1, int(breaks[5]), int(breaks[6]) - 1]
    for t in walk:
        got = traj.sample(t)
        i = int(breaks.searchsorted(t, side="right")) - 1
        want = evaluate(blocks[i], (t - origins[i]) * 1e-9)
        assert np.array_equal(np.stack(got), want), t
        assert not any(field.flags.writeable for field in got)


def test_effort_is_linear_feed_forward() -> None:
    config = make_config(
        joints=("j",), command_interfaces=("effort",), state_interfaces=("position", "velocity")
    )
    points = [TrajectoryPoint(0.5, [1.0], effort=[2.0]), TrajectoryPoint(1.0, [1.0], effort=[4.0])]
    traj = build(config, points)
    assert traj.sample(T0 + 250 * MS).effort[0] == pytest.approx(1.0)  # ramp from 0 at start
    assert traj.sample(T0 + 750 * MS).effort[0] == pytest.approx(3.0)
    assert traj.sample(T0 + 5 * S).effort[0] == 4.0  # held after the end


# -- replacement: the four scenarios of the reference's figures ----------------------------------

RED = [TrajectoryPoint(t, [p]) for t, p in ((1.0, 1.0), (2.0, 2.0), (3.0, 0.5))]


def test_replacement_from_hold_with_future_start() -> None:
    """Figure 1: holding; a trajectory with a future start. The hold lasts until its start."""
    config = one_joint()
    hold = Trajectory.constant(T0, [0.3])
    start = T0 + 2 * S
    traj = build(config, RED, now=T0, start_time_ns=start, base=hold)
    for t in frange(T0, start, 100 * MS):
        assert traj.sample(t).positions[0] == 0.3  # still holding before traj start
    assert traj.sample(start + 1 * S).positions[0] == 1.0
    assert traj.sample(start + 3 * S).positions[0] == 0.5
    assert traj.sample(start + 30 * S).positions[0] == 0.5  # last point held


def _executing_red(config: ControllerConfig) -> Trajectory:
    return build(config, RED, now=T0, base=Trajectory.constant(T0, [0.0]))


GREEN = [TrajectoryPoint(t, [p]) for t, p in ((1.0, -1.0), (2.0, -0.5))]


def test_replacement_with_future_start_keeps_current_until_then() -> None:
    config = one_joint()
    red = _executing_red(config)
    now, start = T0 + 500 * MS, T0 + 1500 * MS
    green = build(config, GREEN, now=now, start_time_ns=start, base=red)
    for t in frange(now, start, 50 * MS):
        np.testing.assert_array_equal(green.sample(t).positions, red.sample(t).positions)
    assert green.sample(start + 1 * S).positions[0] == -1.0
    assert green.sample(start + 2 * S).positions[0] == -0.5
    assert jumps(green, [start])[0, 0] < 1e-6  # bridge starts where red was


def test_replacement_with_zero_start_starts_now() -> None:
    config = one_joint()
    red = _executing_red(config)
    now = T0 + 500 * MS
    green = build(config, GREEN, now=now, base=red)
    np.testing.assert_array_equal(green.sample(now).positions, red.sample(now).positions)
    assert green.sample(now + 1 * S).positions[0] == -1.0
    assert green.sample(now + 2 * S).positions[0] == -0.5
    assert green.end_ns == now + 2 * S


def test_replacement_with_past_start_discards_past_points() -> None:
    """Last figure: start and first waypoint in the past; only the second is realized."""
    config = one_joint()
    red = _executing_red(config)
    now = T0 + 1500 * MS
    start = now - 1200 * MS  # first green point due at now - 0.2 s, second at now + 0.8 s
    green = build(config, GREEN, now=now, start_time_ns=start, base=red)
    assert green.sample(now).positions[0] == pytest.approx(red.sample(now).positions[0])
    positions = [green.sample(t).positions[0] for t in frange(now, now + 800 * MS, 10 * MS)]
    assert -1.0 not in positions  # the discarded waypoint is never targeted
    assert green.sample(now + 800 * MS).positions[0] == -0.5


def test_replacement_with_all_points_in_past_is_rejected() -> None:
    config = one_joint()
    red = _executing_red(config)
    now = T0 + 5 * S
    with pytest.raises(GoalRejected) as info:
        build(config, GREEN, now=now, start_time_ns=T0, base=red)
    assert info.value.error_code == ErrorCode.OLD_HEADER_TIMESTAMP
    assert "past" in info.value.reason and "3.000000 s before now" in info.value.reason


def test_partial_goal_keeps_other_joints_on_their_trajectory() -> None:
    config = make_config(allow_partial_joints_goal=True)
    both = JointTrajectory(("j1", "j2"), [TrajectoryPoint(2.0, [1.0, 2.0])])
    base = Trajectory.constant(T0, [0.0, 0.0])
    wrap = np.array(config.wraparound)
    first = base.splice(T0, prepare(config, both), "splines", wrap)
    now = T0 + 500 * MS
    only_j2 = JointTrajectory(("j2",), [TrajectoryPoint(1.0, [-1.0])])
    second = first.splice(now, prepare(config, only_j2), "splines", wrap)
    for t in frange(now, T0 + 4 * S, 50 * MS):
        assert second.sample(t).positions[0] == pytest.approx(first.sample(t).positions[0])
    assert second.sample(now + 1 * S).positions[1] == -1.0
    assert second.end_ns == T0 + 2 * S  # j1 is still moving until then


# -- continuous joints -------------------------------------------------------------------------


def wrapping(**params: Any) -> ControllerConfig:
    return make_config(joints=("j",), gains={"j": {"angle_wraparound": True}}, **params)


@pytest.mark.parametrize(
    ("start", "target", "expected_end"),
    [
        (3.1, -3.1, 2 * math.pi - 3.1),  # across +pi: short way up, not -6.2 rad
        (-3.1, 3.1, 3.1 - 2 * math.pi),  # across -pi: short way down
        (0.0, 2 * math.pi + 0.5, 0.5),  # a full turn too many in the goal
        (0.0, 1.0, 1.0),  # nothing to wrap
    ],
)
def test_wraparound_takes_the_short_way_without_a_step(
    start: float, target: float, expected_end: float
) -> None:
    traj = build(wrapping(), [TrajectoryPoint(1.0, [target])], start=(start, 0, 0))
    assert traj.sample(T0).positions[0] == start  # no step: starts where the joint is
    end = traj.sample(T0 + 1 * S).positions[0]
    assert end == pytest.approx(expected_end)
    travel = max(abs(traj.sample(t).positions[0] - start) for t in frange(T0, T0 + S, 10 * MS))
    assert travel <= math.pi + 1e-9


def test_wraparound_tie_at_pi_follows_raw_direction() -> None:
    up = build(wrapping(), [TrajectoryPoint(1.0, [math.pi])], start=(0.0, 0, 0))
    down = build(wrapping(), [TrajectoryPoint(1.0, [-math.pi])], start=(0.0, 0, 0))
    assert up.sample(T0 + S).positions[0] == pytest.approx(math.pi)
    assert down.sample(T0 + S).positions[0] == pytest.approx(-math.pi)


def test_non_continuous_joint_is_never_wrapped() -> None:
    traj = build(make_config(joints=("j",)), [TrajectoryPoint(1.0, [-3.1])], start=(3.1, 0, 0))
    assert traj.sample(T0 + S).positions[0] == -3.1
