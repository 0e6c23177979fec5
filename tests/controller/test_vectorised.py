"""The vectorised validation and splicing against the scalar code they replaced.

``scalar_reference.py`` is the per-point implementation that defined the behaviour. Random
goals -- valid or broken in one of the ways a client can break them, given as points or as
``PointColumns``, spliced onto random references (holds, earlier goals, partial goals, starts
in the past and the future, plans kept from before now) -- must give:

- the same rejection (``GoalRejected`` with the same message and code) or none from both;
- bit-identical trajectories: breakpoints, every coefficient, origins, kinds and the final state.

Plus the edge cases whose code paths the vectorised code changed (runs of integrated points,
zero-length bridges, grids a partial goal splits, times at the end of the clock's range).
"""

from __future__ import annotations

import math
import re
from functools import cache
from typing import Any

import numpy as np
import pytest
import scalar_reference as scalar
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from jtc_hw import GoalRejected, JointTrajectory, Trajectory, TrajectoryPoint
from jtc_hw.controller.config import ControllerConfig
from jtc_hw.controller.messages import FIELDS, PointColumns
from jtc_hw.controller.trajectory import MAX_TIME_NS
from jtc_hw.controller.validation import prepare

from conftest import MS, S, make_config

JOINTS = tuple(f"j{i}" for i in range(1, 7))

SETTINGS = settings(
    max_examples=300,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

value = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False, allow_subnormal=False)


@cache
def config(
    n: int,
    integrate: bool,
    effort: bool,
    partial: bool,
    method: str,
    nonzero_end: bool,
) -> ControllerConfig:
    return make_config(
        joints=JOINTS[:n],
        command_interfaces=("effort",) if effort else ("position",),
        allow_integration_in_goal_trajectories=integrate,
        allow_partial_joints_goal=partial,
        interpolation_method=method,
        allow_nonzero_velocity_at_trajectory_end=nonzero_end,
    )


@st.composite
def configs(draw: st.DrawFn, n: int | None = None) -> ControllerConfig:
    method = draw(st.sampled_from(["splines", "splines", "none"]))
    return config(
        draw(st.integers(1, 6)) if n is None else n,
        draw(st.booleans()),
        draw(st.booleans()),
        draw(st.booleans()),
        method,
        draw(st.booleans()),
    )


# Field combinations of a point: p(ositions), v(elocities), a(ccelerations), e(ffort).
COMBOS = ("p", "pv", "pva", "v", "a", "va", "pa", "")


@st.composite
def goals(draw: st.DrawFn, cfg: ControllerConfig, valid: bool) -> JointTrajectory:
    """A goal for ``cfg``: valid ones use what it accepts; others may break any rule."""
    n = len(cfg.joints)
    k = draw(st.integers(1, n)) if cfg.allow_partial_joints_goal else n
    names = draw(st.permutations(cfg.joints))[:k]
    m = draw(st.integers(1, 12))
    times = sorted(draw(st.sets(st.integers(0, 4000), min_size=m, max_size=m)))
    step_ms = draw(st.sampled_from([1, 1, 7]))
    times = [t * step_ms for t in times]
    effort = "effort" in cfg.command_interfaces
    if valid:
        allowed = ["p", "pv", "pva"]
        if cfg.allow_integration_in_goal_trajectories and cfg.interpolation_method != "none":
            allowed += ["v", "a", "va"]
        combos = (
            [draw(st.sampled_from(allowed))] * m
            if draw(st.booleans())
            else draw(st.lists(st.sampled_from(allowed), min_size=m, max_size=m))
        )
        combos = [c + ("e" if effort else "") for c in combos]
    else:
        combos = draw(st.lists(st.sampled_from(COMBOS), min_size=m, max_size=m))
        combos = [c + ("e" if draw(st.booleans()) else "") for c in combos]
    points = []
    for t, combo in zip(times, combos):
        fields: dict[str, Any] = {}
        for letter, name in zip("pvae", FIELDS):
            if letter in combo:
                fields[name] = draw(st.lists(value, min_size=k, max_size=k))
        if valid and not cfg.allow_nonzero_velocity_at_trajectory_end and t == times[-1]:
            if "velocities" in fields:
                fields["velocities"] = [0.0] * k
        points.append(TrajectoryPoint(time_from_start_ns=t * MS, **fields))
    if not valid:
        points = draw(broken(points, k))
    start = draw(st.sampled_from([0, 0, 5 * S, 10 * S - 1500 * MS, 10 * S + 300 * MS]))
    return JointTrajectory(names, points, start)


