"""``jtc-hw calibrate feetech`` against the emulator, the emulator playing the user's hand.

The procedure is driven two ways: its functions in this process (the test turns the shafts
and waits, on an event, until the range recording has read each end), and the whole command in
a subprocess fed its Enter key on standard input (the test waits for its prompts, and for the
emulator to have served reads after each turn of a shaft). Also: the LeRobot JSON import, and
the robot file's other content kept as written.
"""

from __future__ import annotations

import json
import math
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers.hardware_threads import start_as_hardware

from jtc_hw.drivers.feetech import calibration as cal
from jtc_hw.drivers.feetech.control_table import model_by_name
from jtc_hw.drivers.feetech.emulator import FeetechEmulator
from jtc_hw.errors import ConfigurationError

pytestmark = pytest.mark.usefixtures("no_leaks")

ROOT = Path(__file__).resolve().parents[3]
SO101 = ROOT / "config" / "so101-follower.yaml"
JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
STS3215 = model_by_name("STS3215")
STEP = 2 * math.pi / 4096
WAIT_S = 20.0
#: Where the test's hand puts each servo: the middle, then the two ends (shaft steps).
MIDDLE = {1: 2000, 2: 2100, 3: 1900, 4: 2048, 5: 2200, 6: 1800}
LOW = {1: 800, 2: 900, 3: 1000, 4: 700, 5: 300, 6: 1500}
HIGH = {1: 3300, 2: 3200, 3: 3000, 4: 3400, 5: 3900, 6: 3100}
#: A range that crosses the 4095/0 wrap (servo 5 when the middle is near the top).
WRAPPING = {5: (3800, 3000, 4095 + 700)}


def _emulator(ids: list[int]) -> FeetechEmulator:
    emu = FeetechEmulator(ids, "STS3215", initial_positions=MIDDLE)
    start_as_hardware(emu.start)
    return emu


@pytest.fixture
def emu() -> Iterator[FeetechEmulator]:
    with _emulator(list(MIDDLE)) as e:
        yield e


@pytest.fixture
def bus(emu: FeetechEmulator) -> Iterator[Any]:
    pytest.importorskip("scservo_sdk", reason="feetech-servo-sdk (jtc_hw[feetech]) is missing")
    from jtc_hw.drivers.feetech.bus import FeetechBus

    b = FeetechBus(emu.device_path, 1_000_000, STS3215.series, timeout_ms=250.0,
                   return_delay_us=500.0)
    b.open()
    try:
        yield b
    finally:
        b.close()


def _eeprom(emu: FeetechEmulator, ids: list[int]) -> dict[int, tuple[int, ...]]:
    names = ("homing_offset", "min_position_limit", "max_position_limit", "id", "baud_rate")
    return {i: tuple(emu.stored_register(i, n) for n in names) for i in ids}


def _record_by_hand(
    bus: Any, emu: FeetechEmulator, middles: Mapping[int, int],
    ends: Mapping[int, tuple[int, int]], homing: int = 0,
) -> dict[int, cal.JointRange]:
    """Run record_ranges in a thread while the hand takes each servo to its two ends (shaft
    steps, unwrapped), waiting (on the recording's own samples) until each end has been read
    (less ``homing``, the servos' Homing Offset); then press Enter."""
    stop = threading.Event()
    seen: dict[int, cal.JointRange] = {}
    changed = threading.Condition()
    result: dict[str, Any] = {}

    def on_sample(ranges: Mapping[int, cal.JointRange]) -> None:
        with changed:
            seen.update(ranges)
            changed.notify_all()

    def record() -> None:
        try:
            result["ranges"] = cal.record_ranges(bus, middles, STS3215, stop, 0.005, on_sample)
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            result["error"] = exc

    thread = threading.Thread(target=record, name="record-ranges")
    thread.start()
    try:
        for servo_id, (low, high) in ends.items():
            for target, reached in ((low, lambda r, t=low - homing: r.low <= t),
                                    (high, lambda r, t=high - homing: r.high >= t)):
                emu.turn_by_hand(servo_id, target % 4096)
                with changed:
                    ok = changed.wait_for(lambda s=servo_id, f=reached: s in seen and f(seen[s]),
                                          WAIT_S)
                assert ok, f"servo {servo_id} at {target} never read: {seen.get(servo_id)}"
    finally:
        stop.set()
        thread.join(WAIT_S)
    assert not thread.is_alive()
    if "error" in result:
        raise result["error"]
    return result["ranges"]


