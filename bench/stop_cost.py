#!/usr/bin/env python3
"""Cost of decelerating stops (``constraints.decelerate_on_cancel``) in ``update()``.

Two figures per joint count and stop kind:
  stop cycle   the ``update()`` that applies a cancel: builds the stop trajectory from the
               measured state (closed form per joint, exact polynomial pieces) and samples it;
               it happens once per stop. Median and max over the repetitions.
  following    every later ``update()`` while the joints decelerate: sampling the stop like
               any reference. Median and p99; the targets are bench/update_cost.py's (6 joints
               < 60 us, 96 joints < 200 us median).

Stop kinds: ``constant`` (upstream's constant deceleration) and ``jerk`` (a jerk limit on every
joint: the S-curve, up to three pieces per joint). Position command interface, 1 kHz, every
joint cruising at a different velocity when the cancel comes, so every joint stops at its own
time (the most pieces). The state fed back is the previous command (an ideal joint).

Usage:  python bench/stop_cost.py [--repeat N] [--joints 6 24 96] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jtc_hw import (  # noqa: E402
    JointState,
    JointTrajectory,
    JointTrajectoryController,
    TrajectoryPoint,
    load_config,
)
from jtc_hw.config.limits import JointLimits  # noqa: E402

TARGET_MEDIAN_US = {6: 60.0, 96: 200.0}
RATE_HZ = 1000.0
FOLLOW_CYCLES = 200


def controller(joints: int, kind: str) -> JointTrajectoryController:
    names = [f"joint{i}" for i in range(joints)]
    config = load_config({
        "joints": names,
        "command_interfaces": ["position"],
        "state_interfaces": ["position", "velocity"],
        "update_rate": RATE_HZ,
        "constraints": {
            "decelerate_on_cancel": True,
            **{n: {"max_deceleration_on_cancel": 4.0 + 0.05 * i} for i, n in enumerate(names)},
        },
    })
    if kind == "jerk":
        config = dataclasses.replace(config, limits={n: JointLimits(jerk=40.0) for n in names})
    return JointTrajectoryController(config)


def cruise(joints: int) -> JointTrajectory:
    """Every joint at its own constant velocity from 0.2 s to 1.2 s (straight quintics)."""
    v = 1.5 + 0.02 * np.arange(joints)
    points = [
        TrajectoryPoint(t, list(v * (t - 0.1)), list(v), [0.0] * joints)
        for t in (0.2, 1.2, 2.2)
    ]
    return JointTrajectory([f"joint{i}" for i in range(joints)], points)


def measure(joints: int, kind: str, repeat: int) -> dict[str, Any]:
    period = round(1e9 / RATE_HZ)
    clock = time.perf_counter_ns
    stop_costs = np.empty(repeat, dtype=np.int64)
    follow_costs = np.empty((repeat, FOLLOW_CYCLES), dtype=np.int64)
    segments = 0
    for r in range(repeat):
        ctrl = controller(joints, kind)
        now = 1_000_000_000
        ctrl.activate(now, JointState(np.zeros(joints), np.zeros(joints)))
        # The jerk limit that shapes the stop also bounds the goal (issue 12 part A): slowed
        # to fit it, the goal is still cruising when the stop comes.
        goal = ctrl.send_goal(
            now, cruise(joints), time_scaling="fit" if kind == "jerk" else None
        )
        previous = np.zeros(joints)
        state = JointState(np.zeros(joints), np.zeros(joints))
        for _ in range(600):  # cruising at 0.6 s
            out = ctrl.update(now, period, state)
            p = out.command.positions
            state = JointState(p, (p - previous) * RATE_HZ)
            previous = p
            now += period
        ctrl.cancel_goal(goal)
        gc.collect()
        gc.freeze()
        begin = clock()
        out = ctrl.update(now, period, state)
        stop_costs[r] = clock() - begin
        segments = len(ctrl.reference.breakpoints_ns) - 1
        for k in range(FOLLOW_CYCLES):
            p = out.command.positions
            state = JointState(p, (p - previous) * RATE_HZ)
            previous = p
            now += period
            begin = clock()
            out = ctrl.update(now, period, state)
            follow_costs[r, k] = clock() - begin
        gc.unfreeze()
        if ctrl.stopping_until_ns is None or ctrl.stopping_until_ns <= now:
            raise RuntimeError("the stop ended during the benchmark; the figures would be unfair")
    stop_us = stop_costs / 1000.0
    follow_us = follow_costs.ravel() / 1000.0
    return {
        "joints": joints,
        "kind": kind,
        "segments": segments,
        "stop_cycle_median_us": round(float(np.median(stop_us)), 2),
        "stop_cycle_max_us": round(float(stop_us.max()), 2),
        "following_median_us": round(float(np.median(follow_us)), 2),
        "following_p99_us": round(float(np.percentile(follow_us, 99)), 2),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=20, help="stops per case (default 20)")
    parser.add_argument("--joints", type=int, nargs="+", default=[6, 24, 96])
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    rows = [measure(n, kind, args.repeat) for n in args.joints for kind in ("constant", "jerk")]
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    print(
        f"decelerating stop cost, {args.repeat} stops per case at {RATE_HZ:g} Hz, "
        f"Python {sys.version.split()[0]}, numpy {np.__version__}"
    )
    print(
        f"{'joints':>6}  {'kind':<8}  {'pieces':>6}  {'stop cycle us (median/max)':>26}  "
        f"{'following us (median/p99)':>25}  target"
    )
    for row in rows:
        target = TARGET_MEDIAN_US.get(row["joints"])
        ok = target is not None and row["following_median_us"] < target
        verdict = "" if target is None else f"median < {target:.0f} us: {'ok' if ok else 'MISSED'}"
        print(
            f"{row['joints']:>6}  {row['kind']:<8}  {row['segments']:>6}  "
            f"{row['stop_cycle_median_us']:>12.1f} / {row['stop_cycle_max_us']:>11.1f}  "
            f"{row['following_median_us']:>11.1f} / {row['following_p99_us']:>11.1f}  {verdict}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
