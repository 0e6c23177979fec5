"""The unix socket and TCP transport: NDJSON over streams, one task pair per client (asyncio).

Theory of operation
-------------------
What this adds to the request layer (``jtc_hw.daemon.core.requests``, which executes every
operation): **framing** (``protocol.Decoder`` reads NDJSON lines and binary frames; after a
``bad_frame`` the connection is closed, its stream being out of sync; ``framing.encode``'s
bytes are written), **slots** (who may connect, how many), **authentication** on TCP (the token
handshake, ``jtc_hw.daemon.transports.tcp_door``) and **deadlines** (authentication, idleness). Each
connection is a ``Connection``: the request layer's ``Outlet`` for its client's later
messages (goal events, state), and the holder of its ``Caller``. Long lines are decoded in a
worker thread, so that no client's big goal holds the event loop (an operator's ``stop``).

Per client, a reader task handles requests one after another (so replies come back in request
order; each reply is queued before the reader awaits anything else, as the request layer
asks) and a writer task drains a bounded outgoing queue: ``state`` and ``feedback`` are
dropped (and counted) beyond ``client_queue_size`` messages, replies and results never; a
client whose queue reaches ``client_queue_hard_cap`` is disconnected (docs/protocol.md, "Slow
subscribers").

Admission (docs/protocol.md, "A stop always gets through"): the unix socket and TCP have
separate limits (``max_clients``, ``tcp.max_clients``); ``RESERVED_UNIX_CLIENTS`` more unix
connections are admitted for peers whose ``SO_PEERCRED`` uid is the daemon's or root's. A
connection over its limit may send one ``stop`` within ``OVER_LIMIT_DEADLINE_S``
(``_serve_over_limit``; on TCP once authenticated, ``stop_only``), then it is closed. A TCP
connection first waits to authenticate in the ``TcpDoor``'s room, so strangers never take
``tcp.max_clients`` slots. Admitted connections are closed by their deadlines:
``tcp.auth_timeout_s`` to authenticate, ``idle_timeout_s`` idle (no request, no subscription,
no goal running).
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

from ... import __version__
from ...api.framing import (
    BAD_FRAME,
    BUSY,
    IDLE,
    PROTOCOL_VERSION,
    UNAUTHORIZED,
    RequestError,
    encode,
    error_reply,
    reply,
)
from ...api.protocol import Decoder
from ...api.requests import Auth, Request, Stop
from ...errors import ControllerStateError
from ..core.backend_api import Backend
from ..core.requests import Caller, Requests
from ..settings import DaemonSettings
from .connection import (
    OVER_LIMIT_CLIENTS,
    OVER_LIMIT_DEADLINE_S,
    RESERVED_UNIX_CLIENTS,
    Connection,
    is_privileged,
    peer_identity,
)
from .tcp_door import TcpDoor
from .unix_socket import bind_unix, remove_socket_file

__all__ = ["Server"]

log = logging.getLogger("jtc_hw.server")

_READ_CHUNK = 256 << 10
"""Bytes one read of a connection takes at most: asyncio's transports receive at most 256 KiB
at a time."""
_STREAM_LIMIT = 256 << 10
"""asyncio's stream buffer limit: a connection's transport stops reading once twice this is
buffered and not read. The default (64 KiB) made a 200 kB goal frame arrive in four reads with
a pause and a resume of the transport between them (0.3 ms each)."""
DECODE_IN_WORKER_BYTES = 64 * 1024
"""Lines at least this long (a goal of a few hundred points and more) are decoded and parsed in
a worker thread: a 2,000-point goal takes ~10 ms, a 6 MB one 150-300 ms, during which the
event loop would serve nobody else (an operator's ``stop`` included)."""
_OVER_LIMIT_MAX_BYTES = 4096
"""Longest request read from a connection over the limit (``auth`` and ``stop`` are short)."""
_WRITE_BATCH = 65536


class Server:
    """The unix socket and TCP endpoints in front of the request layer.

    Example::

        server = Server(backend, DaemonSettings(socket="/run/jtc-hw/jtc-hw.sock"))
        await server.start()
        ...
        await server.close()

    Args:
        backend: the control loop's host.
        settings: the daemon's settings (checked when they were built).
        requests: the request layer shared with the other transports; ``None``: one of its
            own over ``backend`` (closed with the server).
    """

    def __init__(
        self, backend: Backend, settings: DaemonSettings, requests: Requests | None = None
    ) -> None:
        self.backend = backend
        self.settings = settings
        self._owns_requests = requests is None
        if requests is None:
            requests = Requests(backend, self.settings.max_message_bytes)
        self.requests = requests
        self._servers: list[asyncio.Server] = []
        self._conns: dict[int, Connection] = {}
        self._tasks: dict[int, asyncio.Task[None]] = {}
        self._number = 0
        self._refused_busy = 0
        self._over_limit = {"unix": 0, "tcp": 0}  # connections over the limit, being served
        self._stops_over_limit = 0
        self._socket_identity: tuple[int, int] | None = None
        self._started = False
        self._closed = False
        self._tcp_address: tuple[str, int] | None = None
        self._token = b"" if self.settings.tcp is None else self.settings.tcp.token.encode()
        self._decoding: ThreadPoolExecutor | None = None  # created on the first long line
        tcp = self.settings.tcp
        self._door = (
            None if tcp is None else TcpDoor(tcp.max_unauthenticated, tcp.auth_failure_delay_s)
        )

    # -- lifecycle ----------------------------------------------------------------------------

    @property
    def path(self) -> Path | None:
        """The unix socket file, if one is configured."""
        p = self.settings.socket
        return None if p is None else Path(p)

    @property
    def tcp_address(self) -> tuple[str, int] | None:
        """The bound TCP ``(host, port)`` once started (the real port when 0 was asked)."""
        return self._tcp_address

    async def start(self) -> None:
        """Have the request layer listen to the backend, and start listening.

        Raises:
            ConfigurationError: the socket path is in use by a live daemon, is not a socket,
                or cannot be bound (names the path and what to check).
            OSError: the TCP address cannot be bound.
            ControllerStateError: already started.
        """
        if self._started:
            raise ControllerStateError("the server is already started")
        self._started = True
        self.requests.listen()
        self.requests.server_status = self.stats
        try:
            if self.path is not None:
                sock, self._socket_identity = bind_unix(
                    self.path, self.settings.socket_mode, self.settings.socket_group
                )
                self._servers.append(
                    await asyncio.start_unix_server(
                        partial(self._accept, "unix"), sock=sock, limit=_STREAM_LIMIT
                    )
                )
                log.info("listening on %s (mode %03o)", self.path, self.settings.socket_mode)
            endpoint = self.settings.tcp
            if endpoint is not None:
                # "localhost" could bind ::1 and 127.0.0.1 on two different free ports.
                host = "127.0.0.1" if endpoint.host == "localhost" else endpoint.host
                tcp = await asyncio.start_server(
                    partial(self._accept, "tcp"), host, endpoint.port, limit=_STREAM_LIMIT
                )
                self._servers.append(tcp)
                name = tcp.sockets[0].getsockname()
                self._tcp_address = (name[0], name[1])
                log.info("listening on tcp %s:%d (token required)", name[0], name[1])
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        """Stop listening, give each client up to ``close_timeout_s`` to read what is queued,
        disconnect them, and remove the socket file (if it is still ours). Idempotent; as
        ``Transport.close``, errors while closing are logged."""
        if self._closed:
            return
        self._closed = True
        if self._owns_requests:
            self.requests.close()  # events from now on are ignored, as the clients go
        for srv in self._servers:
            srv.close()
        tasks = list(self._tasks.values())
        decoding, self._decoding = self._decoding, None
        for conn in self._conns.values():
            conn.close_reason = "server closing"
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)
        for srv in self._servers:
            await srv.wait_closed()
        self._servers.clear()
        if self.path is not None and self._socket_identity is not None:
            remove_socket_file(self.path, self._socket_identity)
            self._socket_identity = None
        if decoding is not None:  # the readers are gone: nothing is decoding any more
            decoding.shutdown(wait=True)

    async def __aenter__(self) -> Server:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- connections --------------------------------------------------------------------------

    async def _accept(
        self, kind: str, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        self._number += 1
        number = self._number
        peer, uid, host = peer_identity(kind, writer)
        if self._closed:
            writer.transport.abort()
            return
        now = time.monotonic()
        conn = Connection(number, kind, peer, reader, writer, self.settings, uid, now, host)
        task = asyncio.current_task()
        assert task is not None
        if kind == "tcp":
            self._wait_to_authenticate(conn, now)
        admitted = self._admit(conn)
        if admitted is None:
            self._tasks[number] = task
            try:
                await self._serve_over_limit(conn)
            except asyncio.CancelledError:
                writer.transport.abort()  # the server is closing
            finally:
                self._tasks.pop(number, None)
            return
        conn.reserved = admitted
        self._conns[number] = conn
        self._tasks[number] = task
        log.info("%s connected%s", conn.label, " (reserved slot)" if conn.reserved else "")
        writer_task = asyncio.create_task(self._write_loop(conn))
        try:
            await self._read_loop(conn)
        except asyncio.CancelledError:
            pass  # the server is closing; this is the connection's top-level task
        except OSError as exc:
            conn.close_reason = f"connection error: {exc}"
        finally:
            await self._finish(conn, writer_task)

    def _wait_to_authenticate(self, conn: Connection, now: float) -> None:
        """Let a TCP connection into the handshake room, closing those it replaces."""
        assert self._door is not None
        for old in self._door.enter(conn, now):
            if isinstance(old, Connection):
                old.abort(
                    "unauthorized: closed to make room for a newer connection "
                    f"({self._door.max_unauthenticated} waited to authenticate, "
                    "tcp.max_unauthenticated)"
                )

    def _limit(self, kind: str) -> tuple[int, str]:
        """A transport's connection limit and the setting that says so."""
        if kind == "tcp":
            assert self.settings.tcp is not None
            return self.settings.tcp.max_clients, "tcp.max_clients"
        return self.settings.max_clients, "max_clients"

    def _admit(self, conn: Connection) -> bool | None:
        """Whether ``conn`` gets a slot: ``False`` an ordinary one, ``True`` a reserved one,
        ``None`` none (it is over its transport's limit). A TCP connection is let in to
        authenticate; its slot is decided by ``_authenticate``."""
        if conn.kind == "tcp":
            return False
        count = sum(1 for c in self._conns.values() if c.kind == conn.kind)
        limit, _ = self._limit(conn.kind)
        if count < limit:
            return False
        if conn.kind == "unix" and is_privileged(conn.uid):
            if count < limit + RESERVED_UNIX_CLIENTS:
                return True
        return None

    def _busy_message(self, kind: str) -> str:
        limit, setting = self._limit(kind)
        since = "its auth request" if kind == "tcp" else "connecting"
        return (
            f"the daemon already serves {limit} {kind} clients ({setting}); over the limit a "
            f"connection may only send a 'stop' request, within {OVER_LIMIT_DEADLINE_S:g} s "
            f"of {since}; try again later"
        )

    async def _serve_over_limit(self, conn: Connection) -> None:
        """Serve a unix connection over the limit: one ``stop`` within ``OVER_LIMIT_DEADLINE_S``,
        else ``busy``; then close it (TCP: ``Connection.stop_only``). A stop must get through
        when every slot is taken (by forgotten clients, or by someone holding them on purpose);
        the deadline and ``OVER_LIMIT_CLIENTS`` bound what the connections over the limit can
        hold in turn."""
        self._refused_busy += 1
        kind, writer = conn.kind, conn.writer
        if self._over_limit[kind] >= OVER_LIMIT_CLIENTS:
            log.warning(
                "%s refused: over the limit (%d connections over it already being served)",
                conn.label,
                self._over_limit[kind],
            )
            busy = error_reply(None, BUSY, self._busy_message(kind))
            await self._write_and_close(writer, [encode(busy)])
            return
        log.info("%s is over the limit: serving only a stop request", conn.label)
        self._over_limit[kind] += 1
        try:
            answer = await self._over_limit_request(conn)
        finally:
            self._over_limit[kind] -= 1
        await self._write_and_close(writer, answer)

    async def _over_limit_request(self, conn: Connection) -> list[bytes]:
        """The messages to send before closing (an ``auth`` reply is written at once)."""
        deadline = time.monotonic() + OVER_LIMIT_DEADLINE_S
        decoder = Decoder(_OVER_LIMIT_MAX_BYTES)
        out: list[bytes] = []
        while True:
            try:
                data = await asyncio.wait_for(
                    conn.reader.read(_READ_CHUNK), max(0.0, deadline - time.monotonic())
                )
            except asyncio.TimeoutError:  # the builtin TimeoutError from 3.11 on
                out.append(encode(error_reply(None, BUSY, self._busy_message(conn.kind))))
                return out
            except OSError:
                return out
            for item in decoder.feed(data) if data else decoder.end():
                conn.requests += 1
                rid = item.request_id if isinstance(item, RequestError) else item.id
                if isinstance(item, RequestError):
                    # Say what is wrong with it (e.g. a stop without its newline is not run).
                    out.append(self.requests.refuse(conn.caller, None, item).data)
                    return out
                if isinstance(item, Stop):
                    self._stops_over_limit += 1
                    log.info("%s: stop (over the limit)", conn.label)
                    out.append((await self.requests.answer(conn.caller, item)).data)
                    return out
                out.append(encode(error_reply(rid, BUSY, self._busy_message(conn.kind))))
                return out
            if not data:
                return out

    async def _write_and_close(self, writer: asyncio.StreamWriter, messages: list[bytes]) -> None:
        writer.write(b"".join(messages))
        try:
            await asyncio.wait_for(writer.drain(), self.settings.close_timeout_s)
            writer.close()
            await asyncio.wait_for(writer.wait_closed(), self.settings.close_timeout_s)
        except (OSError, asyncio.TimeoutError):
            writer.transport.abort()

    async def _finish(self, conn: Connection, writer_task: asyncio.Task[None]) -> None:
        conn.closing = True
        conn.wake.set()
        try:
            await asyncio.wait_for(writer_task, self.settings.close_timeout_s)
        except asyncio.TimeoutError:
            conn.abort(f"{conn.close_reason}; did not read its last messages in time")
        except asyncio.CancelledError:
            writer_task.cancel()
            conn.abort(conn.close_reason)
        if not conn.gone:
            conn.gone = True
            conn.writer.close()
            try:
                await asyncio.wait_for(conn.writer.wait_closed(), self.settings.close_timeout_s)
            except (OSError, asyncio.TimeoutError, asyncio.CancelledError):
                conn.writer.transport.abort()
        self._conns.pop(conn.number, None)
        self._tasks.pop(conn.number, None)
        if self._door is not None:
            self._door.leave(conn)
        self.requests.leave(conn.caller)
        running = sorted(conn.caller.goals)
        extra = ""
        if running:
            extra = (
                f"; goal(s) {', '.join(map(str, running))} still running: they run on to "
                "their results, which will be discarded"
            )
        level = logging.WARNING if conn.too_slow else logging.INFO
        log.log(
            level,
            "%s disconnected: %s (%d requests, %d state and %d feedback messages dropped)%s",
            conn.label,
            conn.close_reason,
            conn.requests,
            conn.caller.dropped_state,
            conn.caller.dropped_feedback,
            extra,
        )

    def _read_timeout(self, conn: Connection, now: float) -> float | None:
        """How long the next read may wait before the connection's deadline is looked at."""
        if not conn.authenticated or conn.stop_only:
            return max(0.0, conn.auth_deadline - now)
        idle = self.settings.idle_timeout_s
        if not idle:
            return None
        if conn.caller.engaged:
            return float(idle)  # then look again: it may have become idle meanwhile
        return max(0.0, conn.activity + idle - now)

    def _timed_out(self, conn: Connection, now: float) -> bool:
        """After a read timed out: whether the connection must close (and why, queued)."""
        if conn.stop_only:
            self._reject(conn, None, RequestError(BUSY, self._busy_message(conn.kind)))
            conn.close_reason = "over the limit: no stop in time"
            return True
        if not conn.authenticated:
            assert self.settings.tcp is not None
            message = (
                f"no auth request within {self.settings.tcp.auth_timeout_s:g} s of "
                "connecting; closing the connection"
            )
            self._reject(conn, None, RequestError(UNAUTHORIZED, message))
            conn.close_reason = "unauthorized (no auth request in time)"
            return True
        idle = self.settings.idle_timeout_s
        if conn.caller.engaged:
            conn.last_activity = now
            return False
        if not idle or now < conn.activity + idle:
            return False
        message = (
            f"no request for {idle:g} s, no subscription and no goal running (idle_timeout_s); "
            "closing the connection"
        )
        self._reject(conn, None, RequestError(IDLE, message))
        conn.close_reason = f"idle for {idle:g} s (idle_timeout_s)"
        return True

    async def _decode(self, decoder: Decoder, data: bytes) -> list[Any]:
        """``decoder.feed(data)``; in the worker thread when it completes a long line (a binary
        frame's raw bytes count for less: ``Decoder.decode_cost``).

        Each connection's reader awaits its own decode, so its requests stay in order; the
        event loop serves the other connections meanwhile (the worker holds the interpreter
        lock only for switch intervals at a time). A cheap feed stays in the event loop: the
        hop to the worker and back cost 0.4 ms of a 2,000-point goal frame's 0.6.
        """
        if decoder.decode_cost(data) < DECODE_IN_WORKER_BYTES:
            return decoder.feed(data)
        if self._decoding is None:
            self._decoding = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jtc-hw-decode")
        return await asyncio.get_running_loop().run_in_executor(self._decoding, decoder.feed, data)

    async def _read_loop(self, conn: Connection) -> None:
        decoder = Decoder(self.settings.max_message_bytes)
        while not conn.closing:
            timeout = self._read_timeout(conn, time.monotonic())
            try:
                if timeout is None:
                    data = await conn.reader.read(_READ_CHUNK)
                else:
                    data = await asyncio.wait_for(conn.reader.read(_READ_CHUNK), timeout)
            except asyncio.TimeoutError:  # before OSError (3.11 on: the builtin, an OSError)
                if self._timed_out(conn, time.monotonic()):
                    return
                continue
            except OSError as exc:
                conn.close_reason = f"connection error: {exc}"
                return
            items = await self._decode(decoder, data) if data else decoder.end()
            for item in items:
                await self._handle(conn, item)
                if isinstance(item, RequestError) and item.code == BAD_FRAME:
                    # The decoder reads nothing more: the stream is out of sync.
                    conn.close_reason = "bad_frame: the stream is out of sync"
                    conn.closing = True
                if conn.closing:
                    return
            if not data:
                return

    async def _write_loop(self, conn: Connection) -> None:
        writer = conn.writer
        try:
            while True:
                if not conn.queue:
                    if conn.closing or conn.gone:
                        return
                    conn.wake.clear()
                    await conn.wake.wait()
                    continue
                batch: list[bytes] = []
                size = 0
                while conn.queue and size < _WRITE_BATCH:
                    data = conn.queue.popleft()
                    batch.append(data)
                    size += len(data)
                writer.write(b"".join(batch))
                await writer.drain()
        except OSError as exc:
            if not conn.gone:
                conn.close_reason = f"connection lost while writing: {exc}"
                conn.gone = True
                conn.queue.clear()
                conn.closing = True
                writer.transport.abort()

    # -- requests -----------------------------------------------------------------------------

    async def _handle(self, conn: Connection, item: Request | RequestError) -> None:
        conn.requests += 1
        conn.last_activity = time.monotonic()
        if not conn.authenticated:
            await self._authenticate(conn, item)
            return
        if conn.stop_only:
            await self._stop_only(conn, item)
            return
        if isinstance(item, Auth) and conn.kind == "tcp" and not self._token_ok(item.token):
            await self._authenticate(conn, item)  # a wrong token is a failed handshake
            return
        answered = await self.requests.answer(conn.caller, item)
        conn.send(answered.data)  # before awaiting anything (jtc_hw.daemon.core.requests)

    async def _authenticate(self, conn: Connection, item: Request | RequestError) -> None:
        """The handshake's one request: ``auth`` with the token takes a TCP slot (over
        ``tcp.max_clients``: a stop-only one); anything else is answered ``unauthorized``
        after the peer's delay (``TcpDoor.failure``) and the connection is closed."""
        assert self._door is not None
        if isinstance(item, Auth) and self._token_ok(item.token):
            self._door.leave(conn)
            conn.authenticated = True
            limit, _ = self._limit("tcp")
            held = sum(
                1 for c in self._conns.values()
                if c.kind == "tcp" and c.authenticated and not c.stop_only and c is not conn
            )
            if held >= limit:
                conn.stop_only = True
                conn.auth_deadline = time.monotonic() + OVER_LIMIT_DEADLINE_S
                self._refused_busy += 1
                log.info("%s authenticated, over the limit: serving only a stop", conn.label)
            else:
                log.info("%s authenticated", conn.label)
            conn.send(encode(reply(item.id, authenticated=True)))
            return
        delay = self._door.failure(conn.host, time.monotonic())
        if delay > 0:
            await asyncio.sleep(delay)  # the rate limit of failures, not a wait for anything
        if isinstance(item, Auth):
            message = "wrong token; closing the connection"
        else:
            message = (
                'the first request on a TCP connection must be {"op": "auth", "token": ...}; '
                "closing the connection"
            )
        rid = item.request_id if isinstance(item, RequestError) else item.id
        self._reject(
            conn,
            item if not isinstance(item, RequestError) else None,
            RequestError(UNAUTHORIZED, message, rid),
        )
        conn.close_reason = "unauthorized"
        conn.closing = True
        conn.wake.set()

    async def _stop_only(self, conn: Connection, item: Request | RequestError) -> None:
        """An authenticated TCP connection over ``tcp.max_clients``: a ``stop`` is executed
        and answered, anything else gets ``busy``; either way the connection then closes."""
        if isinstance(item, Stop):
            self._stops_over_limit += 1
            log.info("%s: stop (over the limit)", conn.label)
            conn.send((await self.requests.answer(conn.caller, item)).data)
        else:
            request = None if isinstance(item, RequestError) else item
            rid = item.request_id if isinstance(item, RequestError) else item.id
            self._reject(conn, request, RequestError(BUSY, self._busy_message(conn.kind), rid))
        conn.close_reason = "over the limit: served one request"
        conn.closing = True
        conn.wake.set()

    def _token_ok(self, token: str) -> bool:
        return bool(self._token) and hmac.compare_digest(token.encode("utf-8"), self._token)

    def _reject(self, conn: Connection, request: Request | None, error: RequestError) -> None:
        conn.send(self.requests.refuse(conn.caller, request, error).data)

    def stats(self, caller: Caller | None = None) -> dict[str, Any]:
        """The server's part of ``get_status`` (``server``), as ``caller`` asks it."""
        return {
            "version": __version__,
            "protocol_version": PROTOCOL_VERSION,
            "max_clients": self.settings.max_clients,
            "reserved_clients": RESERVED_UNIX_CLIENTS,
            "tcp_max_clients": None if self.settings.tcp is None else self.settings.tcp.max_clients,
            "idle_timeout_s": self.settings.idle_timeout_s,
            "tcp": None if self._door is None else self._door.stats(),
            "clients": [c.stats() for c in self._conns.values()],
            "you": None if caller is None else caller.number,
            "connections_total": self._number,
            "refused_busy": self._refused_busy,
            "stops_over_limit": self._stops_over_limit,
            "goals_routed": self.requests.goals_routed,
            "results_discarded": self.requests.results_discarded,
        }
