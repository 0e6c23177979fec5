"""End to end on emulated STS3215 servos (an SO-101): ``python -m jtc_hw run`` with
``kind: feetech``, through Feetech's SDK and the emulator's pty.

The goal that succeeds runs against ``jtc-hw emulate feetech`` in a subprocess, with the robot
file of ``config/so101-follower-emulated.yaml``. The faults are injected into an emulator
living in this test process (its thread at a real-time priority, as the Dynamixel daemon tests
run theirs); the daemon is a subprocess that opens its pty as it would open ``/dev/ttyACM0``.
Waits are on messages with deadlines; nothing asserts a duration.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers.daemon import (
    MS,
    WAIT_S,
    ConfiguredDaemon,
    DaemonProcess,
    connect,
    loop_process,
    next_state,
    settle,
    wait_gone,
)
from helpers.hardware_threads import start_as_hardware

from jtc_hw.drivers.feetech.codec import StatusError
from jtc_hw.drivers.feetech.emulator import FeetechEmulator

from conftest import ROOT, TEST_LOOP_REALTIME, make_robot_config

pytest.importorskip("scservo_sdk", reason="feetech-servo-sdk (jtc_hw[feetech]) is missing")
pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
IDS = [1, 2, 3, 4, 5, 6]
START = {i: 2048 + 40 * (i - 3) for i in IDS}  # steps; 2048 (mid-range) is joint 0
#: ``timeout_ms`` of a daemon driving an emulator of this test: the emulator is a thread of the
#: test's process, scheduled beside busy processes on a 2-core machine (helpers/dynamixel.py,
#: DAEMON_TEST_TIMEOUT_MS, says why 1 s); no test here is about how soon a silence is noticed.
TIMEOUT_MS = 1000.0
FAULTED = 3  # the servo the faults are injected into
FAULTED_JOINT = JOINTS[FAULTED - 1]


def robot(socket_path: Path, device: str, path_tolerance: float = 0.15) -> dict[str, Any]:
    params: dict[str, Any] = {
        "port": device,
        "baud_rate": 1_000_000,
        "ids": IDS,
        "model": "STS3215",
        "offset": -3.141592653589793,
        "timeout_ms": TIMEOUT_MS,
        "max_retries": 1,
    }
    hardware = [{"name": "so101", "kind": "feetech", "joints": JOINTS, "params": params}]
    return make_robot_config(socket_path, JOINTS, hardware, update_rate=100, goal_time=1.0,
                             path_tolerance=path_tolerance, goal_tolerance=0.03)


def traj(positions: list[float], t: float) -> dict[str, Any]:
    return {
        "joint_names": JOINTS,
        "points": [{"time_from_start": t, "positions": positions, "velocities": [0.0] * 6}],
    }


@contextlib.contextmanager
def emulated_so101() -> Iterator[FeetechEmulator]:
    """Six STS3215 in this process, answering at a real-time priority where permitted."""
    emu = FeetechEmulator(IDS, "STS3215", initial_positions=START)
    start_as_hardware(emu.start)
    with emu:
        yield emu


@contextlib.contextmanager
def daemon_on(directory: Path, emu: FeetechEmulator, **kwargs: Any) -> Iterator[ConfiguredDaemon]:
    d = ConfiguredDaemon(directory, lambda sock: robot(sock, emu.device_path, **kwargs))
    with d.serving():
        yield d


# -- a goal through `jtc-hw emulate feetech` and the example robot file -------------------------


@pytest.fixture
def emulator_cli(tmp_path: Path) -> Iterator[str]:
    """``jtc-hw emulate feetech`` in a subprocess (the command line a user runs); its link."""
    link = str(tmp_path / "jtc-hw-fee")
    argv = [sys.executable, "-m", "jtc_hw", "emulate", "feetech", "--ids", "1-6", "--model",
            "STS3215", "--link", link, "--stats", "exit"]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                          cwd=ROOT) as proc:
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline().strip() == link  # printed once it serves
            yield link
            proc.terminate()
            assert proc.wait(timeout=10) == 0
        finally:
            if proc.returncode is None:
                proc.kill()


def example_config(socket_path: Path, link: str) -> dict[str, Any]:
    """config/so101-follower-emulated.yaml on this test's emulator and socket."""
    config = yaml.safe_load((ROOT / "config" / "so101-follower-emulated.yaml").read_text())
    params = config["hardware"][0]["params"]
    params["port"] = link
    params["timeout_ms"] = TIMEOUT_MS  # the test's machine may be busy (see TIMEOUT_MS)
    config["daemon"] = {"socket": str(socket_path), "realtime": dict(TEST_LOOP_REALTIME)}
    return config


def test_a_goal_on_the_emulated_so101_succeeds(tmp_path: Path, emulator_cli: str) -> None:
    d = ConfiguredDaemon(tmp_path / "d", lambda sock: example_config(sock, emulator_cli))
    with d.serving(), connect(d) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        assert p0 == pytest.approx([0.0] * 6, abs=0.01)  # the emulator starts at mid-range
        target = [0.4, -0.3, 0.5, -0.5, 1.0, 0.8]
        result = client.send_goal(traj(target, 2.0)).wait(timeout_s=WAIT_S)
        assert result["status"] == "succeeded", (result, d.log())
        state = settle(sub, result["time_ns"] + 50 * MS)
        assert state["actual"]["positions"] == pytest.approx(target, abs=0.03)
        (so101,) = client.get_status()["hardware"]["components"]
        assert so101["kind"] == "feetech" and so101["state"] == "active"
        assert so101["details"]["bus"]["timeouts"] == 0


