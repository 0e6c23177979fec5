"""Runtime parameters (issue 11 point 14): ``set_parameters`` / ``get_parameters`` on the
controller, driven with the simulated clock.

Reference: jtc_upstream_behaviour.md section 7 step 2 (parameters re-read at the next update:
default tolerances recomputed, PID gains updated), 8.2 (active tolerances are not refreshed:
a change reaches the next goal) and 1 (which parameters are read-only; ``cmd_timeout`` is
resolved at activation).
"""

from __future__ import annotations

import pickle
from typing import Any

import numpy as np
import pytest

from jtc_hw import (
    ConfigurationError,
    ErrorCode,
    GoalRejected,
    GoalResult,
    GoalStatus,
    JointTrajectory,
    TrajectoryPoint,
)
from jtc_hw.config.controller import GAIN_PARAMETERS, PARAMETERS
from jtc_hw.config.reading import load_config
from jtc_hw.config.schema import Effect
from jtc_hw.controller.parameters import parameter_names

from conftest import Rig, S, make_config

NAMES = ("j1", "j2")


def traj(*points: tuple[float, list[float]], **fields: Any) -> JointTrajectory:
    return JointTrajectory(NAMES, [TrajectoryPoint(t, p, **fields) for t, p in points])


def test_a_gain_change_applies_at_the_next_cycle_and_keeps_the_integral() -> None:
    """Section 7 step 2: changed gains are used from the next update (control_toolbox's
    ``set_gains``: the integral accumulated so far stays).

    Two controllers see the same errors (the joints are frozen, so the error is the reference
    alone): one with ``p = 7`` from the start, one with ``p = 2`` changed to 7 mid-way. From the
    cycle after the change their commands are equal, which needs the new gain and the kept
    integral (it would differ from the other's had the change reset it); before, they differ.
    """

    def rig(p: float) -> Rig:
        cfg = make_config(
            command_interfaces=("velocity",),
            gains={j: {"p": p, "i": 3.0, "i_clamp": 100.0} for j in NAMES},
        )
        r = Rig(cfg, [0.0, 0.0])
        r.ctrl.send_goal(r.now, traj((1.0, [1.0, 1.0])))
        r.mirror.frozen = True
        return r

    changed, reference = rig(2.0), rig(7.0)
    for r in (changed, reference):
        r.step(20)
    assert changed.last.command.velocities[0] != pytest.approx(
        reference.last.command.velocities[0]
    )

    change = changed.ctrl.set_parameters({"gains.j1.p": 7.0})

    assert change.effects == {"gains.j1.p": Effect.NEXT_CYCLE}
    for _ in range(3):
        a, b = changed.step().command.velocities, reference.step().command.velocities
        assert a[0] == pytest.approx(b[0], rel=1e-12)  # j1: the new gain, the same integral
        assert a[1] != pytest.approx(b[1])  # j2 keeps p = 2


def test_new_default_tolerances_apply_to_the_next_goal_not_the_running_one() -> None:
    """Section 8.2: a parameter change updates the defaults only; the running goal keeps the
    tolerances it was accepted with, the next goal gets the new ones."""
    rig = Rig(make_config(), [0.0, 0.0])
    first = rig.ctrl.send_goal(rig.now, traj((1.0, [1.0, 1.0])))
    rig.mirror.frozen = True  # the joints stay behind: the path error grows to 1 rad
    rig.step(10)

    change = rig.ctrl.set_parameters({"constraints.j1.trajectory": 0.05})

    assert change.effects == {"constraints.j1.trajectory": Effect.NEXT_COMMAND}
    rig.step(50)  # error far above 0.05 rad
    assert rig.results(first) == []
    second = rig.ctrl.send_goal(rig.now, traj((1.0, [2.0, 2.0])))
    rig.run_until(lambda _: rig.results(second))
    (result,) = rig.results(second)
    assert result.status is GoalStatus.ABORTED
    assert result.error_code is ErrorCode.PATH_TOLERANCE_VIOLATED
    assert rig.results(first)[0].status is GoalStatus.CANCELED  # preempted, not aborted


