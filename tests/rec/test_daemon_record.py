"""``daemon.record: DIR``: the daemon records its run from the start into one bag.

The daemon runs as a subprocess on simulated joints; the bag, finished at SIGTERM, is read back
with the ``mcap`` package's reader and ``mcap-ros2-support``'s decoder (not our writer's code).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers.daemon import WAIT_S, DaemonProcess, connect, next_state, traj

pytest.importorskip("rosbags")
mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

pytestmark = pytest.mark.usefixtures("no_leaks")


def test_the_run_is_recorded_from_the_start(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    d = DaemonProcess(tmp_path / "d", record=str(runs))
    d.start()
    try:
        d.wait_ready()
        with connect(d) as client:
            result = client.send_goal(traj([0.2] * 6, 0.5)).wait(timeout_s=WAIT_S)
            assert result["status"] == "succeeded", result
            status = client.get_status()
            bag = Path(status["recording"]["file"])
            assert bag.parent == runs and bag.name.endswith("Z-run")
    finally:
        code = d.shutdown()
    assert code == 0, d.log()
    assert f"recording to {bag}" in d.log() and f"recorded {bag}" in d.log()
    (path,) = bag.glob("*.mcap")
    with path.open("rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        messages = [(c.topic, m) for _, c, _, m in reader.iter_decoded_messages()]
    topics = {topic for topic, _ in messages}
    assert {"/joint_states", "/joint_trajectory_controller/controller_state",
            "/joint_trajectory_controller/goal_events", "/diagnostics"} <= topics
    events = [json.loads(m.data) for topic, m in messages if topic.endswith("goal_events")]
    assert {"event": "result", "goal_id": result["goal_id"], "status": "succeeded"}.items() <= \
        next(e for e in events if e["event"] == "result").items()
    # The accepted command, as sent: header stamp 0 ("start now"), one point at 0.5 s.
    (command,) = [m for topic, m in messages
                  if topic == "/joint_trajectory_controller/joint_trajectory"]
    assert list(command.joint_names) == [f"joint{i}" for i in range(1, 7)]
    assert (command.header.stamp.sec, command.header.stamp.nanosec) == (0, 0)
    (point,) = command.points
    assert list(point.positions) == [0.2] * 6
    assert (point.time_from_start.sec, point.time_from_start.nanosec) == (0, 500_000_000)
    final = [m for topic, m in messages if topic == "/joint_states"][-1]
    assert list(final.position) == pytest.approx([0.2] * 6, abs=0.02)


def test_plot_marks_the_commanded_waypoints(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from jtc_hw.rec.plot import plot_bag, read_series

    runs = tmp_path / "runs"
    d = DaemonProcess(tmp_path / "d", record=str(runs))
    d.start()
    try:
        d.wait_ready()
        with connect(d) as client, client.subscribe_state() as sub:
            result = client.send_goal(traj([0.3] * 6, 0.5)).wait(timeout_s=WAIT_S)
            assert result["status"] == "succeeded", result
            # The recording holds the states the loop published (50 Hz): stopping the daemon
            # within a publication period of the result would leave out the state in which
            # the reference reached the waypoint. One published past it was recorded too
            # (the recorder is handed each state before the subscribers).
            next_state(sub, lambda s: s["desired"]["time_from_start"] >= 0.5)
    finally:
        assert d.shutdown() == 0, d.log()
    (bag,) = runs.iterdir()
    series = read_series(bag, "joint_trajectory_controller")
    assert sorted(name for _, name, _ in series["waypoints"]) == sorted(
        f"joint{i}" for i in range(1, 7))
    (at,) = {round(t, 6) for t, _, _ in series["waypoints"]}
    assert {v for _, _, v in series["waypoints"]} == {0.3}
    # The waypoint is where the desired position arrives at it, 0.5 s after the goal's start
    # (the recording goes on at least until the result, a cycle after that).
    import numpy as np

    assert at <= series["t"][-1] + 0.03
    desired = np.interp(at, series["t"], series["ref_pos"][:, 0])
    # A "start now" command is placed at the time the loop confirmed it (its log time), which
    # may precede the actual start by up to the plan's lead: the marker is in the last part of
    # the move, not exactly at its end (docs/recording.md).
    assert desired > 0.2
    assert np.interp(at - 0.3, series["t"], series["ref_pos"][:, 0]) < 0.2
    assert series["tolerances"]["joint1"]["path"] == 0.05
    out = plot_bag(bag, tmp_path / "p.png")
    assert out.stat().st_size > 10_000
