"""Configuration loading and validation (jtc_hw.config: the controller's parameters)."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
from pathlib import Path
from typing import Any

import pytest
import yaml

from jtc_hw.config.controller import (
    ALLOWED_COMMAND_INTERFACE_COMBINATIONS,
    CONTROLLER_TYPE,
    DEFAULTS,
    Constraints,
    ControllerConfig,
    Gains,
    JointConstraints,
)
from jtc_hw.config.controller_file import config_to_dict
from jtc_hw.config.reading import load_config
from jtc_hw.controller.parameters import explain
from jtc_hw.errors import ConfigurationError

BASE: dict[str, Any] = {
    "joints": ["j1", "j2"],
    "command_interfaces": ["position"],
    "state_interfaces": ["position", "velocity"],
}


def plain(**params: Any) -> dict[str, Any]:
    mapping = copy.deepcopy(BASE)
    mapping.update(params)
    return mapping


def nested(params: dict[str, Any], name: str = "arm_controller", **cm: Any) -> dict[str, Any]:
    data: dict[str, Any] = {name: {"ros__parameters": params}}
    if cm:
        data["controller_manager"] = {"ros__parameters": cm}
    return data


def error_of(source: Any, controller_name: str | None = None) -> ConfigurationError:
    with pytest.raises(ConfigurationError) as info:
        load_config(source, controller_name)
    return info.value


# The snippet of "Using Joint Trajectory Controller(s)", with `type` indented under the
# controller's name (as printed it sits next to it).
REFERENCE_SNIPPET = """\
controller_manager:
  ros__parameters:
    joint_trajectory_controller:
      type: "joint_trajectory_controller/JointTrajectoryController"

joint_trajectory_controller:
  ros__parameters:
    joints:
      - joint1
      - joint2
      - joint3
      - joint4
      - joint5
      - joint6

    command_interfaces:
      - position

    state_interfaces:
      - position
      - velocity

    state_publish_rate: 50.0
    action_monitor_rate: 20.0

    allow_partial_joints_goal: false
    open_loop_control: true
    constraints:
      stopped_velocity_tolerance: 0.01
      goal_time: 0.0
      joint1:
        trajectory: 0.05
        goal: 0.03
"""

# "An example parameter file", verbatim.
REFERENCE_EXAMPLE_FILE = """\
joint_trajectory_controller:
  ros__parameters:
    action_monitor_rate: 20.0
    allow_integration_in_goal_trajectories: false
    allow_nonzero_velocity_at_trajectory_end: true
    allow_partial_joints_goal: false
    cmd_timeout: 0.0
    command_interfaces: '{}'
    command_joints: '{}'
    constraints:
      <joints>:
        goal: 0.0
        trajectory: 0.0
      goal_time: 0.0
      stopped_velocity_tolerance: 0.01
    gains:
      <joints>:
        angle_wraparound: false
        d: 0.0
        ff_velocity_scale: 0.0
        i: 0.0
        i_clamp: 0.0
        normalize_error: false
        p: 0.0
    interpolation_method: splines
    joints: '{}'
    open_loop_control: false
    set_last_command_interface_value_as_state_on_activation: true
    state_interfaces: '{}'
    state_publish_rate: 50.0
"""


# ------------------------------------------------------------------------------------------
# Forms and sources
# ------------------------------------------------------------------------------------------


def test_plain_mapping() -> None:
    cfg = load_config(plain(update_rate=250))
    assert cfg.name == "joint_trajectory_controller"
    assert cfg.joints == ("j1", "j2")
    assert cfg.command_interfaces == ("position",)
    assert cfg.state_interfaces == ("position", "velocity")
    assert cfg.update_rate == 250.0 and isinstance(cfg.update_rate, float)


def test_plain_mapping_takes_controller_name_as_its_name() -> None:
    assert load_config(plain(), "left_arm").name == "left_arm"


def test_nested_mapping() -> None:
    cfg = load_config(nested(plain(cmd_timeout=0.5), update_rate=500))
    assert cfg.name == "arm_controller"
    assert cfg.cmd_timeout == 0.5
    assert cfg.update_rate == 500.0


@pytest.mark.parametrize("as_path", [str, Path])
def test_plain_file(tmp_path: Path, as_path: Any) -> None:
    file = tmp_path / "plain.yaml"
    file.write_text(yaml.safe_dump(plain(open_loop_control=True)))
    cfg = load_config(as_path(file))
    assert cfg.open_loop_control is True
    assert cfg.joints == ("j1", "j2")


def test_nested_file(tmp_path: Path) -> None:
    file = tmp_path / "nested.yaml"
    file.write_text(yaml.safe_dump(nested(plain(), name="jtc", update_rate=125)))
    cfg = load_config(file)
    assert (cfg.name, cfg.update_rate) == ("jtc", 125.0)


def test_reference_snippet(tmp_path: Path) -> None:
    file = tmp_path / "snippet.yaml"
    file.write_text(REFERENCE_SNIPPET)
    cfg = load_config(file)
    assert cfg.name == "joint_trajectory_controller"
    assert cfg.joints == tuple(f"joint{i}" for i in range(1, 7))
    assert cfg.open_loop_control is True
    assert cfg.constraints.joints["joint1"] == JointConstraints(trajectory=0.05, goal=0.03)
    assert cfg.constraints.joints["joint6"] == JointConstraints()
    assert cfg.update_rate == 100.0  # not in the snippet: our default


def test_reference_snippet_as_printed_also_loads(tmp_path: Path) -> None:
    """As printed, `type` is a sibling of the controller name; the manager's keys are ignored."""
    printed = REFERENCE_SNIPPET.replace('      type: "', '    type: "')
    assert yaml.safe_load(printed)["controller_manager"]["ros__parameters"] == {
        "joint_trajectory_controller": None,
        "type": CONTROLLER_TYPE,
    }
    file = tmp_path / "printed.yaml"
    file.write_text(printed)
    assert load_config(file).joints[0] == "joint1"


