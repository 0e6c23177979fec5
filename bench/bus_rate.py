#!/usr/bin/env python3
"""Bus cycle rate: the real driver's read + write cycle against paced emulated motors.

Dynamixel: six XM430-W350 at 1, 2 and 4 Mbit/s. The emulator runs in its own process
(``python -m jtc_hw.drivers.dynamixel.emulator --pace``) so that it holds every reply back to the
wire time of a real bus and does not share this process's interpreter lock. The real
``DynamixelHardware`` (real SDK, real pty) runs ``read`` (one Sync Read of the present block) and
``write`` (one Sync Write of Goal Position) back to back for ``--duration`` seconds.

Columns: ``rate_hz`` achieved cycles per second; ``cycle_us`` the mean cycle; ``wire_us`` the
cycle's wire time from the Protocol 2.0 packet sizes at 10 bits per byte: the Sync Read
instruction, the six status packets (or the one Fast Sync Read status) and the Sync Write
instruction (``packets.sync_read_cycle_bytes`` + ``sync_write_bytes``); ``delay_us`` the
servos' return delays (each servo waits its Return Delay Time before answering; 0 here);
``ratio`` (cycle_us - delay_us) / wire_us; ``driver_cpu_us`` this thread's CPU time per cycle
(the driver's own cost, excluding the emulator's) and ``driver_ratio`` (wire_us +
driver_cpu_us) / wire_us.

Target (the issue): at 4 Mbit/s a cycle costs at most 1.3 x its wire time plus the servos'
return delays, i.e. ``cycle_us <= 1.3 * wire_us + delay_us`` (``ratio <= 1.3``); a verdict line
per bit rate follows the table.

``--profile`` also runs each configuration unpaced (the emulator answers at once) and splits the
paced cycle into read and write: what is left over the wire time is the software (SDK, Python,
pty round trips, emulator) cost.

CAN rows (``--bus can-mit`` / ``can-cia402``) come from ``bench/bus_rate_can.py``
(``mit_rows(duration_s)``) and ``bench/bus_rate_cia402.py`` (``cia402_rows(duration_s)``) when
those files exist; otherwise those buses are reported as not available.

Feetech rows (``--bus feetech``, issue 26) come from ``bench/bus_rate_feetech.py``
(``feetech_rows``): six STS3215 at 1 Mbit/s on ``jtc-hw emulate feetech``, our
``FeetechHardware`` (row ``feetech jtc_hw``) beside a hand-written ``scservo_sdk`` loop doing the
same two transactions, as a LeRobot user runs them (row ``feetech sdk loop``); the target
``ratio <= 1.3`` is our row's, with a verdict line that names the SDK loop's figure too.

``--breakdown`` splits each measured cycle into wire time, time inside dynamixel-sdk's /
python-can's calls, our own driver code's CPU and time blocked, and prints the p50 of each
(keys under ``breakdown`` in ``--json`` rows; bench/bus_breakdown.py says how they are taken).
``--neighbour`` runs beside one busy Python process that the bench starts for each measurement
and stops after (rows say ``neighbour: true``); ``--neighbour both`` alternates an idle run and
a run with the neighbour for each configuration, so their ratios compare in one sitting.

``--priority N`` runs the driver as the daemon runs its loop with ``daemon.realtime.priority:
N`` (SCHED_FIFO), and the emulators at the same priority: they stand for the motors, whose
electronics share no CPU with the robot's computer, so a neighbour must not slow the replies
down either. The neighbour stays at normal priority. Rows say ``priority``.

Usage:  python bench/bus_rate.py [--duration 3] [--bus dynamixel can-mit can-cia402 feetech]
                                 [--bitrates 1000000 2000000 4000000] [--profile] [--json]
                                 [--breakdown] [--neighbour [on|both]] [--priority N]
"""

from __future__ import annotations

import argparse
import gc
import importlib.util
import json
import math
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

