"""The daemon's cycle ring in /dev/shm: there while it runs, gone after SIGTERM; after a SIGKILL
of the whole daemon (its resource tracker too) it stays until the next daemon starts.

Two daemons on simulated joints, one after the other on the same socket; waits are on the
socket and the process with deadlines. What a starting daemon removes is shown in-process on a
directory of the test's own (other daemons on the machine clean /dev/shm too).
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.daemon import DaemonProcess, wait_gone

from jtc_hw.daemon.channel import cyclering
from jtc_hw.daemon.core.observers import Recorders
from jtc_hw.daemon.settings import DaemonSettings

from conftest import make_config

pytestmark = pytest.mark.usefixtures("no_leaks")

pytest.importorskip("rosbags")  # the flight recorder (the ring's reader) needs it

SHM = Path("/dev/shm")
if not SHM.is_dir():
    pytest.skip("no /dev/shm on this system", allow_module_level=True)


def rings(d: DaemonProcess) -> list[Path]:
    return sorted(SHM.glob(f"jtc_hw_{d.pid}_*"))


def test_a_killed_daemons_ring_stays_until_the_next_daemon_starts(tmp_path: Path) -> None:
    """A daemon killed with its whole process group leaves its ring; once the next daemon on
    the same socket is ready it is gone (a starting daemon removes every stale ring: with two
    suites side by side, another session's daemon may be the one that starts first, so which
    daemon removed it is shown in-process by the test below), and that daemon runs with its
    own ring, which SIGTERM removes."""
    where = tmp_path
    first = DaemonProcess(where / "d", flight_recorder_dir=str(where / "bags"))
    first.start()
    try:
        first.wait_ready()
        left = rings(first)
        assert len(left) == 1, sorted(SHM.iterdir())
        os.killpg(first.pid, signal.SIGKILL)  # API process, loop, resource tracker: all
        assert first.wait_exit() == -signal.SIGKILL
        assert first.leftovers() == {}
        assert left[0].exists()  # nobody was left to remove it
    finally:
        if first.proc is not None and first.proc.poll() is None:  # failed before the kill
            first.shutdown()
    second = DaemonProcess(where / "d", flight_recorder_dir=str(where / "bags"))
    second.start()
    try:
        second.wait_ready()
        assert not left[0].exists()
        own = rings(second)
        assert len(own) == 1
    finally:
        code = second.shutdown()
    assert code == 0, second.log()
    assert not own[0].exists()  # SIGTERM: the daemon removed its own
    wait_gone(second.pid)


def test_a_starting_daemon_removes_the_rings_of_killed_daemons(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
) -> None:
    """What a daemon's start does (its recorders, before it makes its own ring), on a shared
    memory directory of this test's own, where no other daemon can remove the stale ring
    first (tools/ci-under-load at 2bb5c65: beside busy processes, in 3 of 3 rounds another
    suite's daemon had started between a kill and the restart, and removed it)."""
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    stale = tmp_path / f"jtc_hw_{int(done.stdout)}_0badc0de"  # its pid runs nothing now
    stale.write_bytes(b"")
    alive = tmp_path / f"jtc_hw_{os.getpid()}_0badc0de"
    alive.write_bytes(b"")
    monkeypatch.setattr(cyclering, "SHM_DIR", str(tmp_path))
    settings = DaemonSettings(socket=str(tmp_path / "d.sock"),
                              flight_recorder_dir=str(tmp_path / "bags"))
    recorders = Recorders(settings, make_config(), dict)

    async def start() -> str | None:
        try:
            return recorders.start()
        finally:
            recorders.close_ring()
            await recorders.close()

    with caplog.at_level(logging.INFO, logger="jtc_hw.backend"):
        ring = asyncio.run(start())
    assert ring is not None  # it made its own ring after the removal
    assert not stale.exists() and alive.exists()
    assert f"removed {stale.name}, the cycle ring of a daemon that was killed" in caplog.messages
