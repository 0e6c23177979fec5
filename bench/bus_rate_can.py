#!/usr/bin/env python3
"""CAN bus rate: the real MitHardware read+write cycle against wire-time-paced MIT emulators.

For 6 motors on one 1 Mbit/s bus, on two buses of 3, and (the parallelism reference) 3 motors
on one bus alone, the cycle ``write`` (one set-point frame per motor, the buses taking turns)
then ``read`` (waits for every reply, bounded by the bus's ``receive_timeout``) runs as fast
as it can for ``--duration`` seconds.

The buses and their motors are one ``jtc-hw emulate can --pace --one-thread`` process (the
buses are hardware outside the driver's process: an emulator sharing the driver's interpreter
lock would queue its work behind the driver's instead of overlapping the wire time; one thread
serves every bus, each bus's wire modelled on its own, so with two buses two busy processes
share the two cores, not three), reached through python-can's stock ``socketcand`` interface
(``tcp_tune`` on). The emulator releases
each reply when the command's and the reply's bits (exact stuffing) would have crossed the
wire, frames on one bus one after another, the wire starting when the command reached the
server's socket (kernel receive stamp).

Columns: achieved rate, measured cycle time, wire time per cycle (the busiest bus: buses run in
parallel; a set-point and a reply per motor), and their ratio; the driver's own CPU time per
cycle (``time.thread_time`` of the cycling thread: encoding, python-can's socketcand client --
an ASCII element, a ``send`` and a ``setsockopt`` per frame out, a ``select``, ``recv`` and
``setsockopt`` per segment in -- decoding, checks; not the time blocked waiting) and
``(wire + driver cpu) / wire``. Targets: ratio <= 1.3, and two buses of 3 at >= 0.9 x the rate
of one bus of 3 alone (the verdict lines).

Usage:  python bench/bus_rate_can.py [--duration S] [--json]
"""

from __future__ import annotations

import argparse
import gc
import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import can

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jtc_hw.controller.joints import JointCommand  # noqa: E402
from jtc_hw.drivers.can.bus import wire_time_s  # noqa: E402
from jtc_hw.drivers.can.mit.codec import (  # noqa: E402
    MODEL_PRESETS,
    MitCommand,
    MitReply,
    encode_command,
    encode_reply,
)
from jtc_hw.drivers.can.mit.hardware import MitHardware  # noqa: E402
from jtc_hw.hardware.timing import reduce_timer_slack  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bus_breakdown import Breakdown, neighbour  # noqa: E402

CAN_CALLS = ("send", "recv")
"""The python-can bus methods our driver calls each cycle (the python-can boundary)."""

BITRATE = 1_000_000
MOTORS = 6
TARGET_RATIO = 1.3
PARALLEL_TARGET = 0.9
"""Two buses of 3 count as parallel at >= this fraction of one bus of 3's rate."""
MODEL = "AK80-9"


def _wire_us(ids: list[int]) -> float:
    """Wire time of one cycle on a bus: a set-point and a reply per motor (typical values)."""
    limits = MODEL_PRESETS[MODEL]
    frames = []
    for motor_id in ids:
        cmd = encode_command(MitCommand(0.0, 0.0, 20.0, 0.5, 0.0), limits)
        reply = encode_reply(MitReply(motor_id, 0.0, 0.0, 0.0), limits)
        frames.append(can.Message(arbitration_id=motor_id, is_extended_id=False, data=cmd))
        frames.append(can.Message(arbitration_id=0, is_extended_id=False, data=reply))
    return wire_time_s(frames, BITRATE) * 1e6


