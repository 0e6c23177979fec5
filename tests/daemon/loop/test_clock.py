"""Absolute-deadline ticker driven by a fake clock (jtc_hw.daemon.loop.clock); no wall time
anywhere."""

from __future__ import annotations

import pytest

from jtc_hw.daemon.loop.clock import Tick, Ticker

MS = 1_000_000
US = 1_000


class FakeClock:
    """A monotonic nanosecond clock that only moves when told to.

    ``sleep`` advances it by the requested time plus ``oversleep_ns`` (a kernel's wake-up error),
    or by only ``early_fraction`` of it (an interrupted sleep). Each read advances it by
    ``read_cost_ns`` (so busy-polling terminates, as on a real clock).
    """

    def __init__(self, t_ns: int, oversleep_ns: int = 0, read_cost_ns: int = 0) -> None:
        self.t = t_ns
        self.oversleep_ns = oversleep_ns
        self.read_cost_ns = read_cost_ns
        self.early_fraction: float | None = None
        self.sleeps: list[int] = []  # requested durations, rounded to ns
        self.reads = 0

    def now(self) -> int:
        self.reads += 1
        t = self.t
        self.t += self.read_cost_ns
        return t

    def sleep(self, seconds: float) -> None:
        assert seconds > 0, "never asked to sleep for nothing or a negative time"
        ns = round(seconds * 1e9)
        self.sleeps.append(ns)
        if self.early_fraction is not None:
            self.t += max(1, int(ns * self.early_fraction))
        else:
            self.t += ns + self.oversleep_ns

    def work(self, ns: int) -> None:
        self.t += ns


def ticker(clock: FakeClock, period_ns: int = MS, **kwargs: int) -> Ticker:
    return Ticker(period_ns, now=clock.now, sleep=clock.sleep, **kwargs)


def test_exact_deadlines_from_the_anchor() -> None:
    clock = FakeClock(5_000 * MS)
    t = ticker(clock)
    ticks = [t.wait() for _ in range(5)]
    assert ticks == [Tick(5_000 * MS + k * MS, 5_000 * MS + k * MS, 0) for k in range(1, 6)]
    assert clock.sleeps == [MS] * 5


def test_sleep_is_the_remainder_after_the_cycle_cost() -> None:
    clock = FakeClock(0)
    t = ticker(clock, period_ns=10 * MS)
    t.wait()
    for cost in [1 * MS, 3 * MS, 9 * MS + 999_999]:
        clock.work(cost)
        tick = t.wait()
        assert tick.woke_ns == tick.deadline_ns
    assert clock.sleeps == [10 * MS, 9 * MS, 7 * MS, 1]


def test_oversleep_does_not_drift() -> None:
    clock = FakeClock(0, oversleep_ns=70 * US)
    t = ticker(clock)
    ticks = [t.wait() for _ in range(1000)]
    assert [tick.deadline_ns for tick in ticks] == [k * MS for k in range(1, 1001)]
    assert all(tick.woke_ns - tick.deadline_ns == 70 * US for tick in ticks)
    # The first sleep is a whole period, every later one is shortened by the overshoot.
    assert clock.sleeps == [MS] + [MS - 70 * US] * 999


def test_late_by_less_than_a_period_runs_at_once_without_skipping() -> None:
    clock = FakeClock(0)
    t = ticker(clock)
    t.wait()  # deadline 1 ms
    clock.work(MS + 400 * US)  # now 2.4 ms: the 2 ms deadline is 0.4 ms late
    sleeps = len(clock.sleeps)
    assert t.wait() == Tick(2 * MS, 2 * MS + 400 * US, 0)
    assert len(clock.sleeps) == sleeps  # did not sleep
    assert t.wait() == Tick(3 * MS, 3 * MS, 0)  # and the next one is on time again
    assert clock.sleeps[-1] == 600 * US


def test_long_stall_skips_and_never_bunches() -> None:
    clock = FakeClock(0)
    t = ticker(clock)
    t.wait()  # 1 ms
    clock.work(3 * MS + 500 * US)  # stall until 4.5 ms: 2, 3, 4 ms all missed
    tick = t.wait()
    assert tick == Tick(5 * MS, 5 * MS, 3)
    assert clock.sleeps[-1] == 500 * US
    assert t.skipped_total == 3
    # Afterwards, one cycle per period again: no burst of catch-up cycles.
    later = [t.wait() for _ in range(3)]
    assert later == [Tick(k * MS, k * MS, 0) for k in (6, 7, 8)]


def test_stall_of_exactly_one_period_runs_the_current_deadline_now() -> None:
    clock = FakeClock(0)
    t = ticker(clock)
    t.wait()  # 1 ms
    clock.work(2 * MS)  # now 3 ms: the 2 ms deadline is a full period late, 3 ms is due now
    sleeps = len(clock.sleeps)
    assert t.wait() == Tick(3 * MS, 3 * MS, 1)
    assert len(clock.sleeps) == sleeps


