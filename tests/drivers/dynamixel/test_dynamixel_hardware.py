"""DynamixelHardware against the pty emulator, in process: the real SDK on a real pty.

The emulator (drivers/dynamixel/emulator.py) speaks Protocol 2.0 on a pseudo-terminal from its
own thread; the driver under test opens that pty with the ROBOTIS SDK exactly as it opens a USB
adapter. Faults are injected into the emulator (silent servo, dropped replies, corrupt CRC,
hardware error). Waits are on conditions (what the servos report) with deadlines; nothing here
asserts a duration.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.dynamixel import (
    DRIVER_TEST_TIMEOUT_MS,
    IDS,
    OFFSET,
    START,
    TICK,
    WAIT_S,
    driver_factory,
    emulated_arm,
    now_ns,
)

from jtc_hw.controller.joints import JointCommand
from jtc_hw.drivers.dynamixel.bus import DynamixelBus, ServoStatusError, latency_timer_ms
from jtc_hw.drivers.dynamixel.control_table import HardwareError, model_by_name
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator
from jtc_hw.drivers.dynamixel.hardware import DynamixelHardware
from jtc_hw.errors import CommunicationError, ConfigurationError, MotorFault
from jtc_hw.hardware import LifecycleState

S = 1_000_000_000
XM430 = model_by_name("XM430-W350")




@pytest.fixture
def emulator() -> Iterator[DynamixelEmulator]:
    yield from emulated_arm()


@pytest.fixture
def make_hw(emulator: DynamixelEmulator) -> Iterator[Callable[..., DynamixelHardware]]:
    """Build drivers on the emulator's pty; each is shut down after the test."""
    yield from driver_factory(emulator)


def expected_joint(motor_rad: float, offset: float = OFFSET, direction: int = 1,
                   gear: float = 1.0) -> float:
    ticks = round(motor_rad / TICK)
    return direction * ticks * TICK / gear + offset


def read_until(hw: DynamixelHardware, predicate: Callable[[np.ndarray], bool],
               timeout_s: float = WAIT_S) -> np.ndarray:
    """Read (the servos move in emulated time) until ``predicate(positions)`` holds."""
    deadline = time.monotonic() + timeout_s
    while True:
        positions = hw.read(now_ns()).positions
        if predicate(positions):
            return positions
        assert time.monotonic() < deadline, f"condition not reached; positions {positions}"


# -- lifecycle ----------------------------------------------------------------------------------


def test_configure_activate_read_write_deactivate(
    make_hw: Callable[..., DynamixelHardware], emulator: DynamixelEmulator
) -> None:
    hw = make_hw()
    hw.configure()
    state = hw.read(now_ns())
    assert state.positions == pytest.approx([expected_joint(START[i]) for i in IDS], abs=1e-12)
    held = hw.activate(now_ns())
    assert held.positions is not None
    # Seeded from the measured position: no jump.
    assert held.positions == pytest.approx(state.positions, abs=1e-12)
    assert hw.bus is not None
    assert [hw.bus.read(i, 64, 1) for i in IDS] == [1, 1, 1]  # torque on
    assert [hw.bus.read(i, 11, 1) for i in IDS] == [3, 3, 3]  # position mode

    target = state.positions + np.array([0.2, -0.1, 0.0])
    hw.write(now_ns(), JointCommand(positions=target))
    reached = read_until(hw, lambda p: bool(np.all(np.abs(p - target) < 2 * TICK)))
    assert reached == pytest.approx(target, abs=2 * TICK)
    motor = emulator.positions()
    assert motor[1] == pytest.approx(target[0] - OFFSET, abs=2 * TICK)

    # NaN: that joint's goal is not written.
    hw.write(now_ns(), JointCommand(positions=[math.nan, target[1], target[2]]))
    hw.deactivate(now_ns())
    assert hw.state is LifecycleState.INACTIVE
    assert [hw.bus.read(i, 64, 1) for i in IDS] == [1, 1, 1]  # hold: torque stays on
    hw.cleanup()
    assert hw.bus is None


def test_torque_off_safe_action(make_hw: Callable[..., DynamixelHardware]) -> None:
    hw = make_hw(safe_action="torque_off")
    hw.configure()
    hw.activate(now_ns())
    hw.deactivate(now_ns())
    assert hw.bus is not None
    assert [hw.bus.read(i, 64, 1) for i in IDS] == [0, 0, 0]