def test_goal_checks_change_from_the_next_goal() -> None:
    """Section 7 step 2 / 5: the goal checks read the parameters when a goal arrives."""
    rig = Rig(make_config(allow_nonzero_velocity_at_trajectory_end=True), [0.0, 0.0])
    moving_end = traj((1.0, [1.0, 1.0]), velocities=[0.5, 0.5])
    rig.ctrl.send_goal(rig.now, moving_end)
    rig.ctrl.set_parameters({"allow_nonzero_velocity_at_trajectory_end": False})
    with pytest.raises(GoalRejected, match="velocit"):
        rig.ctrl.send_goal(rig.now, moving_end)


def test_cmd_timeout_takes_effect_at_the_next_activation() -> None:
    """Section 1 and 3 (activate step 7): upstream resolves ``cmd_timeout`` in on_activate,
    against the ``goal_time`` of that moment; a runtime change waits for the next activation."""
    cfg = make_config(constraints={j: {"goal": 0.01} for j in NAMES})  # goal_time 0: forever
    rig = Rig(cfg, [0.0, 0.0])
    change = rig.ctrl.set_parameters({"cmd_timeout": 0.2})
    assert change.effects == {"cmd_timeout": Effect.NEXT_ACTIVATION}
    goal = rig.ctrl.send_goal(rig.now, traj((0.5, [1.0, 1.0])))
    rig.mirror.frozen = True  # never inside the goal tolerance
    rig.step(150)  # 1.5 s: 1 s past the end, five times the new cmd_timeout
    assert rig.results(goal) == []

    rig.events.extend(rig.ctrl.deactivate(rig.now))
    rig.ctrl.activate(rig.now, rig.mirror.state())
    goal = rig.ctrl.send_goal(rig.now, traj((0.5, [1.0, 1.0])))
    end_ns = rig.now + S // 2
    rig.run_until(lambda _: rig.results(goal), limit_s=2.0)
    (result,) = rig.results(goal)
    assert result.status is GoalStatus.ABORTED  # nothing else can end it: goal_time is 0
    assert result.error_code is ErrorCode.GOAL_TOLERANCE_VIOLATED
    assert "cmd_timeout" in result.error_string
    late_ns = result.time_ns - end_ns
    assert S // 5 - 2 * rig.period <= late_ns <= S // 5 + 2 * rig.period  # 0.2 s, not 0


def test_read_only_parameters_are_refused_naming_them_and_nothing_changes() -> None:
    """Section 1: parameters marked read-only cannot change after configuration."""
    rig = Rig(make_config(), [0.0, 0.0])
    before = rig.ctrl.get_parameters()
    with pytest.raises(ConfigurationError) as refused:
        rig.ctrl.set_parameters(
            {"gains.j1.p": 3.0, "interpolation_method": "none", "update_rate": 50.0}
        )
    message = str(refused.value)
    assert "interpolation_method" in message and "update_rate" in message
    assert "gains.j1.p" not in message
    assert "read-only" in message
    assert rig.ctrl.get_parameters() == before


def test_the_read_only_set_is_upstreams() -> None:
    """Section 1 marks joints, command_joints, the interfaces, action_monitor_rate,
    interpolation_method and interpolate_from_desired_state (open_loop_control) read-only; the
    loop rate is the controller manager's, and wraparound is fixed at configuration."""
    fixed = {name for name, p in PARAMETERS.items() if p.read_only}
    assert fixed == {
        "joints", "command_joints", "command_interfaces", "state_interfaces",
        "open_loop_control", "action_monitor_rate", "interpolation_method", "update_rate",
    }
    assert {name for name, p in GAIN_PARAMETERS.items() if p.read_only} == {
        "normalize_error", "angle_wraparound",
    }


