#!/usr/bin/env python3
"""Feetech bus rate: our driver's read + write cycle beside a hand-written SDK loop (issue 26).

Six STS3215 (LeRobot's SO-101 follower) at 1 Mbit/s, the servos' fastest setting, served by
``jtc-hw emulate feetech`` in its own process: a pty paced at the baud rate (each reply held
back until the request's and its own bytes would have crossed the wire), so the emulator does
not share the client's interpreter lock, as a real bus shares no CPU with the host. Two rows,
each on a fresh emulator, measured one after the other in one sitting:

``jtc_hw``
    The real ``FeetechHardware`` (real ``scservo_sdk``, real pty): ``read`` (one Sync Read of
    Present Position / Speed / Load, 56..61) then ``write`` (one Sync Write of Goal Position,
    42), back to back for ``duration_s``. Health reads are put off (``health_period_s`` 60, at
    most one in a run, in the warm-up): the SDK loop makes none, and the row is about the
    cycle's two transactions.
``sdk loop``
    What a LeRobot user runs today (``FeetechMotorsBus``): ``scservo_sdk`` alone, a
    ``GroupSyncRead`` of the same 6 bytes (parameters cleared and added, ``txRxPacket``, three
    ``getData`` per servo, sign-magnitude decoded) then a ``GroupSyncWrite`` of the same goals
    (cleared, added, ``txPacket``), with the port's packet timeout widened as LeRobot's patch
    widens it (wire time + 3 bytes + 50 ms). Written for this bench from the SDK's API, not
    LeRobot's code: no calibration or normalisation, which LeRobot adds on top.

Columns as ``bench/bus_rate.py``'s: ``wire_us`` the cycle's bytes at 10 bits per byte (the Sync
Read request, six status packets, the Sync Write; :func:`wire_us`), ``delay_us`` the servos'
Return Delay Times (set to 0 by both clients, as LeRobot's ``configure_motors`` does), ``ratio``
(cycle - delays) / wire; ``driver_cpu_us`` the cycling thread's CPU per cycle. Target (the
issue): our row's ratio <= 1.3.

``--breakdown`` (bench/bus_breakdown.py): the ``sdk`` part is the time inside scservo_sdk's
calls. Our driver's cycle makes none (the Sync Read request comes from our codec and the
replies go through our decoder, the port's reads and writes are our ``DescriptorIO``), so its
``sdk`` is 0 by construction; the SDK loop's is its group objects' calls.

Usage: ``python bench/bus_rate.py --bus feetech [--duration S] [--breakdown] [--neighbour
[on|both]] [--priority N] [--json]``; this module has no command line of its own.
"""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import scservo_sdk as scs  # noqa: E402

from jtc_hw.controller.joints import JointCommand  # noqa: E402
from jtc_hw.drivers.feetech.codec import (  # noqa: E402
    decode_sign_magnitude,
    encode_status,
    encode_sync_read,
    encode_sync_write,
)
from jtc_hw.drivers.feetech.hardware import FeetechHardware  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bus_breakdown import Breakdown, neighbour  # noqa: E402

BAUD = 1_000_000
MOTORS = 6
IDS = tuple(range(1, MOTORS + 1))
MODEL = "STS3215"
TARGET_RATIO = 1.3
RETURN_DELAY_US = 0  # what both clients write to the servos
PRESENT_ADDRESS, PRESENT_SIZE = 56, 6  # Present Position, Speed, Load
GOAL_ADDRESS, GOAL_SIZE = 42, 2  # Goal Position
RETURN_DELAY_ADDRESS, TORQUE_ADDRESS = 7, 40
WARMUP_CYCLES = 20
SDK_GROUP_CALLS = ("clearParam", "addParam", "txRxPacket", "getData", "txPacket")
"""The scservo_sdk group methods the SDK loop calls each cycle (its SDK boundary)."""
DRIVER_SDK_CALLS = ("txRxPacket", "readTxRx", "writeTxRx")
"""The scservo_sdk packet handler's methods our bus module calls (none in the usual cycle)."""


def wire_us() -> float:
    """Wire time of one cycle of MOTORS servos, us (return delays excluded): the Sync Read
    request, one status packet of PRESENT_SIZE bytes per servo, the Sync Write of Goal Position,
    sized by our codec, at 10 bits per byte (8N1)."""
    request = len(encode_sync_read(PRESENT_ADDRESS, PRESENT_SIZE, IDS))
    replies = sum(len(encode_status(i, 0, bytes(PRESENT_SIZE))) for i in IDS)
    write = len(encode_sync_write(GOAL_ADDRESS, GOAL_SIZE, {i: bytes(GOAL_SIZE) for i in IDS}))
    return (request + replies + write) * 10 / BAUD * 1e6