def test_setup_registers_are_written(make_hw: Callable[..., DynamixelHardware]) -> None:
    hw = make_hw(return_delay_time_us=4, position_p_gain=[900, 901, 902],
                 profile_velocity=1.0, position_limits=[-1.0, 1.0])
    hw.configure()
    bus = hw.bus
    assert bus is not None
    assert [bus.read(i, 9, 1) for i in IDS] == [2, 2, 2]  # return delay in 2 us units
    assert [bus.read(i, 84, 2) for i in IDS] == [900, 901, 902]
    assert bus.read(1, 112, 4) == round(1.0 / XM430.velocity_unit_rad_s)
    assert bus.read(1, 52, 4) == round((-1.0 - OFFSET) / TICK)  # min position limit
    assert bus.read(1, 48, 4) == round((1.0 - OFFSET) / TICK)


# -- unit conversion ----------------------------------------------------------------------------


def test_unit_conversion_is_exact_and_symmetric() -> None:
    hw = DynamixelHardware(
        "arm", ["a", "b", "c"], ["position"], ["position"],
        {"port": "/dev/null", "ids": [1, 2, 3], "offset": [0.0, -math.pi, 0.25],
         "direction": [1, -1, -1], "gear_ratio": [1.0, 2.0, 3.5], "extended_position": True},
    )
    ticks = np.array([[0, 0, 0], [2048, 2048, 2048], [-5000, 123456, 4095], [1, -1, 77]])
    for row in ticks:
        joint = hw.units.ticks_to_joint(row)
        assert list(hw.units.joint_to_ticks(joint)) == list(row)
    # The documented formula, literally.
    j = hw.units.ticks_to_joint(np.array([1024, 1024, 1024]))
    assert j[0] == pytest.approx(math.pi / 2)
    assert j[1] == pytest.approx(-(math.pi / 2) / 2.0 - math.pi)
    assert j[2] == pytest.approx(-(math.pi / 2) / 3.5 + 0.25)
    # Velocity: 0.229 rev/min per count; effort: 2.69 mA per count * torque constant * gear.
    v = hw.units.velocity_to_joint(np.array([100, 100, 100]))
    unit = 0.229 * 2 * math.pi / 60
    assert v == pytest.approx([100 * unit, -100 * unit / 2.0, -100 * unit / 3.5])
    assert list(hw.units.joint_to_velocity(v)) == [100, 100, 100]
    e = hw.units.current_to_joint(np.array([10, 10, 10]))
    kt = 4.1 / 2.3
    assert e == pytest.approx([10 * 0.00269 * kt, -10 * 0.00269 * kt * 2.0,
                               -10 * 0.00269 * kt * 3.5])
    assert list(hw.units.joint_to_current(e)) == [10, 10, 10]


def test_direction_and_gear_against_the_emulator(
    make_hw: Callable[..., DynamixelHardware]
) -> None:
    hw = make_hw(direction=[1, -1, 1], gear_ratio=[1.0, 1.0, 2.0], offset=[OFFSET, 0.5, 0.0],
                 extended_position=True)
    hw.configure()
    positions = hw.read(now_ns()).positions
    assert positions == pytest.approx([
        expected_joint(START[1]),
        expected_joint(START[2], 0.5, -1),
        expected_joint(START[3], 0.0, 1, 2.0),
    ], abs=1e-12)


def test_bad_parameters_are_configuration_errors() -> None:
    def build(**params: Any) -> DynamixelHardware:
        return DynamixelHardware("arm", ["a", "b"], ["position"], ["position"],
                                 {"port": "/dev/null", "ids": [1, 2], **params})

    with pytest.raises(ConfigurationError, match="servo id 1 is given to both"):
        build(ids=[1, 1])
    with pytest.raises(ConfigurationError, match=r"params\.direction: must be 1 or -1, got 0"):
        build(direction=0)
    with pytest.raises(ConfigurationError, match="baud rate must be one of"):
        build(baud_rate=12345)
    with pytest.raises(ConfigurationError, match="unknown Dynamixel model"):
        build(model="XM999")
    with pytest.raises(ConfigurationError, match="outside Position mode"):
        build(position_limits=[-1.0, 1.0])  # offset 0: negative ticks
    with pytest.raises(ConfigurationError, match="exactly one command interface"):
        DynamixelHardware("arm", ["a"], ["position", "velocity"], ["position"],
                          {"port": "/dev/null", "ids": [1]})
    with pytest.raises(ConfigurationError, match="no current mode"):
        DynamixelHardware("arm", ["a"], ["effort"], ["position"],
                          {"port": "/dev/null", "ids": [1], "model": "XL430-W250"})


