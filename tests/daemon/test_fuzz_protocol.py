"""Fuzz of the wire protocol: random and mutated lines of every documented op, pipelined on one
connection to the real ``Server`` (the stand-in backend runs the real controller, stepped as the
lines go). Every complete line must get exactly one reply, in order (echoing the request's id
when it was readable), and no reply may be an ``internal`` error. With a third of the messages
binary frames (protocol version 2), a frame that cannot be trusted gets ``bad_frame`` and the
connection closes; the fuzz goes on with a new one. The 100,000-line version
against a real daemon is ``bench/fuzz_protocol.py``.
"""

from __future__ import annotations

import asyncio
import collections
import json
import re
from pathlib import Path
from typing import Any

import pytest
from helpers.fake_backend import FakeBackend
from helpers.fuzz import Fuzzer, Line, segments
from helpers.peers import Peer, run

from jtc_hw.api.framing import ERROR_CODES
from jtc_hw.api.protocol import OPS
from jtc_hw.daemon.settings import DaemonSettings
from jtc_hw.daemon.transports.server import Server

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

ROOT = Path(__file__).resolve().parents[2]
SEED = 20261201
LINES = 10_000
MAX_MESSAGE_BYTES = 2048


def documented_ops() -> set[str]:
    """The ops with a section under "## Operations" in docs/protocol.md."""
    text = (ROOT / "docs" / "protocol.md").read_text()
    section = text.split("\n## Operations\n", 1)[1].split("\n## ", 1)[0]
    return {
        name
        for heading in re.findall(r"^### (.+)$", section, re.MULTILINE)
        for name in re.findall(r"`([a-z_]+)`", heading)
    }


def test_the_fuzz_covers_every_documented_op() -> None:
    assert documented_ops() == set(OPS)
    fuzzer = Fuzzer(SEED, ["j1", "j2"])
    assert {fuzzer.line().op for _ in range(2000)} == set(OPS)


async def exchange(
    peer: Peer, backend: FakeBackend, lines: list[Line], timeout_s: float = 60.0
) -> tuple[list[dict[str, Any]], int]:
    """Send every line (stepping the controller as they go), read the replies; the events
    received are counted, not kept."""

    async def write() -> None:
        for start in range(0, len(lines), 50):
            peer.writer.write(b"".join(line.data for line in lines[start : start + 50]))
            await peer.writer.drain()
            backend.step(0.05)  # goals progress: feedback, results, preemptions
            backend.publish_state(seq=start)

    writer = asyncio.create_task(write())
    replies: list[dict[str, Any]] = []
    events = 0
    try:
        while len(replies) < len(lines):
            data = await asyncio.wait_for(peer.reader.readline(), timeout_s)
            assert data.endswith(b"\n"), (
                f"the server closed the connection after {len(replies)} replies; the next "
                f"line was {lines[len(replies)].data[:300]!r}"
            )
            message = json.loads(data)
            if "event" in message:
                events += 1
            else:
                replies.append(message)
        await writer
    finally:
        writer.cancel()
    return replies, events


def test_every_line_gets_one_reply_in_order_and_none_is_internal(tmp_path: Path) -> None:
    fuzzer = Fuzzer(SEED, ["j1", "j2"], ("mirror",), MAX_MESSAGE_BYTES)
    lines = [fuzzer.line() for _ in range(LINES)]

    async def main() -> tuple[list[dict[str, Any]], int]:
        backend = FakeBackend()
        settings = DaemonSettings(
            socket=str(tmp_path / "d.sock"), max_message_bytes=MAX_MESSAGE_BYTES
        )
        async with Server(backend, settings):
            peer = await Peer.unix(tmp_path / "d.sock")
            try:
                return await exchange(peer, backend, lines)
            finally:
                await peer.close()

    replies, events = run(main(), timeout_s=120.0)
    codes: collections.Counter[str] = collections.Counter()
    for line, reply in zip(lines, replies, strict=True):
        where = f"seed {SEED}, line {line.data[:300]!r} -> {reply!r:.400}"
        if line.request_id is not None:
            assert reply["id"] == line.request_id, where
        if reply["ok"]:
            codes["ok"] += 1
            continue
        code = reply["error"]["code"]
        assert code != "internal", where
        assert code in ERROR_CODES and reply["error"]["message"], where
        codes[code] += 1
    # The fuzz reached every kind of answer a request can get here.
    for code in ("ok", "bad_json", "too_large", "bad_request", "unknown_op", "goal_rejected",
                 "not_found"):
        assert codes[code] > 0, (code, codes)
    assert events > 0


BINARY_LINES = 3000


async def exchange_segments(
    path: Path, backend: FakeBackend, lines: list[Line], timeout_s: float = 60.0
) -> list[dict[str, Any]]:
    """Each segment on a connection of its own (docs/protocol.md: after ``bad_frame`` the
    daemon closes it); after a segment's closing frame the writing side is shut (a frame cut
    short is told by the end of the stream) and the daemon must close the connection."""
    replies: list[dict[str, Any]] = []
    for number, part in enumerate(segments(lines)):
        peer = await Peer.unix(path)
        try:
            peer.writer.write(b"".join(line.data for line in part))
            await peer.writer.drain()
            if part[-1].closes:
                peer.writer.write_eof()
            backend.step(0.05)
            backend.publish_state(seq=number)
            got = 0
            while got < len(part):
                data = await asyncio.wait_for(peer.reader.readline(), timeout_s)
                assert data.endswith(b"\n"), (
                    f"closed after {got} replies; next: {part[got].data[:300]!r}")
                message = json.loads(data)
                if "event" not in message:
                    replies.append(message)
                    got += 1
            if part[-1].closes:
                while (data := await asyncio.wait_for(peer.reader.readline(), timeout_s)):
                    assert "event" in json.loads(data), data  # nothing else is answered
        finally:
            await peer.close()
    return replies


def test_binary_frames_get_one_reply_each_and_untrusted_ones_close_the_connection(
    tmp_path: Path,
) -> None:
    fuzzer = Fuzzer(SEED, ["j1", "j2"], ("mirror",), MAX_MESSAGE_BYTES, binary=1 / 3)
    lines = [fuzzer.line() for _ in range(BINARY_LINES)]
    assert 800 < sum(line.binary for line in lines) < 1200

    async def main() -> list[dict[str, Any]]:
        backend = FakeBackend()
        settings = DaemonSettings(
            socket=str(tmp_path / "d.sock"), max_message_bytes=MAX_MESSAGE_BYTES
        )
        async with Server(backend, settings):
            return await exchange_segments(tmp_path / "d.sock", backend, lines)

    replies = run(main(), timeout_s=180.0)
    codes: collections.Counter[str] = collections.Counter()
    for line, reply in zip(lines, replies, strict=True):
        where = f"seed {SEED}, line {line.data[:300]!r} -> {reply!r:.400}"
        if line.request_id is not None:
            assert reply["id"] == line.request_id, where
        code = "ok" if reply["ok"] else reply["error"]["code"]
        assert code != "internal", where
        assert (code == "bad_frame") == line.closes, where
        if line.binary:
            codes[code] += 1
    for code in ("ok", "bad_request", "too_large", "bad_frame", "goal_rejected"):
        assert codes[code] > 0, (code, codes)

