"""Binary goal frames end to end, by a client written from docs/protocol.md alone.

The client here builds every frame with ``json``, ``struct`` and ``numpy.tobytes`` as the doc's
"Binary frames" section describes it, and reads replies as JSON lines from a plain unix socket:
no ``jtc_hw.api`` (``test_this_client_uses_nothing_of_jtc_hw``; the daemon itself is started
by the shared helpers). Against a real daemon (``python -m jtc_hw run``, mirror joints): a
binary goal is accepted and succeeds, and each bad frame of the doc's table gets its one error,
after which the daemon still holds where it was (nothing moves). Waits are on messages, with
deadlines; nothing is timed.
"""

from __future__ import annotations

import ast
import json
import socket
import struct
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.daemon import JOINTS, WAIT_S, DaemonProcess

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

MAX_MESSAGE_BYTES = 65536


class Peer:
    """A plain unix socket: bytes out, JSON lines in (events kept apart)."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(WAIT_S)
        self.sock.connect(str(path))
        self.buffer = b""
        self.events: list[dict[str, Any]] = []
        self.ids = 0

    def close(self) -> None:
        self.sock.close()

    def line(self, timeout_s: float = WAIT_S) -> bytes | None:
        """The next line, or None when the daemon closed the connection."""
        deadline = time.monotonic() + timeout_s
        while b"\n" not in self.buffer:
            self.sock.settimeout(max(0.001, deadline - time.monotonic()))
            chunk = self.sock.recv(65536)
            if not chunk:
                return None
            self.buffer += chunk
        line, _, self.buffer = self.buffer.partition(b"\n")
        return line

    def reply(self, timeout_s: float = WAIT_S) -> dict[str, Any]:
        while True:
            line = self.line(timeout_s)
            assert line is not None, "the daemon closed the connection"
            message: dict[str, Any] = json.loads(line)
            if "event" not in message:
                return message
            self.events.append(message)

    def request(self, op: str, **fields: Any) -> dict[str, Any]:
        self.ids += 1
        self.sock.sendall(json.dumps({"id": self.ids, "op": op, **fields}).encode() + b"\n")
        answer = self.reply()
        assert answer["id"] == self.ids, answer
        return answer

    def result(self, goal_id: int, timeout_s: float = 30.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while True:
            for event in self.events:
                if event["event"] == "result" and event["goal_id"] == goal_id:
                    return event
            line = self.line(max(0.001, deadline - time.monotonic()))
            assert line is not None, "the daemon closed the connection"
            self.events.append(json.loads(line))


def frame(request: dict[str, Any], values: np.ndarray, names: list[str],
          **header: Any) -> bytes:
    """The doc's layout: the request line with its attachment header, the raw little-endian
    float64 bytes row by row, one newline. ``header`` overrides the header's fields."""
    raw = values.astype("<f8").tobytes()
    attachment = {"bytes": len(raw), "dtype": "<f8", "shape": list(values.shape),
                  "columns": names, **header}
    line = json.dumps({**request, "attachment": attachment}).encode()
    return line + b"\n" + raw + b"\n"


def columns(*fields: str) -> list[str]:
    return ["time_from_start"] + [f"{f}.{j}" for f in fields for j in JOINTS]


def goal(peer: Peer, request_id: int) -> dict[str, Any]:
    return {"id": request_id, "op": "send_goal", "trajectory": {"joint_names": JOINTS}}


def ramp(start: list[float], target: list[float], points: int = 150,
         duration_s: float = 1.5) -> np.ndarray:
    """Positions and velocities of a smooth move (cosine profile), one row per point."""
    t = np.linspace(duration_s / points, duration_s, points)
    s = (1 - np.cos(np.pi * t / duration_s)) / 2
    ds = np.pi / duration_s * np.sin(np.pi * t / duration_s) / 2
    a, b = np.array(start), np.array(target)
    positions = a + np.outer(s, b - a)
    velocities = np.outer(ds, b - a)
    return np.column_stack([t, positions, velocities])


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    d = DaemonProcess(tmp_path_factory.mktemp("binary"), max_message_bytes=MAX_MESSAGE_BYTES)
    with d.serving():
        yield d


@pytest.fixture
def peer(daemon: DaemonProcess) -> Iterator[Peer]:
    p = Peer(daemon.socket)
    try:
        assert p.request("hello", protocol_version=2)["protocol_version"] == 2
        p.request("stop")
        yield p
    finally:
        p.close()


def held(peer: Peer) -> list[float]:
    """Where the daemon will be in 0.5 s; while it holds, where it is."""
    reply = peer.request("query_state", **{"in": 0.5})
    assert reply["ok"], reply
    positions: list[float] = reply["positions"]
    return positions


def test_this_client_uses_nothing_of_jtc_hw() -> None:
    tree = ast.parse(Path(__file__).read_text())
    imported = {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import)
                for alias in node.names}
    imported |= {node.module or "" for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom)}
    assert not any(name.startswith("jtc_hw") for name in imported), imported


