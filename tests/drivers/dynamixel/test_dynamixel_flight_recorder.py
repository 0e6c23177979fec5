"""The flight recorder on emulated Dynamixel servos: an abort writes the seconds before it.

A servo reports an overload mid-goal (the emulator latches the hardware error as the servo
does); the loop faults and the goal is aborted. The flight recorder in the API process then
writes a rosbag2/MCAP directory covering ``flight_recorder_s`` before the fault and a second
after, whose path the result's ``details``, ``get_status`` and the log name. The bag is read back
with the ``mcap`` package's reader and ``mcap-ros2-support``'s decoder. SIGTERM writes one too.
Waits are on messages and log lines with deadlines; nothing asserts a duration.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers.daemon import MS, WAIT_S, connect, next_state, skipped_deadlines_until_now
from helpers.dynamixel import servos_as_hardware
from test_dynamixel_daemon import IDS, START, DxlDaemon, robot, traj

from jtc_hw.drivers.dynamixel.control_table import HardwareError
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator

pytest.importorskip("rosbags")
mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

pytestmark = pytest.mark.usefixtures("no_leaks")

CONTROLLER = "joint_trajectory_controller"
BEFORE_S = 2.0
STATE_PERIOD_NS = 20 * MS
CYCLE_PERIOD_NS = 5 * MS  # update_rate 200 Hz (test_dynamixel_daemon.robot)


@pytest.fixture(scope="module")
def emulator() -> Iterator[DynamixelEmulator]:
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        yield emu


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory,
           emulator: DynamixelEmulator) -> Iterator[DxlDaemon]:
    directory = tmp_path_factory.mktemp("flight")

    def config(sock: Path) -> dict[str, Any]:
        cfg = robot(sock, emulator.device_path)
        cfg["daemon"].update(flight_recorder_s=BEFORE_S, flight_recorder_keep=5,
                             flight_recorder_dir=str(directory / "bags"))
        return cfg

    d = DxlDaemon(directory, config)
    d.start()
    try:
        d.wait_ready()
        yield d
    finally:
        d.shutdown()


def read_bag(bag: Path) -> tuple[int, list[tuple[str, Any]]]:
    """(clock offset, [(topic, decoded message)]) read by mcap's reader, not our writer."""
    metadata = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    offset = int(metadata["custom_data"]["jtc_hw.clock_offset_ns"])
    (path,) = bag.glob("*.mcap")
    with path.open("rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        return offset, [(channel.topic, decoded)
                        for _, channel, _, decoded in reader.iter_decoded_messages()]


def shm_segments(d: DxlDaemon) -> list[Path]:
    """The daemon's shared memory segments (its cycle ring), named by its pid."""
    return sorted(Path("/dev/shm").glob(f"jtc_hw_{d.pid}_*"))


def stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def test_an_abort_writes_the_seconds_before_it_named_in_the_result(
    daemon: DxlDaemon, emulator: DynamixelEmulator
) -> None:
    with connect(daemon) as client, client.subscribe_state() as sub:
        first = next_state(sub, lambda s: True)["time_ns"]
        # Running long enough that the recorder holds the whole window before the fault.
        p0 = next_state(sub, lambda s: s["time_ns"] >= first + round((BEFORE_S + 0.5) * 1e9)
                        )["actual"]["positions"]
        goal = client.send_goal(traj([p - 0.4 for p in p0], 2.0))
        for feedback in goal.feedback(timeout_s=WAIT_S):
            if feedback["time_from_start"] >= 0.4:
                break
        emulator.raise_hardware_error(3, HardwareError.OVERLOAD)
        result = goal.wait(timeout_s=WAIT_S)
        assert result["status"] == "aborted", result
        found = re.search(r"flight recorder: (\S+)", result["details"])
        assert found, result
        bag = Path(found.group(1))
        assert bag.name.endswith("-fault")  # the fault triggered it; the abort shares the bag
        daemon.wait_log(f"flight recorder: wrote {bag}", timeout_s=WAIT_S + 1.0)
        status = client.get_status()["flight_recorder"]
        assert status["last_file"] == str(bag) and status["enabled"] is True
        assert status["seconds"] == BEFORE_S and status["errors"] == 0
        assert status["source"] == "cycles" and status["cycle_rate_hz"] == 200
        assert status["lost_cycles"] == 0
        skipped = skipped_deadlines_until_now(client)
    assert f"flight recorder: fault; writing {bag}" in daemon.log()

    offset, messages = read_bag(bag)
    states = [m for topic, m in messages if topic == f"/{CONTROLLER}/controller_state"]
    joint_states = [m for topic, m in messages if topic == "/joint_states"]
    times = [stamp_ns(m) - offset for m in states]
    abort_ns = result["time_ns"]
    # Every cycle, not the published states: stamps on the 200 Hz deadline grid, consecutive
    # ones one period apart except where the loop skipped a deadline (a busy machine: the loop
    # counts them) and at the fault's own cycle, which has no row (its read raised: nothing
    # was measured; the abort is stamped with it).
    steps = [b - a for a, b in zip(times, times[1:])]
    assert all(step > 0 and step % CYCLE_PERIOD_NS == 0 for step in steps)
    assert abort_ns not in times and (abort_ns - times[0]) % CYCLE_PERIOD_NS == 0
    missing = sum(step // CYCLE_PERIOD_NS - 1 for step in steps)
    assert missing <= skipped + 1, (missing, skipped)
    assert [stamp_ns(m) - offset for m in joint_states] == times
    # The window: BEFORE_S before the trigger (the fault, a cycle or so before the abort) ...
    assert abort_ns - round(BEFORE_S * 1e9) - 3 * STATE_PERIOD_NS <= times[0]
    assert times[0] <= abort_ns - round(BEFORE_S * 1e9) + 3 * STATE_PERIOD_NS
    before = [t for t in times if t <= abort_ns]
    assert len(before) >= BEFORE_S * 1e9 / CYCLE_PERIOD_NS - 3 * STATE_PERIOD_NS / CYCLE_PERIOD_NS \
        - skipped
    # ... and the second after: while faulted the loop keeps reading the joints (nothing is
    # commanded: no reference, no output), at the cycle rate too.
    assert times[-1] >= abort_ns + 800 * MS
    after = [m for m, t in zip(states, times) if t > abort_ns + 10 * MS]
    assert len(after) >= 0.75 / (CYCLE_PERIOD_NS / 1e9) - skipped
    assert all(len(m.reference.positions) == 0 and len(m.output.positions) == 0
               for m in after)
    assert all(len(m.feedback.positions) == len(p0) for m in after)
    assert len({topic for topic, _ in messages}) >= 3
    # The goal's motion before the fault is in it: the reference moved away from p0.
    last_controlled = [m for m, t in zip(states, times) if len(m.reference.positions)][-1]
    moved = [abs(a - b) for a, b in zip(last_controlled.reference.positions, p0)]
    assert max(moved) > 0.02  # 0.4 s into a 2 s cubic move of 0.4 rad: about 0.04
    # The aborted goal's command is in it.
    (command,) = [m for topic, m in messages if topic == f"/{CONTROLLER}/joint_trajectory"]
    assert list(command.points[0].positions) == pytest.approx([p - 0.4 for p in p0])
    events = [json.loads(m.data) for topic, m in messages
              if topic == f"/{CONTROLLER}/goal_events"]
    results = [e for e in events if e["event"] == "result"]
    assert [(e["goal_id"], e["status"]) for e in results] == [(result["goal_id"], "aborted")]
    assert str(bag) in results[0]["details"]
    assert "servo 3" in results[0]["error_string"]


def test_sigterm_writes_a_bag(daemon: DxlDaemon) -> None:
    directory = Path(daemon.config_path).parent / "bags"
    segments = shm_segments(daemon)
    assert daemon.stop() == 0, daemon.log()
    # The cycle ring's shared memory was there while it ran, and is gone after SIGTERM.
    assert len(segments) == 1 and not segments[0].exists()
    shutdown = [p for p in directory.iterdir() if p.name.endswith("-shutdown")]
    assert len(shutdown) == 1, sorted(directory.iterdir())
    _, messages = read_bag(shutdown[0])
    assert any(topic == "/joint_states" for topic, _ in messages)
