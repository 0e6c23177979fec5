"""The Feetech emulator over its pty: instructions, SCS's silences, faults, the command line.

The SDK runs in this process against an in-process emulator (its thread answers while the SDK
spins on the port: a short GIL switch interval lets it); its packet timeout is raised from 34
to 502 ms (``LATENCY_TIMER`` 250): the emulator's thread, normally scheduled in the test's
process, can be descheduled for tens of milliseconds beside busy processes.
Where the absence of a reply is the point, a later request's reply proves it: the emulator
answers in order, so what comes back first would have been the unwanted reply.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from jtc_hw.drivers.feetech import codec as fc
from jtc_hw.drivers.feetech import control_table as ct
from jtc_hw.drivers.feetech.emulator import FeetechEmulator
from jtc_hw.drivers.pty_emulator import wire_time_s

scs = pytest.importorskip("scservo_sdk", reason="feetech-servo-sdk (jtc_hw[feetech]) is missing")
from scservo_sdk import port_handler, scservo_def  # noqa: E402

STS = ct.STS_SMS
ADDR = {name: reg.address for name, reg in STS.registers.items()}


@pytest.fixture(autouse=True)
def sdk_timing(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setattr(port_handler, "LATENCY_TIMER", 250)
    # PacketHandler(1) sets the SDK's module-global byte order: back to 0 afterwards.
    monkeypatch.setattr(scservo_def, "SCS_END", 0)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(0.0005)
    yield
    sys.setswitchinterval(interval)


class Bus:
    """The SDK on an emulator's pty."""

    def __init__(self, emulator: FeetechEmulator, end: int = 0) -> None:
        self.emu = emulator
        self.port = scs.PortHandler(emulator.device_path)
        self.ph = scs.PacketHandler(end)
        assert self.port.openPort() and self.port.setBaudRate(1_000_000)

    def raw(self, packet: bytes, expect: int) -> bytes:
        """Send ``packet`` as bytes and read ``expect`` bytes back (deadline 2 s)."""
        self.port.ser.reset_input_buffer()
        self.port.ser.write(packet)
        data = b""
        deadline = time.monotonic() + 2.0
        while len(data) < expect:
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"only {data.hex()} of {expect} bytes"
            select.select([self.port.ser.fileno()], [], [], remaining)
            data += self.port.ser.read(expect - len(data))
        return data


@pytest.fixture
def emu() -> Iterator[FeetechEmulator]:
    with FeetechEmulator([1, 2, 3], "STS3215", return_delay_us=0) as emulator:
        yield emulator


@pytest.fixture
def bus(emu: FeetechEmulator) -> Iterator[Bus]:
    b = Bus(emu)
    yield b
    b.port.closePort()


def test_read_write_and_reg_write_action(bus: Bus) -> None:
    assert bus.ph.read1ByteTxRx(bus.port, 2, ADDR["id"]) == (2, scs.COMM_SUCCESS, 0)
    assert bus.ph.write2ByteTxRx(bus.port, 2, ADDR["goal_velocity"], 500) == (
        scs.COMM_SUCCESS, 0)
    assert bus.emu.register(2, "goal_velocity") == 500
    # REG_WRITE is held until ACTION (broadcast: nobody answers it).
    assert bus.ph.regWriteTxRx(bus.port, 2, ADDR["acceleration"], 1, [20]) == (
        scs.COMM_SUCCESS, 0)
    assert bus.emu.register(2, "acceleration") == 0
    assert bus.ph.action(bus.port, fc.BROADCAST_ID) == scs.COMM_SUCCESS
    assert bus.ph.read1ByteTxRx(bus.port, 2, ADDR["acceleration"]) == (20, scs.COMM_SUCCESS, 0)


def test_broadcast_ping_answers_in_id_order_on_sts(bus: Bus) -> None:
    replies = bus.raw(fc.encode_ping(fc.BROADCAST_ID), 3 * 6)
    assert replies == b"".join(fc.encode_status(i) for i in (1, 2, 3))


def test_response_status_level_0_answers_only_reads_and_pings(bus: Bus) -> None:
    assert bus.ph.write1ByteTxRx(bus.port, 1, ADDR["response_status_level"], 0) == (
        scs.COMM_SUCCESS, 0)
    # The write is obeyed, unanswered: the ping's status is the first thing that comes back.
    reply = bus.raw(fc.encode_write(1, ADDR["acceleration"], b"\x05") + fc.encode_ping(1), 6)
    assert reply == fc.encode_status(1)
    assert bus.emu.register(1, "acceleration") == 5


