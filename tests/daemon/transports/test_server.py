"""The socket server over real unix/TCP sockets, with a stand-in backend hosting the controller.

``FakeBackend`` is not a protocol mock: it is a small controller host (the real
``JointTrajectoryController`` over ideal mirrored joints, on a simulated clock the test steps),
implementing the ``Backend`` interface that the daemon's loop backend implements for real.
Tests wait on messages and log records with timeouts, never on sleeps.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import stat
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.fake_backend import TOKEN, FakeBackend
from helpers.peers import LogWatch, Peer, goal_msg, run, watch_server_log

from jtc_hw import GoalResult
from jtc_hw.api.paths import default_socket_path
from jtc_hw.daemon.settings import DaemonSettings, TcpSettings
from jtc_hw.daemon.transports.server import Server
from jtc_hw.errors import ConfigurationError

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

S = 1_000_000_000


@pytest.fixture
def logs() -> Iterator[LogWatch]:
    with watch_server_log() as watch:
        yield watch


@contextlib.asynccontextmanager
async def serving(
    path: Path, backend: FakeBackend | None = None, **settings: Any
) -> AsyncIterator[tuple[Server, FakeBackend]]:
    backend = backend or FakeBackend()
    server = Server(backend, DaemonSettings(socket=str(path), **settings))
    await server.start()
    try:
        yield server, backend
    finally:
        await server.close()


@pytest.fixture
def sock(tmp_path: Path) -> Path:
    return tmp_path / "d.sock"


# -- tests --------------------------------------------------------------------------------------


def test_hello(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock) as (_, backend):
            peer = await Peer.unix(sock)
            await peer.send({"id": "h", "op": "hello", "protocol_version": 1})
            hello = await peer.recv()
            assert hello["id"] == "h" and hello["ok"] is True
            # Version 2 added binary frames; a version 1 client is served (NDJSON unchanged).
            assert hello["protocol_version"] == 2 and hello["server_version"] == "0.1.0"
            assert hello["joint_names"] == ["j1", "j2"] and hello["update_rate"] == 100.0
            assert hello["now_ns"] == backend.t and hello["max_message_bytes"] == 4 << 20
            v2 = await peer.request("hello", protocol_version=2)
            assert v2["ok"] is True and v2["protocol_version"] == 2
            wrong = await peer.request("hello", protocol_version=3)
            assert wrong["error"]["code"] == "bad_request"
            assert "speaks versions 1, 2" in wrong["error"]["message"]
            await peer.close()

    run(main())


def test_goal_events_go_to_the_sender_only(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock) as (server, backend):
            a, b, c = [await Peer.unix(sock) for _ in range(3)]
            accepted = await b.request(
                "send_goal",
                trajectory=goal_msg(),
                goal_tolerance=[{"name": "j1", "position": 0.01}],
            )
            assert accepted["ok"] and accepted["accepted"] is True
            goal_id = accepted["goal_id"]
            backend.step(0.3)
            feedback = await b.event("feedback")
            assert feedback["goal_id"] == goal_id and feedback["joint_names"] == ["j1", "j2"]
            assert set(feedback["desired"]) == {
                "positions",
                "velocities",
                "accelerations",
                "effort",
            }
            assert set(feedback["error"]) == {"positions", "velocities", "accelerations"}
            assert 0.0 <= feedback["time_from_start"] <= 0.3
            backend.step(1.5)
            result = await b.event("result")
            assert result == {
                "event": "result",
                "goal_id": goal_id,
                "status": "succeeded",
                "error_code": 0,
                "error_string": "Goal successfully reached!",
                "details": "",
                "time_ns": result["time_ns"],
            }
            # Exactly one result: nothing else for this goal arrives before a later reply.
            await b.request("get_status")
            assert not [m for m in b.inbox if m["event"] == "result"]
            # The other clients got nothing at all.
            for other in (a, c):
                assert (await other.request("get_status"))["ok"]
                assert other.inbox == []
            # A goal from c preempts b's: b gets its canceled result, c the new goal's events.
            second = (await b.request("send_goal", trajectory=goal_msg(t=5.0)))["goal_id"]
            third = (await c.request("send_goal", trajectory=goal_msg((0, 0))))["goal_id"]
            backend.step(0.05)
            preempted = await b.event("result")
            assert preempted["goal_id"] == second and preempted["status"] == "canceled"
            assert (await c.event("feedback"))["goal_id"] == third
            backend.step(2.0)
            assert (await c.event("result"))["status"] == "succeeded"
            assert server.stats()["goals_routed"] == []
            for peer in (a, b, c):
                await peer.close()

    run(main())


def test_goal_rejections_carry_reason_and_error_code(sock: Path, logs: LogWatch) -> None:
    async def main() -> None:
        async with serving(sock) as (_, backend):
            peer = await Peer.unix(sock)
            cases = [
                (goal_msg() | {"joint_names": ["j1", "elbow"]}, -2, "elbow"),
                (goal_msg(start_time_ns=1), -3, "in the past"),
                (
                    goal_msg() | {"points": [{"time_from_start": 1, "positions": [1.0]}]},
                    -1,
                    "point #0",
                ),
            ]
            for trajectory, code, fragment in cases:
                rejected = await peer.request("send_goal", trajectory=trajectory)
                assert rejected["ok"] is False
                error = rejected["error"]
                assert error["code"] == "goal_rejected" and error["error_code"] == code
                assert fragment in error["message"], error["message"]
            bad_tolerance = await peer.request(
                "send_goal", trajectory=goal_msg(), path_tolerance=[{"name": "j9", "position": 1}]
            )
            assert bad_tolerance["error"]["error_code"] == -2
            assert "path_tolerance: joint 'j9'" in bad_tolerance["error"]["message"]
            topic = await peer.request("send_trajectory", trajectory=goal_msg(start_time_ns=1))
            assert topic["error"]["code"] == "goal_rejected"
            assert topic["error"]["error_code"] == -3
            assert backend.ctrl.holding  # nothing changed
            await peer.close()

    run(main())
    assert logs.count("rejected send_goal (id ") == 4
    assert logs.count("rejected send_trajectory") == 1
    assert any("goal_rejected: " in m and "elbow" in m for m in logs.messages)


def test_cancel(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock) as (_, backend):
            owner, other = await Peer.unix(sock), await Peer.unix(sock)
            goal_id = (await owner.request("send_goal", trajectory=goal_msg(t=5.0)))["goal_id"]
            backend.step(0.1)
            canceled = await other.request("cancel_goal", goal_id=goal_id)  # any client may
            assert canceled == {"id": 1, "ok": True, "goal_id": goal_id, "canceling": True}
            backend.step(0.05)
            result = await owner.event("result")
            assert result["status"] == "canceled" and result["goal_id"] == goal_id
            again = await owner.request("cancel_goal", goal_id=goal_id)
            assert again["error"]["code"] == "not_found"
            assert f"goal {goal_id} is not executing" in again["error"]["message"]
            assert other.inbox == []
            await owner.close()
            await other.close()

    run(main())


def test_query_state_and_not_active(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock) as (_, backend):
            peer = await Peer.unix(sock)
            await peer.request("send_goal", trajectory=goal_msg((1.0, 2.0), t=1.0))
            at_end = await peer.request("query_state", time_ns=backend.t + 2 * S)
            assert at_end["positions"] == [1.0, 2.0] and at_end["time_ns"] == backend.t + 2 * S
            assert at_end["joint_names"] == ["j1", "j2"] and at_end["velocities"] == [0.0, 0.0]
            ahead = await peer.request("query_state", **{"in": 0.5})
            assert ahead["time_ns"] == backend.t + S // 2
            assert 0.0 < ahead["positions"][0] < 1.0 and set(ahead) >= {"accelerations", "effort"}
            backend.ctrl.deactivate(backend.t)
            inactive = await peer.request("query_state", **{"in": 0})
            assert inactive["error"]["code"] == "not_active"
            assert "not active" in inactive["error"]["message"]
            await peer.close()

    run(main())


def test_topic_trajectory_preempts_goal_and_empty_one_stops(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock) as (_, backend):
            owner, topic = await Peer.unix(sock), await Peer.unix(sock)
            goal_id = (await owner.request("send_goal", trajectory=goal_msg(t=5.0)))["goal_id"]
            sent = await topic.request("send_trajectory", trajectory=goal_msg((0.2, 0.2), t=3.0))
            assert sent == {"id": 1, "ok": True, "stopping": False}
            backend.step(0.05)
            result = await owner.event("result")
            assert result["goal_id"] == goal_id and result["status"] == "canceled"
            assert not backend.ctrl.holding
            stop = await topic.request(
                "send_trajectory", trajectory={"joint_names": [], "points": []}
            )
            assert stop["stopping"] is True
            backend.step(0.02)
            assert backend.ctrl.holding
            assert topic.inbox == []
            await owner.close()
            await topic.close()

    run(main())


def test_subscribe_with_a_client_that_does_not_read(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock, client_queue_size=8) as (_, backend):
            slow, fast = await Peer.unix(sock, limit=32_768), await Peer.unix(sock)
            assert (await slow.request("subscribe_state"))["subscribed"] is True
            await fast.request("subscribe_state")
            goal_id = (await fast.request("send_goal", trajectory=goal_msg(t=1.0)))["goal_id"]
            # ~3 MB of state for the slow client, which reads nothing: its socket buffers fill,
            # then its queue, then its state messages are dropped.
            for seq in range(150):
                backend.publish_state(seq, pad=20_000)
                state = await fast.event("state")
                assert state["seq"] == seq and state["dropped"] == 0
                backend.step(0.01)
            backend.step(1.0)
            result = await fast.event("result")  # results still reach the other client
            assert result["goal_id"] == goal_id and result["status"] == "succeeded"
            status = await fast.request("get_status")
            by_client = {c["client"]: c for c in status["server"]["clients"]}
            me = status["server"]["you"]
            slow_stats = next(c for n, c in by_client.items() if n != me)
            assert slow_stats["subscribed"] and slow_stats["dropped_state"] > 0
            assert by_client[me]["dropped_state"] == 0
            # The slow client now reads: its backlog, then a state that reports the loss.
            assert (await slow.request("get_status"))["ok"]
            backlog = [m for m in slow.inbox if m["event"] == "state"]
            assert len(backlog) == len(slow.inbox)
            slow.inbox.clear()
            backend.publish_state(999)
            last = await slow.event("state")
            assert last["seq"] == 999
            received = backlog + [last]
            assert len(received) + last["dropped_total"] == 151
            assert sum(m["dropped"] for m in received) == last["dropped_total"]
            assert last["dropped_total"] == slow_stats["dropped_state"]
            assert (await fast.event("state"))["seq"] == 999
            await slow.request("unsubscribe_state")
            backend.publish_state(1000)
            assert (await fast.event("state"))["seq"] == 1000
            assert (await slow.request("get_status"))["ok"] and slow.inbox == []
            await slow.close()
            await fast.close()

    run(main(), timeout_s=30)


def test_a_client_too_slow_for_its_replies_is_disconnected(sock: Path, logs: LogWatch) -> None:
    async def main() -> None:
        backend = FakeBackend()
        backend.config_padding = 200_000
        async with serving(sock, backend, client_queue_size=2, client_queue_hard_cap=4):
            peer, other = await Peer.unix(sock, limit=32_768), await Peer.unix(sock)
            for i in range(40):  # 8 MB of replies nobody reads
                await peer.send({"id": i, "op": "get_config"})
            message = await logs.wait_for("client_queue_hard_cap")
            assert "not reading" in message
            assert (await other.request("hello"))["ok"]  # the server is fine
            await peer.eof()
            await peer.close()
            await other.close()

    run(main())


def test_max_clients(sock: Path, logs: LogWatch) -> None:
    """This test runs as the daemon's user: it gets the two reserved slots too (the limits
    for other users are in test_connection_limits)."""

    async def main() -> None:
        async with serving(sock, max_clients=2) as (server, _):
            peers = [await Peer.unix(sock) for _ in range(4)]
            for peer in peers:
                assert (await peer.request("hello"))["ok"]
            stats = server.stats()
            assert [c["reserved_slot"] for c in stats["clients"]] == [False, False, True, True]
            extra = await Peer.unix(sock)
            busy = await extra.request("hello")
            assert busy["id"] == 1 and busy["ok"] is False
            assert busy["error"]["code"] == "busy"
            assert "2 unix clients (max_clients)" in busy["error"]["message"]
            assert "only send a 'stop' request" in busy["error"]["message"]
            assert await extra.eof() == b""
            await extra.close()
            await peers[0].close()
            await logs.wait_for("client 1 (unix pid")  # open line
            await logs.wait_for("disconnected: closed by the client")
            c = await Peer.unix(sock)  # a slot is free again
            assert (await c.request("hello"))["ok"]
            assert server.stats()["refused_busy"] == 1
            for peer in (*peers[1:], c):
                await peer.close()

    run(main())
    assert logs.count("is over the limit: serving only a stop request") == 1


def test_oversize_message_keeps_the_connection(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock, max_message_bytes=1024):  # the schema's least
            peer = await Peer.unix(sock)
            big = {"id": 1, "op": "send_goal", "trajectory": goal_msg(), "pad": "x" * 5000}
            await peer.send(json.dumps(big).encode() + b'\n{"id": 2, "op": "hello"}\n')
            too_large = await peer.recv()
            assert too_large["ok"] is False and too_large["id"] is None
            assert too_large["error"]["code"] == "too_large"
            assert "1024 bytes" in too_large["error"]["message"]
            assert (await peer.recv())["id"] == 2
            assert (await peer.request("get_status"))["ok"]
            await peer.close()

    run(main())


def test_a_long_request_being_decoded_does_not_hold_up_other_clients(
    sock: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A long line (a large goal) is decoded in a worker thread: while its decode is held up
    here (deterministically, by a gate), another client's request is answered."""
    import threading

    from jtc_hw.api.protocol import Decoder
    from jtc_hw.daemon.transports.server import DECODE_IN_WORKER_BYTES

    gate = threading.Event()
    feed = Decoder.feed
    marked: set[int] = set()

    def gated_feed(self: Decoder, data: bytes) -> Any:
        if b"GATED" in data:
            marked.add(id(self))
        if id(self) in marked and b"\n" in data:  # the data completing the long line
            assert gate.wait(10.0), "the event loop was held up by the long line's decode"
        return feed(self, data)

    monkeypatch.setattr(Decoder, "feed", gated_feed)

    async def main() -> None:
        async with serving(sock):
            slow, quick = await Peer.unix(sock), await Peer.unix(sock)
            pad = "GATED" + "x" * DECODE_IN_WORKER_BYTES
            await slow.send({"id": 1, "op": "hello", "client_name": "slow", "pad": pad})
            answer = await quick.request("hello")  # served while the long line waits
            assert answer["ok"] is True
            gate.set()
            reply = await slow.recv()
            assert reply["id"] == 1 and reply["error"]["code"] == "bad_request"  # "pad"
            await slow.close()
            await quick.close()

    try:
        run(main())
    finally:
        gate.set()