# -- configure errors ---------------------------------------------------------------------------


def test_model_mismatch_names_the_servo_and_both_models(
    make_hw: Callable[..., DynamixelHardware]
) -> None:
    hw = make_hw(model={"elbow": "XM540-W270"})
    with pytest.raises(ConfigurationError) as info:
        hw.configure()
    message = str(info.value)
    assert "servo 2" in message and "'elbow'" in message
    assert "XM430-W350" in message and "XM540-W270" in message
    assert hw.state is LifecycleState.UNCONFIGURED


def test_missing_servo_at_configure(make_hw: Callable[..., DynamixelHardware]) -> None:
    hw = make_hw(ids=[1, 2, 9])
    with pytest.raises(CommunicationError) as info:
        hw.configure()
    assert "servo 9" in str(info.value) and "'wrist'" in str(info.value)
    assert "timeout" in str(info.value)


def test_a_missed_reply_at_configure_is_retried(
    make_hw: Callable[..., DynamixelHardware], emulator: DynamixelEmulator
) -> None:
    """A ping (or register read) of configuration whose reply is lost is retried, as the
    cycle's Sync Read is (``max_retries``): one lost reply on a busy host made the demo's
    daemon refuse to start (tools/ci-under-load, issue 22). Without retries it is still an
    error naming the servo."""
    emulator.drop_replies(2, 1)  # servo 2's first packet is its ping
    hw = make_hw(max_retries=1)
    hw.configure()
    assert hw.status()["details"]["retries"] == 1
    emulator.drop_replies(2, 1)
    strict = make_hw(max_retries=0)
    with pytest.raises(CommunicationError, match=r"servo 2 \(joint 'elbow'\): ping at configure"):
        strict.configure()


# -- faults -------------------------------------------------------------------------------------


@pytest.fixture
def active(make_hw: Callable[..., DynamixelHardware]) -> DynamixelHardware:
    hw = make_hw(max_retries=1)
    hw.configure()
    hw.activate(now_ns())
    hw.read(now_ns())
    return hw


def _assert_positions_kept(hw: DynamixelHardware, before: np.ndarray) -> None:
    after = hw.last_positions
    assert after is not None
    assert np.array_equal(after, before)  # never replaced by a failed read's zeros
    assert not np.any(after == OFFSET)  # tick 0 would read as the offset


def test_silent_servo_is_a_communication_error_naming_it(
    active: DynamixelHardware, emulator: DynamixelEmulator
) -> None:
    before = active.last_positions
    assert before is not None
    emulator.set_silent(2, True)
    with pytest.raises(CommunicationError) as info:
        active.read(now_ns())
    message = str(info.value)
    assert "servo 2" in message and "'elbow'" in message and "timeout" in message
    assert "2 attempts" in message
    _assert_positions_kept(active, before)
    assert active.status()["details"]["servos"]["2"]["last_fault"]
    emulator.set_silent(2, False)
    assert active.read(now_ns()).positions == pytest.approx(before, abs=2 * TICK)


def test_dropped_replies_within_retries_are_absorbed(
    active: DynamixelHardware, emulator: DynamixelEmulator
) -> None:
    emulator.drop_replies(3, 1)  # max_retries=1: the retry succeeds
    active.read(now_ns())
    assert active.status()["details"]["retries"] == 1


def test_dropped_replies_beyond_retries_are_a_fault(
    active: DynamixelHardware, emulator: DynamixelEmulator
) -> None:
    before = active.last_positions
    assert before is not None
    emulator.drop_replies(3, 2)
    with pytest.raises(CommunicationError, match=r"servo 3 \(joint 'wrist'\)"):
        active.read(now_ns())
    _assert_positions_kept(active, before)
    active.read(now_ns())  # the emulator answers again


def test_corrupt_crc_is_a_communication_error(
    active: DynamixelHardware, emulator: DynamixelEmulator
) -> None:
    before = active.last_positions
    assert before is not None
    emulator.corrupt_crc(1, 2)
    with pytest.raises(CommunicationError) as info:
        active.read(now_ns())
    assert "servo 1" in str(info.value) and "corrupt" in str(info.value)
    _assert_positions_kept(active, before)


