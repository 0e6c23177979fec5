"""What the loop does after a cycle: a plan or request the inbox completes is handled at once.

A real ``ControlLoop`` on simulated joints, stepped on a simulated clock, with the API end of a
real socketpair: a plan sent while the loop cycles must be committed by the ``after_cycle`` that
reads its last bytes, at that cycle's deadline, and the ``committed`` answer written by that same
``after_cycle`` -- not a period later -- without the joints' command changing at that deadline.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.daemon.channel.messages import Commit, Committed, Reference, Reply, Request, Stop
from jtc_hw.daemon.channel.pipe import Inbox, send_framed
from jtc_hw.daemon.loop.cycle import ControlLoop
from jtc_hw.daemon.loop.outbox import Outbox
from jtc_hw.daemon.robot import load_robot

from conftest import make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")

JOINTS = ["a", "b"]
RATE = 500
PERIOD_NS = 1_000_000_000 // RATE


class Rig:
    def __init__(self, tmp_path: Path) -> None:
        hardware = [{"name": "arm", "kind": "mirror", "joints": JOINTS, "params": {}}]
        robot = load_robot(
            make_robot_config(tmp_path / "x.sock", JOINTS, hardware, update_rate=RATE)
        )
        self.api, self.loop_end = multiprocessing.Pipe(duplex=True)
        self.now = 10_000_000_000
        self.outbox = Outbox(self.loop_end, 1 << 20, lambda: self.now)
        self.loop_inbox = Inbox(self.loop_end, 1 << 20)
        self.api_inbox = Inbox(self.api, 1 << 20, framed=False)
        self.loop = ControlLoop(robot, self.outbox)
        self.loop.start(self.now)

    def close(self) -> None:
        for inbox in (self.loop_inbox, self.api_inbox):
            inbox.close()
        self.outbox.close()
        self.api.close()
        self.loop_end.close()

    def cycle(self) -> None:
        self.now += PERIOD_NS
        self.loop.cycle(self.now, PERIOD_NS, self.loop_inbox)

    def received(self) -> list[Any]:
        self.api_inbox.pump()
        out = []
        while (message := self.api_inbox.pop()) is not None:
            out.append(message)
        return out


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    r = Rig(tmp_path)
    try:
        yield r
    finally:
        r.close()


def test_a_plan_is_committed_by_the_after_cycle_that_completes_it(rig: Rig) -> None:
    rig.cycle()
    rig.loop.after_cycle(rig.now, rig.loop_inbox)
    rig.received()
    trajectory = JointTrajectory(JOINTS, [TrajectoryPoint(1.0, [0.5, -0.5], [0.0, 0.0])])
    # Planned as the API process plans: a little ahead, valid from two periods back.
    plan = rig.loop.ctrl.plan_goal(
        rig.now + 3 * PERIOD_NS, trajectory, valid_from_ns=rig.now - 2 * PERIOD_NS
    )
    rig.cycle()  # the plan is sent while this cycle runs
    sampled = rig.loop.ctrl.reference.sample(rig.now)
    send_framed(rig.api, Commit(41, plan))
    messages: list[Any] = []
    for _ in range(100):  # the pump stops at a time of the real clock: it may take several
        rig.loop.after_cycle(rig.now, rig.loop_inbox)
        messages += rig.received()
        if rig.loop.ctrl.active_goal is not None:
            break  # committed by this after_cycle: its answer must be out already
        assert not messages
    committed = [m for m in messages if isinstance(m, Committed)]
    assert committed == [Committed(41, 1)]
    references = [m for m in messages if isinstance(m, Reference)]
    assert references and references[-1].plan_id == 41  # by plan id, before Committed
    assert messages.index(references[-1]) < messages.index(committed[0])
    assert rig.loop.ctrl.active_goal == 1
    # The deadline already sampled gets the same desired state from the new reference.
    after = rig.loop.ctrl.reference.sample(rig.now)
    for a, b in zip(sampled, after, strict=True):
        np.testing.assert_array_equal(a, b)
    rig.cycle()  # and the next cycle follows the goal
    assert rig.loop.ctrl.active_goal == 1


def test_a_request_is_answered_by_the_after_cycle_that_completes_it(rig: Rig) -> None:
    rig.cycle()
    send_framed(rig.api, Request(5, Stop()), bulk=False)
    rig.loop.after_cycle(rig.now, rig.loop_inbox)  # one record: read whatever the time
    assert Reply(5, True) in rig.received()



def test_a_state_is_written_a_cycle_after_the_one_that_builds_it(rig: Rig) -> None:
    """No cycle pays for both building the State and writing it (the period's p99): the State
    waits in the outbox for the next cycle's write, unless an ordered message is behind it;
    and none is dropped for it when the next cycle publishes one too."""
    from jtc_hw.daemon.channel.messages import State

    def states() -> list[State]:
        return [m for m in rig.received() if isinstance(m, State)]

    rig.loop.state_every_ns = 10 * PERIOD_NS
    rig.cycle()  # the first State, the reference: written at once (ordered messages wait)
    rig.loop.serve_outbox(rig.now)
    rig.received()
    for _ in range(30):  # until a cycle publishes the next
        rig.cycle()
        if rig.loop._state_cycle:
            break
        rig.loop.serve_outbox(rig.now)
    built = rig.now
    rig.loop.serve_outbox(rig.now)
    assert states() == []  # not written by the cycle that built it
    rig.cycle()
    rig.loop.serve_outbox(rig.now)
    assert [s.time_ns for s in states()] == [built]  # the next one did
    # An ordered message behind it: written at once, State and all, in order.
    for _ in range(30):
        rig.cycle()
        if rig.loop._state_cycle:
            break
    rig.loop.send(Reply(9, True))
    rig.loop.serve_outbox(rig.now)
    got = rig.received()
    assert [type(m) for m in got][-2:] == [State, Reply]
    # A State every cycle: each one written by its own cycle (deferring would drop half).
    rig.loop.state_every_ns = PERIOD_NS
    rig.loop._next_state_ns = 0
    written = []
    for _ in range(5):
        rig.cycle()
        rig.loop.serve_outbox(rig.now)
        written += [s.time_ns for s in states()]
    assert written == [rig.now - k * PERIOD_NS for k in range(4, -1, -1)]
    assert rig.outbox.dropped == 0
