"""Speed scaling and pause (issue 12 part C) on the simulated clock.

Pause at half of a goal on each command interface: the velocity ramps to 0 with no step larger
than a period's worth of the joint's acceleration limit, the joints stay within the path
tolerance, resume finishes the goal and exactly one result arrives. Also: upstream's time
mapping (trajectory time advances by the period times the factor; the goal is judged in it),
the default ramp without limits, and the parameters.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from jtc_hw import GoalStatus, JointTrajectory, JointTrajectoryController, TrajectoryPoint
from jtc_hw.config.limits import JointLimits
from jtc_hw.errors import ConfigurationError

from conftest import MS, Mirror, S, make_config

NAMES = ("j1", "j2")
ACCEL = {"j1": 4.0, "j2": 3.0}
"""Acceleration limits: above what the goal itself needs at full speed (checked below)."""
PATH_TOL = 0.05

INTERFACES: dict[str, dict[str, Any]] = {
    "position": {"command_interfaces": ("position",)},
    "position_velocity": {"command_interfaces": ("position", "velocity")},
    "position_velocity_acceleration": {
        "command_interfaces": ("position", "velocity", "acceleration"),
        "state_interfaces": ("position", "velocity", "acceleration"),
    },
    "velocity": {
        "command_interfaces": ("velocity",),
        "gains": {j: {"p": 20.0, "ff_velocity_scale": 1.0} for j in NAMES},
    },
    "effort": {
        "command_interfaces": ("effort",),
        "gains": {j: {"p": 400.0, "d": 40.0, "ff_velocity_scale": 0.0} for j in NAMES},
    },
}


def goal() -> JointTrajectory:
    return JointTrajectory(
        NAMES,
        [
            TrajectoryPoint(1.0, [0.5, -0.3], [0.6, -0.3]),
            TrajectoryPoint(2.0, [1.0, -0.5], [0.0, 0.0]),
        ],
    )


def config(interfaces: str, **extra: Any) -> Any:
    params: dict[str, Any] = {
        "constraints": {
            "goal_time": 1.0,
            **{j: {"trajectory": PATH_TOL, "goal": 0.01} for j in NAMES},
        },
        **INTERFACES[interfaces],
        **extra,
    }
    cfg = make_config(NAMES, **params)
    import dataclasses

    return dataclasses.replace(
        cfg, limits={j: JointLimits(acceleration=a) for j, a in ACCEL.items()}
    )


class Run:
    """A controller and ideal joints on the simulated clock, recording what moved."""

    def __init__(self, cfg: Any) -> None:
        self.ctrl = JointTrajectoryController(cfg)
        self.mirror = Mirror([0.0, 0.0])
        self.now = 10 * S
        self.period = round(S / cfg.update_rate)
        self.events: list[Any] = []
        self.desired_v: list[np.ndarray] = []
        self.actual_v: list[np.ndarray] = []
        self.commands: list[Any] = []
        self.states: list[Any] = []
        self.ctrl.activate(self.now, self.mirror.state())

    def step(self) -> Any:
        out = self.ctrl.update(self.now, self.period, self.mirror.state())
        self.events.extend(out.events)
        self.mirror.apply(out.command, self.period / S)
        self.desired_v.append(out.desired.velocities.copy())
        self.actual_v.append(self.mirror.v.copy())
        self.commands.append(out.command)
        self.states.append(out.state)
        self.now += self.period
        return out

    def until(self, predicate: Any, limit_s: float = 20.0) -> Any:
        for _ in range(int(limit_s * S / self.period)):
            out = self.step()
            if predicate(out):
                return out
        raise AssertionError("condition not reached within the simulated time limit")

    def results(self) -> list[Any]:
        from jtc_hw import GoalResult

        return [e for e in self.events if isinstance(e, GoalResult)]


def max_step(values: list[np.ndarray]) -> np.ndarray:
    return np.abs(np.diff(np.array(values), axis=0)).max(axis=0)  # type: ignore[no-any-return]


def test_the_goal_fits_the_limits_at_full_speed() -> None:
    """The bound asserted below is the limit: the goal alone must not need more."""
    run = Run(config("position"))
    run.ctrl.send_goal(run.now, goal())
    run.until(lambda out: bool(run.results()))
    dt = run.period / S
    steps = max_step(run.desired_v)
    assert (steps <= np.array([ACCEL[j] for j in NAMES]) * dt).all(), steps


@pytest.mark.parametrize("interfaces", list(INTERFACES))
def test_pause_at_half_ramps_to_rest_within_the_bound_and_resume_finishes(
    interfaces: str,
) -> None:
    run = Run(config(interfaces))
    gid = run.ctrl.send_goal(run.now, goal())
    run.until(lambda out: out.state.reference_time_from_start >= 1.0)
    start = len(run.desired_v) - 1
    run.ctrl.set_speed_scaling(0.0)
    run.until(lambda out: out.state.speed_scaling_factor == 0.0, limit_s=2.0)
    ramp_end = len(run.desired_v)
    for _ in range(50):  # stays paused
        run.step()
    dt = run.period / S
    bound = np.array([ACCEL[j] for j in NAMES]) * dt
    # The reference the joints are given ramps to rest: no step above the limit's worth of a
    # period (2 % for the reference's own change of acceleration within one period).
    steps = max_step(run.desired_v[start:])
    assert (steps <= bound * 1.02 + 1e-12).all(), (steps, bound)
    assert np.all(run.desired_v[-1] == 0.0)
    assert ramp_end - start > 5, "the pause stepped instead of ramping"
    if interfaces in ("position", "position_velocity", "position_velocity_acceleration"):
        # Forwarded commands: the joints themselves move as commanded.
        assert (max_step(run.actual_v[start:]) <= bound * 1.02 + 1e-12).all()
        np.testing.assert_allclose(run.actual_v[-1], 0.0, atol=1e-12)
    if interfaces == "position_velocity_acceleration":
        # The acceleration command is the derivative of the velocity command (a s^2 + v ds/dt)
        # from the first update after the pause was asked: that update already takes the ramp's
        # first velocity step (upstream: in force from the next update), so the acceleration
        # written by the update before it, when no pause had been asked, cannot include it.
        v = np.array([c.velocities for c in run.commands[start + 1:ramp_end]])
        a = np.array([c.accelerations for c in run.commands[start + 1:ramp_end]])
        np.testing.assert_allclose(np.diff(v, axis=0) / dt, a[:-1], atol=0.05 * max(ACCEL.values()))
    paused_at = run.mirror.p.copy()
    assert run.results() == [], "no result while paused"
    errors = np.array([abs(s.error[0]) for s in run.states])
    assert (errors <= PATH_TOL).all(), errors.max()
    assert run.states[-1].speed_scaling_target == 0.0
    np.testing.assert_allclose(run.mirror.p, paused_at)

    assert run.ctrl.resume_speed_scaling() == 1.0
    run.until(lambda out: bool(run.results()))
    for _ in range(100):
        run.step()
    results = run.results()
    assert len(results) == 1, results
    assert results[0].goal_id == gid and results[0].status is GoalStatus.SUCCEEDED
    np.testing.assert_allclose(run.mirror.p, [1.0, -0.5], atol=0.01)
    steps = max_step(run.desired_v[start:])
    assert (steps <= bound * 1.02 + 1e-12).all(), (steps, bound)


def test_trajectory_time_advances_by_the_period_times_the_factor() -> None:
    """Upstream section 13: at factor 0.5 a 2 s goal takes 4 s; goal time is judged in
    trajectory time, so it succeeds rather than running late."""
    cfg = config("position", speed_scaling={"initial_scaling_factor": 0.5})
    run = Run(cfg)
    begin = run.now
    run.ctrl.send_goal(run.now, goal())
    run.until(lambda out: bool(run.results()))
    took = (run.now - begin) / S
    assert 3.9 <= took <= 4.02, took
    assert run.results()[0].status is GoalStatus.SUCCEEDED
    state = run.states[-1]
    assert state.speed_scaling_factor == 0.5
    # desired.tfs ~ actual.tfs x factor (upstream's feedback)
    assert state.reference_time_from_start == pytest.approx(
        state.feedback_time_from_start * 0.5, abs=0.02
    )
    assert run.ctrl.trajectory_time_ns < run.now


def test_velocity_and_acceleration_are_those_of_the_slowed_time() -> None:
    cfg = config("position_velocity_acceleration", speed_scaling={"initial_scaling_factor": 0.5})
    slow = Run(cfg)
    full = Run(config("position_velocity_acceleration"))
    for run in (slow, full):
        run.ctrl.send_goal(run.now, goal())
    # The command samples one unscaled period ahead (upstream section 7): after 80 periods at
    # 0.5 and 40 at 1 both are at trajectory time 0.4 s and command the reference at 0.41 s.
    for _ in range(81):
        slow.step()
    for _ in range(41):
        full.step()
    # Same place on the path; velocity halved, acceleration quartered.
    np.testing.assert_allclose(slow.commands[-1].positions, full.commands[-1].positions,
                               atol=1e-9)
    np.testing.assert_allclose(slow.commands[-1].velocities, full.commands[-1].velocities * 0.5,
                               atol=1e-9)
    np.testing.assert_allclose(slow.commands[-1].accelerations,
                               full.commands[-1].accelerations * 0.25, atol=1e-9)


def test_without_limits_the_factor_ramps_over_the_ramp_time() -> None:
    cfg = make_config(NAMES, speed_scaling={"ramp_time": 0.2})  # 100 Hz: 20 cycles from 1 to 0
    run = Run(cfg)
    run.ctrl.send_goal(run.now, goal())
    run.until(lambda out: out.state.reference_time_from_start >= 0.5)
    run.ctrl.set_speed_scaling(0.0)
    # As upstream, a factor set between two updates is in force from the next: that update
    # takes the ramp's first step, and the 20th reaches the target.
    factors = [run.step().state.speed_scaling_factor for _ in range(25)]
    assert factors[0] == pytest.approx(0.95)
    assert np.all(np.diff(factors) <= 0.0)
    assert factors.index(0.0) == 19
    np.testing.assert_allclose(np.diff([1.0, *factors[:20]]), -0.05)


def test_ramp_time_zero_steps_as_upstream() -> None:
    run = Run(make_config(NAMES, speed_scaling={"ramp_time": 0.0}))
    run.ctrl.set_speed_scaling(0.3)
    assert run.step().state.speed_scaling_factor == 0.3
    assert run.step().state.speed_scaling_factor == 0.3


def test_a_goal_sent_while_paused_waits_for_resume() -> None:
    run = Run(config("position", speed_scaling={"max_scaling_factor": 2.0}))
    run.ctrl.set_speed_scaling(0.0)
    run.step()
    gid = run.ctrl.send_goal(run.now, goal())
    run.step()
    # The position command leads by one unscaled period (upstream section 7), even paused: the
    # joints take that one period's step into the goal and stay there.
    first = run.mirror.p.copy()
    assert np.abs(first).max() < 1e-3
    for _ in range(100):
        run.step()
    np.testing.assert_allclose(run.mirror.p, first)
    assert run.results() == []
    run.ctrl.set_speed_scaling(2.0)  # above 1: faster than planned (the bound allows it)
    run.until(lambda out: bool(run.results()))
    assert [r.goal_id for r in run.results()] == [gid]
    assert run.results()[0].status is GoalStatus.SUCCEEDED


def test_a_stamped_goal_starts_at_its_stamp_while_slowed() -> None:
    """As upstream (section 14.1): the stamp's distance from now is scaled by the factor."""
    run = Run(config("position", speed_scaling={"initial_scaling_factor": 0.5}))
    for _ in range(101):  # 100 periods at 0.5: trajectory time lags the clock by 0.5 s
        run.step()
    assert run.now - run.period - run.ctrl.trajectory_time_ns == 500 * MS
    traj = goal()
    stamped = JointTrajectory(traj.joint_names, traj.points, run.now + 200 * MS)
    run.ctrl.send_goal(run.now, stamped)
    for _ in range(19):  # up to the stamp (the command leads by a period): nothing moves
        run.step()
    np.testing.assert_allclose(run.mirror.p, [0.0, 0.0])
    for _ in range(3):
        run.step()
    assert np.abs(run.mirror.p).max() > 0.0
    run.until(lambda out: bool(run.results()))
    assert run.results()[0].status is GoalStatus.SUCCEEDED


