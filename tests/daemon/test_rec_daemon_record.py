"""``daemon.record: DIR``: the daemon records its run from the start into one bag.

The daemon runs as a subprocess on simulated joints; the bag, finished at SIGTERM, is read back
with the ``mcap`` package's reader and ``mcap-ros2-support``'s decoder (not our writer's code).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers.daemon import WAIT_S, DaemonProcess, connect, traj

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
