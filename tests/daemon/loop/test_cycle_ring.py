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


# -- the States -------------------------------------------------------------------------------


def test_a_state_slot_and_its_row_give_the_state_the_loop_would_have_sent() -> None:
    """Every field of the loop's ``State``, from the row and its state slot, value for value,
    with None where the loop's arrays were None (an interface not configured)."""
    rng = np.random.default_rng(49)
    ring = CycleRing.create(JOINTS, 64)

    def arrays(k: int) -> list[np.ndarray]:
        return [rng.standard_normal(JOINTS) for _ in range(k)]

    try:
        states = []
        for k in range(5):
            p, v, a = arrays(3)
            desired = TrajectorySample(*arrays(4))
            error = rng.standard_normal((3, JOINTS))
            measured = JointState(p, v if k % 2 else None, a if k % 3 == 0 else None)
            command = JointCommand(*arrays(2), None, arrays(1)[0] if k else None)
            output = JointCommand(command.positions, None, None, command.effort)
            ring.write(10_000 + k, None if k == 1 else 7 + k, k == 2, False, 0.25 * k, k / 3,
                       k / 7, measured, desired, output)
            ring.write_state(error, command, output, measured, 0.125 * k, 2**40 + k)
            states.append((k, desired, error, measured, command, output))
        got, next_since, lost = ring.read_states(0)
        assert (len(got), next_since, lost) == (5, 5, 0)
        for state, (k, desired, error, measured, command, output) in zip(
                got, states, strict=True):
            assert state.time_ns == 10_000 + k
            assert np.array_equal(state.desired, np.stack(desired))
            assert np.array_equal(state.positions, measured.positions)
            for mine, theirs in ((state.velocities, measured.velocities),
                                 (state.accelerations, measured.accelerations)):
                assert (mine is None) == (theirs is None)
                assert theirs is None or np.array_equal(mine, theirs)
            assert np.array_equal(state.error, error)
            for mine_command, theirs_command in ((state.command, command),
                                                 (state.output, output)):
                for field in ("positions", "velocities", "accelerations", "effort"):
                    mine, theirs = getattr(mine_command, field), getattr(theirs_command, field)
                    assert (mine is None) == (theirs is None), (k, field)
                    assert theirs is None or np.array_equal(mine, theirs)
            assert state.holding is (k == 2)
            assert state.active_goal == (None if k == 1 else 7 + k)
            assert (state.reference_time_from_start, state.feedback_time_from_start) == (
                k / 3, k / 7)
            assert (state.speed_scaling_factor, state.speed_scaling_target) == (
                0.25 * k, 0.125 * k)
            assert state.trajectory_time_ns == 2**40 + k
        assert ring.read_states(next_since) == ([], 5, 0)
    finally:
        ring.close()


def test_states_overwritten_before_they_were_read_are_counted_not_returned() -> None:
    ring = CycleRing.create(JOINTS, 64)
    try:
        x = np.zeros(JOINTS)
        for k in range(40):
            ring.write(k, None, True, False, 1.0, 0.0, 0.0, JointState(x, x, None),
                       TrajectorySample(x, x, x, x), JointCommand(x, None, None, None))
            if k % 2:  # a State every other cycle: 20
                ring.write_state(np.zeros((3, JOINTS)), JointCommand(x, None, None, None),
                                 JointCommand(x, None, None, None), JointState(x, x, None),
                                 1.0, k)
        got, next_since, lost = ring.read_states(0)
        assert (next_since, lost) == (20, 4)  # the ring keeps the newest 16
        assert [s.time_ns for s in got] == list(range(9, 40, 2))
        # A State whose row was overwritten since (the rows wrapped) is lost too.
        small = CycleRing.create(JOINTS, 4)
        try:
            for k in range(6):
                small.write(k, None, True, False, 1.0, 0.0, 0.0, JointState(x, x, None),
                            TrajectorySample(x, x, x, x), JointCommand(x, None, None, None))
                if k == 0:
                    small.write_state(np.zeros((3, JOINTS)), JointCommand(x, None, None, None),
                                      JointCommand(x, None, None, None),
                                      JointState(x, x, None), 1.0, 0)
            assert small.read_states(0) == ([], 1, 1)
        finally:
            small.close()
    finally:
        ring.close()
