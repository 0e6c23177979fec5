"""The control loop when the API process stops reading: it never waits, it ends the goal.

A real ``ControlLoop`` on simulated joints, stepped on a simulated clock (the outbox's clock is
the same), writing into a real socketpair that nobody reads until the test says so: the
outbox fills the socket, the oldest result-bearing message waits ``api_stall_s``, and the loop
must end the goal ``ABORTED``, hold, refuse new goals and keep cycling; once the other end
reads, everything kept arrives in order and goals are accepted again.
"""

from __future__ import annotations

import multiprocessing
import socket
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jtc_hw.controller.goals import GoalResult, GoalStatus
from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.daemon.channel.messages import Commit, Committed, Events, Reference, Stale, State
from jtc_hw.daemon.channel.pipe import Inbox
from jtc_hw.daemon.loop.cycle import ControlLoop
from jtc_hw.daemon.loop.outbox import Outbox
from jtc_hw.daemon.robot import load_robot
from jtc_hw.errors import GoalRejected

from conftest import Rig as ControllerRig
from conftest import make_config, make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")

JOINTS = ["a", "b"]
RATE = 500
PERIOD_NS = 1_000_000_000 // RATE
API_STALL_S = 0.2


class Clock:
    def __init__(self) -> None:
        self.now = 10_000_000_000

    def __call__(self) -> int:
        return self.now


class Rig:
    """A loop, its two pipe ends and the simulated clock."""

    def __init__(self, tmp_path: Path, api: Connection, loop_end: Connection) -> None:
        hardware = [{"name": "arm", "kind": "mirror", "joints": JOINTS, "params": {}}]
        robot = load_robot(
            make_robot_config(tmp_path / "x.sock", JOINTS, hardware, update_rate=RATE,
                              api_stall_s=API_STALL_S)
        )
        self.clock = Clock()
        self.outbox = Outbox(loop_end, 1 << 20, self.clock)
        self.loop_inbox = Inbox(loop_end, 1 << 20)
        self.api_inbox = Inbox(api, 1 << 20, framed=False)
        self.loop = ControlLoop(robot, self.outbox)
        self.loop.start(self.clock.now)
        self.received: list[Any] = []
        self.cycles = 0

    def close(self) -> None:
        for inbox in (self.loop_inbox, self.api_inbox):
            inbox.close()
        self.outbox.close()

    def step(self, n: int = 1, read: bool = False) -> None:
        """``n`` cycles as ``ControlLoop.run`` does them; the API end reads if ``read``."""
        for _ in range(n):
            self.clock.now += PERIOD_NS
            self.loop.cycle(self.clock.now, PERIOD_NS, self.loop_inbox)
            self.loop.serve_outbox(self.clock.now)
            self.cycles += 1
            if read:
                self.read()

    def read(self) -> None:
        self.api_inbox.pump()
        while (message := self.api_inbox.pop()) is not None:
            self.received.append(message)

    def commit_goal(self, target: float, duration_s: float) -> Any:
        trajectory = JointTrajectory(
            JOINTS, [TrajectoryPoint(duration_s, [target] * len(JOINTS), [0.0] * len(JOINTS))]
        )
        plan = self.loop.ctrl.plan_goal(self.clock.now, trajectory)
        self.loop._handle(Commit(1, plan), self.clock.now)

    def results(self) -> list[GoalResult]:
        return [
            event
            for message in self.received
            if isinstance(message, Events)
            for event in message.events
            if isinstance(event, GoalResult)
        ]


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    api, loop_end = multiprocessing.Pipe(duplex=True)
    with socket.socket(fileno=loop_end.fileno()) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 16384)  # fills in a few cycles
        sock.detach()
    r = Rig(tmp_path, api, loop_end)
    try:
        yield r
    finally:
        r.close()
        api.close()
        loop_end.close()


