"""The request layer without a transport: every operation answered as a value, later messages
through an outlet the test implements (as a transport would), goal events routed in order; and
the transports' registry over it.

``FakeBackend`` is the small controller host of the server tests (the real controller on a
simulated clock), so these run in milliseconds and need no socket.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.fake_backend import FakeBackend
from helpers.peers import goal_msg, run

from jtc_hw.api.framing import RequestError, encode
from jtc_hw.api.protocol import OPS, parse_request
from jtc_hw.controller.limits_check import TimeScaling
from jtc_hw.daemon.core.backend_api import Accepted
from jtc_hw.daemon.core.requests import Caller, Requests, accepted_goal
from jtc_hw.daemon.settings import DaemonSettings
from jtc_hw.daemon.transports.registry import TRANSPORTS, Wiring
from jtc_hw.daemon.transports.server import Server
from jtc_hw.daemon.transports.zenoh_iface import ZenohInterface
from jtc_hw.daemon.zenoh_config import ZenohSettings


class Outlet:
    """A transport's outlet that records what it was given (``room``: droppable ones taken)."""

    def __init__(self, room: int = 1000) -> None:
        self.gone = False
        self.room = room
        self.messages: list[dict[str, Any]] = []

    def send(self, data: bytes) -> bool:
        if self.gone:
            return False
        self.messages.append(json.loads(data))
        return True

    def offer(self, data: bytes) -> bool:
        if self.gone or self.room <= 0:
            return False
        self.room -= 1
        self.messages.append(json.loads(data))
        return True

    def events(self, kind: str) -> list[dict[str, Any]]:
        return [m for m in self.messages if m.get("event") == kind]


@pytest.fixture
def layer() -> Iterator[tuple[Requests, FakeBackend]]:
    backend = FakeBackend()
    requests = Requests(backend, max_message_bytes=1024)
    requests.listen()
    yield requests, backend
    requests.close()


def caller(number: int = 1, outlet: Outlet | None = None) -> Caller:
    return Caller(number, f"test caller {number}", outlet or Outlet())


async def ask(requests: Requests, who: Caller, op: str, **fields: Any) -> dict[str, Any]:
    answer = await requests.answer(who, parse_request({"id": op, "op": op, **fields}))
    assert answer.data == encode(answer.message)  # the bytes every transport sends
    assert answer.message["id"] == op
    return answer.message


REQUESTS: dict[str, dict[str, Any]] = {
    "hello": {"protocol_version": 1},
    "auth": {"token": "anything: the transport checked it"},
    "send_goal": {"trajectory": goal_msg()},
    "cancel_goal": {"goal_id": 999},
    "send_trajectory": {"trajectory": goal_msg()},
    "stop": {},
    "query_state": {"in": 0.0},
    "subscribe_state": {"commands": True},
    "unsubscribe_state": {},
    "get_config": {},
    "get_status": {},
    "sim": {"component": "mirror", "freeze": True},
    "rearm": {},
    "get_parameters": {"names": ["cmd_timeout"]},
    "set_parameters": {"parameters": {"cmd_timeout": 1}},
    "set_speed_scaling": {"factor": 0.5},
}


def test_every_operation_is_answered_as_a_value(layer: tuple[Requests, FakeBackend]) -> None:
    requests, _ = layer
    assert set(REQUESTS) == set(OPS)
    requests.status_sections["extra"] = lambda: {"counted": 1}
    requests.server_status = lambda who: {"you": who.number}
    who = caller(7)

    async def main() -> dict[str, dict[str, Any]]:
        return {op: await ask(requests, who, op, **fields) for op, fields in REQUESTS.items()}

    replies = run(main())
    failed = {op: r["error"]["code"] for op, r in replies.items() if not r["ok"]}
    assert failed == {"cancel_goal": "not_found"}
    assert replies["send_goal"]["accepted"] is True and replies["auth"]["authenticated"]
    assert replies["hello"]["max_message_bytes"] == 1024
    status = replies["get_status"]
    assert list(status)[-2:] == ["extra", "server"]  # the sections, the server's last
    assert status["extra"] == {"counted": 1} and status["server"] == {"you": 7}
    assert replies["subscribe_state"]["commands"] is True
    assert not who.subscribed and not who.commands  # unsubscribed after
    assert replies["stop"]["stopped"] is True and replies["rearm"]["rearmed"] is False


def test_failures_are_error_replies_never_exceptions(
    layer: tuple[Requests, FakeBackend], caplog: pytest.LogCaptureFixture
) -> None:
    requests, backend = layer
    who = caller()

    async def main() -> None:
        refused = await requests.answer(who, RequestError("bad_json", "line 1: nope", 4))
        assert refused.message == {
            "id": 4, "ok": False, "error": {"code": "bad_json", "message": "line 1: nope"}}
        unknown = await ask(requests, who, "sim", component="arm", freeze=True)
        assert unknown["error"]["code"] == "bad_request"
        backend.status_error = RuntimeError("boom")
        failed = await ask(requests, who, "get_status")
        assert failed["error"] == {"code": "internal", "message": "internal error: "
                                   "RuntimeError: boom"}
        backend.status_error = None
        backend.extra_config = object()  # not JSON-able: encoding fails inside the layer
        unencodable = await ask(requests, who, "get_config")
        assert unencodable["error"]["code"] == "internal"

    with caplog.at_level(logging.INFO, logger="jtc_hw.server"):
        run(main())
    assert "test caller 1: rejected request (id 4): bad_json" in caplog.text
    assert "test caller 1: get_status failed" in caplog.text