def test_hardware_error_is_a_motor_fault_naming_servo_and_cause(
    active: DynamixelHardware, emulator: DynamixelEmulator
) -> None:
    emulator.raise_hardware_error(2, HardwareError.OVERLOAD)
    with pytest.raises(MotorFault) as info:
        active.read(now_ns())
    message = str(info.value)
    assert "servo 2" in message and "'elbow'" in message and "overload" in message
    assert active.status()["details"]["servos"]["2"]["hardware_error"] == "overload"


def test_reboot_and_rearm_without_a_jump(
    active: DynamixelHardware, emulator: DynamixelEmulator
) -> None:
    emulator.raise_hardware_error(2, HardwareError.OVERLOAD)
    with pytest.raises(MotorFault):
        active.read(now_ns())
    active.deactivate(now_ns())
    # What the loop's rearm does: cleanup -> configure -> recover -> activate.
    active.cleanup()
    active.configure()
    with pytest.raises(MotorFault, match="servo 2"):
        active.activate(now_ns())  # still latched: activating needs the explicit recover
    active.recover()
    held = active.activate(now_ns())
    measured = active.read(now_ns()).positions
    assert held.positions is not None
    assert held.positions == pytest.approx(measured, abs=2 * TICK)
    assert active.status()["details"]["servos"]["2"]["hardware_error"] is None
    assert active.bus is not None
    assert active.bus.read(2, 64, 1) == 1  # torque back on
    assert active.bus.read(2, 70, 1) == 0
    # Holding: the servo stays where it was.
    assert read_until(active, lambda p: True) == pytest.approx(measured, abs=3 * TICK)


def test_without_recover_a_latched_fault_blocks_activation(
    make_hw: Callable[..., DynamixelHardware], emulator: DynamixelEmulator
) -> None:
    emulator.raise_hardware_error(1, HardwareError.OVERHEATING)
    hw = make_hw()
    hw.configure()  # configure tolerates it (so that a re-arm can reboot the servo)
    with pytest.raises(MotorFault, match=r"servo 1 .*overheating"):
        hw.activate(now_ns())


# -- velocity and current modes -----------------------------------------------------------------


def test_velocity_mode(make_hw: Callable[..., DynamixelHardware]) -> None:
    hw = make_hw(("velocity",), direction=[1, -1, 1])
    hw.configure()
    assert hw.bus is not None
    assert [hw.bus.read(i, 11, 1) for i in IDS] == [1, 1, 1]
    held = hw.activate(now_ns())
    assert held.velocities is not None and list(held.velocities) == [0.0, 0.0, 0.0]
    start = hw.read(now_ns()).positions
    hw.write(now_ns(), JointCommand(velocities=[0.5, 0.5, math.nan]))
    moved = read_until(hw, lambda p: bool(p[0] - start[0] > 0.05 and p[1] - start[1] > 0.05))
    assert abs(moved[2] - start[2]) < 0.02
    # Direction -1: the joint moves positive, the servo negative.
    assert hw.bus.read(2, 104, 4) == (-round(0.5 / XM430.velocity_unit_rad_s)) & 0xFFFFFFFF
    state = hw.read(now_ns())
    assert state.velocities is not None
    assert state.velocities[0] == pytest.approx(0.5, abs=0.1)
    hw.deactivate(now_ns())  # hold: velocity 0
    assert hw.bus.read(1, 104, 4) == 0


def test_current_mode(make_hw: Callable[..., DynamixelHardware]) -> None:
    hw = make_hw(("effort",), direction=[1, -1, 1])
    hw.configure()
    assert hw.bus is not None
    assert [hw.bus.read(i, 11, 1) for i in IDS] == [0, 0, 0]
    held = hw.activate(now_ns())
    assert held.effort is not None and list(held.effort) == [0.0, 0.0, 0.0]
    start = hw.read(now_ns()).positions
    hw.write(now_ns(), JointCommand(effort=[0.3, 0.3, math.nan]))
    counts = round(0.3 / (0.00269 * 4.1 / 2.3))
    assert hw.bus.read(1, 102, 2) == counts
    assert hw.bus.read(2, 102, 2) == (-counts) & 0xFFFF
    read_until(hw, lambda p: bool(p[0] - start[0] > 0.05 and p[1] - start[1] > 0.05))
    assert hw.last_efforts[0] == pytest.approx(0.3, abs=0.05)
    # Hold: switched to position mode at the present position (zero current would drop it).
    hw.deactivate(now_ns())
    assert hw.bus.read(1, 11, 1) == 3 and hw.bus.read(1, 64, 1) == 1
    hw.activate(now_ns())
    assert hw.bus.read(1, 11, 1) == 0


