"""The States the API process publishes: from the cycle ring, or through the loop's pipe when
there is no shared memory for the ring; a failure to publish one does not stop the next ones.

A real ``LoopBackend`` (the loop process on simulated joints), its ``_on_state`` wrapped to
count what arrives; waits are on a deadline, nothing asserts a duration.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Any

import pytest

from jtc_hw.daemon.channel.cyclering import CycleRing
from jtc_hw.daemon.core.backend import LoopBackend
from jtc_hw.daemon.robot import load_robot

from conftest import make_robot_config

WAIT_S = 20.0


def run(tmp_path: Path, fail_first: bool) -> tuple[list[Any], bool]:
    """States published (after a first one that fails, with ``fail_first``), and whether the
    backend had a ring."""
    joints = ["a", "b"]
    hardware = [{"name": "arm", "kind": "mirror", "joints": joints, "params": {}}]
    source = make_robot_config(tmp_path / "x.sock", joints, hardware)
    seen: list[Any] = []

    async def scenario() -> bool:
        backend = LoopBackend(load_robot(source), source)
        publish = backend._on_state
        failed = [not fail_first]

        def on_state(state: Any) -> None:
            if not failed[0]:
                failed[0] = True
                raise RuntimeError("an observer's bug")
            publish(state)
            seen.append(state)

        backend._on_state = on_state  # type: ignore[method-assign]
        await backend.start()
        try:
            deadline = asyncio.get_running_loop().time() + WAIT_S
            while len(seen) < 5 and asyncio.get_running_loop().time() < deadline:
                await asyncio.sleep(0.01)
            return backend.recorders.ring is not None
        finally:
            assert await backend.stop("test over") == 0

    return seen, asyncio.run(scenario())


def test_states_come_from_the_ring_and_a_failed_one_does_not_stop_the_next(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.ERROR, logger="jtc_hw.backend"):
        seen, ring = run(tmp_path, fail_first=True)
    assert ring
    assert len(seen) >= 5, "the States stopped after a failed one"
    times = [s.time_ns for s in seen]
    assert times == sorted(set(times))  # each once, in order
    assert "publishing the control loop's states failed" in caplog.text


def test_without_shared_memory_for_the_ring_states_come_through_the_pipe(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def refuse(*args: Any, **kwargs: Any) -> CycleRing:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(CycleRing, "create", refuse)
    seen, ring = run(tmp_path, fail_first=False)
    assert not ring
    assert len(seen) >= 5
    assert [s.time_ns for s in seen] == sorted({s.time_ns for s in seen})