@contextmanager
def emulator_process(priority: int) -> Iterator[str]:
    """``jtc-hw emulate feetech`` (paced, its default) for MOTORS STS3215 in a subprocess;
    yields the device path. ``priority``: its SCHED_FIFO priority (0: the command's own
    default, the lowest real-time priority where permitted)."""
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
        argv = [sys.executable, "-m", "jtc_hw", "emulate", "feetech", "--ids", f"1-{MOTORS}",
                "--model", MODEL, "--baud", str(BAUD), "--link", os.path.join(tmp, "fee"),
                "--stats", "exit"]
        if priority:
            argv += ["--priority", str(priority)]
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                env=env, text=True)
        try:
            assert proc.stdout is not None
            path = proc.stdout.readline().strip()  # printed once the pty is served
            if not path:
                raise RuntimeError(f"the Feetech emulator did not start (exit {proc.wait()}); "
                                   f"run {' '.join(argv[1:])} by hand to see why")
            yield path
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _run(cycle: Callable[[], None], duration_s: float,
         breakdown: Breakdown | None) -> dict[str, float]:
    """Warm up, then run ``cycle`` back to back for ``duration_s``: mean and worst cycle, CPU."""
    for _ in range(WARMUP_CYCLES):
        cycle()
    clock = time.perf_counter_ns
    gc.collect()
    gc.disable()
    try:
        cycles = worst = 0
        cpu0 = time.thread_time_ns()
        start = now = clock()
        end = start + int(duration_s * 1e9)
        while now < end:
            if breakdown is not None:
                breakdown.begin()
            t0 = clock()
            cycle()
            now = clock()
            if breakdown is not None:
                breakdown.end()
            worst = max(worst, now - t0)
            cycles += 1
        cpu = time.thread_time_ns() - cpu0
    finally:
        gc.enable()
    return {"cycles": cycles, "cycle_us": (now - start) / cycles / 1e3,
            "driver_cpu_us": cpu / cycles / 1e3, "max_cycle_us": worst / 1e3}


def measure_driver(device: str, duration_s: float,
                   breakdown: Breakdown | None) -> dict[str, float]:
    """Our ``FeetechHardware``: read + write, holding where the servos stand."""
    joints = [f"joint{i}" for i in IDS]
    hw = FeetechHardware("bench", joints, ["position"], ["position", "velocity"], {
        "port": device, "baud_rate": BAUD, "ids": list(IDS), "model": [MODEL] * MOTORS,
        "return_delay_time_us": RETURN_DELAY_US,
        # Wide: this bench is not real-time, a stall on a busy machine is not a missing servo.
        "timeout_ms": 50.0, "health_period_s": 60.0,
    })
    hw.configure()
    try:
        held = hw.activate(time.monotonic_ns())
        command = JointCommand(positions=held.positions)

        def cycle() -> None:
            hw.read(time.monotonic_ns())
            hw.write(time.monotonic_ns(), command)

        if breakdown is not None:
            assert hw.bus is not None
            breakdown.wrap(hw.bus._handler, *DRIVER_SDK_CALLS)
        return _run(cycle, duration_s, breakdown)
    finally:
        hw.shutdown(time.monotonic_ns())


class _LeRobotTimeoutPort(scs.PortHandler):  # type: ignore[misc]
    """The SDK's port with the packet timeout LeRobot patches in (wire time + 3 bytes + 50 ms,
    instead of the SDK's 34 ms counted before the request has left)."""

    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802 - the SDK's name
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * (packet_length + 3) + 50.0


def _sdk_check(what: str, result: int, error: int = 0) -> None:
    if result != scs.COMM_SUCCESS or error:
        raise RuntimeError(f"sdk loop: {what}: result {result}, error {error}; the emulator "
                           "did not answer as six STS3215 would (a loaded machine?)")


