"""Health of Cia402Hardware against emulated CiA 402 drives on python-can's virtual bus.

Statusword and error code come with every cycle's TPDOs; the error register 0x1001 is read by
an expedited SDO upload at a low rate (one request frame after a cycle's SYNC, the answer taken
with a later cycle's TPDOs). Waits are on conditions with a deadline.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest

from jtc_hw.drivers.can.cia402.emulator import Cia402DriveEmulator
from jtc_hw.drivers.can.cia402.hardware import Cia402Hardware
from jtc_hw.errors import HardwareError

pytestmark = pytest.mark.usefixtures("no_leaks")

JOINTS = ("shoulder", "elbow")
NODES = (3, 7)
BOUND_S = 5.0


@pytest.fixture
def rig() -> Iterator[tuple[can.BusABC, dict[int, Cia402DriveEmulator], Cia402Hardware]]:
    channel = f"cia402-health-{uuid.uuid4().hex[:8]}"
    bus = can.Bus(interface="virtual", channel=channel)
    drives = {n: Cia402DriveEmulator(bus, n, initial_position=0.1 * n) for n in NODES}
    for d in drives.values():
        d.start()
    hw = Cia402Hardware("arm", JOINTS, ["position"], ["position", "velocity"], {
        "buses": {"can0": {"interface": "virtual", "channel": channel,
                           "receive_timeout": 0.005, "setup_timeout": 0.5}},
        "node_id": list(NODES),
        "feedback_timeout_s": 0.3,
        "watchdog_s": 1.0,
        "health_period_s": 0.02,
    })
    try:
        yield bus, drives, hw
    finally:
        try:
            hw.shutdown(time.monotonic_ns())
        finally:
            for d in drives.values():
                d.stop()
            bus.shutdown()


def cycle_until(hw: Cia402Hardware, done: Callable[[dict[str, Any]], bool]) -> dict[str, Any]:
    """Write/read cycles (faults raised by read are expected and ignored here) until the
    health meets ``done``; fails after ``BOUND_S``."""
    deadline = time.monotonic() + BOUND_S
    while True:
        hw.write(time.monotonic_ns(), hw.nan_command())
        try:
            hw.read(time.monotonic_ns())
        except HardwareError:
            pass
        health = hw.health()
        if done(health):
            return health
        assert time.monotonic() < deadline, f"health never got there: {health}"


def test_error_register_is_read_by_sdo_without_a_cycle_waiting_for_it(
    rig: tuple[can.BusABC, dict[int, Cia402DriveEmulator], Cia402Hardware],
) -> None:
    _, drives, hw = rig
    hw.configure()
    hw.activate(time.monotonic_ns())
    health = cycle_until(hw, lambda h: all(m["error_register"] is not None
                                           for m in h["motors"]))
    for motor, node, joint in zip(health["motors"], NODES, JOINTS, strict=True):
        assert (motor["motor"], motor["joint"]) == (node, joint)
        assert motor["error_register"] == "0x00" and motor["error_code"] == "0x0000"
        assert motor["state"] == "operation enabled" and motor["torque_enabled"] is True
        assert motor["errors"] == []
        assert motor["temperature_c"] is None  # no standard CiA 402 object for it
    assert health["bus"]["sdo_aborts"] == 0
    # A drive fault: the error code from the TPDO, the error register from the next SDO read.
    drives[7].inject_fault(0x4310)
    health = cycle_until(hw, lambda h: h["motors"][1]["error_register"] not in (None, "0x00"))
    elbow = health["motors"][1]
    assert elbow["error_code"] == "0x4310"
    assert int(elbow["error_register"], 16) == drives[7].error_register
    assert any("0x4310" in e for e in elbow["errors"])
    assert any("error register" in w for w in health["warnings"])


def test_after_the_drives_fall_silent_health_no_longer_says_torque_enabled(
    rig: tuple[can.BusABC, dict[int, Cia402DriveEmulator], Cia402Hardware],
) -> None:
    """Issue 21: the drives stop answering (a bus loss, their supply gone): health shows
    their readings as unknown with the age of the last TPDO, not "operation enabled"."""
    _, drives, hw = rig
    hw.configure()
    hw.activate(time.monotonic_ns())
    health = cycle_until(hw, lambda h: all(m["torque_enabled"] for m in h["motors"]))
    assert all(m["stale"] is False and m["age_s"] is not None for m in health["motors"])
    for d in drives.values():
        d.stop()
    health = cycle_until(hw, lambda h: all(m["stale"] for m in h["motors"]))
    for motor in health["motors"]:
        assert motor["torque_enabled"] is None and motor["state"] is None, motor
        assert motor["statusword"] is None and motor["error_code"] is None, motor
        # Stale: older than feedback_timeout_s (0.3 s); the age is given in whole ms.
        assert motor["age_s"] >= 0.3 and "torque_enabled" in motor["unknown"], motor
