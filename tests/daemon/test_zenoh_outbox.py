"""The Zenoh interface's bounds, without a Zenoh session: its outbox (what is dropped when
Zenoh is slow) and its limit on queries executing at once (``busy``)."""

from __future__ import annotations

import asyncio
import json
import threading
from types import SimpleNamespace
from typing import Any

import pytest

from jtc_hw.daemon.zenoh_config import ZenohSettings
from jtc_hw.daemon.zenoh_iface import MAX_QUERIES, ZenohInterface, _Outbox

pytestmark = pytest.mark.usefixtures("no_leaks")


def test_outbox_drops_state_first_and_keeps_results_up_to_its_hard_cap() -> None:
    gate = threading.Event()
    ran: list[str] = []
    outbox = _Outbox(size=2, hard_cap=4)
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


class FakeQuery:
    def __init__(self, key: str, body: bytes = b"{}") -> None:
        self.key_expr = key
        self.payload = SimpleNamespace(to_bytes=lambda: body)
        self.replies: list[tuple[str, dict[str, Any]]] = []
        self.dropped = False

    def reply(self, key: str, data: bytes) -> None:
        self.replies.append((key, json.loads(data)))

    def drop(self) -> None:
        self.dropped = True


def interface() -> ZenohInterface:
    server = SimpleNamespace(backend=SimpleNamespace(joint_names=["j1"]),
                             settings=SimpleNamespace(max_message_bytes=1024))
    return ZenohInterface(ZenohSettings(prefix="jtc/t/a"), "c", server,  # type: ignore[arg-type]
                          dict)


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
