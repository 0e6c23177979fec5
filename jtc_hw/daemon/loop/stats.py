"""Control-loop timing statistics: constant work per cycle, percentiles only on request.

Theory of operation: the loop calls :meth:`LoopStats.record` once per cycle with how late it woke
(``woke - deadline``), how long the cycle's work took, and how many deadlines were skipped before
it. ``record`` stores the two durations in preallocated ``int64`` ring buffers and updates a few
integer counters: no buffer is allocated (only the interpreter's own short-lived int objects),
nothing is sorted, and the only data-dependent work is two comparisons for the all-time worst
cases. :meth:`LoopStats.snapshot`, called off the hot path (by the publisher a few times a
second, or on request), selects the percentiles from the window (``np.partition``).

Why ring buffers rather than a fixed-bin histogram: the percentiles are exact (the nearest-rank
sample, an actual measured cycle, at any resolution and any range, where bins would quantise a
10 us lateness and a 10 ms stall alike or need a log scale and a range guess), they describe a
sliding window of the most recent cycles (a histogram accumulates since reset unless it also
keeps the samples to subtract), and the memory is small and fixed: two ``int64`` per cycle of
window, 160 kB for 10 s at 1 kHz. The cost of exactness, a selection over the window, is paid
only in ``snapshot()``.

Percentiles use the nearest-rank definition: ``pP`` is the smallest sample with at least P % of
the window at or below it, i.e. ``sorted[ceil(P/100 * n) - 1]``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["LoopStats"]

DEFAULT_WINDOW_S = 10.0
_NO_SAMPLE = -(1 << 63)  # below any int64 sample, so the first record always sets the worst


class LoopStats:
    """Lateness, cost and overrun statistics of a fixed-rate loop over a window of cycles.

    Not synchronised: call :meth:`record` and :meth:`snapshot` from the loop's thread (e.g. take a
    snapshot every N cycles and publish the dict), or accept that a snapshot taken concurrently
    may mix one cycle's old and new values.

    Attributes:
        rate_hz: the loop's nominal rate.
        window: how many of the most recent cycles the percentiles cover.
    """

    def __init__(self, rate_hz: float, window: int | None = None) -> None:
        """Preallocates the ring buffers (``window``: default 10 s of cycles at ``rate_hz``).

        Raises:
            ValueError: ``rate_hz`` is not a positive finite number or ``window`` is not a
                positive integer.
        """
        if isinstance(rate_hz, bool) or not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"LoopStats: rate_hz must be a positive number, got {rate_hz!r}")
        if window is None:
            window = max(1, round(rate_hz * DEFAULT_WINDOW_S))
        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise ValueError(f"LoopStats: window must be a positive integer, got {window!r}")
        self.rate_hz = float(rate_hz)
        self.window = window
        self._lateness: NDArray[np.int64] = np.zeros(window, dtype=np.int64)
        self._cost: NDArray[np.int64] = np.zeros(window, dtype=np.int64)
        self.reset()

    def record(self, lateness_ns: int, cost_ns: int, overruns: int) -> None:
        """Records one cycle; constant time, writes into the preallocated buffers.

        Args:
            lateness_ns: how long after its deadline the cycle started (negative if early).
            cost_ns: how long the cycle's work took (the daemon's loop: everything it did
                between waking and sleeping again).
            overruns: deadlines skipped before this cycle (0 normally).

        Raises:
            OverflowError: a value does not fit in 64 bits.
        """
        i = self._index
        self._lateness[i] = lateness_ns
        self._cost[i] = cost_ns
        i += 1
        self._index = 0 if i == self.window else i
        self._cycles += 1
        if overruns:
            self._overruns += overruns
            self._overrun_cycles += 1
        if lateness_ns > self._worst_lateness:
            self._worst_lateness = lateness_ns
        if cost_ns > self._worst_cost:
            self._worst_cost = cost_ns

    def snapshot(self) -> dict[str, Any]:
        """The statistics as a new JSON-able dict, which later cycles do not change (selecting
        the percentiles happens here, not in :meth:`record`).

        Keys: ``rate_hz``; ``period_us``; ``cycles`` recorded since reset; ``overruns``, the
        deadlines skipped since reset; ``overrun_cycles``, cycles that followed a skip;
        ``window_cycles``, how many cycles the percentiles cover (``min(cycles, window)``);
        ``lateness_us`` and ``cost_us``, each ``{"p50", "p99", "max", "worst"}`` where
        ``p50``/``p99``/``max`` describe the window and ``worst`` is the maximum since reset
        (a spike stays visible after it leaves the window). Durations are microseconds
        (floats); percentiles are ``None`` before the first cycle.
        """
        n = min(self._cycles, self.window)
        return {
            "rate_hz": self.rate_hz,
            "period_us": 1e6 / self.rate_hz,
            "cycles": self._cycles,
            "overruns": self._overruns,
            "overrun_cycles": self._overrun_cycles,
            "window_cycles": n,
            "lateness_us": _summary(self._lateness[:n], self._worst_lateness),
            "cost_us": _summary(self._cost[:n], self._worst_cost),
        }

    def reset(self) -> None:
        """Forgets every cycle (e.g. after start-up, or when a client asks); keeps the buffers."""
        self._index = 0
        self._cycles = 0
        self._overruns = 0
        self._overrun_cycles = 0
        self._worst_lateness = _NO_SAMPLE
        self._worst_cost = _NO_SAMPLE


def _summary(samples: NDArray[np.int64], worst_ns: int) -> dict[str, float | None]:
    n = samples.size
    if n == 0:
        return {"p50": None, "p99": None, "max": None, "worst": None}
    # A selection, not a sort: the loop thread publishes this twice a second, and sorting a
    # 10 s window at 1 kHz took ~0.4 ms of its spare time (partition: a fraction of it).
    ranks = (_rank(50, n), _rank(99, n), n - 1)
    picked = np.partition(samples, ranks)
    return {
        "p50": _us(picked[ranks[0]]),
        "p99": _us(picked[ranks[1]]),
        "max": _us(picked[ranks[2]]),
        "worst": _us(worst_ns),
    }


def _rank(percent: int, n: int) -> int:
    """Index of the nearest-rank ``percent``-th percentile in a sorted array of ``n``."""
    # Integer arithmetic: ceil(percent * n / 100) without float rounding.
    return max(0, -(-percent * n // 100) - 1)


def _us(ns: int | np.int64) -> float:
    return int(ns) / 1000.0
