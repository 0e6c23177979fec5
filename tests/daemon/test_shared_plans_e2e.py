"""Large plans reach the loop in shared memory, and the memory is reused, then returned.

Against a real daemon (``python -m jtc_hw run``, mirror joints): goals whose plans are over
``SHARED_MIN_BYTES`` travel as a ``memfd`` region of the API process's pool
(``jtc_hw.daemon.channel.shared``). ``get_status``'s ``plan_memory`` shows it: a region the
loop still maps is not reused (a second region is made), a region the loop has released is
(``Released``), and once large goals stop coming the pool returns its regions to the system
after ``IDLE_S``. Every goal still gets exactly one result. Waits are on the daemon's status,
with deadlines; nothing is timed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from helpers.daemon import JOINTS, WAIT_S, DaemonProcess, RecordingClient, connect

from jtc_hw.daemon.channel.shared import IDLE_S, SHARED_AVAILABLE

pytestmark = [
    pytest.mark.usefixtures("no_leaks"),  # threads, sockets, resources
    pytest.mark.skipif(not SHARED_AVAILABLE, reason="no memfd_create on this system"),
]

POINTS = 400  # a plan of ~480 kB: over SHARED_MIN_BYTES (256 KiB) for six joints


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    d = DaemonProcess(tmp_path_factory.mktemp("shared"))
    with d.serving():
        yield d


def wave(phase: float, duration_s: float = 4.0) -> dict[str, Any]:
    """A slow wave around zero, ``POINTS`` points (positions and velocities)."""
    t = np.linspace(duration_s / POINTS, duration_s, POINTS)
    w = 2 * np.pi / duration_s
    positions = 0.05 * np.sin(w * t[:, None] + phase + np.arange(6))
    positions -= 0.05 * np.sin(phase + np.arange(6))  # starts where the hold at zero is
    velocities = 0.05 * w * np.cos(w * t[:, None] + phase + np.arange(6))
    return {
        "joint_names": JOINTS,
        "points": [
            {"time_from_start": float(s), "positions": p.tolist(), "velocities": v.tolist()}
            for s, p, v in zip(t, positions, velocities, strict=True)
        ],
    }


def memory_when(
    client: RecordingClient, ok: Callable[[dict[str, int]], bool], timeout_s: float = WAIT_S
) -> dict[str, int]:
    """``plan_memory`` once ``ok`` holds for it (the status is refreshed on every request)."""
    deadline = time.monotonic() + timeout_s
    while True:
        memory: dict[str, int] = client.get_status()["plan_memory"]
        if ok(memory):
            return memory
        assert time.monotonic() < deadline, f"plan_memory stayed {memory}"
        time.sleep(0.05)  # polling the daemon's status; nothing to block on


def test_large_plans_share_memory_reuse_it_and_return_it(daemon: DaemonProcess) -> None:
    client = connect(daemon)
    try:
        client.stop()
        base = memory_when(client, lambda m: m["busy_bytes"] == 0)
        first = client.send_goal(wave(0.0))
        after_first = client.get_status()["plan_memory"]
        assert after_first["busy_bytes"] > 0  # the loop maps the first plan's region
        assert after_first["made"] > base["made"]

        second = client.send_goal(wave(0.5))  # preempts the first; its region is still mapped
        # The loop gives the first plan's region back in spare time once nothing uses it.
        released = memory_when(client, lambda m: m["free_bytes"] > 0)
        assert released["busy_bytes"] > 0  # the second plan's

        third = client.send_goal(wave(1.0))
        reused = client.get_status()["plan_memory"]
        assert reused["reused"] == released["reused"] + 1
        assert reused["made"] == released["made"]  # nothing new allocated

        client.stop()
        for goal in (first, second, third):
            result = goal.wait(timeout_s=WAIT_S)
            assert len(client.received("result", goal.goal_id)) == 1, result
        # Large goals stopped: every region goes back to the system after IDLE_S unused.
        done = memory_when(
            client, lambda m: m["regions"] == 0, timeout_s=IDLE_S + 2 * WAIT_S
        )
        assert done["dropped"] >= 2 and done["busy_bytes"] == done["free_bytes"] == 0
    finally:
        client.close()
