"""The cycle ring: every cycle's row from the loop process to the API process in shared memory.

Rows written by another process (spawned, as the loop is) are read back with their values;
a reader that falls more than the ring's capacity behind gets the newest rows and the count of
those lost, never an overwritten row taken for a newer one; the owner removes the segment.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jtc_hw.controller.joints import JointCommand, JointState
from jtc_hw.controller.trajectory import TrajectorySample
from jtc_hw.daemon.channel.cyclering import CycleRing, remove_stale
from jtc_hw.errors import JtcHwError

JOINTS = 3


def write_rows(ring: CycleRing, first: int, n: int) -> None:
    for k in range(first, first + n):
        x = np.arange(JOINTS, dtype=np.float64) + k
        ring.write(
            1_000_000 * k, k // 10 or None, k % 2 == 0, False, 0.5, k / 100, k / 50,
            JointState(x, -x, None),
            TrajectorySample(x + 0.5, x + 0.25, x * 0.0, x * 0.0),
            JointCommand(x + 1.0, None, None, None),
        )


def writer_process(name: str, n: int) -> None:
    ring = CycleRing.attach(name)
    try:
        write_rows(ring, 0, n)
    finally:
        ring.close()


def test_rows_written_by_another_process_are_read_back() -> None:
    ring = CycleRing.create(JOINTS, 64)
    try:
        process = multiprocessing.get_context("spawn").Process(
            target=writer_process, args=(ring.name, 40))
        process.start()
        process.join(60)
        assert process.exitcode == 0
        rows, next_since, lost = ring.read(0)
        assert (len(rows), next_since, lost) == (40, 40, 0)
        layout = ring.layout
        assert layout.times(rows).tolist() == [1_000_000 * k for k in range(40)]
        row = rows[25]
        assert row[layout.block("measured_positions")].tolist() == [25.0, 26.0, 27.0]
        assert row[layout.block("measured_velocities")].tolist() == [-25.0, -26.0, -27.0]
        assert np.isnan(row[layout.block("measured_accelerations")]).all()  # not measured
        assert row[layout.block("reference_positions")].tolist() == [25.5, 26.5, 27.5]
        assert row[layout.block("output_positions")].tolist() == [26.0, 27.0, 28.0]
        assert np.isnan(row[layout.block("output_velocities")]).all()  # not configured
        assert row[layout.column("active_goal")] == 2
        assert math.isnan(rows[5][layout.column("active_goal")])  # k // 10 == 0: none
        assert row[layout.column("holding")] == 0.0 and rows[24][layout.column("holding")] == 1
        assert row[layout.column("reference_time_from_start")] == pytest.approx(0.25)
        # Nothing new: nothing returned, nothing lost.
        rows, next_since, lost = ring.read(next_since)
        assert (len(rows), next_since, lost) == (0, 40, 0)
    finally:
        ring.close()


def test_a_reader_that_fell_behind_gets_the_newest_rows_and_counts_the_lost() -> None:
    ring = CycleRing.create(JOINTS, 16)
    try:
        write_rows(ring, 0, 10)
        rows, since, lost = ring.read(0)
        assert (len(rows), since, lost) == (10, 10, 0)
        write_rows(ring, 10, 40)  # 40 more into 16 places: 24 overwritten unread
        rows, since, lost = ring.read(since)
        assert (len(rows), since, lost) == (16, 50, 24)
        assert ring.layout.times(rows).tolist() == [1_000_000 * k for k in range(34, 50)]
    finally:
        ring.close()


def test_a_row_whose_sequence_number_is_not_the_expected_one_is_not_taken() -> None:
    ring = CycleRing.create(JOINTS, 16)
    try:
        write_rows(ring, 0, 5)
        # As if the writer had begun reusing row 3's place: its sequence number is another.
        ring._ints[3, ring.layout.column("seq")] = 19
        rows, since, lost = ring.read(0)
        assert ring.layout.times(rows).tolist() == [0, 1_000_000, 2_000_000, 4_000_000]
        assert (since, lost) == (5, 1)
    finally:
        ring.close()


def test_the_owner_removes_the_segment_and_attaching_to_a_missing_one_says_so() -> None:
    ring = CycleRing.create(JOINTS, 8)
    name = ring.name
    assert name.startswith(f"jtc_hw_{os.getpid()}_")
    shm = Path("/dev/shm") / name
    if Path("/dev/shm").is_dir():
        assert shm.exists()
    other = CycleRing.attach(name)
    other.close()  # not the owner: the segment stays
    if Path("/dev/shm").is_dir():
        assert shm.exists()
    ring.close()
    assert not shm.exists()
    with pytest.raises(JtcHwError, match="cannot attach the cycle ring"):
        CycleRing.attach(name)


def test_a_killed_daemons_ring_is_removed_by_the_next_one(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    dead = int(done.stdout)  # a process that has exited (reaped): its pid runs nothing now
    for name in (f"jtc_hw_{dead}_0badc0de", f"jtc_hw_{os.getpid()}_0badc0de", "other_1_2",
                 f"jtc_hw_{dead}"):
        (tmp_path / name).write_bytes(b"")
    assert remove_stale(str(tmp_path)) == [f"jtc_hw_{dead}_0badc0de"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [f"jtc_hw_{os.getpid()}_0badc0de", "other_1_2", f"jtc_hw_{dead}"])