# -- faults: each gives one ABORTED result naming the servo -------------------------------------


def _abort_by(tmp_path: Path, inject: Callable[[FeetechEmulator], None], *, duration_s: float,
              path_tolerance: float = 0.15) -> tuple[dict[str, Any], str]:
    """A goal under way, ``inject`` the fault; the goal's one result and the daemon's log."""
    with emulated_so101() as emu, daemon_on(tmp_path / "d", emu,
                                            path_tolerance=path_tolerance) as d:
        with connect(d) as client, client.subscribe_state() as sub:
            p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
            goal = client.send_goal(traj([p + 0.6 for p in p0], duration_s))
            for feedback in goal.feedback(timeout_s=WAIT_S):
                if feedback["time_from_start"] >= 0.3:
                    break
            inject(emu)
            result = goal.wait(timeout_s=WAIT_S + duration_s)
            # The loop is stopped (no states while faulted): a status round trip instead. A
            # second result would be the same cycle's and come before the reply.
            controller = client.get_status()["controller"]
            assert len(client.received("result", goal.goal_id)) == 1
            assert controller["active"] is False
            assert f"servo {FAULTED}" in controller["fault"]
        return result, d.log()


def _names_the_servo(result: dict[str, Any]) -> None:
    assert result["status"] == "aborted", result
    text = result["error_string"]
    assert f"servo {FAULTED} (joint '{FAULTED_JOINT}')" in text, text


def test_a_silent_servo_aborts_the_goal_naming_it(tmp_path: Path) -> None:
    result, _ = _abort_by(tmp_path, lambda emu: emu.set_silent(FAULTED, True), duration_s=3.0)
    _names_the_servo(result)
    assert "timeout (no reply)" in result["error_string"]


def test_a_stream_of_checksum_errors_aborts_the_goal_naming_the_servo(tmp_path: Path) -> None:
    result, _ = _abort_by(tmp_path, lambda emu: emu.corrupt_checksum(FAULTED, 1_000_000),
                          duration_s=3.0)
    _names_the_servo(result)
    assert "corrupt reply" in result["error_string"]


def test_an_overheating_servo_aborts_the_goal_naming_it(tmp_path: Path) -> None:
    result, _ = _abort_by(tmp_path, lambda emu: emu.set_temperature(FAULTED, 80.0),
                          duration_s=3.0)
    _names_the_servo(result)
    assert "overheating" in result["error_string"]


def test_an_overloaded_servo_aborts_the_goal_naming_it(tmp_path: Path) -> None:
    """An obstacle holds servo 3: its torque stays above Overload Torque for Protection Time
    (2 s) and its protection switches it off. Path tolerances are off here, so that the
    servo's own report, not the tracking error it causes, ends the goal."""

    def obstacle(emu: FeetechEmulator) -> None:
        emu.block(FAULTED)
        emu.wait_protection(FAULTED, StatusError.OVERLOAD, timeout_s=WAIT_S)

    result, _ = _abort_by(tmp_path, obstacle, duration_s=8.0, path_tolerance=0.0)
    _names_the_servo(result)
    assert "overload" in result["error_string"]


# -- no watchdog: what a dead daemon leaves ------------------------------------------------------


def test_sigkill_of_the_daemon_leaves_the_servos_holding_their_last_goal(tmp_path: Path) -> None:
    """docs/safety.md, Feetech: no bus watchdog exists. The daemon killed mid-goal, every
    servo keeps its torque on and comes to rest at the last goal it was sent; nothing else
    happens to it until its power is cut."""
    with emulated_so101() as emu:
        d: DaemonProcess = ConfiguredDaemon(tmp_path / "d", lambda sock: robot(
            sock, emu.device_path))
        d.start()
        try:
            d.wait_ready()
            with connect(d) as client, client.subscribe_state() as sub:
                p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
                goal = client.send_goal(traj([p + 0.8 for p in p0], 3.0))
                for feedback in goal.feedback(timeout_s=WAIT_S):
                    if feedback["time_from_start"] >= 0.5:
                        break
                loop = loop_process(d)
                os.killpg(d.pid, signal.SIGKILL)
                wait_gone(loop)
        finally:
            assert d.proc is not None
            with contextlib.suppress(ProcessLookupError):
                os.killpg(d.pid, signal.SIGKILL)
            d.proc.wait(timeout=WAIT_S)
        # The last Sync Write may still be on its way through the pty: judge once every servo
        # has come to rest at the goal it holds.
        deadline = time.monotonic() + WAIT_S
        while True:
            goals = {i: emu.register(i, "goal_position") for i in IDS}
            at = emu.positions()
            if all(abs(at[i] - goals[i]) <= 2 and emu.register(i, "moving") == 0 for i in IDS):
                break
            assert time.monotonic() < deadline, (at, goals)
            time.sleep(0.01)  # watching the emulated motors reach their last goal
        assert all(emu.register(i, "torque_enable") == 1 for i in IDS)
        moved = 0.8 / (2 * 3.14159265 / 4096)
        assert all(START[i] < goals[i] < START[i] + moved for i in IDS), goals