def test_a_binary_goal_is_accepted_and_reaches_its_target(peer: Peer) -> None:
    start = held(peer)
    target = [s + 0.2 * (-1) ** i for i, s in enumerate(start)]
    values = ramp(start, target)
    assert struct.unpack("<d", values.astype("<f8").tobytes()[:8])[0] == values[0, 0]
    peer.sock.sendall(frame(goal(peer, 101), values, columns("positions", "velocities")))
    accepted = peer.reply()
    assert accepted["id"] == 101 and accepted["ok"] and accepted["accepted"], accepted
    result = peer.result(accepted["goal_id"])
    assert result["status"] == "succeeded", result
    assert np.allclose(held(peer), target, atol=0.01)
    # The connection goes on with ordinary lines after a frame.
    assert peer.request("get_status")["ok"]


def bad_values(kind: str) -> np.ndarray:
    values = np.zeros((3, 1 + len(JOINTS)))
    values[:, 0] = [0.5, 1.0, 1.5]
    values[:, 1:] = 0.3  # somewhere else: if any of these were run, the arm would move
    if kind == "nan":
        values[1, 3] = np.nan
    elif kind == "inf":
        values[2, 0] = np.inf
    return values


BAD_REQUESTS = {
    # what is wrong: (frame, header overrides, what the message says)
    "shape": ({"shape": [4, 7]}, "of <f8 is 224 bytes, the attachment has 168"),
    "dtype": ({"dtype": "<f4"}, "the only dtype is \"<f8\""),
    "columns": ({"columns": ["time_from_start"] + [f"positions.{j}" for j in reversed(JOINTS)]},
                'expected "positions.joint1"'),
    "nan": ({}, 'point 1, column "positions.joint3": nan is not a finite number'),
    "inf": ({}, 'point 2, column "time_from_start": inf is not a finite number'),
}


@pytest.mark.parametrize("kind", sorted(BAD_REQUESTS))
def test_a_wrong_frame_is_one_bad_request_and_nothing_moves(peer: Peer, kind: str) -> None:
    before = held(peer)
    header, says = BAD_REQUESTS[kind]
    peer.sock.sendall(frame(goal(peer, 7), bad_values(kind), columns("positions"), **header))
    error = peer.reply()
    assert error["id"] == 7 and error["ok"] is False, error
    assert error["error"]["code"] == "bad_request" and says in error["error"]["message"], error
    assert held(peer) == before  # the connection goes on; the arm holds where it was


BAD_FRAMES = {
    "length too short": lambda data: data.replace(b'"bytes": 168', b'"bytes": 160', 1),
    "length too long": lambda data: data.replace(b'"bytes": 168', b'"bytes": 176', 1),
    "length not a number": lambda data: data.replace(b'"bytes": 168', b'"bytes": "168"', 1),
    "no newline after the bytes": lambda data: data[:-1] + b"{",
}


@pytest.mark.parametrize("kind", sorted(BAD_FRAMES))
def test_an_untrustworthy_frame_is_bad_frame_and_the_connection_closes(
    daemon: DaemonProcess, peer: Peer, kind: str
) -> None:
    before = held(peer)
    data = BAD_FRAMES[kind](frame(goal(peer, 8), bad_values("ok"), columns("positions")))
    # a request after it that must never run: the stream is out of sync
    peer.sock.sendall(data + b'{"id": 9, "op": "get_status"}\n')
    error = peer.reply()
    assert error["ok"] is False and error["error"]["code"] == "bad_frame", error
    assert "out of sync" in error["error"]["message"]
    while (line := peer.line()) is not None:  # then the daemon closes; nothing else answered
        assert "event" in json.loads(line), line
    other = Peer(daemon.socket)
    try:
        assert held(other) == before
    finally:
        other.close()


def test_a_truncated_frame_is_bad_frame_and_nothing_moves(
    daemon: DaemonProcess, peer: Peer
) -> None:
    before = held(peer)
    data = frame(goal(peer, 10), bad_values("ok"), columns("positions"))
    peer.sock.sendall(data[:-40])
    peer.sock.shutdown(socket.SHUT_WR)  # the client died mid-write (it can still read)
    error = peer.reply()
    assert error["error"]["code"] == "bad_frame", error
    assert "ended after 129 of the attachment's 168 bytes" in error["error"]["message"]
    other = Peer(daemon.socket)
    try:
        assert held(other) == before
    finally:
        other.close()


def test_an_oversized_attachment_is_too_large_skipped_and_the_connection_goes_on(
    peer: Peer,
) -> None:
    before = held(peer)
    values = np.zeros((MAX_MESSAGE_BYTES // 56 + 1, 1 + len(JOINTS)))
    values[:, 0] = np.arange(1, len(values) + 1) * 0.01
    peer.sock.sendall(frame(goal(peer, 11), values, columns("positions")))
    error = peer.reply()
    assert error["id"] == 11 and error["error"]["code"] == "too_large", error
    assert held(peer) == before