def test_malformed_json_unknown_op_and_bad_fields(sock: Path, logs: LogWatch) -> None:
    async def main() -> None:
        async with serving(sock):
            peer = await Peer.unix(sock)
            await peer.send(b'{"id": 1, "op": "hello"\n')
            bad = await peer.recv()
            assert bad["error"]["code"] == "bad_json"
            assert bad["error"]["message"].startswith("line 1, column 24: malformed JSON")
            await peer.send(b'{"id": 2, "op": "hello", "x": NaN}\n')
            assert "NaN" in (await peer.recv())["error"]["message"]
            unknown = await peer.request("subscribe")
            assert unknown["error"]["code"] == "unknown_op"
            assert "did you mean 'subscribe_state'" in unknown["error"]["message"]
            traj = goal_msg()
            traj["points"][0]["positions"] = [0.1, "x"]
            wrong = await peer.request("send_goal", trajectory=traj)
            assert wrong["error"] == {
                "code": "bad_request",
                "message": "trajectory.points[0].positions[1]: expected a number, got a "
                'string ("x")',
            }
            sim = await peer.request("sim", component="arm", freeze=True)
            assert sim["error"]["code"] == "bad_request" and "'arm'" in sim["error"]["message"]
            assert (await peer.request("hello"))["ok"]  # still connected
            await peer.close()

    run(main())
    assert logs.count("rejected") == 5


