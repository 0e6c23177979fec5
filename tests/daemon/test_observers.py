"""The backend's observers (jtc_hw.daemon.core.observers): every one hears every message, in the
order they were added, and one that raises costs the others nothing."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pytest

from jtc_hw.controller.goals import GoalFeedback, GoalResult
from jtc_hw.controller.joints import JointCommand
from jtc_hw.controller.messages import JointTrajectory
from jtc_hw.daemon.channel.messages import State
from jtc_hw.daemon.core.observers import Observers, state_json


class Seen:
    def __init__(self, name: str, log: list[tuple[str, str]], fail: bool = False) -> None:
        self.name, self.log, self.fail = name, log, fail

    def _saw(self, what: str) -> None:
        self.log.append((self.name, what))
        if self.fail:
            raise RuntimeError(f"{self.name} broke")

    def on_state(self, snapshot: dict[str, Any]) -> None:
        self._saw("state")

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None:
        self._saw("goal_event")

    def on_command(self, traj: JointTrajectory, goal_id: int | None) -> None:
        self._saw("command")

    def on_record(self, event: dict[str, Any]) -> None:
        self._saw("record")


def test_every_observer_hears_every_message_in_order_despite_one_failing(
    caplog: pytest.LogCaptureFixture,
) -> None:
    log: list[tuple[str, str]] = []
    observers = Observers()
    assert not observers
    for name, fail in (("recorders", False), ("server", True), ("view", False)):
        observers.add(Seen(name, log, fail))
    assert observers
    with caplog.at_level(logging.ERROR, logger="jtc_hw.backend"):
        observers.state({"time_ns": 1})
        observers.goal_event(None)  # type: ignore[arg-type]
        observers.command(JointTrajectory(["a"], []), None)
        observers.record({"event": "fault"})
    kinds = ("state", "goal_event", "command", "record")
    assert log == [(name, kind) for kind in kinds for name in ("recorders", "server", "view")]
    assert [r.getMessage() for r in caplog.records] == [
        f"Seen.on_{kind} failed; skipped" for kind in kinds
    ]


def test_the_state_snapshot_is_the_socket_state_event_body() -> None:
    nan = float("nan")
    command = JointCommand(np.array([0.5, nan]), None, None, None)
    state = State(7, np.arange(8.0).reshape(4, 2), np.array([0.1, 0.2]), np.array([0.0, 1.0]),
                  np.zeros((3, 2)), command, False, 3, 0.25, 0.2, None, command, 0.5, 1.0, 6)
    snapshot = state_json(state, ("a", "b"))
    assert snapshot["time_ns"] == 7 and snapshot["joint_names"] == ["a", "b"]
    assert snapshot["desired"] == {"positions": [0.0, 1.0], "velocities": [2.0, 3.0],
                                   "accelerations": [4.0, 5.0], "effort": [6.0, 7.0],
                                   "time_from_start": 0.25}
    assert snapshot["actual"]["accelerations"] is None
    assert snapshot["command"] == {"positions": [0.5, None]}  # NaN: nothing, as null
    assert snapshot["active_goal"] == 3 and snapshot["holding"] is False
    assert snapshot["speed_scaling"] == {"factor": 0.5, "target": 1.0}
