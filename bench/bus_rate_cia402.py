#!/usr/bin/env python3
"""Cycle rate of the real CiA 402 driver against wire-paced emulated drives.

Six drives (``Cia402DriveEmulator``, pacing their bus at 1 Mbit/s) on one bus, and on two
buses of three, each on python-can ``virtual`` buses in this process. The real
``Cia402Hardware`` runs read + write cycles as fast as it can for ``--duration`` seconds:
``write`` sends every drive's RPDO1 (controlword + target position, 6 bytes) and a SYNC, then
``read`` waits (bounded at 50 ms) until every drive's two TPDOs (8 + 7 bytes) have arrived.

Figures per row:

- ``rate_hz`` / ``cycle_us``: achieved cycles per second and the mean cycle.
- ``wire_us``: the time one cycle's frames occupy the busiest bus, from their exact stuffed
  bit count (``jtc_hw.drivers.can.bus.wire_time_s``): RPDOs + SYNC + TPDOs; with two buses
  the buses carry their frames at the same time, so the larger of the two.
- ``ratio``: ``cycle_us / wire_us`` (1.0: the wire is the only limit).

The emulators share this process (and its interpreter lock) with the driver: their receive
threads, the motor physics and the pacing sleeps compete with the driver for the CPU, which a
real bus with real drives would not. ``--profile`` adds where the driver's cycle time goes
(time inside ``read`` waiting for frames vs. everything else).

Usage:  python bench/bus_rate_cia402.py [--duration S] [--json] [--profile]
Target: cycle <= 1.3 x wire time; two buses in parallel at about the rate of one bus of three.
"""

from __future__ import annotations

import argparse
import json
import time
import uuid
from typing import Any

import can
import numpy as np
from jtc_hw.drivers.can import cia402_codec as c4
from jtc_hw.drivers.can.bus import wire_time_s
from jtc_hw.drivers.can.cia402 import Cia402Hardware
from jtc_hw.drivers.can.cia402_emulator import Cia402DriveEmulator
from jtc_hw.drivers.motor_model import MotorParams

from jtc_hw.joints import JointCommand

BITRATE = 1_000_000
MOTORS = 6
PHYSICS = MotorParams(max_step_s=0.0005)
"""Motor physics integrated in sub-steps of at most 0.5 ms (the default 0.2 ms costs the
emulators' thread, which shares this interpreter with the driver, 2.5x the CPU)."""


def _cycle_frames(node_ids: list[int]) -> list[can.Message]:
    """One cycle's frames on a bus carrying ``node_ids`` (typical payload values)."""
    frames = [
        can.Message(arbitration_id=c4.rpdo_cob_id(1, n), is_extended_id=False,
                    data=c4.RPDO_CSP.encode(0x000F, 0x00012345))
        for n in node_ids
    ]
    frames.append(can.Message(arbitration_id=c4.SYNC_COB_ID, is_extended_id=False, data=b""))
    for n in node_ids:
        frames.append(can.Message(arbitration_id=c4.tpdo_cob_id(1, n), is_extended_id=False,
                                  data=c4.TPDO_STATUS.encode(0x1237, 0x00012345, 12)))
        frames.append(can.Message(arbitration_id=c4.tpdo_cob_id(2, n), is_extended_id=False,
                                  data=c4.TPDO_FEEDBACK.encode(250, 0, 8)))
    return frames


def _run(
    buses: int, duration_s: float, profile: bool = False, motors: int = MOTORS
) -> dict[str, Any]:
    per_bus = motors // buses
    tag = uuid.uuid4().hex[:6]
    channels = [f"bench-cia402-{tag}-{i}" for i in range(buses)]
    emulator_buses = [can.Bus(interface="virtual", channel=ch) for ch in channels]
    layout = {ch: list(range(1, per_bus + 1)) for ch in channels}
    drives = [
        Cia402DriveEmulator(bus, node, pace_bitrate=BITRATE, motor_params=PHYSICS)
        for bus, ch in zip(emulator_buses, channels, strict=True) for node in layout[ch]
    ]
    joints = [f"j{i}" for i in range(motors)]
    params = {
        "buses": {f"can{i}": {"interface": "virtual", "channel": ch, "bitrate": BITRATE,
                              "receive_timeout": 0.05, "setup_timeout": 0.5}
                  for i, ch in enumerate(channels)},
        "bus": [f"can{i // per_bus}" for i in range(motors)],
        "node_id": [layout[channels[i // per_bus]][i % per_bus] for i in range(motors)],
        "feedback_timeout_s": 1.0,
    }
    hw = Cia402Hardware("bench", joints, ["position"], ["position", "velocity"], params)
    waited = 0.0
    try:
        for d in drives:
            d.start()
        hw.configure()
        held = hw.activate(time.monotonic_ns())
        target = held.positions
        assert target is not None
        command = JointCommand(target.copy())
        # Warm-up, then the measured run.
        for _ in range(20):
            hw.write(time.monotonic_ns(), command)
            hw.read(time.monotonic_ns())
        cycles = 0
        start = time.perf_counter()
        end = start + duration_s
        while True:
            now = time.perf_counter()
            if now >= end:
                break
            hw.write(time.monotonic_ns(), command)
            t = time.perf_counter()
            hw.read(time.monotonic_ns())
            waited += time.perf_counter() - t
            cycles += 1
        elapsed = time.perf_counter() - start
        missed = sum(v["missed"] for v in hw.status()["details"]["drives"].values())
    finally:
        hw.shutdown(time.monotonic_ns())
        for d in drives:
            d.stop()
        for bus in emulator_buses:
            bus.shutdown()
    wire_s = max(wire_time_s(_cycle_frames(layout[ch]), BITRATE) for ch in channels)
    cycle_s = elapsed / max(cycles, 1)
    row: dict[str, Any] = {
        "bus": "can-cia402",
        "bitrate": BITRATE,
        "motors": motors,
        "buses": buses,
        "rate_hz": round(cycles / elapsed, 1),
        "cycle_us": round(cycle_s * 1e6, 1),
        "wire_us": round(wire_s * 1e6, 1),
        "ratio": round(cycle_s / wire_s, 3),
    }
    if profile:
        row["read_wait_us"] = round(waited / max(cycles, 1) * 1e6, 1)
        row["missed_answers"] = int(missed)
    return row


def cia402_rows(duration_s: float, profile: bool = False) -> list[dict[str, Any]]:
    """Rows for six drives on one 1 Mbit/s bus and on two buses of three (module docstring).

    Raises:
        jtc_hw.errors.HardwareError: the emulated drives could not be configured or enabled.
    """
    return [_run(buses, duration_s, profile) for buses in (1, 2)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3.0, help="seconds per row")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    parser.add_argument("--profile", action="store_true", help="add read-wait figures")
    args = parser.parse_args()
    rows = cia402_rows(args.duration, args.profile)
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return
    keys = list(rows[0])
    print("  ".join(f"{k:>14}" for k in keys))
    for row in rows:
        print("  ".join(f"{row[k]!s:>14}" for k in keys))
    best = np.array([r["ratio"] for r in rows])
    print(f"target: ratio <= 1.3 (worst here {best.max():.2f})")
    if args.profile:
        alone = _run(1, args.duration, True, motors=MOTORS // 2)
        print(f"reference: {MOTORS // 2} drives on one bus alone: {alone['rate_hz']} Hz "
              f"(two buses of {MOTORS // 2}: {rows[1]['rate_hz']} Hz), ratio {alone['ratio']}")


if __name__ == "__main__":
    main()