@pytest.mark.parametrize(
    "bad", [-0.1, float("nan"), float("inf"), True, "1", 1.5, 1e308, 10**400, -(10**400)]
)
def test_a_bad_factor_is_refused_by_name(bad: Any) -> None:
    run = Run(make_config(NAMES))
    with pytest.raises(ConfigurationError, match=r"factor: .*must be a number in \[0, 1\]"):
        run.ctrl.set_speed_scaling(bad)
    assert run.ctrl.speed_scaling_target == 1.0


def test_the_factor_is_bounded_by_max_scaling_factor() -> None:
    """Issue 21 point 4: upstream's [0, 1] by default; ``max_scaling_factor`` (read-only, at
    most 10) allows more. A refused factor leaves the controller as it was: an unbounded one
    used to make every later goal fail with an overflow."""
    run = Run(config("position"))
    with pytest.raises(ConfigurationError, match="max_scaling_factor allows up to 10"):
        run.ctrl.set_speed_scaling(1e308)
    gid = run.ctrl.send_goal(run.now, goal())
    run.until(lambda out: bool(run.results()))
    assert [(r.goal_id, r.status) for r in run.results()] == [(gid, GoalStatus.SUCCEEDED)]

    run = Run(config("position", speed_scaling={"max_scaling_factor": 3.0}))
    run.ctrl.set_speed_scaling(3.0)
    assert run.ctrl.speed_scaling_target == 3.0
    with pytest.raises(ConfigurationError, match=r"must be a number in \[0, 3\]"):
        run.ctrl.set_speed_scaling(3.5)
    assert run.ctrl.speed_scaling_target == 3.0
    with pytest.raises(ConfigurationError, match="read-only"):
        run.ctrl.set_parameters({"speed_scaling.max_scaling_factor": 1e308})
    for bad, message in [
        ({"max_scaling_factor": 1e308}, r"max_scaling_factor: must be in \[1, 10\]"),
        ({"max_scaling_factor": 0.5}, r"max_scaling_factor: must be in \[1, 10\]"),
        ({"max_scaling_factor": float("nan")}, "max_scaling_factor: expected a finite number"),
        ({"initial_scaling_factor": 2.0}, r"initial_scaling_factor: must be in \[0, 1\]"),
        (
            {"initial_scaling_factor": 4.0, "max_scaling_factor": 3.0},
            r"initial_scaling_factor: must be in \[0, 3\]",
        ),
    ]:
        with pytest.raises(ConfigurationError, match=message):
            make_config(NAMES, speed_scaling=bad)
    both = {"initial_scaling_factor": 2, "max_scaling_factor": 2}
    faster = make_config(NAMES, speed_scaling=both)
    assert faster.speed_scaling.initial_scaling_factor == 2.0