def test_reference_example_file_points_at_the_placeholder(tmp_path: Path) -> None:
    file = tmp_path / "example.yaml"
    file.write_text(REFERENCE_EXAMPLE_FILE)
    err = error_of(file)
    assert err.path == "constraints.<joints>"
    assert "placeholder" in str(err) and "replace it with a joint name" in str(err)


def test_reference_example_file_without_placeholders_needs_joints() -> None:
    data = yaml.safe_load(REFERENCE_EXAMPLE_FILE)
    params = data["joint_trajectory_controller"]["ros__parameters"]
    del params["constraints"]["<joints>"], params["gains"]["<joints>"]
    err = error_of(data)
    assert err.path == "joints" and "must not be empty" in str(err)
    params["joints"] = ["j1"]
    err = error_of(data)
    assert err.path == "command_interfaces" and "must not be empty" in str(err)
    params["command_interfaces"] = ["position"]
    err = error_of(data)
    assert err.path == "state_interfaces" and "must not be empty" in str(err)
    params["state_interfaces"] = ["position"]
    cfg = load_config(data)
    assert cfg.command_joints == ()


def test_gains_placeholder_is_explained_too() -> None:
    err = error_of(plain(gains={"<joints>": {"p": 1.0}}))
    assert err.path == "gains.<joints>" and "placeholder" in str(err)
    assert "j1, j2" in str(err)


@pytest.mark.parametrize("empty", ["{}", "[]", [], " {} "])
def test_empty_list_spellings(empty: Any) -> None:
    assert load_config(plain(command_joints=empty)).command_joints == ()


def test_reserved_top_level_keys_are_ignored() -> None:
    data = nested(plain())
    data["hardware"] = {"anything": 1}
    data["daemon"] = {"port": 1234}
    assert load_config(data).name == "arm_controller"
    assert load_config(plain(hardware={"x": 1}, daemon=None)).joints == ("j1", "j2")


def test_unknown_top_level_key_in_nested_form() -> None:
    data = nested(plain())
    data["controler_manager"] = {"foo": 1}
    err = error_of(data)
    assert err.path == "controler_manager"
    assert "did you mean 'controller_manager'?" in str(err)


def test_misspelt_ros_parameters_is_pointed_out() -> None:
    data = nested(plain())
    data["other"] = {"ros_parameters": {}}
    err = error_of(data)
    assert "did you mean 'ros__parameters' instead of 'ros_parameters'?" in str(err)


def test_extra_key_next_to_ros_parameters() -> None:
    data = nested(plain())
    data["arm_controller"]["joints"] = ["j1"]
    err = error_of(data)
    assert err.path == "arm_controller.joints" and "next to 'ros__parameters'" in str(err)


def test_empty_ros_parameters_reports_missing_joints() -> None:
    err = error_of({"jtc": {"ros__parameters": None}})
    assert err.path == "joints" and "missing required parameter 'joints'" in str(err)


# ------------------------------------------------------------------------------------------
# Controller selection and update rate
# ------------------------------------------------------------------------------------------


def two_controllers(**cm: Any) -> dict[str, Any]:
    data = nested(plain(), name="left", **cm)
    data["right"] = {"ros__parameters": plain(joints=["r1", "r2"])}
    return data


def test_several_controllers_need_a_name() -> None:
    err = error_of(two_controllers())
    assert "several controllers (left, right)" in str(err)
    assert "controller_name" in str(err)


def test_controller_name_selects() -> None:
    data = two_controllers()
    assert load_config(data, "right").joints == ("r1", "r2")
    assert load_config(data, "left").joints == ("j1", "j2")


def test_unknown_controller_name_suggests() -> None:
    err = error_of(two_controllers(), "rigth")
    assert "no controller section named 'rigth'" in str(err)
    assert "left, right" in str(err) and "did you mean 'right'?" in str(err)


def test_only_controller_declared_with_our_type_is_chosen() -> None:
    data = two_controllers(
        right={"type": CONTROLLER_TYPE}, left={"type": "forward_command_controller/X"}
    )
    assert load_config(data).name == "right"


def test_selected_controller_with_another_type_is_refused() -> None:
    data = two_controllers(left={"type": "joint_state_broadcaster/JointStateBroadcaster"})
    err = error_of(data, "left")
    assert err.path == "controller_manager.ros__parameters.left.type"
    assert CONTROLLER_TYPE in str(err)


