"""Issue 11 points 6 and 8 in the daemon: what deactivating the controller writes to the
hardware, and the log line of a result.

A real ``ControlLoop`` on two simulated (mirror) components, stepped on a simulated clock, its
messages read from a real socketpair. Each component's ``write`` and ``deactivate`` are
recorded (and still run): the point is the order in which the loop drives the hardware.
Sections refer to ``../shared/reference/jtc_upstream_behaviour.md``.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import pytest

from jtc_hw.controller.goals import ErrorCode, GoalResult, GoalStatus
from jtc_hw.controller.joints import JointCommand
from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.daemon.channel.messages import Commit, Events
from jtc_hw.daemon.channel.pipe import Inbox
from jtc_hw.daemon.core.backend import LoopBackend
from jtc_hw.daemon.loop.cycle import ControlLoop
from jtc_hw.daemon.loop.outbox import Outbox
from jtc_hw.daemon.robot import load_robot
from jtc_hw.hardware.mirror import MirrorHardware

from conftest import make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")

JOINTS = ["a", "b"]
RATE = 500
PERIOD_NS = 1_000_000_000 // RATE


class Rig:
    """A loop over components ``left`` (joint a) and ``right`` (joint b), recording their
    writes and deactivations in order."""

    def __init__(
        self, tmp_path: Path, api: Connection, loop_end: Connection, command: list[str]
    ) -> None:
        hardware = [
            {"name": "left", "kind": "mirror", "joints": ["a"], "params": {}},
            {"name": "right", "kind": "mirror", "joints": ["b"], "params": {}},
        ]
        robot = load_robot(
            make_robot_config(
                tmp_path / "x.sock", JOINTS, hardware, update_rate=RATE,
                command_interfaces=command, path_tolerance=0.0, goal_tolerance=0.0,
            )
        )
        self.now = 10_000_000_000
        self.outbox = Outbox(loop_end, 1 << 20, lambda: self.now)
        self.loop_inbox = Inbox(loop_end, 1 << 20)
        self.api_inbox = Inbox(api, 1 << 20, framed=False)
        self.loop = ControlLoop(robot, self.outbox)
        self.calls: list[tuple[str, str, JointCommand | None]] = []
        for comp in self.loop.hardware.components:
            self._record(comp)
        self.loop.start(self.now)
        self.received: list[Any] = []

    def _record(self, comp: Any) -> None:
        write, deactivate = comp.write, comp.deactivate

        def recorded_write(now_ns: int, command: JointCommand) -> None:
            self.calls.append((comp.name, "write", command))
            write(now_ns, command)

        def recorded_deactivate(now_ns: int) -> None:
            self.calls.append((comp.name, "deactivate", None))
            deactivate(now_ns)

        comp.write, comp.deactivate = recorded_write, recorded_deactivate

    def close(self) -> None:
        for inbox in (self.loop_inbox, self.api_inbox):
            inbox.close()
        self.outbox.close()

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self.now += PERIOD_NS
            self.loop.cycle(self.now, PERIOD_NS, self.loop_inbox)
            self.loop.serve_outbox(self.now)
            self.read()

    def read(self) -> None:
        self.api_inbox.pump()
        while (message := self.api_inbox.pop()) is not None:
            self.received.append(message)

    def commit_goal(self, target: float, duration_s: float) -> None:
        trajectory = JointTrajectory(JOINTS, [TrajectoryPoint(duration_s, [target, -target])])
        plan = self.loop.ctrl.plan_goal(self.now, trajectory)
        self.loop._handle(Commit(1, plan), self.now)

    def results(self) -> list[GoalResult]:
        return [
            event
            for message in self.received
            if isinstance(message, Events)
            for event in message.events
            if isinstance(event, GoalResult)
        ]

    def since(self, mark: int) -> list[tuple[str, str, JointCommand | None]]:
        return self.calls[mark:]


@pytest.fixture
def make_rig(tmp_path: Path) -> Iterator[Any]:
    made: list[tuple[Rig, Connection, Connection]] = []

    def make(command: list[str]) -> Rig:
        api, loop_end = multiprocessing.Pipe(duplex=True)
        rig = Rig(tmp_path, api, loop_end, command)
        made.append((rig, api, loop_end))
        return rig

    yield make
    for rig, api, loop_end in made:
        rig.close()
        api.close()
        loop_end.close()


def _velocity(command: JointCommand | None) -> float:
    assert command is not None and command.velocities is not None
    return float(command.velocities[0])


def test_stopping_the_daemon_writes_zero_velocity_before_the_safe_action(make_rig: Any) -> None:
    """Sections 3 and 9 (deactivate): the goal ends ABORTED (-1) and velocity commands are
    written 0, position left as it is (NaN: not written), to every component, before each
    component's own safe action."""
    rig = make_rig(["position", "velocity"])
    rig.commit_goal(1.0, 2.0)
    rig.step(100)
    (_, op, moving) = rig.calls[-1]
    assert op == "write" and abs(_velocity(moving)) > 0.1  # the joints were commanded to move
    mark = len(rig.calls)
    rig.loop._shutdown_reason = "daemon stopping (SIGTERM)"
    rig.loop.shutdown(rig.now)
    rig.loop.serve_outbox(rig.now)
    rig.read()
    calls = rig.since(mark)
    assert [(name, op) for name, op, _ in calls] == [
        ("left", "write"), ("right", "write"), ("left", "deactivate"), ("right", "deactivate"),
    ]
    for _, _, command in calls[:2]:
        assert command is not None and command.positions is not None
        assert _velocity(command) == 0.0 and math.isnan(command.positions[0])
    (result,) = rig.results()
    assert (result.status, result.error_code, result.error_string) == (
        GoalStatus.ABORTED,
        ErrorCode.INVALID_GOAL,
        "daemon stopping (SIGTERM): holding position",
    )


