"""Issue 26's "done when": Feetech's SDK, used directly as an SO-101 owner would, works against
the emulator started from its command line.

This file imports the SDK (``scservo_sdk``, PyPI ``feetech-servo-sdk``) and nothing of jtc_hw:
the emulator runs as ``python -m jtc_hw.drivers.feetech.emulator`` in a subprocess and is
reached only through the pty it prints. The SDK is used as LeRobot's ``FeetechMotorsBus`` uses
it (``src/lerobot/motors/feetech/feetech.py``): ``PacketHandler(0)`` for STS servos, its
``GroupSyncRead`` / ``GroupSyncWrite``, and its patch of the port's packet timeout (the wire
time plus a fixed allowance instead of the PyPI SDK's 34 ms; see :data:`ALLOWANCE_MS`). Waits
are on conditions read over the bus, with a deadline, never fixed sleeps.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

scs = pytest.importorskip("scservo_sdk", reason="feetech-servo-sdk (jtc_hw[feetech]) is missing")

IDS = [1, 2, 3, 4, 5, 6]
STS3215 = 777
ADDR_MODEL_NUMBER = 3
ADDR_TORQUE_ENABLE = 40
ADDR_GOAL_POSITION = 42
ADDR_LOCK = 55
ADDR_PRESENT_POSITION = 56  # 2 bytes, then Present Speed (58, 2 bytes)


#: The fixed part of the reply timeout, ms: LeRobot's is 50. The SDK checks its deadline after
#: an empty read and before the next one, so a host thread descheduled for longer than that
#: between the two reports a timeout although the reply has arrived; this test's process is
#: normally scheduled beside busy ones (a 50 ms allowance failed once in ten runs so, the
#: emulator being at SCHED_FIFO). Nothing here waits that long unless something is wrong.
ALLOWANCE_MS = 1000.0


def lerobot_packet_timeout(self: Any, packet_length: int) -> None:
    """LeRobot's replacement of ``PortHandler.setPacketTimeout`` (its formula, with
    :data:`ALLOWANCE_MS` for its 50 ms)."""
    self.packet_start_time = self.getCurrentTime()
    self.packet_timeout = self.tx_time_per_byte * (packet_length + 3) + ALLOWANCE_MS


@pytest.fixture
def emulator(tmp_path: Path) -> Iterator[str]:
    """The emulator's command line in a subprocess; yields the link it serves."""
    link = str(tmp_path / "jtc-hw-fee")
    argv = [sys.executable, "-m", "jtc_hw.drivers.feetech.emulator", "--ids", "1-6",
            "--model", "STS3215", "--link", link]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, text=True) as proc:
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline().strip() == link  # printed once it serves
            yield link
            proc.terminate()  # SIGTERM: a clean stop, exit status 0
            assert proc.wait(timeout=10) == 0
        finally:
            if proc.returncode is None:
                proc.kill()


@pytest.fixture
def port(emulator: str) -> Iterator[Any]:
    handler = scs.PortHandler(emulator)
    handler.setPacketTimeout = lerobot_packet_timeout.__get__(handler, scs.PortHandler)
    assert handler.openPort()
    assert handler.setBaudRate(1_000_000)
    try:
        yield handler
    finally:
        handler.closePort()


def sync_read_positions(port: Any, ph: Any) -> dict[int, tuple[int, int]]:
    """id -> (Present Position, Present Speed) of all six, in one Sync Read."""
    reader = scs.GroupSyncRead(port, ph, ADDR_PRESENT_POSITION, 4)
    for servo_id in IDS:
        assert reader.addParam(servo_id)
    result = reader.txRxPacket()
    assert result == scs.COMM_SUCCESS, ph.getTxRxResult(result)
    out = {}
    for servo_id in IDS:
        assert reader.isAvailable(servo_id, ADDR_PRESENT_POSITION, 4)
        position = reader.getData(servo_id, ADDR_PRESENT_POSITION, 2)
        speed = reader.getData(servo_id, ADDR_PRESENT_POSITION + 2, 2)
        # Sign-magnitude, bit 15: the SDK's own helper decodes it.
        out[servo_id] = (scs.SCS_TOHOST(position, 15), scs.SCS_TOHOST(speed, 15))
    return out


def test_the_sdk_drives_six_sts3215_on_the_emulator(port: Any) -> None:
    ph = scs.PacketHandler(0)  # STS/SMS: little-endian words

    for servo_id in IDS:
        model, result, error = ph.ping(port, servo_id)
        assert (model, result, error) == (STS3215, scs.COMM_SUCCESS, 0), servo_id
    model, result, error = ph.read2ByteTxRx(port, 1, ADDR_MODEL_NUMBER)
    assert (model, result, error) == (STS3215, scs.COMM_SUCCESS, 0)
    # An id nobody has: no answer (after the allowance).
    assert ph.ping(port, 7)[1] == scs.COMM_RX_TIMEOUT

    start = sync_read_positions(port, ph)
    assert {i: p for i, (p, _) in start.items()} == {i: 2048 for i in IDS}  # mid-range
    assert all(speed == 0 for _, speed in start.values())

    for servo_id in IDS:  # as LeRobot's enable_torque: Torque_Enable 1, then Lock 1
        assert ph.write1ByteTxRx(port, servo_id, ADDR_TORQUE_ENABLE, 1) == (scs.COMM_SUCCESS, 0)
        assert ph.write1ByteTxRx(port, servo_id, ADDR_LOCK, 1) == (scs.COMM_SUCCESS, 0)

    goals = {servo_id: 2048 + (servo_id - 3) * 150 for servo_id in IDS}  # 1748 .. 2498
    writer = scs.GroupSyncWrite(port, ph, ADDR_GOAL_POSITION, 2)
    for servo_id, goal in goals.items():
        assert writer.addParam(servo_id, [scs.SCS_LOBYTE(goal), scs.SCS_HIBYTE(goal)])
    assert writer.txPacket() == scs.COMM_SUCCESS

    # The positions move toward the goals: on the way, every servo is somewhere between its
    # start and its goal, turning the goal's way while it is still far; then they arrive.
    deadline = time.monotonic() + 10.0
    saw_moving = set()
    while True:
        now = sync_read_positions(port, ph)
        for servo_id, (position, speed) in now.items():
            low, high = sorted((2048, goals[servo_id]))
            assert low - 3 <= position <= high + 3, (servo_id, position)
            if speed and abs(goals[servo_id] - position) > 10:
                assert (speed > 0) == (goals[servo_id] > 2048), (servo_id, speed)
                saw_moving.add(servo_id)
        if all(abs(now[i][0] - goals[i]) <= 2 for i in IDS):
            break
        assert time.monotonic() < deadline, f"not at the goals {goals} within 10 s: {now}"
    assert saw_moving, "no servo was seen moving"
    # And they hold there.
    assert all(abs(p - goals[i]) <= 2 for i, (p, _) in sync_read_positions(port, ph).items())