def test_update_rate_from_controller_manager() -> None:
    assert load_config(nested(plain(), update_rate=1000)).update_rate == 1000.0


def test_update_rate_from_controller_parameters() -> None:
    assert load_config(nested(plain(update_rate=50))).update_rate == 50.0


def test_update_rate_given_twice_must_agree() -> None:
    assert load_config(nested(plain(update_rate=200.0), update_rate=200)).update_rate == 200.0
    err = error_of(nested(plain(update_rate=50), update_rate=100))
    assert err.path == "update_rate" and "differs" in str(err) and "100" in str(err)


def test_controller_manager_update_rate_is_checked() -> None:
    err = error_of(nested(plain(), update_rate="fast"))
    assert err.path == "controller_manager.ros__parameters.update_rate"
    assert "expected a number, got 'fast' (str)" in str(err)


def test_controller_manager_without_ros_parameters() -> None:
    data = nested(plain())
    data["controller_manager"] = {"update_rate": 100}
    err = error_of(data)
    assert err.path == "controller_manager" and "ros__parameters" in str(err)


# ------------------------------------------------------------------------------------------
# Defaults (the reference's parameter list; start_with_holding from the older reference)
# ------------------------------------------------------------------------------------------

REFERENCE_DEFAULTS: dict[str, Any] = {
    "joints": (),
    "command_joints": (),
    "command_interfaces": (),
    "state_interfaces": (),
    "allow_partial_joints_goal": False,
    "open_loop_control": False,
    "allow_integration_in_goal_trajectories": False,
    "state_publish_rate": 50.0,
    "set_last_command_interface_value_as_state_on_activation": True,
    "action_monitor_rate": 20.0,
    "interpolation_method": "splines",
    "allow_nonzero_velocity_at_trajectory_end": True,
    "cmd_timeout": 0.0,
    "start_with_holding": True,
    "update_rate": 100.0,
    "constraints": {
        "stopped_velocity_tolerance": 0.01,
        "goal_time": 0.0,
        "decelerate_on_cancel": False,
        "<joints>": {"trajectory": 0.0, "goal": 0.0, "max_deceleration_on_cancel": 0.0},
    },
    "gains": {
        "<joints>": {
            "p": 0.0,
            "i": 0.0,
            "d": 0.0,
            "i_clamp": 0.0,
            "ff_velocity_scale": 0.0,
            "normalize_error": False,
            "angle_wraparound": False,
        }
    },
    "speed_scaling": {
        "initial_scaling_factor": 1.0,
        "max_scaling_factor": 1.0,
        "state_interface": "",
        "command_interface": "",
        "ramp_time": 0.5,
    },
}


def _thaw(value: Any) -> Any:
    if hasattr(value, "items"):
        return {k: _thaw(v) for k, v in value.items()}
    return value


def test_defaults_table_matches_reference() -> None:
    assert _thaw(DEFAULTS) == REFERENCE_DEFAULTS


def test_loaded_defaults_match_reference() -> None:
    cfg = load_config(BASE)
    for name, value in REFERENCE_DEFAULTS.items():
        if name in ("constraints", "gains", "speed_scaling") or name in BASE:
            continue
        assert getattr(cfg, name) == value, name
        assert type(getattr(cfg, name)) is type(value), name
    c = REFERENCE_DEFAULTS["constraints"]
    assert cfg.constraints.stopped_velocity_tolerance == c["stopped_velocity_tolerance"]
    assert cfg.constraints.goal_time == c["goal_time"]
    g = REFERENCE_DEFAULTS["gains"]["<joints>"]
    for joint in cfg.joints:
        assert dataclasses.asdict(cfg.constraints.joints[joint]) == c["<joints>"]
        assert dataclasses.asdict(cfg.gains[joint]) == g
    assert dataclasses.asdict(cfg.speed_scaling) == REFERENCE_DEFAULTS["speed_scaling"]


def test_dataclass_defaults_match_reference() -> None:
    assert dataclasses.asdict(Gains()) == REFERENCE_DEFAULTS["gains"]["<joints>"]
    assert dataclasses.asdict(JointConstraints()) == REFERENCE_DEFAULTS["constraints"]["<joints>"]
    assert Constraints().stopped_velocity_tolerance == 0.01
    assert Constraints().goal_time == 0.0


def test_every_joint_gets_constraints_and_gains() -> None:
    cfg = load_config(plain(constraints={"j2": {"goal": 0.1}}, gains={"j1": {"p": 2}}))
    assert list(cfg.constraints.joints) == ["j1", "j2"]
    assert list(cfg.gains) == ["j1", "j2"]
    assert cfg.constraints.joints["j2"].goal == 0.1
    assert cfg.constraints.joints["j2"].trajectory == 0.0
    assert cfg.gains["j1"].p == 2.0 and cfg.gains["j2"] == Gains()


# ------------------------------------------------------------------------------------------
# Validation
# ------------------------------------------------------------------------------------------