def test_resume_goes_back_to_the_factor_before_the_pause() -> None:
    run = Run(make_config(NAMES))
    run.ctrl.set_speed_scaling(0.4)
    run.ctrl.set_speed_scaling(0.0)
    assert run.ctrl.resume_speed_scaling() == 0.4
    run.ctrl.set_speed_scaling(0.0)
    assert run.ctrl.resume_speed_scaling() == 0.4
    paused = JointTrajectoryController(
        make_config(NAMES, speed_scaling={"initial_scaling_factor": 0.0})
    )
    assert paused.resume_speed_scaling() == 1.0


def test_activation_resets_the_factor_to_the_initial_one() -> None:
    run = Run(make_config(NAMES, speed_scaling={"initial_scaling_factor": 0.7}))
    run.ctrl.set_speed_scaling(0.2)
    run.step()
    run.ctrl.deactivate(run.now)
    run.ctrl.activate(run.now, run.mirror.state())
    assert (run.ctrl.speed_scaling_factor, run.ctrl.speed_scaling_target) == (0.7, 0.7)


def test_a_new_target_mid_ramp_turns_the_ramp_without_a_jump() -> None:
    run = Run(make_config(NAMES, speed_scaling={"ramp_time": 0.2}))
    run.ctrl.set_speed_scaling(0.0)
    factors = [run.step().state.speed_scaling_factor for _ in range(6)]
    run.ctrl.set_speed_scaling(0.9)
    factors += [run.step().state.speed_scaling_factor for _ in range(20)]
    steps = np.diff(factors)
    assert np.abs(steps).max() <= 0.05 + 1e-12, steps
    # The first update is at the activation's time (no time elapsed, no step); the new target
    # is in force from the next update, which turns the ramp where the factor is.
    assert factors[:6] == pytest.approx([1.0, 0.95, 0.9, 0.85, 0.8, 0.75])
    assert min(factors) == pytest.approx(0.75)
    assert factors[6] == pytest.approx(0.8)
    assert factors[-1] == 0.9


