"""Motor health of DynamixelHardware against the pty emulator, in process (real SDK, real pty).

The driver reads temperature, supply voltage, hardware error and moving status at a low rate,
one Sync Read after a cycle's write; ``health()`` reports the last readings and the warnings of
``temperature_warn_c`` / ``voltage_range``. The cycles here are driven by hand with a synthetic
clock, so "a health period later" is a count of cycles, not a wait.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from helpers.dynamixel import IDS, driver_factory, emulated_arm, now_ns

from jtc_hw.controller.joints import JointCommand
from jtc_hw.drivers.dynamixel.control_table import HardwareError
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator
from jtc_hw.drivers.dynamixel.hardware import DynamixelHardware
from jtc_hw.errors import ConfigurationError
from jtc_hw.errors import HardwareError as DriverError

MS = 1_000_000
PERIOD_NS = 5 * MS


@pytest.fixture
def emulator() -> Iterator[DynamixelEmulator]:
    yield from emulated_arm()


@pytest.fixture
def make_hw(emulator: DynamixelEmulator) -> Iterator[Callable[..., DynamixelHardware]]:
    yield from driver_factory(emulator)


class Cycles:
    """Read -> write cycles at a synthetic 5 ms period, holding the first measured position."""

    def __init__(self, hw: DynamixelHardware) -> None:
        self.hw = hw
        self.t = now_ns()
        hw.configure()
        hw.activate(self.t)
        self.hold = hw.read(self.t).positions.copy()

    def run(self, n: int) -> list[int]:
        """``n`` cycles; returns the bus transactions each one took."""
        bus = self.hw.bus
        assert bus is not None
        costs = []
        for _ in range(n):
            self.t += PERIOD_NS
            before = bus.stats.transactions
            self.hw.read(self.t)
            self.hw.write(self.t, JointCommand(self.hold.copy()))
            costs.append(bus.stats.transactions - before)
        return costs

    def motor(self, servo_id: int) -> dict[str, Any]:
        motors = self.hw.health()["motors"]
        found: dict[str, Any] = next(m for m in motors if m["motor"] == servo_id)
        return found


def cycles_per_period(hw: DynamixelHardware) -> int:
    """Cycles that surely cover one full health period (every block read once)."""
    return int(hw.params["health_period_s"] * 1e9 / PERIOD_NS) + 2


def test_health_reports_model_firmware_torque_temperature_and_voltage(
    make_hw: Callable[..., DynamixelHardware], emulator: DynamixelEmulator,
) -> None:
    emulator.set_firmware_version(2, 46)
    hw = make_hw()
    before = hw.health()
    assert [m["motor"] for m in before["motors"]] == IDS
    assert before["motors"][0]["temperature_c"] is None  # nothing read yet, nothing invented
    c = Cycles(hw)
    c.run(cycles_per_period(hw))
    health = hw.health()
    for m, servo_id in zip(health["motors"], IDS, strict=True):
        assert m["model"] == "XM430-W350"
        assert m["firmware"] == (46 if servo_id == 2 else emulator.register(1, "firmware_version"))
        assert m["mode"] == "position"
        assert m["torque_enabled"] is True
        assert m["temperature_c"] == 35
        assert m["voltage_v"] == pytest.approx(12.0)
        assert m["errors"] == []
        assert m["moving"] is False
        assert m["motor"] == servo_id
    assert health["warnings"] == []
    bus = health["bus"]
    assert bus["transactions"] > 0 and bus["timeouts"] == 0 and bus["crc_errors"] == 0
    # The same report rides in status() (what the loop publishes).
    assert hw.status()["health"]["motors"][1]["voltage_v"] == pytest.approx(12.0)


def test_no_cycle_pays_more_than_one_extra_transaction(
    make_hw: Callable[..., DynamixelHardware],
) -> None:
    hw = make_hw(health_period_s=0.03)  # a health read every 2 cycles of 5 ms
    c = Cycles(hw)
    costs = c.run(60)
    # read (Sync Read) + write (Sync Write, no reply) = 2; a health slot adds one Sync Read.
    assert set(costs) == {2, 3}
    assert costs.count(3) >= 20


def test_changes_in_the_emulator_show_and_a_hot_motor_warns_once(
    make_hw: Callable[..., DynamixelHardware], emulator: DynamixelEmulator,
    caplog: pytest.LogCaptureFixture,
) -> None:
    hw = make_hw(temperature_warn_c=60.0, voltage_range=[11.0, 13.0])
    c = Cycles(hw)
    emulator.set_temperature(2, 66.0)  # hot, but below the XM430's 80 degC shutdown limit
    emulator.set_input_voltage(3, 10.5)  # below voltage_range, inside the servo's limits
    c.run(cycles_per_period(hw))
    with caplog.at_level(logging.WARNING, logger="jtc_hw.hardware"):
        first = hw.health()
        again = hw.health()
    assert c.motor(2)["temperature_c"] == 66
    assert c.motor(3)["voltage_v"] == pytest.approx(10.5)
    assert len(first["warnings"]) == 2
    hot = next(w for w in first["warnings"] if "temperature" in w)
    assert "motor 2" in hot and "66 degC" in hot and "temperature_warn_c 60" in hot
    low = next(w for w in first["warnings"] if "supply" in w)
    assert "motor 3" in low and "10.5 V" in low and "[11, 13]" in low
    assert again["warnings"] == first["warnings"]
    logged = [r.getMessage() for r in caplog.records]
    assert len(logged) == 2, logged  # once per crossing, not at every status
    # Back within the limits: the warnings clear.
    emulator.set_temperature(2, 40.0)
    emulator.set_input_voltage(3, None)
    c.run(cycles_per_period(hw))
    assert hw.health()["warnings"] == []
    assert c.motor(2)["temperature_c"] == 40


def test_the_default_supply_range_follows_the_model(
    make_hw: Callable[..., DynamixelHardware], emulator: DynamixelEmulator,
) -> None:
    hw = make_hw()
    c = Cycles(hw)
    emulator.set_input_voltage(1, 10.0)  # a 12 V servo: below 0.85 x 12 V, above its 9.5 V limit
    c.run(cycles_per_period(hw))
    (warning,) = hw.health()["warnings"]
    assert "motor 1" in warning and "10 V outside voltage_range [10.2, 15] V" in warning
    assert emulator.register(1, "hardware_error_status") == 0  # a warning, not the servo's error


def test_overheating_past_the_servo_limit_is_a_latched_hardware_error(
    make_hw: Callable[..., DynamixelHardware], emulator: DynamixelEmulator,
) -> None:
    hw = make_hw()
    Cycles(hw)
    emulator.set_temperature(1, 85.0)  # XM430 Temperature Limit: 80 degC
    assert emulator.register(1, "hardware_error_status") == HardwareError.OVERHEATING
    assert emulator.register(1, "torque_enable") == 0  # Shutdown holds the overheating bit
    emulator.set_temperature(1, 30.0)
    assert emulator.register(1, "hardware_error_status") == HardwareError.OVERHEATING  # latched


def test_an_input_voltage_error_does_not_shut_the_servo_down_by_default(
    emulator: DynamixelEmulator,
) -> None:
    emulator.set_input_voltage(2, 20.0)  # above Max Voltage Limit (16 V)
    assert emulator.register(2, "hardware_error_status") == HardwareError.INPUT_VOLTAGE
    emulator.set_input_voltage(2, 12.0)
    assert emulator.register(2, "hardware_error_status") == 0
    assert emulator.register(2, "present_input_voltage") == 120


def test_health_limits_are_checked_parameters(make_hw: Callable[..., DynamixelHardware]) -> None:
    with pytest.raises(ConfigurationError, match="voltage_range"):
        make_hw(voltage_range="high")
    with pytest.raises(ConfigurationError, match="temperature_warn_c"):
        make_hw(temperature_warn_c="hot")
    hw = make_hw()
    assert hw.params["temperature_warn_c"] == 65.0
    assert hw.params["voltage_range"] is None  # per servo: its model's nominal supply
    assert [m["voltage_range_v"] for m in hw.health()["motors"]] == [[10.2, 15.0]] * 3


def test_a_kind_without_health_reports_its_joints_with_nothing_known() -> None:
    from jtc_hw.hardware import HEALTH_FIELDS
    from jtc_hw.hardware.mirror import MirrorHardware

    hw = MirrorHardware("sim", ["a", "b"], ("position",), ("position",), {})
    health = hw.health()
    assert [m["joint"] for m in health["motors"]] == ["a", "b"]
    assert set(HEALTH_FIELDS) <= set(health["motors"][0])
    assert health["motors"][0]["temperature_c"] is None
    assert health["bus"] is None and health["warnings"] == []


def test_health_of_servos_no_longer_heard_is_unknown_not_the_last_reading(
    make_hw: Callable[..., DynamixelHardware], emulator: DynamixelEmulator,
) -> None:
    """Issue 21: the servos stop answering (a bus loss, their supply gone): once their health
    blocks are older than two health periods, health shows them as unknown with their age,
    not "torque on" as last read."""
    cycles = Cycles(make_hw(health_period_s=0.1))
    deadline = time.monotonic() + 10.0
    while cycles.motor(1)["stale"]:
        cycles.run(1)
        assert time.monotonic() < deadline, cycles.motor(1)
    assert cycles.motor(1)["torque_enabled"] is True and cycles.motor(1)["age_s"] >= 0.0
    for servo_id in IDS:
        emulator.set_silent(servo_id, True)
    while not (motor := cycles.motor(1))["stale"]:
        try:
            cycles.run(1)
        except DriverError:
            pass  # the silent servos: what this test is about is the health afterwards
        assert time.monotonic() < deadline, motor
    assert motor["torque_enabled"] is None and motor["temperature_c"] is None, motor
    assert motor["voltage_v"] is None and "torque_enabled" in motor["unknown"], motor
    assert motor["age_s"] > 0.2, motor  # older than two health periods
