#!/usr/bin/env python3
"""CAN bus rate: the real MitHardware read+write cycle against wire-time-paced MIT emulators.

For 6 motors on one 1 Mbit/s bus, and on two buses of 3, the cycle ``write`` (one set-point
frame per motor, every bus first) then ``read`` (waits for every reply, bounded by the bus's
``receive_timeout``) runs as fast as it can for ``--duration`` seconds. The emulators (python-can
``virtual`` buses, in this process) deliver each reply only once the command's and the reply's
bits would have crossed the wire at the bitrate (bit stuffing counted exactly), one frame at a
time per bus.

Columns: achieved rate, measured cycle time, wire time per cycle (the slowest bus: buses run in
parallel), and their ratio; the driver's own CPU time per cycle (``time.thread_time`` of the
cycling thread: encoding, sending, decoding, checks -- not the time blocked waiting) and
``(wire + driver cpu) / wire``, what the cycle would cost if the frames' transport added nothing.
The rest of ``cycle - wire - driver cpu`` is the emulation's: with ``virtual`` the emulators'
threads share this interpreter's lock with the driver; with ``socketcand`` every frame crosses
Python threads and TCP in both processes. Target: ratio <= 1.3, and two buses close to one
bus of 3.

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
import uuid
from pathlib import Path
from typing import Any

import can

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jtc_hw.drivers.can.bus import wire_time_s  # noqa: E402
from jtc_hw.drivers.can.emulator import MitBusEmulator  # noqa: E402
from jtc_hw.drivers.can.frames import (  # noqa: E402
    MODEL_PRESETS,
    MitCommand,
    MitReply,
    encode_command,
    encode_reply,
)
from jtc_hw.drivers.can.mit import MitHardware  # noqa: E402

from jtc_hw.joints import JointCommand  # noqa: E402
from jtc_hw.realtime import reduce_timer_slack  # noqa: E402

BITRATE = 1_000_000
MOTORS = 6
TARGET_RATIO = 1.3
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


def _emulator_process(layout: dict[str, list[int]]) -> tuple[subprocess.Popen[str], int]:
    """``jtc-hw emulate can --pace`` as a subprocess; returns it and its socketcand port."""
    cmd = [sys.executable, "-m", "jtc_hw.drivers.can.emulator", "--pace", "--model", MODEL,
           "--bitrate", str(BITRATE)]
    for name, ids in layout.items():
        cmd += ["--channel", name, "--ids", f"{ids[0]}-{ids[-1]}"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    fields = dict(f.split("=", 1) for f in line.split())
    return proc, int(fields["port"])


def measure(buses: int, duration_s: float, transport: str = "virtual") -> dict[str, Any]:
    """One row: 6 motors spread over ``buses`` paced buses.

    ``transport``: ``virtual`` (emulators in this process on python-can virtual buses) or
    ``socketcand`` (emulators in another process, reached over python-can's socketcand client,
    so that they do not share this interpreter's lock).
    """
    per_bus = MOTORS // buses
    layout = {f"can{b}": list(range(1, per_bus + 1)) for b in range(buses)}
    peers: dict[str, can.BusABC] = {}
    emulators: list[MitBusEmulator] = []
    proc: subprocess.Popen[str] | None = None
    if transport == "virtual":
        channels = {name: f"bench-{name}-{uuid.uuid4().hex}" for name in layout}
        peers = {name: can.Bus(interface="virtual", channel=ch) for name, ch in channels.items()}
        emulators = [
            MitBusEmulator(peers[name], ids, MODEL, bitrate=BITRATE, pace=True)
            for name, ids in layout.items()
        ]
        bus_params = {name: {"interface": "virtual", "channel": ch}
                      for name, ch in channels.items()}
    else:
        proc, port = _emulator_process(layout)
        bus_params = {name: {"interface": "socketcand", "channel": name, "port": port}
                      for name in layout}
    joints = [f"j{i}" for i in range(MOTORS)]
    hw = MitHardware("bench", joints, ["position"], ["position", "velocity"], {
        "buses": {name: {**settings, "bitrate": BITRATE, "receive_timeout": 0.05}
                  for name, settings in bus_params.items()},
        "bus": [name for name, ids in layout.items() for _ in ids],
        "ids": [i for ids in layout.values() for i in ids],
        "feedback_timeout": 1.0,
    })
    for emulator in emulators:
        emulator.start()
    try:
        hw.configure()
        hold = hw.activate(time.monotonic_ns())
        command = JointCommand(positions=hold.positions)
        gc.collect()
        gc.freeze()
        cycles = 0
        cpu0 = time.thread_time()
        t0 = time.perf_counter()
        end = t0 + duration_s
        now = time.perf_counter
        clock = time.monotonic_ns
        while now() < end:
            hw.write(clock(), command)
            hw.read(clock())
            cycles += 1
        elapsed = time.perf_counter() - t0
        cpu = time.thread_time() - cpu0
        gc.unfreeze()
        missed = sum(m["missed_replies"] for m in hw.status()["details"]["motors"].values())
    finally:
        hw.shutdown(time.monotonic_ns())
        for emulator in emulators:
            emulator.stop()
        for bus in peers.values():
            bus.shutdown()
        if proc is not None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=10)
    cycle_us = elapsed / max(cycles, 1) * 1e6
    wire_us = max(_wire_us(ids) for ids in layout.values())
    return {
        "bus": "can-mit",
        "transport": transport,
        "bitrate": BITRATE,
        "motors": MOTORS,
        "buses": buses,
        "rate_hz": round(cycles / elapsed, 1),
        "cycle_us": round(cycle_us, 1),
        "wire_us": round(wire_us, 1),
        "ratio": round(cycle_us / wire_us, 3),
        "driver_cpu_us": round(cpu / max(cycles, 1) * 1e6, 1),
        "driver_ratio": round((wire_us + cpu / max(cycles, 1) * 1e6) / wire_us, 3),
        "missed_replies": missed,
    }


def mit_rows(duration_s: float) -> list[dict[str, Any]]:
    """Rows for 6 motors on one bus and on two buses of 3, emulators in this process
    (``virtual``) and in another one (``socketcand``); see the module docstring."""
    return [measure(buses, duration_s, transport)
            for transport in ("virtual", "socketcand") for buses in (1, 2)]


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
    print(f"MIT mode, {MOTORS} motors at {BITRATE // 1000} kbit/s, paced emulators "
          f"(target ratio <= {TARGET_RATIO})")
    print(f"{'transport':>10} {'buses':>5} {'rate Hz':>8} {'cycle us':>8} {'wire us':>7} "
          f"{'ratio':>6} {'driver cpu us':>13} {'wire+cpu':>8} {'missed':>6}")
    for row in rows:
        flag = "" if row["ratio"] <= TARGET_RATIO else "  (over target)"
        print(f"{row['transport']:>10} {row['buses']:>5} {row['rate_hz']:>8.1f} "
              f"{row['cycle_us']:>8.1f} {row['wire_us']:>7.1f} {row['ratio']:>6.3f} "
              f"{row['driver_cpu_us']:>13.1f} {row['driver_ratio']:>8.3f} "
              f"{row['missed_replies']:>6}{flag}")
    for one, two in (rows[0:2], rows[2:4]):
        print(f"{one['transport']}: two buses of 3 vs one of 6: "
              f"{one['cycle_us'] / two['cycle_us']:.2f}x faster (2.00x: perfectly parallel)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