def measure_sdk_loop(device: str, duration_s: float,
                     breakdown: Breakdown | None) -> dict[str, float]:
    """A hand-written ``scservo_sdk`` loop: GroupSyncRead + GroupSyncWrite (module docstring)."""
    port = _LeRobotTimeoutPort(device)
    if not port.openPort() or not port.setBaudRate(BAUD):
        raise RuntimeError(f"sdk loop: cannot open {device} at {BAUD} bit/s")
    try:
        handler = scs.PacketHandler(0)  # STS: little-endian words
        for servo_id in IDS:
            _sdk_check(f"ping {servo_id}", *handler.ping(port, servo_id)[1:])
            _sdk_check(f"return delay of {servo_id}",
                       *handler.write1ByteTxRx(port, servo_id, RETURN_DELAY_ADDRESS, 0))
            _sdk_check(f"torque of {servo_id}",
                       *handler.write1ByteTxRx(port, servo_id, TORQUE_ADDRESS, 1))
        reader = scs.GroupSyncRead(port, handler, PRESENT_ADDRESS, PRESENT_SIZE)
        writer = scs.GroupSyncWrite(port, handler, GOAL_ADDRESS, GOAL_SIZE)
        state: dict[int, tuple[int, int, int]] = {}

        def read() -> None:
            reader.clearParam()
            for servo_id in IDS:
                reader.addParam(servo_id)
            _sdk_check("sync read", reader.txRxPacket())
            for servo_id in IDS:
                state[servo_id] = (
                    decode_sign_magnitude(reader.getData(servo_id, 56, 2), 15),
                    decode_sign_magnitude(reader.getData(servo_id, 58, 2), 15),
                    decode_sign_magnitude(reader.getData(servo_id, 60, 2), 10))

        read()
        goals = {servo_id: state[servo_id][0] for servo_id in IDS}  # hold where they stand

        def cycle() -> None:
            read()
            writer.clearParam()
            for servo_id, goal in goals.items():
                writer.addParam(servo_id, [scs.SCS_LOBYTE(goal), scs.SCS_HIBYTE(goal)])
            _sdk_check("sync write", writer.txPacket())

        if breakdown is not None:
            breakdown.wrap(reader, *SDK_GROUP_CALLS)
            breakdown.wrap(writer, "clearParam", "addParam", "txPacket")
        return _run(cycle, duration_s, breakdown)
    finally:
        port.closePort()


CLIENTS: dict[str, Callable[[str, float, Breakdown | None], dict[str, float]]] = {
    "jtc_hw": measure_driver,
    "sdk loop": measure_sdk_loop,
}


def _row(client: str, duration_s: float, breakdown: bool, busy: bool,
         priority: int) -> dict[str, Any]:
    samples = Breakdown() if breakdown else None
    with neighbour(busy), emulator_process(priority) as device:
        got = CLIENTS[client](device, duration_s, samples)
    wire = wire_us()
    delays = MOTORS * RETURN_DELAY_US
    row: dict[str, Any] = {
        "bus": "feetech",
        "client": client,
        "bitrate": BAUD,
        "motors": MOTORS,
        "buses": 1,
        "rate_hz": round(1e6 / got["cycle_us"], 1),
        "cycle_us": round(got["cycle_us"], 1),
        "wire_us": round(wire, 1),
        "ratio": round((got["cycle_us"] - delays) / wire, 2),
        "delay_us": float(delays),
        "target_us": round(TARGET_RATIO * wire + delays, 1),
        "target_met": got["cycle_us"] <= TARGET_RATIO * wire + delays,
        "driver_cpu_us": round(got["driver_cpu_us"], 1),
        "driver_ratio": round((wire + got["driver_cpu_us"]) / wire, 2),
        "max_cycle_us": round(got["max_cycle_us"], 1),
        "neighbour": busy,
    }
    if samples is not None:
        row["breakdown"] = samples.summary(wire)
    return row


def feetech_rows(duration_s: float, breakdown: bool = False,
                 neighbours: Sequence[bool] = (False,), priority: int = 0) -> list[dict[str, Any]]:
    """Per neighbour mode (idle ``False``, beside a busy process ``True``), our driver's row
    then the SDK loop's, each on a fresh emulator (``priority``: the emulator's SCHED_FIFO
    priority, the bench's ``--priority``; 0: the emulator's default)."""
    return [_row(client, duration_s, breakdown, busy, priority)
            for busy in neighbours for client in CLIENTS]


def verdicts(rows: Sequence[dict[str, Any]]) -> list[str]:
    """A line per neighbour mode: our row against the target, beside the SDK loop's."""
    lines = []
    for ours in rows:
        if ours["client"] != "jtc_hw":
            continue
        sdk = next((r for r in rows if r["client"] == "sdk loop"
                    and r["neighbour"] == ours["neighbour"]), None)
        met = ours["target_met"]
        line = (f"feetech {BAUD / 1e6:g} Mbit/s{' with a neighbour' if ours['neighbour'] else ''}"
                f" target: cycle {ours['cycle_us']:.1f} us {'<=' if met else '>'} {TARGET_RATIO}"
                f" x wire {ours['wire_us']:.1f} us + return delays {ours['delay_us']:.1f} us = "
                f"{ours['target_us']:.1f} us (ratio {ours['ratio']:.2f}): "
                f"{'met' if met else 'NOT met'}")
        if sdk is not None:
            line += (f"; sdk loop {sdk['cycle_us']:.1f} us (ratio {sdk['ratio']:.2f}), ours "
                     f"{sdk['cycle_us'] / ours['cycle_us']:.2f} x its rate")
        lines.append(line)
    return lines
