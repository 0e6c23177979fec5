"""Absolute deadlines on the monotonic clock for a fixed-rate loop.

Theory of operation: deadline ``k`` is ``t0 + k * period_ns`` (``k = 1, 2, ...``), computed from the
anchor each time rather than accumulated, so sleep overshoot and cycle cost never make the loop
drift: a cycle that starts 30 us late sleeps 30 us less before the next one. :meth:`Ticker.wait`
handles three cases, by how far past the next deadline ``d`` the clock already is on entry:

* ``now < d`` (the normal case): sleep until ``d``, return ``(d, woke, 0)``;
* ``d <= now < d + period``: return ``d`` at once, late (``woke - d`` is the lateness); the
  following deadline is still at most one period away, so this catches up without bunching;
* ``now >= d + period`` (a stall of at least one period, e.g. a bus time-out): every deadline
  before ``now`` is skipped and counted, and the first deadline at or after ``now`` is returned,
  after sleeping if it is in the future. The loop never runs the missed cycles back to back to
  catch up: a JTC cycle samples the trajectory at its deadline, and a burst of stale cycles
  would only send a burst of stale commands to the motors.

Sleeping uses ``time.sleep`` on the remaining time; on Linux (Python 3.11+) it is
``clock_nanosleep`` on ``CLOCK_MONOTONIC``. The wake-up error comes from the kernel: the timer
slack (50 us by default for normal tasks, none for ``SCHED_FIFO`` ones) plus scheduling latency.
``spin_ns`` optionally wakes that much early and busy-polls the clock for the rest, trading CPU
time for a tighter wake-up; leave it 0 unless the loop has a core of its own. A sleep that returns
early (a signal, an injected fake) is simply repeated on the remainder.

The clock and the sleep are parameters, so tests drive a fake clock: nothing here assumes more of
the clock than that it never goes backwards (its epoch, its sign and whether two reads may be
equal are irrelevant).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

__all__ = ["Tick", "Ticker"]


class Tick(NamedTuple):
    """What :meth:`Ticker.wait` returns."""

    deadline_ns: int
    """The deadline this cycle belongs to (``t0 + k * period_ns``): the cycle's time ``t_k``."""
    woke_ns: int
    """The clock when ``wait`` returned; ``woke_ns - deadline_ns`` is the lateness."""
    skipped: int
    """Deadlines skipped (never run) since the previous tick; 0 normally."""


class Ticker:
    """Yields absolute deadlines ``t0 + k * period_ns`` and sleeps until each.

    Attributes:
        period_ns, spin_ns: as given (:meth:`__init__`).
        skipped_total: deadlines skipped since construction.
    """

    def __init__(
        self,
        period_ns: int,
        now: Callable[[], int] = time.monotonic_ns,
        sleep: Callable[[float], object] = time.sleep,
        spin_ns: int = 0,
        start_ns: int | None = None,
    ) -> None:
        """Anchors the deadlines at ``start_ns`` (default: the clock now).

        Args:
            period_ns: the loop period in nanoseconds, e.g. ``round(1e9 / update_rate)``.
            now: the clock, in integer nanoseconds; must never go backwards.
            sleep: sleeps for a duration in seconds (may return early: it is repeated).
            spin_ns: the final part of each wait that is busy-polled instead of slept.
            start_ns: the anchor ``t0``; the first deadline is ``t0 + period_ns``.

        Raises:
            ValueError: ``period_ns`` is not a positive integer, or ``spin_ns`` is not a
                non-negative integer.
        """
        if isinstance(period_ns, bool) or not isinstance(period_ns, int) or period_ns <= 0:
            raise ValueError(f"Ticker: period_ns must be a positive integer, got {period_ns!r}")
        if isinstance(spin_ns, bool) or not isinstance(spin_ns, int) or spin_ns < 0:
            raise ValueError(f"Ticker: spin_ns must be a non-negative integer, got {spin_ns!r}")
        self.period_ns = period_ns
        self.spin_ns = spin_ns
        self._now = now
        self._sleep = sleep
        self._t0 = now() if start_ns is None else start_ns
        self._k = 0
        self.skipped_total = 0

    def wait(self) -> Tick:
        """Waits for the next deadline, skipping those already missed by a period or more
        (the module docstring has the three cases).

        Raises:
            Exception: whatever the injected ``now`` or ``sleep`` raises (``time.sleep`` raises
                ``KeyboardInterrupt`` or a signal handler's exception when interrupted).
        """
        period = self.period_ns
        k = self._k + 1
        deadline = self._t0 + k * period
        now = self._now()
        skipped = 0
        late = now - deadline
        if late >= period:
            # Skip every deadline strictly before now: ceil(late / period) of them.
            skipped = -(-late // period)
            k += skipped
            deadline = self._t0 + k * period
            self.skipped_total += skipped
        spin = self.spin_ns
        while deadline - now > spin:
            self._sleep((deadline - now - spin) / 1e9)
            now = self._now()
        while now < deadline:
            now = self._now()
        self._k = k
        return Tick(deadline, now, skipped)