from jtc_hw.controller.joints import JointCommand  # noqa: E402
from jtc_hw.drivers.dynamixel.control_table import PRESENT_BLOCK_SIZE  # noqa: E402
from jtc_hw.drivers.dynamixel.hardware import DynamixelHardware  # noqa: E402
from jtc_hw.drivers.dynamixel.packets import (  # noqa: E402
    sync_read_cycle_bytes,
    sync_write_bytes,
    wire_time_s,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bus_breakdown import (  # noqa: E402
    NEIGHBOUR_MODES,
    Breakdown,
    breakdown_line,
    neighbour,
    neighbour_modes,
)

MOTORS = 6
BITRATES = (1_000_000, 2_000_000, 4_000_000)
TARGET_RATIO = 1.3
RETURN_DELAY_US = 0  # written to the servos by the driver (return_delay_time_us)
SDK_CALLS = ("syncReadTx", "rxPacket", "readTxRx", "writeTxRx", "ping", "reboot")
"""The dynamixel-sdk packet handler's methods our bus module calls (the SDK boundary)."""
CAN_SOURCES = {
    "can-mit": ("bus_rate_can.py", "mit_rows"),
    "can-cia402": ("bus_rate_cia402.py", "cia402_rows"),
}
FEETECH_SOURCE = ("bus_rate_feetech.py", "feetech_rows")
BUSES = ("dynamixel", *CAN_SOURCES, "feetech")


@contextmanager
def emulator_process(bitrate: int, pace: bool) -> Iterator[str]:
    """A paced emulator of MOTORS servos in a subprocess; yields the device path."""
    with tempfile.TemporaryDirectory() as tmp:
        link = os.path.join(tmp, "dxl")
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
        argv = [sys.executable, "-m", "jtc_hw.drivers.dynamixel.emulator",
                "--ids", f"1-{MOTORS}", "--baud", str(bitrate), "--link", link]
        if pace:
            argv.append("--pace")
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                env=env, text=True)
        try:
            assert proc.stdout is not None
            path = proc.stdout.readline().strip()  # printed once the pty is served
            if not path:
                raise RuntimeError(f"the emulator did not start (exit {proc.wait()})")
            yield path
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def wire_us(bitrate: int, fast: bool = False) -> float:
    """Wire time of one read + write cycle of MOTORS servos (return delays excluded), us.

    Sync Read instruction + the status packets (six, or one Fast Sync Read status) + the Sync
    Write of Goal Position (4 bytes per servo), 10 bits per byte (8N1).
    """
    sent, received = sync_read_cycle_bytes(MOTORS, PRESENT_BLOCK_SIZE, fast)
    written = sync_write_bytes(MOTORS, 4)
    return wire_time_s(sent + received + written, bitrate) * 1e6


def return_delays_us() -> float:
    """The servos' return delays in one cycle (each answers after its own), us."""
    return MOTORS * RETURN_DELAY_US


def measure(bitrate: int, duration_s: float, pace: bool,
            health_period_s: float | None = None,
            breakdown: Breakdown | None = None, busy: bool = False) -> dict[str, float]:
    """Run the driver's cycle for ``duration_s``; mean cycle, read and write times, us
    (``health_period_s``: the driver's health reads, ``None``: its default; ``breakdown``:
    sample each cycle and the SDK's calls into it; ``busy``: with a busy neighbour process)."""
    health = {} if health_period_s is None else {"health_period_s": health_period_s}
    with neighbour(busy), emulator_process(bitrate, pace) as device:
        joints = [f"joint{i}" for i in range(1, MOTORS + 1)]
        hw = DynamixelHardware(
            "bench", joints, ["position"], ["position", "velocity"],
            {"port": device, "baud_rate": bitrate, "ids": list(range(1, MOTORS + 1)),
             "offset": -math.pi, "return_delay_time_us": RETURN_DELAY_US,
             "timeout_ms": 50.0, "latency_timer_warn": False,
             # The servos' Bus Watchdog: long, so that a stall of this (not real-time)
             # process on a busy machine does not stop them mid-run (as bus_rate_cia402.py).
             "watchdog_s": 1.0, **health},
        )
        hw.configure()
        try:
            held = hw.activate(time.monotonic_ns())
            assert held.positions is not None
            command = JointCommand(positions=held.positions)
            clock = time.perf_counter_ns
            for _ in range(20):  # warm up
                hw.read(time.monotonic_ns())
                hw.write(time.monotonic_ns(), command)
            if breakdown is not None:
                assert hw.bus is not None
                # The calls our bus module makes into dynamixel-sdk's packet handler.
                breakdown.wrap(hw.bus._handler, *SDK_CALLS)
            gc.collect()
            gc.disable()
            read_ns = write_ns = worst_ns = 0
            cycles = 0
            cpu0 = time.thread_time_ns()
            start = clock()
            end = start + int(duration_s * 1e9)
            now = start
            while now < end:
                if breakdown is not None:
                    breakdown.begin()
                t0 = clock()
                hw.read(t0)
                t1 = clock()
                hw.write(t1, command)
                now = clock()
                if breakdown is not None:
                    breakdown.end()
                read_ns += t1 - t0
                write_ns += now - t1
                worst_ns = max(worst_ns, now - t0)
                cycles += 1
            cpu_ns = time.thread_time_ns() - cpu0
            gc.enable()
            elapsed = now - start
        finally:
            hw.shutdown(time.monotonic_ns())
    return {
        "cycles": cycles,
        "cycle_us": elapsed / cycles / 1e3,
        "read_us": read_ns / cycles / 1e3,
        "write_us": write_ns / cycles / 1e3,
        "driver_cpu_us": cpu_ns / cycles / 1e3,
        "max_cycle_us": worst_ns / 1e3,
    }


