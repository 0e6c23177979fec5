#!/usr/bin/env python3
"""How soon ``jtc-hw send`` of a large CSV shows its progress bar, and when the goal is accepted.

Starts ``python -m jtc_hw run`` on six simulated (mirror) joints (``bench/loop_jitter.py``'s
``Daemon``: the demo arm, socket and files in a temporary directory), writes a CSV trajectory
of ``--points`` points 1 ms apart (a small wave on all six joints, positions only) and runs the
``jtc-hw`` console script (``send FILE --socket ...``) ``--runs`` times on a pseudo-terminal,
as a user at a terminal would. From the moment the command is spawned it reads the terminal:

- ``bar_ms``: the first character of the progress bar (``[``) on the terminal;
- ``accepted_ms``: the ``goal N accepted`` line (the file read, the client loaded, the goal
  sent, parsed, checked and planned by the daemon);

then, both seen, sends Ctrl-C (SIGINT), which cancels the goal, and waits for the command to
exit. (Before issue 24 the bar came with the goal's first feedback, after ``accepted``.)
``python_ms`` is the floor: the same interpreter spawned on the same terminal, printing one
character (``python -c``; no site-packages work of ours).

Usage:  python bench/send_start.py [--points 20000] [--runs 7] [--json]
``--json`` prints one JSON object per line instead of the table:
``{"kind": "send_start", "points", "runs", "bar_ms_p50", "bar_ms_max", "accepted_ms_p50",
"python_ms_p50", "load_average"}``.
Target (issue 24): the bar within 100 ms of the command's start, for 20,000 points.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pty
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from loop_jitter import Daemon  # noqa: E402

from jtc_hw.cli.demo import DEMO_JOINTS  # noqa: E402

SPACING_S = 0.001
AMPLITUDE = 0.02  # rad: a goal preempting the held position stays inside the path tolerance
TIMEOUT_S = 60.0
TARGET_POINTS = 20000
TARGET_MS = 100.0


def write_csv(path: Path, points: int) -> None:
    """``points`` rows 1 ms apart of q_j = A sin(w_j t), six joints, positions only."""
    lines = ["time_from_start," + ",".join(DEMO_JOINTS)]
    for i in range(1, points + 1):
        t = i * SPACING_S
        lines.append(
            f"{t:.3f},"
            + ",".join(
                f"{AMPLITUDE * math.sin(2 * math.pi * 0.5 * (1 + 0.1 * j) * t):.6f}"
                for j in range(len(DEMO_JOINTS))
            )
        )
    path.write_text("\n".join(lines) + "\n")


def command() -> list[str]:
    """The console script a user runs (beside this interpreter), else ``python -m jtc_hw``."""
    script = Path(sys.executable).parent / "jtc-hw"
    return [str(script)] if script.exists() else [sys.executable, "-m", "jtc_hw"]


def on_terminal(argv: list[str], marks: dict[str, bytes], interrupt: bool) -> dict[str, float]:
    """Run ``argv`` on a new pseudo-terminal; ms from the spawn to each mark's first sight.

    ``interrupt``: the command gets SIGINT (Ctrl-C) once every mark has shown.

    Raises:
        RuntimeError: a mark never showed (the output is quoted).
    """
    master, slave = pty.openpty()
    begin = time.perf_counter()
    process = subprocess.Popen(
        argv, stdin=slave, stdout=slave, stderr=slave, close_fds=True, cwd=ROOT
    )
    os.close(slave)
    seen: dict[str, float] = {}
    output = b""
    deadline = begin + TIMEOUT_S
    try:
        while len(seen) < len(marks) and time.perf_counter() < deadline:
            ready, _, _ = select.select([master], [], [], 0.5)
            if not ready:
                continue
            try:
                chunk = os.read(master, 65536)
            except OSError:  # the command exited and closed the terminal
                break
            now = time.perf_counter()
            output += chunk
            for name, mark in marks.items():
                if name not in seen and mark in output:
                    seen[name] = (now - begin) * 1e3
            if interrupt and len(seen) == len(marks) and process.poll() is None:
                process.send_signal(signal.SIGINT)
        if len(seen) < len(marks):
            raise RuntimeError(f"{argv[-3:]}: no {set(marks) - set(seen)} in: {output[-2000:]!r}")
        # Drain the terminal until the command exits (it cancels its goal on Ctrl-C).
        while process.poll() is None and time.perf_counter() < deadline:
            if select.select([master], [], [], 0.1)[0]:
                try:
                    os.read(master, 65536)
                except OSError:
                    break
        process.wait(timeout=max(0.1, deadline - time.perf_counter()))
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        os.close(master)
    return seen


def percentile(values: list[float], p: float) -> float:
    """Nearest-rank percentile."""
    ordered = sorted(values)
    return ordered[max(0, math.ceil(p / 100 * len(ordered)) - 1)]


def measure(args: argparse.Namespace, note: Any) -> dict[str, Any]:
    bars, accepted, floor = [], [], []
    with tempfile.TemporaryDirectory(prefix="jtc-hw-send-start-") as tmp:
        csv_path = Path(tmp) / "goal.csv"
        write_csv(csv_path, args.points)
        note(f"{args.points} points: {csv_path.stat().st_size} bytes of CSV")
        with Daemon(args.rate, 0, None, False) as daemon:
            daemon.connect().close()
            argv = [*command(), "send", str(csv_path), "--socket", daemon.socket]
            for run in range(args.runs + 1):  # the first run warms the file cache
                marks = on_terminal(argv, {"bar": b"[", "accepted": b"accepted"}, True)
                ms = on_terminal([sys.executable, "-c", "print('[')"], {"bar": b"["}, False)
                if run == 0:
                    continue
                bars.append(marks["bar"])
                accepted.append(marks["accepted"])
                floor.append(ms["bar"])
                note(f"  run {run}: bar {marks['bar']:.1f} ms, accepted "
                     f"{marks['accepted']:.1f} ms (python alone {ms['bar']:.1f} ms)")
    return {
        "kind": "send_start",
        "points": args.points,
        "runs": args.runs,
        "bar_ms_p50": round(percentile(bars, 50), 1),
        "bar_ms_max": round(max(bars), 1),
        "accepted_ms_p50": round(percentile(accepted, 50), 1),
        "python_ms_p50": round(percentile(floor, 50), 1),
        "load_average": os.getloadavg()[0],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=TARGET_POINTS,
                        help=f"points in the CSV (default {TARGET_POINTS})")
    parser.add_argument("--runs", type=int, default=7, help="measured runs (default 7)")
    parser.add_argument("--rate", type=float, default=500.0,
                        help="the daemon's update rate (default 500 Hz)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    note = (lambda _: None) if args.json else print
    row = measure(args, note)
    if args.json:
        print(json.dumps(row))
        return 0
    verdict = "met" if row["bar_ms_p50"] <= TARGET_MS else "MISSED"
    print(f"\n{'points':>7} {'bar p50':>9} {'bar max':>9} {'accepted p50':>13} "
          f"{'python alone':>13} {'load':>5}")
    print(f"{row['points']:>7} {row['bar_ms_p50']:>7.1f}ms {row['bar_ms_max']:>7.1f}ms "
          f"{row['accepted_ms_p50']:>11.1f}ms {row['python_ms_p50']:>11.1f}ms "
          f"{row['load_average']:>5.2f}")
    print(f"target: the bar within {TARGET_MS:.0f} ms of the command's start ({verdict})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