INVALID: list[tuple[dict[str, Any], str, list[str]]] = [
    # types
    ({"constraints": {"j1": {"goal": "abc"}}}, "constraints.j1.goal",
     ["expected a number, got 'abc' (str)"]),
    ({"state_publish_rate": True}, "state_publish_rate", ["expected a number, got True (bool)"]),
    ({"cmd_timeout": math.nan}, "cmd_timeout", ["expected a finite number", "nan"]),
    ({"cmd_timeout": math.inf}, "cmd_timeout", ["expected a finite number", "inf"]),
    ({"update_rate": None}, "update_rate", ["expected a number, got None"]),
    ({"open_loop_control": 1}, "open_loop_control", ["expected true or false, got 1 (int)"]),
    ({"open_loop_control": "true"}, "open_loop_control",
     ["expected true or false", "without quotes"]),
    ({"gains": {"j1": {"angle_wraparound": "yes"}}}, "gains.j1.angle_wraparound",
     ["expected true or false, got 'yes' (str)"]),
    ({"interpolation_method": 3}, "interpolation_method", ["expected a string, got 3 (int)"]),
    ({"joints": "j1"}, "joints", ["expected a list of strings, got 'j1' (str)", "[j1]"]),
    ({"joints": ["j1", 2]}, "joints", ["element 1 is 2 (int)"]),
    ({"joints": ["j1", ""]}, "joints", ["element 1 is an empty name"]),
    ({"command_interfaces": {"position": 1}}, "command_interfaces",
     ["expected a list of strings"]),
    ({"constraints": [1]}, "constraints", ["expected a mapping, got [1] (list)"]),
    ({"gains": {"j1": 1.0}}, "gains.j1", ["expected a mapping, got 1.0 (float)"]),
    ({"constraints": {1: {}}}, "constraints", ["keys must be strings", "quote it"]),
    # duplicates
    ({"joints": ["j1", "j2", "j1"]}, "joints", ["'j1' more than once"]),
    ({"command_joints": ["c1", "c1"]}, "command_joints", ["'c1' more than once"]),
    ({"command_interfaces": ["position", "position"]}, "command_interfaces",
     ["'position' more than once"]),
    ({"state_interfaces": ["position", "velocity", "velocity"]}, "state_interfaces",
     ["'velocity' more than once"]),
    # empty / lengths
    ({"joints": []}, "joints", ["must not be empty"]),
    ({"command_interfaces": "{}"}, "command_interfaces", ["must not be empty"]),
    ({"state_interfaces": []}, "state_interfaces", ["must not be empty"]),
    ({"command_joints": ["c1"]}, "command_joints",
     ["names [c1], which is not in joints (j1, j2)", "must be a subset of joints"]),
    ({"command_joints": ["j1", "j2", "j3"]}, "command_joints",
     ["has 3 names but joints has only 2"]),
    # allowed values
    ({"command_interfaces": ["positon"]}, "command_interfaces",
     ["'positon' is not an allowed interface type",
      "[position, velocity, acceleration, effort]", "did you mean 'position'?"]),
    ({"state_interfaces": ["position", "effort"]}, "state_interfaces",
     ["'effort' is not an allowed interface type", "[position, velocity, acceleration]"]),
    ({"interpolation_method": "spline"}, "interpolation_method",
     ["'spline' is not allowed", "'splines', 'none'", "did you mean 'splines'?"]),
    # ranges
    ({"state_publish_rate": 0.05}, "state_publish_rate", [">= 0.1", "0.05"]),
    ({"action_monitor_rate": 0}, "action_monitor_rate", [">= 0.1", "got 0"]),
    ({"update_rate": 0}, "update_rate", [">= 0.1"]),
    ({"update_rate": -100}, "update_rate", [">= 0.1", "-100"]),
    ({"cmd_timeout": -1.0}, "cmd_timeout", [">= 0", "-1.0"]),
    ({"constraints": {"goal_time": -0.5}}, "constraints.goal_time", [">= 0", "-0.5"]),
    ({"constraints": {"stopped_velocity_tolerance": -0.01}},
     "constraints.stopped_velocity_tolerance", [">= 0"]),
    ({"constraints": {"j2": {"trajectory": -1}}}, "constraints.j2.trajectory", [">= 0", "-1"]),
    ({"constraints": {"j1": {"goal": -0.1}}}, "constraints.j1.goal", [">= 0"]),
    ({"gains": {"j2": {"i_clamp": -2.0}}}, "gains.j2.i_clamp", [">= 0", "-2.0"]),
    # unknown keys
    ({"allow_partial_joint_goal": True}, "allow_partial_joint_goal",
     ["unknown parameter 'allow_partial_joint_goal'",
      "did you mean 'allow_partial_joints_goal'?"]),
    ({"constraints": {"goal_tme": 1.0}}, "constraints.goal_tme",
     ["'goal_tme' is not a configured joint", "(joints: j1, j2)", "did you mean 'goal_time'?"]),
    ({"constraints": {"j3": {"goal": 1.0}}}, "constraints.j3",
     ["'j3' is not a configured joint", "stopped_velocity_tolerance, goal_time",
      "(joints: j1, j2)"]),
    ({"constraints": {"j1": {"gaol": 1.0}}}, "constraints.j1.gaol",
     ["unknown parameter 'gaol'", "did you mean 'goal'?"]),
    ({"gains": {"joint1": {"p": 1.0}}}, "gains.joint1",
     ["'joint1' is not a configured joint", "(joints: j1, j2)"]),
    ({"gains": {"j1": {"kp": 1.0}}}, "gains.j1.kp", ["unknown parameter 'kp'"]),
    ({"gains": {"j1": {"angle_wrap_around": True}}}, "gains.j1.angle_wrap_around",
     ["did you mean 'angle_wraparound'?"]),
    ({"constraints.goal_time": 1.0}, "constraints.goal_time",
     ["unknown parameter", "nest it under 'constraints'"]),
    ({"zzz": 1}, "zzz", ["unknown parameter 'zzz'", "known parameters: joints,"]),
]


