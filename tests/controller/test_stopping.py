"""Decelerating stops (issue 12 part B; upstream's decelerate_on_cancel, section 11.3).

Every test runs the controller on the simulated clock against the ideal mirror of conftest.
"Commanded velocity" is the velocity command (``position`` + ``velocity`` command interfaces):
the reference one period ahead, what the joints are told to have by the next cycle.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from jtc_hw import (
    ConfigurationError,
    ErrorCode,
    GoalStatus,
    JointTrajectory,
    TrajectoryPoint,
    TrajectoryStopped,
)
from jtc_hw.config.controller_file import config_to_dict
from jtc_hw.config.limits import JointLimits
from jtc_hw.config.reading import load_config
from jtc_hw.controller.outcomes import CANCELED_DECELERATING_DETAILS, CANCELED_DETAILS
from jtc_hw.controller.parameters import get_parameters
from jtc_hw.controller.stopping import (
    DERIVED_STOP_TIME_S,
    stop_decelerations,
    stop_phases,
    stop_unavailable_reason,
)

from conftest import MS, Rig, S, make_config

PV = ("position", "velocity")
RATE = 1000.0
T_S = 1.0 / RATE


def decel_config(decel: float = 5.0, **params: Any) -> Any:
    """Two joints, position + velocity commands, 1 kHz, decelerate_on_cancel with ``decel``."""
    constraints = params.pop("constraints", {})
    return make_config(
        command_interfaces=params.pop("command_interfaces", PV),
        update_rate=RATE,
        constraints={
            "decelerate_on_cancel": True,
            "j1": {"max_deceleration_on_cancel": decel},
            "j2": {"max_deceleration_on_cancel": decel},
            **constraints,
        },
        **params,
    )


def cruise_goal() -> JointTrajectory:
    """Both joints cruise at 3 rad/s (j1) and -2 rad/s (j2) between 1 s and 2 s: a quintic
    between points of equal velocity and zero acceleration whose positions differ by exactly
    velocity x time is a straight line, so a stop there starts with no reference acceleration."""
    return JointTrajectory(
        ("j1", "j2"),
        [
            TrajectoryPoint(1.0, [1.5, -1.0], [3.0, -2.0], [0.0, 0.0]),
            TrajectoryPoint(2.0, [4.5, -3.0], [3.0, -2.0], [0.0, 0.0]),
            TrajectoryPoint(3.0, [6.0, -4.0], [0.0, 0.0], [0.0, 0.0]),
        ],
    )


def run_stop(rig: Rig, cycles: int) -> tuple[np.ndarray, np.ndarray]:
    """Step ``cycles`` times; commanded velocities and measured positions, a row per cycle."""
    v, p = [], []
    for _ in range(cycles):
        out = rig.step()
        v.append(out.command.velocities.copy())
        p.append(rig.mirror.p.copy())
    return np.array(v), np.array(p)


def assert_ramps_to_rest(v: np.ndarray, decel: float | np.ndarray, v0: np.ndarray) -> None:
    """Every commanded velocity step is at most one period's worth of the deceleration, the
    magnitude never grows, and the joints end at rest."""
    bound = np.broadcast_to(np.asarray(decel, dtype=float) * T_S, v0.shape)
    steps = np.abs(np.diff(np.vstack([v0, v]), axis=0))
    assert (steps <= bound * (1 + 1e-9) + 1e-12).all(), steps.max(axis=0)
    assert (np.diff(np.abs(v), axis=0) <= 1e-12).all()
    assert (v[-1] == 0.0).all()
    assert np.isfinite(v).all()


# -- parameters ---------------------------------------------------------------------------------


def test_parameters_default_off_and_round_trip() -> None:
    plain = make_config()
    assert plain.constraints.decelerate_on_cancel is False
    assert plain.constraints.joints["j1"].max_deceleration_on_cancel == 0.0
    cfg = decel_config(4.0)
    assert cfg.constraints.decelerate_on_cancel is True
    assert cfg.constraints.joints["j2"].max_deceleration_on_cancel == 4.0
    assert load_config(config_to_dict(cfg)) == cfg
    values = get_parameters(cfg)
    assert values["constraints.decelerate_on_cancel"] is True
    assert values["constraints.j1.max_deceleration_on_cancel"] == 4.0


def test_parameters_are_read_only_and_checked() -> None:
    rig = Rig(decel_config(), [0.0, 0.0])
    with pytest.raises(ConfigurationError, match="read-only parameter.*decelerate_on_cancel"):
        rig.ctrl.set_parameters({"constraints.decelerate_on_cancel": False})
    with pytest.raises(ConfigurationError, match="read-only.*j1.max_deceleration_on_cancel"):
        rig.ctrl.set_parameters({"constraints.j1.max_deceleration_on_cancel": 1.0})
    with pytest.raises(ConfigurationError, match=r"constraints\.j1\.max_deceleration_on_cancel"):
        decel_config(-1.0)
    with pytest.raises(ConfigurationError, match=r"constraints\.decelerate_on_cancel"):
        make_config(constraints={"decelerate_on_cancel": "maybe"})
    changed = dataclasses.replace(
        rig.ctrl.config,
        constraints=dataclasses.replace(rig.ctrl.config.constraints, decelerate_on_cancel=False),
    )
    with pytest.raises(ConfigurationError, match="constraints.decelerate_on_cancel"):
        rig.ctrl.apply_parameters(changed)


def test_deceleration_derived_from_limits() -> None:
    cfg = make_config(
        command_interfaces=PV, update_rate=RATE,
        constraints={"decelerate_on_cancel": True, "j1": {"max_deceleration_on_cancel": 7.0}},
    )
    assert stop_decelerations(cfg) is None
    assert "j2" in (stop_unavailable_reason(cfg) or "")
    with_acc = dataclasses.replace(cfg, limits={"j2": JointLimits(velocity=2.0, acceleration=3.0)})
    np.testing.assert_array_equal(stop_decelerations(with_acc), [7.0, 3.0])
    with_vel = dataclasses.replace(cfg, limits={"j2": JointLimits(velocity=2.0)})
    np.testing.assert_array_equal(stop_decelerations(with_vel), [7.0, 2.0 / DERIVED_STOP_TIME_S])


def test_preconditions_fall_back_to_the_hold() -> None:
    no_velocity_state = decel_config(state_interfaces=["position"])
    assert "state_interfaces" in (stop_unavailable_reason(no_velocity_state) or "")
    off = decel_config(constraints={"decelerate_on_cancel": False})
    for cfg in (no_velocity_state, off):
        rig = Rig(cfg, [0.0, 0.0])
        goal = rig.ctrl.send_goal(rig.now, cruise_goal())
        rig.step(1500)
        assert rig.ctrl.cancel_goal(goal)
        rig.step()
        assert rig.ctrl.stopping_until_ns is None
        assert rig.ctrl.reference.breakpoints_ns == (rig.now - rig.period,)  # a plain hold
        assert rig.results(goal)[0].details == CANCELED_DETAILS


# -- each kind of stop decelerates ------------------------------------------------------------


def test_cancel_decelerates_within_the_bound() -> None:
    rig = Rig(decel_config(5.0), [0.0, 0.0])
    goal = rig.ctrl.send_goal(rig.now, cruise_goal())
    rig.step(1500)
    v_before = rig.last.command.velocities.copy()
    np.testing.assert_allclose(v_before, [3.0, -2.0])
    measured = rig.mirror.state()
    assert rig.ctrl.cancel_goal(goal)
    v, p = run_stop(rig, 700)
    # 3 rad/s at 5 rad/s^2: at rest after 0.6 s, 0.9 rad further on (upstream's hold point).
    assert_ramps_to_rest(v, 5.0, v_before)
    first_zero = int(np.flatnonzero((v == 0.0).all(axis=1))[0])
    assert first_zero <= math.ceil(0.6 / T_S)
    rest = measured.positions + np.sign(measured.velocities) * measured.velocities**2 / 10.0
    np.testing.assert_allclose(p[-1], rest, atol=1e-9)
    [result] = rig.results(goal)
    assert result.status is GoalStatus.CANCELED
    assert result.error_code is ErrorCode.SUCCESSFUL
    assert result.details == CANCELED_DECELERATING_DETAILS
    assert rig.ctrl.holding


def test_stop_starts_from_the_measured_state() -> None:
    """Upstream's p0, v0: the stop's sample at the stop time is the measured state."""
    rig = Rig(decel_config(5.0), [0.0, 0.0])
    goal = rig.ctrl.send_goal(rig.now, cruise_goal())
    rig.step(1234)
    measured = rig.mirror.state()
    rig.ctrl.cancel_goal(goal)
    rig.step()
    stop_start = rig.now - rig.period
    s = rig.ctrl.reference.sample(stop_start)
    np.testing.assert_array_equal(s.positions, measured.positions)
    np.testing.assert_array_equal(s.velocities, measured.velocities)
    assert rig.ctrl.stopping_until_ns == stop_start + round(3.0 / 5.0 * S)


def test_path_abort_decelerates() -> None:
    cfg = decel_config(6.0, constraints={"j1": {"trajectory": 0.05,
                                                "max_deceleration_on_cancel": 6.0}})
    rig = Rig(cfg, [0.0, 0.0])
    goal = rig.ctrl.send_goal(rig.now, cruise_goal())
    rig.step(1500)
    rig.mirror.p[0] -= 0.1  # the joint slips: path tolerance violated
    v_meas = rig.mirror.v.copy()
    out = rig.step()
    [result] = rig.results(goal)
    assert result.error_code is ErrorCode.PATH_TOLERANCE_VIOLATED
    assert rig.ctrl.stopping_until_ns is not None
    v, _ = run_stop(rig, 700)
    assert_ramps_to_rest(np.vstack([out.command.velocities, v]), 6.0, v_meas)


def test_goal_time_abort_decelerates() -> None:
    cfg = decel_config(5.0, constraints={"goal_time": 0.05, "j1": {
        "goal": 0.001, "max_deceleration_on_cancel": 5.0}})
    rig = Rig(cfg, [0.0, 0.0])
    goal = rig.ctrl.send_goal(rig.now, cruise_goal())
    rig.step(2800)
    rig.mirror.frozen = True  # j1 never arrives: measured velocity stays at its last value
    v_meas = rig.mirror.v.copy()
    assert abs(v_meas[0]) > 0.0
    rig.run_until(lambda out: bool(rig.results(goal)))
    [result] = rig.results(goal)
    assert result.error_code is ErrorCode.GOAL_TOLERANCE_VIOLATED
    assert rig.ctrl.stopping_until_ns is not None
    first = rig.last.command.velocities.copy()  # the abort cycle already commands the stop
    v, _ = run_stop(rig, 100)
    assert_ramps_to_rest(np.vstack([first, v]), 5.0, v_meas)


def test_cmd_timeout_and_empty_topic_trajectory_decelerate() -> None:
    # Velocity commands forwarded (the mirror integrates them): a streamed point's velocity is
    # kept after it (upstream), so the joints keep moving until cmd_timeout stops them.
    cfg = decel_config(5.0, cmd_timeout=0.2, command_interfaces=["velocity"],
                       open_loop_control=True)
    rig = Rig(cfg, [0.0, 0.0])
    rig.ctrl.send_trajectory(
        rig.now, JointTrajectory(("j1", "j2"), [TrajectoryPoint(0.5, [0.5, 0.0], [2.0, 0.0])])
    )
    rig.run_until(lambda out: any(isinstance(e, TrajectoryStopped) for e in out.events))
    assert rig.ctrl.stopping_until_ns is not None
    first = rig.last.command.velocities.copy()  # the timeout's cycle already commands the stop
    v, _ = run_stop(rig, 500)
    assert_ramps_to_rest(np.vstack([first, v]), 5.0, np.array([2.0, 0.0]))

    rig.ctrl.send_trajectory(
        rig.now, JointTrajectory(("j1", "j2"), [TrajectoryPoint(0.5, [1.5, 0.0], [2.0, 0.0])])
    )
    rig.step(500)
    v_meas = rig.mirror.v.copy()
    rig.ctrl.send_trajectory(rig.now, JointTrajectory(("j1", "j2"), []))  # stop
    v, _ = run_stop(rig, 500)
    assert rig.ctrl.stopping_until_ns is not None
    assert_ramps_to_rest(v, 5.0, v_meas)


def test_stop_for_shutdown_aborts_and_is_not_restarted() -> None:
    rig = Rig(decel_config(5.0), [0.0, 0.0])
    goal = rig.ctrl.send_goal(rig.now, cruise_goal())
    rig.step(1500)
    rig.ctrl.stop("daemon stopping: decelerating to a stop")
    assert rig.ctrl.stop_pending
    rig.step()
    [result] = rig.results(goal)
    assert result.status is GoalStatus.ABORTED
    assert result.error_code is ErrorCode.INVALID_GOAL
    assert result.error_string == "daemon stopping: decelerating to a stop"
    end = rig.ctrl.stopping_until_ns
    assert end is not None
    version = rig.ctrl.reference_version
    rig.step(10)
    rig.ctrl.stop("again")  # a stop under way goes on
    rig.step()
    assert rig.ctrl.reference_version == version
    assert rig.ctrl.stopping_until_ns == end
    rig.ctrl.request_stop()  # the stop op / an empty topic trajectory: the same
    rig.step()
    assert rig.ctrl.reference_version == version
    rig.step(round((end - rig.now) / rig.period) + 1)
    assert (rig.last.command.velocities == 0.0).all()
    assert len(rig.results()) == 1


def test_abort_from_outside_decelerates() -> None:
    """``abort`` (the daemon's API-stall guard) takes the same stop."""
    rig = Rig(decel_config(5.0), [0.0, 0.0])
    goal = rig.ctrl.send_goal(rig.now, cruise_goal())
    rig.step(1500)
    rig.ctrl.abort("nobody reads")
    v, _ = run_stop(rig, 700)
    assert_ramps_to_rest(v, 5.0, np.array([3.0, -2.0]))
    assert rig.results(goal)[0].error_string == "nobody reads"


# -- jerk-limited (beyond upstream) -----------------------------------------------------------


def test_jerk_limited_stop_is_an_s_curve() -> None:
    decel, jerk = 5.0, 40.0
    cfg = dataclasses.replace(
        decel_config(decel, command_interfaces=["position", "velocity", "acceleration"],
                     state_interfaces=["position", "velocity"]),
        limits={"j1": JointLimits(jerk=jerk), "j2": JointLimits(jerk=jerk)},
    )
    rig = Rig(cfg, [0.0, 0.0])
    goal = rig.ctrl.send_goal(rig.now, cruise_goal())
    rig.step(1500)
    v0 = rig.last.command.velocities.copy()
    a_before = rig.last.command.accelerations.copy()
    rig.ctrl.cancel_goal(goal)
    vs, accs = [], []
    for _ in range(900):
        out = rig.step()
        vs.append(out.command.velocities.copy())
        accs.append(out.command.accelerations.copy())
    v, a = np.array(vs), np.array(accs)
    assert_ramps_to_rest(v, decel, v0)
    a_steps = np.abs(np.diff(np.vstack([a_before, a]), axis=0))
    assert (a_steps <= jerk * T_S * (1 + 1e-9) + 1e-12).all()  # no acceleration step either
    assert (np.abs(a) <= decel * (1 + 1e-12)).all()
    assert (a[-1] == 0.0).all()
    # 3 rad/s: ramp 0.125 s to -5, hold, ramp 0.125 s back: 0.6 s + 0.125 s at rest.
    phases, _ = stop_phases(0.0, 3.0, 0.0, decel, jerk)
    assert phases[-1].end_s == pytest.approx(3.0 / decel + decel / jerk)
    first_zero = int(np.flatnonzero(v[:, 0] == 0.0)[0])
    assert first_zero <= math.ceil(phases[-1].end_s / T_S) + 1


@pytest.mark.parametrize(
    ("v0", "a0"), [(3.0, 0.0), (3.0, 4.0), (3.0, -5.0), (0.05, -4.0), (-0.2, 3.0), (0.0, 2.0)]
)
def test_s_curve_phases_end_at_rest(v0: float, a0: float) -> None:
    decel, jerk = 5.0, 40.0
    phases, rest = stop_phases(1.0, v0, a0, decel, jerk)
    state = (1.0, v0, min(max(a0, -decel), decel))
    for ph in phases:
        assert ph.position == pytest.approx(state[0], abs=1e-12)
        assert ph.velocity == pytest.approx(state[1], abs=1e-12)
        assert ph.acceleration == pytest.approx(state[2], abs=1e-12)
        assert abs(ph.jerk) in (0.0, jerk)
        dt = ph.end_s - ph.start_s
        state = (
            ph.position + ph.velocity * dt + ph.acceleration * dt**2 / 2 + ph.jerk * dt**3 / 6,
            ph.velocity + ph.acceleration * dt + ph.jerk * dt**2 / 2,
            ph.acceleration + ph.jerk * dt,
        )
        assert abs(ph.acceleration) <= decel + 1e-12
    assert state[1] == pytest.approx(0.0, abs=1e-9)
    assert state[2] == pytest.approx(0.0, abs=1e-9)
    assert rest == pytest.approx(state[0], abs=1e-12)


def test_the_stop_is_reported_as_a_reference_change() -> None:
    """The daemon replicates the reference by version: a stop is a new one, sent by value."""
    rig = Rig(decel_config(5.0), [0.0, 0.0])
    goal = rig.ctrl.send_goal(rig.now, cruise_goal())
    rig.step(1500)
    version = rig.ctrl.reference_version
    rig.ctrl.cancel_goal(goal)
    rig.step()
    assert rig.ctrl.reference_version == version + 1
    assert len(rig.ctrl.reference.breakpoints_ns) <= 3  # a few pieces, not one per period
    assert rig.ctrl.reference.state_before_ns == rig.now - rig.period
    assert rig.ctrl.reference.end_ns == rig.now - rig.period + 600 * MS


def test_check_warns_when_decelerate_on_cancel_falls_back() -> None:
    from jtc_hw.controller.parameters import explain

    assert not [w for w in explain(decel_config()) if "decelerate_on_cancel" in w]
    [warning] = [w for w in explain(decel_config(state_interfaces=["position"]))
                 if "decelerate_on_cancel" in w]
    assert "hold on the spot" in warning and "state_interfaces" in warning


def test_topic_path_violation_decelerates() -> None:
    cfg = decel_config(6.0, constraints={"j1": {"trajectory": 0.05,
                                                "max_deceleration_on_cancel": 6.0}})
    rig = Rig(cfg, [0.0, 0.0])
    rig.ctrl.send_trajectory(rig.now, cruise_goal())
    rig.step(1500)
    rig.mirror.p[0] -= 0.1  # the joint slips: path tolerance violated
    v_meas = rig.mirror.v.copy()
    out = rig.step()
    [stopped] = [e for e in out.events if isinstance(e, TrajectoryStopped)]
    assert stopped.reason == "Aborted due to path tolerance violation"
    assert rig.ctrl.stopping_until_ns is not None
    v, _ = run_stop(rig, 700)
    assert_ramps_to_rest(np.vstack([out.command.velocities, v]), 6.0, v_meas)


@pytest.mark.parametrize("factor", [0.5, 0.0])
def test_a_stop_runs_on_the_clock_whatever_the_speed_scaling(factor: float) -> None:
    """Sections 11.3 and 13 together: a decelerating stop starts from the measured velocity
    and decelerates at the configured rate on the clock, not in trajectory time, so neither
    a slowed-down goal (0.5) nor a pause (0: trajectory time stands still) stretches or
    freezes it; the factor set by the operator stays for the next command."""
    cfg = decel_config(5.0, speed_scaling={"ramp_time": 0.0})  # the factor steps
    rig = Rig(cfg, [0.0, 0.0])
    goal = rig.ctrl.send_goal(rig.now, cruise_goal())
    rig.step(1500)
    rig.ctrl.set_speed_scaling(0.5)
    rig.step(100)
    v_before = rig.last.command.velocities.copy()
    np.testing.assert_allclose(v_before, [1.5, -1.0])  # cruising at half speed
    measured = rig.mirror.state()
    rig.ctrl.set_speed_scaling(factor)
    assert rig.ctrl.cancel_goal(goal)
    v, p = run_stop(rig, 400)
    assert_ramps_to_rest(v, 5.0, measured.velocities)
    first_zero = int(np.flatnonzero((v == 0.0).all(axis=1))[0])
    assert first_zero <= math.ceil(1.5 / 5.0 / T_S) + 1  # 1.5 rad/s at 5 rad/s^2: 0.3 s
    rest = measured.positions + np.sign(measured.velocities) * measured.velocities**2 / 10.0
    np.testing.assert_allclose(p[-1], rest, atol=1e-6)
    assert rig.ctrl.speed_scaling_target == factor