def test_a_goals_events_follow_its_reply_even_when_they_arrive_first(
    layer: tuple[Requests, FakeBackend],
) -> None:
    """The backend delivers the goal's first feedback before ``send_goal`` returns; the
    transport queues the reply at once (its one rule); a feedback arriving before the held
    one is released queues up behind it."""
    requests, backend = layer
    backend.early_feedback = True
    outlet = Outlet()
    who = caller(outlet=outlet)

    async def main() -> None:
        answer = await requests.answer(
            who, parse_request({"id": 1, "op": "send_goal", "trajectory": goal_msg()}))
        outlet.send(answer.data)  # the transport's reply, queued before it awaits
        goal_id = answer.message["goal_id"]
        assert requests.goals_routed == [goal_id] and who.goals == {goal_id}
        backend.step(0.05)  # more feedback before the event loop's next round
        assert [m.get("event") for m in outlet.messages] == [None]
        await asyncio.sleep(0)
        kinds = [m.get("event") for m in outlet.messages]
        assert kinds[0] is None and set(kinds[1:]) == {"feedback"} and len(kinds) > 2
        times = [m["time_from_start"] for m in outlet.events("feedback")]
        assert times == sorted(times)
        backend.step(1.5)
        assert [m["goal_id"] for m in outlet.events("result")] == [goal_id]
        assert requests.goals_routed == [] and not who.goals

    run(main())


def test_a_result_whose_caller_left_is_discarded_and_counted(
    layer: tuple[Requests, FakeBackend],
) -> None:
    requests, backend = layer
    outlet = Outlet()
    who = caller(outlet=outlet)

    async def main() -> None:
        await ask(requests, who, "send_goal", trajectory=goal_msg(t=0.2))
        outlet.gone = True
        requests.leave(who)
        backend.step(1.0)

    run(main())
    assert requests.results_discarded == 1 and outlet.messages == []
    assert who.goals_ended_at > float("-inf")  # the idle clock starts at the goal's end


def test_state_reaches_subscribers_with_what_each_missed(
    layer: tuple[Requests, FakeBackend],
) -> None:
    requests, backend = layer
    full, roomy, deaf = Outlet(room=0), Outlet(), Outlet()
    a, b, c = caller(1, full), caller(2, roomy), caller(3, deaf)

    async def main() -> None:
        await ask(requests, a, "subscribe_state")
        await ask(requests, b, "subscribe_state")

    run(main())
    backend.publish_state(seq=1)
    full.room = 1
    backend.publish_state(seq=2)
    assert [s["seq"] for s in roomy.events("state")] == [1, 2]
    assert [(s["seq"], s["dropped"]) for s in full.events("state")] == [(2, 1)]
    assert a.dropped_state == 1 and a.dropped_total == 1 and a.dropped_since_state == 0
    assert deaf.messages == [] and not c.subscribed
    requests.leave(b)
    backend.publish_state(seq=3)
    assert [s["seq"] for s in roomy.events("state")] == [1, 2]


def test_the_accepted_goal_is_read_in_one_place() -> None:
    assert accepted_goal(Accepted(7)) == (7, {})
    assert accepted_goal(Accepted.of(8, None)) == (8, {})
    assert accepted_goal(Accepted.of(9, TimeScaling(2.0, 3.5))) == (
        9, {"time_scale": 2.0, "duration_s": 3.5})
    assert accepted_goal(Accepted(10, 1.0, 2.25)) == (
        10, {"time_scale": 1.0, "duration_s": 2.25})


def test_a_transport_is_one_registration_over_the_shared_layer(tmp_path: Path) -> None:
    backend = FakeBackend()
    requests = Requests(backend, max_message_bytes=1024)
    observers: list[object] = []
    socket = str(tmp_path / "d.sock")
    plain = Wiring(requests, DaemonSettings(socket=socket), "arm", observers.append, backend.status)
    assert [r.name for r in TRANSPORTS] == ["socket", "zenoh", "ros2"]
    opened = {r.name: r.open(plain) for r in TRANSPORTS}
    server = opened["socket"]
    assert isinstance(server, Server) and server.requests is requests
    assert opened["zenoh"] is None  # daemon.zenoh absent: off
    assert opened["ros2"] is None  # daemon.ros2 absent: off
    zenoh = ZenohSettings(prefix="jtc/t/a", token="0123456789abcdef-token")
    wired = Wiring(requests, DaemonSettings(socket=socket, zenoh=zenoh), "arm", observers.append,
                   backend.status)
    iface = TRANSPORTS[1].open(wired)
    assert isinstance(iface, ZenohInterface) and iface.prefix == "jtc/t/a"
    assert observers == [] and requests.status_sections == {}  # both once started
