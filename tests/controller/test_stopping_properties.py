"""Property tests of decelerating stops (issue 12 part B): stops at random times.

A random goal runs on the simulated clock against the ideal mirror; at a random cycle it is
stopped by a random means (cancel, empty topic trajectory, ``stop`` as the daemon's shutdown,
``abort`` as its API-stall guard). With ``decelerate_on_cancel`` and random decelerations (and
jerk limits on some joints), every stop must: give the goal exactly one result; start from the
measured position and velocity; change the velocity by at most one period's worth of the
deceleration between cycles (and the acceleration by one period's worth of the jerk where a
jerk limit is set, with ``|a|`` never above the deceleration); be at rest by
``stopping_until_ns`` and stay there; and never command NaN.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

from jtc_hw import GoalResult, JointTrajectory, TrajectoryPoint
from jtc_hw.config.limits import JointLimits
from jtc_hw.controller.stopping import stop_duration_bound_s, stop_phases, stop_trajectory

from conftest import Rig, S, make_config

JOINTS = ("j1", "j2", "j3")
KINDS = ("cancel", "empty_topic", "stop", "abort")


@st.composite
def scenarios(draw: st.DrawFn) -> dict[str, object]:
    rate = draw(st.sampled_from([100.0, 250.0, 500.0, 1000.0]))
    interfaces = draw(st.sampled_from([
        ("position",), ("position", "velocity"), ("position", "velocity", "acceleration"),
    ]))
    decel = draw(st.lists(st.floats(0.5, 30.0), min_size=3, max_size=3))
    jerk = draw(st.lists(st.one_of(st.none(), st.floats(5.0, 500.0)), min_size=3, max_size=3))
    n_points = draw(st.integers(1, 4))
    times = sorted(draw(st.lists(st.integers(5, 300), min_size=n_points, max_size=n_points,
                                 unique=True)))
    points = [
        TrajectoryPoint(
            t / 100.0,
            draw(st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3)),
            draw(st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3))
            if i < n_points - 1 else [0.0, 0.0, 0.0],
        )
        for i, t in enumerate(times)
    ]
    stop_at_s = draw(st.floats(0.0, times[-1] / 100.0 + 0.2))
    return {
        "rate": rate, "interfaces": interfaces, "decel": decel, "jerk": jerk,
        "points": points, "stop_at_s": stop_at_s, "kind": draw(st.sampled_from(KINDS)),
    }


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios())
def test_stops_at_random_times(sc: dict[str, object]) -> None:
    note(repr(sc))
    rate = float(sc["rate"])  # type: ignore[arg-type]
    decel = np.array(sc["decel"])
    jerks = list(sc["jerk"])  # type: ignore[call-overload]
    cfg = make_config(
        JOINTS, command_interfaces=sc["interfaces"], update_rate=rate,  # type: ignore[arg-type]
        constraints={
            "decelerate_on_cancel": True,
            **{j: {"max_deceleration_on_cancel": float(d)} for j, d in zip(JOINTS, decel)},
        },
    )
    cfg = dataclasses.replace(cfg, limits={
        j: JointLimits(jerk=jk) for j, jk in zip(JOINTS, jerks) if jk is not None
    })
    jerk = np.array([np.inf if jk is None else jk for jk in jerks])
    rig = Rig(cfg, [0.0, 0.0, 0.0])
    ctrl = rig.ctrl
    assert ctrl.decelerates
    # The jerk limits shape the stops; the goal itself is slowed to them (issue 12 part A
    # checks every goal against the limits), so it is still a random motion to stop from.
    goal = ctrl.send_goal(
        rig.now, JointTrajectory(JOINTS, sc["points"]), time_scaling="fit"  # type: ignore[arg-type]
    )
    rig.step(round(float(sc["stop_at_s"]) * rate))  # type: ignore[arg-type]
    kind = sc["kind"]
    executing = ctrl.active_goal == goal
    if kind == "cancel":
        ctrl.cancel_goal(goal)
    elif kind == "empty_topic":
        ctrl.send_trajectory(rig.now, JointTrajectory(JOINTS, []))
    elif kind == "stop":
        ctrl.stop("daemon stopping")
    else:
        ctrl.abort("nobody reads")
    measured = rig.mirror.state()
    stop_ns = rig.now
    out = rig.step()
    c = out.command
    fields = (c.positions, c.velocities, c.accelerations, c.effort)
    assert all(np.isfinite(f).all() for f in fields if f is not None)
    until = ctrl.stopping_until_ns
    if kind in ("abort", "cancel") and not executing:
        # Both do nothing once the goal has finished: nothing to stop.
        assert until is None and ctrl.holding
    else:
        assert until is not None
        ref = ctrl.reference
        assert ref.state_before_ns == stop_ns
        s0 = ref.sample(stop_ns)
        np.testing.assert_array_equal(s0.positions, measured.positions)
        moving = np.abs(measured.velocities) > 1.2e-7
        np.testing.assert_array_equal(s0.velocities[moving], measured.velocities[moving])
        period = rig.period
        grid = range(stop_ns, until + 3 * period, period)
        samples = [ref.sample(t) for t in grid]
        v = np.array([s.velocities for s in samples])
        a = np.array([s.accelerations for s in samples])
        p = np.array([s.positions for s in samples])
        assert np.isfinite(v).all() and np.isfinite(a).all() and np.isfinite(p).all()
        # Phase boundaries sit on the integer-nanosecond time base (docs/decisions.md 1): a
        # piece starts up to 0.5 ns from its exact time, which is worth one nanosecond of the
        # deceleration (and of the jerk) in the bounds.
        t_s = (period + 1) / S
        assert (np.abs(np.diff(v, axis=0)) <= decel * t_s * (1 + 1e-9) + 1e-12).all()
        assert (np.abs(a) <= decel * (1 + 1e-9)).all()
        limited = np.isfinite(jerk)
        if limited.any():
            steps = np.abs(np.diff(a[:, limited], axis=0))
            assert (steps <= jerk[limited] * t_s * (1 + 1e-9) + 1e-9).all()
        # Without a jerk limit the speed never grows. With one, an acceleration under way
        # must first be ramped down, which adds at most a0^2 / (2 J) to the speed.
        free = ~limited
        assert (np.diff(np.abs(v[:, free]), axis=0) <= 1e-9).all()
        if limited.any():
            a0 = np.minimum(np.abs(a[0, limited]), decel[limited])
            grow = a0 * a0 / (2 * jerk[limited])
            assert (np.abs(v[:, limited]) <= np.abs(v[0, limited]) + grow + 1e-9).all()
        rest = ref.sample(until)
        assert (rest.velocities == 0.0).all() and (rest.accelerations == 0.0).all()
        assert (p[-1] == rest.positions).all()
    rig.step(round((max(until or 0, rig.now) - rig.now) / rig.period) + 5)
    assert (np.abs(rig.last.command.positions - rig.mirror.p) < 1e-9).all()
    results = [e for e in rig.events if isinstance(e, GoalResult)]
    assert [r.goal_id for r in results] == [goal]


@settings(max_examples=200, deadline=None)
@given(
    st.floats(-5.0, 5.0), st.floats(-5.0, 5.0), st.floats(-20.0, 20.0),
    st.floats(0.5, 30.0), st.one_of(st.just(np.inf), st.floats(2.0, 1000.0)),
)
def test_the_stop_trajectory_follows_the_closed_form(
    p0: float, v0: float, a0: float, decel: float, jerk: float
) -> None:
    """``stop_trajectory`` (all joints at once) equals ``stop_phases`` (one joint, the
    documented closed form) at every phase boundary and at rest."""
    traj = stop_trajectory(
        0, np.array([p0]), np.array([v0]), np.array([a0]), np.array([decel]), np.array([jerk])
    )
    phases, rest = stop_phases(p0, v0, a0, decel, jerk)
    bound = stop_duration_bound_s(
        np.array([v0]), np.array([a0]), np.array([decel]), np.array([jerk])
    )
    assert traj.end_ns / S <= bound + 1e-9
    assert traj.sample(traj.end_ns + S).positions[0] == pytest.approx(rest, abs=1e-9)
    for ph in phases:
        t_ns = round(ph.start_s * S)
        if round(ph.end_s * S) == t_ns:
            continue  # shorter than a nanosecond: never sampled
        s = traj.sample(t_ns)
        assert s.positions[0] == pytest.approx(ph.position, abs=1e-6)
        assert s.velocities[0] == pytest.approx(ph.velocity, abs=1e-6)
        assert s.accelerations[0] == pytest.approx(ph.acceleration, abs=1e-6)