def test_one_shot_client_half_closes_and_still_gets_its_reply(sock: Path) -> None:
    """As ``echo '{...}' | socat - UNIX-CONNECT:...``: the client half-closes after writing."""

    async def main() -> None:
        async with serving(sock):
            peer = await Peer.unix(sock)
            await peer.send(b'{"id": 1, "op": "hello"}\n{"id": 2, "op": "query_state", "in": 0}\n')
            peer.writer.write_eof()
            lines = (await peer.eof()).splitlines()
            assert [json.loads(x)["id"] for x in lines] == [1, 2]
            assert json.loads(lines[1])["positions"] == [0.0, 0.0]
            await peer.close()

    run(main())


def test_edge_inputs_are_answered_and_never_executed(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock) as (_, backend):
            peer = await Peer.unix(sock)
            # A lone surrogate: answered (the text escaped), the connection kept, not run.
            await peer.send(b'{"id": 1, "op": "sim", "component": "mirror", "freeze": true, '
                            b'"fault": "servo \\ud800"}\n')
            refused = await peer.reply(1)
            assert refused["error"]["code"] == "bad_request"
            assert 'fault "servo \\ud800" holds a lone UTF-16 surrogate' in (
                refused["error"]["message"]
            )
            assert not backend.mirror.frozen
            await peer.send(b'{"id": "\\udc00", "op": "send_goal", "trajectory": '
                            + json.dumps(goal_msg()).encode() + b"}\n")
            assert (await peer.reply(None))["error"]["code"] == "bad_request"
            assert backend.ctrl.active_goal is None
            assert (await peer.request("get_status"))["ok"]  # nothing poisoned
            # The end of the clock, and absurd values: refused, naming the point.
            late = await peer.request("send_goal", trajectory=goal_msg(start_time_ns=2**63 - 1))
            assert late["error"]["code"] == "bad_request"
            assert "after the end of the daemon clock's range" in late["error"]["message"]
            huge = await peer.request("send_goal", trajectory=goal_msg(positions=(0.0, 1e308)))
            assert huge["error"]["message"].startswith(
                "trajectory.points[0].positions[1] (joint 'j2'): 1e+308 is out of range"
            )
            assert backend.ctrl.active_goal is None
            await peer.close()

    run(main())