@contextmanager
def emulator_processes(
    protocol: str, layout: dict[str, list[int]], extra: Sequence[str] = (),
    separate: bool = False,
) -> Iterator[dict[str, dict[str, Any]]]:
    """The paced ``jtc-hw emulate can --one-thread`` process serving every bus of ``layout``
    (``separate``: one process per bus). The buses and their motors are hardware outside the
    driver's process: they must not share its interpreter lock. One thread serves every bus
    (a heap of due replies per bus, each bus's wire modelled on its own, the buses
    concurrent): with two buses, two busy processes on the two cores (driver, emulator),
    where a process per bus made three compete for them. Yields ``{bus name: socketcand bus
    settings}``."""
    procs: list[subprocess.Popen[str]] = []
    settings: dict[str, dict[str, Any]] = {}
    groups = [[n] for n in layout] if separate else [list(layout)]
    try:
        for group in groups:
            cmd = [sys.executable, "-m", "jtc_hw", "emulate", "can", "--protocol", protocol,
                   "--pace", "--bitrate", str(BITRATE), "--socketcand-port", "0",
                   "--one-thread", *extra]
            for name in group:
                cmd += ["--channel", name, "--ids", ",".join(map(str, layout[name]))]
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
            procs.append(proc)
            assert proc.stdout is not None
            line = proc.stdout.readline()  # "interface=socketcand host=H port=P channel=C"
            if not line:
                raise RuntimeError(f"emulator for {name} did not start (exit {proc.wait()})")
            fields = dict(f.split("=", 1) for f in line.split())
            for name in group:
                settings[name] = {"interface": "socketcand", "channel": name,
                                  "host": fields["host"], "port": int(fields["port"])}
        yield settings
    finally:
        for proc in procs:
            proc.send_signal(signal.SIGTERM)
        for proc in procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def parallel_check(rows: list[dict[str, Any]]) -> list[str]:
    """Verdict lines: each row against the ratio target, two buses against one bus of 3."""
    lines = []
    for r in rows:
        ok = r["ratio"] <= TARGET_RATIO
        beside = " with a neighbour" if r.get("neighbour") else ""
        lines.append(f"{r['bus']} {r['motors']} motors on {r['buses']} bus(es){beside}: ratio "
                     f"{r['ratio']:.2f} {'<=' if ok else '>'} {TARGET_RATIO}: "
                     f"{'ok' if ok else 'MISSED'}")
    for two in rows:
        if "parallel" not in two:
            continue
        share = two["parallel"]
        ok = share >= PARALLEL_TARGET
        beside = " with a neighbour" if two.get("neighbour") else ""
        lines.append(f"{two['bus']} two buses of {MOTORS // 2}{beside}: {two['rate_hz']:.0f} Hz "
                     f"= {share:.2f} x one bus of {MOTORS // 2} alone "
                     f"({two['alone_rate_hz']:.0f} Hz; >= {PARALLEL_TARGET} counts as "
                     f"parallel): {'ok' if ok else 'MISSED'}")
    return lines


class CycleRun(NamedTuple):
    """What :func:`run_cycles` measured."""

    cycles: int
    elapsed_s: float
    cpu_s: float  # this thread's CPU time: the driver's own work
    read_s: float  # time spent in read(): mostly waiting for the replies


def run_cycles(hw: Any, command: JointCommand, duration_s: float,
               breakdown: Breakdown | None = None, buses: Sequence[Any] = ()) -> CycleRun:
    """Warm up, then run ``hw.write`` + ``hw.read`` back to back for ``duration_s``
    (``breakdown``: sample each cycle, timing python-can's calls on ``buses``)."""
    clock = time.monotonic_ns
    for _ in range(50):  # warm up (caches, TCP windows)
        hw.write(clock(), command)
        hw.read(clock())
    if breakdown is not None:
        for bus in buses:
            breakdown.wrap(bus, *CAN_CALLS)
    gc.collect()
    gc.freeze()
    try:
        cycles = 0
        read_s = 0.0
        now = time.perf_counter
        cpu0 = time.thread_time()
        t0 = now()
        end = t0 + duration_s
        while (t := now()) < end:
            if breakdown is not None:
                breakdown.begin()
            hw.write(clock(), command)
            t = now()
            hw.read(clock())
            read_s += now() - t
            if breakdown is not None:
                breakdown.end()
            cycles += 1
        elapsed = now() - t0
        cpu = time.thread_time() - cpu0
    finally:
        gc.unfreeze()
    return CycleRun(cycles, elapsed, cpu, read_s)


