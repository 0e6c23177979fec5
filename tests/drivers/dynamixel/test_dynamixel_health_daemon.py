"""``jtc-hw hardware`` end to end on emulated Dynamixel servos.

The emulator runs in this test process (its own thread, on a pty); the daemon is a subprocess
whose loop opens the pty with the real SDK. Temperature and voltage are changed in the emulator;
the test waits (with a deadline) until the daemon's status shows them, then checks the table,
``--json``, the warning in status and the one line in the daemon's log.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import WAIT_S, DaemonProcess, connect
from helpers.daemon import ConfiguredDaemon as DxlDaemon
from helpers.dynamixel import DAEMON_TEST_TIMEOUT_MS, servos_as_hardware

from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_NO_DAEMON
from jtc_hw.cli.status import format_hardware, hardware_report
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator

from conftest import make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")

JOINTS = ["shoulder", "elbow", "wrist"]
IDS = [1, 2, 3]
START = {i: math.pi + 0.1 * (i - 2) for i in IDS}


def robot(socket_path: Path, device: str) -> dict[str, Any]:
    params: dict[str, Any] = {
        "port": device,
        "baud_rate": 4_000_000,
        "ids": IDS,
        "offset": -math.pi,
        # The emulator shares the test process: allow for its thread being starved.
        "timeout_ms": DAEMON_TEST_TIMEOUT_MS,
        "latency_timer_warn": False,
        "watchdog_s": 1.0,
        "health_period_s": 0.2,
        "temperature_warn_c": 60.0,
        # Narrower than the servos' own 9.5..16 V limits: a warning, not an alert (a servo
        # reporting an input voltage error is a fault the driver stops on).
        "voltage_range": [11.0, 13.0],
    }
    hardware = [{"name": "arm", "kind": "dynamixel", "joints": JOINTS, "params": params}]
    return make_robot_config(socket_path, JOINTS, hardware, update_rate=200)


@pytest.fixture(scope="module")
def emulator() -> Iterator[DynamixelEmulator]:
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        yield emu


@pytest.fixture(scope="module")
def daemon(
    tmp_path_factory: pytest.TempPathFactory, emulator: DynamixelEmulator
) -> Iterator[DxlDaemon]:
    d = DxlDaemon(tmp_path_factory.mktemp("health"),
                  lambda sock: robot(sock, emulator.device_path))
    with d.serving():
        yield d


def motor_health(status: dict[str, Any], servo_id: int) -> dict[str, Any]:
    """Servo ``servo_id``'s health in ``status`` (empty before the loop's first status)."""
    if "hardware" not in status:
        return {}
    (component,) = status["hardware"]["components"]
    found: dict[str, Any] = next(
        m for m in component["health"]["motors"] if m["motor"] == servo_id)
    return found


def wait_status(d: DaemonProcess, condition: Callable[[dict[str, Any]], bool]) -> dict[str, Any]:
    """The first status (polled) that meets ``condition``; fails after ``WAIT_S``."""
    deadline = time.monotonic() + WAIT_S
    with connect(d) as client:
        while True:
            status: dict[str, Any] = client.get_status()
            if condition(status):
                return status
            assert time.monotonic() < deadline, f"no such status; last: {status}"
            time.sleep(0.05)  # the status is refreshed at 2 Hz: ask again a little later


def hardware_table(d: DaemonProcess, capsys: pytest.CaptureFixture[str], *extra: str) -> str:
    assert main(["hardware", "--socket", str(d.socket), *extra]) == 0
    out: str = capsys.readouterr().out
    return out


def test_hardware_shows_temperature_and_voltage(
    daemon: DxlDaemon, capsys: pytest.CaptureFixture[str]
) -> None:
    wait_status(daemon, lambda s: motor_health(s, 3).get("temperature_c") is not None
                and motor_health(s, 3).get("voltage_v") is not None)
    table = hardware_table(daemon, capsys)
    lines = table.splitlines()
    assert lines[0].startswith("arm (dynamixel, active)  bus: ")
    assert "temp degC" in lines[1] and "supply V" in lines[1]
    for line, servo_id, joint in zip(lines[2:5], IDS, JOINTS, strict=True):
        cells = line.split()
        assert cells[:3] == [str(servo_id), joint, "XM430-W350"]
        assert cells[4:8] == ["position", "on", "35", "12.0"]
    report = json.loads(hardware_table(daemon, capsys, "--json"))
    (component,) = report["components"]
    assert [m["temperature_c"] for m in component["motors"]] == [35, 35, 35]
    assert component["warnings"] == []


def test_a_hot_motor_and_a_low_supply_show_in_status_the_table_and_the_log(
    daemon: DxlDaemon, emulator: DynamixelEmulator, capsys: pytest.CaptureFixture[str]
) -> None:
    emulator.set_temperature(2, 71.0)  # above temperature_warn_c 60, below the 80 degC limit
    emulator.set_input_voltage(1, 10.0)  # below voltage_range, inside the servo's limits
    try:
        status = wait_status(daemon, lambda s: motor_health(s, 2)["temperature_c"] == 71
                             and motor_health(s, 1)["voltage_v"] == 10.0)
        (component,) = status["hardware"]["components"]
        warnings = component["health"]["warnings"]
        assert any("motor 2 (joint 'elbow')" in w and "71 degC" in w for w in warnings)
        assert any("motor 1 (joint 'shoulder')" in w and "10 V" in w for w in warnings)
        table = hardware_table(daemon, capsys)
        elbow = next(line for line in table.splitlines() if line.split()[:2] == ["2", "elbow"])
        assert "71" in elbow.split()
        assert "WARNING: dynamixel hardware 'arm': motor 2 (joint 'elbow'): temperature 71" \
            in table
        daemon.wait_log("motor 2 (joint 'elbow'): temperature 71 degC at or above "
                        "temperature_warn_c 60 degC")
    finally:
        emulator.set_temperature(2, 35.0)
        emulator.set_input_voltage(1, None)
    # Back within the limits: the warnings clear, and the log said so once per warning.
    wait_status(daemon, lambda s: not s["hardware"]["components"][0]["health"]["warnings"])
    daemon.wait_log("cleared: dynamixel hardware 'arm': motor 2 (joint 'elbow'): temperature 71")
    hot = [line for line in daemon.log().splitlines() if "temperature 71 degC" in line]
    assert [line.split()[0] for line in hot] == ["WARNING", "INFO"], hot


def test_hardware_without_a_daemon_exits_3_and_before_the_first_status_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["hardware", "--socket", str(tmp_path / "none.sock")]) == EXIT_NO_DAEMON
    assert "cannot reach a jtc-hw daemon" in capsys.readouterr().err
    text = format_hardware(hardware_report({"alive": True}))
    assert text.startswith("no hardware status yet")