def test_a_reactivation_after_slowing_commands_at_once() -> None:
    """Trajectory time lags the clock after a slowed stretch and stays continuous across
    activations: the new hold starts at trajectory time, so the first cycle commands."""
    run = Run(config("position"))
    run.ctrl.send_goal(run.now, goal())
    run.ctrl.set_speed_scaling(0.2)
    for _ in range(100):
        run.step()
    assert run.ctrl.trajectory_time_ns < run.now - 500 * MS
    run.ctrl.deactivate(run.now)
    run.ctrl.activate(run.now, run.mirror.state())
    held = run.mirror.p.copy()
    out = run.step()
    np.testing.assert_array_equal(out.command.positions, held)
    assert out.state.speed_scaling_factor == 1.0
    gid = run.ctrl.send_goal(run.now, goal())
    run.until(lambda out: bool([r for r in run.results() if r.goal_id == gid]))
    assert run.results()[-1].status is GoalStatus.SUCCEEDED


def test_the_parameters_are_checked_and_named() -> None:
    # Upstream's interface names are '<component>/<interface>' here (which component offers
    # it is checked when the hardware is created: tests/daemon/test_robot.py).
    accepted = make_config(NAMES, speed_scaling={"state_interface": "arm/speed_scaling",
                                                 "command_interface": "arm/x"})
    assert accepted.speed_scaling.state_interface == "arm/speed_scaling"
    for bad, message in [
        ({"state_interface": "arm"}, "speed_scaling.state_interface: 'arm': expected "
                                     "'<component>/<interface>'"),
        ({"command_interface": "a/b/c"}, "speed_scaling.command_interface: 'a/b/c': expected"),
        ({"command_interface": "/x"}, "expected '<component>/<interface>'"),
        ({"command_interface": "arm/x "}, "expected '<component>/<interface>'"),
        ({"initial_scaling_factor": -0.5}, "speed_scaling.initial_scaling_factor: must be >= 0"),
        ({"ramp_time": -1}, "speed_scaling.ramp_time: must be >= 0"),
        ({"ramp": 1}, "did you mean 'ramp_time'"),
    ]:
        with pytest.raises(ConfigurationError, match=message):
            make_config(NAMES, speed_scaling=bad)