@pytest.mark.parametrize(("change", "path", "fragments"), INVALID)
def test_invalid(change: dict[str, Any], path: str, fragments: list[str]) -> None:
    err = error_of(plain(**change))
    assert err.path == path
    message = str(err)
    assert message.startswith(f"{path}: ")
    for fragment in fragments:
        assert fragment in message


@pytest.mark.parametrize("missing", ["joints", "command_interfaces", "state_interfaces"])
def test_missing_required(missing: str) -> None:
    params = plain()
    del params[missing]
    err = error_of(params)
    assert err.path == missing
    assert f"missing required parameter '{missing}'" in str(err)


def test_error_carries_the_value() -> None:
    err = error_of(plain(constraints={"j1": {"goal": "abc"}}))
    assert err.value == "abc"
    assert str(err) == "constraints.j1.goal: expected a number, got 'abc' (str)"


def test_typo_suggestion_exact_message() -> None:
    err = error_of(plain(allow_partial_joint_goal=True))
    assert str(err).endswith(
        "unknown parameter 'allow_partial_joint_goal'; did you mean 'allow_partial_joints_goal'?"
    )


def test_numbers_accept_int_and_become_float() -> None:
    cfg = load_config(plain(state_publish_rate=10, constraints={"goal_time": 1}))
    assert cfg.state_publish_rate == 10.0 and isinstance(cfg.state_publish_rate, float)
    assert isinstance(cfg.constraints.goal_time, float)


def test_command_joints_of_the_right_length() -> None:
    assert load_config(plain(command_joints=["c1", "c2"])).command_joints == ("c1", "c2")


# ------------------------------------------------------------------------------------------
# Interface combinations
# ------------------------------------------------------------------------------------------

ALLOWED_COMMAND = [
    ["position"],
    ["position", "velocity"],
    ["velocity", "position"],
    ["position", "velocity", "acceleration"],
    ["acceleration", "position", "velocity"],
    ["velocity"],
    ["effort"],
]


@pytest.mark.parametrize("command", ALLOWED_COMMAND)
def test_allowed_command_combination(command: list[str]) -> None:
    cfg = load_config(plain(command_interfaces=command, state_interfaces=["position", "velocity"]))
    assert cfg.command_interfaces == tuple(command)


ALL_COMMAND_SETS = [
    list(c)
    for n in range(1, 5)
    for c in itertools.combinations(["position", "velocity", "acceleration", "effort"], n)
]
FORBIDDEN_COMMAND = [
    c for c in ALL_COMMAND_SETS
    if frozenset(c) not in {frozenset(a) for a in ALLOWED_COMMAND_INTERFACE_COMBINATIONS}
]


def test_forbidden_command_list_is_complete() -> None:
    assert len(ALL_COMMAND_SETS) == 15 and len(FORBIDDEN_COMMAND) == 10


@pytest.mark.parametrize("command", FORBIDDEN_COMMAND)
def test_forbidden_command_combination(command: list[str]) -> None:
    err = error_of(
        plain(command_interfaces=command, state_interfaces=["position", "velocity", "acceleration"])
    )
    assert err.path == "command_interfaces"
    message = str(err)
    assert f"combination [{', '.join(command)}] is not supported" in message
    assert (
        "allowed combinations: [position], [position, velocity], "
        "[position, velocity, acceleration], [velocity], [effort]"
    ) in message


@pytest.mark.parametrize(
    ("command", "reason"),
    [
        (["position", "effort"], "'effort' has to be the only command interface"),
        (["velocity", "acceleration"], "'velocity' can only be used alone or together"),
        (["position", "acceleration"], "'acceleration' can only be used together with"),
        (["acceleration"], "'acceleration' can only be used together with"),
    ],
)
def test_forbidden_command_combination_says_why(command: list[str], reason: str) -> None:
    assert reason in str(error_of(plain(command_interfaces=command)))


@pytest.mark.parametrize(
    "state", [["position"], ["position", "velocity"], ["position", "velocity", "acceleration"],
              ["velocity", "position"], ["acceleration", "velocity", "position"]]
)
def test_allowed_state_combination_with_position_command(state: list[str]) -> None:
    assert load_config(plain(state_interfaces=state)).state_interfaces == tuple(state)