@pytest.mark.parametrize(
    ("change", "file_entry"),
    [
        ({"constraints.j1.goal": -1}, {"constraints": {"j1": {"goal": -1}}}),
        ({"gains.j2.i_clamp": "big"}, {"gains": {"j2": {"i_clamp": "big"}}}),
        ({"gains.j1.q": 1.0}, {"gains": {"j1": {"q": 1.0}}}),
        ({"gains.elbow.p": 1.0}, {"gains": {"elbow": {"p": 1.0}}}),
        ({"cmd_timeout": True}, {"cmd_timeout": True}),
        ({"allow_partial_joints_goal": "yes"}, {"allow_partial_joints_goal": "yes"}),
        ({"constraints.goal_tim": 1.0}, {"constraints": {"goal_tim": 1.0}}),
    ],
)
def test_a_bad_value_gets_the_configuration_files_message(
    change: dict[str, Any], file_entry: dict[str, Any]
) -> None:
    """Section 7 step 2: a change is validated as the parameter file is (same messages)."""
    cfg = make_config()
    with pytest.raises(ConfigurationError) as from_file:
        load_config({
            "joints": list(NAMES), "command_interfaces": ["position"],
            "state_interfaces": ["position", "velocity"], **file_entry,
        })
    rig = Rig(cfg, [0.0, 0.0])
    with pytest.raises(ConfigurationError) as at_runtime:
        rig.ctrl.set_parameters(change)
    assert str(at_runtime.value) == str(from_file.value)
    assert at_runtime.value.path == from_file.value.path


def test_get_parameters_names_every_parameter_and_reflects_a_change() -> None:
    """Section 1: the parameter list with ROS names (``gains.<joint>.p``)."""
    rig = Rig(make_config(), [0.0, 0.0])
    values = rig.ctrl.get_parameters()
    assert list(values) == parameter_names(rig.ctrl.config)
    assert values["constraints.goal_time"] == 0.0 and values["joints"] == ["j1", "j2"]
    change = rig.ctrl.set_parameters({"constraints.goal_time": 2, "gains.j2.d": 0.5})
    assert change.values == {"constraints.goal_time": 2.0, "gains.j2.d": 0.5}
    assert rig.ctrl.get_parameters(["gains.j2.d", "constraints.goal_time"]) == change.values
    with pytest.raises(ConfigurationError, match="'gains.j3'|j3"):
        rig.ctrl.get_parameters(["gains.j3.p"])


def test_a_change_reports_the_warnings_it_introduces() -> None:
    """Section 1: cmd_timeout is ignored unless it exceeds goal_time (jtc-hw check warns)."""
    rig = Rig(make_config(cmd_timeout=1.0), [0.0, 0.0])
    change = rig.ctrl.set_parameters({"constraints.goal_time": 2.0})
    assert len(change.warnings) == 1 and "cmd_timeout" in change.warnings[0]


def test_apply_parameters_refuses_a_configuration_with_other_read_only_values() -> None:
    """Section 1: the loop process applies a change checked elsewhere; read-only ones cannot
    slip through that way either."""
    rig = Rig(make_config(), [0.0, 0.0])
    other = make_config(gains={"j1": {"angle_wraparound": True}})
    with pytest.raises(ConfigurationError, match=r"gains\.j1\.angle_wraparound"):
        rig.ctrl.apply_parameters(other)
    assert rig.ctrl.config.gains["j1"].angle_wraparound is False


def test_a_configuration_crosses_a_process_boundary_unchanged() -> None:
    """The daemon validates a change once (API process) and pickles the result to the loop."""
    cfg = make_config(constraints={"j1": {"goal": 0.02}}, gains={"j2": {"p": 3.0}})
    copy = pickle.loads(pickle.dumps(cfg))
    assert copy == cfg
    assert np.isclose(copy.gains["j2"].p, 3.0)
    with pytest.raises(TypeError):
        copy.gains["j1"] = None  # still read-only after the trip

    rig = Rig(make_config(), [0.0, 0.0])
    changed = rig.ctrl.set_parameters({"gains.j1.p": 4.0}).config
    rig.ctrl.apply_parameters(pickle.loads(pickle.dumps(changed)))
    assert rig.ctrl.get_parameters(["gains.j1.p"]) == {"gains.j1.p": 4.0}
    assert not any(isinstance(e, GoalResult) for e in rig.events)
