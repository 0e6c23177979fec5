"""A shutdown with decelerating stops ends once the joints were read at rest, counted in cycles.

A real ``ControlLoop`` on simulated (mirror) joints, stepped on a simulated clock. The mirror
reaches a command at the next read, so the joints are read at rest one cycle after the cycle
that wrote the stop's rest command. On a busy host the cycle due at the stop's end can be
skipped; the loop must then still run the cycle after the one writing the rest command
(issue 22: it ended one period after the stop's end in clock time, before that reading).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterator
from pathlib import Path

import pytest

from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.daemon.channel.messages import Commit, Request, Shutdown
from jtc_hw.daemon.channel.pipe import Inbox
from jtc_hw.daemon.loop.cycle import ControlLoop
from jtc_hw.daemon.loop.outbox import Outbox
from jtc_hw.daemon.robot import load_robot

from conftest import make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")

JOINTS = ["a", "b"]
RATE = 500
PERIOD_NS = 1_000_000_000 // RATE
DECEL = 2.0


@pytest.fixture
def loop(tmp_path: Path) -> Iterator[tuple[ControlLoop, Inbox]]:
    hardware = [{"name": "arm", "kind": "mirror", "joints": JOINTS, "params": {}}]
    controller = {"constraints": {"decelerate_on_cancel": True, **{
        j: {"max_deceleration_on_cancel": DECEL} for j in JOINTS}}}
    robot = load_robot(make_robot_config(tmp_path / "x.sock", JOINTS, hardware,
                                         update_rate=RATE, controller=controller,
                                         path_tolerance=0.0, goal_tolerance=0.0))
    api, loop_end = multiprocessing.Pipe(duplex=True)
    outbox = Outbox(loop_end, 1 << 20, lambda: 0)
    inbox = Inbox(loop_end, 1 << 20)
    try:
        yield ControlLoop(robot, outbox), inbox
    finally:
        inbox.close()
        outbox.close()
        api.close()
        loop_end.close()


def moving_half_way(ctl: ControlLoop, inbox: Inbox) -> int:
    """Start the loop on a 2 s goal and cycle to its middle (the joints moving); the time."""
    now = 10_000_000_000
    ctl.start(now)
    trajectory = JointTrajectory(JOINTS, [TrajectoryPoint(2.0, [1.0, -1.0])])
    ctl._handle(Commit(1, ctl.ctrl.plan_goal(now, trajectory)), now)
    for _ in range(RATE // 2):
        now += PERIOD_NS
        ctl.cycle(now, PERIOD_NS, inbox)
    return now


def test_a_skipped_deadline_at_the_stops_end_does_not_end_the_loop_before_the_rest_reading(
    loop: tuple[ControlLoop, Inbox],
) -> None:
    ctl, inbox = loop
    now = moving_half_way(ctl, inbox)
    ctl._handle(Request(2, Shutdown("test")), now)
    end = None
    while end is None:
        now += PERIOD_NS
        ctl.cycle(now, PERIOD_NS, inbox)
        end = ctl.ctrl.stopping_until_ns
    # Regular cycles up to two periods before the stop's end, then two deadlines skipped (the
    # loop writes each cycle's command for the next deadline: the cycle writing the rest
    # command is the first whose next deadline is at or after the end).
    while now + 2 * PERIOD_NS < end:
        now += PERIOD_NS
        ctl.cycle(now, PERIOD_NS, inbox)
        assert not ctl._shutdown_stop_done(now)
    period = 3 * PERIOD_NS
    for _ in range(10):
        now += period
        ctl.cycle(now, period, inbox)
        period = PERIOD_NS
        if ctl._shutdown_stop_done(now):
            break
    else:
        pytest.fail("the loop never ended the shutdown's stop")
    # The cycle the loop ends on read the joints where the stop holds them: a further cycle
    # (the rest command written again) finds them not moved.
    last = ctl._last_state
    assert last is not None
    now += PERIOD_NS
    ctl.cycle(now, PERIOD_NS, inbox)
    after = ctl._last_state
    assert after is not None
    assert list(last.positions) == pytest.approx(list(after.positions), abs=1e-12)


def test_a_stop_the_host_starved_past_its_bound_ends_the_loop_and_says_so(
    loop: tuple[ControlLoop, Inbox], caplog: pytest.LogCaptureFixture,
) -> None:
    """The shutdown waits for the decelerating stop at most its duration plus a margin: a loop
    starved beyond that (no cycle for a second here) holds where the joints are, and its log
    says the stop was cut and how many deadlines were skipped, the evidence a reader needs."""
    ctl, inbox = loop
    now = moving_half_way(ctl, inbox)
    bound_s = ctl._begin_shutdown(now)
    assert isinstance(bound_s, float) and bound_s > 0
    for _ in range(3):  # the stop under way
        now += PERIOD_NS
        ctl.cycle(now, PERIOD_NS, inbox)
        assert not ctl._shutdown_stop_done(now)
    assert "decelerating stop had not ended" not in caplog.text
    starved = round(bound_s * RATE) + 1  # deadlines missed: the next cycle is past the bound
    now += (starved + 1) * PERIOD_NS
    ctl.cycle(now, (starved + 1) * PERIOD_NS, inbox)
    assert ctl._shutdown_stop_done(now)
    assert (f"daemon stopping: the decelerating stop had not ended by its bound; holding where "
            f"the joints are ({starved} deadlines skipped since the stop began)") in caplog.text