# -- bus level ----------------------------------------------------------------------------------


def test_latency_timer_warning(
    tmp_path: Path, emulator: DynamixelEmulator, caplog: pytest.LogCaptureFixture
) -> None:
    link = tmp_path / "ttyUSB7"
    link.symlink_to(emulator.device_path)
    tty = Path(emulator.device_path).resolve().name
    node = tmp_path / "sys" / "bus" / "usb-serial" / "devices" / tty
    node.mkdir(parents=True)
    (node / "latency_timer").write_text("16\n")
    assert latency_timer_ms(str(link), tmp_path / "sys") == 16
    # (A generous timeout: the ping's reply comes from this process's emulator thread, late
    # on a busy host; the warning is what is tested.)
    with caplog.at_level(logging.WARNING), \
            DynamixelBus(str(link), 4_000_000, sysfs_root=tmp_path / "sys",
                         timeout_ms=DRIVER_TEST_TIMEOUT_MS) as bus:
        assert bus.ping(1) == XM430.model_number
    assert "latency timer is 16 ms" in caplog.text
    assert f"/sys/bus/usb-serial/devices/{tty}/latency_timer" in caplog.text
    (node / "latency_timer").write_text("1\n")
    caplog.clear()
    with caplog.at_level(logging.WARNING), \
            DynamixelBus(str(link), 4_000_000, sysfs_root=tmp_path / "sys"):
        pass
    assert "latency timer" not in caplog.text


def test_sync_read_is_all_or_nothing(emulator: DynamixelEmulator) -> None:
    with DynamixelBus(emulator.device_path, 4_000_000, timeout_ms=DRIVER_TEST_TIMEOUT_MS,
                      latency_timer_warn=False) as bus:
        result = bus.sync_read(IDS, 132, 4)
        assert sorted(result.data) == IDS and result.errors == {}
        emulator.set_silent(3, True)
        with pytest.raises(CommunicationError, match="servo 3"):
            bus.sync_read(IDS, 132, 4)
        emulator.set_silent(3, False)
        assert bus.sync_read(IDS, 132, 4).data == result.data
        assert bus.stats.timeouts == 1


def test_fast_sync_read(make_hw: Callable[..., DynamixelHardware],
                        emulator: DynamixelEmulator) -> None:
    hw = make_hw(fast_sync_read=True)
    hw.configure()
    positions = hw.read(now_ns()).positions
    assert positions == pytest.approx([expected_joint(START[i]) for i in IDS], abs=1e-12)
    emulator.set_silent(2, True)
    with pytest.raises(CommunicationError, match=r"servo 2 \(joint 'elbow'\)"):
        hw.read(now_ns())
    assert hw.last_positions is not None
    assert np.array_equal(hw.last_positions, positions)


def test_waiting_for_a_silent_servo_does_not_spin(emulator: DynamixelEmulator) -> None:
    """The SDK polls a non-blocking port in a loop; ours blocks in select() until the deadline.

    Measured as this thread's CPU time against the time the failed read took: a busy loop
    would burn all of it. (This compares CPU with elapsed time; it asserts no duration.)
    """
    with DynamixelBus(emulator.device_path, 4_000_000, timeout_ms=100.0,
                      latency_timer_warn=False) as bus:
        emulator.set_silent(2, True)
        cpu0, wall0 = time.thread_time(), time.monotonic()
        with pytest.raises(CommunicationError, match="servo 2"):
            bus.sync_read(IDS, 132, 4)
        cpu, wall = time.thread_time() - cpu0, time.monotonic() - wall0
    assert cpu < 0.25 * wall, (cpu, wall)


def test_the_sdk_port_uses_the_monotonic_clock(emulator: DynamixelEmulator) -> None:
    bus = DynamixelBus(emulator.device_path, 4_000_000, latency_timer_warn=False)
    before = time.monotonic_ns() / 1e6
    value = bus._port.getCurrentTime()  # the SDK's own timeout arithmetic calls this
    assert before <= value <= time.monotonic_ns() / 1e6