@pytest.mark.parametrize(
    ("state", "reason"),
    [
        (["velocity"], "velocity state interface cannot be used if the position interface is "
                       "missing"),
        (["acceleration"], "acceleration state interface cannot be used if position and velocity"),
        (["position", "acceleration"], "acceleration state interface cannot be used"),
        (["velocity", "acceleration"], "acceleration state interface cannot be used"),
    ],
)
def test_forbidden_state_combination(state: list[str], reason: str) -> None:
    err = error_of(plain(state_interfaces=state))
    assert err.path == "state_interfaces"
    assert f"combination [{', '.join(state)}] is not supported" in str(err)
    assert reason in str(err)
    assert "allowed combinations: [position], [position, velocity], " in str(err)


@pytest.mark.parametrize(
    "command", [["velocity"], ["effort"], ["position", "velocity", "acceleration"]]
)
def test_command_needing_velocity_state(command: list[str]) -> None:
    err = error_of(plain(command_interfaces=command, state_interfaces=["position"]))
    assert err.path == "state_interfaces"
    assert f"with command_interfaces [{', '.join(command)}]" in str(err)
    assert "must include position and velocity, got [position]" in str(err)


@pytest.mark.parametrize("command", [["position"], ["position", "velocity"]])
def test_command_accepting_position_state_only(command: list[str]) -> None:
    assert load_config(plain(command_interfaces=command, state_interfaces=["position"]))


STATE_SETS = [
    list(c) for n in range(1, 4)
    for c in itertools.combinations(["position", "velocity", "acceleration"], n)
]


@pytest.mark.parametrize("command", ALL_COMMAND_SETS, ids=lambda c: "+".join(c))
@pytest.mark.parametrize("state", STATE_SETS, ids=lambda s: "+".join(s))
def test_every_combination_follows_the_reference(command: list[str], state: list[str]) -> None:
    """Each rule of "Hardware interface types", written out independently."""
    c, s = set(command), set(state)
    ok = frozenset(c) in {
        frozenset(x) for x in (["position"], ["position", "velocity"],
                               ["position", "velocity", "acceleration"], ["velocity"], ["effort"])
    }
    if c == {"velocity"} or "effort" in c or "acceleration" in c:
        ok = ok and {"position", "velocity"} <= s
    ok = ok and "position" in s  # at least position feedback
    ok = ok and ("velocity" not in s or "position" in s)
    ok = ok and ("acceleration" not in s or {"position", "velocity"} <= s)
    params = plain(command_interfaces=command, state_interfaces=state)
    if ok:
        load_config(params)
    else:
        with pytest.raises(ConfigurationError):
            load_config(params)


# ------------------------------------------------------------------------------------------
# Immutability and direct construction
# ------------------------------------------------------------------------------------------


def test_immutable() -> None:
    cfg = load_config(plain(gains={"j1": {"p": 1.0}}))
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.cmd_timeout = 1.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.constraints.goal_time = 1.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.gains["j1"].p = 2.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.constraints.joints["j1"].goal = 2.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        cfg.gains["j3"] = Gains()  # type: ignore[index]
    with pytest.raises(TypeError):
        cfg.constraints.joints["j3"] = JointConstraints()  # type: ignore[index]
    assert isinstance(cfg.joints, tuple) and isinstance(cfg.command_interfaces, tuple)


def test_input_mapping_is_not_shared() -> None:
    params = plain(gains={"j1": {"p": 1.0}})
    cfg = load_config(params)
    params["joints"].append("j3")
    params["gains"]["j1"]["p"] = 5.0
    assert cfg.joints == ("j1", "j2") and cfg.gains["j1"].p == 1.0


def test_direct_construction_is_validated_and_filled() -> None:
    cfg = ControllerConfig(
        joints=["a"],  # type: ignore[arg-type]
        command_interfaces=("effort",),
        state_interfaces=("position", "velocity"),
        gains={"a": Gains(p=3)},
    )
    assert cfg.joints == ("a",) and cfg.gains["a"].p == 3.0
    assert cfg.constraints.joints["a"] == JointConstraints()
    with pytest.raises(ConfigurationError, match=r"gains.b: 'b' is not a configured joint"):
        ControllerConfig(
            joints=("a",), command_interfaces=("position",), state_interfaces=("position",),
            gains={"b": Gains()},
        )


def test_replace_is_validated() -> None:
    cfg = load_config(plain())
    assert dataclasses.replace(cfg, cmd_timeout=2).cmd_timeout == 2.0
    with pytest.raises(ConfigurationError, match="cmd_timeout: must be >= 0"):
        dataclasses.replace(cfg, cmd_timeout=-1.0)
    with pytest.raises(ConfigurationError, match="command_interfaces"):
        dataclasses.replace(cfg, command_interfaces=("acceleration",))


# ------------------------------------------------------------------------------------------
# Derived properties
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("command", "open_loop", "expected"),
    [
        (["position"], False, False),
        (["position", "velocity"], False, False),
        (["position", "velocity", "acceleration"], False, False),
        (["velocity"], False, True),
        (["velocity"], True, False),
        (["effort"], False, True),
        (["effort"], True, True),
    ],
)
def test_use_pid(command: list[str], open_loop: bool, expected: bool) -> None:
    cfg = load_config(plain(command_interfaces=command, open_loop_control=open_loop))
    assert cfg.use_pid is expected