def dynamixel_rows(duration_s: float, bitrates: list[int], profile: bool,
                   health_period_s: float | None = None, breakdown: bool = False,
                   neighbours: list[bool] | None = None) -> list[dict[str, Any]]:
    """A row per bit rate and neighbour mode (``neighbours``: idle ``False`` and/or with a busy
    neighbour ``True``, run in that order for each bit rate; default idle only)."""
    rows = []
    for bitrate in bitrates:
        for busy in neighbours or [False]:
            rows.append(_dynamixel_row(bitrate, duration_s, profile, health_period_s,
                                       breakdown, busy))
    return rows


def _dynamixel_row(bitrate: int, duration_s: float, profile: bool,
                   health_period_s: float | None, breakdown: bool,
                   busy: bool) -> dict[str, Any]:
    samples = Breakdown() if breakdown else None
    paced = measure(bitrate, duration_s, pace=True, health_period_s=health_period_s,
                    breakdown=samples, busy=busy)
    wire = wire_us(bitrate)
    delays = return_delays_us()
    row: dict[str, Any] = {
        "bus": "dynamixel",
        "bitrate": bitrate,
        "motors": MOTORS,
        "buses": 1,
        "rate_hz": round(1e6 / paced["cycle_us"], 1),
        "cycle_us": round(paced["cycle_us"], 1),
        "wire_us": round(wire, 1),
        "ratio": round((paced["cycle_us"] - delays) / wire, 2),
        "delay_us": round(delays, 1),
        "target_us": round(TARGET_RATIO * wire + delays, 1),
        "target_met": paced["cycle_us"] <= TARGET_RATIO * wire + delays,
        # The driver's own CPU per cycle (SDK, Python, numpy): what a real bus adds to the
        # wire time at most if nothing overlaps, whatever the emulator costs.
        "driver_cpu_us": round(paced["driver_cpu_us"], 1),
        "driver_ratio": round((wire + paced["driver_cpu_us"]) / wire, 2),
        # The slowest cycle: one with a health read (a third Sync Read) if any.
        "max_cycle_us": round(paced["max_cycle_us"], 1),
        "health_period_s": health_period_s,
        "neighbour": busy,
    }
    if samples is not None:
        row["breakdown"] = samples.summary(wire)
    if profile:
        unpaced = measure(bitrate, duration_s, pace=False, busy=busy)
        row["profile"] = {
            "read_us": round(paced["read_us"], 1),
            "write_us": round(paced["write_us"], 1),
            "unpaced_cycle_us": round(unpaced["cycle_us"], 1),
            "unpaced_read_us": round(unpaced["read_us"], 1),
            "unpaced_write_us": round(unpaced["write_us"], 1),
        }
    return row