def test_upstreams_parameters_are_read_only_and_the_ramp_time_changes_next_cycle() -> None:
    run = Run(make_config(NAMES, speed_scaling={"ramp_time": 0.2}))
    assert run.ctrl.get_parameters(["speed_scaling.initial_scaling_factor"]) == {
        "speed_scaling.initial_scaling_factor": 1.0
    }
    for name in ("initial_scaling_factor", "max_scaling_factor", "state_interface",
                 "command_interface"):
        with pytest.raises(ConfigurationError, match="read-only"):
            run.ctrl.set_parameters({f"speed_scaling.{name}": 0.5})
    change = run.ctrl.set_parameters({"speed_scaling.ramp_time": 1.0})
    assert change.effects["speed_scaling.ramp_time"].value == "next cycle"
    run.ctrl.set_speed_scaling(0.0)
    run.step()  # at the activation's time: no time elapsed, no step
    assert run.step().state.speed_scaling_factor == pytest.approx(0.99)  # 1 / 1.0 s at 100 Hz


def test_check_warns_when_the_controller_starts_paused() -> None:
    from jtc_hw.controller.parameters import explain

    assert not [w for w in explain(make_config(NAMES)) if "speed_scaling" in w]
    warnings = explain(make_config(NAMES, speed_scaling={"initial_scaling_factor": 0.0}))
    assert [w for w in warnings if w.startswith("speed_scaling.initial_scaling_factor: is 0")]