@pytest.mark.parametrize(
    ("cmd_timeout", "goal_time", "expected"),
    [(0.0, 0.0, 0.0), (0.5, 0.0, 0.5), (0.5, 0.4, 0.5), (0.5, 0.5, 0.0), (0.5, 1.0, 0.0)],
)
def test_effective_cmd_timeout(cmd_timeout: float, goal_time: float, expected: float) -> None:
    cfg = load_config(plain(cmd_timeout=cmd_timeout, constraints={"goal_time": goal_time}))
    assert cfg.effective_cmd_timeout == expected
    assert cfg.cmd_timeout == cmd_timeout


def test_wraparound() -> None:
    cfg = load_config(
        plain(joints=["a", "b", "c"], gains={"a": {"angle_wraparound": True},
                                             "c": {"normalize_error": True}})
    )
    assert cfg.wraparound == (True, False, True)
    assert cfg.gains["c"].wraps and not cfg.gains["b"].wraps


def test_has_command_and_state() -> None:
    cfg = load_config(plain(command_interfaces=["position", "velocity"]))
    assert cfg.has_command("velocity") and not cfg.has_command("effort")
    assert cfg.has_state("velocity") and not cfg.has_state("acceleration")


# ------------------------------------------------------------------------------------------
# explain()
# ------------------------------------------------------------------------------------------


# Effort and velocity command interfaces below come with a cmd_timeout: without one, the
# default allow_nonzero_velocity_at_trajectory_end (true) is warned about (issue 11; tested in
# tests/controller/test_sampling.py).
GUARDED = {"cmd_timeout": 1.0}


def test_explain_nothing_to_say() -> None:
    assert explain(load_config(plain())) == []
    assert explain(load_config(plain(command_interfaces=["effort"], **GUARDED, gains={
        "j1": {"p": 1, "i": 1, "i_clamp": 1}, "j2": {"p": 1}}))) == []


def test_explain_integral_without_clamp() -> None:
    cfg = load_config(plain(command_interfaces=["effort"], **GUARDED,
                            gains={"j1": {"p": 1, "i": 0.5}, "j2": {"p": 1}}))
    (warning,) = explain(cfg)
    assert warning.startswith("gains.j1.i_clamp:")
    assert "the integral term is clamped to zero; set i_clamp" in warning


def test_explain_gains_ignored() -> None:
    cfg = load_config(plain(gains={"j1": {"p": 10.0, "angle_wraparound": True}}))
    (warning,) = explain(cfg)
    assert warning.startswith("gains.j1:") and "(p)" in warning
    assert "ignored with these command interfaces" in warning
    cfg = load_config(plain(command_interfaces=["velocity"], open_loop_control=True, **GUARDED,
                            gains={"j2": {"d": 1.0}}))
    (warning,) = explain(cfg)
    assert warning.startswith("gains.j2:") and "open_loop_control" in warning


def test_explain_zero_gains_with_pid() -> None:
    cfg = load_config(plain(command_interfaces=["velocity"], **GUARDED, gains={"j1": {"p": 1}}))
    (warning,) = explain(cfg)
    assert warning.startswith("gains.j2:") and "velocity command of 'j2' is always 0" in warning


def test_explain_cmd_timeout_ignored() -> None:
    cfg = load_config(plain(cmd_timeout=0.5, constraints={"goal_time": 0.5}))
    (warning,) = explain(cfg)
    assert warning.startswith("cmd_timeout:")
    assert "ignored: it must be greater than constraints.goal_time" in warning


def test_explain_normalize_error_deprecated() -> None:
    cfg = load_config(plain(gains={"j2": {"normalize_error": True}}))
    (warning,) = explain(cfg)
    assert warning.startswith("gains.j2.normalize_error:")
    assert "deprecated" in warning and "angle_wraparound" in warning


# ------------------------------------------------------------------------------------------
# config_to_dict
# ------------------------------------------------------------------------------------------

RICH: dict[str, Any] = plain(
    command_interfaces=["velocity"],
    command_joints=["c1", "c2"],
    open_loop_control=False,
    cmd_timeout=1.5,
    update_rate=333.0,
    interpolation_method="none",
    start_with_holding=False,
    constraints={"goal_time": 0.5, "j1": {"goal": 0.01, "trajectory": 0.2}},
    gains={"j2": {"p": 3.0, "i": 0.1, "i_clamp": 2.0, "angle_wraparound": True}},
)


def test_round_trip_plain() -> None:
    cfg = load_config(RICH)
    data = config_to_dict(cfg)
    assert "name" not in data and data["joints"] == ["j1", "j2"]
    assert load_config(data) == cfg


