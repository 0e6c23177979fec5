"""``jtc-hw record`` and ``jtc-hw plot`` on emulated Dynamixel servos, read back independently.

The daemon drives the emulated servos through the real driver and SDK (as in
``test_dynamixel_daemon.py``); ``jtc-hw record`` runs as its own process, a client of the daemon's
state stream, and writes the bag with ``rosbags``. The bag is read back with the ``mcap`` package's
reader and ``mcap-ros2-support``'s CDR decoder, never with our writer's code, and compared with the
states this test received from the daemon itself. Waits are on messages and process exits with
deadlines; nothing asserts a duration.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers.daemon import MS, WAIT_S, connect, daemon_env, skipped_deadlines_until_now
from helpers.dynamixel import servos_as_hardware
from test_dynamixel_daemon import GOAL_TOL, IDS, JOINTS, PATH_TOL, START, DxlDaemon, robot, traj

from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator

pytest.importorskip("rosbags")
mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

pytestmark = pytest.mark.usefixtures("no_leaks")

CONTROLLER = "joint_trajectory_controller"
STATE_PERIOD_NS = 20 * MS  # make_robot_config's state_publish_rate: 50 Hz
LOOP_PERIOD_NS = 5 * MS  # robot()'s update_rate: 200 Hz
RECORD_S = 4.0


@pytest.fixture(scope="module")
def emulator() -> Iterator[DynamixelEmulator]:
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        yield emu


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory,
           emulator: DynamixelEmulator) -> Iterator[DxlDaemon]:
    d = DxlDaemon(tmp_path_factory.mktemp("rec"), lambda sock: robot(sock, emulator.device_path))
    with d.serving():
        yield d


def jtc_hw(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "jtc_hw", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=daemon_env())


@pytest.fixture(scope="module")
def recording(daemon: DxlDaemon, tmp_path_factory: pytest.TempPathFactory
              ) -> tuple[Path, list[dict[str, Any]], dict[str, Any]]:
    """A bag of a goal: (bag directory, the states this test received, the goal's result)."""
    bag = tmp_path_factory.mktemp("bags") / "goal"
    recorder = jtc_hw("record", str(bag), "--duration", str(RECORD_S),
                      "--socket", str(daemon.socket))
    try:
        assert recorder.stdout is not None
        line = recorder.stdout.readline()  # printed once subscribed: the goal is recorded
        assert line.startswith("recording to"), (line, recorder.stderr and recorder.stderr.read())
        states: list[dict[str, Any]] = []
        with connect(daemon) as client, client.subscribe_state(maxlen=10_000) as sub:

            def take(pred: Any) -> dict[str, Any]:
                while True:
                    state = sub.get(timeout_s=WAIT_S)
                    states.append(state)
                    if pred(state):
                        return state

            p0 = take(lambda s: s["active_goal"] is None)["actual"]["positions"]
            result = client.send_goal(traj([p + 0.3 for p in p0], 1.0)).wait(timeout_s=WAIT_S)
            take(lambda s: s["time_ns"] >= result["time_ns"] + 50 * MS)
        out, err = recorder.communicate(timeout=WAIT_S + RECORD_S * 10)
    finally:
        if recorder.poll() is None:
            recorder.kill()
            recorder.communicate()
    assert recorder.returncode == 0, (out, err)
    assert result["status"] == "succeeded", result
    return bag, states, result


def read_bag(bag: Path) -> list[tuple[str, str, int, Any]]:
    """(topic, schema name, log time, decoded message) of every message, by mcap's reader."""
    files = list(bag.glob("*.mcap"))
    assert len(files) == 1, files
    out = []
    with files[0].open("rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            out.append((channel.topic, schema.name, message.log_time, decoded))
    return out


def stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def test_bag_has_the_ros2_topics_and_types(recording: Any) -> None:
    bag, _, _ = recording
    metadata = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["storage_identifier"] == "mcap"
    types = {t["topic_metadata"]["name"]: t["topic_metadata"]["type"]
             for t in metadata["topics_with_message_count"]}
    assert types == {
        "/joint_states": "sensor_msgs/msg/JointState",
        f"/{CONTROLLER}/controller_state": "control_msgs/msg/JointTrajectoryControllerState",
        f"/{CONTROLLER}/goal_events": "std_msgs/msg/String",
        "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
        f"/{CONTROLLER}/joint_trajectory": "trajectory_msgs/msg/JointTrajectory",  # the goal
        # results (issue 22): the action's status topic and their text on /rosout
        f"/{CONTROLLER}/follow_joint_trajectory/_action/status":
            "action_msgs/msg/GoalStatusArray",
        "/rosout": "rcl_interfaces/msg/Log",
    }
    messages = read_bag(bag)
    assert {(topic, schema) for topic, schema, _, _ in messages} == set(types.items())
    counts = Counter(topic for topic, _, _, _ in messages)
    assert counts == {t["topic_metadata"]["name"]: t["message_count"]
                      for t in metadata["topics_with_message_count"]}
    # The configured tolerances, for the plot's band.
    tolerances = json.loads(metadata["custom_data"]["jtc_hw.tolerances"])
    assert tolerances == {j: {"path": PATH_TOL, "goal": GOAL_TOL} for j in JOINTS}


def test_states_at_the_publish_rate_with_the_controllers_values(
    recording: Any, daemon: DxlDaemon
) -> None:
    bag, states, result = recording
    with connect(daemon) as client:
        skipped = skipped_deadlines_until_now(client)
    offset = int(yaml.safe_load((bag / "metadata.yaml").read_text())
                 ["rosbag2_bagfile_information"]["custom_data"]["jtc_hw.clock_offset_ns"])
    messages = read_bag(bag)
    controller = [m for topic, _, _, m in messages if topic == f"/{CONTROLLER}/controller_state"]
    joint_states = [m for topic, _, _, m in messages if topic == "/joint_states"]
    assert len(controller) == len(joint_states)
    times = [stamp_ns(m) - offset for m in controller]
    assert times == sorted(times) and len(set(times)) == len(times)
    # The states at state_publish_rate: the loop publishes on the first cycle at least 20 ms
    # after the previous state, so a gap is 20 ms, or a loop period more per deadline the loop
    # skipped (a busy machine; it counts them); the span is the --duration (daemon clock).
    gaps = Counter(b - a for a, b in zip(times, times[1:]))
    assert all(gap % LOOP_PERIOD_NS == 0 and gap >= STATE_PERIOD_NS for gap in gaps), gaps
    late = sum((gap - STATE_PERIOD_NS) // LOOP_PERIOD_NS * n for gap, n in gaps.items())
    assert late <= skipped, (gaps, skipped)
    # (it ends at the last state before the first one past the duration: a gap away)
    assert RECORD_S * 1e9 - STATE_PERIOD_NS - skipped * LOOP_PERIOD_NS < times[-1] - times[0] \
        <= RECORD_S * 1e9
    assert times[0] <= states[0]["time_ns"] and result["time_ns"] <= times[-1]
    # Values: the same as the state events this test received, message by message: every
    # state published while both listened, from before the goal to past its result.
    recorded = {t: (msg, js) for t, msg, js in zip(times, controller, joint_states)}
    during = [s for s in states if times[0] <= s["time_ns"] <= times[-1]]
    assert any(s["active_goal"] is None for s in during)  # p0: before the goal was sent
    assert during[-1]["time_ns"] >= result["time_ns"]
    assert [s["time_ns"] for s in during] == [
        t for t in times if during[0]["time_ns"] <= t <= during[-1]["time_ns"]]
    for state in during:
        msg, js = recorded[state["time_ns"]]
        assert list(msg.joint_names) == JOINTS and list(js.name) == JOINTS
        assert list(msg.reference.positions) == state["desired"]["positions"]
        assert list(msg.reference.velocities) == state["desired"]["velocities"]
        assert list(msg.feedback.positions) == state["actual"]["positions"]
        assert list(js.position) == state["actual"]["positions"]
        assert list(js.velocity) == state["actual"]["velocities"]
        assert list(msg.error.positions) == state["error"]["positions"]
        assert list(msg.output.positions) == state["output"]["positions"]
        assert msg.speed_scaling_factor == state["speed_scaling"]["factor"]
        assert stamp_ns(js) == stamp_ns(msg)
    # The goal moved the joints by 0.3 rad: the recording shows it.
    first, last = controller[0], controller[-1]
    for a, b in zip(first.feedback.positions, last.feedback.positions):
        assert b - a == pytest.approx(0.3, abs=0.02)


def test_goal_events_and_diagnostics(recording: Any) -> None:
    bag, _, result = recording
    messages = read_bag(bag)
    events = [json.loads(m.data) for topic, _, _, m in messages
              if topic == f"/{CONTROLLER}/goal_events"]
    assert sorted((e["event"], e["goal_id"]) for e in events) == sorted([
        ("goal_started", result["goal_id"]), ("result", result["goal_id"]),
        ("goal_ended", result["goal_id"])])
    # The result with its status and text (issue 22: record gets every result, any client's).
    (recorded,) = [e for e in events if e["event"] == "result"]
    assert (recorded["status"], recorded["error_string"]) == (
        result["status"], result["error_string"])
    logs = [m for topic, _, _, m in messages if topic == "/rosout"]
    assert [m.msg.startswith(f"goal {result['goal_id']} succeeded") for m in logs] == [True]
    diagnostics = [m for topic, _, _, m in messages if topic == "/diagnostics"]
    # Once a second of daemon time, from the first state on (the last one only if a state
    # falls exactly on the recording's end).
    assert math.floor(RECORD_S) <= len(diagnostics) <= math.floor(RECORD_S) + 1
    names = {s.name for s in diagnostics[0].status}
    assert {"jtc_hw: loop", "jtc_hw: controller"} <= names
    loop = next(s for s in diagnostics[0].status if s.name == "jtc_hw: loop")
    assert any(kv.key == "cycles" for kv in loop.values)


def test_plot_writes_a_png_with_content(recording: Any, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from PIL import Image

    bag, _, _ = recording
    out = tmp_path / "goal.png"
    plot = jtc_hw("plot", str(bag), "--joints", "joint1", "joint3", "--out", str(out))
    stdout, stderr = plot.communicate(timeout=120)
    assert plot.returncode == 0, stderr
    with Image.open(out) as image:
        assert image.format == "PNG"
        width, height = image.size
        assert width >= 400 and height >= 200
        colors = image.convert("RGB").getcolors(maxcolors=1 << 20)
    assert colors is not None and len(colors) > 50  # lines, labels, grid: not a blank canvas
    assert "joint" in stdout or str(out) in stdout


def test_plot_names_an_unknown_joint(recording: Any) -> None:
    pytest.importorskip("matplotlib")
    bag, _, _ = recording
    plot = jtc_hw("plot", str(bag), "--joints", "elbow", "--out", "/dev/null")
    _, stderr = plot.communicate(timeout=120)
    assert plot.returncode == 2
    assert "elbow" in stderr and "joint1" in stderr and "Traceback" not in stderr


def test_record_refuses_an_existing_directory(daemon: DxlDaemon, tmp_path: Path) -> None:
    recorder = jtc_hw("record", str(tmp_path), "--duration", "1", "--socket", str(daemon.socket))
    _, stderr = recorder.communicate(timeout=60)
    assert recorder.returncode == 2
    assert str(tmp_path) in stderr and "exists" in stderr and "Traceback" not in stderr


@pytest.mark.parametrize(("blocked", "command", "hint"), [
    ("matplotlib", ["plot", "BAG"], "pip install 'jtc_hw[plot]'"),
    ("rosbags", ["plot", "BAG"], "pip install 'jtc_hw[record]'"),
    ("rosbags", ["record", "NEW", "--socket", "SOCKET"], "pip install 'jtc_hw[record]'"),
])
def test_a_missing_extra_gives_the_install_hint(
    recording: Any, daemon: DxlDaemon, tmp_path: Path, blocked: str, command: list[str],
    hint: str,
) -> None:
    bag, _, _ = recording
    argv = [str(bag) if a == "BAG" else str(tmp_path / "new") if a == "NEW"
            else str(daemon.socket) if a == "SOCKET" else a for a in command]
    # The library made unimportable in the CLI's process, as when it is not installed.
    code = (f"import sys; sys.modules[{blocked!r}] = None; from jtc_hw.cli import main; "
            f"sys.exit(main({argv!r}))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=daemon_env())
    assert done.returncode == 2, done
    assert hint in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert not (tmp_path / "new").exists()
