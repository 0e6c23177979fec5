"""Reading joint limits (issue 12 part A): the ``limits`` section and URDF files."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml

from jtc_hw import ConfigurationError, load_config
from jtc_hw.config.controller_file import config_to_dict
from jtc_hw.config.limits import JointLimits
from jtc_hw.controller.parameters import explain, get_parameters, set_parameters

DATA = Path(__file__).resolve().parents[1] / "data"
URDF = DATA / "limits_arm.urdf"
JOINTS = ["shoulder", "elbow", "wrist", "rail"]


def plain(**extra: Any) -> dict[str, Any]:
    return {
        "joints": JOINTS,
        "command_interfaces": ["position"],
        "state_interfaces": ["position", "velocity"],
        **extra,
    }


def nested(limits: Any) -> dict[str, Any]:
    return {
        "controller_manager": {"ros__parameters": {"update_rate": 100}},
        "arm": {"ros__parameters": plain()},
        "hardware": [],
        "limits": limits,
    }


def test_per_joint_limits_from_the_yaml_section() -> None:
    cfg = load_config(plain(limits={
        "shoulder": {"position": [-2, 2], "velocity": 3, "acceleration": 10.0, "jerk": 200},
        "rail": {"velocity": 0.25},
    }))
    assert cfg.limits["shoulder"] == JointLimits((-2.0, 2.0), 3.0, 10.0, 200.0, None)
    assert cfg.limits["rail"] == JointLimits(velocity=0.25)
    assert "elbow" not in cfg.limits and cfg.time_scaling == "reject"


def test_the_nested_layout_takes_limits_at_the_top_level_beside_hardware() -> None:
    cfg = load_config(nested({"time_scaling": "fit", "elbow": {"velocity": 1.0}}))
    assert cfg.limits == {"elbow": JointLimits(velocity=1.0)} and cfg.time_scaling == "fit"


def test_a_urdf_gives_limit_and_safety_controller_values(tmp_path: Path) -> None:
    shutil.copy(URDF, tmp_path / "arm.urdf")
    file = tmp_path / "robot.yaml"
    file.write_text(yaml.safe_dump(nested({"urdf": "arm.urdf"})))  # relative to the file
    cfg = load_config(file)
    # Soft limits narrow the range; the hard ones stay outside it.
    assert cfg.limits["shoulder"] == JointLimits((-2.0, 2.2), 3.0, None, None, 40.0)
    assert cfg.limits["elbow"] == JointLimits((-1.5, 1.5), 2.0, None, None, 20.0)
    # Continuous: no position range; effort 0 is URDF's "not given".
    assert cfg.limits["wrist"] == JointLimits(None, 6.0, None, None, None)
    assert cfg.limits["rail"] == JointLimits((0.0, 0.8), 0.5, None, None, 100.0)


def test_explicit_entries_override_the_urdf_field_by_field_and_null_removes_one() -> None:
    cfg = load_config(
        plain(limits={
            "urdf": str(URDF),
            "shoulder": {"velocity": 1.0, "acceleration": 4.0},
            "elbow": {"position": None},
        })
    )
    assert cfg.limits["shoulder"] == JointLimits((-2.0, 2.2), 1.0, 4.0, None, 40.0)
    assert cfg.limits["elbow"] == JointLimits(None, 2.0, None, None, 20.0)


def test_joints_absent_from_the_urdf_stay_unlimited_and_its_other_joints_are_skipped(
    tmp_path: Path,
) -> None:
    cfg = load_config({
        "joints": ["shoulder", "gripper"],
        "command_interfaces": ["position"],
        "state_interfaces": ["position"],
        "limits": {"urdf": str(URDF)},
    })
    assert set(cfg.limits) == {"shoulder"}


@pytest.mark.parametrize(
    ("limits", "path", "words"),
    [
        ({"shouldr": {"velocity": 1}}, "limits.shouldr", "did you mean 'shoulder'"),
        ({"shoulder": {"velocty": 1}}, "limits.shoulder.velocty", "did you mean 'velocity'"),
        ({"shoulder": {"velocity": 0}}, "limits.shoulder.velocity", "> 0"),
        ({"shoulder": {"jerk": "fast"}}, "limits.shoulder.jerk", "expected a number"),
        ({"shoulder": {"position": [1, -1]}}, "limits.shoulder.position", "min < max"),
        ({"shoulder": {"position": 2.0}}, "limits.shoulder.position", "expected [min, max]"),
        ({"time_scaling": "slow"}, "limits.time_scaling", "'reject', 'fit'"),
        ({"urdf": 3}, "limits.urdf", "path of a URDF file"),
        ([1, 2], "limits", "expected a mapping"),
    ],
)
def test_bad_entries_name_the_key(limits: Any, path: str, words: str) -> None:
    with pytest.raises(ConfigurationError) as error:
        load_config(plain(limits=limits))
    assert error.value.path == path and words in str(error.value)


def write_urdf(tmp_path: Path, body: str) -> str:
    file = tmp_path / "bad.urdf"
    file.write_text(body)
    return str(file)


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ("<robot><joint name='shoulder' type='revolute'>", "is not well-formed XML"),
        ("<model/>", "the root element is <model>, not <robot>"),
        (
            "<robot><joint name='shoulder' type='revolute'><limit velocity='fast'/></joint>"
            "</robot>",
            "joint 'shoulder': <limit velocity='fast'> is not a finite number",
        ),
        (
            "<robot><joint name='elbow' type='revolute'><limit velocity='-1'/></joint></robot>",
            "joint 'elbow': <limit velocity='-1'> must not be negative",
        ),
        (
            "<robot><joint name='elbow' type='revolute'><limit lower='1' upper='2'/>"
            "<safety_controller soft_lower_limit='2.5'/></joint></robot>",
            "joint 'elbow': the position range [2.5, 2] (from <limit lower upper>",
        ),
        (
            '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY a "aaaaaaaaaa">]>'
            "<robot><joint name='elbow' type='revolute'><limit velocity='&a;'/></joint></robot>",
            "document type declaration",
        ),
    ],
)
def test_urdf_errors_name_the_file_the_joint_and_the_attribute(
    tmp_path: Path, body: str, words: str
) -> None:
    filename = write_urdf(tmp_path, body)
    with pytest.raises(ConfigurationError) as error:
        load_config(plain(limits={"urdf": filename}))
    assert error.value.path == "limits.urdf"
    assert f"URDF {filename}: " in str(error.value) and words in str(error.value)


def test_a_missing_urdf_is_named_with_the_directory_it_was_looked_up_in(tmp_path: Path) -> None:
    file = tmp_path / "robot.yaml"
    file.write_text(yaml.safe_dump(plain(limits={"urdf": "nowhere.urdf"})))
    with pytest.raises(ConfigurationError, match=f"URDF {tmp_path}/nowhere.urdf: cannot read"):
        load_config(file)


def test_config_to_dict_round_trips_the_limits_in_both_layouts(tmp_path: Path) -> None:
    cfg = load_config(plain(limits={"urdf": str(URDF), "time_scaling": "fit",
                                    "elbow": {"jerk": 50.0}}))
    data = config_to_dict(cfg)
    assert data["limits"]["time_scaling"] == "fit"
    assert data["limits"]["shoulder"] == {"position": [-2.0, 2.2], "velocity": 3.0, "effort": 40.0}
    assert load_config(data) == cfg
    file = tmp_path / "out.yaml"
    file.write_text(yaml.safe_dump(config_to_dict(cfg, nested=True)))
    assert load_config(file) == cfg


def test_time_scaling_is_a_runtime_parameter_and_the_limits_are_fixed() -> None:
    cfg = load_config(plain(limits={"elbow": {"velocity": 1.0}}))
    assert get_parameters(cfg, ["limits.time_scaling"]) == {"limits.time_scaling": "reject"}
    change = set_parameters(cfg, {"limits.time_scaling": "fit"})
    assert change.config.time_scaling == "fit" and change.config.limits == cfg.limits
    assert change.effects["limits.time_scaling"].value == "next goal or trajectory"
    with pytest.raises(ConfigurationError, match="'reject', 'fit'"):
        set_parameters(cfg, {"limits.time_scaling": "maybe"})
    with pytest.raises(ConfigurationError, match="fixed when the configuration is loaded"):
        set_parameters(cfg, {"limits.elbow.velocity": 2.0})


def test_explain_warns_when_fit_has_nothing_to_fit() -> None:
    quiet = load_config(plain(limits={"time_scaling": "fit", "elbow": {"velocity": 1.0}}))
    assert not [w for w in explain(quiet) if w.startswith("limits")]
    cfg = load_config(plain(limits={"time_scaling": "fit", "elbow": {"position": [-1, 1]}}))
    (warning,) = [w for w in explain(cfg) if w.startswith("limits")]
    assert "no joint has one (only position ranges" in warning
