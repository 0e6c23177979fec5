"""Motor health of MitHardware against the MIT bus emulator on python-can's virtual bus.

Damiao replies carry a state code and two temperatures; the driver reports them from the
replies each cycle collects anyway (no extra frame). AK replies carry neither: health says
"unknown" rather than inventing values.
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Iterator

import can
import numpy as np
import pytest

from jtc_hw.cli.status import format_hardware, hardware_report
from jtc_hw.controller.joints import JointCommand
from jtc_hw.drivers.can.mit.emulator import MitBusEmulator
from jtc_hw.drivers.can.mit.hardware import MitHardware

pytestmark = pytest.mark.usefixtures("no_leaks")


@pytest.fixture
def channel() -> Iterator[str]:
    yield f"mit-health-{uuid.uuid4().hex}"


def rig(channel: str, model: str, **params: object) -> tuple[can.BusABC, MitBusEmulator,
                                                             MitHardware]:
    bus = can.Bus(interface="virtual", channel=channel)
    extra = {"master_id": 0x11} if model.startswith("DM") else {}
    emulator = MitBusEmulator(bus, [1, 2], model, master_id=0x11 if extra else 0)
    emulator.start()
    hw = MitHardware("leg", ["a", "b"], ("position",), ("position", "velocity"), {
        "ids": [1, 2], "model": model, "feedback_timeout": 0.5, "watchdog_s": 1.0,
        "buses": {"can0": {"interface": "virtual", "channel": channel,
                           "receive_timeout": 0.05}},
        **extra, **params,
    })
    return bus, emulator, hw


def cycle(hw: MitHardware, n: int = 3) -> None:
    for _ in range(n):
        state = hw.read(time.monotonic_ns())
        hw.write(time.monotonic_ns(), JointCommand(positions=np.array(state.positions)))


def test_damiao_health_reports_temperatures_state_and_warns_once(
    channel: str, caplog: pytest.LogCaptureFixture
) -> None:
    bus, emulator, hw = rig(channel, "DM4310", temperature_warn_c=60.0, max_temperature_c=90.0)
    try:
        hw.configure()
        hw.activate(time.monotonic_ns())
        cycle(hw)
        health = hw.health()
        first = health["motors"][0]
        assert (first["motor"], first["joint"], first["model"]) == (1, "a", "DM4310")
        assert first["torque_enabled"] is True and first["state"] == "enabled"
        assert first["temperature_c"] == 30 and first["rotor_temperature_c"] == 30
        assert first["voltage_v"] is None  # no MIT reply carries the supply
        assert health["bus"]["transactions"] > 0 and health["bus"]["timeouts"] == 0
        assert health["warnings"] == []
        emulator.set_temperature(2, 70)  # warning, below max_temperature_c's fault
        cycle(hw)
        with caplog.at_level(logging.WARNING, logger="jtc_hw.hardware"):
            warned = hw.health()
            hw.health()
        assert warned["motors"][1]["drive_temperature_c"] == 70
        (warning,) = warned["warnings"]
        assert "motor 2 (joint 'b')" in warning and "70 degC" in warning
        assert len(caplog.records) == 1
    finally:
        hw.shutdown(time.monotonic_ns())
        emulator.stop()
        bus.shutdown()


def test_ak_health_reports_nothing_it_cannot_know(channel: str) -> None:
    bus, emulator, hw = rig(channel, "AK80-9")
    try:
        hw.configure()
        hw.activate(time.monotonic_ns())
        cycle(hw)
        motor = hw.health()["motors"][0]
        assert motor["temperature_c"] is None and motor["state"] is None
        # An AK reply does not say whether the motor is in motor mode.
        assert motor["errors"] == [] and motor["torque_enabled"] is None
        assert motor["commanded_mode"] == "mit" and motor["stale"] is False
        assert "voltage_range" not in hw.params
    finally:
        hw.shutdown(time.monotonic_ns())
        emulator.stop()
        bus.shutdown()


def test_a_miss_rate_above_miss_rate_warn_warns_once_and_clears(
    channel: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Replies that do not come in time, too few for a no-feedback fault, are a warning in
    health (status, ``jtc-hw hardware``) once their rate over a window of at least
    MISS_RATE_WINDOW transactions passes ``miss_rate_warn``; logged once per crossing."""
    # The rig's receive_timeout (50 ms) is generous: only the dropped replies are missed.
    bus, emulator, hw = rig(channel, "AK80-9")  # miss_rate_warn: its default, 1 %
    try:
        hw.configure()
        hw.activate(time.monotonic_ns())
        window = 1000 // 2  # cycles: MISS_RATE_WINDOW transactions, two motors a cycle
        cycle(hw, window)
        assert hw.health()["warnings"] == []
        with caplog.at_level(logging.INFO, logger="jtc_hw.hardware"):
            for _ in range(15):  # 15 of ~1000, one at a time: 1.5 %, never a fault
                emulator.drop_replies(2, 1)
                cycle(hw, window // 15)
            cycle(hw, window % 15)
            warned = hw.health()
            cycle(hw, 10)
            again = hw.health()  # the window is still open: the verdict stands, no new line
        (warning,) = warned["warnings"]
        assert "leg" in warning and "15 of" in warning and "miss_rate_warn 1 %" in warning
        assert again["warnings"] == [warning]
        assert [r.levelno for r in caplog.records] == [logging.WARNING]
        report = hardware_report({"hardware": {"components": [
            {"name": "leg", "kind": "can-mit", "state": "active", "health": warned}]}})
        assert f"WARNING: {warning}" in format_hardware(report).splitlines()[-1]
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="jtc_hw.hardware"):
            cycle(hw, window)  # no miss in a whole window: cleared, one line
            assert hw.health()["warnings"] == []
        assert [r.getMessage().startswith("cleared: ") for r in caplog.records] == [True]
    finally:
        hw.shutdown(time.monotonic_ns())
        emulator.stop()
        bus.shutdown()
