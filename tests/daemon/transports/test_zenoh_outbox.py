"""The Zenoh interface's bounds, without a Zenoh session: its outbox (what is dropped when
Zenoh is slow), its limit on queries executing at once (``busy``) and on wrong-token refusals
waiting (``unauthorized``); and a query executed by the request layer."""

from __future__ import annotations

import asyncio
import json
import struct
import threading
from types import SimpleNamespace
from typing import Any

import pytest
from helpers.fake_backend import FakeBackend
from helpers.peers import goal_msg

from jtc_hw.api.framing import RequestError
from jtc_hw.api.requests import SendGoal
from jtc_hw.daemon.core.requests import Requests
from jtc_hw.daemon.transports.zenoh_iface import (
    MAX_QUERIES,
    MAX_REFUSALS_WAITING,
    WRONG_TOKEN_DELAY_S,
    ZenohInterface,
    split_attachment,
)
from jtc_hw.daemon.transports.zenoh_outbox import Outbox
from jtc_hw.daemon.zenoh_config import ZenohSettings

pytestmark = pytest.mark.usefixtures("no_leaks")


def test_outbox_drops_state_first_and_keeps_results_up_to_its_hard_cap() -> None:
    gate = threading.Event()
    ran: list[str] = []
    outbox = Outbox(size=2, hard_cap=4, label="zenoh")
    try:
        assert outbox.put(lambda: (gate.wait(10), ran.append("blocker"))[1])  # Zenoh is slow
        assert outbox.offer(lambda: ran.append("state 1"))
        offered = [outbox.offer(lambda: ran.append("state 2")) for _ in range(3)]
        assert offered.count(True) <= 1 and outbox.dropped >= 2
        assert outbox.put(lambda: ran.append("result"))  # beyond size: still kept
        while outbox.put(lambda: ran.append("reply")):
            pass
        assert outbox.lost == 1  # only at the hard cap
    finally:
        gate.set()
        outbox.close(timeout_s=10)
    assert ran[0] == "blocker" and "result" in ran and ran.index("result") > ran.index("state 1")


TOKEN = "sixteen characters or more"


class FakePayload:
    def __init__(self, body: bytes) -> None:
        self.body = body

    def __len__(self) -> int:
        return len(self.body)

    def to_bytes(self) -> bytes:
        return self.body


class FakeQuery:
    def __init__(self, key: str, body: bytes = b"{}", token: str | None = None) -> None:
        self.key_expr = key
        self.payload = FakePayload(body)
        self.attachment = None if token is None else SimpleNamespace(
            to_bytes=lambda: token.encode())
        self.replies: list[tuple[str, dict[str, Any]]] = []
        self.dropped = False

    def reply(self, key: str, data: bytes) -> None:
        self.replies.append((key, json.loads(data)))

    def drop(self) -> None:
        self.dropped = True


def interface() -> ZenohInterface:
    requests = SimpleNamespace(backend=SimpleNamespace(joint_names=["j1"]),
                               max_message_bytes=1024)
    return ZenohInterface(ZenohSettings(prefix="jtc/t/a", token=TOKEN), "c",
                          requests, dict)  # type: ignore[arg-type]


def test_queries_over_the_limit_are_answered_busy_at_once() -> None:
    iface = interface()
    iface._aio = asyncio.new_event_loop()
    try:
        iface._inflight = MAX_QUERIES  # that many executing already
        query = FakeQuery("jtc/t/a/rpc/get_status")
        iface._on_query(query)
        assert query.dropped and len(query.replies) == 1
        key, reply = query.replies[0]
        assert key == "jtc/t/a/rpc/get_status"
        assert reply["ok"] is False and reply["error"]["code"] == "busy"
        assert iface._inflight == MAX_QUERIES and iface.busy == 1
    finally:
        iface._aio.close()


def test_a_query_naming_no_operation_is_not_answered() -> None:
    iface = interface()
    iface._aio = asyncio.new_event_loop()
    try:
        query = FakeQuery("jtc/**")
        iface._on_query(query)
        assert query.dropped and not query.replies and iface._inflight == 0
    finally:
        iface._aio.close()


