"""Loop statistics on exact synthetic sequences (jtc_hw.daemon.loop.stats)."""

from __future__ import annotations

import json
import tracemalloc
from typing import Any

import pytest

from jtc_hw.daemon.loop.stats import LoopStats

US = 1000  # ns


def record_all(stats: LoopStats, lateness_us: list[int], cost_us: list[int] | None = None) -> None:
    costs = cost_us if cost_us is not None else [0] * len(lateness_us)
    for late, cost in zip(lateness_us, costs):
        stats.record(late * US, cost * US, 0)


def test_empty_snapshot() -> None:
    snap = LoopStats(1000.0, window=8).snapshot()
    assert snap == {
        "rate_hz": 1000.0,
        "period_us": 1000.0,
        "cycles": 0,
        "overruns": 0,
        "overrun_cycles": 0,
        "window_cycles": 0,
        "lateness_us": {"p50": None, "p99": None, "max": None, "worst": None},
        "cost_us": {"p50": None, "p99": None, "max": None, "worst": None},
    }


def test_one_to_hundred_nearest_rank() -> None:
    stats = LoopStats(500.0, window=100)
    # Shuffled deterministically so the order of arrival does not matter.
    values = [(i * 37) % 100 + 1 for i in range(100)]
    assert sorted(values) == list(range(1, 101))
    record_all(stats, values, [v * 2 for v in values])
    snap = stats.snapshot()
    assert snap["period_us"] == 2000.0
    assert snap["cycles"] == 100
    assert snap["window_cycles"] == 100
    assert snap["lateness_us"] == {"p50": 50.0, "p99": 99.0, "max": 100.0, "worst": 100.0}
    assert snap["cost_us"] == {"p50": 100.0, "p99": 198.0, "max": 200.0, "worst": 200.0}


@pytest.mark.parametrize(
    ("samples", "p50", "p99"),
    [
        ([7], 7, 7),
        ([1, 2], 1, 2),
        ([3, 1, 2], 2, 3),
        ([4, 3, 2, 1], 2, 4),
        ([10] * 99 + [5000], 10, 10),  # p99 of 100: the 99th smallest
        ([10] * 98 + [5000, 6000], 10, 5000),
        ([10] * 199 + [5000], 10, 10),  # ceil(0.99 * 200) = 198th
        ([10] * 197 + [5000] * 3, 10, 5000),
    ],
)
def test_nearest_rank_percentiles(samples: list[int], p50: int, p99: int) -> None:
    stats = LoopStats(1000.0, window=len(samples))
    record_all(stats, samples)
    got = stats.snapshot()["lateness_us"]
    assert (got["p50"], got["p99"], got["max"]) == (p50, p99, max(samples))


def test_window_slides_but_worst_is_kept() -> None:
    stats = LoopStats(1000.0, window=4)
    record_all(stats, [900, 1, 2, 3, 4, 5], [50, 6, 7, 8, 9, 10])
    snap = stats.snapshot()
    assert snap["cycles"] == 6
    assert snap["window_cycles"] == 4
    # Window holds the last four: 2, 3, 4, 5 (the 900 us spike has left it).
    assert snap["lateness_us"] == {"p50": 3.0, "p99": 5.0, "max": 5.0, "worst": 900.0}
    assert snap["cost_us"] == {"p50": 8.0, "p99": 10.0, "max": 10.0, "worst": 50.0}


def test_partial_window_ignores_unused_slots() -> None:
    stats = LoopStats(1000.0, window=10)
    record_all(stats, [-5, -3, -4])  # woke early: negative lateness, and zeros are not samples
    snap = stats.snapshot()
    assert snap["window_cycles"] == 3
    assert snap["lateness_us"] == {"p50": -4.0, "p99": -3.0, "max": -3.0, "worst": -3.0}


def test_sub_microsecond_resolution() -> None:
    stats = LoopStats(1000.0, window=3)
    stats.record(1, 1500, 0)
    stats.record(2, 2500, 0)
    stats.record(3, 999, 0)
    snap = stats.snapshot()
    assert snap["lateness_us"] == {"p50": 0.002, "p99": 0.003, "max": 0.003, "worst": 0.003}
    assert snap["cost_us"]["p50"] == 1.5


def test_overruns_count_skipped_deadlines_and_cycles() -> None:
    stats = LoopStats(100.0, window=5)
    for skipped in [0, 3, 0, 0, 1, 0, 7]:
        stats.record(0, 0, skipped)
    snap = stats.snapshot()
    assert snap["period_us"] == 10000.0
    assert snap["cycles"] == 7
    assert snap["overruns"] == 11
    assert snap["overrun_cycles"] == 3


def test_reset_forgets_everything_and_reuses_buffers() -> None:
    stats = LoopStats(1000.0, window=3)
    buffers = (stats._lateness, stats._cost)
    record_all(stats, [100, 200, 300, 400], [1, 2, 3, 4])
    stats.record(0, 0, 5)
    stats.reset()
    assert stats.snapshot() == LoopStats(1000.0, window=3).snapshot()
    record_all(stats, [7], [8])
    snap = stats.snapshot()
    assert snap["cycles"] == 1
    assert snap["lateness_us"] == {"p50": 7.0, "p99": 7.0, "max": 7.0, "worst": 7.0}
    assert snap["cost_us"]["worst"] == 8.0
    assert (stats._lateness, stats._cost) == buffers


def test_snapshot_is_json_and_detached() -> None:
    stats = LoopStats(250.0, window=2)
    record_all(stats, [1, 2], [3, 4])
    snap = stats.snapshot()
    text = json.dumps(snap)
    assert json.loads(text) == snap
    assert all(type(v) in (int, float) for v in snap["lateness_us"].values())
    record_all(stats, [100, 100], [100, 100])
    assert snap["lateness_us"]["max"] == 2.0


def test_default_window_is_ten_seconds() -> None:
    assert LoopStats(1000.0).window == 10_000
    assert LoopStats(0.05).window == 1


def test_record_does_not_grow_memory() -> None:
    stats = LoopStats(1000.0, window=64)
    for i in range(1_000):  # warm every cache the calls touch (3.10 fills some later than 3.11)
        stats.record(1_000_000 + i, 2_000_000 + i, i & 1)
    tracemalloc.start()
    try:
        start, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        for i in range(10_000):
            stats.record(1_000_000 + i, 2_000_000 + i, i & 1)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 512
    assert peak - start < 2048  # transient ints only, never a buffer


def test_overflowing_value_is_refused() -> None:
    stats = LoopStats(1000.0, window=2)
    with pytest.raises(OverflowError):
        stats.record(1 << 63, 0, 0)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"rate_hz": 0.0},
        {"rate_hz": -1.0},
        {"rate_hz": float("nan")},
        {"rate_hz": float("inf")},
        {"rate_hz": True},
        {"rate_hz": 100.0, "window": 0},
        {"rate_hz": 100.0, "window": 2.5},
        {"rate_hz": 100.0, "window": True},
    ],
)
def test_invalid_construction(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        LoopStats(**kwargs)
