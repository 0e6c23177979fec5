"""Binary frames over Zenoh (docs/protocol.md, "Binary frames"): the raw bytes as the query's
payload, the token, a newline and the request line as its attachment; against a real daemon
on loopback (as test_zenoh_iface)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.daemon import GOAL_TOL, JOINTS, WAIT_S
from helpers.zenoh import TOKEN, ZenohDaemon, session_config, started

pytest.importorskip("zenoh", reason="the Zenoh interface needs jtc_hw[zenoh]")

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

from jtc_hw.api import zenoh_client as client_module  # noqa: E402
from jtc_hw.api.zenoh_client import open_session  # noqa: E402


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[ZenohDaemon]:
    d = started(ZenohDaemon(tmp_path / "a", "a"))
    try:
        yield d
    finally:
        assert d.shutdown() == 0


def query(d: ZenohDaemon, values: np.ndarray, token: str, **header: Any) -> dict[str, Any]:
    raw = values.astype("<f8").tobytes()
    columns = ["time_from_start", *(f"positions.{j}" for j in JOINTS)]
    line = json.dumps({"id": 5, "trajectory": {"joint_names": JOINTS}, "attachment": {
        "bytes": len(raw), "dtype": "<f8", "shape": list(values.shape), "columns": columns,
        **header}}).encode()
    session = open_session(session_config(d.endpoint))
    try:
        replies = list(session.get(f"{d.prefix}/rpc/send_goal", payload=raw,
                                   attachment=token.encode() + b"\n" + line + b"\n",
                                   timeout=WAIT_S))
    finally:
        session.close()
    assert len(replies) == 1 and replies[0].ok is not None, replies
    return dict(json.loads(replies[0].ok.payload.to_bytes()))


def test_the_client_sends_a_large_goal_as_a_frame_and_it_succeeds(
    daemon: ZenohDaemon, monkeypatch: pytest.MonkeyPatch
) -> None:
    sent: list[int] = []
    encode_frame = client_module.encode_frame

    def spy(obj: dict[str, Any], values: Any, columns: list[str]) -> bytes:
        sent.append(len(values))
        return encode_frame(obj, values, columns)

    monkeypatch.setattr(client_module, "encode_frame", spy)
    client = daemon.client()
    try:
        t = np.linspace(0.005, 0.6, 120)
        points = [{"time_from_start": float(s), "positions": [0.2 * s / 0.6] * len(JOINTS)}
                  for s in t]
        goal = client.send_goal({"joint_names": JOINTS, "points": points})
        assert sent == [120]
        assert goal.wait(timeout_s=WAIT_S)["status"] == "succeeded"
        # Held where the goal ended: within the goal tolerance of its last point (the hold
        # is the measured position when the goal succeeded, not the reference's end).
        held = client.query_state(in_s=0.0)["positions"]
        assert held == pytest.approx([0.2] * 6, abs=GOAL_TOL)
    finally:
        client.close()


def test_a_wrong_frame_or_token_gets_the_sockets_error(daemon: ZenohDaemon) -> None:
    values = np.zeros((3, 1 + len(JOINTS)))
    values[:, 0] = [0.5, 1.0, 1.5]
    values[1, 2] = np.nan
    nan = query(daemon, values, TOKEN)
    assert nan["id"] == 5 and nan["error"]["code"] == "bad_request", nan
    assert 'point 1, column "positions.joint2": nan' in nan["error"]["message"]
    shape = query(daemon, values, TOKEN, shape=[2, 7])
    assert "[2, 7] of <f8 is 112 bytes, the attachment has 168" in shape["error"]["message"]
    short = query(daemon, values, TOKEN, bytes=160)
    assert short["error"]["code"] == "bad_frame", short
    wrong = query(daemon, values, "not the token at all")
    assert wrong["error"]["code"] == "unauthorized", wrong