def _bench_module(bus: str, filename: str) -> Any:
    """Another bench module of this folder, loaded by path, or why it cannot be (a str)."""
    path = Path(__file__).resolve().parent / filename
    if not path.exists():
        return f"{bus}: bench/{filename} is not available"
    spec = importlib.util.spec_from_file_location(path.stem, path)
    if spec is None or spec.loader is None:
        return f"{bus}: cannot load bench/{filename}"
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def can_rows(bus: str, duration_s: float, breakdown: bool = False,
             neighbours: list[bool] | None = None) -> list[dict[str, Any]] | str:
    """Rows from another helper's bench module, or why there are none."""
    filename, function = CAN_SOURCES[bus]
    module = _bench_module(bus, filename)
    if isinstance(module, str):
        return module
    produce: Callable[..., list[dict[str, Any]]] = getattr(module, function)
    if not breakdown and neighbours is None:
        return list(produce(duration_s))
    return list(produce(duration_s, breakdown=breakdown, neighbours=neighbours or [False]))


def feetech_rows(duration_s: float, breakdown: bool, neighbours: list[bool],
                 priority: int) -> tuple[list[dict[str, Any]], list[str]]:
    """The Feetech rows (ours, then the SDK loop, per neighbour mode) and their verdict lines,
    or no rows and why (bench/bus_rate_feetech.py needs ``scservo_sdk``: ``jtc_hw[feetech]``)."""
    try:
        module = _bench_module("feetech", FEETECH_SOURCE[0])
    except ImportError as exc:
        return [], [f"feetech: {exc}; install the extra: pip install 'jtc_hw[feetech]'"]
    if isinstance(module, str):
        return [], [module]
    rows = list(getattr(module, FEETECH_SOURCE[1])(duration_s, breakdown=breakdown,
                                                   neighbours=neighbours, priority=priority))
    return rows, list(module.verdicts(rows))


def print_table(rows: list[dict[str, Any]], notes: list[str],
                verdicts: Sequence[str] = ()) -> None:
    print(f"{'bus':<21} {'bit/s':>9} {'motors':>6} {'buses':>5} {'nb':>3} {'rate Hz':>9} "
          f"{'cycle us':>9} {'wire us':>9} {'ratio':>6} {'cpu us':>7} {'cpu ratio':>9}")
    for r in rows:
        flag = ""
        if r["bus"] == "dynamixel" and r["bitrate"] == 4_000_000:
            flag = "  ok" if r["target_met"] else f"  above target {TARGET_RATIO}"
        if r["bus"] == "feetech" and r["client"] == "jtc_hw":
            flag = "  ok" if r["target_met"] else f"  above target {TARGET_RATIO}"
        label = r["bus"] + (f"/{r['transport']}" if "transport" in r else "")
        label += f" {r['client']}" if "client" in r else ""
        busy = "yes" if r.get("neighbour") else "no"
        print(f"{label:<21} {r['bitrate']:>9} {r['motors']:>6} {r['buses']:>5} {busy:>3} "
              f"{r['rate_hz']:>9.1f} {r['cycle_us']:>9.1f} {r['wire_us']:>9.1f} "
              f"{r['ratio']:>6.2f} {r.get('driver_cpu_us', float('nan')):>7.1f} "
              f"{r.get('driver_ratio', float('nan')):>9.2f}{flag}")
        if r.get("breakdown"):
            print(breakdown_line("", r["breakdown"]))
        if "profile" in r:
            p = r["profile"]
            print(f"{'':<21} paced: read {p['read_us']:.1f} us + write {p['write_us']:.1f} us; "
                  f"unpaced cycle {p['unpaced_cycle_us']:.1f} us (read {p['unpaced_read_us']:.1f}"
                  f" + write {p['unpaced_write_us']:.1f})")
    for r in rows:
        if r["bus"] == "dynamixel":
            print(verdict(r))
    for line in verdicts:
        print(line)
    for note in notes:
        print(note)