def test_calibration_turns_the_torque_off_records_the_ranges_and_writes_no_eeprom(
    bus: Any, emu: FeetechEmulator
) -> None:
    ids = list(MIDDLE)
    before = _eeprom(emu, ids)
    for i in ids:  # the servos hold their positions: the hand cannot turn them
        bus.write_bytes(i, 40, bytes([1]))
    with pytest.raises(RuntimeError, match="torque"):
        emu.turn_by_hand(1, 100)
    cal.torque_off(bus, ids)
    assert all(emu.register(i, "torque_enable") == 0 for i in ids)
    middles = cal.read_positions(bus, ids)
    assert middles == MIDDLE
    ranges = _record_by_hand(bus, emu, middles, {i: (LOW[i], HIGH[i]) for i in ids})
    for i in ids:
        assert (ranges[i].middle, ranges[i].low, ranges[i].high) == (MIDDLE[i], LOW[i], HIGH[i])
    values = cal.joint_values(JOINTS, [ranges[i] for i in ids], STS3215, [1, -1, 1, 1, 1, 1],
                              [1.0] * 6)
    assert values["offset"][0] == pytest.approx(-MIDDLE[1] * STEP)
    assert values["offset"][1] == pytest.approx(MIDDLE[2] * STEP)  # direction -1
    assert values["position_limits"][0] == pytest.approx(
        [(LOW[1] - MIDDLE[1]) * STEP, (HIGH[1] - MIDDLE[1]) * STEP])
    assert values["position_limits"][1] == pytest.approx(
        [-(HIGH[2] - MIDDLE[2]) * STEP, -(LOW[2] - MIDDLE[2]) * STEP])
    assert _eeprom(emu, ids) == before  # nothing stored in the servos
    assert all(emu.register(i, "homing_offset") == 0 for i in ids)


def test_write_eeprom_stores_the_homing_offset_through_the_lock_and_closes_it(
    bus: Any, emu: FeetechEmulator
) -> None:
    ids = list(MIDDLE)
    cal.torque_off(bus, ids)
    emu.turn_by_hand(5, 3800)  # this joint's range will cross the wrap
    middles = cal.read_positions(bus, ids)
    written = cal.write_homing_offsets(bus, middles, STS3215)
    assert written == {i: middles[i] - 2047 for i in ids}
    for i in ids:
        assert emu.stored_register(i, "homing_offset") == written[i]  # kept over power cycles
        assert emu.register(i, "lock") == 1  # closed again
        assert emu.stored_register(i, "lock") == 1
    assert cal.read_positions(bus, ids) == dict.fromkeys(ids, 2047)
    emu.power_cycle(3)
    assert cal.read_positions(bus, [3]) == {3: 2047}


def test_a_range_across_the_wrap_is_refused_without_eeprom_and_measured_with_it(
    bus: Any, emu: FeetechEmulator
) -> None:
    cal.torque_off(bus, [5])
    middle, low, high = WRAPPING[5]
    emu.turn_by_hand(5, middle)
    middles = cal.read_positions(bus, [5])
    ranges = _record_by_hand(bus, emu, middles, {5: (low, high)})
    assert (ranges[5].low, ranges[5].high) == (low, high)  # unwrapped about the middle
    with pytest.raises(ConfigurationError, match="--write-eeprom"):
        cal.joint_values(["wrist_roll"], [ranges[5]], STS3215, [1], [1.0])
    emu.turn_by_hand(5, middle)
    cal.write_homing_offsets(bus, cal.read_positions(bus, [5]), STS3215)
    centred = cal.read_positions(bus, [5])
    homing = emu.register(5, "homing_offset")
    ranges = _record_by_hand(bus, emu, centred, {5: (low, high)}, homing)
    values = cal.joint_values(["wrist_roll"], [ranges[5]], STS3215, [1], [1.0])
    assert values["position_limits"][0] == pytest.approx([(low - middle) * STEP,
                                                          (high - middle) * STEP], abs=STEP)


