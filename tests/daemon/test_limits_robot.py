"""Joint limits in the robot file (issue 12 part A): a URDF beside it, and ``jtc-hw check``."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_OK
from jtc_hw.config.limits import JointLimits
from jtc_hw.daemon.robot import load_robot

URDF = Path(__file__).resolve().parents[1] / "data" / "limits_arm.urdf"


def robot_file(tmp_path: Path, limits: object, position_limits: list[float]) -> Path:
    data = {
        "joints": ["shoulder", "elbow"],
        "command_interfaces": ["position"],
        "state_interfaces": ["position", "velocity"],
        "hardware": [{
            "name": "arm", "kind": "mirror", "joints": ["shoulder", "elbow"],
            "params": {"position_limits": [position_limits, position_limits]},
        }],
        "daemon": {"socket": "arm.sock"},
        "limits": limits,
    }
    file = tmp_path / "robot.yaml"
    file.write_text(yaml.safe_dump(data))
    return file


def test_the_daemon_reads_a_urdf_relative_to_the_robot_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "urdf").mkdir()
    shutil.copy(URDF, tmp_path / "urdf" / "arm.urdf")
    file = robot_file(tmp_path, {"urdf": "urdf/arm.urdf"}, [-3.0, 3.0])
    monkeypatch.chdir("/")  # not the file's directory
    robot = load_robot(file)
    assert robot.controller.limits["elbow"] == JointLimits((-1.5, 1.5), 2.0, None, None, 20.0)


def test_check_prints_the_limits_and_warns_of_hardware_narrower_than_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    limits = {"time_scaling": "fit", "shoulder": {"position": [-2, 2], "velocity": 3,
                                                  "acceleration": 10, "jerk": 200}}
    file = robot_file(tmp_path, limits, [-3.0, 3.0])
    assert main(["check", str(file)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "time_scaling fit" in out
    assert [line.split() for line in out.splitlines() if "shoulder" in line and "[-2" in line] == [
        ["shoulder", "[-2,", "2]", "3", "10", "200"]
    ]
    assert "warning" not in out
    file = robot_file(tmp_path, limits, [-1.0, 3.0])
    assert main(["check", str(file)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "limits.shoulder.position: [-2, 2] reaches beyond the hardware's position_limits " \
        "[-1, 3]" in out


def test_check_says_when_goals_are_not_checked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    file = robot_file(tmp_path, {}, [-3.0, 3.0])
    assert main(["check", str(file)]) == EXIT_OK
    assert "limits          none: goals are not checked" in capsys.readouterr().out
