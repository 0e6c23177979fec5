"""The API process's pool of shared memory for plans (jtc_hw.daemon.channel.shared)."""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from jtc_hw.daemon.channel.shared import (
    REGION_ROUND,
    SEALS,
    SHARED_AVAILABLE,
    SharedPool,
    layout,
)

pytestmark = pytest.mark.skipif(not SHARED_AVAILABLE, reason="no memfd_create on this system")


@pytest.fixture
def pool() -> Iterator[SharedPool]:
    p = SharedPool()
    try:
        yield p
    finally:
        p.close()


def _open_fds() -> set[int]:
    return {int(name) for name in os.listdir("/proc/self/fd")}


def test_layout_aligns_each_buffer() -> None:
    assert layout([1, 64, 65, 0, 8]) == ([0, 64, 128, 256, 256], 320)
    assert layout([]) == ([], 1)


def test_a_region_is_sealed_against_resizing_and_holds_what_is_written(pool: SharedPool) -> None:
    region = pool.acquire(5000)
    assert region.size == REGION_ROUND and region.busy
    assert fcntl.fcntl(region.fd, fcntl.F_GET_SEALS) & SEALS == SEALS
    with pytest.raises(PermissionError):
        os.ftruncate(region.fd, 10)  # shrinking would fault the loop's mapping (SIGBUS)
    data = np.arange(100, dtype=np.float64)
    region.write(64, memoryview(data).cast("B"))
    assert os.pread(region.fd, data.nbytes, 64) == data.tobytes()


def test_a_region_is_reused_only_once_released(pool: SharedPool) -> None:
    first = pool.acquire(3 * REGION_ROUND)
    second = pool.acquire(3 * REGION_ROUND)  # the first is busy: a new one
    assert second.token != first.token and pool.made == 2
    pool.released((first.token, 999))  # an unknown token is ignored
    again = pool.acquire(2 * REGION_ROUND + 1)
    assert again is first and not pool.free_bytes and pool.reused == 1
    pool.unsent(again)  # never handed to the loop: free again
    assert pool.free_bytes == first.size


def test_a_region_far_larger_than_needed_is_not_reused(pool: SharedPool) -> None:
    big = pool.acquire(8 * REGION_ROUND)
    pool.released((big.token,))
    small = pool.acquire(REGION_ROUND)  # 8 MiB for 1 MiB would tie the big one up
    assert small is not big
    too_big = pool.acquire(9 * REGION_ROUND)  # and a region too small is never used
    assert too_big is not big and pool.made == 3


def test_trim_drops_only_regions_idle_long_enough(pool: SharedPool) -> None:
    before = _open_fds()
    old = pool.acquire(REGION_ROUND)
    recent = pool.acquire(REGION_ROUND)
    busy = pool.acquire(REGION_ROUND)
    pool.released((old.token,), now=100.0)
    pool.released((recent.token,), now=104.0)
    assert pool.trim(idle_s=5.0, now=105.5) == old.size
    assert pool.status() == {
        "regions": 2, "busy_bytes": busy.size, "free_bytes": recent.size,
        "made": 3, "reused": 0, "dropped": 1,
    }
    assert old.mapping.closed
    assert pool.trim(idle_s=5.0, now=110.0) == recent.size
    pool.close()
    assert busy.mapping.closed and _open_fds() == before


def test_a_closed_pool_makes_no_region(pool: SharedPool) -> None:
    pool.close()
    before = _open_fds()
    with pytest.raises(OSError, match="closed"):
        pool.acquire(100)
    assert _open_fds() == before


def test_no_shared_memory_rejects_the_large_goal_clearly_and_the_loop_holds_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Out of memory for a plan's region: that goal is rejected with the reason (nothing is
    sent to the loop), the controller keeps holding, small goals (through the pipe) are still
    accepted, and a large goal is again once memory can be had."""
    import asyncio
    import errno

    from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
    from jtc_hw.daemon.core.backend import LoopBackend
    from jtc_hw.daemon.robot import load_robot
    from jtc_hw.errors import GoalRejected

    from conftest import make_robot_config

    joints = ["a", "b", "c"]
    hardware = [{"name": "arm", "kind": "mirror", "joints": joints, "params": {}}]
    source = make_robot_config(tmp_path / "x.sock", joints, hardware)

    def goal(points: int) -> JointTrajectory:  # 600 points: a plan of ~360 kB over 256 KiB
        return JointTrajectory(joints, [
            TrajectoryPoint(0.01 * (i + 1), [0.001 * i] * 3, [0.0] * 3) for i in range(points)
        ])

    real_acquire = SharedPool.acquire

    def refuse(self: SharedPool, nbytes: int) -> object:
        raise OSError(errno.ENOMEM, "Cannot allocate memory")

    async def scenario() -> None:
        backend = LoopBackend(load_robot(source), source)
        await backend.start()
        try:
            monkeypatch.setattr(SharedPool, "acquire", refuse)
            with pytest.raises(GoalRejected, match="could not be handed to the loop: .*memory"):
                await backend.send_goal(goal(600))
            # (the loop's own status comes at 2 Hz and may not be in yet: ask the backend)
            assert backend.alive and backend.death is None
            assert backend.status()["plan_memory"]["busy_bytes"] == 0
            await backend.send_goal(goal(1))  # small: through the pipe, accepted
            monkeypatch.setattr(SharedPool, "acquire", real_acquire)
            await backend.send_goal(goal(600))
            assert backend.status()["plan_memory"]["busy_bytes"] > 0
        finally:
            assert await backend.stop("test over") == 0

    asyncio.run(scenario())