def test_a_last_message_without_its_newline_is_never_executed(sock: Path) -> None:
    """It may be cut off (a client that died mid-write): a stop, a goal, anything."""

    async def main() -> None:
        async with serving(sock) as (_, backend):
            peer = await Peer.unix(sock)
            goal = {"id": 2, "op": "send_goal", "trajectory": goal_msg()}
            await peer.send(b'{"id": 1, "op": "hello"}\n' + json.dumps(goal).encode())
            peer.writer.write_eof()
            lines = (await peer.eof()).splitlines()
            first, refused = (json.loads(x) for x in lines)
            assert first["id"] == 1 and first["ok"]
            assert refused["id"] is None and refused["error"]["code"] == "bad_json"
            assert "ended before this message's newline; it was not executed" in (
                refused["error"]["message"]
            )
            assert backend.ctrl.active_goal is None and backend.ctrl.holding
            await peer.close()

    run(main())


def test_internal_error_is_reported_and_logged(sock: Path, logs: LogWatch) -> None:
    async def main() -> None:
        async with serving(sock) as (_, backend):
            peer = await Peer.unix(sock)
            backend.status_error = RuntimeError("boom")
            failed = await peer.request("get_status")
            assert failed["error"] == {
                "code": "internal",
                "message": "internal error: RuntimeError: boom",
            }
            backend.status_error = None
            backend.extra_config = object()  # not JSON-able
            unencodable = await peer.request("get_config")
            assert unencodable["error"]["code"] == "internal"
            assert "cannot encode a object" in unencodable["error"]["message"]
            backend.extra_config = None
            assert (await peer.request("get_status"))["ok"]
            await peer.request("subscribe_state")
            assert backend.listener is not None
            backend.listener.on_state({"bad": object()})  # logged and skipped, never raised
            backend.publish_state(seq=5)
            assert (await peer.event("state"))["seq"] == 5
            await peer.close()

    run(main())
    assert any("get_status failed" in m for m in logs.messages)
    assert any("cannot encode a state snapshot" in m for m in logs.messages)