def test_a_stalled_reader_ends_the_goal_and_the_loop_holds_and_recovers(rig: Rig) -> None:
    rig.step(5, read=True)
    rig.commit_goal(1.0, 10.0)
    rig.step(50, read=True)  # 0.1 s of a 10 s goal
    assert rig.loop.ctrl.active_goal is not None
    assert [m for m in rig.received if isinstance(m, Committed)]
    rig.received.clear()

    # The API process stops reading. The socket fills; the loop goes on cycling regardless.
    stall_cycles = 0
    while not rig.loop.api_stalled:
        rig.step()
        stall_cycles += 1
        assert stall_cycles < 10 * RATE, "no stall detected in 10 s of cycles"
    assert rig.loop.api_stalls == 1
    # It took at least api_stall_s of cycles after the socket filled.
    assert stall_cycles >= API_STALL_S * RATE
    rig.step()  # the abort is applied by the next update
    assert rig.loop.ctrl.holding and rig.loop.ctrl.active_goal is None
    assert rig.loop.ctrl.active and rig.loop.fault is None
    held = rig.loop.ctrl.reference.sample(rig.clock.now).positions.copy()

    # Still stalled: it keeps cycling (and holding) for another second, queueing little.
    pending = rig.outbox.pending_bytes
    full = rig.outbox.full_flushes
    rig.step(RATE)
    assert rig.outbox.full_flushes >= full + RATE - 1  # every cycle tried and left it waiting
    assert rig.outbox.pending_bytes < pending + 50_000  # state and status coalesced
    np.testing.assert_array_equal(rig.loop.ctrl.reference.sample(rig.clock.now).positions, held)

    # A goal now is refused: its feedback and result could not be delivered either.
    rig.commit_goal(0.0, 1.0)
    assert rig.loop.ctrl.active_goal is None

    # The API process reads again: everything kept arrives, in order; serving resumes.
    rig.step(20, read=True)
    assert not rig.loop.api_stalled
    (result,) = rig.results()
    assert result.status is GoalStatus.ABORTED
    assert "has not read the control loop's messages" in result.error_string
    assert "daemon.api_stall_s: 0.2 s" in result.error_string
    stale = [m for m in rig.received if isinstance(m, Stale)]
    assert len(stale) == 1 and "has not yet read" in stale[0].reason
    # The abort's new reference (a hold) comes right before the result: a client that sees
    # the result finds the hold in query_state.
    at = next(i for i, m in enumerate(rig.received)
              if isinstance(m, Events) and result in m.events)
    assert isinstance(rig.received[at - 1], Reference)
    assert rig.received[at - 1].trajectory is not None  # a hold, sent by value
    states = [m.time_ns for m in rig.received if isinstance(m, State)]
    assert states == sorted(states)
    assert len(states) < (rig.cycles * 50) // RATE  # fewer than published: coalesced
    status = rig.loop.status()["loop"]
    assert status["api_stalls"] == 1 and status["api_stalled"] is False
    assert status["outbox"]["dropped"] > 0 and status["outbox"]["full_flushes"] > RATE

    rig.commit_goal(0.0, 0.5)
    assert rig.loop.ctrl.active_goal is not None
    rig.step(RATE, read=True)
    (_, second) = rig.results()
    assert second.status is GoalStatus.SUCCEEDED


def test_a_reader_that_only_lags_behind_droppable_messages_is_not_a_stall(rig: Rig) -> None:
    rig.step(5, read=True)
    rig.commit_goal(0.5, 4.0)
    # Read only every 0.1 s: state piles up between reads, but nothing waits 0.2 s.
    for _ in range(30):
        rig.step(RATE // 10)
        rig.read()
    assert rig.loop.api_stalls == 0
    assert rig.loop.ctrl.active_goal is not None
    assert rig.results() == []


def test_controller_abort_as_the_loop_uses_it() -> None:
    """``abort`` ends a goal ABORTED and holds the measured position; a topic trajectory just
    stops; while holding, or inactive, nothing (or a refusal) happens."""
    rig = ControllerRig(make_config(), [0.0, 0.0])
    version = rig.ctrl.reference_version
    rig.ctrl.abort("nobody reads")  # holding: nothing to abort
    rig.step()
    assert rig.ctrl.reference_version == version and rig.results() == []

    goal_id = rig.ctrl.send_goal(rig.now, JointTrajectory(
        ("j1", "j2"), [TrajectoryPoint(2.0, [1.0, 1.0])]))
    rig.step(50)
    rig.ctrl.abort("nobody reads")
    rig.step()
    (result,) = rig.results(goal_id)
    assert (result.status, int(result.error_code), result.error_string) == (
        GoalStatus.ABORTED, -1, "nobody reads")
    assert rig.ctrl.holding
    held = rig.ctrl.reference.sample(rig.now).positions
    np.testing.assert_allclose(held, rig.mirror.p, atol=0.05)  # where the joints were
    assert 0.0 < held[0] < 1.0

    topic = JointTrajectory(("j1", "j2"), [TrajectoryPoint(2.0, [0.0, 0.0])])
    rig.ctrl.send_trajectory(rig.now, topic)
    rig.step(10)
    rig.ctrl.abort("nobody reads")
    rig.step()
    assert rig.ctrl.holding and len(rig.results()) == 1  # a topic trajectory has no result

    rig.ctrl.deactivate(rig.now)
    with pytest.raises(GoalRejected):
        rig.ctrl.abort("nobody reads")