def test_a_joint_left_still_is_named() -> None:
    r = [cal.JointRange(1, 2048, 1000, 3000), cal.JointRange(2, 2048, 2040, 2050)]
    with pytest.raises(ConfigurationError, match=r"shoulder_lift \(servo 2\) did not move"):
        cal.joint_values(JOINTS[:2], r, STS3215, [1, 1], [1.0, 1.0])


# -- LeRobot's JSON and the robot file ------------------------------------------------------------

LEROBOT = {
    "shoulder_pan": {"id": 1, "drive_mode": 0, "homing_offset": -1365, "range_min": 746,
                     "range_max": 3477},
    "shoulder_lift": {"id": 2, "drive_mode": 0, "homing_offset": -1200, "range_min": 822,
                      "range_max": 3211},
    "elbow_flex": {"id": 3, "drive_mode": 0, "homing_offset": -986, "range_min": 901,
                   "range_max": 3110},
    "wrist_flex": {"id": 4, "drive_mode": 0, "homing_offset": -1696, "range_min": 849,
                   "range_max": 3216},
    "wrist_roll": {"id": 5, "drive_mode": 0, "homing_offset": 1580, "range_min": 0,
                   "range_max": 4095},
    "gripper": {"id": 6, "drive_mode": 1, "homing_offset": 1400, "range_min": 2023,
                "range_max": 3530},
}


def _jtc_hw(*args: str, cwd: Path, stdin: Any = subprocess.DEVNULL,
            **kwargs: Any) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1",
               PYTHONPATH=os.pathsep.join([str(ROOT), *filter(None, [os.environ.get(
                   "PYTHONPATH")])]))
    return subprocess.Popen([sys.executable, "-m", "jtc_hw", "calibrate", "feetech", *args],
                            stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, cwd=cwd, env=env, **kwargs)


def test_from_lerobot_writes_the_file_keeping_its_other_content(tmp_path: Path) -> None:
    robot = tmp_path / "robot.yaml"
    original = SO101.read_text()
    robot.write_text(original)
    (tmp_path / "follower.json").write_text(json.dumps(LEROBOT, indent=4))
    p = _jtc_hw(str(robot), "--from-lerobot", "follower.json", "--margin-deg", "0",
                cwd=tmp_path)
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 0, out
    assert "wrist_roll" in out and "Wrote to" in out
    params = yaml.safe_load(robot.read_text())["hardware"][0]["params"]
    assert params["direction"] == [1, 1, 1, 1, 1, -1]
    assert params["offset"] == pytest.approx([-2047 * STEP] * 5 + [2047 * STEP], abs=1e-6)
    assert params["position_limits"][0] == pytest.approx(
        [(746 - 2047) * STEP, (3477 - 2047) * STEP], abs=1e-4)
    assert params["position_limits"][5] == pytest.approx(
        [-(3530 - 2047) * STEP, -(2023 - 2047) * STEP], abs=1e-4)
    # Everything but those three values is as written: comments, order, the other sections.
    changed = {"offset", "direction", "position_limits"}
    kept_old = [line for line in original.splitlines()
                if not any(line.strip().startswith(f"{k}:") for k in changed)
                and not line.strip().startswith("- [")]
    kept_new = [line for line in robot.read_text().splitlines()
                if not any(line.strip().startswith(f"{k}:") for k in changed)
                and not line.strip().startswith("- [")]
    assert kept_new == kept_old
    assert "# rad; commands are clamped" in robot.read_text()