def test_a_missing_token_is_refused_at_once_a_wrong_one_late_and_bounded() -> None:
    iface = interface()
    aio = iface._aio = asyncio.new_event_loop()
    iface._outbox = Outbox(OUTBOX, OUTBOX, "zenoh")
    try:
        missing = FakeQuery("jtc/t/a/rpc/stop")
        iface._on_query(missing)
        iface._outbox.close(timeout_s=10)  # runs what waits: the refusal, sent at once
        assert missing.dropped and [r["error"]["code"] for _, r in missing.replies] == [
            "unauthorized"]
        iface._outbox = Outbox(OUTBOX, OUTBOX, "zenoh")
        t0 = aio.time()
        wrong = [FakeQuery("jtc/t/a/rpc/send_goal", token="x" * 16)
                 for _ in range(MAX_REFUSALS_WAITING + 1)]
        for query in wrong:
            iface._on_query(query)
        # Not one answered yet; the one beyond the bound is dropped without a reply.
        assert not any(q.replies for q in wrong)
        assert wrong[-1].dropped and all(not q.dropped for q in wrong[:-1])
        assert iface._refusals_waiting == MAX_REFUSALS_WAITING and iface._inflight == 0
        # The refusals are timers of the event loop, due after the delay.
        aio.run_until_complete(asyncio.sleep(0))  # call_soon_threadsafe's callbacks ran
        timers = sorted(h.when() for h in aio._scheduled)  # type: ignore[attr-defined]
        assert len(timers) == MAX_REFUSALS_WAITING
        assert timers[0] >= t0 + WRONG_TOKEN_DELAY_S  # on the loop's clock
        aio.run_until_complete(asyncio.sleep(WRONG_TOKEN_DELAY_S + 0.1))  # the loop's clock
        iface._outbox.close(timeout_s=10)
        assert all(q.replies[0][1]["error"]["code"] == "unauthorized" for q in wrong[:-1])
        assert iface._refusals_waiting == 0 and iface.unauthorized == len(wrong) + 1
        # The right token goes on to the event loop, as before.
        good = FakeQuery("jtc/t/a/rpc/stop", token=TOKEN)
        iface._on_query(good)
        assert iface._inflight == 1 and not good.replies and not good.dropped
        iface._inflight = 0
    finally:
        aio.close()


OUTBOX = 64


@pytest.mark.parametrize(("op", "body", "code"), [
    ("stop", b"", None),
    ("stop", b'{"op": "stop", "id": "x"}', None),
    ("stop", b'{\n  "id": 3\n}\n', None),
    ("stop", b'{"op": "hello"}', "bad_request"),
    ("auth", b'{"token": "t"}', "bad_request"),
    ("nope", b"{}", "unknown_op"),
    ("stop", b"{nope", "bad_json"),
    ("stop", b'{"pad": "' + b"x" * 2000 + b'"}', "too_large"),
])
def test_decode(op: str, body: bytes, code: str | None) -> None:
    item = ZenohInterface.decode(op, body, 1024)
    if code is None:
        assert getattr(item, "op", None) == op, item
    else:
        assert getattr(item, "code", None) == code, item


def test_a_query_is_answered_by_the_request_layer_with_no_stand_in_connection() -> None:
    """``send_goal`` too: its reply is the layer's returned value (the socket's bytes), and
    the goal's later events, published on ``events`` by the observer, go nowhere else."""
    backend = FakeBackend()
    requests = Requests(backend, max_message_bytes=1 << 20)
    requests.listen()
    iface = ZenohInterface(ZenohSettings(prefix="jtc/t/a", token=TOKEN), "c", requests, dict)
    aio = iface._aio = asyncio.new_event_loop()
    iface._outbox = Outbox(OUTBOX, OUTBOX, "zenoh")
    body = json.dumps({"id": 5, "trajectory": goal_msg()}).encode()
    query = FakeQuery("jtc/t/a/rpc/send_goal", body, token=TOKEN)
    try:
        iface._inflight = 1  # as _on_query leaves it
        aio.run_until_complete(iface._execute(query, "send_goal", body))
        iface._outbox.close(timeout_s=10)
        assert query.dropped and iface._inflight == 0
        [(key, reply)] = query.replies
        goal_id = reply["goal_id"]
        assert key == "jtc/t/a/rpc/send_goal"
        assert reply == {"id": 5, "ok": True, "goal_id": goal_id, "accepted": True}
        assert requests.goals_routed == [goal_id]
        backend.step(1.5)  # feedback and the result reach the query's caller: discarded
        assert requests.goals_routed == [] and requests.results_discarded == 0
    finally:
        aio.close()
        requests.close()


def test_a_binary_query_is_decoded_from_its_attachment_and_payload() -> None:
    """docs/protocol.md, "Binary frames": the payload is the raw bytes, the attachment the
    token, a newline and the request line; a payload shorter than announced is bad_frame."""
    raw = struct.pack("<6d", 1.0, 0.5, -0.5, 2.0, 1.0, 0.0)
    header = json.dumps({"id": 3, "trajectory": {"joint_names": ["j1", "j2"]}, "attachment": {
        "bytes": 48, "dtype": "<f8", "shape": [2, 3],
        "columns": ["time_from_start", "positions.j1", "positions.j2"]}}).encode()
    attachment = FakeQuery("k", b"", token=TOKEN + "\n" + header.decode() + "\n").attachment
    token, line = split_attachment(attachment)
    assert token == TOKEN.encode() and line == header
    goal = ZenohInterface.decode("send_goal", raw, 1024, line)
    assert isinstance(goal, SendGoal) and len(goal.trajectory.points) == 2
    short = ZenohInterface.decode("send_goal", raw[:40], 1024, line)
    assert isinstance(short, RequestError) and short.code == "bad_frame"
    assert split_attachment(FakeQuery("k", b"", token=TOKEN).attachment) == (TOKEN.encode(), None)