def test_a_late_reply_is_not_taken_for_the_next_one(
    make_hw: Callable[..., DynamixelHardware], emulator: DynamixelEmulator
) -> None:
    """A Sync Read times out, its replies arrive afterwards, and the next read returns the
    servos' new positions, never the stale ones waiting in the port.

    Ordered by events, not by the host's timing: the late replies are on the wire (the
    emulator counted them sent) before the servos move and before the next request. Before,
    a late reply raced the next read beside busy processes (a "short reply" once on an idle
    run, 2026-12-06)."""
    hw = make_hw(max_retries=0)
    hw.configure()
    hw.activate(now_ns())
    good = hw.read(now_ns()).positions
    sent = emulator.stats()["replies_sent"]
    emulator.delay_replies(1, 2 * DRIVER_TEST_TIMEOUT_MS / 1000)  # answers after the timeout
    with pytest.raises(CommunicationError, match="servo 1"):
        hw.read(now_ns())
    emulator.delay_replies(1, 0.0)
    deadline = time.monotonic() + WAIT_S
    while emulator.stats()["replies_sent"] < sent + len(IDS):  # all three, late, holding `good`
        assert time.monotonic() < deadline, "the late replies were never sent"
        time.sleep(0.005)
    target = good + 0.3
    before = [emulator.register(i, "goal_position") for i in IDS]
    hw.write(now_ns(), JointCommand(positions=target))
    while True:  # the write served, then the servos at their new goals
        goals = [emulator.register(i, "goal_position") for i in IDS]
        present = [emulator.register(i, "present_position") for i in IDS]
        if all(g != b and abs(p - g) <= 1 for g, b, p in zip(goals, before, present)):
            break
        assert time.monotonic() < deadline, f"servos at {present}, goals {goals}"
        time.sleep(0.005)
    assert hw.read(now_ns()).positions == pytest.approx(target, abs=2 * TICK)


def test_the_shipped_configurations_load() -> None:
    from jtc_hw.daemon.robot import create_hardware_set, load_robot

    root = Path(__file__).resolve().parents[3] / "config"
    for name in ("dynamixel-arm.yaml", "dynamixel-arm-emulated.yaml"):
        robot = load_robot(root / name)
        (component,) = create_hardware_set(robot).components
        assert isinstance(component, DynamixelHardware)
        assert component.ids == (1, 2, 3, 4, 5, 6)
        assert component.watchdog_timeout_s == pytest.approx(0.1)


def test_a_refused_write_names_the_servo_and_cause(emulator: DynamixelEmulator) -> None:
    with DynamixelBus(emulator.device_path, 4_000_000, timeout_ms=DRIVER_TEST_TIMEOUT_MS,
                      latency_timer_warn=False) as bus:
        bus.write(2, 64, 1, 1)  # torque on: the EEPROM area is locked
        with pytest.raises(ServoStatusError, match="servo 2 .*access error") as info:
            bus.write(2, 9, 1, 0)  # return delay time (EEPROM)
        assert info.value.servo_id == 2


def test_commands_are_clamped_to_the_servo_limits(
    make_hw: Callable[..., DynamixelHardware]
) -> None:
    hw = make_hw(("velocity",))
    hw.configure()
    hw.activate(now_ns())
    assert hw.bus is not None
    limit = hw.bus.read(1, 44, 4)  # Velocity Limit
    hw.write(now_ns(), JointCommand(velocities=[100.0, -100.0, 0.0]))
    assert hw.bus.read(1, 104, 4) == limit
    assert hw.bus.read(2, 104, 4) == (-limit) & 0xFFFFFFFF
    hw.write(now_ns(), JointCommand(velocities=[0.0, 0.0, 0.0]))


def test_packet_timeout_is_wire_time_plus_our_allowance(emulator: DynamixelEmulator) -> None:
    """Not the SDK's wire time + 2 x 16 ms + 2 ms (its LATENCY_TIMER constant stays as is)."""
    import dynamixel_sdk.port_handler as sdk_port

    with DynamixelBus(emulator.device_path, 4_000_000, timeout_ms=3.0,
                      latency_timer_warn=False) as bus:
        port = bus._port  # the SDK subclass: its timeout arithmetic is what is checked
        port.setPacketTimeout(6 * 21)
        assert port.packet_timeout == pytest.approx(6 * 21 * 10 / 4_000_000 * 1e3 + 3.0)
    assert sdk_port.LATENCY_TIMER == 16