@st.composite
def broken(draw: st.DrawFn, points: list[TrajectoryPoint], k: int) -> list[TrajectoryPoint]:
    """The points with zero to two of the mistakes a client can make."""
    for _ in range(draw(st.integers(0, 2))):
        i = draw(st.integers(0, len(points) - 1))
        p = points[i]
        fields = {name: getattr(p, name) for name in FIELDS}
        t = p.time_from_start_ns
        how = draw(
            st.sampled_from(["value", "length", "time", "negative", "huge_time", "drop"])
        )
        name = draw(st.sampled_from(FIELDS))
        if how == "value":
            bad = draw(
                st.sampled_from(
                    [math.nan, math.inf, -math.inf, True, "1.0", None, 10**400, 2**60]
                    + [np.float64(1.5), np.float32(0.5), np.int64(3)]
                )
            )
            row = list(fields[name] or [0.0] * k)
            row[draw(st.integers(0, len(row) - 1))] = bad  # a row made shorter before
            fields[name] = row
        elif how == "length":
            fields[name] = [0.5] * draw(st.sampled_from([k - 1, k + 1])) or None
        elif how == "time":
            t = points[i - 1].time_from_start_ns if i else t
        elif how == "negative":
            t = -t - 1
        elif how == "huge_time":
            t = MAX_TIME_NS + 1 + t
        else:
            fields[name] = None
        points[i] = TrajectoryPoint(time_from_start_ns=t, **fields)
    return points


def as_columns(msg: JointTrajectory) -> JointTrajectory | None:
    """The same goal with ``PointColumns``, when its points make regular float arrays."""
    k = len(msg.joint_names)
    arrays: dict[str, Any] = {}
    present: dict[str, np.ndarray] = {}
    for name in FIELDS:
        given = [getattr(p, name) for p in msg.points]
        if all(v is None for v in given):
            continue
        if any(v is not None and len(v) != k for v in given):
            return None
        if any(type(x) is not float for v in given if v is not None for x in v):
            return None
        arrays[name] = np.array([v if v is not None else [7.0] * k for v in given], dtype=float)
        present[name] = np.array([v is not None for v in given])
    times = [p.time_from_start_ns for p in msg.points]
    if max(times) > MAX_TIME_NS or min(times) < -MAX_TIME_NS - 1:  # not int64
        return None
    columns = PointColumns(times, present=present, **arrays)
    return JointTrajectory(msg.joint_names, columns, msg.start_time_ns)


def outcome(fn: Any, *args: Any) -> Any:
    """What ``fn(*args)`` gives: ("ok", value) or ("rejected", reason, code)."""
    try:
        return ("ok", fn(*args))
    except GoalRejected as exc:
        return ("rejected", exc.reason, exc.error_code)


def assert_same_prepared(new: Any, old: Any) -> None:
    assert new.joint_indices.tolist() == old.joint_indices.tolist()
    assert new.start_time_ns == old.start_time_ns
    assert new.times_ns.dtype == np.int64 and new.times_ns.tolist() == list(old.times_ns)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(new, name), getattr(old, name), err_msg=name)
        flags = getattr(new, f"has_{name}")
        assert flags.dtype == bool and flags.tolist() == list(getattr(old, f"has_{name}"))


def assert_bit_identical(new: Trajectory, old: Any) -> None:
    assert new.breakpoints_ns == tuple(old._breaks)
    for mine, theirs in (
        (new._blocks, old._blocks),
        (new._origins, old._origins),
        (new._kinds, old._kinds),
        (new._final, old._final),
    ):
        assert mine.dtype == theirs.dtype and mine.shape == theirs.shape
        assert mine.tobytes() == theirs.tobytes()


# -- validation -----------------------------------------------------------------------------


