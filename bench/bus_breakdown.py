"""Helpers of ``bench/bus_rate.py``: the per-cycle breakdown and the busy neighbour.

Breakdown (``--breakdown``)
---------------------------
Each measured cycle is split into:

- ``wire``: the cycle's wire time, computed from its frames / packets by the bench (a constant
  per configuration);
- ``sdk``: the time spent inside the third-party calls at the boundary of our driver
  (dynamixel-sdk's packet handler, python-can's ``send`` / ``recv``), timed by wrapping those
  calls on the driver's own objects, in the bench only (the driver is not changed for it).
  ``sdk_cpu`` is the CPU the cycling thread spent in them, ``sdk`` their wall time (which
  includes blocking waits inside them: python-can's ``recv`` waits in ``select``). Our
  callbacks run by the SDK (the Dynamixel port's ``writePort``, ``updateCRC``) count as SDK time;
- ``driver``: our own driver code, the rest of the cycling thread's CPU (``cpu - sdk_cpu``);
- ``blocked``: the rest of the wall time, the thread not running: waiting for the wire and the
  emulator, and waiting to be scheduled again once woken (``cycle - cpu``).

The probes cost time themselves (two clock reads around each boundary call, one of them a
system call): ``probe_us`` estimates that cost per cycle, calibrated on a no-op; compare rows
taken with the same flags.

Neighbour (``--neighbour``)
---------------------------
:func:`neighbour` starts one busy process (a Python busy loop at normal priority, as
``tools/cpu-hog`` does) for the duration of a measurement and stops it (by its pid) after.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

NEIGHBOUR_MODES = ("off", "on", "both")


def neighbour_modes(mode: str) -> list[bool]:
    """The runs one configuration gets: idle, with the neighbour, or both alternated."""
    return {"off": [False], "on": [True], "both": [False, True]}[mode]


def _spin() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    # Forked from a bench that may run at SCHED_FIFO (bus_rate --priority): a neighbour is an
    # ordinary process.
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    x = 0
    while True:
        x = (x + 1) & 0xFFFF


@contextmanager
def neighbour(active: bool) -> Iterator[int | None]:
    """One busy process at normal priority while the block runs (``active``); yields its pid.

    Started before the measurement's emulators and driver, stopped (by its pid) after.
    """
    if not active:
        yield None
        return
    proc = multiprocessing.get_context("fork").Process(target=_spin, daemon=True)
    proc.start()
    try:
        yield proc.pid
    finally:
        proc.terminate()
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
            proc.join(10.0)


class Breakdown:
    """Per-cycle samples of wall time, thread CPU and time inside the wrapped boundary calls.

    Usage: :meth:`wrap` the third-party methods on the driver's objects once, then call
    :meth:`begin` before and :meth:`end` after each measured cycle.
    """

    def __init__(self) -> None:
        self._wall = time.perf_counter_ns
        self._cpu = time.thread_time_ns
        self._sdk_wall = 0
        self._sdk_cpu = 0
        self._calls = 0
        self._t0 = self._c0 = 0
        self.cycles: list[int] = []
        self.cpus: list[int] = []
        self.sdk_walls: list[int] = []
        self.sdk_cpus: list[int] = []
        self.calls: list[int] = []
        self.probe_ns = self._calibrate()

    def wrap(self, obj: Any, *names: str) -> None:
        """Time every call of ``obj.<name>`` (an instance attribute shadowing the method)."""
        for name in names:
            setattr(obj, name, self._timed(getattr(obj, name)))

    def _timed(self, call: Callable[..., Any]) -> Callable[..., Any]:
        wall, cpu = self._wall, self._cpu

        def timed(*args: Any, **kwargs: Any) -> Any:
            c0 = cpu()
            t0 = wall()
            try:
                return call(*args, **kwargs)
            finally:
                t1 = wall()
                self._sdk_cpu += cpu() - c0
                self._sdk_wall += t1 - t0
                self._calls += 1

        return timed

    def _calibrate(self) -> float:
        """The probes' own cost per wrapped call, ns (a no-op timed many times)."""
        noop = self._timed(lambda: None)
        plain: Callable[[], None] = lambda: None  # noqa: E731
        rounds = 2000
        t0 = time.perf_counter_ns()
        for _ in range(rounds):
            plain()
        t1 = time.perf_counter_ns()
        for _ in range(rounds):
            noop()
        t2 = time.perf_counter_ns()
        self._sdk_wall = self._sdk_cpu = self._calls = 0
        return max(0.0, ((t2 - t1) - (t1 - t0)) / rounds)

    def begin(self) -> None:
        self._sdk_wall = self._sdk_cpu = self._calls = 0
        self._c0 = self._cpu()
        self._t0 = self._wall()

    def end(self) -> None:
        t1 = self._wall()
        self.cpus.append(self._cpu() - self._c0)
        self.cycles.append(t1 - self._t0)
        self.sdk_walls.append(self._sdk_wall)
        self.sdk_cpus.append(self._sdk_cpu)
        self.calls.append(self._calls)

    def summary(self, wire_us: float) -> dict[str, Any]:
        """p50 per part, us, and the p50 of each cycle's ratio to the wire time."""
        if not self.cycles:
            return {}

        def p50(values: list[int] | list[float]) -> float:
            return round(statistics.median(values) / 1e3, 1)

        drivers = [c - s for c, s in zip(self.cpus, self.sdk_cpus, strict=True)]
        blocked = [w - c for w, c in zip(self.cycles, self.cpus, strict=True)]
        return {
            "cycles": len(self.cycles),
            "cycle_p50_us": p50(self.cycles),
            "cycle_p99_us": round(_quantile(self.cycles, 0.99) / 1e3, 1),
            "ratio_p50": round(statistics.median(self.cycles) / 1e3 / wire_us, 3),
            "wire_us": round(wire_us, 1),
            "sdk_p50_us": p50(self.sdk_walls),
            "sdk_cpu_p50_us": p50(self.sdk_cpus),
            "driver_cpu_p50_us": p50(drivers),
            "blocked_p50_us": p50(blocked),
            "calls_per_cycle": statistics.median(self.calls),
            "probe_us": round(statistics.median(self.calls) * self.probe_ns / 1e3, 1),
        }


def _quantile(values: list[int], q: float) -> float:
    ordered = sorted(values)
    return float(ordered[min(len(ordered) - 1, int(q * len(ordered)))])


def breakdown_line(label: str, b: dict[str, Any]) -> str:
    """One printed line of a row's breakdown (p50 per part)."""
    return (f"{label:<21} p50: cycle {b['cycle_p50_us']:.1f} us = wire {b['wire_us']:.1f} "
            f"x {b['ratio_p50']:.2f}; sdk {b['sdk_p50_us']:.1f} us (cpu "
            f"{b['sdk_cpu_p50_us']:.1f}), driver cpu {b['driver_cpu_p50_us']:.1f} us, blocked "
            f"{b['blocked_p50_us']:.1f} us; {b['calls_per_cycle']:g} calls, probes "
            f"~{b['probe_us']:.1f} us")