def test_status_config_and_sim(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock) as (_, backend):
            peer = await Peer.unix(sock)
            status = await peer.request("get_status")
            assert status["loop"] == {"cycles": 0} and status["hardware"] == {"mirror": "ok"}
            assert status["server"]["you"] == 1 and status["server"]["max_clients"] == 16
            config = await peer.request("get_config")
            assert config["config"]["controller"]["joints"] == ["j1", "j2"]
            frozen = await peer.request("sim", component="mirror", freeze=True)
            assert frozen == {"id": 3, "ok": True, "component": "mirror", "frozen": True}
            assert backend.mirror.frozen
            await peer.close()

    run(main())


def test_client_vanishing_mid_goal(sock: Path, logs: LogWatch) -> None:
    async def main() -> None:
        async with serving(sock) as (server, backend):
            owner, other = await Peer.unix(sock), await Peer.unix(sock)
            goal_id = (await owner.request("send_goal", trajectory=goal_msg(t=1.0)))["goal_id"]
            await owner.close()
            message = await logs.wait_for("client 1 (unix")
            message = await logs.wait_for("disconnected: closed by the client")
            assert f"goal(s) {goal_id} still running" in message
            delivered = backend.step(2.0)  # the goal runs on; the backend still delivers
            assert any(isinstance(e, GoalResult) for e in delivered)
            await logs.wait_for(f"goal {goal_id} succeeded")
            assert server.stats()["results_discarded"] == 1
            assert (await other.request("hello"))["ok"] and other.inbox == []
            await other.close()

    run(main())
    assert any("result discarded" in m for m in logs.messages)