@SETTINGS
@given(data=st.data())
def test_prepare_accepts_and_rejects_exactly_as_the_scalar_code(data: st.DataObject) -> None:
    cfg = data.draw(configs())
    msg = data.draw(goals(cfg, valid=data.draw(st.booleans())))
    try:
        old = outcome(scalar.prepare, cfg, msg)
    except (OverflowError, TypeError, ValueError) as exc:  # the scalar code's crashes
        beyond = [i for i, p in enumerate(msg.points) if p.time_from_start_ns > MAX_TIME_NS]
        if beyond:
            # New: a time beyond the clock's range is refused at its point, which can come
            # before the value the scalar code crashed on (an int too large for a float).
            new = outcome(prepare, cfg, msg)
            if new[0] == "rejected" and "beyond the controller clock's range" in new[1]:
                assert new[1].startswith(f"point #{beyond[0]}: time_from_start "), new
                return
        with pytest.raises(type(exc)):
            prepare(cfg, msg)
        return
    new = outcome(prepare, cfg, msg)
    beyond = [i for i, p in enumerate(msg.points) if p.time_from_start_ns > MAX_TIME_NS]
    if beyond and new[0] == "rejected" and "beyond the controller clock's range" in new[1]:
        # New: such a time is refused at its point (the scalar code let it through to crash
        # in the splice), unless the scalar code found an earlier point's problem first. The
        # effort rule ("no effort while other points do") is about the whole trajectory, found
        # after every point was read: it names the first point without effort, not a problem
        # of that point, so a bad time at any point comes first.
        assert new[1].startswith(f"point #{beyond[0]}: ")
        local = old[0] == "rejected" and "no effort while other points do" not in old[1]
        earlier = re.match(r"point #(\d+)", old[1]) if local else None
        assert earlier is None or int(earlier[1]) >= beyond[0], (new, old)
        return
    assert new[0] == old[0], (new, old)
    event(f"prepare: {old[0]}" + (f" ({old[1][:30]}...)" if old[0] == "rejected" else ""))
    if old[0] == "rejected":
        assert new[1:] == old[1:]
    else:
        assert_same_prepared(new[1], old[1])
    columns = as_columns(msg)
    if columns is not None:
        from_columns = outcome(prepare, cfg, columns)
        assert from_columns[0] == old[0]
        if old[0] == "rejected":
            assert from_columns[1:] == old[1:]
        else:
            assert_same_prepared(from_columns[1], old[1])


# -- splicing -------------------------------------------------------------------------------


@st.composite
def references(draw: st.DrawFn, n: int) -> tuple[Trajectory, Any]:
    """The same reference in both implementations: a (moving) hold, maybe with earlier goals
    spliced onto it."""
    state = [np.array(draw(st.lists(value, min_size=n, max_size=n))) for _ in range(4)]
    t0 = draw(st.integers(0, 9 * S))
    new = Trajectory.constant(t0, *state)
    old = scalar.Trajectory.constant(t0, *state)
    for _ in range(draw(st.integers(0, 2))):
        cfg = draw(configs(n))
        msg = draw(goals(cfg, valid=True))
        now = draw(st.integers(t0, 10 * S))
        wrap = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)))
        method = cfg.interpolation_method
        try:
            old_next = old.splice(now, scalar.prepare(cfg, msg), method, wrap)
        except GoalRejected:
            continue
        new, old = new.splice(now, prepare(cfg, msg), method, wrap), old_next
        assert_bit_identical(new, old)
    return new, old


