"""The live view's messages, built without a server: ROS 2 field layouts, stamps, diagnostics
levels, and ``jtc-hw check``'s line about the view."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_OK
from jtc_hw.controller.goals import ErrorCode, GoalFeedback, GoalResult, GoalStatus
from jtc_hw.controller.messages import JointTrajectory, PointColumns, TrajectoryPoint
from jtc_hw.controller.trajectory import TrajectorySample
from jtc_hw.daemon.settings import FoxgloveSettings
from jtc_hw.daemon.transports.liveview import (
    ERROR,
    OK,
    WARN,
    LiveView,
    controller_state_message,
    diagnostics_message,
    goal_event_message,
    joint_state_message,
    ros_time,
    topics,
    trajectory_message,
)

SNAPSHOT = {
    "time_ns": 5_000_000_000,
    "joint_names": ["a", "b"],
    "desired": {"positions": [1.0, 2.0], "velocities": [0.1, 0.2], "accelerations": None,
                "effort": None, "time_from_start": 1.25},
    "actual": {"positions": [0.9, 2.1], "velocities": [0.0, None], "accelerations": None,
               "time_from_start": 1.25},
    "error": {"positions": [0.1, -0.1], "velocities": [0.1, None], "accelerations": None},
    "command": {"positions": [1.0, 2.0]},
    "output": {"positions": [1.0, 2.0]},
    "holding": False,
    "active_goal": 3,
    "speed_scaling": {"factor": 0.5, "target": 0.5},
}


def test_ros_time_keeps_nanosec_in_range_for_negative_times() -> None:
    assert ros_time(1_500_000_000) == {"sec": 1, "nanosec": 500_000_000}
    assert ros_time(-1) == {"sec": -1, "nanosec": 999_999_999}
    assert ros_time(0) == {"sec": 0, "nanosec": 0}


def test_joint_state_and_controller_state_follow_the_ros_layouts() -> None:
    js = joint_state_message(SNAPSHOT, 7_000_000_001)
    assert js == {
        "header": {"stamp": {"sec": 7, "nanosec": 1}, "frame_id": ""},
        "name": ["a", "b"], "position": [0.9, 2.1], "velocity": [0.0, None], "effort": [],
    }
    cs = controller_state_message(SNAPSHOT, 7_000_000_001)
    assert cs["joint_names"] == ["a", "b"]
    assert cs["reference"]["positions"] == [1.0, 2.0]
    assert cs["reference"]["time_from_start"] == {"sec": 1, "nanosec": 250_000_000}
    assert cs["feedback"]["positions"] == [0.9, 2.1]
    assert cs["error"]["positions"] == [0.1, -0.1]
    assert cs["error"]["accelerations"] == []
    assert cs["output"]["positions"] == [1.0, 2.0]
    assert cs["speed_scaling_factor"] == 0.5


def test_a_command_in_rows_and_in_columns_gives_the_same_trajectory_message() -> None:
    rows = JointTrajectory(["a", "b"], [
        TrajectoryPoint(0.5, [0.0, 1.0]),
        TrajectoryPoint(1.0, [1.0, float("nan")], [0.0, 0.0]),
    ], start_time_ns=0)
    columns = JointTrajectory(["a", "b"], PointColumns(
        [500_000_000, 1_000_000_000],
        positions=np.array([[0.0, 1.0], [1.0, np.nan]]),
        velocities=np.array([[0.0, 0.0], [0.0, 0.0]]),
        present={"velocities": np.array([False, True])},
    ))
    by_rows = trajectory_message(rows, 0, 4)
    assert by_rows["header"] == {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": "goal 4"}
    assert by_rows["points"][1] == {
        "positions": [1.0, None], "velocities": [0.0, 0.0], "accelerations": [], "effort": [],
        "time_from_start": {"sec": 1, "nanosec": 0},
    }
    assert by_rows["points"][0]["velocities"] == []
    by_columns = trajectory_message(columns, 0, 4)
    assert by_columns == by_rows
    assert trajectory_message(rows, 2_000_000_000, None)["header"]["frame_id"] == "topic"


def test_goal_events_carry_results_and_feedback() -> None:
    result = GoalResult(3, GoalStatus.ABORTED, ErrorCode.PATH_TOLERANCE_VIOLATED,
                        "Aborted due to path tolerance violation", 9, "joint a: 0.2 > 0.1")
    message = goal_event_message(result, ["a"], 9)
    assert message["event"] == "result" and message["goal_id"] == 3
    assert message["status"] == "aborted"
    assert message["error_code"] == int(ErrorCode.PATH_TOLERANCE_VIOLATED)
    assert message["details"] == "joint a: 0.2 > 0.1"
    desired = TrajectorySample(np.array([1.0]), np.array([0.5]), np.array([0.0]), np.array([0.0]))
    feedback = GoalFeedback(3, 9, 0.25, desired, np.array([0.9]), None,
                            np.array([[0.1], [0.5], [0.0]]))
    message = goal_event_message(feedback, ["a"], 9)
    assert message["event"] == "feedback" and message["joint_names"] == ["a"]
    assert message["desired"]["positions"] == [1.0]
    assert message["actual"]["velocities"] == []
    assert message["error"]["velocities"] == [0.5]
    assert message["desired"]["time_from_start"] == {"sec": 0, "nanosec": 250_000_000}


def test_diagnostics_levels_follow_faults_and_warnings() -> None:
    status = {
        "loop": {"overruns": 0, "period": {"p99_us": 12.5}, "api_stalled": False},
        "controller": {"active": True, "holding": True, "fault": None},
        "hardware": {"components": [
            {"name": "arm", "kind": "dynamixel", "state": "active", "last_fault": None,
             "counters": {"reads": 10}},
            {"name": "leg", "kind": "can_mit", "state": "active", "last_fault": None,
             "warnings": ["motor 1 at 71 C"]},
            {"name": "hand", "kind": "cia402", "state": "active",
             "last_fault": "drive 2: fault 0x2310"},
        ]},
    }
    entries = {s["name"]: s for s in diagnostics_message(status, 1)["status"]}
    assert entries["jtc_hw: loop"]["level"] == OK
    values = {v["key"]: v["value"] for v in entries["jtc_hw: loop"]["values"]}
    assert values["period.p99_us"] == "12.5"
    assert entries["jtc_hw: controller"]["message"] == "holding"
    assert entries["jtc_hw: hardware arm"]["level"] == OK
    assert entries["jtc_hw: hardware leg"]["level"] == WARN
    assert entries["jtc_hw: hardware leg"]["message"] == "motor 1 at 71 C"
    assert entries["jtc_hw: hardware hand"]["level"] == ERROR
    assert entries["jtc_hw: hardware hand"]["message"] == "drive 2: fault 0x2310"
    faulted = dict(status, controller={"fault": "hardware fault", "active": False},
                   loop={"api_stalled": True})
    entries = {s["name"]: s for s in diagnostics_message(faulted, 1)["status"]}
    assert entries["jtc_hw: controller"]["level"] == ERROR
    assert entries["jtc_hw: loop"]["level"] == WARN


@pytest.mark.parametrize(
    ("daemon", "line"),
    [
        ("", "live view       off (daemon.foxglove)"),
        ("foxglove: {}", "live view       Foxglove WebSocket ws://127.0.0.1:8765, every state"),
        ("foxglove: {port: 9000, rate: 10}",
         "live view       Foxglove WebSocket ws://127.0.0.1:9000, 10 Hz"),
    ],
)
def test_check_shows_the_live_view(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], daemon: str, line: str
) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(
        "joints: [j1]\ncommand_interfaces: [position]\nstate_interfaces: [position]\n"
        f"daemon: {{socket: {tmp_path}/d.sock, {daemon}}}\n"
    )
    assert main(["check", str(path)]) == EXIT_OK
    assert line in capsys.readouterr().out


def test_a_port_in_use_is_refused_with_the_key_to_change() -> None:
    """(Not under ``no_leaks``: the SDK's runtime, started here in the test process, keeps its
    own sockets for the life of the process.)"""
    pytest.importorskip("foxglove")
    import asyncio
    import socket

    from jtc_hw.daemon.settings import FoxgloveSettings
    from jtc_hw.daemon.transports.liveview import LiveView
    from jtc_hw.errors import ConfigurationError

    async def attempt(port: int) -> str:
        view = LiveView(FoxgloveSettings(port=port), "jtc", ["a"], 50.0, dict)
        try:
            view.start()
        except ConfigurationError as exc:
            return str(exc)
        finally:
            await view.close()
        return "started"

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        message = asyncio.run(attempt(taken.getsockname()[1]))
    assert message.startswith("daemon.foxglove.port: cannot serve the live view on 127.0.0.1:")
    assert "choose another port (0: any free one)" in message


class _Channel:
    """Stands in for an SDK channel: records what would be sent."""

    def __init__(self, sinks: bool = True) -> None:
        self.sinks = sinks
        self.logged: list[tuple[dict[str, object], int]] = []

    def has_sinks(self) -> bool:
        return self.sinks

    def log(self, message: dict[str, object], *, log_time: int) -> None:
        self.logged.append((message, log_time))


def _view_with_channels(rate: float | None) -> tuple[LiveView, dict[str, _Channel]]:

    view = LiveView(FoxgloveSettings(rate=rate), "jtc", ["a", "b"], 50.0, dict)
    channels = {role: _Channel() for role in topics("jtc")}
    view._channels = channels
    view._server = object()  # "started" (the channels above stand in for the SDK's)
    return view, channels


@pytest.mark.parametrize(("rate", "published"), [(None, 10), (50.0, 10), (10.0, 2)])
def test_rate_thins_the_states_on_the_loops_clock(rate: float | None, published: int) -> None:
    view, channels = _view_with_channels(rate)
    for k in range(10):  # 10 states 20 ms apart (50 Hz)
        view.on_state(dict(SNAPSHOT, time_ns=1_000_000_000 + k * 20_000_000))
    assert len(channels["joint_states"].logged) == published
    assert len(channels["controller_state"].logged) == published
    stamps = [t for _, t in channels["joint_states"].logged]
    assert len(set(np.diff(stamps))) <= 1, "evenly spaced, on the loop's grid"


def test_nothing_is_built_for_a_channel_nobody_subscribes_to() -> None:
    view, channels = _view_with_channels(None)
    channels["joint_states"].sinks = False
    view.on_state(dict(SNAPSHOT))
    assert channels["joint_states"].logged == []
    assert len(channels["controller_state"].logged) == 1