def test_round_trip_nested_keeps_the_name(tmp_path: Path) -> None:
    cfg = load_config(nested(RICH, name="my_jtc"))
    data = config_to_dict(cfg, nested=True)
    assert data["controller_manager"]["ros__parameters"]["update_rate"] == 333
    file = tmp_path / "out.yaml"
    file.write_text(yaml.safe_dump(data))
    again = load_config(file)
    assert again == cfg and again.name == "my_jtc"


def test_round_trip_through_yaml_plain(tmp_path: Path) -> None:
    cfg = load_config(RICH, "x")
    file = tmp_path / "plain.yaml"
    file.write_text(yaml.safe_dump(config_to_dict(cfg)))
    assert load_config(file, "x") == cfg


def test_config_to_dict_returns_fresh_data() -> None:
    cfg = load_config(RICH)
    data = config_to_dict(cfg)
    data["gains"]["j2"]["p"] = 100.0
    data["joints"].append("j3")
    assert cfg.gains["j2"].p == 3.0 and config_to_dict(cfg)["joints"] == ["j1", "j2"]


# ------------------------------------------------------------------------------------------
# Files
# ------------------------------------------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    err = error_of(tmp_path / "nope.yaml")
    assert "cannot read configuration file" in str(err) and "nope.yaml" in str(err)


def test_invalid_yaml(tmp_path: Path) -> None:
    file = tmp_path / "bad.yaml"
    file.write_text("joints: [j1\n")
    message = str(error_of(file))
    assert "bad.yaml, line 2, column 1: not valid YAML: " in message  # one line, the position
    assert "\n" not in message


@pytest.mark.parametrize(
    ("content", "where", "what"),
    [
        (b"joints: [j1]\nname: caf\xe9\n", "line 2, column 10", "not UTF-8 text (byte 0xe9"),
        (b"\x89PNG\r\n\x1a\n\x00\x00", "line 1, column 1", "not UTF-8 text (byte 0x89"),
        (b"joints: [j1]\nx: \x00\x01\n", "line 2, column 4", "the character #x0000 is not"),
        (b"[" * 5000 + b"]" * 5000, "line 1, column 101", "nested more than 100 levels"),
        (
            b"".join(b"  " * i + b"a:\n" for i in range(5000)),
            "line 100, column 199",
            "nested more than 100 levels",
        ),
    ],
    ids=["latin-1", "binary", "control-character", "deep-flow", "deep-block"],
)
def test_an_unreadable_file_is_one_configuration_error_with_its_position(
    tmp_path: Path, content: bytes, where: str, what: str
) -> None:
    """Issue 21 point 7: not UTF-8, a binary file, YAML nested 5,000 levels deep raised
    UnicodeDecodeError and RecursionError out of load_config; now one line naming the file
    and the position."""
    file = tmp_path / "robot.yaml"
    file.write_bytes(content)
    message = str(error_of(file))
    assert f"configuration file {file}, {where}: " in message and what in message, message
    assert "\n" not in message


def test_nesting_up_to_the_limit_is_read(tmp_path: Path) -> None:
    from jtc_hw.config.reading import MAX_DEPTH, load_yaml

    deep = load_yaml("[" * MAX_DEPTH + "]" * MAX_DEPTH, "x")
    for _ in range(MAX_DEPTH - 1):
        deep = deep[0]
    assert deep == []
    with pytest.raises(ConfigurationError, match="x, line 1, column 101: nested more than"):
        load_yaml("[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1), "x")


def test_duplicate_yaml_key(tmp_path: Path) -> None:
    file = tmp_path / "dup.yaml"
    file.write_text(yaml.safe_dump(BASE) + "joints: [x]\n")
    err = error_of(file)
    assert "duplicate key 'joints'" in str(err)


def test_empty_file(tmp_path: Path) -> None:
    file = tmp_path / "empty.yaml"
    file.write_text("# nothing\n")
    assert "is empty" in str(error_of(file))


def test_top_level_not_a_mapping(tmp_path: Path) -> None:
    file = tmp_path / "list.yaml"
    file.write_text("- a\n- b\n")
    assert "mapping at the top level, got list" in str(error_of(file))


def test_wrong_source_type() -> None:
    with pytest.raises(TypeError, match="path or a mapping"):
        load_config(42)  # type: ignore[arg-type]


def test_nested_form_without_a_controller_section() -> None:
    err = error_of({"controller_manager": {"ros__parameters": {"update_rate": 100}}})
    assert "no controller section found" in str(err)


def test_direct_construction_rejects_wrong_section_types() -> None:
    with pytest.raises(ConfigurationError, match="constraints: expected a Constraints instance"):
        ControllerConfig(
            joints=("a",), command_interfaces=("position",), state_interfaces=("position",),
            constraints={"goal_time": 1.0},  # type: ignore[arg-type]
        )
    with pytest.raises(ConfigurationError, match="gains.a: expected a Gains instance"):
        ControllerConfig(
            joints=("a",), command_interfaces=("position",), state_interfaces=("position",),
            gains={"a": {"p": 1.0}},  # type: ignore[dict-item]
        )
    with pytest.raises(ConfigurationError, match="name: expected a non-empty controller name"):
        ControllerConfig(
            name="", joints=("a",), command_interfaces=("position",),
            state_interfaces=("position",),
        )