@SETTINGS
@given(data=st.data())
def test_splice_gives_bit_identical_trajectories(data: st.DataObject) -> None:
    cfg = data.draw(configs())
    n = len(cfg.joints)
    new_ref, old_ref = data.draw(references(n))
    msg = data.draw(goals(cfg, valid=True))
    now = data.draw(st.integers(9 * S, 11 * S))
    keep_from = data.draw(st.one_of(st.none(), st.integers(now - 20 * MS, now + MS)))
    wrap = np.array(data.draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    use_wrap = data.draw(st.booleans())
    method = cfg.interpolation_method
    old = outcome(
        old_ref.splice, now, scalar.prepare(cfg, msg), method, wrap if use_wrap else None, keep_from
    )
    columns = as_columns(msg)
    for variant in (msg, columns) if columns is not None else (msg,):
        new = outcome(
            new_ref.splice, now, prepare(cfg, variant), method, wrap if use_wrap else None,
            keep_from,
        )
        assert new[0] == old[0], (new, old)
        event(f"splice: {old[0]}, {'columns' if variant is columns else 'points'}")
        if old[0] == "rejected":
            assert new[1:] == old[1:]
            continue
        assert_bit_identical(new[1], old[1])
        for t in data.draw(st.lists(st.integers(now - 30 * MS, now + 45 * S), max_size=20)):
            if t < new[1].state_before_ns:  # issue 11: not defined before it is installed
                with pytest.raises(ValueError, match="defined from"):
                    new[1].sample(t)
                continue
            for mine, theirs in zip(new[1].sample(t), old[1].sample(t)):
                assert mine.tobytes() == theirs.tobytes(), t


# -- edge cases of the vectorised code paths ------------------------------------------------


def splice_both(cfg: ControllerConfig, msg: JointTrajectory, now: int = 0) -> Trajectory:
    """Splice ``msg`` onto a hold at 0 with both implementations; check they agree."""
    n = len(cfg.joints)
    method = cfg.interpolation_method
    new = Trajectory.constant(0, np.zeros(n)).splice(now, prepare(cfg, msg), method)
    old = scalar.Trajectory.constant(0, np.zeros(n)).splice(
        now, scalar.prepare(cfg, msg), cfg.interpolation_method
    )
    assert_bit_identical(new, old)
    return new


def test_alternating_integrated_points_are_separate_runs() -> None:
    cfg = config(2, True, False, False, "splines", True)
    points = []
    for i in range(1, 41):
        fields = ["positions", "velocities", "accelerations"][i % 3]
        points.append(TrajectoryPoint(i * 0.01, **{fields: [0.1 * i, -0.2 * i]}))
    traj = splice_both(cfg, JointTrajectory(("j1", "j2"), points))
    assert len(traj.breakpoints_ns) == 41


def test_long_velocity_only_goal_integrates_in_one_run() -> None:
    cfg = config(2, True, False, False, "splines", True)
    t = np.arange(1, 3001) * 0.001
    points = [TrajectoryPoint(s, velocities=[math.sin(s), math.cos(s)]) for s in t]
    traj = splice_both(cfg, JointTrajectory(("j1", "j2"), points))
    # Heun's method over 3 s of sin/cos: 1 - cos(3) and sin(3), less the bridge's share (it
    # starts at rest, so its first millisecond averages the velocities 0 and cos(0.001)).
    expected = [1 - math.cos(3), math.sin(3) - 0.0005]
    np.testing.assert_allclose(traj.sample(traj.end_ns).positions, expected, atol=1e-6)


@pytest.mark.parametrize("fields", ["p", "pv", "pva"])
def test_a_long_goal_at_a_fixed_rate_fits_bit_identically(fields: str) -> None:
    """A goal of hundreds of segments with few distinct durations (a fixed rate, and the
    nanosecond rounding of its times) takes the path that raises each distinct duration once
    (``interpolation._powers``): the same bits as one ``pow`` per segment."""
    cfg = config(3, False, False, False, "splines", True)
    points = []
    for i in range(1, 1201):
        s = i * 0.004 + (0.002 if i > 600 else 0.0)  # 3 distinct durations, after rounding
        values = {"positions": [math.sin(s), math.cos(s), s]}
        if "v" in fields:
            values["velocities"] = [math.cos(s), -math.sin(s), 1.0]
        if "a" in fields:
            values["accelerations"] = [-math.sin(s), -math.cos(s), 0.0]
        points.append(TrajectoryPoint(s, **values))
    traj = splice_both(cfg, JointTrajectory(JOINTS[:3], points))
    assert len(traj.breakpoints_ns) == 1201


def test_first_point_due_at_the_splice_has_no_bridge() -> None:
    cfg = config(1, False, False, False, "splines", True)
    msg = JointTrajectory(("j1",), [TrajectoryPoint(0.0, [1.0]), TrajectoryPoint(1.0, [2.0])])
    traj = splice_both(cfg, msg, now=5 * S)
    assert traj.breakpoints_ns == (0, 5 * S, 6 * S)  # the hold, then the first point's segment
    assert traj.sample(5 * S).positions.tolist() == [1.0]


def test_single_point_due_at_the_splice_is_a_hold() -> None:
    cfg = config(1, False, False, False, "splines", True)
    traj = splice_both(cfg, JointTrajectory(("j1",), [TrajectoryPoint(0.0, [1.0])]), now=S)
    assert traj.breakpoints_ns == (0, S)
    assert traj.sample(S).positions.tolist() == [1.0]
    assert traj.sample(S).velocities.tolist() == [0.0]


def test_partial_goal_splits_the_other_joints_segments() -> None:
    cfg = config(3, False, False, True, "splines", True)
    first = JointTrajectory(JOINTS[:3], [TrajectoryPoint(s, [s, -s, 2 * s]) for s in (0.3, 0.7)])
    second = JointTrajectory(("j2",), [TrajectoryPoint(s, [s]) for s in (0.1, 0.2, 0.5, 0.9)])
    new = Trajectory.constant(0, np.zeros(3)).splice(0, prepare(cfg, first))
    old = scalar.Trajectory.constant(0, np.zeros(3)).splice(0, scalar.prepare(cfg, first))
    new = new.splice(150 * MS, prepare(cfg, second), keep_from_ns=140 * MS)
    old = old.splice(150 * MS, scalar.prepare(cfg, second), keep_from_ns=140 * MS)
    assert_bit_identical(new, old)


def test_time_beyond_the_clock_is_rejected_precisely() -> None:
    cfg = config(1, False, False, False, "splines", True)
    far = TrajectoryPoint(time_from_start_ns=MAX_TIME_NS + 1, positions=[1.0])
    with pytest.raises(GoalRejected, match=r"point #0: time_from_start .* beyond the controller"):
        prepare(cfg, JointTrajectory(("j1",), [far]))


def test_start_plus_time_beyond_the_clock_is_rejected_precisely() -> None:
    cfg = config(1, False, False, False, "splines", True)
    msg = JointTrajectory(("j1",), [TrajectoryPoint(10.0, [1.0])], MAX_TIME_NS - S)
    with pytest.raises(GoalRejected, match="beyond the controller clock's range") as info:
        Trajectory.constant(0, [0.0]).splice(0, prepare(cfg, msg))
    assert info.value.error_code == -1


def test_point_columns_are_the_points_they_stand_for() -> None:
    columns = PointColumns(
        [1 * MS, 2 * MS],
        positions=np.array([[1.0, 2.0], [3.0, 4.0]]),
        velocities=np.array([[0.5, 0.5], [9.0, 9.0]]),
        present={"velocities": np.array([True, False])},
    )
    points = (
        TrajectoryPoint(0.001, [1.0, 2.0], [0.5, 0.5]),
        TrajectoryPoint(0.002, [3.0, 4.0]),
    )
    assert len(columns) == 2 and bool(columns)
    assert columns[0] == points[0] and columns[-1] == points[1] and columns[:] == points
    assert columns == points and points == columns and tuple(columns) == points
    assert JointTrajectory(("a", "b"), columns) == JointTrajectory(("a", "b"), points)
    assert hash(JointTrajectory(("a", "b"), columns)) == hash(JointTrajectory(("a", "b"), points))
    assert type(columns[1].positions[0]) is float
    with pytest.raises(IndexError):
        columns[2]
    with pytest.raises(ValueError, match="positions must have shape"):
        PointColumns([0, 1], positions=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="without values"):
        PointColumns([0], present={"effort": np.array([True])})


def test_nbytes_is_what_a_copy_moves_and_can_be_told_in_advance() -> None:
    import pickle

    cfg = config(3, False, False, False, "splines", True)
    points = [TrajectoryPoint(0.1 * i, [i, -i, 0.5]) for i in range(1, 51)]
    msg = JointTrajectory(JOINTS[:3], points)
    traj = Trajectory.constant(0, np.zeros(3)).splice(0, prepare(cfg, msg))
    segments = len(traj.breakpoints_ns) - 1
    assert segments == 50 and traj.nbytes == Trajectory.nbytes_for(segments, 3)
    buffers: list[pickle.PickleBuffer] = []
    pickle.dumps(traj, protocol=5, buffer_callback=buffers.append)
    assert sum(b.raw().nbytes for b in buffers) == traj.nbytes  # all of it out of band
    assert Trajectory.constant(0, np.zeros(3)).nbytes == Trajectory.nbytes_for(0, 3)
