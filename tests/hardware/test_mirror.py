"""The mirror hardware: physics per interface with exact numbers, test knobs, lifecycle."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pytest

from jtc_hw.controller.controller import JointTrajectoryController
from jtc_hw.controller.goals import ErrorCode, GoalResult, GoalStatus
from jtc_hw.controller.joints import JointCommand
from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.errors import CommunicationError, ConfigurationError, HardwareError
from jtc_hw.hardware.mirror import MirrorHardware

from conftest import MS, S, make_config

NAN = math.nan
HALF = S // 2
ALL_STATES = ("position", "velocity", "acceleration")


def mirror(
    joints: Sequence[str] = ("a", "b"),
    command: Sequence[str] = ("position",),
    state: Sequence[str] = ALL_STATES,
    **params: Any,
) -> MirrorHardware:
    """A configured and activated mirror, its clock started at 0."""
    hw = MirrorHardware("sim", joints, command, state, params)
    hw.configure()
    hw.activate(0)
    return hw


def read(hw: MirrorHardware, now: int) -> tuple[list[float], list[float], list[float]]:
    s = hw.read(now)
    assert s.velocities is not None and s.accelerations is not None
    return s.positions.tolist(), s.velocities.tolist(), s.accelerations.tolist()


# --------------------------------------------------------------------------------------------
# Parameters and lifecycle
# --------------------------------------------------------------------------------------------


def test_parameters_defaults_and_status() -> None:
    hw = MirrorHardware("sim", ["a", "b"], ["position"], ["position"], {})
    assert dict(hw.params) == {
        "safe_action": "hold",
        "lag_s": 0.0,
        "position_limits": ((-math.inf, math.inf),) * 2,
        "velocity_limit": (0.0, 0.0),
        "initial_positions": (0.0, 0.0),
        "damping": 0.0,
        "speed_scaling_factor": 1.0,
    }
    assert hw.status()["details"] == {
        "frozen": False, "injected_fault": None,
        "speed_scaling_factor": {"state": None, "command": None},
    }
    assert MirrorHardware.kind == "mirror"


@pytest.mark.parametrize(
    ("params", "path", "message"),
    [
        ({"lag_s": -0.1}, "params.lag_s", "must be >= 0, got -0.1"),
        ({"velocity_limit": [1.0, -1.0]}, "params.velocity_limit[1]", "must be >= 0"),
        ({"damping": "high"}, "params.damping", "expected a number"),
        ({"initial_positions": [0.0, 2.0], "position_limits": [None, [-1, 1]]},
         "params.initial_positions",
         "initial position 2 of joint 'b' is outside its position_limits [-1, 1]"),
        ({"lag": 0.1}, "params.lag", "did you mean 'lag_s'?"),
    ],
)
def test_invalid_parameters(params: dict[str, Any], path: str, message: str) -> None:
    with pytest.raises(ConfigurationError) as info:
        MirrorHardware("sim", ["a", "b"], ["position"], ["position"], params)
    assert info.value.path == path
    assert message in str(info.value)


def test_only_position_velocity_acceleration_states() -> None:
    with pytest.raises(ConfigurationError, match="does not support the 'effort' interface"):
        MirrorHardware("sim", ["a"], ["position"], ["position", "effort"], {})


def test_state_interfaces_reported_are_those_asked_for() -> None:
    hw = mirror(state=("position",), initial_positions=[0.5, -0.25])
    s = hw.read(0)
    assert s.positions.tolist() == [0.5, -0.25]
    assert s.velocities is None and s.accelerations is None
    hw2 = mirror(state=("position", "velocity"))
    s2 = hw2.read(0)
    assert s2.velocities is not None and s2.velocities.tolist() == [0.0, 0.0]
    assert s2.accelerations is None


def test_reads_return_copies() -> None:
    hw = mirror()
    first = hw.read(0)
    first.positions[0] = 99.0
    assert hw.read(0).positions.tolist() == [0.0, 0.0]


def test_activate_reports_nan_first_then_the_last_written_command() -> None:
    hw = MirrorHardware("sim", ["a", "b"], ["position", "velocity"], ALL_STATES, {})
    hw.configure()
    held = hw.activate(0)
    assert held.positions is not None and held.velocities is not None
    assert np.isnan(held.positions).all() and np.isnan(held.velocities).all()
    assert held.accelerations is None and held.effort is None
    hw.write(0, JointCommand([1.0, 2.0], [0.5, NAN]))
    hw.write(S, JointCommand([NAN, 3.0], [NAN, NAN]))
    hw.deactivate(2 * S)
    held = hw.activate(3 * S)
    assert held.positions is not None and held.velocities is not None
    assert held.positions.tolist() == [1.0, 3.0]
    np.testing.assert_array_equal(held.velocities, [0.5, NAN])


def test_torque_off_forgets_the_held_command_and_stops_in_place() -> None:
    hw = mirror(joints=("a",), lag_s=0.5, safe_action="torque_off")
    hw.write(0, JointCommand([1.0]))
    hw.deactivate(HALF)
    stopped = 1.0 - math.exp(-1.0)
    assert hw.read(HALF).positions[0] == pytest.approx(stopped, rel=1e-15)
    assert hw.read(2 * S).positions[0] == pytest.approx(stopped, rel=1e-15)
    held = hw.activate(3 * S)
    assert held.positions is not None and np.isnan(held.positions).all()


def test_hold_keeps_the_position_servo_on_its_last_target() -> None:
    hw = mirror(joints=("a",), lag_s=0.5)
    hw.write(0, JointCommand([1.0]))
    hw.deactivate(HALF)
    # Inactive: no more commands, but the servo still converges on its target.
    assert hw.read(S).positions[0] == pytest.approx(1.0 - math.exp(-2.0), rel=1e-15)
    held = hw.activate(2 * S)
    assert held.positions is not None and held.positions.tolist() == [1.0]


def test_hold_stops_a_velocity_driven_joint() -> None:
    hw = mirror(joints=("a",), command=("velocity",), state=("position", "velocity"))
    hw.write(0, JointCommand(velocities=[2.0]))
    hw.deactivate(HALF)
    s = hw.read(S)
    assert s.velocities is not None
    assert (s.positions.tolist(), s.velocities.tolist()) == ([1.0], [0.0])
    assert hw.read(2 * S).positions.tolist() == [1.0]


def test_configure_again_forgets_commands_but_positions_persist() -> None:
    hw = mirror(joints=("a",))
    hw.write(0, JointCommand([1.5]))
    hw.read(S)
    hw.deactivate(S)
    hw.cleanup()
    hw.configure()
    held = hw.activate(5 * S)
    assert held.positions is not None and np.isnan(held.positions).all()
    assert hw.read(6 * S).positions.tolist() == [1.5]


def test_time_must_not_go_backwards() -> None:
    hw = mirror(joints=("a",))
    hw.read(S)
    with pytest.raises(HardwareError) as info:
        hw.read(S - 1)
    assert str(info.value) == (
        "mirror hardware 'sim': time went backwards (999999999 ns after 1000000000 ns); "
        "pass the loop's monotonic time"
    )


# --------------------------------------------------------------------------------------------
# Physics
# --------------------------------------------------------------------------------------------


def test_ideal_position_is_reached_at_the_next_read() -> None:
    hw = mirror(initial_positions=[0.5, -0.25])
    assert read(hw, 0) == ([0.5, -0.25], [0.0, 0.0], [0.0, 0.0])
    hw.write(0, JointCommand([1.0, -2.0]))
    assert read(hw, HALF) == ([1.0, -2.0], [1.0, -3.5], [2.0, -7.0])
    assert read(hw, HALF) == ([1.0, -2.0], [1.0, -3.5], [2.0, -7.0])  # no time, no change
    assert read(hw, S) == ([1.0, -2.0], [0.0, 0.0], [-2.0, 7.0])


def test_nan_entries_are_not_written() -> None:
    hw = mirror()
    hw.write(0, JointCommand([1.0, 2.0]))
    hw.write(HALF, JointCommand([NAN, 3.0]))
    assert read(hw, S)[0] == [1.0, 3.0]


def test_first_order_lag() -> None:
    hw = mirror(joints=("a",), lag_s=0.5)
    hw.write(0, JointCommand([2.0]))
    p1, v1, _ = read(hw, S // 4)
    assert p1[0] == pytest.approx(2.0 * (1.0 - math.exp(-0.5)), rel=1e-15)
    assert v1[0] == pytest.approx(p1[0] / 0.25, rel=1e-15)
    p2, v2, a2 = read(hw, S)
    assert p2[0] == pytest.approx(2.0 * (1.0 - math.exp(-2.0)), rel=1e-15)
    assert v2[0] == pytest.approx((p2[0] - p1[0]) / 0.75, rel=1e-15)
    assert a2[0] == pytest.approx((v2[0] - v1[0]) / 0.75, rel=1e-15)
    one_step = mirror(joints=("a",), lag_s=0.5)
    one_step.write(0, JointCommand([2.0]))
    assert read(one_step, S)[0][0] == pytest.approx(p2[0], rel=1e-15)


def test_velocity_limit_ramps_an_ideal_joint() -> None:
    hw = mirror(joints=("a", "b"), velocity_limit={"a": 1.0})
    hw.write(0, JointCommand([2.0, 2.0]))
    trace = [read(hw, k * HALF)[:2] for k in range(1, 6)]
    assert trace == [
        ([0.5, 2.0], [1.0, 4.0]),
        ([1.0, 2.0], [1.0, 0.0]),
        ([1.5, 2.0], [1.0, 0.0]),
        ([2.0, 2.0], [1.0, 0.0]),
        ([2.0, 2.0], [0.0, 0.0]),
    ]


def test_velocity_limit_saturates_the_lag_into_a_ramp() -> None:
    hw = mirror(joints=("a",), lag_s=0.1, velocity_limit=1.0)
    hw.write(0, JointCommand([1.0]))
    # |error| > vmax * lag: constant speed until the error is 0.1 (at t = 0.9 s) ...
    assert read(hw, HALF)[:2] == ([0.5], [1.0])
    # ... then exponential: 0.4 s of ramp and 0.1 s (one time constant) of lag.
    assert read(hw, S)[0][0] == pytest.approx(1.0 - 0.1 * math.exp(-1.0), rel=1e-15)


def test_position_limits_clamp_the_target() -> None:
    hw = mirror(position_limits=[[-1.0, 1.0], None])
    hw.write(0, JointCommand([5.0, 5.0]))
    assert read(hw, HALF)[0] == [1.0, 5.0]
    hw.write(HALF, JointCommand([-5.0, -5.0]))
    assert read(hw, S)[0] == [-1.0, -5.0]


def test_velocity_commands_integrate() -> None:
    hw = mirror(command=("velocity",), velocity_limit=[0.0, 1.0])
    hw.write(0, JointCommand(velocities=[0.5, -1.5]))
    assert read(hw, 2 * S) == ([1.0, -2.0], [0.5, -1.0], [0.25, -0.5])
    assert read(hw, 3 * S) == ([1.5, -3.0], [0.5, -1.0], [0.0, 0.0])


def test_a_joint_driven_into_its_limit_stops_there() -> None:
    hw = mirror(command=("velocity",), position_limits=[[-1.0, 0.75], None])
    hw.write(0, JointCommand(velocities=[1.0, 1.0]))
    assert read(hw, S) == ([0.75, 1.0], [0.0, 1.0], [0.0, 1.0])


def test_acceleration_commands_integrate_twice() -> None:
    hw = mirror(joints=("a", "b"), command=("position", "velocity", "acceleration"),
                velocity_limit=[0.0, 1.5])
    hw.write(0, JointCommand([NAN, NAN], [NAN, NAN], [2.0, 2.0]))
    assert read(hw, HALF) == ([0.25, 0.25], [1.0, 1.0], [2.0, 2.0])
    # b reaches 1.5 rad/s after 0.25 s more: 0.25 + 0.25 + 0.0625 + 1.5 * 0.25
    assert read(hw, S) == ([1.0, 0.9375], [2.0, 1.5], [2.0, 0.0])


def test_position_takes_priority_over_velocity_and_acceleration() -> None:
    hw = mirror(joints=("a",), command=("position", "velocity", "acceleration"))
    hw.write(0, JointCommand([1.0], [5.0], [7.0]))
    # The velocity state is the actual rate of change, not the commanded feed-forward.
    assert read(hw, HALF) == ([1.0], [2.0], [4.0])


def test_effort_drives_a_unit_inertia() -> None:
    hw = mirror(command=("effort",))
    hw.write(0, JointCommand(effort=[2.0, -1.0]))
    assert read(hw, HALF) == ([0.25, -0.125], [1.0, -0.5], [2.0, -1.0])
    assert read(hw, S) == ([1.0, -0.5], [2.0, -1.0], [2.0, -1.0])


def test_effort_with_damping_is_solved_exactly() -> None:
    hw = mirror(joints=("a",), command=("effort",), damping=2.0)
    hw.write(0, JointCommand(effort=[2.0]))
    p, v, a = read(hw, HALF)
    # dv/dt = 2 - 2 v from rest: v = 1 - e^{-2t}, p = t - (1 - e^{-2t}) / 2, at t = 0.5
    assert v[0] == pytest.approx(1.0 - math.exp(-1.0), rel=1e-15)
    assert p[0] == pytest.approx(0.5 - (1.0 - math.exp(-1.0)) / 2.0, rel=1e-14)
    assert a[0] == pytest.approx(2.0 - 2.0 * v[0], rel=1e-15)
    in_steps = mirror(joints=("a",), command=("effort",), damping=2.0)
    in_steps.write(0, JointCommand(effort=[2.0]))
    for k in range(1, 6):
        in_steps.read(k * S // 10)
    assert read(in_steps, HALF)[0][0] == pytest.approx(p[0], rel=1e-14)


def test_interfaces_not_configured_are_ignored() -> None:
    hw = mirror(joints=("a",))
    hw.write(0, JointCommand([1.0], velocities=[9.0], effort=[9.0]))
    assert read(hw, HALF)[0] == [1.0]


# --------------------------------------------------------------------------------------------
# Test knobs
# --------------------------------------------------------------------------------------------


def test_frozen_feedback_repeats_and_resumes_without_a_jump() -> None:
    hw = mirror(joints=("a",))
    hw.write(0, JointCommand([1.0]))
    hw.set_frozen(True)
    assert hw.frozen and hw.status()["details"]["frozen"] is True
    assert read(hw, HALF) == ([0.0], [0.0], [0.0])
    hw.write(HALF, JointCommand([2.0]))
    assert read(hw, S) == ([0.0], [0.0], [0.0])
    hw.set_frozen(False)
    assert read(hw, S + HALF) == ([2.0], [4.0], [8.0])


def test_displaced_joints_read_where_they_were_put_then_follow_their_commands() -> None:
    hw = mirror(command=("position", "velocity"), position_limits=[None, [-1.0, 1.0]])
    hw.write(0, JointCommand([1.0, NAN], [NAN, 0.5]))
    assert read(hw, HALF) == ([1.0, 0.25], [2.0, 0.5], [4.0, 1.0])
    hw.displace([0.5, 3.0])  # b against its upper limit
    assert read(hw, HALF) == ([0.5, 1.0], [2.0, 0.5], [4.0, 1.0])  # no time: states kept
    p, _, _ = read(hw, S)
    assert p == [1.0, 1.0]  # a back on its target; b still at its limit
    with pytest.raises(ValueError, match="1 positions for 2 joints"):
        hw.displace([0.0])
    hw.set_frozen(True)
    hw.displace([0.0, 0.0])
    assert read(hw, 2 * S)[0] == [0.0, 0.0]  # frozen joints stay where they were put


def test_injected_fault_raises_on_read_until_cleared() -> None:
    hw = mirror(joints=("a",), command=("velocity",))
    hw.write(0, JointCommand(velocities=[1.0]))
    hw.inject_fault("bus down")
    for now in (HALF, S):
        with pytest.raises(CommunicationError) as info:
            hw.read(now)
        assert str(info.value) == "bus down"
    status = hw.status()
    assert status["last_fault"] == "bus down"
    assert status["counters"]["read_errors"] == 2
    assert status["details"]["injected_fault"] == "bus down"
    assert hw.state.value == "active"
    hw.clear_fault()
    # The joint kept moving meanwhile.
    assert read(hw, S + HALF)[:2] == ([1.5], [1.0])


# --------------------------------------------------------------------------------------------
# With the controller
# --------------------------------------------------------------------------------------------


class Loop:
    """read -> update -> write at 100 Hz with the mirror as the hardware."""

    def __init__(self, hw: MirrorHardware, **params: Any) -> None:
        self.hw = hw
        self.ctrl = JointTrajectoryController(make_config(joints=hw.joints, **params))
        self.period = 10 * MS
        self.now = 0
        hw.configure()
        held = hw.activate(self.now)
        self.ctrl.activate(self.now, hw.read(self.now), held)
        self.results: list[GoalResult] = []

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self.now += self.period
            out = self.ctrl.update(self.now, self.period, self.hw.read(self.now))
            self.hw.write(self.now, out.command)
            self.results.extend(e for e in out.events if isinstance(e, GoalResult))


def goal(positions: Sequence[float], at_s: float = 1.0) -> JointTrajectory:
    return JointTrajectory(["j1", "j2"], [TrajectoryPoint(at_s, positions)])


TOLERANCES = {"j1": {"trajectory": 0.05, "goal": 0.01}, "j2": {"trajectory": 0.05, "goal": 0.01}}


def test_controller_reaches_a_goal_on_the_mirror() -> None:
    hw = MirrorHardware("arm", ["j1", "j2"], ["position"], ["position", "velocity"],
                        {"initial_positions": [0.1, 0.2]})
    loop = Loop(hw, constraints=TOLERANCES)
    gid = loop.ctrl.send_goal(loop.now, goal([0.5, -0.5]))
    loop.step(110)
    assert [(r.goal_id, r.status) for r in loop.results] == [(gid, GoalStatus.SUCCEEDED)]
    np.testing.assert_allclose(hw.read(loop.now).positions, [0.5, -0.5], atol=1e-12)


def test_frozen_mirror_makes_the_controller_abort() -> None:
    hw = MirrorHardware("arm", ["j1", "j2"], ["position"], ["position", "velocity"], {})
    loop = Loop(hw, constraints=TOLERANCES)
    gid = loop.ctrl.send_goal(loop.now, goal([0.0, 1.0]))
    loop.step(20)
    hw.set_frozen(True)
    loop.step(50)
    (result,) = loop.results
    assert (result.goal_id, result.status, result.error_code) == (
        gid, GoalStatus.ABORTED, ErrorCode.PATH_TOLERANCE_VIOLATED,
    )
    assert "j2" in result.details


def test_reactivation_resumes_from_the_held_command() -> None:
    hw = MirrorHardware("arm", ["j1", "j2"], ["position"], ["position", "velocity"],
                        {"lag_s": 0.05})
    loop = Loop(hw)
    loop.ctrl.send_goal(loop.now, goal([0.3, 0.3], at_s=0.2))
    loop.step(30)
    loop.ctrl.deactivate(loop.now)
    hw.deactivate(loop.now)
    held = hw.activate(loop.now)
    assert held.positions is not None
    np.testing.assert_allclose(held.positions, [0.3, 0.3], atol=1e-12)


def test_the_speed_scaling_scalar_interface_mirrors_what_is_written() -> None:
    """One scalar interface, state and command (docs/behaviour.md, "Speed scaling"): the
    parameter's value until a write, then what was written, from the next read on, as
    GenericSystem mirrors; what the last read left, with no I/O in between."""
    hw = MirrorHardware("sim", ["a"], ["position"], ["position"], {"speed_scaling_factor": 0.5})
    assert hw.SCALAR_STATE_INTERFACES == hw.SCALAR_COMMAND_INTERFACES == ("speed_scaling_factor",)
    hw.configure()
    hw.activate(0)
    assert math.isnan(hw.scalar_state("speed_scaling_factor"))  # nothing read yet
    hw.read(0)
    assert hw.scalar_state("speed_scaling_factor") == 0.5
    hw.set_scalar_command("speed_scaling_factor", 0.8)
    hw.read(MS)
    assert hw.scalar_state("speed_scaling_factor") == 0.5  # set, not yet written
    hw.write(MS, hw.nan_command())
    assert hw.scalar_state("speed_scaling_factor") == 0.5  # written, not yet read
    hw.read(2 * MS)
    assert hw.scalar_state("speed_scaling_factor") == 0.8
    assert hw.status()["details"]["speed_scaling_factor"] == {"state": 0.8, "command": 0.8}
    hw.set_frozen(True)  # frozen feedback: the state keeps its value too
    hw.set_scalar_command("speed_scaling_factor", 0.2)
    hw.write(3 * MS, hw.nan_command())
    hw.read(4 * MS)
    assert hw.scalar_state("speed_scaling_factor") == 0.8
    hw.set_frozen(False)
    hw.read(5 * MS)
    assert hw.scalar_state("speed_scaling_factor") == 0.2
    with pytest.raises(ConfigurationError, match="must be >= 0"):
        MirrorHardware("sim", ["a"], ["position"], ["position"], {"speed_scaling_factor": -1})
