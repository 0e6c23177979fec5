#!/usr/bin/env python3
"""Missed MIT replies at a fixed loop rate, idle and beside a CPU hog (issue 22, point 8).

The daemon's cycle on the emulated leg of ``config/can-mit-leg-emulated.yaml``: six AK80-9
motors on one 1 Mbit/s bus, served by ``jtc-hw emulate can --pace`` (its own process, as
that file's comment starts it) over socketcand, driven by the real ``MitHardware`` at 500 Hz
on the daemon's own absolute-deadline ticker (:class:`jtc_hw.daemon.loop.clock.Ticker`: a late
cycle is followed by a shorter one, a stall of a period or more skips deadlines), each cycle
``read`` (the replies to the previous cycle's ``write``, ``receive_timeout`` 1 ms as in that
file) then ``write``. Nothing runs at a realtime priority: the default deployment.

Each row: the transactions (set-points sent), the replies missed (not in by the read's
deadline: the driver's ``missed_replies``, the ``timeouts`` of ``jtc-hw hardware``), their
rate, the cycles' lateness (median, 99th percentile, on the ticker's stamps), the deadlines
skipped, the emulator process's CPU share, and the load average at the start. ``--hog N``
adds a row with N busy Python processes running beside it (``tools/cpu-hog``'s load).

The emulator runs at its default priority (SCHED_FIFO 1 where permitted) unless
``--emulator-priority`` says otherwise (0: normal scheduling, as before issue 22).

Usage:  python bench/miss_rate_can.py [--duration S] [--hog N] [--emulator-priority N] [--json]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jtc_hw.controller.joints import JointCommand  # noqa: E402
from jtc_hw.daemon.loop.clock import Ticker  # noqa: E402
from jtc_hw.drivers.can.mit.hardware import MitHardware  # noqa: E402
from jtc_hw.hardware.timing import reduce_timer_slack  # noqa: E402

MOTORS = 6
RATE_HZ = 500
RECEIVE_TIMEOUT_S = 0.001  # config/can-mit-leg-emulated.yaml


def _spin() -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    x = 0
    while True:
        x = (x + 1) & 0xFFFF


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(duration_s: float, hogs: int, priority: int | None = None) -> dict[str, Any]:
    """One row: the loop for ``duration_s`` with ``hogs`` busy processes beside it, the
    emulator at SCHED_FIFO ``priority`` (``None``: its default; 0: normal scheduling)."""
    ctx = multiprocessing.get_context("fork")
    spinners = [ctx.Process(target=_spin, daemon=True) for _ in range(hogs)]
    for p in spinners:
        p.start()
    load = os.getloadavg()[0]
    emulator = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "emulate", "can", "--protocol", "mit", "--ids",
         f"1-{MOTORS}", "--model", "AK80-9", "--pace", "--socketcand-port", "0",
         *([] if priority is None else ["--priority", str(priority)])],
        stdout=subprocess.PIPE, text=True)
    try:
        assert emulator.stdout is not None
        fields = dict(f.split("=", 1) for f in emulator.stdout.readline().split())
        joints = [f"j{i}" for i in range(MOTORS)]
        hw = MitHardware("leg", joints, ["position"], ["position", "velocity"], {
            "buses": {"can0": {"interface": "socketcand", "channel": "can0",
                               "host": fields["host"], "port": int(fields["port"]),
                               "receive_timeout": RECEIVE_TIMEOUT_S}},
            "ids": list(range(1, MOTORS + 1)), "model": "AK80-9",
            "feedback_timeout": 1.0,  # counted here, never a fault
        })
        hw.configure()
        try:
            command = JointCommand(positions=hw.activate(time.monotonic_ns()).positions)
            before = hw.health()["bus"]
            cpu0 = _cpu_s(emulator.pid)
            ticker = Ticker(round(1e9 / RATE_HZ))
            late: list[int] = []
            end = time.monotonic_ns() + round(duration_s * 1e9)
            while (tick := ticker.wait()).woke_ns < end:
                late.append(tick.woke_ns - tick.deadline_ns)
                hw.read(tick.woke_ns)
                hw.write(time.monotonic_ns(), command)
            after = hw.health()["bus"]
            cpu = _cpu_s(emulator.pid) - cpu0
        finally:
            hw.shutdown(time.monotonic_ns())
    finally:
        emulator.send_signal(signal.SIGTERM)
        emulator.wait(10)
        for p in spinners:
            p.terminate()
            p.join(5)
    sent = after["transactions"] - before["transactions"]
    missed = after["timeouts"] - before["timeouts"]
    late.sort()
    return {
        "bench": "miss_rate_can",
        "hogs": hogs,
        "emulator_priority": priority,
        "load_1min": round(load, 2),
        "rate_hz": RATE_HZ,
        "motors": MOTORS,
        "transactions": sent,
        "missed": missed,
        "miss_rate": round(missed / max(sent, 1), 5),
        "late_p50_us": round(late[len(late) // 2] / 1e3, 1),
        "late_p99_us": round(late[int(len(late) * 0.99)] / 1e3, 1),
        "skipped": ticker.skipped_total,
        "emulator_cpu": round(cpu / duration_s, 3),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per row")
    parser.add_argument("--hog", type=int, default=2,
                        help="busy processes for the loaded row (0: idle row only)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    parser.add_argument("--emulator-priority", type=int, default=None, metavar="N",
                        help="the emulator's --priority (default: its own default)")
    args = parser.parse_args(argv)
    reduce_timer_slack()  # as the daemon's loop process does
    prio = args.emulator_priority
    rows = [measure(args.duration, 0, prio)]
    if args.hog:
        rows.append(measure(args.duration, args.hog, prio))
    for row in rows:
        if args.json:
            print(json.dumps(row))
        else:
            print(f"emulator priority {row['emulator_priority']}, hogs {row['hogs']} "
                  f"(load {row['load_1min']}): {row['missed']} of "
                  f"{row['transactions']} replies missed ({row['miss_rate'] * 100:.2f} %), "
                  f"lateness p50 {row['late_p50_us']} us p99 {row['late_p99_us']} us, "
                  f"{row['skipped']} skipped, emulator {row['emulator_cpu'] * 100:.0f} % CPU")
    return 0


if __name__ == "__main__":
    sys.exit(main())
