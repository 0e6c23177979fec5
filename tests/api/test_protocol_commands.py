"""``subscribe_state`` with ``commands``, and the ``command`` event's round trip."""

from __future__ import annotations

import pytest

from jtc_hw.api.events import command_event, trajectory_from_json
from jtc_hw.api.framing import RequestError
from jtc_hw.api.protocol import parse_request
from jtc_hw.api.requests import SubscribeState
from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint


def test_commands_is_an_optional_boolean() -> None:
    assert parse_request({"op": "subscribe_state", "id": 1}) == SubscribeState(1, False)
    assert parse_request({"op": "subscribe_state", "id": 2, "commands": True}) == \
        SubscribeState(2, True)
    with pytest.raises(RequestError, match="commands") as info:
        parse_request({"op": "subscribe_state", "id": 3, "commands": "yes"})
    assert info.value.request_id == 3


def test_a_command_event_gives_back_the_trajectory() -> None:
    sent = JointTrajectory(
        ["a", "b"],
        [TrajectoryPoint(0.25, [1.0, 2.0], [0.0, 0.5]),
         TrajectoryPoint(1.5, [1.5, 2.5], None, None, [0.1, 0.2])],
        start_time_ns=123_456_789,
    )
    event = command_event(sent, 7, 42)
    assert (event["event"], event["goal_id"], event["time_ns"]) == ("command", 7, 42)
    back = trajectory_from_json(event["trajectory"])
    assert back.joint_names == sent.joint_names and back.start_time_ns == sent.start_time_ns
    assert [p.time_from_start_ns for p in back.points] == [250_000_000, 1_500_000_000]
    assert [p.positions for p in back.points] == [(1.0, 2.0), (1.5, 2.5)]
    assert back.points[0].velocities == (0.0, 0.5) and back.points[1].velocities is None
    assert back.points[1].effort == (0.1, 0.2)
    stop = trajectory_from_json(command_event(JointTrajectory(["a"], []), None, 1)["trajectory"])
    assert stop.points == () and stop.start_time_ns == 0
