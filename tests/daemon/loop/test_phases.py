"""The loop's phase recorder (``bench/loop_jitter.py --breakdown``): off without its variable,
each wrapped phase's time in its own column, the period closed by the ticker's wait, and a real
``ControlLoop``'s phases all wrapped (a phase left unwrapped would read 0 every cycle)."""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from jtc_hw.daemon.channel.cyclering import CycleRing
from jtc_hw.daemon.channel.pipe import Inbox
from jtc_hw.daemon.loop.clock import Ticker
from jtc_hw.daemon.loop.cycle import ControlLoop
from jtc_hw.daemon.loop.outbox import Outbox
from jtc_hw.daemon.loop.phases import (
    COLUMNS,
    PHASES_ENV,
    PhaseRecorder,
    read_rows,
    summarise,
)
from jtc_hw.daemon.robot import load_robot

from conftest import make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")


class FakeClock:
    def __init__(self) -> None:
        self.now = 1_000_000

    def __call__(self) -> int:
        return self.now


class Part:
    """Something whose methods take a known time on the fake clock."""

    def __init__(self, clock: FakeClock, cost_ns: int) -> None:
        self.clock, self.cost_ns = clock, cost_ns

    def work(self, value: int) -> int:
        self.clock.now += self.cost_ns
        return value + 1


class FakeTicker:
    def __init__(self, clock: FakeClock, sleep_ns: int) -> None:
        self.clock, self.sleep_ns = clock, sleep_ns

    def wait(self) -> str:
        self.clock.now += self.sleep_ns  # asleep: never counted as work
        return "tick"


def test_without_the_variable_there_is_no_recorder(tmp_path: Path) -> None:
    assert PhaseRecorder.from_env({}) is None
    assert PhaseRecorder.from_env({PHASES_ENV: ""}) is None
    recorder = PhaseRecorder.from_env({PHASES_ENV: str(tmp_path / "p.bin")})
    assert recorder is not None
    recorder.close()
    rows, count = read_rows(tmp_path / "p.bin")
    assert count == 0 and rows.shape == (0, len(COLUMNS))


def test_each_phase_lands_in_its_column_and_the_wait_closes_the_period(tmp_path: Path) -> None:
    clock = FakeClock()
    path = tmp_path / "phases.bin"
    recorder = PhaseRecorder(path, capacity=4, clock=clock)
    read, update, stats = Part(clock, 7_000), Part(clock, 20_000), Part(clock, 3_000)
    ticker = FakeTicker(clock, 900_000)
    recorder.wrap(read, "work", "read")
    recorder.wrap(update, "work", "update")
    recorder.wrap(stats, "work", "stats")
    recorder.wrap_ticker(ticker)  # type: ignore[arg-type]
    assert ticker.wait() == "tick"  # the first wake-up opens cycle 0
    for cycle in range(6):
        assert read.work(cycle) == cycle + 1  # a wrapped method still returns its result
        update.work(0)
        if cycle % 2:
            update.work(0)  # twice in a cycle: both counted
        stats.work(0)
        clock.now += 1_000  # work no phase claims
        ticker.wait()
    rows, count = read_rows(path, since=0)
    assert count == 6
    # The ring holds 4 rows; the newest may be being written: cycles 3, 4 and 5 are read.
    assert rows.shape == (3, len(COLUMNS))
    col = {name: i for i, name in enumerate(COLUMNS)}
    assert rows[:, col["read"]].tolist() == [7_000] * 3
    assert rows[:, col["update"]].tolist() == [40_000, 20_000, 40_000]
    assert rows[:, col["stats"]].tolist() == [3_000] * 3
    assert rows[:, col["period"]].tolist() == [51_000, 31_000, 51_000]
    assert rows[:, col["write"]].tolist() == [0] * 3
    summary = summarise(rows)
    assert summary["period"]["p50"] == 51.0 and summary["period"]["max"] == 51.0
    assert summary["update"]["mean"] == pytest.approx(100 / 3)
    assert summary["write"]["runs"] == 0
    # A parent's rest is its time less its children's: "period" holds "stats" (and "cycle",
    # not wrapped here), "cycle" holds "read" and "update" (so its rest is negative here).
    assert summary["period: rest"]["p50"] == 48.0
    assert summary["cycle: rest"]["max"] == -27.0
    assert read_rows(path, since=5)[0].shape == (1, len(COLUMNS))
    recorder.close()


@pytest.fixture
def loop_parts(tmp_path: Path) -> Iterator[tuple[ControlLoop, Inbox]]:
    joints = ["a", "b"]
    hardware = [{"name": "arm", "kind": "mirror", "joints": joints, "params": {}}]
    robot = load_robot(make_robot_config(tmp_path / "x.sock", joints, hardware))
    api, loop_end = multiprocessing.Pipe(duplex=True)
    outbox = Outbox(loop_end, 1 << 20)
    inbox = Inbox(loop_end, 1 << 20)
    ring = CycleRing.create(len(joints), 16)
    loop = ControlLoop(robot, outbox, ring)
    try:
        yield loop, inbox
    finally:
        ring.close()
        inbox.close()
        outbox.close()
        api.close()
        loop_end.close()


def test_every_phase_of_a_control_loop_is_timed(
    tmp_path: Path, loop_parts: tuple[ControlLoop, Inbox]
) -> None:
    loop, inbox = loop_parts
    sim = FakeClock()
    ticker = Ticker(loop.period_ns, now=sim, sleep=lambda s: None)
    path = tmp_path / "phases.bin"
    recorder = PhaseRecorder(path)
    recorder.instrument(loop, ticker, inbox)
    loop.start(sim.now)
    loop.state_every_ns = 0  # a State every cycle
    for _ in range(3):
        sim.now += loop.period_ns
        deadline, woke, skipped = ticker.wait()
        loop.cycle(deadline, loop.period_ns, inbox)  # as run() does, in its order
        loop.stats.record(woke - deadline, 0, skipped)
        loop.publish(Status_of(loop))
        loop.after_cycle(deadline, inbox)
        if not inbox.release():
            loop.collect_garbage(0)
    sim.now += loop.period_ns
    ticker.wait()  # closes the third cycle
    rows, count = read_rows(path)
    assert count == 3
    summary = summarise(rows)
    for name in COLUMNS:
        assert summary[name]["runs"] == 3, name  # every phase ran and was timed each cycle
    for parent in ("cycle", "period"):
        assert summary[f"{parent}: rest"]["p50"] >= 0.0
    recorder.close()


def Status_of(loop: ControlLoop) -> object:  # noqa: N802 - reads as the message it builds
    from jtc_hw.daemon.channel.messages import Status

    return Status(loop.status())


def test_the_ring_keeps_the_newest_rows(tmp_path: Path) -> None:
    clock = FakeClock()
    recorder = PhaseRecorder(tmp_path / "p.bin", capacity=8, clock=clock)
    ticker = FakeTicker(clock, 1)
    recorder.wrap_ticker(ticker)  # type: ignore[arg-type]
    ticker.wait()
    for k in range(20):
        clock.now += k
        ticker.wait()
    rows, count = read_rows(tmp_path / "p.bin", since=3)
    assert count == 20
    assert rows[:, 0].tolist() == list(range(13, 20))
    assert np.all(rows[:, 1:] == 0)
    recorder.close()
