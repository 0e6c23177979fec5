"""The official Dynamixel SDK against the emulator, over its pseudo-terminal.

The SDK's packet timeout is ``LATENCY_TIMER * 2 + 2`` ms plus the wire time, where
``LATENCY_TIMER`` is a module global of ``dynamixel_sdk.port_handler`` (16 by default, not a
PortHandler attribute); the tests raise it (see ``sdk_timing``).
"""

from __future__ import annotations

import json
import math
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import dynamixel_sdk as sdk
import pytest
from dynamixel_sdk import port_handler

from jtc_hw.drivers.dynamixel.control_table import MODELS, HardwareError
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator, parse_ids
from jtc_hw.drivers.dynamixel.packets import ALERT_BIT, ErrorNumber, Instruction, encode_instruction

XM = MODELS["XM430-W350"]
ADDR = {name: XM.register(name).address for name in XM.registers}
IDS = [1, 2, 3]


def wait_for(predicate: Callable[[], Any], timeout_s: float = 5.0) -> Any:
    """Poll ``predicate`` until it returns a truthy value; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"condition not met within {timeout_s} s")
        time.sleep(0.005)


@pytest.fixture(autouse=True)
def sdk_timing(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    # The SDK spins on the port while the emulator thread (same process here) must answer: a
    # short GIL switch interval lets it. The SDK's timeout is raised (102 ms instead of 34 ms):
    # on this loaded 2-core machine an in-process reply was sometimes later than 34 ms.
    monkeypatch.setattr(port_handler, "LATENCY_TIMER", 50)
    old = sys.getswitchinterval()
    sys.setswitchinterval(0.0005)
    try:
        yield
    finally:
        sys.setswitchinterval(old)


class Bus:
    def __init__(self, emulator: DynamixelEmulator) -> None:
        self.emu = emulator
        self.port = sdk.PortHandler(emulator.device_path)
        self.ph = sdk.PacketHandler(2.0)
        assert self.port.openPort()
        assert self.port.setBaudRate(4_000_000)

    def read(self, dxl_id: int, name: str) -> tuple[int, int, int]:
        size = XM.register(name).size
        fn = {1: self.ph.read1ByteTxRx, 2: self.ph.read2ByteTxRx, 4: self.ph.read4ByteTxRx}[size]
        value, result, error = fn(self.port, dxl_id, ADDR[name])
        if XM.register(name).signed and value >= 1 << (8 * size - 1):
            value -= 1 << (8 * size)
        return value, result, error

    def write(self, dxl_id: int, name: str, value: int) -> tuple[int, int]:
        size = XM.register(name).size
        fn = {1: self.ph.write1ByteTxRx, 2: self.ph.write2ByteTxRx, 4: self.ph.write4ByteTxRx}
        return fn[size](self.port, dxl_id, ADDR[name], value & ((1 << (8 * size)) - 1))


@pytest.fixture
def bus() -> Iterator[Bus]:
    before = set(threading.enumerate())
    emulator = DynamixelEmulator(IDS, "XM430-W350", return_delay_us=20, reboot_time_s=0.02)
    emulator.start()
    b: Bus | None = None
    try:
        b = Bus(emulator)
        yield b
    finally:
        if b is not None:
            b.port.closePort()
        emulator.close()
        assert set(threading.enumerate()) <= before


def test_ping_reports_the_model_number(bus: Bus) -> None:
    for dxl_id in IDS:
        model, result, error = bus.ph.ping(bus.port, dxl_id)
        assert (model, result, error) == (1020, sdk.COMM_SUCCESS, 0)
    _, result, _ = bus.ph.ping(bus.port, 9)
    assert result == sdk.COMM_RX_TIMEOUT
    found, result = bus.ph.broadcastPing(bus.port)
    assert result == sdk.COMM_SUCCESS and sorted(found) == IDS


def test_read_write_1_2_4_bytes(bus: Bus) -> None:
    for name, value in (("led", 1), ("position_p_gain", 1234), ("profile_velocity", 77777 % 32768)):
        assert bus.write(2, name, value) == (sdk.COMM_SUCCESS, 0)
        assert bus.read(2, name) == (value, sdk.COMM_SUCCESS, 0)
        assert bus.read(1, name)[0] == XM.register(name).default
    assert bus.read(3, "present_position") == (2048, sdk.COMM_SUCCESS, 0)
    assert bus.read(3, "model_number")[0] == 1020


def test_write_errors(bus: Bus) -> None:
    assert bus.write(1, "present_position", 5)[1] == ErrorNumber.ACCESS  # read only
    assert bus.write(1, "status_return_level", 3)[1] == ErrorNumber.DATA_RANGE
    assert bus.write(1, "goal_position", 5000)[1] == ErrorNumber.DATA_LIMIT  # position mode
    assert bus.write(1, "goal_current", 2000)[1] == ErrorNumber.DATA_RANGE  # > 1193
    assert bus.write(1, "current_limit", 500) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(1, "goal_current", -600)[1] == ErrorNumber.DATA_LIMIT
    assert bus.write(1, "goal_current", -400) == (sdk.COMM_SUCCESS, 0)
    # Half of a 4-byte register.
    result, error = bus.ph.write2ByteTxRx(bus.port, 1, ADDR["goal_position"], 100)
    assert (result, error) == (sdk.COMM_SUCCESS, ErrorNumber.DATA_LENGTH)
    assert bus.read(1, "goal_position")[0] != 100


def test_eeprom_locked_while_torque_on(bus: Bus) -> None:
    assert bus.write(1, "torque_enable", 1) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(1, "operating_mode", 1) == (sdk.COMM_SUCCESS, ErrorNumber.ACCESS)
    assert bus.read(1, "operating_mode")[0] == 3
    assert bus.write(1, "torque_enable", 0) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(1, "operating_mode", 1) == (sdk.COMM_SUCCESS, 0)
    assert bus.read(1, "operating_mode")[0] == 1


def test_sync_write_and_sync_read(bus: Bus) -> None:
    writer = sdk.GroupSyncWrite(bus.port, bus.ph, ADDR["profile_velocity"], 4)
    for dxl_id in IDS:
        assert writer.addParam(dxl_id, list((100 * dxl_id).to_bytes(4, "little")))
    assert writer.txPacket() == sdk.COMM_SUCCESS
    reader = sdk.GroupSyncRead(bus.port, bus.ph, ADDR["profile_velocity"], 4)
    for dxl_id in IDS:
        assert reader.addParam(dxl_id)
    assert reader.txRxPacket() == sdk.COMM_SUCCESS
    assert [reader.getData(i, ADDR["profile_velocity"], 4) for i in IDS] == [100, 200, 300]
    block = sdk.GroupSyncRead(bus.port, bus.ph, 126, 10)
    for dxl_id in IDS:
        block.addParam(dxl_id)
    assert block.txRxPacket() == sdk.COMM_SUCCESS
    assert [block.getData(i, ADDR["present_position"], 4) for i in IDS] == [2048] * 3


def test_fast_sync_read(bus: Bus) -> None:
    for dxl_id in IDS:
        bus.write(dxl_id, "profile_acceleration", 10 * dxl_id)
    reader = sdk.GroupSyncRead(bus.port, bus.ph, ADDR["profile_acceleration"], 8)
    for dxl_id in IDS:
        reader.addParam(dxl_id)
    for _ in range(3):
        assert reader.fastSyncRead() == sdk.COMM_SUCCESS
        assert [reader.getData(i, ADDR["profile_acceleration"], 4) for i in IDS] == [10, 20, 30]
    # A silent servo truncates the single status packet: the SDK reports a failure.
    bus.emu.set_silent(2, True)
    assert reader.fastSyncRead() != sdk.COMM_SUCCESS
    bus.emu.set_silent(2, False)
    assert reader.fastSyncRead() == sdk.COMM_SUCCESS


def test_bulk_write_and_bulk_read(bus: Bus) -> None:
    writer = sdk.GroupBulkWrite(bus.port, bus.ph)
    assert writer.addParam(1, ADDR["led"], 1, [1])
    assert writer.addParam(2, ADDR["position_p_gain"], 2, list((900).to_bytes(2, "little")))
    assert writer.txPacket() == sdk.COMM_SUCCESS
    reader = sdk.GroupBulkRead(bus.port, bus.ph)
    assert reader.addParam(1, ADDR["led"], 1)
    assert reader.addParam(2, ADDR["position_p_gain"], 2)
    assert reader.addParam(3, ADDR["present_position"], 4)
    assert reader.txRxPacket() == sdk.COMM_SUCCESS
    assert reader.getData(1, ADDR["led"], 1) == 1
    assert reader.getData(2, ADDR["position_p_gain"], 2) == 900
    assert reader.getData(3, ADDR["present_position"], 4) == 2048


def test_reboot_clears_a_latched_hardware_error(bus: Bus) -> None:
    bus.write(1, "torque_enable", 1)
    bus.emu.raise_hardware_error(1, HardwareError.OVERLOAD)
    value, result, error = bus.read(1, "hardware_error_status")
    assert result == sdk.COMM_SUCCESS and error & ALERT_BIT
    assert value == HardwareError.OVERLOAD
    assert bus.read(1, "torque_enable")[0] == 0
    assert bus.write(1, "torque_enable", 1)[1] & 0x7F == ErrorNumber.RESULT_FAIL
    assert bus.ph.reboot(bus.port, 1)[0] == sdk.COMM_SUCCESS
    # Silent while it reboots, then back without the error.
    wait_for(lambda: bus.ph.ping(bus.port, 1)[1] == sdk.COMM_SUCCESS)
    assert bus.read(1, "hardware_error_status") == (0, sdk.COMM_SUCCESS, 0)
    assert bus.write(1, "torque_enable", 1) == (sdk.COMM_SUCCESS, 0)


def test_silent_servo_times_out(bus: Bus) -> None:
    bus.emu.set_silent(2, True)
    assert bus.read(2, "present_position")[1] == sdk.COMM_RX_TIMEOUT
    reader = sdk.GroupSyncRead(bus.port, bus.ph, 126, 10)
    for dxl_id in IDS:
        reader.addParam(dxl_id)
    assert reader.txRxPacket() != sdk.COMM_SUCCESS
    bus.emu.set_silent(2, False)
    assert reader.txRxPacket() == sdk.COMM_SUCCESS


def test_dropped_and_corrupted_replies(bus: Bus) -> None:
    bus.emu.drop_replies(1, 1)
    assert bus.read(1, "present_position")[1] == sdk.COMM_RX_TIMEOUT
    assert bus.read(1, "present_position")[1] == sdk.COMM_SUCCESS
    bus.emu.corrupt_crc(3, 1)
    assert bus.read(3, "present_position")[1] == sdk.COMM_RX_CORRUPT
    assert bus.read(3, "present_position")[1] == sdk.COMM_SUCCESS


def test_delayed_replies_time_out(bus: Bus) -> None:
    bus.emu.delay_replies(1, 0.3)
    assert bus.read(1, "led")[1] != sdk.COMM_SUCCESS
    bus.emu.delay_replies(1, 0.0)
    wait_for(lambda: bus.read(1, "led")[1] == sdk.COMM_SUCCESS)


def test_status_return_level_1_answers_reads_only(bus: Bus) -> None:
    assert bus.write(1, "status_return_level", 1) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(1, "led", 1)[0] == sdk.COMM_RX_TIMEOUT  # applied, but no status
    assert bus.read(1, "led") == (1, sdk.COMM_SUCCESS, 0)


def test_position_goal_moves_the_servo(bus: Bus) -> None:
    assert bus.write(1, "torque_enable", 1) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(1, "goal_position", 3072) == (sdk.COMM_SUCCESS, 0)
    goal = XM.ticks_to_rad(3072)
    wait_for(lambda: abs(bus.emu.positions()[1] - goal) < 0.01)
    assert abs(bus.read(1, "present_position")[0] - 3072) <= 8
    assert bus.emu.positions()[2] == pytest.approx(math.pi)  # torque off: did not move


def test_velocity_mode_and_reverse_drive_mode(bus: Bus) -> None:
    assert bus.write(2, "drive_mode", 1) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(2, "operating_mode", 1) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(2, "torque_enable", 1) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(2, "goal_velocity", 50) == (sdk.COMM_SUCCESS, 0)
    wait_for(lambda: abs(bus.read(2, "present_velocity")[0] - 50) <= 2)
    # Reversed: the register counts up from -2048 (shaft at +2048) while the shaft turns back.
    wait_for(lambda: bus.read(2, "present_position")[0] > -2048 + 20)
    assert bus.emu.positions()[2] > -math.pi


def test_link_and_pacing(tmp_path: Any) -> None:
    link = str(tmp_path / "dxl")
    os.symlink("/nonexistent", link)  # stale: replaced
    with DynamixelEmulator([5], pace=True, baud=1_000_000, link=link) as emu:
        assert emu.device_path == link and os.readlink(link) == emu.slave_path
        port = sdk.PortHandler(link)
        ph = sdk.PacketHandler(2.0)
        try:
            assert port.openPort() and port.setBaudRate(1_000_000)
            assert ph.ping(port, 5)[1] == sdk.COMM_SUCCESS
        finally:
            port.closePort()
    assert not os.path.lexists(link)


def test_parse_ids() -> None:
    assert parse_ids("1-3,7") == [1, 2, 3, 7]
    assert parse_ids("4") == [4]
    for bad in ("", "3-1", "1,1", "300"):
        with pytest.raises(ValueError):
            parse_ids(bad)


def test_cli_serves_until_sigterm() -> None:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "jtc_hw.drivers.dynamixel.emulator",
            "--ids",
            "1-2",
            "--return-delay-us",
            "0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/")
        port = sdk.PortHandler(path)
        ph = sdk.PacketHandler(2.0)
        try:
            assert port.openPort() and port.setBaudRate(4_000_000)
            assert ph.ping(port, 2)[:2] == (1020, sdk.COMM_SUCCESS)
        finally:
            port.closePort()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


def test_reg_write_action_and_refused_factory_reset(bus: Bus) -> None:
    # 7 is out of LED's range: REG_WRITE already refuses it.
    result, error = bus.ph.regWriteTxRx(bus.port, 2, ADDR["led"], 1, [7])
    assert (result, error) == (sdk.COMM_SUCCESS, ErrorNumber.DATA_RANGE)
    assert bus.ph.regWriteTxRx(bus.port, 2, ADDR["led"], 1, [1]) == (sdk.COMM_SUCCESS, 0)
    assert bus.read(2, "led")[0] == 0 and bus.read(2, "registered_instruction")[0] == 1
    # The SDK's action() does not read the status the servo returns to a unicast ACTION: wait
    # until it is out, so that the next request's clearPort() discards it.
    sent = bus.emu.stats()["replies_sent"]
    assert bus.ph.action(bus.port, 2) == sdk.COMM_SUCCESS
    wait_for(lambda: bus.emu.stats()["replies_sent"] > sent)
    assert bus.read(2, "led")[0] == 1 and bus.read(2, "registered_instruction")[0] == 0
    result, error = bus.ph.factoryReset(bus.port, 2, 0xFF)
    assert (result, error) == (sdk.COMM_SUCCESS, ErrorNumber.RESULT_FAIL)
    assert bus.read(2, "led")[0] == 1


def test_fast_bulk_read(bus: Bus) -> None:
    bus.write(1, "position_p_gain", 700)
    reader = sdk.GroupBulkRead(bus.port, bus.ph)
    assert reader.addParam(1, ADDR["position_p_gain"], 2)
    assert reader.addParam(3, ADDR["present_position"], 4)
    assert reader.fastBulkRead() == sdk.COMM_SUCCESS
    assert reader.getData(1, ADDR["position_p_gain"], 2) == 700
    assert reader.getData(3, ADDR["present_position"], 4) == 2048


def test_bad_crc_from_the_host_gets_a_crc_error_status(bus: Bus) -> None:
    from jtc_hw.drivers.dynamixel.packets import Decoder, Instruction, encode_instruction

    frame = bytearray(encode_instruction(1, Instruction.READ, bytes((132, 0, 4, 0))))
    frame[-1] ^= 0x55
    ser = bus.port.ser  # the SDK's pyserial port: raw bytes, no mock
    ser.reset_input_buffer()
    ser.write(bytes(frame))
    decoder = Decoder()
    status = wait_for(lambda: decoder.feed(ser.read(64)))
    assert status[0].id == 1 and status[0].error == ErrorNumber.CRC
    assert bus.emu.stats()["crc_errors"] == 1


def test_xl430_has_present_load_and_no_current_mode() -> None:
    with DynamixelEmulator([1], "XL430-W250", baud=1_000_000) as emu:
        b = Bus.__new__(Bus)
        b.emu, b.port, b.ph = emu, sdk.PortHandler(emu.device_path), sdk.PacketHandler(2.0)
        try:
            assert b.port.openPort() and b.port.setBaudRate(1_000_000)
            assert b.ph.ping(b.port, 1)[:2] == (1060, sdk.COMM_SUCCESS)
            assert b.write(1, "operating_mode", 0) == (sdk.COMM_SUCCESS, ErrorNumber.DATA_RANGE)
            assert b.write(1, "torque_enable", 1) == (sdk.COMM_SUCCESS, 0)
            _, result, error = b.read(1, "present_current")  # address 126: present_load
            assert (result, error) == (sdk.COMM_SUCCESS, 0)
        finally:
            b.port.closePort()


def test_homing_offset_and_clear_multi_turn() -> None:
    start = 3 * 2 * math.pi + 1.0  # three turns and one radian
    with DynamixelEmulator([4], initial_positions={4: start}, return_delay_us=0) as emu:
        b = Bus.__new__(Bus)
        b.emu, b.port, b.ph = emu, sdk.PortHandler(emu.device_path), sdk.PacketHandler(2.0)
        try:
            assert b.port.openPort() and b.port.setBaudRate(4_000_000)
            ticks = XM.rad_to_ticks(start)
            assert b.read(4, "present_position")[0] == ticks
            assert b.write(4, "homing_offset", 100) == (sdk.COMM_SUCCESS, 0)
            assert b.read(4, "present_position")[0] == ticks + 100
            assert b.write(4, "operating_mode", 4) == (sdk.COMM_SUCCESS, 0)
            assert b.ph.clearMultiTurn(b.port, 4) == (sdk.COMM_SUCCESS, 0)
            assert b.read(4, "present_position")[0] == XM.rad_to_ticks(1.0) + 100
        finally:
            b.port.closePort()


# -- Bus Watchdog (address 98; e-Manual semantics, see the emulator's module docstring) -------

GOALS = ("goal_pwm", "goal_current", "goal_velocity", "goal_position")


def _set_moving(bus: Bus, dxl_id: int, mode: int) -> None:
    """Torque on in ``mode`` with a goal that makes the shaft turn; wait until it does."""
    assert bus.write(dxl_id, "operating_mode", mode) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(dxl_id, "torque_enable", 1) == (sdk.COMM_SUCCESS, 0)
    goal = {0: ("goal_current", 200), 1: ("goal_velocity", 200), 3: ("goal_position", 4000),
            16: ("goal_pwm", 400)}[mode]
    if mode == 3:
        assert bus.write(dxl_id, "profile_velocity", 100) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(dxl_id, *goal) == (sdk.COMM_SUCCESS, 0)
    wait_for(lambda: abs(bus.emu.register(dxl_id, "present_velocity")) > 20)


@pytest.mark.parametrize("mode", [1, 3, 0, 16], ids=["velocity", "position", "current", "pwm"])
def test_bus_watchdog_expiry_stops_the_servo_in_every_mode(bus: Bus, mode: int) -> None:
    _set_moving(bus, 1, mode)
    goals_before = [bus.read(1, name)[0] for name in GOALS]
    since = time.monotonic()
    assert bus.write(1, "bus_watchdog", 2) == (sdk.COMM_SUCCESS, 0)  # 40 ms
    # Silence on the bus: reading the emulator in-process sends no packet.
    trip = bus.emu.wait_watchdog_stopped([1], timeout_s=5.0, since_s=since)[1]
    assert trip.timeout_s == pytest.approx(0.04)
    assert trip.expired_s == pytest.approx(trip.last_instruction_s + 0.04, abs=1e-9)
    assert trip.speed_at_expiry_rad_s > 0.3  # it was turning when the watchdog expired
    assert trip.stopped_s is not None and trip.stopped_s >= trip.expired_s
    assert trip.stopped_position_rad is not None
    assert bus.read(1, "bus_watchdog") == (-1, sdk.COMM_SUCCESS, 0)
    assert bus.read(1, "present_velocity")[0] == 0
    assert bus.read(1, "torque_enable")[0] == 1  # stopped and holding, not limp
    # The goals keep their values; they are read-only now.
    assert [bus.read(1, name)[0] for name in GOALS] == goals_before
    assert [t.servo_id for t in bus.emu.watchdog_trips(since)] == [1]


def test_tripped_goals_answer_range_error_until_cleared_with_zero(bus: Bus) -> None:
    _set_moving(bus, 1, 1)
    since = time.monotonic()
    assert bus.write(1, "bus_watchdog", 1) == (sdk.COMM_SUCCESS, 0)  # 20 ms
    bus.emu.wait_watchdog_stopped([1], timeout_s=5.0, since_s=since)
    for name in GOALS:
        before = bus.read(1, name)[0]
        assert bus.write(1, name, 10)[1] == ErrorNumber.DATA_RANGE, name
        assert bus.read(1, name)[0] == before, name
    # A Sync Write has no reply to carry the error: the value simply stays.
    writer = sdk.GroupSyncWrite(bus.port, bus.ph, ADDR["goal_velocity"], 4)
    assert writer.addParam(1, list((77).to_bytes(4, "little")))
    assert writer.txPacket() == sdk.COMM_SUCCESS
    assert bus.read(1, "goal_velocity")[0] == 200
    # Only 0 clears it (-1 is out of range; re-arming needs the clear first).
    assert bus.write(1, "bus_watchdog", 5)[1] == ErrorNumber.DATA_RANGE
    assert bus.write(1, "bus_watchdog", -1)[1] == ErrorNumber.DATA_RANGE
    assert bus.read(1, "bus_watchdog")[0] == -1
    assert bus.write(1, "bus_watchdog", 0) == (sdk.COMM_SUCCESS, 0)
    assert bus.read(1, "bus_watchdog")[0] == 0
    # Cleared, the servo still holds still although Goal Velocity says 200: it only moves on
    # a new goal. Servo 2, given the same goal now, is the clock: once it has turned a while,
    # servo 1 has had as long to start.
    held = bus.emu.positions()[1]
    _set_moving(bus, 2, 1)
    assert bus.emu.positions()[1] == pytest.approx(held, abs=1e-3)
    assert bus.write(1, "goal_velocity", 150) == (sdk.COMM_SUCCESS, 0)
    wait_for(lambda: bus.emu.register(1, "present_velocity") > 100)


def test_bus_watchdog_rearms_after_the_clear(bus: Bus) -> None:
    _set_moving(bus, 1, 1)
    since = time.monotonic()
    assert bus.write(1, "bus_watchdog", 1) == (sdk.COMM_SUCCESS, 0)
    first = bus.emu.wait_watchdog_stopped([1], timeout_s=5.0, since_s=since)[1]
    assert bus.write(1, "bus_watchdog", 0) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(1, "goal_velocity", -150) == (sdk.COMM_SUCCESS, 0)
    wait_for(lambda: bus.emu.register(1, "present_velocity") < -100)
    assert bus.write(1, "bus_watchdog", 3) == (sdk.COMM_SUCCESS, 0)  # 60 ms
    second = bus.emu.wait_watchdog_stopped([1], timeout_s=5.0, since_s=first.stopped_s or 0.0)[1]
    assert second.expired_s > first.expired_s and second.timeout_s == pytest.approx(0.06)
    assert [t.expired_s for t in bus.emu.watchdog_trips(since)] == [first.expired_s,
                                                                   second.expired_s]


def test_bus_watchdog_watches_only_with_torque_on(bus: Bus) -> None:
    # Servo 2 armed with its torque off; servo 1, armed after it and turning, is the clock:
    # once servo 1 has tripped, servo 2 has been silent for longer.
    assert bus.write(2, "bus_watchdog", 1) == (sdk.COMM_SUCCESS, 0)
    _set_moving(bus, 1, 1)
    since = time.monotonic()
    assert bus.write(1, "bus_watchdog", 1) == (sdk.COMM_SUCCESS, 0)
    bus.emu.wait_watchdog_stopped([1], timeout_s=5.0, since_s=since)
    assert bus.emu.register(2, "bus_watchdog") == 1
    assert [t.servo_id for t in bus.emu.watchdog_trips()] == [1]


def test_which_packets_feed_the_bus_watchdog(bus: Bus) -> None:
    emu = bus.emu
    assert bus.ph.ping(bus.port, 1)[1] == sdk.COMM_SUCCESS
    heard = emu.last_instruction_s(1)
    # Unicast to another servo: not for servo 1.
    assert bus.ph.ping(bus.port, 2)[1] == sdk.COMM_SUCCESS
    assert emu.last_instruction_s(1) == heard
    # A bad CRC addressed to servo 1: not an instruction it accepts.
    packet = bytearray(encode_instruction(1, Instruction.PING))
    packet[-1] ^= 0xFF
    bus.port.clearPort()
    bus.port.writePort(list(packet))
    bus.port.setPacketTimeout(11)
    status, result = bus.ph.rxPacket(bus.port, False)  # the servo's "CRC error" status
    assert result == sdk.COMM_SUCCESS and status[8] == ErrorNumber.CRC
    assert emu.last_instruction_s(1) == heard
    # Broadcast: a Sync Read that asks servo 2 only still reaches servo 1.
    reader = sdk.GroupSyncRead(bus.port, bus.ph, ADDR["present_position"], 4)
    assert reader.addParam(2)
    assert reader.txRxPacket() == sdk.COMM_SUCCESS
    after_sync = emu.last_instruction_s(1)
    assert after_sync > heard
    # And to servo 1 itself.
    assert bus.ph.ping(bus.port, 1)[1] == sdk.COMM_SUCCESS
    assert emu.last_instruction_s(1) > after_sync


def test_reboot_resets_the_bus_watchdog(bus: Bus) -> None:
    _set_moving(bus, 1, 1)
    since = time.monotonic()
    assert bus.write(1, "bus_watchdog", 1) == (sdk.COMM_SUCCESS, 0)
    bus.emu.wait_watchdog_stopped([1], timeout_s=5.0, since_s=since)
    assert bus.ph.reboot(bus.port, 1)[0] == sdk.COMM_SUCCESS
    wait_for(lambda: bus.ph.ping(bus.port, 1)[1] == sdk.COMM_SUCCESS)
    assert bus.read(1, "bus_watchdog") == (0, sdk.COMM_SUCCESS, 0)
    assert bus.read(1, "torque_enable")[0] == 0
    assert bus.write(1, "goal_velocity", 10) == (sdk.COMM_SUCCESS, 0)
    assert len(bus.emu.watchdog_trips(since)) == 1  # the record outlives the reboot


def test_firmware_before_v38_has_no_bus_watchdog(bus: Bus) -> None:
    bus.emu.set_firmware_version(2, 37)
    assert bus.read(2, "firmware_version")[0] == 37
    assert bus.write(2, "bus_watchdog", 1)[1] == ErrorNumber.ACCESS
    assert bus.read(2, "bus_watchdog")[0] == 0
    # Servo 2 keeps turning on its last command while servo 1 (v48) stops on its watchdog.
    _set_moving(bus, 2, 1)
    _set_moving(bus, 1, 1)
    since = time.monotonic()
    assert bus.write(1, "bus_watchdog", 1) == (sdk.COMM_SUCCESS, 0)
    bus.emu.wait_watchdog_stopped([1], timeout_s=5.0, since_s=since)
    assert bus.emu.register(2, "present_velocity") > 100
    assert [t.servo_id for t in bus.emu.watchdog_trips()] == [1]


def test_fail_next_torque_on_latches_the_error_after_acknowledging(bus: Bus) -> None:
    bus.emu.fail_next_torque_on(3, HardwareError.ELECTRICAL_SHOCK)
    result, error = bus.write(3, "torque_enable", 1)
    assert result == sdk.COMM_SUCCESS and error == ALERT_BIT  # accepted, then the fault
    assert bus.read(3, "torque_enable")[0] == 0
    assert bus.read(3, "hardware_error_status")[0] == HardwareError.ELECTRICAL_SHOCK


def _stderr_line(proc: subprocess.Popen[bytes], prefix: str, timeout_s: float = 10.0) -> str:
    """The first line of ``proc``'s stderr starting with ``prefix``, waiting at most
    ``timeout_s`` (read unbuffered from the descriptor, so select() sees every byte)."""
    assert proc.stderr is not None
    fd = proc.stderr.fileno()
    deadline = time.monotonic() + timeout_s
    pending = b""
    while True:
        *lines, pending = pending.split(b"\n")
        for line in lines:
            if line.startswith(prefix.encode()):
                return line.decode()
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            pytest.fail(f"no stderr line starting with {prefix!r} within {timeout_s} s")
        ready, _, _ = select.select([fd], [], [], remaining)
        if ready:
            chunk = os.read(fd, 4096)
            if not chunk:
                pytest.fail(f"the process exited without a line starting with {prefix!r}")
            pending += chunk


def test_cli_reports_watchdog_trips_as_json_lines() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw.drivers.dynamixel.emulator", "--ids", "1",
         "--baud", "4000000"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        assert proc.stdout is not None
        device = proc.stdout.readline().decode().strip()
        port = sdk.PortHandler(device)
        ph = sdk.PacketHandler(2.0)
        try:
            assert port.openPort() and port.setBaudRate(4_000_000)
            assert ph.write1ByteTxRx(port, 1, ADDR["operating_mode"], 1) == (sdk.COMM_SUCCESS, 0)
            assert ph.write1ByteTxRx(port, 1, ADDR["torque_enable"], 1) == (sdk.COMM_SUCCESS, 0)
            assert ph.write4ByteTxRx(port, 1, ADDR["goal_velocity"], 100) == (sdk.COMM_SUCCESS, 0)
            assert ph.write1ByteTxRx(port, 1, ADDR["bus_watchdog"], 1) == (sdk.COMM_SUCCESS, 0)
        finally:
            port.closePort()
        record = json.loads(_stderr_line(proc, "watchdog ")[len("watchdog "):])
        assert record["servo_id"] == 1 and record["timeout_s"] == pytest.approx(0.02)
        assert record["stopped_s"] >= record["expired_s"] > record["last_instruction_s"]
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=10)


def test_current_and_current_based_position_modes(bus: Bus) -> None:
    # Current mode: the present current is the goal (the torque constant maps both ways).
    assert bus.write(1, "operating_mode", 0) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(1, "torque_enable", 1) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(1, "goal_current", -30) == (sdk.COMM_SUCCESS, 0)
    assert abs(bus.read(1, "present_current")[0] + 30) <= 1
    wait_for(lambda: bus.read(1, "present_velocity")[0] < -5)
    # Current-based position: moving toward the goal with the current capped by Goal Current.
    assert bus.write(3, "operating_mode", 5) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(3, "goal_current", 20) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(3, "torque_enable", 1) == (sdk.COMM_SUCCESS, 0)
    assert bus.write(3, "goal_position", 2048 + 4096) == (sdk.COMM_SUCCESS, 0)  # multi-turn
    wait_for(lambda: bus.read(3, "present_velocity")[0] > 5)
    assert 0 < bus.read(3, "present_current")[0] <= 20


def _fifo_permitted() -> bool:
    probe = "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))"
    return subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0


@pytest.mark.parametrize("priority", [None, "0"])
def test_the_command_line_emulator_answers_at_a_real_time_priority(
    priority: str | None,
) -> None:
    """``jtc-hw emulate dynamixel`` runs its threads at SCHED_FIFO 1 where permitted, as
    ``jtc-hw emulate can`` does (``--priority 0``: normal scheduling): normally scheduled on a
    busy machine it missed a daemon's 20 ms ping at configure (issue 22)."""
    if priority is None and not _fifo_permitted():
        pytest.skip("this user may not have a SCHED_FIFO priority")
    argv = [sys.executable, "-m", "jtc_hw", "emulate", "dynamixel", "--ids", "1"]
    proc = subprocess.Popen(argv + ([] if priority is None else ["--priority", priority]),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip()  # serving: its threads have started
        # The main thread, and the serving thread it started once set. numpy's BLAS may have
        # started idle threads at import, before the priority was set: they serve nothing and
        # stay normally scheduled. (Not told apart by thread id: ids wrap around, a serving
        # thread's was once below the main thread's on a busy machine.)
        policies = {int(t): os.sched_getscheduler(int(t))
                    for t in os.listdir(f"/proc/{proc.pid}/task")}
        main = policies.pop(proc.pid)
        assert policies, "no thread besides the main one"
        if priority == "0":
            assert {main, *policies.values()} == {os.SCHED_OTHER}
        else:
            assert main == os.SCHED_FIFO and os.SCHED_FIFO in policies.values(), policies
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=10)
    assert proc.returncode == 0


def test_a_priority_out_of_range_is_one_line() -> None:
    done = subprocess.run([sys.executable, "-m", "jtc_hw", "emulate", "dynamixel",
                           "--priority", "100"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--priority must be 0..99, got 100" in done.stderr
