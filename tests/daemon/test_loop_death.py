"""Loop death seen from the API process (jtc_hw.daemon.core.backend.LoopBackend), in process.

The backend spawns its real loop process on simulated joints; the test kills that process and
checks what the service and the server build on: exactly one ABORTED result per goal the loop
had accepted and not finished, the fault in the status, every later goal and request refused
with the reason, and ``wait_exited`` returning (the service then exits non-zero; the subprocess
tests in test_failsafe.py check that part).
"""

from __future__ import annotations

import asyncio
import os
import signal
from pathlib import Path
from typing import Any

import pytest

from jtc_hw.controller.goals import GoalFeedback, GoalResult, GoalStatus
from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.daemon.core.backend import LoopBackend
from jtc_hw.daemon.robot import load_robot
from jtc_hw.errors import ControllerStateError, GoalRejected

from conftest import make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")

JOINTS = ["a", "b", "c"]
WAIT_S = 10.0


class Recorder:
    """An observer of the backend: every goal event, in order."""

    def __init__(self) -> None:
        self.events: list[GoalResult | GoalFeedback] = []
        self.changed = asyncio.Event()

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None:
        self.events.append(event)
        self.changed.set()

    def on_state(self, snapshot: dict[str, Any]) -> None:
        pass

    def on_command(self, traj: JointTrajectory, goal_id: int | None) -> None:
        pass

    def on_record(self, event: dict[str, Any]) -> None:
        pass

    def results(self, goal_id: int) -> list[GoalResult]:
        return [e for e in self.events if isinstance(e, GoalResult) and e.goal_id == goal_id]

    async def wait_for(self, predicate: Any) -> None:
        async def until() -> None:
            while not predicate():
                self.changed.clear()
                await self.changed.wait()

        await asyncio.wait_for(until(), WAIT_S)  # asyncio.timeout is Python 3.11


def goal(target: float, duration_s: float) -> JointTrajectory:
    return JointTrajectory(
        JOINTS, [TrajectoryPoint(duration_s, [target] * len(JOINTS), [0.0] * len(JOINTS))]
    )


def test_a_killed_loop_gives_each_open_goal_one_aborted_result_and_refuses_the_rest(
    tmp_path: Path,
) -> None:
    hardware = [{"name": "arm", "kind": "mirror", "joints": JOINTS, "params": {}}]
    source = make_robot_config(tmp_path / "x.sock", JOINTS, hardware)

    async def scenario() -> None:
        backend = LoopBackend(load_robot(source), source)
        recorder = Recorder()
        backend.add_observer(recorder)
        await backend.start()
        try:
            first = (await backend.send_goal(goal(0.5, 20.0))).goal_id
            await recorder.wait_for(lambda: any(e.goal_id == first for e in recorder.events))
            # A second goal preempts the first; the loop is killed before anything else.
            second = (await backend.send_goal(goal(-0.5, 20.0))).goal_id
            assert backend.info is not None
            assert backend.status()["loop_pid"] == backend.info.pid
            os.kill(backend.info.pid, signal.SIGKILL)
            code = await asyncio.wait_for(backend.wait_exited(), WAIT_S)
            assert code == -signal.SIGKILL

            death = "control loop died: killed by SIGKILL"
            assert backend.death == death
            for goal_id in (first, second):
                results = recorder.results(goal_id)
                assert len(results) == 1, (goal_id, recorder.events)
            (last,) = recorder.results(second)
            assert (last.status, int(last.error_code), last.error_string) == (
                GoalStatus.ABORTED, -1, death,
            )
            # The first ended once: preempted by the loop before it died, or by the backend.
            (early,) = recorder.results(first)
            assert early.status in (GoalStatus.CANCELED, GoalStatus.ABORTED)

            status = backend.status()
            assert status["alive"] is False
            controller = status["controller"]
            assert controller["fault"] == death
            assert controller["active"] is False and controller["active_goal"] is None

            with pytest.raises(GoalRejected) as refused:
                await backend.send_goal(goal(0.0, 1.0))
            assert str(refused.value).startswith(death)
            assert "restarts it" in str(refused.value)
            with pytest.raises(GoalRejected):
                await backend.send_trajectory(goal(0.0, 1.0))
            with pytest.raises(ControllerStateError) as request:
                await backend.cancel_goal(second)
            assert str(request.value).startswith(death)
            count = len(recorder.events)
            await asyncio.sleep(0)  # nothing else is pending: no second result comes
            assert len(recorder.events) == count
        finally:
            await backend.stop("test over")
        assert backend.exit_code == -signal.SIGKILL

    asyncio.run(scenario())


def test_a_requested_stop_is_not_a_death(tmp_path: Path) -> None:
    hardware = [{"name": "arm", "kind": "mirror", "joints": JOINTS, "params": {}}]
    source = make_robot_config(tmp_path / "x.sock", JOINTS, hardware)

    async def scenario() -> None:
        backend = LoopBackend(load_robot(source), source)
        recorder = Recorder()
        backend.add_observer(recorder)
        await backend.start()
        goal_id = (await backend.send_goal(goal(0.5, 20.0))).goal_id
        assert await backend.stop("test over") == 0
        assert backend.death is None
        (result,) = recorder.results(goal_id)
        assert result.status is GoalStatus.ABORTED  # a deactivation, as upstream's
        assert result.error_string == "test over: holding position"
        assert backend.status()["alive"] is False
        assert backend.status()["controller"]["fault"] is None

    asyncio.run(scenario())