def test_events_arriving_before_send_goal_returns_are_delivered_after_the_reply(
    sock: Path,
) -> None:
    async def main() -> None:
        backend = FakeBackend()
        backend.early_feedback = True
        async with serving(sock, backend):
            peer = await Peer.unix(sock)
            await peer.send({"id": 1, "op": "send_goal", "trajectory": goal_msg()})
            accepted = await peer.recv()
            assert accepted["accepted"] is True
            early = await peer.recv()
            assert early["event"] == "feedback" and early["goal_id"] == accepted["goal_id"]
            backend.step(1.5)
            assert (await peer.event("result"))["goal_id"] == accepted["goal_id"]
            await peer.close()

    run(main())


def test_unix_socket_file_mode_directory_and_removal(tmp_path: Path) -> None:
    path = tmp_path / "run" / "sub" / "d.sock"

    async def main() -> None:
        async with serving(path):
            st = os.stat(path)
            assert stat.S_ISSOCK(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o660
            # Created directories: only the daemon's user writes them (nobody else can swap
            # the socket); the group that socket_mode lets connect may enter.
            for directory in (path.parent, path.parent.parent):
                assert stat.S_IMODE(os.stat(directory).st_mode) == 0o710
            peer = await Peer.unix(path)
            assert (await peer.request("hello"))["ok"]
            await peer.close()
        assert not path.exists()
        async with serving(path, socket_mode=0o600):
            assert stat.S_IMODE(os.stat(path).st_mode) == 0o600

    run(main())


@pytest.mark.skipif(os.geteuid() != 0, reason="makes a directory of another user: needs root")
def test_a_default_socket_directory_of_another_user_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    runtime = tmp_path / "xdg"
    runtime.mkdir(0o700)
    os.chown(runtime, 65534, -1)
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))

    async def main() -> None:
        server = Server(FakeBackend(), DaemonSettings(socket=str(default_socket_path())))
        with pytest.raises(ConfigurationError) as info:
            await server.start()
        assert str(info.value) == (
            f"socket: refusing the default socket directory: {runtime} belongs to uid 65534, "
            "not to uid 0 or root: another user may have created it to put a socket of theirs "
            "in the daemon's place. Remove it (as root) and start again, or set daemon.socket "
            "to a path in a directory only this daemon's user can write"
        )
        assert not (runtime / "jtc-hw.sock").exists()
        # Another path in it, configured explicitly, is the operator's choice.
        async with serving(runtime / "named.sock"):
            assert (runtime / "named.sock").exists()

    run(main())


