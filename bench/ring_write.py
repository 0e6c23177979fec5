#!/usr/bin/env python3
"""What the cycle ring costs the loop: one ``CycleRing.write`` per cycle, median and p99.

The loop process writes every cycle's row (deadline, measured, reference and output values per
joint) into the shared-memory ring the flight recorder reads
(``jtc_hw/daemon/channel/cyclering.py``).
This times that call alone, with the arrays one controller cycle produces (position, velocity
and acceleration reference, position and velocity measured, a position command), the garbage
collector frozen as in the loop; and the reader's copy of a 100 ms batch (the API process, for
scale). A reader keeps up throughout, as the daemon's does.

Usage:  python bench/ring_write.py [--cycles N] [--joints 6 24 96] [--json]
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jtc_hw.controller.joints import JointCommand, JointState  # noqa: E402
from jtc_hw.controller.trajectory import TrajectorySample  # noqa: E402
from jtc_hw.daemon.channel.cyclering import READ_PERIOD_S, RING_S, CycleRing  # noqa: E402

RATE_HZ = 1000.0


def measure(joints: int, cycles: int) -> dict[str, Any]:
    ring = CycleRing.create(joints, round(RING_S * RATE_HZ))
    try:
        x = np.linspace(0.0, 1.0, joints)
        measured = JointState(x.copy(), x * 0.5)
        reference = TrajectorySample(x + 0.01, x * 0.5, x * 0.0, x * 0.0)
        output = JointCommand(x + 0.01, None, None, None)
        costs = np.empty(cycles, dtype=np.int64)
        batch = round(READ_PERIOD_S * RATE_HZ)
        reads: list[int] = []
        since = 0
        clock = time.perf_counter_ns
        gc.collect()
        gc.freeze()
        gc.disable()
        try:
            for k in range(cycles):
                t0 = clock()
                ring.write(k * 1_000_000, 1, False, False, 1.0, k / RATE_HZ, k / RATE_HZ,
                           measured, reference, output)
                costs[k] = clock() - t0
                if (k + 1) % batch == 0:  # the reader's turn (not timed with the writes)
                    t0 = clock()
                    _, since, _ = ring.read(since)
                    reads.append(clock() - t0)
        finally:
            gc.enable()
            gc.unfreeze()
        return {
            "joints": joints,
            "cycles": cycles,
            "row_bytes": ring.layout.width * 8,
            "write_median_us": float(np.median(costs)) / 1e3,
            "write_p99_us": float(np.percentile(costs, 99)) / 1e3,
            "read_batch_rows": batch,
            "read_median_us": float(np.median(reads)) / 1e3 if reads else None,
        }
    finally:
        ring.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=20_000, help="rows written per case")
    parser.add_argument("--joints", type=int, nargs="+", default=[6, 24, 96],
                        help="joint counts to measure")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args()
    rows = [measure(j, args.cycles) for j in args.joints]
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    print(f"{'joints':>6} {'row B':>6} {'write median us':>16} {'write p99 us':>13} "
          f"{'read 100 ms us':>15}")
    for r in rows:
        read = "-" if r["read_median_us"] is None else f"{r['read_median_us']:.1f}"
        print(f"{r['joints']:>6} {r['row_bytes']:>6} {r['write_median_us']:>16.2f} "
              f"{r['write_p99_us']:>13.2f} {read:>15}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