def test_a_fault_writes_zero_velocity_only_to_the_components_that_did_not_fail(
    make_rig: Any,
) -> None:
    """Section 3 (deactivate) with a hardware fault: the controller is deactivated; the healthy
    component gets the zeroed velocity command, the failed one is not written (as upstream's
    controller manager stops writing to a component in error); both then take their safe
    action."""
    rig = make_rig(["position", "velocity"])
    rig.commit_goal(1.0, 2.0)
    rig.step(100)
    right = rig.loop.hardware.component("right")
    assert isinstance(right, MirrorHardware)
    right.inject_fault("servo 2 stopped answering (injected)")
    mark = len(rig.calls)
    rig.step()
    calls = rig.since(mark)
    assert [(name, op) for name, op, _ in calls] == [
        ("left", "write"), ("left", "deactivate"), ("right", "deactivate"),
    ]
    assert _velocity(calls[0][2]) == 0.0
    (result,) = rig.results()
    assert (result.status, result.error_code) == (GoalStatus.ABORTED, ErrorCode.INVALID_GOAL)
    assert result.error_string.startswith("hardware fault: ")


def test_position_only_commands_are_not_written_again_at_deactivation(make_rig: Any) -> None:
    """Section 3 (deactivate): with only a position command interface there is nothing to zero
    and the position is left as it is: no write, just the safe action."""
    rig = make_rig(["position"])
    rig.commit_goal(0.5, 1.0)
    rig.step(20)
    mark = len(rig.calls)
    rig.loop.shutdown(rig.now)
    assert [(name, op) for name, op, _ in rig.since(mark)] == [
        ("left", "deactivate"), ("right", "deactivate"),
    ]


def test_the_daemon_log_line_of_a_result_has_its_details(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Section 7 step 8d: the result keeps upstream's text; the daemon's log line adds the
    details after it, so the journal still says which joint failed."""
    hardware = [{"name": "arm", "kind": "mirror", "joints": JOINTS, "params": {}}]
    source = make_robot_config(tmp_path / "x.sock", JOINTS, hardware)
    backend = LoopBackend(load_robot(source), source)
    result = GoalResult(
        4, GoalStatus.ABORTED, ErrorCode.PATH_TOLERANCE_VIOLATED,
        "Aborted due to path tolerance violation", 1,
        "joint 'b' position error +0.06 exceeds 0.05",
    )
    with caplog.at_level(logging.INFO, logger="jtc_hw.backend"):
        backend._dispatch(Events((result,)))
    assert caplog.messages == [
        "goal 4 aborted (-4): Aborted due to path tolerance violation: joint 'b' position "
        "error +0.06 exceeds 0.05"
    ]
    assert backend._open_goals == {}