def test_a_factor_set_between_updates_is_in_force_from_the_next_update() -> None:
    """Upstream (section 7 step 1, its ``setting_scaling_factor_works_correctly``): with no ramp,
    the update right after the set reports the new factor, advances trajectory time by the
    period times it and commands the velocity of the slowed time. Before this was fixed the
    factor and the velocity lagged one update, and trajectory time two."""
    cfg = make_config(NAMES, command_interfaces=("position", "velocity"),
                      speed_scaling={"ramp_time": 0.0})
    run = Run(cfg)
    run.ctrl.send_goal(run.now, goal())
    for _ in range(30):
        run.step()
    for factor in (0.765, 0.5, 0.0, 1.0):
        before_tau = run.ctrl.trajectory_time_ns
        before_ref = run.states[-1].reference_time_from_start
        run.ctrl.set_speed_scaling(factor)
        out = run.step()
        assert out.state.speed_scaling_factor == factor
        assert run.ctrl.trajectory_time_ns - before_tau == round(run.period * factor)
        assert out.state.reference_time_from_start - before_ref == pytest.approx(
            run.period * factor / S, abs=1e-12)
        # The command samples one unscaled period ahead (upstream section 7 step 7), at the
        # velocity of the slowed time.
        ahead = run.ctrl.reference.sample(run.ctrl.trajectory_time_ns + run.period)
        np.testing.assert_array_equal(out.command.positions, ahead.positions)
        np.testing.assert_allclose(out.command.velocities, ahead.velocities * factor, rtol=1e-12)
        # ... and it stays in force.
        tau = run.ctrl.trajectory_time_ns
        assert run.step().state.speed_scaling_factor == factor
        assert run.ctrl.trajectory_time_ns - tau == round(run.period * factor)


def test_a_ramp_takes_its_first_step_at_the_next_update() -> None:
    """With acceleration limits the factor ramps; its first step is the update right after the
    set, and that update's trajectory time advances at the factor it reports."""
    run = Run(config("position_velocity"))
    run.ctrl.send_goal(run.now, goal())
    run.until(lambda out: out.state.reference_time_from_start >= 1.0)
    tau = run.ctrl.trajectory_time_ns
    run.ctrl.set_speed_scaling(0.0)
    out = run.step()
    factor = out.state.speed_scaling_factor
    assert 0.0 < factor < 1.0
    assert run.ctrl.trajectory_time_ns - tau == round(run.period * factor)
    assert out.state.speed_scaling_target == 0.0


