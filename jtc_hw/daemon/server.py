"""The daemon's socket server: asyncio, one task pair per client, the wire format of ``protocol``.

Theory of operation
-------------------
The server owns sockets and nothing else. It decodes requests with ``protocol.Decoder``, calls
the ``Backend`` (which runs the control loop elsewhere, in another process) and writes replies
and events with ``framing.encode``. It never waits on the control loop while holding anything
another client needs: backend coroutines (``send_goal``, ``cancel_goal``, ``send_trajectory``)
are awaited by the requesting client's own task, and the synchronous backend methods must
return at once (they read replicas and caches; see ``Backend``).

Per client, a reader task handles requests one after another (so replies come back in request
order) and a writer task drains a bounded outgoing queue:

- ``state`` and ``feedback`` events are dropped while the queue holds ``client_queue_size``
  messages; the loss is counted per client, reported in the next ``state`` event's ``dropped``
  and in ``get_status``;
- replies and goal ``result`` events are never dropped; a client so slow that its queue reaches
  ``client_queue_hard_cap`` messages is disconnected (and logged).

Goal routing: a goal's events go to the connection that sent it. ``Backend.send_goal`` returns
the id and the server registers the route before it awaits anything else, so no event can
overtake the registration through this server's own scheduling. A backend may still deliver a
goal's events *before* the ``send_goal`` coroutine resumes (e.g. it resolves the id's future and
then, in the same callback, dispatches a batch of events that includes the goal's first
feedback): events for a goal id without a route are held (bounded) and delivered right after
the ``accepted`` reply once the route exists.

A client that disconnects while its goal runs does not stop the goal (as with a ROS action
client that vanishes): the goal runs on to its result, which is logged and discarded.

Admission (a stop always gets through): the unix socket and TCP have separate limits
(``max_clients``, ``tcp.max_clients``); ``RESERVED_UNIX_CLIENTS`` more unix connections are
admitted for peers whose ``SO_PEERCRED`` uid is the daemon's or root's. A unix connection over
its limit is served by ``_serve_over_limit``: one ``stop`` within ``OVER_LIMIT_DEADLINE_S``,
else ``busy``; then it is closed. A TCP connection first waits to authenticate in a room of its
own (``TcpDoor``: at most ``tcp.max_unauthenticated``, the longest waiting dropped for a
newcomer, failed handshakes answered slowly per address), so strangers never take
``tcp.max_clients`` slots; authenticated over that limit, it may send one ``stop`` (``stop_only``).
Admitted connections are closed by their deadlines: a TCP connection that has not authenticated
``tcp.auth_timeout_s`` after opening, and a connection idle (no request, no subscription, no
goal running) for ``idle_timeout_s``.
"""

from __future__ import annotations

import asyncio
import collections
import hmac
import logging
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

from .. import __version__
from ..api.framing import (
    BAD_REQUEST,
    BUSY,
    GOAL_REJECTED,
    HARDWARE,
    IDLE,
    INTERNAL,
    NOT_ACTIVE,
    NOT_FOUND,
    PROTOCOL_VERSION,
    UNAUTHORIZED,
    RequestError,
    encode,
    error_reply,
    reply,
)
from ..api.protocol import (
    Auth,
    CancelGoal,
    Decoder,
    GetConfig,
    GetParameters,
    GetStatus,
    Hello,
    QueryState,
    Rearm,
    Request,
    SendGoal,
    SendTrajectory,
    SetParameters,
    SetSpeedScaling,
    Sim,
    Stop,
    SubscribeState,
    UnsubscribeState,
    command_event,
    feedback_event,
    record_event,
    result_event,
    sample_to_json,
)
from ..controller.goals import GoalFeedback, GoalResult
from ..controller.limits_check import scaling_fields
from ..controller.trajectory import JointTrajectory
from ..errors import (
    ConfigurationError,
    ControllerStateError,
    GoalRejected,
    HardwareError,
    JtcHwError,
)
from .backend_api import Backend, Observer
from .connection import (
    OVER_LIMIT_CLIENTS,
    OVER_LIMIT_DEADLINE_S,
    RESERVED_UNIX_CLIENTS,
    Connection,
    is_privileged,
    peer_identity,
)
from .settings import DaemonSettings
from .tcp_door import TcpDoor
from .unix_socket import bind_unix, remove_socket_file