def test_scs_has_no_sync_read_and_no_broadcast_ping() -> None:
    with FeetechEmulator([1, 2], "SCS0009", return_delay_us=0) as emulator:
        b = Bus(emulator, end=1)
        try:
            assert b.ph.ping(b.port, 1) == (1284, scs.COMM_SUCCESS, 0)  # big-endian words
            silent = fc.encode_sync_read(56, 2, [1, 2]) + fc.encode_ping(fc.BROADCAST_ID)
            # Neither is answered: the first bytes back are the unicast ping's.
            assert b.raw(silent + fc.encode_ping(2), 6) == fc.encode_status(2)
            # The SDK reads SCS servos one at a time, big-endian.
            value, result, _ = b.ph.read2ByteTxRx(b.port, 2, 56)
            assert (value, result) == (512, scs.COMM_SUCCESS)
            # Sync Write they know (the SDK packs the words big-endian with end 1).
            assert b.ph.write1ByteTxRx(b.port, 2, 40, 1) == (scs.COMM_SUCCESS, 0)
            writer = scs.GroupSyncWrite(b.port, b.ph, 42, 2)
            writer.addParam(2, [scs.SCS_LOBYTE(600), scs.SCS_HIBYTE(600)])
            assert writer.txPacket() == scs.COMM_SUCCESS
            deadline = time.monotonic() + 5.0
            while b.ph.read2ByteTxRx(b.port, 2, 56)[0] != 600:
                assert time.monotonic() < deadline, "the SCS servo did not reach 600"
            assert emulator.register(2, "goal_position") == 600
        finally:
            b.port.closePort()
        assert emulator.stats()["packets_served"] >= 4


def test_a_silent_servo_times_out_and_fails_the_sync_read(bus: Bus) -> None:
    bus.emu.set_silent(2, True)
    assert bus.ph.ping(bus.port, 2)[1] == scs.COMM_RX_TIMEOUT
    reader = scs.GroupSyncRead(bus.port, bus.ph, ADDR["present_position"], 2)
    for i in (1, 2, 3):
        reader.addParam(i)
    assert reader.txRxPacket() == scs.COMM_RX_TIMEOUT
    bus.emu.set_silent(2, False)
    assert bus.ph.ping(bus.port, 2)[1] == scs.COMM_SUCCESS


def test_checksum_errors_both_ways(bus: Bus) -> None:
    bus.emu.corrupt_checksum(1, 1)
    assert bus.ph.ping(bus.port, 1)[1] == scs.COMM_RX_CORRUPT
    assert bus.ph.ping(bus.port, 1)[:2] == (777, scs.COMM_SUCCESS)  # only the next one
    # A request with a bad checksum is not answered (no status bit could say so) and counted.
    bad = bytearray(fc.encode_ping(3))
    bad[-1] ^= 0xFF
    assert bus.raw(bytes(bad) + fc.encode_ping(3), 6) == fc.encode_status(3)
    assert bus.emu.stats()["checksum_errors"] == 1


def test_overload_through_the_bus(bus: Bus) -> None:
    assert bus.ph.write1ByteTxRx(bus.port, 3, ADDR["torque_enable"], 1) == (scs.COMM_SUCCESS, 0)
    bus.emu.block(3)
    since = time.monotonic()
    assert bus.ph.write2ByteTxRx(bus.port, 3, ADDR["goal_position"], 3000)[0] == (
        scs.COMM_SUCCESS)
    event = bus.emu.wait_protection(3, fc.StatusError.OVERLOAD, timeout_s=10.0, since_s=since)
    assert event.torque_off and event.servo_id == 3
    # Protection Time (2 s) on the servo's own clock, from when the torque rose (soon after
    # the goal's write arrived: a busy host may deliver it late).
    assert 2.0 <= event.at_s - since < 3.0
    # The status byte of every reply says so, and the torque is off.
    value, result, error = bus.ph.read1ByteTxRx(bus.port, 3, ADDR["torque_enable"])
    assert (value, result, error) == (0, scs.COMM_SUCCESS, fc.StatusError.OVERLOAD)
    assert bus.ph.read1ByteTxRx(bus.port, 3, ADDR["status"])[0] == fc.StatusError.OVERLOAD
    assert "Overload" in bus.ph.getRxPacketError(error)


