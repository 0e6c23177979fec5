"""Motor health while faulted, end to end on emulated Dynamixel servos.

A servo reports an overload (the emulator latches the hardware error as the servo does); the
loop faults, applies the safe action and disarms the Bus Watchdogs. It keeps cycling: each cycle
reads the joints and the health block due (``HardwareInterface.monitor``), commanding nothing.
So a temperature changed in the emulator after the fault shows in the status and in
``jtc-hw hardware``, next to the fault itself. Waits are on the status with a deadline.

The driver side: while a servo's Bus Watchdog may still be armed (the deactivation could not
disarm it), ``monitor`` sends nothing at all, since every packet on the bus would feed it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import WAIT_S, connect
from helpers.daemon import ConfiguredDaemon as DxlDaemon
from helpers.dynamixel import servos_as_hardware
from test_dynamixel_health_daemon import IDS, JOINTS, motor_health, robot, wait_status

from jtc_hw.cli import main
from jtc_hw.drivers.dynamixel.control_table import HardwareError
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator
from jtc_hw.drivers.dynamixel.hardware import DynamixelHardware

pytestmark = pytest.mark.usefixtures("no_leaks")

START = {i: math.pi + 0.1 * (i - 2) for i in IDS}


@pytest.fixture(scope="module")
def emulator() -> Iterator[DynamixelEmulator]:
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        yield emu


@pytest.fixture(scope="module")
def daemon(
    tmp_path_factory: pytest.TempPathFactory, emulator: DynamixelEmulator
) -> Iterator[DxlDaemon]:
    d = DxlDaemon(tmp_path_factory.mktemp("faulted"),
                  lambda sock: robot(sock, emulator.device_path))
    with d.serving():
        yield d


def test_health_is_read_while_faulted_and_the_fault_is_shown(
    daemon: DxlDaemon, emulator: DynamixelEmulator, capsys: pytest.CaptureFixture[str]
) -> None:
    wait_status(daemon, lambda s: motor_health(s, 3).get("temperature_c") == 35)
    emulator.raise_hardware_error(2, HardwareError.OVERLOAD)
    faulted = wait_status(daemon, lambda s: bool((s.get("controller") or {}).get("fault")))
    assert "servo 2" in faulted["controller"]["fault"]
    reads_then = faulted["hardware"]["components"][0]["counters"]["reads"]
    try:
        # After the fault: the emulator's motors warm up; the status must follow.
        emulator.set_temperature(3, 66.0)  # above temperature_warn_c 60
        status = wait_status(daemon, lambda s: motor_health(s, 3)["temperature_c"] == 66)
        (component,) = status["hardware"]["components"]
        assert component["state"] == "inactive"  # still faulted: nothing re-armed it
        assert status["controller"]["fault"] == faulted["controller"]["fault"]
        assert component["counters"]["reads"] == reads_then  # monitoring is not a cycle's read
        assert any("motor 3 (joint 'wrist')" in w and "66 degC" in w
                   for w in component["health"]["warnings"])
        overloaded = motor_health(status, 2)
        assert any("overload" in e.lower() for e in overloaded["errors"]), overloaded
        assert overloaded["torque_enabled"] is False  # the servo's own reaction to overload

        assert main(["hardware", "--socket", str(daemon.socket)]) == 0
        table = capsys.readouterr().out
        assert table.splitlines()[0].startswith("arm (dynamixel, inactive)")
        wrist = next(line for line in table.splitlines()
                     if line.split()[:2] == ["3", JOINTS[2]])
        assert "66" in wrist.split()
        assert "controller fault: " in table and "servo 2" in table
        assert main(["hardware", "--socket", str(daemon.socket), "--json"]) == 0
        report = json.loads(capsys.readouterr().out)
        assert "servo 2" in report["fault"]
        assert report["components"][0]["motors"][2]["temperature_c"] == 66
    finally:
        emulator.set_temperature(3, 35.0)
    # A rearm reboots the servo (clearing its overload) and the loop controls again.
    with connect(daemon) as client:
        client.rearm()
    status = wait_status(daemon, lambda s: not s["controller"]["fault"]
                         and motor_health(s, 3)["temperature_c"] == 35)
    assert status["hardware"]["components"][0]["state"] == "active"


def test_monitor_sends_nothing_while_a_watchdog_may_still_be_armed(
    emulator: DynamixelEmulator, daemon: DxlDaemon
) -> None:
    # The daemon holds the port: stop it first (module fixture: this test runs last).
    assert daemon.stop() == 0, daemon.log()
    params: dict[str, Any] = dict(robot(Path("/nonexistent.sock"), emulator.device_path)[
        "hardware"][0]["params"])
    hw = DynamixelHardware("arm", JOINTS, ["position"], ["position", "velocity"], params)
    hw.configure()
    try:
        now = 1_000_000_000
        hw.activate(now)
        hw.deactivate(now)
        bus = hw.bus
        assert bus is not None
        before = bus.stats.transactions
        state = hw.monitor(now)  # disarmed by the deactivation: reads
        assert state is not None and len(state.positions) == len(JOINTS)
        assert bus.stats.transactions > before
        # As if the deactivation had not been able to disarm servo 1 (a broken bus).
        hw._left_armed = {1}
        before = bus.stats.transactions
        assert hw.monitor(now + 10_000_000) is None
        assert bus.stats.transactions == before
    finally:
        hw.cleanup()
    assert WAIT_S > 0