def measure(motors: int, buses: int, duration_s: float, breakdown: bool = False,
            busy: bool = False) -> dict[str, Any]:
    """One row: ``motors`` MIT motors spread over ``buses`` paced buses, emulated by one
    one-thread process behind a socketcand server, reached with python-can's stock ``socketcand``
    client (``tcp_tune`` on); ``breakdown``: with the per-cycle split; ``busy``: beside one busy
    process (bench/bus_breakdown.py)."""
    per_bus = motors // buses
    layout = {f"can{b}": list(range(1, per_bus + 1)) for b in range(buses)}
    samples = Breakdown() if breakdown else None
    with neighbour(busy), emulator_processes("mit", layout, ("--model", MODEL)) as bus_params:
        joints = [f"j{i}" for i in range(motors)]
        hw = MitHardware("bench", joints, ["position"], ["position", "velocity"], {
            "buses": {name: {**settings, "bitrate": BITRATE, "receive_timeout": 0.05}
                      for name, settings in bus_params.items()},
            "bus": [name for name, ids in layout.items() for _ in ids],
            "ids": [i for ids in layout.values() for i in ids],
            "feedback_timeout": 1.0,
        })
        try:
            hw.configure()
            hold = hw.activate(time.monotonic_ns())
            run = run_cycles(hw, JointCommand(positions=hold.positions), duration_s, samples,
                             [link.bus for link in hw._links.values()])
            cycles, elapsed, cpu = run.cycles, run.elapsed_s, run.cpu_s
            missed = sum(m["missed_replies"] for m in hw.status()["details"]["motors"].values())
        finally:
            hw.shutdown(time.monotonic_ns())
    cycle_us = elapsed / max(cycles, 1) * 1e6
    wire_us = max(_wire_us(ids) for ids in layout.values())
    return {
        "bus": "can-mit",
        "bitrate": BITRATE,
        "motors": motors,
        "buses": buses,
        "rate_hz": round(cycles / elapsed, 1),
        "cycle_us": round(cycle_us, 1),
        "wire_us": round(wire_us, 1),
        "ratio": round(cycle_us / wire_us, 3),
        "transport": "socketcand",
        "driver_cpu_us": round(cpu / max(cycles, 1) * 1e6, 1),
        "driver_ratio": round((wire_us + cpu / max(cycles, 1) * 1e6) / wire_us, 3),
        "missed_replies": missed,
        "neighbour": busy,
        **({"breakdown": samples.summary(wire_us)} if samples is not None else {}),
    }


def mit_rows(duration_s: float, reference: bool = True, breakdown: bool = False,
             neighbours: Sequence[bool] = (False,)) -> list[dict[str, Any]]:
    """Rows for 6 motors on one bus and on two buses of 3 and, with ``reference``, 3 motors
    on one bus alone (the parallelism check); see the module docstring. Each layout runs once
    per entry of ``neighbours`` (idle ``False``, beside a busy process ``True``), in turn."""
    layouts = [(MOTORS, 1), (MOTORS, 2)] + ([(MOTORS // 2, 1)] if reference else [])
    rows = [measure(motors, buses, duration_s, breakdown, busy)
            for motors, buses in layouts for busy in neighbours]
    _mark_parallel(rows)
    return rows


def _mark_parallel(rows: list[dict[str, Any]]) -> None:
    """Add to the two-bus row the rate of one bus of 3 alone (with the same neighbour) and
    the fraction reached."""
    by_layout = {(r["motors"], r["buses"], r.get("neighbour", False)): r for r in rows}
    for busy in (False, True):
        two = by_layout.get((MOTORS, 2, busy))
        alone = by_layout.get((MOTORS // 2, 1, busy))
        if two is not None and alone is not None:
            two["alone_rate_hz"] = alone["rate_hz"]
            two["parallel"] = round(two["rate_hz"] / alone["rate_hz"], 3)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=2.0, help="seconds per row")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    reduce_timer_slack()  # as the daemon's loop process does
    rows = mit_rows(args.duration)
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    print(f"MIT mode at {BITRATE // 1000} kbit/s, one paced one-thread emulator process, "
          f"socketcand (target ratio <= {TARGET_RATIO})")
    print(f"{'motors':>6} {'buses':>5} {'rate Hz':>8} {'cycle us':>8} {'wire us':>7} "
          f"{'ratio':>6} {'driver cpu us':>13} {'wire+cpu':>8} {'missed':>6}")
    for row in rows:
        print(f"{row['motors']:>6} {row['buses']:>5} {row['rate_hz']:>8.1f} "
              f"{row['cycle_us']:>8.1f} {row['wire_us']:>7.1f} {row['ratio']:>6.3f} "
              f"{row['driver_cpu_us']:>13.1f} {row['driver_ratio']:>8.3f} "
              f"{row['missed_replies']:>6}")
    for line in parallel_check(rows):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