def test_overheating_unloads_and_reports(bus: Bus) -> None:
    assert bus.ph.write1ByteTxRx(bus.port, 1, ADDR["torque_enable"], 1) == (scs.COMM_SUCCESS, 0)
    bus.emu.set_temperature(1, 85.0)
    [event] = bus.emu.protection_events()
    assert (event.servo_id, event.error, event.torque_off) == (1, fc.StatusError.OVERHEAT, True)
    value, result, error = bus.ph.read1ByteTxRx(bus.port, 1, ADDR["present_temperature"])
    assert (value, result, error) == (85, scs.COMM_SUCCESS, fc.StatusError.OVERHEAT)
    assert bus.emu.register(1, "torque_enable") == 0
    bus.emu.set_supply_voltage(2, 3.0)
    assert bus.ph.ping(bus.port, 2)[2] == fc.StatusError.VOLTAGE
    bus.emu.set_angle_fault(2, True)
    assert bus.ph.ping(bus.port, 2)[2] == fc.StatusError.VOLTAGE | fc.StatusError.ANGLE


def test_power_cycle_keeps_what_the_lock_let_it_store(bus: Bus) -> None:
    lock = ADDR["lock"]
    assert bus.ph.write2ByteTxRx(bus.port, 1, ADDR["max_position_limit"], 3000)[0] == 0
    assert bus.ph.write1ByteTxRx(bus.port, 1, lock, 0)[0] == 0
    assert bus.ph.write2ByteTxRx(bus.port, 1, ADDR["min_position_limit"], 100)[0] == 0
    assert bus.emu.stored_register(1, "min_position_limit") == 100
    assert bus.emu.stored_register(1, "max_position_limit") == 4095  # written while locked
    bus.emu.power_cycle(1)
    assert bus.ph.read2ByteTxRx(bus.port, 1, ADDR["min_position_limit"])[0] == 100
    assert bus.ph.read2ByteTxRx(bus.port, 1, ADDR["max_position_limit"])[0] == 4095
    assert bus.ph.read1ByteTxRx(bus.port, 1, lock)[0] == 1


def test_paced_replies_are_due_after_the_wire_and_the_return_delay() -> None:
    # The schedule, not the wall clock: request 8 bytes, two 8-byte replies at 1 Mbit/s
    # (10 us a byte), each servo's return delay before its reply.
    emulator = FeetechEmulator([1, 2], pace=True)
    due = emulator._schedule(10.0, 8, 1_000_000, [(500e-6, b"a" * 8, 1_000_000),
                                                  (500e-6, b"b" * 8, 1_000_000)])
    one = wire_time_s(8, 1_000_000)
    assert one == pytest.approx(80e-6)
    assert [t for t, _ in due] == pytest.approx([10.0 + one + 500e-6 + one,
                                                 10.0 + 3 * one + 1000e-6])
    # The next request waits for the bus if it arrives before the last reply ended.
    again = emulator._schedule(10.0, 8, 1_000_000, [(0.0, b"c" * 8, 1_000_000)])
    assert again[0][0] == pytest.approx(due[-1][0] + 2 * one)


def test_bad_options_are_refused() -> None:
    with pytest.raises(ValueError, match="2000000"):
        FeetechEmulator([1], baud=2_000_000)
    with pytest.raises(ValueError, match="0..253"):
        FeetechEmulator([254])
    with pytest.raises(KeyError, match="STS3215"):
        FeetechEmulator([1], "XM430")


def test_jtc_hw_emulate_feetech_serves_until_sigterm(tmp_path: Path) -> None:
    link = str(tmp_path / "fee")
    argv = [sys.executable, "-m", "jtc_hw", "emulate", "feetech", "--ids", "1-2", "--model",
            "SCS0009", "--link", link, "--return-delay-us", "0", "--stats", "exit"]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True) as proc:
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline().strip() == link and os.path.islink(link)
            port = scs.PortHandler(link)
            assert port.openPort() and port.setBaudRate(1_000_000)
            pinged = scs.PacketHandler(1).ping(port, 2)
            port.closePort()
            assert pinged[:2] == (1284, scs.COMM_SUCCESS)
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=10)
        except BaseException:
            proc.kill()
            raise
    assert proc.returncode == 0
    assert "serving 2 x SCS0009 (ids 1-2) at 1000000 bit/s paced" in err
    assert "packets_served=2" in err
    assert not os.path.exists(link)  # removed on exit


def test_the_command_line_refuses_a_bad_baud_in_one_line() -> None:
    done = subprocess.run([sys.executable, "-m", "jtc_hw.drivers.feetech.emulator", "--baud",
                           "9600", "--priority", "0"], capture_output=True, text=True,
                          timeout=30)
    assert done.returncode == 2
    assert done.stderr.strip().startswith("jtc-hw emulate feetech: Feetech servos do not "
                                          "support 9600 bit/s")

