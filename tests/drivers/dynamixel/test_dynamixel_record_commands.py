"""``jtc-hw record`` records every accepted command on ``/<controller>/joint_trajectory``.

The daemon drives emulated Dynamixel servos through the real driver and SDK. ``jtc-hw record``
(a client, its own process) subscribes with ``commands``: the daemon sends it a ``command``
event for every command it accepts, from any client. One client sends an action goal, another a
topic trajectory and then an empty one (a stop); the bag is read back with the ``mcap``
package's reader and ``mcap-ros2-support``'s decoder, never with our writer's code. A
subscriber without ``commands`` gets no such event. Waits are on messages and process exits
with deadlines; nothing asserts a duration.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import MS, WAIT_S, connect, daemon_env
from helpers.dynamixel import servos_as_hardware
from test_dynamixel_daemon import IDS, JOINTS, START, DxlDaemon, robot, traj

from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator

pytest.importorskip("rosbags")
mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

pytestmark = pytest.mark.usefixtures("no_leaks")

TOPIC = "/joint_trajectory_controller/joint_trajectory"


@pytest.fixture(scope="module")
def emulator() -> Iterator[DynamixelEmulator]:
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        yield emu


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory,
           emulator: DynamixelEmulator) -> Iterator[DxlDaemon]:
    d = DxlDaemon(tmp_path_factory.mktemp("reccmd"),
                  lambda sock: robot(sock, emulator.device_path))
    with d.serving():
        yield d


def read_commands(bag: Path) -> list[tuple[str, int, Any]]:
    """(schema name, log time, decoded message) on the commands topic, by mcap's reader."""
    (path,) = bag.glob("*.mcap")
    with path.open("rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        return [(schema.name, message.log_time, decoded)
                for schema, channel, message, decoded in reader.iter_decoded_messages()
                if channel.topic == TOPIC]


def test_record_has_every_accepted_command_of_every_client(
    daemon: DxlDaemon, tmp_path: Path
) -> None:
    bag = tmp_path / "commands"
    # Started with SIGINT ignored, as a shell starts a background job (`jtc-hw record out &`):
    # its Ctrl-C below must still finish the bag.
    recorder = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "record", str(bag), "--socket", str(daemon.socket)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=daemon_env(),
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        assert recorder.stdout is not None
        line = recorder.stdout.readline()  # printed once subscribed
        assert line.startswith("recording to"), (line, recorder.stderr and recorder.stderr.read())
        with connect(daemon) as goals, connect(daemon) as topic, \
                connect(daemon) as plain, plain.subscribe_state() as plain_sub, \
                connect(daemon) as watcher, watcher.subscribe_state(commands=True) as sub:
            p0 = next(s for s in sub if s.get("event") == "state")["actual"]["positions"]
            goal_target = [p + 0.1 for p in p0]
            result = goals.send_goal(traj(goal_target, 0.5)).wait(timeout_s=WAIT_S)
            assert result["status"] == "succeeded", result
            topic_target = [p + 0.15 for p in p0]
            topic.send_trajectory({
                "joint_names": JOINTS,
                "points": [{"time_from_start": 0.3, "positions": topic_target},
                           {"time_from_start": 0.6, "positions": goal_target}],
            })
            topic.send_trajectory({"joint_names": JOINTS, "points": []})  # a stop
            # This client sees the three commands as events, in order, with the states.
            commands = []
            while len(commands) < 3:
                message = sub.get(timeout_s=WAIT_S)
                if message.get("event") == "command":
                    commands.append(message)
            last_command_ns = commands[-1]["time_ns"]
            # Once a state after the last command has come, the recorder (a subscriber like
            # this one) has been sent everything it must write.
            while sub.get(timeout_s=WAIT_S)["time_ns"] < last_command_ns + 50 * MS:
                pass
            # A subscriber that did not ask for commands got states only.
            assert all(plain_sub.get(timeout_s=WAIT_S).get("event") == "state"
                       for _ in range(5))
        assert [c["goal_id"] for c in commands] == [result["goal_id"], None, None]
        assert commands[0]["trajectory"]["points"][0]["positions"] == pytest.approx(goal_target)
        assert commands[2]["trajectory"]["points"] == []
        recorder.send_signal(2)  # Ctrl-C: the recorder finishes the bag
        out, err = recorder.communicate(timeout=WAIT_S)
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.communicate()
    assert recorder.returncode == 0, (out, err)
    assert f"{TOPIC}: 3" in out, out

    recorded = read_commands(bag)
    assert [schema for schema, _, _ in recorded] == ["trajectory_msgs/msg/JointTrajectory"] * 3
    goal_msg, topic_msg, stop_msg = (m for _, _, m in recorded)
    assert list(goal_msg.joint_names) == JOINTS
    assert [list(p.positions) for p in goal_msg.points] == [pytest.approx(goal_target)]
    assert (goal_msg.points[0].time_from_start.sec,
            goal_msg.points[0].time_from_start.nanosec) == (0, 500_000_000)
    assert (goal_msg.header.stamp.sec, goal_msg.header.stamp.nanosec) == (0, 0)  # start now
    assert [list(p.positions) for p in topic_msg.points] == [
        pytest.approx(topic_target), pytest.approx(goal_target)]
    assert [p.time_from_start.nanosec for p in topic_msg.points] == [300_000_000, 600_000_000]
    assert len(stop_msg.points) == 0
    # Log times: when the daemon accepted each, in order, on the wall clock the bag maps to.
    times = [t for _, t, _ in recorded]
    assert times == sorted(times)
    offsets = [t - c["time_ns"] for t, c in zip(times, commands)]
    assert max(offsets) == min(offsets)  # one clock offset for the whole bag