def test_from_lerobot_names_a_missing_motor_and_leaves_the_file(tmp_path: Path) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(SO101.read_text())
    broken = {k: v for k, v in LEROBOT.items() if k != "gripper"}
    (tmp_path / "follower.json").write_text(json.dumps(broken))
    p = _jtc_hw(str(robot), "--from-lerobot", "follower.json", cwd=tmp_path)
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 2, out
    assert "'gripper'" in out
    assert robot.read_text() == SO101.read_text()


class _Lines:
    """A subprocess's output lines, waited for with a timeout."""

    def __init__(self, p: subprocess.Popen[str]) -> None:
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        self.ended = False
        assert p.stdout is not None
        threading.Thread(target=self._read, args=(p.stdout,), daemon=True).start()

    def _read(self, stream: Any) -> None:
        for line in stream:
            self.lines.put(line)
        self.lines.put("")

    def wait_for(self, text: str) -> None:
        deadline = time.monotonic() + WAIT_S
        while True:
            line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            self.seen.append(line)
            if text in line:
                return
            assert line, f"ended before {text!r}: {''.join(self.seen)}"

    def rest(self) -> str:
        """The whole output, once it has ended."""
        while not self.ended and (line := self.lines.get(timeout=WAIT_S)) != "":
            self.seen.append(line)
        self.ended = True
        return "".join(self.seen)


def _served_after(emu: FeetechEmulator, reads: int) -> None:
    """Wait until the emulator has served ``reads`` more packets than now: the calibration has
    read the positions since the hand moved (a read in flight during the move is not enough)."""
    start = emu.stats()["packets_served"]
    done = threading.Event()
    deadline = time.monotonic() + WAIT_S
    while emu.stats()["packets_served"] < start + reads:
        assert time.monotonic() < deadline, "the calibration stopped reading the servos"
        done.wait(0.01)


def test_the_command_calibrates_the_emulated_arm_and_writes_the_file(
    tmp_path: Path, emu: FeetechEmulator
) -> None:
    pytest.importorskip("scservo_sdk", reason="feetech-servo-sdk (jtc_hw[feetech]) is missing")
    robot = tmp_path / "robot.yaml"
    robot.write_text(SO101.read_text())
    before = _eeprom(emu, list(MIDDLE))
    p = _jtc_hw(str(robot), "--port", emu.device_path, "--ids", "1-6", "--margin-deg", "0",
                cwd=tmp_path, stdin=subprocess.PIPE)
    assert p.stdin is not None
    out = _Lines(p)
    try:
        out.wait_for("1/2")
        assert all(emu.register(i, "torque_enable") == 0 for i in MIDDLE)
        p.stdin.write("\n")
        p.stdin.flush()
        out.wait_for("2/2")
        for i in MIDDLE:
            for target in (LOW[i], HIGH[i]):
                emu.turn_by_hand(i, target)
                _served_after(emu, 2)
        p.stdin.write("\n")
        p.stdin.close()
        text = out.rest()
        assert p.wait(WAIT_S) == 0, text
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        out.rest()  # to the end of the output, then its pipe is closed
        assert p.stdout is not None
        p.stdout.close()
    assert "Wrote to" in text
    params = yaml.safe_load(robot.read_text())["hardware"][0]["params"]
    assert params["offset"] == pytest.approx([-MIDDLE[i] * STEP for i in MIDDLE], abs=1e-6)
    got = [v for pair in params["position_limits"] for v in pair]
    assert got == pytest.approx(
        [v for i in MIDDLE for v in ((LOW[i] - MIDDLE[i]) * STEP, (HIGH[i] - MIDDLE[i]) * STEP)],
        abs=1e-4)
    assert _eeprom(emu, list(MIDDLE)) == before
