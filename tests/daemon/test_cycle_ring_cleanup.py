"""The daemon's cycle ring in /dev/shm: there while it runs, gone after SIGTERM; after a SIGKILL
of the whole daemon (its resource tracker too) it stays until the next daemon starts.

Two daemons on simulated joints, one after the other on the same socket; waits are on the
socket and the process with deadlines.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
from helpers.daemon import DaemonProcess, wait_gone

pytestmark = pytest.mark.usefixtures("no_leaks")

pytest.importorskip("rosbags")  # the flight recorder (the ring's reader) needs it

SHM = Path("/dev/shm")
if not SHM.is_dir():
    pytest.skip("no /dev/shm on this system", allow_module_level=True)


def rings(d: DaemonProcess) -> list[Path]:
    return sorted(SHM.glob(f"jtc_hw_{d.pid}_*"))


def foreign_rings(*ours: DaemonProcess) -> list[Path]:
    """Rings of daemons this test did not start (another test session on the machine)."""
    pids = {d.pid for d in ours}
    return [p for p in SHM.glob("jtc_hw_*_*") if p.name.split("_")[2] not in map(str, pids)]


def test_a_killed_daemons_ring_is_removed_when_the_next_one_starts(tmp_path: Path) -> None:
    first = DaemonProcess(tmp_path / "d", flight_recorder_dir=str(tmp_path / "bags"))
    first.start()
    try:
        first.wait_ready()
        others = foreign_rings(first)
        left = rings(first)
        assert len(left) == 1, sorted(SHM.iterdir())
        os.killpg(first.pid, signal.SIGKILL)  # API process, loop, resource tracker: all
        assert first.wait_exit() == -signal.SIGKILL
        assert first.leftovers() == {}
        assert left[0].exists()  # nobody was left to remove it
    finally:
        if first.proc is not None and first.proc.poll() is None:  # failed before the kill
            first.shutdown()
    second = DaemonProcess(tmp_path / "d", flight_recorder_dir=str(tmp_path / "bags"))
    second.start()
    try:
        second.wait_ready()
        assert not left[0].exists()
        # Which daemon removed it: this one, unless another session's daemon ran meanwhile
        # (.ci/run runs two suites side by side; any starting daemon removes every stale ring,
        # which is the design). Such a daemon's ring is seen here or above.
        others += foreign_rings(first, second)
        if not others:
            assert "the cycle ring of a daemon that was killed" in second.log()
        own = rings(second)
        assert len(own) == 1
    finally:
        code = second.shutdown()
    assert code == 0, second.log()
    assert not own[0].exists()  # SIGTERM: the daemon removed its own
    wait_gone(second.pid)