def test_stale_socket_is_replaced(sock: Path, logs: LogWatch) -> None:
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(str(sock))  # a daemon that died without removing its socket
    dead.close()
    assert stat.S_ISSOCK(os.stat(sock).st_mode)

    async def main() -> None:
        async with serving(sock):
            peer = await Peer.unix(sock)
            assert (await peer.request("hello"))["ok"]
            await peer.close()

    run(main())
    assert any("replacing stale socket" in m for m in logs.messages)


def test_live_socket_or_other_file_is_refused(sock: Path) -> None:
    async def main() -> None:
        async with serving(sock):
            second = Server(FakeBackend(), DaemonSettings(socket=str(sock)))
            with pytest.raises(ConfigurationError, match="another daemon is listening on"):
                await second.start()
            await second.close()
            assert sock.exists()  # the live daemon's socket is untouched
        other = sock.with_name("plain")
        other.write_text("not a socket")
        third = Server(FakeBackend(), DaemonSettings(socket=str(other)))
        with pytest.raises(ConfigurationError, match="is not a socket"):
            await third.start()
        assert other.read_text() == "not a socket"

    run(main())


def test_tcp_with_token(tmp_path: Path, logs: LogWatch) -> None:
    async def main() -> None:
        settings = DaemonSettings(socket=str(tmp_path / "d.sock"),
                                  tcp=TcpSettings("127.0.0.1", 0, TOKEN))
        server = Server(FakeBackend(), settings)
        async with server:
            address = server.tcp_address
            assert address is not None and address[0] == "127.0.0.1" and address[1] > 0
            good = await Peer.tcp(address)
            assert (await good.request("auth", token=TOKEN))["authenticated"] is True
            assert (await good.request("hello"))["joint_names"] == ["j1", "j2"]
            bad = await Peer.tcp(address)
            refused = await bad.request("auth", token="guess")
            assert refused["error"] == {
                "code": "unauthorized",
                "message": "wrong token; closing the connection",
            }
            assert await bad.eof() == b""
            skipped = await Peer.tcp(address)
            no_auth = await skipped.request("hello")
            assert no_auth["error"]["code"] == "unauthorized"
            assert '{"op": "auth", "token": ...}' in no_auth["error"]["message"]
            assert await skipped.eof() == b""
            garbage = await Peer.tcp(address)
            await garbage.send(b"{{{\n")
            assert (await garbage.recv())["error"]["code"] == "unauthorized"
            assert await garbage.eof() == b""
            for peer in (good, bad, skipped, garbage):
                await peer.close()

    run(main())
    assert not any(TOKEN in m or "guess" in m for m in logs.messages)


