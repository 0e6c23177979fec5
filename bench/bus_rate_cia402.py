#!/usr/bin/env python3
"""Cycle rate of the real CiA 402 driver against wire-paced emulated drives.

Six drives on one 1 Mbit/s bus, on two buses of three, and (the parallelism reference) three
drives on one bus alone. The buses and their drives are one ``jtc-hw emulate can --protocol
cia402 --pace --one-thread`` process (outside the driver's process, as separate hardware is;
one thread serves every bus, each bus's wire modelled on its own, so two buses make two busy
processes on the two cores, not three), reached through python-can's stock ``socketcand``
interface (``tcp_tune`` on). The real
``Cia402Hardware`` runs write + read cycles as fast as it can for ``--duration`` seconds:
``write`` sends every drive's RPDO1 (controlword + target position, 6 bytes) and a SYNC, then
``read`` waits (bounded at 50 ms) until every drive's two TPDOs (8 + 7 bytes) have arrived.

Figures per row:

- ``rate_hz`` / ``cycle_us``: achieved cycles per second and the mean cycle.
- ``wire_us``: the time one cycle's frames occupy the busiest bus, from their exact stuffed
  bit count (``jtc_hw.drivers.can.bus.wire_time_s``): RPDOs + SYNC + TPDOs; with two buses
  the buses carry their frames at the same time, so the larger of the two.
- ``ratio``: ``cycle_us / wire_us`` (1.0: the wire is the only limit).
- ``driver_cpu_us``: the cycling thread's CPU time per cycle; ``driver_ratio``:
  ``(wire + driver cpu) / wire``.
- the two-bus row: ``alone_rate_hz`` (three drives on one bus alone) and ``parallel`` (its
  rate over that; >= 0.9 counts as parallel).

``--profile`` adds the time spent inside ``read`` and the missed answers.

Usage:  python bench/bus_rate_cia402.py [--duration S] [--json] [--profile]
Target: cycle <= 1.3 x wire time; two buses in parallel at about the rate of one bus of three.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can

from jtc_hw.controller.joints import JointCommand
from jtc_hw.drivers.can.bus import wire_time_s
from jtc_hw.drivers.can.cia402 import codec as c4
from jtc_hw.drivers.can.cia402.hardware import Cia402Hardware
from jtc_hw.hardware.timing import reduce_timer_slack

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bus_breakdown import Breakdown, neighbour  # noqa: E402
from bus_rate_can import (  # noqa: E402
    _mark_parallel,
    emulator_processes,
    parallel_check,
    run_cycles,
)

BITRATE = 1_000_000
MOTORS = 6


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
    buses: int, duration_s: float, profile: bool = False, motors: int = MOTORS,
    breakdown: bool = False, busy: bool = False,
) -> dict[str, Any]:
    per_bus = motors // buses
    layout = {f"can{i}": list(range(1, per_bus + 1)) for i in range(buses)}
    joints = [f"j{i}" for i in range(motors)]
    samples = Breakdown() if breakdown else None

    with neighbour(busy), emulator_processes("cia402", layout) as bus_params:
        params = {
            "buses": {name: {**settings, "bitrate": BITRATE, "receive_timeout": 0.05,
                             "setup_timeout": 0.5}
                      for name, settings in bus_params.items()},
            "bus": [name for name, ids in layout.items() for _ in ids],
            "node_id": [n for ids in layout.values() for n in ids],
            "feedback_timeout_s": 1.0,
            # The drives' heartbeat watchdog: long, as the feedback timeout, so that a stall of
            # this (not real-time) process on a busy machine does not stop them mid-run.
            "watchdog_s": 1.0,
        }
        hw = Cia402Hardware("bench", joints, ["position"], ["position", "velocity"], params)
        try:
            hw.configure()
            held = hw.activate(time.monotonic_ns())
            target = held.positions
            assert target is not None
            run = run_cycles(hw, JointCommand(target.copy()), duration_s, samples,
                             [b.bus for b in hw._buses.values()])
            cycles, elapsed, cpu, waited = run.cycles, run.elapsed_s, run.cpu_s, run.read_s
            missed = sum(v["missed"] for v in hw.status()["details"]["drives"].values())
        finally:
            hw.shutdown(time.monotonic_ns())
    wire_s = max(wire_time_s(_cycle_frames(ids), BITRATE) for ids in layout.values())
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
        "transport": "socketcand",
        "driver_cpu_us": round(cpu / max(cycles, 1) * 1e6, 1),
        "driver_ratio": round((wire_s + cpu / max(cycles, 1)) / wire_s, 3),
        "neighbour": busy,
    }
    if samples is not None:
        row["breakdown"] = samples.summary(wire_s * 1e6)
    if profile:
        row["read_wait_us"] = round(waited / max(cycles, 1) * 1e6, 1)
        row["missed_answers"] = int(missed)
    return row


def cia402_rows(
    duration_s: float, profile: bool = False, reference: bool = True, breakdown: bool = False,
    neighbours: Sequence[bool] = (False,),
) -> list[dict[str, Any]]:
    """Rows for six drives on one 1 Mbit/s bus, on two buses of three and, with
    ``reference``, three drives on one bus alone (the parallelism check; module docstring).
    Each layout runs once per entry of ``neighbours`` (idle ``False``, beside a busy process
    ``True``), in turn; ``breakdown`` adds the per-cycle split (bench/bus_breakdown.py).

    Raises:
        jtc_hw.errors.HardwareError: the emulated drives could not be configured or enabled.
        RuntimeError: an emulator process did not start.
    """
    layouts = [(MOTORS, 1), (MOTORS, 2)] + ([(MOTORS // 2, 1)] if reference else [])
    rows = [_run(buses, duration_s, profile, motors=motors, breakdown=breakdown, busy=busy)
            for motors, buses in layouts for busy in neighbours]
    _mark_parallel(rows)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3.0, help="seconds per row")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    parser.add_argument("--profile", action="store_true", help="add read-wait figures")
    args = parser.parse_args()
    reduce_timer_slack()  # as the daemon's loop process does
    rows = cia402_rows(args.duration, args.profile)
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return
    keys = list(rows[0])
    print("  ".join(f"{k:>14}" for k in keys))
    for row in rows:
        print("  ".join(f"{row[k]!s:>14}" for k in keys))
    for line in parallel_check(rows):
        print(line)


if __name__ == "__main__":
    main()
