"""The client sends large trajectories as binary frames by itself (docs/protocol.md, "Binary
frames"), against the real server on the stand-in backend: what it sends, and that the daemon
runs the same trajectory as from JSON."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.fake_backend import ServerThread

from jtc_hw import GoalRejected, JointTrajectory, TrajectoryPoint
from jtc_hw.api import client as client_module
from jtc_hw.api.client import Client
from jtc_hw.api.events import BINARY_MIN_POINTS, trajectory_columns
from jtc_hw.controller.messages import PointColumns

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

S = 1_000_000_000


def wire(points: int, scale: float = 0.1) -> dict[str, Any]:
    return {"joint_names": ["j1", "j2"], "points": [
        {"time_from_start": 0.01 * (i + 1), "positions": [scale * i / points, -scale * i / points],
         "velocities": [0.0, 0.0]}
        for i in range(points)]}


@pytest.fixture
def frames(monkeypatch: pytest.MonkeyPatch) -> list[tuple[dict[str, Any], list[str]]]:
    """Every binary frame the client encodes: its request and columns."""
    sent: list[tuple[dict[str, Any], list[str]]] = []
    encode_frame = client_module.encode_frame

    def spy(obj: dict[str, Any], values: Any, columns: list[str]) -> bytes:
        sent.append((obj, columns))
        return encode_frame(obj, values, columns)

    monkeypatch.setattr(client_module, "encode_frame", spy)
    return sent


def test_from_the_threshold_on_a_goal_goes_binary_and_runs_as_from_json(
    daemon: ServerThread, client: Client, frames: list[Any]
) -> None:
    small = client.send_goal(wire(BINARY_MIN_POINTS - 1), start_in=1.0)
    assert frames == []
    client.cancel(small.goal_id)
    goal = client.send_goal(wire(BINARY_MIN_POINTS), start_in=1.0)
    ((request, columns),) = frames
    assert "points" not in request["trajectory"] and request["trajectory"]["start_in"] == 1.0
    assert columns == ["time_from_start", "positions.j1", "positions.j2", "velocities.j1",
                       "velocities.j2"]
    # The daemon samples the binary goal where the JSON one would be: 0.5 s in, point 49.
    state = client.query_state(in_s=1.5)
    assert state["positions"] == pytest.approx([0.1 * 49 / 100, -0.1 * 49 / 100], abs=1e-9)
    client.cancel(goal.goal_id)


def test_a_joint_trajectory_of_columns_or_points_goes_binary(
    client: Client, frames: list[Any]
) -> None:
    t = np.arange(1, 201) * 0.01
    columns = PointColumns((t * S).round().astype(np.int64),
                           positions=np.column_stack([t / 10, -t / 10]))
    for points in (columns, list(columns)):
        client.send_trajectory(JointTrajectory(["j1", "j2"], points))
    assert [c for _, c in frames] == [["time_from_start", "positions.j1", "positions.j2"]] * 2
    assert client.query_state(in_s=1.0)["positions"] == pytest.approx([0.1, -0.1], abs=1e-9)


def test_irregular_points_go_as_json_so_the_daemon_names_the_problem(
    client: Client, frames: list[Any]
) -> None:
    goal = wire(150)
    goal["points"][7]["positions"] = [0.1]
    with pytest.raises(GoalRejected, match="point #7: positions has 1 value"):
        client.send_goal(goal)
    goal["points"][7] = {"time_from_start": 0.08, "positons": [0.1, 0.1]}
    with pytest.raises(Exception, match="positons"):
        client.send_goal(goal)
    assert frames == []


def test_without_a_version_2_hello_the_client_sends_json(
    daemon: ServerThread, sock: Path, frames: list[Any]
) -> None:
    with Client.connect(str(sock), hello=False) as plain:
        plain.send_trajectory(wire(200))
    assert frames == []


def test_trajectory_columns_keeps_what_the_json_form_says() -> None:
    head, values, names = trajectory_columns(wire(100) | {"start_time_ns": 5})  # type: ignore[misc]
    assert head == {"joint_names": ["j1", "j2"], "start_time_ns": 5}
    assert values.shape == (100, 5) and values[99, 0] == 1.0 and names[1] == "positions.j1"
    with pytest.raises(ValueError, match="start_time_ns or start_in"):
        trajectory_columns(wire(100) | {"start_time_ns": 5}, start_in=1.0)
    points = [TrajectoryPoint(0.01 * (i + 1), [0.0, 0.0], None if i == 5 else [0.0, 0.0])
              for i in range(100)]
    assert trajectory_columns(JointTrajectory(["j1", "j2"], points)) is None  # irregular
