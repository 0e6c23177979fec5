#!/usr/bin/env python3
"""Cost of one ``JointTrajectoryController.update()``: median and p99, per joint count and case.

Cases:
  quintic     position command interface, following a 100-point quintic spline (positions,
              velocities, accelerations given), path and goal tolerances checked every cycle.
  pid-effort  effort command interface, PID on every joint (p, i, d, feed-forward), the same
              trajectory (with effort feed-forward), tolerances checked every cycle.
  scaled      as quintic, with position, velocity and acceleration commanded, acceleration
              limits on every joint and speed scaling at 0.5 (velocities and accelerations
              scaled every cycle).
  ramping     as scaled, the factor ramping between 0.5 and 0.8 all the time (the ramp's
              bound from the acceleration limits computed every cycle).

The state fed back is the previous command (an ideal joint), so the goal stays active and every
cycle does the full work: sample twice (now, now + period), error, tolerance checks, control law.
The garbage collector is frozen first, as the daemon does.

Usage:  python bench/update_cost.py [--cycles N] [--joints 6 24 96] [--json]
Targets (2-core dev machine): 6 joints < 60 us median, 96 joints < 200 us median.
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
POINTS = 100
SPACING_S = 0.1
CASES = ("quintic", "pid-effort", "scaled", "ramping")
SCALED = ("scaled", "ramping")


def controller(joints: int, case: str) -> JointTrajectoryController:
    names = [f"joint{i}" for i in range(joints)]
    params: dict[str, Any] = {
        "joints": names,
        "state_interfaces": ["position", "velocity"],
        "update_rate": RATE_HZ,
        "allow_nonzero_velocity_at_trajectory_end": True,
        "constraints": {
            "stopped_velocity_tolerance": 0.05,
            **{n: {"trajectory": 10.0, "goal": 10.0} for n in names},
        },
    }
    if case == "quintic":
        params["command_interfaces"] = ["position"]
    elif case in SCALED:
        params["command_interfaces"] = ["position", "velocity", "acceleration"]
        params["state_interfaces"] = ["position", "velocity", "acceleration"]
    else:
        params["command_interfaces"] = ["effort"]
        params["gains"] = {
            n: {"p": 50.0, "i": 5.0, "d": 2.0, "i_clamp": 1.0, "ff_velocity_scale": 0.5}
            for n in names
        }
    config = load_config(params)
    if case in SCALED:
        config = dataclasses.replace(
            config, limits={n: JointLimits(acceleration=2.0) for n in names}
        )
    return JointTrajectoryController(config)


def trajectory(joints: int, case: str) -> JointTrajectory:
    phase = np.arange(joints) * 0.3
    points = []
    for k in range(1, POINTS + 1):
        t = k * SPACING_S
        points.append(
            TrajectoryPoint(
                t,
                list(np.sin(t + phase)),
                list(np.cos(t + phase)),
                list(-np.sin(t + phase)),
                effort=list(0.1 * np.sin(t + phase)) if case == "pid-effort" else None,
            )
        )
    return JointTrajectory([f"joint{i}" for i in range(joints)], points)


def measure(joints: int, case: str, cycles: int) -> dict[str, Any]:
    ctrl = controller(joints, case)
    period = round(1e9 / RATE_HZ)
    now = 1_000_000_000
    ctrl.activate(now, JointState(np.zeros(joints), np.zeros(joints)))
    # With limits, the lead-in from rest to the first point is beyond them: the goal is slowed
    # to fit (issue 12 part A), as a user would send it.
    ctrl.send_goal(
        now, trajectory(joints, case), time_scaling="fit" if case in SCALED else None
    )
    if case in SCALED:
        ctrl.set_speed_scaling(0.5)
    costs = np.empty(cycles, dtype=np.int64)
    state = JointState(np.zeros(joints), np.zeros(joints))
    clock = time.perf_counter_ns
    gc.collect()
    gc.freeze()
    for k in range(cycles):
        if case == "ramping" and k % 100 == 0:
            # Hardly ever settles: 0.3 of factor takes over 100 cycles at these limits.
            ctrl.set_speed_scaling(0.8 if k % 200 == 0 else 0.5)
        begin = clock()
        out = ctrl.update(now, period, state)
        costs[k] = clock() - begin
        desired = out.desired
        state = JointState(desired.positions, desired.velocities, desired.accelerations)
        now += period
    gc.unfreeze()
    if ctrl.active_goal is None:
        raise RuntimeError("the goal ended during the benchmark; the figures would be unfair")
    us = costs / 1000.0
    return {
        "joints": joints,
        "case": case,
        "median_us": round(float(np.median(us)), 2),
        "p99_us": round(float(np.percentile(us, 99)), 2),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--cycles",
        type=int,
        default=9000,
        help="update() calls per case (default 9000: 9 s of a 10 s trajectory at 1 kHz)",
    )
    parser.add_argument("--joints", type=int, nargs="+", default=[6, 24, 96])
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    if args.cycles > POINTS * SPACING_S * RATE_HZ - 10:
        parser.error(f"--cycles must stay below {int(POINTS * SPACING_S * RATE_HZ) - 10}")
    rows = [
        measure(n, case, args.cycles) for n in args.joints for case in CASES
    ]
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    print(
        f"update() cost, {args.cycles} cycles per case, Python {sys.version.split()[0]}, "
        f"numpy {np.__version__}"
    )
    print(f"{'joints':>6}  {'case':<10}  {'median us':>9}  {'p99 us':>7}  target")
    for row in rows:
        target = TARGET_MEDIAN_US.get(row["joints"])
        verdict = (
            ""
            if target is None
            else (f"median < {target:.0f} us: {'ok' if row['median_us'] < target else 'MISSED'}")
        )
        print(
            f"{row['joints']:>6}  {row['case']:<10}  {row['median_us']:>9.1f}  "
            f"{row['p99_us']:>7.1f}  {verdict}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