def verdict(row: dict[str, Any]) -> str:
    """One line: the Dynamixel row against the target (the issue sets it at 4 Mbit/s)."""
    met = row["target_met"]
    scope = "target" if row["bitrate"] == 4_000_000 else "same bound (not the issue's target)"
    return (
        f"{row['bitrate'] / 1e6:g} Mbit/s{' with a neighbour' if row.get('neighbour') else ''}"
        f" {scope}: cycle {row['cycle_us']:.1f} us "
        f"{'<=' if met else '>'} {TARGET_RATIO} x wire {row['wire_us']:.1f} us + return delays "
        f"{row['delay_us']:.1f} us = {row['target_us']:.1f} us (ratio {row['ratio']:.2f}): "
        f"{'met' if met else 'NOT met'}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        epilog="CAN buses are measured by bench/bus_rate_can.py (mit_rows) and "
        "bench/bus_rate_cia402.py (cia402_rows), Feetech by bench/bus_rate_feetech.py "
        "(feetech_rows), imported only if those files exist.",
    )
    parser.add_argument("--duration", type=float, default=3.0,
                        help="seconds per configuration (default 3)")
    parser.add_argument("--bus", nargs="+", default=list(BUSES), choices=BUSES,
                        help="buses to measure (default: all); feetech: six STS3215 at 1 "
                        "Mbit/s, our driver then a hand-written scservo_sdk loop (LeRobot's "
                        "way) doing the same Sync Read + Sync Write (bench/bus_rate_feetech.py)")
    parser.add_argument("--bitrates", nargs="+", type=int, default=list(BITRATES),
                        help="Dynamixel bit rates (default 1000000 2000000 4000000)")
    parser.add_argument("--profile", action="store_true",
                        help="also split the cycle into read / write and run it unpaced")
    parser.add_argument("--health-period-s", type=float, default=None,
                        help="Dynamixel: the driver's health_period_s (default: the driver's; "
                        "60 all but switches the health reads off, for a comparison)")
    parser.add_argument("--breakdown", action="store_true",
                        help="split each cycle into wire, SDK / python-can and our driver "
                        "code; print the p50 of each (bench/bus_breakdown.py)")
    parser.add_argument("--neighbour", nargs="?", const="on", default="off",
                        choices=NEIGHBOUR_MODES,
                        help="run beside one busy process the bench starts and stops "
                        "('on', the default when given bare), or 'both': an idle run then a "
                        "run with the neighbour, for each configuration")
    parser.add_argument("--priority", type=int, default=0, metavar="N",
                        help="SCHED_FIFO priority of the driver (or the SDK loop) and the "
                        "emulators (the daemon's daemon.realtime.priority; default 0: normal "
                        "scheduling)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    if args.priority:
        try:  # inherited by the emulators this process starts; the neighbour resets its own
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
        except (OSError, ValueError) as exc:
            parser.error(f"--priority {args.priority}: {exc} (needs CAP_SYS_NICE or root)")
    neighbours = neighbour_modes(args.neighbour)
    rows: list[dict[str, Any]] = []
    notes: list[str] = []
    verdicts: list[str] = []
    for bus in args.bus:
        first = len(rows)
        if bus == "feetech":
            got_rows, lines = feetech_rows(args.duration, args.breakdown, neighbours,
                                           args.priority)
            rows += got_rows
            (verdicts if got_rows else notes).extend(lines)
        elif bus == "dynamixel":
            rows += dynamixel_rows(args.duration, args.bitrates, args.profile,
                                   args.health_period_s, args.breakdown, neighbours)
        else:
            got = can_rows(bus, args.duration, args.breakdown,
                           None if args.neighbour == "off" else neighbours)
            if isinstance(got, str):
                notes.append(got)
            else:
                rows += got
        for row in rows[first:]:
            row["priority"] = args.priority
    if args.json:
        for row in rows:
            print(json.dumps(row))
        for row in rows:
            if row["bus"] == "dynamixel":
                print(verdict(row), file=sys.stderr)
        for line in verdicts:
            print(line, file=sys.stderr)
        for note in notes:
            print(note, file=sys.stderr)
    else:
        if args.priority:
            print(f"driver and emulators at SCHED_FIFO priority {args.priority}; the neighbour "
                  "at normal priority")
        print_table(rows, notes, verdicts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