__all__ = [
    "Backend",
    "Observer",
    "Server",
]

log = logging.getLogger("jtc_hw.server")

EARLY_GOALS = 64
"""Goal ids whose events are held while their route is not registered yet."""
EARLY_EVENTS = 256
"""Feedback events held per such goal (results are always held)."""
FINISHED_GOALS = 256
"""Recently finished goal ids remembered, so that a straggling event is ignored, not held."""
_READ_CHUNK = 65536
DECODE_IN_WORKER_BYTES = 64 * 1024
"""Lines at least this long (a goal of a few hundred points and more) are decoded and parsed in
a worker thread: a 2,000-point goal takes ~10 ms, a 6 MB one 150-300 ms, during which the
event loop would serve nobody else (an operator's ``stop`` included)."""
_OVER_LIMIT_MAX_BYTES = 4096
"""Longest request read from a connection over the limit (``auth`` and ``stop`` are short)."""
_WRITE_BATCH = 65536
_RESERVED_STATE_KEYS = frozenset({"event", "dropped", "dropped_total"})


class Server:
    """The socket API in front of a ``Backend``; also an ``Observer`` of the backend.

    Example::

        server = Server(backend, DaemonSettings(socket="/run/jtc-hw/jtc-hw.sock"))
        await server.start()
        ...
        await server.close()

    Args:
        backend: the control loop's host.
        settings: the daemon's settings (checked when they were built).
    """

    def __init__(self, backend: Backend, settings: DaemonSettings) -> None:
        self.backend = backend
        self.settings = settings
        self._servers: list[asyncio.Server] = []
        self._conns: dict[int, Connection] = {}
        self._tasks: dict[int, asyncio.Task[None]] = {}
        self._routes: dict[int, Connection] = {}
        self._early: collections.OrderedDict[int, list[GoalResult | GoalFeedback]] = (
            collections.OrderedDict()
        )
        self._finished: collections.OrderedDict[int, None] = collections.OrderedDict()
        self._number = 0
        self._refused_busy = 0
        self._over_limit = {"unix": 0, "tcp": 0}  # connections over the limit, being served
        self._stops_over_limit = 0
        self._results_discarded = 0
        self.status_sections: dict[str, Callable[[], dict[str, Any]]] = {}
        """More sections of ``get_status`` by name (an add-on's counters: ``zenoh``); each is
        called in the event loop and must not block nor raise."""
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
        """Register as an observer of the backend and start listening.

        Raises:
            ConfigurationError: the socket path is in use by a live daemon, is not a socket,
                or cannot be bound (names the path and what to check).
            OSError: the TCP address cannot be bound.
            ControllerStateError: already started.
        """
        if self._started:
            raise ControllerStateError("the server is already started")
        self._started = True
        self.backend.add_observer(self)
        try:
            if self.path is not None:
                sock, self._socket_identity = bind_unix(
                    self.path, self.settings.socket_mode, self.settings.socket_group
                )
                self._servers.append(
                    await asyncio.start_unix_server(partial(self._accept, "unix"), sock=sock)
                )
                log.info("listening on %s (mode %03o)", self.path, self.settings.socket_mode)
            endpoint = self.settings.tcp
            if endpoint is not None:
                # "localhost" could bind ::1 and 127.0.0.1 on two different free ports.
                host = "127.0.0.1" if endpoint.host == "localhost" else endpoint.host
                tcp = await asyncio.start_server(partial(self._accept, "tcp"), host, endpoint.port)
                self._servers.append(tcp)
                name = tcp.sockets[0].getsockname()
                self._tcp_address = (name[0], name[1])
                log.info("listening on tcp %s:%d (token required)", name[0], name[1])
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        """Stop listening, give each client up to ``close_timeout_s`` to read what is queued,
        disconnect them, and remove the socket file (if it is still ours). Idempotent.

        Raises:
            Nothing: errors while closing are logged.
        """
        if self._closed:
            return
        self._closed = True
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
        self._routes.clear()
        self._early.clear()
        self._finished.clear()
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
        """Serve a unix connection over the limit: its first request, if it comes within
        ``OVER_LIMIT_DEADLINE_S`` and is ``stop``, is executed and answered; anything else is
        answered ``busy``. Then the connection is closed (TCP: ``Connection.stop_only``).

        A stop must get through when every slot is taken (by forgotten clients, or by
        someone holding them on purpose); the deadline and ``OVER_LIMIT_CLIENTS`` bound what
        the connections over the limit can hold in turn.
        """
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
                    out.append(encode(self._error(conn, None, item)))
                    return out
                if isinstance(item, Stop):
                    self._stops_over_limit += 1
                    log.info("%s: stop (over the limit)", conn.label)
                    answer = await self._answer(conn, item)
                    assert answer is not None  # only send_goal sends its own reply
                    out.append(answer)
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
        running = sorted(conn.goals)
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
            conn.dropped_state,
            conn.dropped_feedback,
            extra,
        )

    def _read_timeout(self, conn: Connection, now: float) -> float | None:
        """How long the next read may wait before the connection's deadline is looked at."""
        if not conn.authenticated or conn.stop_only:
            return max(0.0, conn.auth_deadline - now)
        idle = self.settings.idle_timeout_s
        if not idle:
            return None
        if conn.engaged:
            return float(idle)  # then look again: it may have become idle meanwhile
        return max(0.0, conn.last_activity + idle - now)

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
        if conn.engaged:
            conn.last_activity = now
            return False
        if not idle or now < conn.last_activity + idle:
            return False
        message = (
            f"no request for {idle:g} s, no subscription and no goal running (idle_timeout_s); "
            "closing the connection"
        )
        self._reject(conn, None, RequestError(IDLE, message))
        conn.close_reason = f"idle for {idle:g} s (idle_timeout_s)"
        return True

    async def _decode(self, decoder: Decoder, data: bytes, pending: int) -> list[Any]:
        """``decoder.feed(data)``; in the worker thread when it completes a long line.

        ``pending`` is how many bytes of an unfinished line the decoder held before ``data``.
        Each connection's reader awaits its own decode, so its requests stay in order; the
        event loop serves the other connections meanwhile (the worker holds the interpreter
        lock only for switch intervals at a time).
        """
        newline = data.rfind(b"\n")
        if newline < 0 or pending + newline + 1 < DECODE_IN_WORKER_BYTES:
            return decoder.feed(data)
        if self._decoding is None:
            self._decoding = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jtc-hw-decode")
        return await asyncio.get_running_loop().run_in_executor(self._decoding, decoder.feed, data)

    async def _read_loop(self, conn: Connection) -> None:
        decoder = Decoder(self.settings.max_message_bytes)
        pending = 0  # bytes since the last newline: the unfinished line the decoder holds
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
            items = await self._decode(decoder, data, pending) if data else decoder.end()
            newline = data.rfind(b"\n")
            pending = pending + len(data) if newline < 0 else len(data) - newline - 1
            for item in items:
                await self._handle(conn, item)
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
        if isinstance(item, RequestError):
            self._reject(conn, None, item)
            return
        answer = await self._answer(conn, item)
        if answer is not None:
            conn.send(answer)

    async def _answer(self, conn: Connection, item: Request) -> bytes | None:
        """Execute a request: its encoded reply (success or error), or ``None`` when
        ``_dispatch`` has sent it already. Never raises: a failure is an error reply, logged."""
        try:
            answer = await self._dispatch(conn, item)
            return None if answer is None else encode(answer)
        except RequestError as exc:
            error = exc
        except GoalRejected as exc:
            error = RequestError(GOAL_REJECTED, exc.reason, item.id, exc.error_code)
        except ControllerStateError as exc:
            error = RequestError(NOT_ACTIVE, str(exc), item.id)
        except ConfigurationError as exc:
            error = RequestError(BAD_REQUEST, str(exc), item.id)
        except HardwareError as exc:
            error = RequestError(HARDWARE, str(exc), item.id)
        except JtcHwError as exc:
            error = RequestError(INTERNAL, str(exc), item.id)
        except Exception as exc:
            log.exception("%s: %s failed", conn.label, item.op)
            message = f"internal error: {type(exc).__name__}: {exc}"
            error = RequestError(INTERNAL, message, item.id)
            return encode(self._error(conn, item, error, logged=True))
        return encode(self._error(conn, item, error))

    async def answer_remote(self, conn: Connection, item: Request | RequestError) -> bytes:
        """Execute one request of a transport without a stream of its own (a Zenoh query,
        ``jtc_hw.daemon.zenoh_iface``) through the socket's own dispatch, so that replies and
        errors are exactly the socket's: its encoded reply. ``conn`` stands for the querier;
        the reply to ``send_goal`` is the first message it is sent (``conn.send``), and the
        goal's events are routed to it afterwards.

        Raises:
            Nothing: a failure is an error reply, logged.
        """
        conn.requests += 1
        if isinstance(item, RequestError):
            return encode(self._error(conn, None, item))
        answer = await self._answer(conn, item)
        if answer is not None:
            return answer
        sent = conn.queue.popleft() if conn.queue else None
        if sent is None:  # pragma: no cover - _dispatch returns None only after conn.send
            return encode(error_reply(item.id, INTERNAL, f"{item.op}: no reply"))
        return sent

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
            answer = await self._answer(conn, item)
            assert answer is not None  # only send_goal sends its own reply
            conn.send(answer)
        else:
            request = None if isinstance(item, RequestError) else item
            rid = item.request_id if isinstance(item, RequestError) else item.id
            self._reject(conn, request, RequestError(BUSY, self._busy_message(conn.kind), rid))
        conn.close_reason = "over the limit: served one request"
        conn.closing = True
        conn.wake.set()

    def _token_ok(self, token: str) -> bool:
        return bool(self._token) and hmac.compare_digest(token.encode("utf-8"), self._token)

    def _reject(
        self,
        conn: Connection,
        request: Request | None,
        error: RequestError,
        logged: bool = False,
    ) -> None:
        conn.send(encode(self._error(conn, request, error, logged)))

    @staticmethod
    def _error(
        conn: Connection,
        request: Request | None,
        error: RequestError,
        logged: bool = False,
    ) -> dict[str, Any]:
        """The error reply, logged."""
        rid = error.request_id if error.request_id is not None or request is None else request.id
        if not logged:
            op = request.op if request is not None else "request"
            log.info(
                "%s: rejected %s (id %r): %s: %s", conn.label, op, rid, error.code, error.message
            )
        return error_reply(rid, error.code, error.message, error.error_code)

    async def _dispatch(self, conn: Connection, req: Request) -> dict[str, Any] | None:
        backend = self.backend
        match req:
            case Hello():
                if req.protocol_version is not None and req.protocol_version != PROTOCOL_VERSION:
                    raise RequestError(
                        BAD_REQUEST,
                        f"protocol_version: this daemon speaks version {PROTOCOL_VERSION}; "
                        f"the client asked for {req.protocol_version}",
                        req.id,
                    )
                ours = {
                    "protocol_version": PROTOCOL_VERSION,
                    "server_version": __version__,
                    "joint_names": list(backend.joint_names),
                    "now_ns": backend.now_ns(),
                    "max_message_bytes": self.settings.max_message_bytes,
                }
                return self._merge(req.id, backend.hello(), ours)
            case Auth():
                if conn.kind == "tcp" and not self._token_ok(req.token):
                    await self._authenticate(conn, req)
                    return None
                return reply(req.id, authenticated=True)
            case SendGoal():
                traj = req.trajectory.to_joint_trajectory(backend.now_ns())
                accepted = await backend.send_goal(
                    traj,
                    req.path_tolerance,
                    req.goal_tolerance,
                    req.goal_time_tolerance,
                    time_scaling=req.time_scaling,
                )
                goal_id = accepted.goal_id
                # Nothing may be awaited from here on: the route must exist before this task
                # yields, so that every later event of the goal finds it (module docstring).
                self._routes[goal_id] = conn
                conn.goals.add(goal_id)
                if conn.gone:
                    log.info(
                        "%s left before goal %d was accepted; it runs on to its result, "
                        "which will be discarded",
                        conn.label,
                        goal_id,
                    )
                log.info("%s: goal %d accepted", conn.label, goal_id)
                scaled = {} if accepted.time_scaling is None else {
                    "time_scale": accepted.time_scaling, "duration_s": accepted.duration_s}
                conn.send(encode(reply(req.id, goal_id=goal_id, accepted=True, **scaled)))
                for event in self._early.pop(goal_id, ()):
                    self._route(conn, event)
                return None
            case CancelGoal():
                if not await backend.cancel_goal(req.goal_id):
                    raise RequestError(
                        NOT_FOUND,
                        f"goal {req.goal_id} is not executing (unknown, already finished or "
                        "already being canceled); nothing to cancel",
                        req.id,
                    )
                return reply(req.id, goal_id=req.goal_id, canceling=True)
            case SendTrajectory():
                traj = req.trajectory.to_joint_trajectory(backend.now_ns())
                scaling = await backend.send_trajectory(traj, time_scaling=req.time_scaling)
                return reply(req.id, stopping=not traj.points, **scaling_fields(scaling))
            case Stop():
                if not await backend.stop_motion():
                    return reply(
                        req.id,
                        stopped=False,
                        message="nothing to stop: the controller is not active (see "
                        "get_status: controller.fault)",
                    )
                return reply(req.id, stopped=True)
            case QueryState():
                t = req.resolve(backend.now_ns())
                queried = backend.query_state(t)
                return reply(
                    req.id,
                    time_ns=t,
                    success=queried.success,
                    where=queried.where,
                    joint_names=list(backend.joint_names),
                    **sample_to_json(queried),
                )
            case SubscribeState():
                conn.subscribed = True
                conn.commands = conn.commands or req.commands
                return reply(req.id, subscribed=True, commands=conn.commands)
            case UnsubscribeState():
                conn.subscribed = conn.commands = False
                return reply(req.id, subscribed=False)
            case GetConfig():
                return reply(req.id, config=backend.config_dict())
            case GetStatus():
                sections = {name: get() for name, get in self.status_sections.items()}
                return self._merge(req.id, backend.status(),
                                   {**sections, "server": self.stats(conn)})
            case Sim():
                await backend.sim(req.component, req.freeze, req.fault)
                if req.fault is not None:
                    return reply(req.id, component=req.component, fault=req.fault)
                return reply(req.id, component=req.component, frozen=req.freeze)
            case GetParameters():
                return self._merge(req.id, backend.get_parameters(req.names), {})
            case SetParameters():
                change = await backend.set_parameters(req.parameters)
                log.info(
                    "%s: parameters changed: %s",
                    conn.label,
                    ", ".join(f"{k}={v!r}" for k, v in change.values.items()),
                )
                return self._merge(req.id, change.to_json(), {})
            case SetSpeedScaling():
                speed = await backend.set_speed_scaling(None if req.resume else req.factor)
                log.info(
                    "%s: speed scaling %s: ramping from %g to %g",
                    conn.label,
                    "resumed" if req.resume else "set",
                    speed["factor"],
                    speed["target"],
                )
                return reply(req.id, factor=speed["factor"], target=speed["target"])
            case Rearm():
                done = await backend.rearm()
                if not done:
                    return reply(req.id, rearmed=False, message="nothing to re-arm: no fault")
                return reply(req.id, rearmed=True)
        raise AssertionError(f"unhandled request {req!r}")  # pragma: no cover

    @staticmethod
    def _merge(
        request_id: object, theirs: Mapping[str, Any], ours: Mapping[str, Any]
    ) -> dict[str, Any]:
        out: dict[str, Any] = {"id": request_id, "ok": True}
        out.update((k, v) for k, v in theirs.items() if k not in ("id", "ok"))
        out.update(ours)
        return out

    def stats(self, conn: Connection | None = None) -> dict[str, Any]:
        """The server's part of ``get_status``.

        Raises:
            Nothing.
        """
        return {
            "version": __version__,
            "protocol_version": PROTOCOL_VERSION,
            "max_clients": self.settings.max_clients,
            "reserved_clients": RESERVED_UNIX_CLIENTS,
            "tcp_max_clients": None if self.settings.tcp is None else self.settings.tcp.max_clients,
            "idle_timeout_s": self.settings.idle_timeout_s,
            "tcp": None if self._door is None else self._door.stats(),
            "clients": [c.stats() for c in self._conns.values()],
            "you": None if conn is None else conn.number,
            "connections_total": self._number,
            "refused_busy": self._refused_busy,
            "stops_over_limit": self._stops_over_limit,
            "goals_routed": sorted(self._routes),
            "results_discarded": self._results_discarded,
        }

    # -- Observer -----------------------------------------------------------------------------

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None:
        """Route a goal's event to the client that sent the goal.

        Raises:
            Nothing: a result whose client has gone is logged and discarded.
        """
        if self._closed:
            return
        conn = self._routes.get(event.goal_id)
        if conn is None:
            if event.goal_id in self._finished:
                log.debug("ignoring a late event of finished goal %d", event.goal_id)
                return
            self._hold(event)
            return
        self._route(conn, event)

    def _route(self, conn: Connection, event: GoalResult | GoalFeedback) -> None:
        if isinstance(event, GoalResult):
            self._routes.pop(event.goal_id, None)
            conn.goals.discard(event.goal_id)
            if not conn.goals:  # the idle clock starts when the client's last goal ends
                conn.last_activity = time.monotonic()
            self._finished[event.goal_id] = None
            if len(self._finished) > FINISHED_GOALS:
                self._finished.popitem(last=False)
            if not conn.send(encode(result_event(event))):
                self._results_discarded += 1
                log.info(
                    "goal %d %s (%d: %s) after %s disconnected; result discarded",
                    event.goal_id,
                    event.status.value,
                    int(event.error_code),
                    event.error_string,
                    conn.label,
                )
            return
        if conn.gone:
            return
        try:
            data = encode(feedback_event(event, self.backend.joint_names))
        except (TypeError, IndexError):
            log.exception("cannot encode feedback of goal %d; skipped", event.goal_id)
            return
        if not conn.offer(data):
            conn.dropped_feedback += 1
            conn.dropped_since_state += 1

    def _hold(self, event: GoalResult | GoalFeedback) -> None:
        events = self._early.get(event.goal_id)
        if events is None:
            if len(self._early) >= EARLY_GOALS:
                goal_id, lost = self._early.popitem(last=False)
                log.warning(
                    "discarded %d event(s) of goal %d: no client ever claimed the goal",
                    len(lost),
                    goal_id,
                )
            events = self._early[event.goal_id] = []
        if isinstance(event, GoalResult) or len(events) < EARLY_EVENTS:
            events.append(event)

    def on_command(self, trajectory: JointTrajectory, goal_id: int | None) -> None:
        """Send an accepted command (a goal's trajectory, a topic trajectory; empty: a stop)
        to every client subscribed with ``commands`` (``jtc-hw record``). Not droppable: a
        recording must have every command; a client that stops reading is disconnected at the
        queue's hard cap, as for results.

        Raises:
            Nothing: a command that cannot be encoded is logged and skipped.
        """
        if self._closed:
            return
        subscribers = [c for c in self._conns.values() if c.commands and not c.gone]
        if not subscribers:
            return
        try:
            data = encode(command_event(trajectory, goal_id, self.backend.now_ns()))
        except (TypeError, ValueError):
            log.exception("cannot encode an accepted command; skipped")
            return
        for conn in subscribers:
            conn.send(data)

    def on_record(self, event: dict[str, Any]) -> None:
        """Send a result, fault or re-arm (a ``record`` event) to every client subscribed
        with ``commands`` (``jtc-hw record`` writes them into its bag). Not droppable, as
        commands.

        Raises:
            Nothing: an event that cannot be encoded is logged and skipped.
        """
        if self._closed:
            return
        subscribers = [c for c in self._conns.values() if c.commands and not c.gone]
        if not subscribers:
            return
        try:
            data = encode(record_event(event))
        except (TypeError, ValueError):
            log.exception("cannot encode a recorded event; skipped")
            return
        for conn in subscribers:
            conn.send(data)

    def on_state(self, snapshot: dict[str, Any]) -> None:
        """Send a state snapshot to every subscribed client whose queue has room.

        Raises:
            Nothing: a snapshot that cannot be encoded is logged and skipped.
        """
        if self._closed:
            return
        subscribers = [c for c in self._conns.values() if c.subscribed and not c.gone]
        if not subscribers:
            return
        body = {k: v for k, v in snapshot.items() if k not in _RESERVED_STATE_KEYS}
        try:
            head = encode({"event": "state", **body})[:-2]  # without the closing "}\n"
        except TypeError:
            # Never raise into the backend's dispatch: say what is wrong and skip this one.
            log.exception("cannot encode a state snapshot; skipped")
            return
        for conn in subscribers:
            tail = b',"dropped":%d,"dropped_total":%d}\n' % (
                conn.dropped_since_state,
                conn.dropped_total,
            )
            if conn.offer(head + tail):
                conn.dropped_since_state = 0
            else:
                conn.dropped_state += 1
                conn.dropped_since_state += 1