def test_tcp_client_that_never_authenticates_is_closed(tmp_path: Path, logs: LogWatch) -> None:
    async def main() -> None:
        settings = DaemonSettings(
            socket=str(tmp_path / "d.sock"),
            tcp=TcpSettings("127.0.0.1", 0, TOKEN, auth_timeout_s=0.2),
        )
        async with Server(FakeBackend(), settings) as server:
            assert server.tcp_address is not None
            idle = await Peer.tcp(server.tcp_address)
            refused = await idle.recv()
            assert refused["error"]["code"] == "unauthorized"
            assert "no auth request within 0.2 s" in refused["error"]["message"]
            assert await idle.eof() == b""
            await idle.close()

    run(main())
    assert any("unauthorized (no auth request in time)" in m for m in logs.messages)


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.5", "::", "example.com"])
def test_non_loopback_tcp_host_is_refused(host: str) -> None:
    with pytest.raises(ConfigurationError, match="tcp.host"):
        Server(FakeBackend(), DaemonSettings(tcp=TcpSettings(host, 0, TOKEN)))


def test_settings_are_typed_and_check_themselves(sock: Path) -> None:
    # The server takes the daemon's frozen settings as built (no mapping, no duck typing): a
    # value is checked once, by the robot file's schema rows, when the settings are made.
    with pytest.raises(ConfigurationError, match="daemon.tcp.token: must be at least 16"):
        TcpSettings("127.0.0.1", 0)
    with pytest.raises(ConfigurationError, match="daemon.socket: expected an absolute path"):
        DaemonSettings(socket=None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="max_client"):
        DaemonSettings(socket=str(sock), max_client=3)  # type: ignore[call-arg]
    with pytest.raises(ConfigurationError, match="daemon.max_clients: must be >= 1"):
        DaemonSettings(socket=str(sock), max_clients=0)
    with pytest.raises(ConfigurationError, match="daemon.client_queue_hard_cap"):
        DaemonSettings(socket=str(sock), client_queue_size=8, client_queue_hard_cap=4)
    settings = DaemonSettings(socket=str(sock), socket_mode=0o640, max_clients=3,
                              tcp=TcpSettings("::1", 0, TOKEN))
    assert settings.tcp == TcpSettings("::1", 0, TOKEN) and settings.max_clients == 3
    server = Server(FakeBackend(), settings)
    assert server.settings is settings and server.path == sock


@pytest.mark.skipif(os.geteuid() != 0, reason="gives a socket another group: needs root")
def test_socket_group_is_given_to_the_socket_and_its_new_directory(tmp_path: Path) -> None:
    import grp
    import pwd

    group = grp.getgrgid(pwd.getpwuid(65534).pw_gid)  # nobody's group, not root's
    path = tmp_path / "run" / "d.sock"

    async def main() -> None:
        settings = DaemonSettings(socket=str(path), socket_group=group.gr_name)
        async with Server(FakeBackend(), settings):
            assert path.stat().st_gid == group.gr_gid
            assert path.parent.stat().st_gid == group.gr_gid
            assert stat.S_IMODE(path.stat().st_mode) == 0o660
        with pytest.raises(ConfigurationError, match="there is no group 'no-such-group-jtc'"):
            await Server(FakeBackend(), DaemonSettings(socket=str(path),
                                                       socket_group="no-such-group-jtc")).start()

    run(main())
