"""Goal files in ROS 2's shapes (``ros2 topic echo`` of a JointTrajectory, a
FollowJointTrajectory goal) read into the protocol's form, and their errors naming the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from jtc_hw.api.goal_files import ros_goal
from jtc_hw.api.protocol import parse_request
from jtc_hw.api.requests import SendGoal
from jtc_hw.cli.goals import load_goal_file
from jtc_hw.errors import ConfigurationError

from conftest import ROOT

EXAMPLES = ROOT / "examples"


def _parsed(goal: dict[str, object]) -> SendGoal:
    """The goal as the daemon parses it (the protocol's own checks)."""
    request = parse_request({"op": "send_goal", "id": 1, **goal})
    assert isinstance(request, SendGoal)
    return request


def test_ros2_topic_echo_output_is_read_as_printed() -> None:
    goal = load_goal_file(str(EXAMPLES / "joint_trajectory_echo.yaml"))
    assert set(goal) == {"trajectory"}
    trajectory = goal["trajectory"]
    assert "header" not in trajectory
    first, last = trajectory["points"]
    assert first["time_from_start"] == 1 and last["time_from_start"] == 2.5
    assert "velocities" not in first and "effort" not in last  # empty lists: absent
    assert last["velocities"] == [0.0] * 6
    request = _parsed(goal)
    assert [p.time_from_start_ns for p in request.trajectory.points] == [
        1_000_000_000, 2_500_000_000
    ]


def test_follow_joint_trajectory_goal_keeps_its_tolerances() -> None:
    goal = load_goal_file(str(EXAMPLES / "follow_joint_trajectory_goal.yaml"))
    assert goal["goal_time_tolerance"] == 1
    assert "multi_dof_trajectory" not in goal and "component_path_tolerance" not in goal
    request = _parsed(goal)
    assert [(t.name, t.position) for t in request.path_tolerance] == [
        ("joint1", 0.1), ("joint2", 0.1)
    ]
    assert [(t.name, t.position) for t in request.goal_tolerance] == [("joint1", 0.02)]
    assert request.goal_time_tolerance == 1.0
    assert request.trajectory.points[0].time_from_start_ns == 1_200_000_000


@pytest.mark.parametrize("name", ["goal.yaml", "goal.json", "goal.csv"])
def test_the_protocol_forms_still_load(name: str) -> None:
    request = _parsed(load_goal_file(str(EXAMPLES / name)))
    assert request.trajectory.joint_names == tuple(f"joint{i}" for i in range(1, 7))
    assert request.trajectory.points[-1].time_from_start_ns == 2_000_000_000


def test_an_exact_duration_keeps_its_nanoseconds() -> None:
    # 0.1 s + 3 ns is not a float's round number: the parse must still give 100000003 ns.
    goal = ros_goal(
        {"joint_names": ["a"], "points": [
            {"positions": [0.0], "time_from_start": {"sec": 0, "nanosec": 100_000_003}}
        ]},
        "g.yaml",
    )
    assert _parsed(goal).trajectory.points[0].time_from_start_ns == 100_000_003


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (
            "joint_names: [a]\npoints:\n- positions: [0.0]\n"
            "  time_from_start: {sec: 1, nanosec: 1000000000}\n",
            "points[0].time_from_start.nanosec: 1000000000 is out of range",
        ),
        (
            "joint_names: [a]\npoints:\n- positions: [0.0]\n"
            "  time_from_start: {sec: 1.5, nanosec: 0}\n",
            "points[0].time_from_start.sec: expected an integer, got 1.5",
        ),
        (
            "joint_names: [a]\npoints:\n- positions: [0.0]\n"
            "  time_from_start: {sec: 1, nanosecs: 0}\n",
            "unknown Duration field 'nanosecs'",
        ),
        (
            "trajectory: {joint_names: [a], points: [{positions: [0.0], time_from_start: 1}]}\n"
            "goal_time_tolerance: {sec: -1, nanosec: 5000000000}\n",
            "goal_time_tolerance.nanosec: 5000000000 is out of range",
        ),
        (
            "trajectory: {joint_names: [a], points: [{positions: [0.0], time_from_start: 1}]}\n"
            "multi_dof_trajectory: {joint_names: [base], points: [{time_from_start: 1}]}\n",
            "multi_dof_trajectory: not supported",
        ),
        (
            "trajectory: {joint_names: [a], points: [{positions: [0.0], time_from_start: 1}]}\n"
            "component_goal_tolerance: [{joint_name: a, component: 1, position: 0.1}]\n",
            "component_goal_tolerance: not supported",
        ),
        (
            "joint_names: [a]\npoints: [{positions: [0.0], time_from_start: 1}]\n---\n"
            "joint_names: [a]\npoints: [{positions: [1.0], time_from_start: 1}]\n---\n",
            "the file holds 2 YAML documents",
        ),
    ],
)
def test_a_malformed_ros_file_names_the_field(
    tmp_path: Path, content: str, message: str
) -> None:
    path = tmp_path / "goal.yaml"
    path.write_text(content)
    with pytest.raises(ConfigurationError) as info:
        load_goal_file(str(path))
    assert message in str(info.value)
    assert str(path) in str(info.value)


def test_send_of_a_bad_goal_time_tolerance_is_an_error_not_a_crash(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It crashed with a TypeError (exit 1, 'aborted') before reaching any daemon."""
    from jtc_hw.cli import main
    from jtc_hw.cli.common import EXIT_BAD_INPUT

    path = tmp_path / "goal.yaml"
    path.write_text(
        "trajectory: {joint_names: [a], points: [{positions: [0.0], time_from_start: 1}]}\n"
        "goal_time_tolerance: soon\n"
    )
    code = main(["send", str(path), "--socket", str(tmp_path / "none.sock")])
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT, err
    assert "goal_time_tolerance: expected seconds (a number) or {sec, nanosec}, got 'soon'" in err
    assert "Traceback" not in err