@pytest.mark.parametrize(
    ("stall_ns", "expected"),
    [
        (MS - 1, Tick(2 * MS, 2 * MS, 0)),  # now 1 ns before the deadline: sleeps 1 ns
        (MS, Tick(2 * MS, 2 * MS, 0)),  # exactly at the deadline: on time, no sleep
        (2 * MS - 1, Tick(2 * MS, 3 * MS - 1, 0)),  # late by a period minus 1 ns: runs late
        (2 * MS, Tick(3 * MS, 3 * MS, 1)),  # late by exactly a period: skip one
        (2 * MS + 1, Tick(4 * MS, 4 * MS, 2)),  # 1 ns more: 2 and 3 ms missed, sleep to 4
        (100 * MS, Tick(101 * MS, 101 * MS, 99)),
    ],
)
def test_skip_boundaries(stall_ns: int, expected: Tick) -> None:
    clock = FakeClock(0)
    t = ticker(clock)
    t.wait()  # at 1 ms
    clock.work(stall_ns)
    tick = t.wait()
    assert (tick.deadline_ns, tick.skipped) == (expected.deadline_ns, expected.skipped)
    assert tick.woke_ns == max(expected.deadline_ns, MS + stall_ns)


def test_lateness_is_woke_minus_deadline_through_a_mixed_run() -> None:
    clock = FakeClock(0)
    t = ticker(clock, period_ns=4 * MS)
    costs = [MS, 5 * MS, MS, 13 * MS, 0, 0]
    out = []
    for cost in costs:
        tick = t.wait()
        out.append((tick.deadline_ns // MS, (tick.woke_ns - tick.deadline_ns) // MS, tick.skipped))
        clock.work(cost)
    assert out == [(4, 0, 0), (8, 0, 0), (12, 1, 0), (16, 0, 0), (32, 0, 3), (36, 0, 0)]
    assert t.skipped_total == 3


def test_early_return_from_sleep_is_repeated() -> None:
    clock = FakeClock(0)
    clock.early_fraction = 0.5
    t = ticker(clock, period_ns=8 * US)
    tick = t.wait()
    assert tick.deadline_ns == 8 * US
    assert tick.woke_ns >= tick.deadline_ns
    assert clock.sleeps[:3] == [8 * US, 4 * US, 2 * US]


def test_spin_sleeps_short_then_polls_to_the_deadline() -> None:
    clock = FakeClock(0, read_cost_ns=30 * US)
    t = ticker(clock, spin_ns=200 * US, start_ns=0)
    reads = clock.reads
    tick = t.wait()
    # Read at 0 (clock -> 30 us), slept 800 us (-> 830 us), then polled at 830, 860, ... 1010.
    assert clock.sleeps == [800 * US]
    assert tick.deadline_ns == MS
    assert tick.woke_ns == 1010 * US
    assert clock.reads - reads == 1 + 7


def test_spin_without_sleep_when_within_the_spin_window() -> None:
    clock = FakeClock(0, read_cost_ns=100 * US)
    t = ticker(clock, spin_ns=2 * MS, start_ns=0)
    tick = t.wait()
    assert clock.sleeps == []
    assert tick.woke_ns >= tick.deadline_ns == MS


@pytest.mark.parametrize("origin", [0, -(10**15), 2**62, 123_456_789])
def test_any_clock_epoch(origin: int) -> None:
    clock = FakeClock(origin)
    t = ticker(clock, period_ns=3)
    ticks = [t.wait() for _ in range(4)]
    assert [tick.deadline_ns - origin for tick in ticks] == [3, 6, 9, 12]
    clock.work(10)
    assert t.wait() == Tick(origin + 24, origin + 24, 3)


def test_clock_that_reads_equal_values_repeatedly() -> None:
    # Monotonic, not strictly increasing: reads only move when something sleeps or works.
    clock = FakeClock(7)
    t = ticker(clock, period_ns=5)
    assert [t.wait() for _ in range(3)] == [Tick(12, 12, 0), Tick(17, 17, 0), Tick(22, 22, 0)]


def test_explicit_anchor() -> None:
    clock = FakeClock(50 * MS)
    t = ticker(clock, start_ns=40 * MS)
    assert t.wait() == Tick(50 * MS, 50 * MS, 9)  # anchored in the past: 41..49 ms skipped
    assert t.skipped_total == 9


def test_anchor_defaults_to_the_clock_at_construction() -> None:
    clock = FakeClock(42)
    t = ticker(clock, period_ns=10)
    clock.work(5)
    assert t.wait() == Tick(52, 52, 0)
    assert clock.sleeps == [5]


@pytest.mark.parametrize(
    "kwargs",
    [
        {"period_ns": 0},
        {"period_ns": -1},
        {"period_ns": 1.0e6},
        {"period_ns": True},
        {"period_ns": MS, "spin_ns": -1},
        {"period_ns": MS, "spin_ns": 0.5},
    ],
)
def test_invalid_parameters(kwargs: dict[str, object]) -> None:
    clock = FakeClock(0)
    with pytest.raises(ValueError):
        Ticker(now=clock.now, sleep=clock.sleep, **kwargs)  # type: ignore[arg-type]