@pytest.mark.parametrize("ramp_time", [0.0, 0.2])
def test_a_factor_set_after_a_command_installed_between_updates(ramp_time: float) -> None:
    """The rate of the next update's step is chosen at the set, from the reference: one
    committed since the last update starts after that update's trajectory time, so it is
    sampled from its start (the fuzz bench found ``resume`` after a goal failing with
    'cannot sample the trajectory at ...: it is defined from ... on')."""
    run = Run(config("position", speed_scaling={"ramp_time": ramp_time}))
    for _ in range(3):
        run.step()
    gid = run.ctrl.send_goal(run.now, goal())  # the clock is a period past the last update
    assert run.ctrl.reference.state_before_ns > run.ctrl.trajectory_time_ns
    run.ctrl.set_speed_scaling(0.5)
    assert run.step().state.speed_scaling_factor < 1.0
    run.until(lambda out: bool(run.results()))
    assert [(r.goal_id, r.status) for r in run.results()] == [(gid, GoalStatus.SUCCEEDED)]


def scaled_by_hardware(**scaling: Any) -> Run:
    return Run(make_config(NAMES, command_interfaces=("position", "velocity"),
                           speed_scaling={"ramp_time": 0.0, **scaling}))


def test_the_state_interface_sets_the_factor_from_the_next_update() -> None:
    """Upstream's ``scaling_state_interface_sets_value``: with ``speed_scaling.state_interface``
    the hardware's value, read before an update, is that update's factor; what a client sets
    cannot override it, and without a command interface it is refused rather than lost."""
    run = scaled_by_hardware(state_interface="arm/speed_scaling_factor")
    run.ctrl.send_goal(run.now, goal())
    for _ in range(30):
        run.step()
    tau = run.ctrl.trajectory_time_ns
    run.ctrl.set_speed_scaling_state(0.5)
    out = run.step()
    assert (out.state.speed_scaling_factor, out.state.speed_scaling_target) == (0.5, 0.5)
    assert run.ctrl.trajectory_time_ns - tau == run.period // 2
    ahead = run.ctrl.reference.sample(run.ctrl.trajectory_time_ns + run.period)
    np.testing.assert_allclose(out.command.velocities, ahead.velocities * 0.5, rtol=1e-12)
    with pytest.raises(ConfigurationError, match="read from the hardware's "
                       "'arm/speed_scaling_factor' each cycle and no "
                       "speed_scaling.command_interface"):
        run.ctrl.set_speed_scaling(0.2)
    with pytest.raises(ConfigurationError, match="no speed_scaling.command_interface"):
        run.ctrl.resume_speed_scaling()
    # A value the device did not report (NaN), or not a factor, leaves the factor as it is;
    # one above max_scaling_factor is that bound.
    for unreadable in (float("nan"), -0.5, float("inf")):
        run.ctrl.set_speed_scaling_state(unreadable)
        assert run.step().state.speed_scaling_factor == 0.5
    run.ctrl.set_speed_scaling_state(3.0)
    assert run.step().state.speed_scaling_factor == 1.0
    run.until(lambda out: bool(run.results()))
    assert run.results()[0].status is GoalStatus.SUCCEEDED


def test_the_command_interface_carries_the_factor_asked_for() -> None:
    """Upstream's ``scaling_command_interface_sets_value``: the factor asked for is written to
    the command interface each cycle; hardware that loops it back to the state interface shows
    it at the next read, so the factor is in force from the second update after the set."""
    run = scaled_by_hardware(state_interface="arm/speed_scaling_factor",
                             command_interface="arm/speed_scaling_factor",
                             initial_scaling_factor=0.5)
    assert run.ctrl.speed_scaling_request == 0.5
    hardware = 1.0  # the robot's slider, before the controller first writes it
    factors = []
    for k in range(4):
        if k == 1:
            before = run.ctrl.speed_scaling_target
            run.ctrl.set_speed_scaling(0.765)
            assert run.ctrl.speed_scaling_target == before  # the hardware decides
            assert run.ctrl.speed_scaling_request == 0.765
        run.ctrl.set_speed_scaling_state(hardware)  # read
        factors.append(run.step().state.speed_scaling_factor)
        hardware = run.ctrl.speed_scaling_request  # written, looped back
    assert factors == [1.0, 0.5, 0.765, 0.765]
