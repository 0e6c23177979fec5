"""A stop always gets through: connection limits per transport, reserved slots, the stop served
over the limit, the authentication and idle deadlines.

The server runs in process over real sockets with the stand-in backend (``FakeBackend``, the
real controller on a simulated clock). Peers that must not be the daemon's user (which the
tests run as) are connections made by a forked child running as uid 65534 ("nobody"): the
server sees them through ``SO_PEERCRED`` as it would see another local user. Every wait is on a
message, a log record or the end of a connection, with a timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import socket
import tempfile
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.fake_backend import TOKEN, FakeBackend
from helpers.peers import LogWatch, Peer, goal_msg, run, watch_server_log

from jtc_hw.daemon.settings import DaemonSettings, TcpSettings
from jtc_hw.daemon.transports import server as server_module
from jtc_hw.daemon.transports import tcp_door
from jtc_hw.daemon.transports.connection import OVER_LIMIT_CLIENTS, RESERVED_UNIX_CLIENTS
from jtc_hw.daemon.transports.server import Server

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

NOBODY = 65534
HELLO = {"id": 1, "op": "hello"}
STOP = {"id": 1, "op": "stop"}


@pytest.fixture
def logs() -> Iterator[LogWatch]:
    with watch_server_log() as watch:
        yield watch


@pytest.fixture
def shared_dir() -> Iterator[Path]:
    """A directory another user can enter (pytest's own tmp_path is private to root)."""
    path = Path(tempfile.mkdtemp(prefix="jtc-hw-limits-"))
    path.chmod(0o711)
    yield path
    shutil.rmtree(path)


@contextlib.asynccontextmanager
async def serving(
    path: Path, backend: FakeBackend | None = None, **settings: Any
) -> AsyncIterator[tuple[Server, FakeBackend]]:
    backend = backend or FakeBackend()
    server = Server(backend, DaemonSettings(socket=str(path), socket_mode=0o666, **settings))
    await server.start()
    try:
        yield server, backend
    finally:
        await server.close()


class Foreign:
    """Unix connections made by a child process running as another user.

    Each connection sends ``request`` and reports the first line it receives back (or
    ``"EOF"``) to the parent, one JSON line per connection; the child holds its connections
    open until ``close``.
    """

    def __init__(self, path: Path, requests: list[dict[str, Any]], uid: int = NOBODY) -> None:
        self.count = len(requests)
        parent, child = socket.socketpair()
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child; it never returns into the test
            status = 1
            try:
                parent.close()
                os.setgroups([])
                os.setgid(uid)
                os.setuid(uid)
                held = []
                for request in requests:
                    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                    sock.settimeout(10.0)
                    sock.connect(str(path))
                    sock.sendall(json.dumps(request).encode() + b"\n")
                    data = b""
                    while not data.endswith(b"\n"):
                        chunk = sock.recv(4096)
                        if not chunk:
                            break
                        data += chunk
                    child.sendall(data if data.endswith(b"\n") else b'"EOF"\n')
                    held.append(sock)
                child.recv(1)  # until the parent closes its end
                status = 0
            finally:
                os._exit(status)
        child.close()
        self.pid = pid
        self._sock = parent
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    async def replies(self, timeout_s: float = 10.0) -> list[Any]:
        """What each connection received first, in order."""
        self._reader, self._writer = await asyncio.open_connection(sock=self._sock)
        lines = []
        for _ in range(self.count):
            lines.append(json.loads(await asyncio.wait_for(self._reader.readline(), timeout_s)))
        return lines

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            with contextlib.suppress(OSError):
                await self._writer.wait_closed()
        else:
            self._sock.close()
        _, status = os.waitpid(self.pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0


def test_stop_cancels_the_goal_and_holds(tmp_path: Path) -> None:
    async def main() -> None:
        async with serving(tmp_path / "d.sock") as (_, backend):
            owner, operator = await Peer.unix(tmp_path / "d.sock"), await Peer.unix(
                tmp_path / "d.sock"
            )
            goal = await owner.request("send_goal", trajectory=goal_msg(t=5.0))
            backend.step(0.5)
            assert not backend.ctrl.holding
            assert await operator.request("stop") == {"id": 1, "ok": True, "stopped": True}
            backend.step(0.02)
            result = await owner.event("result")
            assert result["goal_id"] == goal["goal_id"] and result["status"] == "canceled"
            assert backend.ctrl.holding and backend.stops == 1
            # A topic trajectory is stopped the same way.
            sent = await operator.request("send_trajectory", trajectory=goal_msg(t=5.0))
            assert sent["stopping"] is False
            backend.step(0.1)
            assert not backend.ctrl.holding
            assert (await operator.request("stop"))["stopped"] is True
            backend.step(0.02)
            assert backend.ctrl.holding
            # Stopped by a fault (not active): nothing to do, and it says so.
            backend.ctrl.deactivate(backend.t, "hardware fault: test")
            nothing = await operator.request("stop")
            assert nothing["ok"] is True and nothing["stopped"] is False
            assert "nothing to stop: the controller is not active" in nothing["message"]
            await owner.close()
            await operator.close()

    run(main())


def test_other_users_cannot_take_the_reserved_slots(shared_dir: Path, logs: LogWatch) -> None:
    path = shared_dir / "d.sock"

    async def main() -> None:
        async with serving(path, max_clients=1) as (server, backend):
            # Another user takes the one ordinary slot; its second connection is over the
            # limit (the reserved slots are not for it): only a stop would be served.
            foreign = Foreign(path, [HELLO, HELLO])
            first, second = await foreign.replies()
            assert first["ok"] is True
            assert second["error"]["code"] == "busy" and second["id"] == 1
            assert "1 unix clients (max_clients)" in second["error"]["message"]
            # The daemon's user (these tests) still gets in: the two reserved slots.
            mine = [await Peer.unix(path) for _ in range(RESERVED_UNIX_CLIENTS)]
            for peer in mine:
                assert (await peer.request("hello"))["ok"]
            clients = server.stats()["clients"]
            assert [(c["peer"].split()[-1], c["reserved_slot"]) for c in clients] == [
                (str(NOBODY), False),
                (str(os.geteuid()), True),
                (str(os.geteuid()), True),
            ]
            # Everything taken: a further connection of anyone is served one stop only.
            extra = await Peer.unix(path)
            assert (await extra.request("get_status"))["error"]["code"] == "busy"
            assert await extra.eof() == b""
            await extra.close()
            backend.ctrl.send_trajectory(backend.t, backend_traj(backend))
            backend.step(0.1)
            stopper = Foreign(path, [STOP])
            (stopped,) = await stopper.replies()
            assert stopped == {"id": 1, "ok": True, "stopped": True}
            backend.step(0.02)
            assert backend.ctrl.holding and server.stats()["stops_over_limit"] == 1
            await stopper.close()
            await foreign.close()
            for peer in mine:
                await peer.close()

    run(main())
    assert logs.count("is over the limit: serving only a stop request") == 3


def backend_traj(backend: FakeBackend) -> Any:
    from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint

    return JointTrajectory(["j1", "j2"], [TrajectoryPoint(5.0, [0.5, -0.5])])


def test_a_stop_gets_through_when_every_slot_is_taken(
    tmp_path: Path, logs: LogWatch, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(server_module, "OVER_LIMIT_DEADLINE_S", 0.5)
    path = tmp_path / "d.sock"

    async def main() -> None:
        async with serving(path, max_clients=1) as (server, backend):
            holders = [await Peer.unix(path) for _ in range(1 + RESERVED_UNIX_CLIENTS)]
            for peer in holders:
                assert (await peer.request("hello"))["ok"]
            goal = await holders[0].request("send_goal", trajectory=goal_msg(t=5.0))
            backend.step(0.2)
            # Connections over the limit that say nothing hold a place for the deadline only;
            # beyond OVER_LIMIT_CLIENTS of them, more are refused at once.
            silent = [await Peer.unix(path) for _ in range(OVER_LIMIT_CLIENTS)]
            await logs.wait_for(f"client {3 + OVER_LIMIT_CLIENTS} (unix pid")
            refused = await Peer.unix(path)
            assert (await refused.recv())["error"]["code"] == "busy"
            assert await refused.eof() == b""
            await logs.wait_for("refused: over the limit (4 connections over it already")
            for peer in silent:
                timed_out = await peer.recv()
                assert timed_out["id"] is None and timed_out["error"]["code"] == "busy"
                assert "within 0.5 s of connecting" in timed_out["error"]["message"]
                assert await peer.eof() == b""
            # A stop is served over the limit, answered, and the connection closed.
            operator = await Peer.unix(path)
            assert await operator.request("stop") == {"id": 1, "ok": True, "stopped": True}
            assert await operator.eof() == b""
            backend.step(0.02)
            result = await holders[0].event("result")
            assert result["goal_id"] == goal["goal_id"] and result["status"] == "canceled"
            # A stop cut off before its newline is not executed, over the limit either.
            cut = await Peer.unix(path)
            await cut.send(b'{"id": 1, "op": "stop"}')
            cut.writer.write_eof()
            refused_cut = await cut.recv()
            assert refused_cut["error"]["code"] == "bad_json"
            assert "it was not executed" in refused_cut["error"]["message"]
            assert await cut.eof() == b""
            # Only the first request counts: a stop after another request is not served.
            late = await Peer.unix(path)
            await late.send(b'{"id": 1, "op": "get_status"}\n{"id": 2, "op": "stop"}\n')
            assert (await late.recv())["error"]["code"] == "busy"
            assert await late.eof() == b""
            assert server.stats()["stops_over_limit"] == 1
            for peer in (*holders, *silent, refused, operator, cut, late):
                await peer.close()

    run(main())


def test_tcp_has_its_own_limit_and_a_short_authentication_deadline(
    tmp_path: Path, logs: LogWatch
) -> None:
    async def main() -> None:
        tcp = TcpSettings("127.0.0.1", 0, TOKEN, max_clients=2, auth_timeout_s=0.3,
                          auth_failure_delay_s=0.0)
        async with serving(tmp_path / "d.sock", tcp=tcp) as (server, backend):
            assert server.tcp_address is not None
            holders = [await Peer.tcp(server.tcp_address) for _ in range(2)]
            for peer in holders:
                assert (await peer.request("auth", token=TOKEN))["authenticated"] is True
            # Over the TCP limit: auth then stop is served; anything else is not.
            over = await Peer.tcp(server.tcp_address)
            assert (await over.request("auth", token=TOKEN))["authenticated"] is True
            assert await over.request("stop") == {"id": 2, "ok": True, "stopped": True}
            assert await over.eof() == b""
            no_auth = await Peer.tcp(server.tcp_address)
            refused = await no_auth.request("stop")
            assert refused["error"]["code"] == "unauthorized"
            assert await no_auth.eof() == b""
            garbage = await Peer.tcp(server.tcp_address)
            await garbage.send(b"{{{\n")
            assert (await garbage.recv())["error"]["code"] == "unauthorized"
            assert await garbage.eof() == b""
            busy = await Peer.tcp(server.tcp_address)
            assert (await busy.request("auth", token=TOKEN))["ok"]
            reply = await busy.request("hello")
            assert reply["error"]["code"] == "busy"
            assert "within 2 s of its auth request" in reply["error"]["message"]
            assert await busy.eof() == b""
            # Squatters never authenticate: they go at the deadline, counted from their
            # opening, even while they trickle bytes (a request never completed). A byte
            # sent after the server closed may reset the connection before its last message
            # is read: the server's log says why it closed.
            squatters = [await Peer.tcp(server.tcp_address) for _ in range(2)]
            for peer in squatters:
                for _ in range(200):
                    try:
                        await peer.send(b" ")
                        closing = await peer.recv(timeout_s=0.05)
                    except asyncio.TimeoutError:  # the builtin TimeoutError from 3.11 on
                        continue
                    except (ConnectionResetError, BrokenPipeError):
                        break
                    assert closing["error"]["code"] == "unauthorized"
                    assert "within 0.3 s of connecting" in closing["error"]["message"]
                    break
                else:
                    raise AssertionError("an unauthenticated connection trickling bytes was kept")
            await logs.wait_count("unauthorized (no auth request in time)", 2)
            await holders[0].close()
            await logs.wait_for("disconnected: closed by the client")
            good = await Peer.tcp(server.tcp_address)  # a slot is free again
            assert (await good.request("auth", token=TOKEN))["ok"]
            assert (await good.request("hello"))["ok"]
            for peer in (*holders, *squatters, over, no_auth, garbage, busy, good):
                await peer.close()
            assert backend.stops == 1

    run(main())


def test_strangers_waiting_to_authenticate_never_take_the_token_holders_slots(
    tmp_path: Path, logs: LogWatch, monkeypatch: pytest.MonkeyPatch
) -> None:
    """30 connections that never authenticate, held open, against 8 authenticated slots and
    16 places to wait: the token holder is served in full (not only a stop), and the longest
    waiting strangers are the ones dropped. (The grace that protects a just-opened connection
    is off, so that which ones go does not depend on how fast this machine opens them.)"""
    monkeypatch.setattr(tcp_door, "HANDSHAKE_GRACE_S", 0.0)

    async def main() -> None:
        tcp = TcpSettings("127.0.0.1", 0, TOKEN, auth_timeout_s=30.0)
        async with serving(tmp_path / "d.sock", tcp=tcp) as (server, backend):
            assert server.tcp_address is not None
            strangers = [await Peer.tcp(server.tcp_address) for _ in range(30)]
            await logs.wait_for("client 30 (tcp 127.0.0.1")
            operator = await Peer.tcp(server.tcp_address)
            assert (await operator.request("auth", token=TOKEN))["authenticated"] is True
            assert (await operator.request("hello"))["ok"]
            assert await operator.request("stop") == {"id": 3, "ok": True, "stopped": True}
            assert backend.stops == 1
            status = (await operator.request("get_status"))["server"]
            clients = status["clients"]
            assert [c["authenticated"] for c in clients].count(True) == 1
            assert status["tcp"]["max_unauthenticated"] == 16
            # 31 came, 16 could wait: the 15 longest waiting went (the operator, then
            # authenticated, waits no more).
            assert status["tcp"]["dropped_waiting"] == 15
            assert status["tcp"]["waiting"] == 15
            for peer in strangers[:15]:  # dropped without an answer
                assert await peer.eof() == b""
            assert not strangers[15].reader.at_eof()
            for peer in (*strangers, operator):
                await peer.close()

    run(main())


def test_failed_authentications_are_answered_slowly_per_address(
    tmp_path: Path, logs: LogWatch
) -> None:
    """Each wrong token from one address is answered at least auth_failure_delay_s after the
    previous one, however many connections try at once; the right token is not held back by
    them; the address is logged once, not once per attempt."""
    delay = 1.0  # long enough that the operator's auth is answered first on a busy machine
    tries = 4

    async def main() -> None:
        tcp = TcpSettings("127.0.0.1", 0, TOKEN, auth_timeout_s=30.0, auth_failure_delay_s=delay)
        async with serving(tmp_path / "d.sock", tcp=tcp) as (server, _):
            assert server.tcp_address is not None
            loop = asyncio.get_running_loop()
            started = loop.time()
            guessers = [await Peer.tcp(server.tcp_address) for _ in range(tries)]
            for peer in guessers:
                await peer.send({"id": 1, "op": "auth", "token": "guess-guess-guess"})
            # Meanwhile the token holder on the same address gets in before any guesser's
            # answer (the first is due `delay` after its failure).
            operator = await Peer.tcp(server.tcp_address)
            assert (await operator.request("auth", token=TOKEN))["authenticated"] is True
            assert server.stats()["tcp"]["failed_auth"] == tries
            for peer in guessers:  # nothing answered yet
                assert not peer.reader.at_eof() and not peer.reader._buffer
            answers = []
            for peer in guessers:
                answers.append(await peer.recv(timeout_s=tries * delay + 10.0))
                assert await peer.eof() == b""
            elapsed = loop.time() - started
            assert all(a["error"]["code"] == "unauthorized" for a in answers)
            # A lower bound: the answers were spaced by the delay.
            assert elapsed >= tries * delay * 0.99, elapsed
            assert logs.count("tcp 127.0.0.1: failed authentication") == 1
            for peer in (*guessers, operator):
                await peer.close()

    run(main())


def test_tcp_connections_do_not_take_unix_slots(tmp_path: Path) -> None:
    path = tmp_path / "d.sock"

    async def main() -> None:
        tcp = TcpSettings("127.0.0.1", 0, TOKEN, max_clients=3)
        async with serving(path, max_clients=1, tcp=tcp) as (server, _):
            assert server.tcp_address is not None
            remote = [await Peer.tcp(server.tcp_address) for _ in range(3)]
            for peer in remote:
                assert (await peer.request("auth", token=TOKEN))["ok"]
            local = await Peer.unix(path)
            assert (await local.request("hello"))["ok"]
            assert [c["transport"] for c in server.stats()["clients"]] == ["tcp"] * 3 + ["unix"]
            assert server.stats()["tcp_max_clients"] == 3
            for peer in (*remote, local):
                await peer.close()

    run(main())


def test_idle_connections_are_closed_engaged_ones_are_not(tmp_path: Path, logs: LogWatch) -> None:
    path = tmp_path / "d.sock"

    async def main() -> None:
        async with serving(path, idle_timeout_s=0.3) as (server, backend):
            subscribed, running, idle = [await Peer.unix(path) for _ in range(3)]
            assert (await subscribed.request("subscribe_state"))["ok"]
            goal = await running.request("send_goal", trajectory=goal_msg(t=5.0))
            assert (await idle.request("hello"))["ok"]
            closing = await idle.recv()
            assert closing["id"] is None and closing["error"]["code"] == "idle"
            assert "no request for 0.3 s" in closing["error"]["message"]
            assert await idle.eof() == b""
            await logs.wait_for("disconnected: idle for 0.3 s (idle_timeout_s)")
            # The other two have not sent anything since either, and are still served.
            assert (await running.request("hello"))["ok"]
            assert (await subscribed.request("hello"))["ok"]
            # The goal ends: from then on, its client is idle too.
            backend.step(5.5)
            result = await running.event("result")
            assert result["goal_id"] == goal["goal_id"]
            assert (await running.recv())["error"]["code"] == "idle"
            assert await running.eof() == b""
            assert (await subscribed.request("get_status"))["ok"]
            assert [c["subscribed"] for c in server.stats()["clients"]] == [True]
            for peer in (subscribed, running, idle):
                await peer.close()

    run(main())
