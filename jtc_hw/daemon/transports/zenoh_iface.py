"""The daemon on Zenoh: state, events and the socket's operations under a key prefix (API process).

Theory of operation
-------------------
``daemon.zenoh`` (``jtc_hw.daemon.zenoh_config``) starts a :class:`ZenohInterface` next to the
socket server. Key expressions (protocol version :data:`ZENOH_PROTOCOL_VERSION`,
docs/zenoh.md)::

    <prefix>            liveliness token: the daemon is up
    <prefix>/state      the socket's ``state`` event, each one the loop publishes, with
                        ``seq``: its number (a gap: a state lost on the way)
    <prefix>/events     goal ``feedback`` and ``result`` events (with ``goal_id``), and
                        ``fault`` events (the controller's fault set or cleared)
    <prefix>/rpc/<op>   a queryable per socket operation: the query's payload is the socket's
                        request body (``op`` may be left out), the reply the socket's reply

A query is answered by ``Requests.answer`` (``jtc_hw.daemon.core.requests``), as a socket
request is, so replies and errors are byte for byte the socket's. Its querier is a ``Caller``
of its own whose outlet discards what is routed to it later: a goal's ``accepted`` reply is
the query's reply, its feedback and its one result are published on ``events`` as those of
every goal are, so a querier that vanishes leaves nothing waiting and the result is never
lost. The publications come from its being an observer of the backend, in the asyncio
thread; the loop process knows nothing of it.

Credentials: loopback is no door at all on a machine with other users, so every query of an
operation in :data:`COMMANDS` (everything that moves the robot or changes its settings, ``stop``
included) must carry ``daemon.zenoh.token`` as its attachment (a binary frame's query: the
token, ``\\n``, the request line, ``\\n``; its payload the raw bytes: :func:`split_attachment`),
checked in Zenoh's thread before the payload is read: none is answered ``unauthorized`` at
once, a wrong one after :data:`WRONG_TOKEN_DELAY_S` with at most :data:`MAX_REFUSALS_WAITING`
refusals waiting (docs/zenoh.md, "The token"). Watching needs no token.

Memory: Zenoh reassembles a query's whole payload in malloc'd buffers that glibc keeps once
freed, so a payload longer than ``daemon.max_message_bytes`` is answered ``too_large`` from its
length, never copied into Python, and every query of :data:`RELEASE_AFTER_BYTES` or more is
followed by releases of freed memory (:data:`RELEASE_AFTER_S`; docs/zenoh.md, "Memory").

Threads (docs/decisions.md 21): Zenoh's Python API is synchronous and calls back in its own
threads. A query callback only hands the query to the event loop (at most :data:`MAX_QUERIES` in
flight, more are answered ``busy`` at once). Everything sent to Zenoh goes through one bounded
outbox drained by a thread of ours, so the event loop never waits on Zenoh: ``state`` and
``feedback`` are dropped beyond :data:`OUTBOX_SIZE` waiting (counted), replies, results and
faults only beyond :data:`OUTBOX_HARD_CAP` (logged). A Zenoh failure is logged; it never reaches
the loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import threading
import time
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any, Final

from ...api.events import command_event, feedback_event, result_event
from ...api.framing import (
    BAD_FRAME,
    BAD_REQUEST,
    BUSY,
    TOO_LARGE,
    UNAUTHORIZED,
    MessageDecoder,
    RequestError,
    encode,
    error_reply,
)
from ...api.protocol import parse_request
from ...api.requests import Request
from ...controller.goals import GoalFeedback, GoalResult
from ...controller.messages import JointTrajectory
from ...errors import ConfigurationError
from ..core.requests import DISCARD, Caller, Requests
from ..realtime import release_freed_memory, return_freed_memory_promptly
from ..zenoh_config import import_zenoh, session_config
from .zenoh_outbox import Outbox

if TYPE_CHECKING:
    from ..zenoh_config import ZenohSettings

log = logging.getLogger("jtc_hw.zenoh")

__all__ = [
    "COMMANDS",
    "MAX_QUERIES",
    "MAX_REFUSALS_WAITING",
    "RELEASE_AFTER_BYTES",
    "NOT_OVER_ZENOH",
    "OUTBOX_HARD_CAP",
    "OUTBOX_SIZE",
    "ZENOH_PROTOCOL_VERSION",
    "WRONG_TOKEN_DELAY_S",
    "ZenohInterface",
    "keys",
    "split_attachment",
]

ZENOH_PROTOCOL_VERSION: Final = 2
"""Version of the key-expression layout (docs/zenoh.md); the payloads are the socket protocol's
(``protocol_version`` in ``rpc/hello``)."""
MAX_QUERIES: Final = 64
"""Queries executing at once; more are answered ``busy``."""
OUTBOX_SIZE: Final = 256
"""Waiting messages above which ``state`` and ``feedback`` are dropped."""
OUTBOX_HARD_CAP: Final = 4096
"""Waiting messages above which even replies and results are dropped (and logged)."""
FAULT_POLL_S: Final = 0.5
"""How often the controller's fault is looked at (the status is refreshed at 2 Hz)."""
CLOSE_FLUSH_S: Final = 1.0
"""How long closing waits for the outbox to drain (the last results)."""
DECODE_IN_WORKER_BYTES: Final = 64 * 1024
"""Request bodies at least this long are decoded in a worker thread (as on the socket)."""
COMMANDS: Final = frozenset({
    "send_goal", "cancel_goal", "send_trajectory", "stop", "set_parameters",
    "set_speed_scaling", "rearm", "sim",
})
"""Operations a query may ask only with the token (module docstring); the others watch."""
WRONG_TOKEN_DELAY_S: Final = 0.5
"""How long a query with a wrong token waits for its ``unauthorized``."""
MAX_REFUSALS_WAITING: Final = 16
"""Wrong-token refusals waiting at once; more are dropped without a reply."""
RELEASE_AFTER_BYTES: Final = 1 << 20
"""A query whose payload is at least this long is followed by releases of freed memory."""
RELEASE_AFTER_S: Final = (0.2, 1.0, 3.0)
"""When, after such a query has ended, freed memory is released: at once (for a burst of large
queries: one release covers them), and twice more for the buffers Zenoh frees late (measured:
up to a third of a 100 MB query's, between 1 and 2 s after it ended)."""
LOG_REFUSALS_EVERY: Final = 100
"""After the first three, one log line per this many refused queries."""
NOT_OVER_ZENOH: Final = {
    "auth": "put the token (daemon.zenoh.token) in each query's attachment (docs/zenoh.md)",
    "subscribe_state": "subscribe to <prefix>/state instead",
    "unsubscribe_state": "subscribe to <prefix>/state instead",
}
"""Socket operations that have no meaning over Zenoh, and what to do instead."""


def keys(prefix: str) -> dict[str, str]:
    """The key expressions of a daemon at ``prefix``."""
    return {
        "liveliness": prefix,
        "state": f"{prefix}/state",
        "events": f"{prefix}/events",
        "rpc": f"{prefix}/rpc/*",
    }


def split_attachment(attachment: Any) -> tuple[bytes, bytes | None]:
    """A query's attachment as ``(token, header)``: ``header`` is a binary frame's request
    line, when the attachment is ``token \\n line \\n`` (docs/protocol.md, "Binary frames"),
    else None and the whole attachment is the token. A request line holds no newline (JSON
    escapes them in strings), so the last one before the end separates the two."""
    given = b"" if attachment is None else bytes(attachment.to_bytes())
    if not given.endswith(b"\n"):
        return given, None
    token, _, header = given[:-1].rpartition(b"\n")
    return token, header


class ZenohInterface:
    """The daemon's Zenoh session (module docstring).

    Args:
        settings: ``daemon.zenoh``.
        controller: the controller's name (the default prefix's last chunk).
        requests: the request layer, which executes the queries.
        status: the backend's ``status`` (polled for faults).
        add_observer: the backend's ``add_observer``: once started, the interface observes the
            backend, and publishes every state, goal event and accepted command.
    """

    def __init__(
        self,
        settings: ZenohSettings,
        controller: str,
        requests: Requests,
        status: Callable[[], dict[str, Any]],
        add_observer: Callable[[ZenohInterface], None] | None = None,
    ) -> None:
        self.settings = settings
        self.prefix = settings.resolved_prefix(controller)
        self.keys = keys(self.prefix)
        self._requests = requests
        self._status = status
        self._add_observer = add_observer
        self._joint_names = list(requests.backend.joint_names)
        self._max_bytes = requests.max_message_bytes
        self._session: Any = None
        self._declared: list[Any] = []
        self._state_pub: Any = None
        self._events_pub: Any = None
        self._outbox: Outbox | None = None
        self._aio: asyncio.AbstractEventLoop | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._inflight = 0
        self._lock = threading.Lock()  # _inflight, from Zenoh's threads and ours
        self._queries = 0
        self._fault_task: asyncio.Task[None] | None = None
        self._fault: object = None
        self._dropped_since_state = 0
        self._state_seq = 0  # states this interface has had from the loop (a gap: a loss)
        self.published = 0
        self.busy = 0
        self._token = settings.token.encode()
        self.unauthorized = 0  # queries refused for a missing or wrong token
        self._refusals_waiting = 0  # under _lock
        self._refused: dict[str, int] = {}  # refusals by reason, for the log; under _lock
        self._release_pending = False  # under _lock
        self.releases = 0  # releases of freed memory after large queries

    # -- lifecycle ----------------------------------------------------------------------------

    async def start(self) -> None:
        """Open the session and declare the token, publishers and the queryable; then observe
        the backend and add ``zenoh`` to ``get_status``.

        Raises:
            ConfigurationError: ``eclipse-zenoh`` is missing (the message says what to
                install), the configuration is unusable, or the session cannot be opened
                (e.g. a listen endpoint is in use).
        """
        zenoh = import_zenoh()
        config = session_config(self.settings)
        log.debug("zenoh: %s", return_freed_memory_promptly())
        self._aio = asyncio.get_running_loop()
        try:
            # Opening connects and binds: not in the event loop's thread.
            self._session = await self._aio.run_in_executor(None, zenoh.open, config)
        except Exception as exc:  # zenoh's ZError: a bind or connect failure
            raise ConfigurationError(
                f"cannot open the Zenoh session: {exc}; check the endpoints (a port in use?)",
                "daemon.zenoh",
            ) from None
        session = self._session
        self._outbox = Outbox(OUTBOX_SIZE, OUTBOX_HARD_CAP, "zenoh")
        self._state_pub = session.declare_publisher(
            self.keys["state"], congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA)
        self._events_pub = session.declare_publisher(
            self.keys["events"], congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.DATA_HIGH)
        self._declared = [
            self._state_pub,
            self._events_pub,
            session.declare_queryable(self.keys["rpc"], self._on_query),
            # Last: clients that see the token find the rest declared.
            session.liveliness().declare_token(self.keys["liveliness"]),
        ]
        self._fault_task = self._aio.create_task(self._watch_fault())
        if self._add_observer is not None:
            self._add_observer(self)
        self._requests.status_sections["zenoh"] = self.stats
        log.info("zenoh: serving under %s (mode %s, listen %s, connect %s)", self.prefix,
                 self.settings.mode or "peer", list(self.settings.listen or ()) or "none",
                 list(self.settings.connect) or "none")

    async def close(self) -> None:
        """Withdraw the token, send what is waiting (the last results) and close the session
        (idempotent; errors while closing are logged)."""
        session, self._session = self._session, None
        if session is None:
            return
        if self._fault_task is not None:
            self._fault_task.cancel()
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        aio = asyncio.get_running_loop()
        outbox, self._outbox = self._outbox, None

        def finish() -> None:
            if outbox is not None:
                outbox.close(CLOSE_FLUSH_S)
            for entity in reversed(self._declared):
                try:
                    entity.undeclare()
                except Exception:
                    log.debug("zenoh: undeclare failed", exc_info=True)
            session.close()

        try:
            await aio.run_in_executor(None, finish)
        except Exception:
            log.exception("zenoh: closing the session failed")
        self._declared.clear()

    # -- observer (the backend calls it in the asyncio thread; it never blocks nor raises) ---

    def on_state(self, snapshot: dict[str, Any]) -> None:
        """Publish the socket's ``state`` event on ``<prefix>/state``."""
        outbox = self._outbox
        if outbox is None:
            return
        self._state_seq += 1
        message = {"event": "state", **snapshot, "dropped": self._dropped_since_state,
                   "dropped_total": outbox.dropped, "seq": self._state_seq}
        if outbox.offer(partial(self._put_state, message)):
            self._dropped_since_state = 0
        else:
            self._dropped_since_state += 1

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None:
        """Publish a goal's feedback (droppable) or result (never dropped) on ``events``."""
        outbox = self._outbox
        if outbox is None:
            return
        if isinstance(event, GoalResult):
            outbox.put(partial(self._put_event, result_event, event))
        elif not outbox.offer(partial(self._put_event, feedback_event, event,
                                      self._joint_names)):
            self._dropped_since_state += 1

    def on_command(self, traj: JointTrajectory, goal_id: int | None) -> None:
        """Publish an accepted command on ``events`` as the socket sends it to a subscriber
        with ``commands`` (``jtc-hw record --zenoh``); never dropped, as results."""
        outbox = self._outbox
        if outbox is None or not traj.points:  # (a stop is for the socket's subscribers)
            return
        outbox.put(partial(self._put_event, command_event, traj, goal_id,
                           self._requests.backend.now_ns()))

    def on_record(self, event: dict[str, Any]) -> None:
        """Nothing: results are on ``events`` already."""

    # -- in the outbox's thread ---------------------------------------------------------------

    def _put_state(self, message: dict[str, Any]) -> None:
        self._state_pub.put(encode(message))
        self.published += 1

    def _put_event(self, build: Callable[..., dict[str, Any]], *args: Any) -> None:
        self._events_pub.put(encode(build(*args)))
        self.published += 1

    def _reply(self, query: Any, data: bytes) -> None:
        try:
            # Our own key: the query's may have wildcards (jtc/**/rpc/get_status, a fleet's).
            op = str(query.key_expr).rsplit("/", 1)[-1]
            query.reply(f"{self.prefix}/rpc/{op}", data)
        finally:
            self._end(query)  # the querier's get ends with this (its last reply)

    # -- faults -------------------------------------------------------------------------------

    async def _watch_fault(self) -> None:
        while True:
            try:
                controller = self._status().get("controller") or {}
                fault = controller.get("fault")
            except Exception:
                log.debug("zenoh: no status", exc_info=True)
                fault = self._fault
            if fault != self._fault:
                self._fault = fault
                message = {"event": "fault", "fault": fault, "time_ns": time.monotonic_ns()}
                if self._outbox is not None:
                    self._outbox.put(partial(self._put_fault, message))
            await asyncio.sleep(FAULT_POLL_S)

    def _put_fault(self, message: dict[str, Any]) -> None:
        self._events_pub.put(encode(message))

    # -- queries ------------------------------------------------------------------------------

    def _on_query(self, query: Any) -> None:
        """Zenoh's thread: check the credential, hand the query to the event loop (or answer
        ``busy``)."""
        try:
            op = str(query.key_expr).rsplit("/", 1)[-1]
            if any(c in op for c in "*$"):
                # The query names no operation (``jtc/**``): not a request to this daemon.
                self._end(query)
                return
            token, header = split_attachment(query.attachment)
            if op in COMMANDS and not self._authorized(query, op, token):
                return
            with self._lock:
                busy = self._inflight >= MAX_QUERIES or self._aio is None
                if not busy:
                    self._inflight += 1
            if busy:
                self.busy += 1
                self._reply(query, encode(error_reply(
                    None, BUSY, f"the daemon is executing {MAX_QUERIES} Zenoh queries; "
                    "try again later")))
                return
            assert self._aio is not None
            self._aio.call_soon_threadsafe(self._start_query, query, op, self._body(query),
                                           header)
        except RuntimeError:  # the event loop is closed: the daemon is exiting
            with self._lock:
                self._inflight -= 1
            self._end(query)
        except Exception:
            log.exception("zenoh: cannot take a query")
            self._end(query)

    def _body(self, query: Any) -> bytes | RequestError:
        """The query's payload as bytes; ``too_large`` without copying it when it is longer
        than ``daemon.max_message_bytes`` (the socket's message, byte for byte)."""
        payload = query.payload
        if payload is None:
            return b""
        if len(payload) > self._max_bytes:
            return RequestError(TOO_LARGE, f"line 1: message longer than the limit of "
                                f"{self._max_bytes} bytes; it was discarded up to its newline")
        return bytes(payload.to_bytes())

    def _end(self, query: Any) -> None:
        """Drop ``query`` (its querier's ``get`` ends) and, if its payload was large, have
        the memory Zenoh held for it given back to the system (module docstring)."""
        payload = query.payload
        large = payload is not None and len(payload) >= RELEASE_AFTER_BYTES
        del payload
        query.drop()
        if large:
            self._release_soon()

    def _release_soon(self) -> None:
        """Release freed memory at each of :data:`RELEASE_AFTER_S` from now, in a worker
        thread (it walks the heap: milliseconds); a schedule under way covers every query
        ended before its first release. Any thread."""
        aio = self._aio
        with self._lock:
            if self._release_pending or aio is None:
                return
            self._release_pending = True
        with contextlib.suppress(RuntimeError):  # the event loop is closed: the daemon is exiting
            aio.call_soon_threadsafe(self._schedule_releases)

    def _schedule_releases(self) -> None:
        aio = asyncio.get_running_loop()
        for index, delay_s in enumerate(RELEASE_AFTER_S):
            aio.call_later(delay_s, self._release, index == 0)

    def _release(self, first: bool) -> None:
        if first:
            with self._lock:
                self._release_pending = False
        self.releases += 1
        asyncio.get_running_loop().run_in_executor(None, release_freed_memory)

    def _authorized(self, query: Any, op: str, given: bytes) -> bool:
        """Whether ``query`` carries the token (``given``, from its attachment); if not, its
        refusal is under way (module docstring). Zenoh's thread."""
        if self._token and given and hmac.compare_digest(given, self._token):
            return True
        what = "a wrong token" if given else "no token"
        with self._lock:
            self.unauthorized += 1
            self._refused[what] = count = self._refused.get(what, 0) + 1
            wait = bool(given) and self._refusals_waiting < MAX_REFUSALS_WAITING
            if wait:
                self._refusals_waiting += 1
        if count <= 3 or count % LOG_REFUSALS_EVERY == 0:
            log.warning("zenoh: refused rpc/%s with %s (%d so far)", op, what, count)
        message = (f"{op} needs the daemon's Zenoh token in the query's attachment "
                   f"({what} given); pass --zenoh-token-file FILE or set $JTC_HW_ZENOH_TOKEN "
                   "(Client.connect(..., token=...)); watching needs none")
        data = encode(error_reply(None, UNAUTHORIZED, message))
        aio = self._aio
        if not given or aio is None:
            self._send_reply(query, data)
        elif not wait:
            self._end(query)  # too many guesses waiting: no reply at all
        else:
            try:
                aio.call_soon_threadsafe(aio.call_later, WRONG_TOKEN_DELAY_S,
                                         self._refuse_late, query, data)
            except RuntimeError:  # the event loop is closed: the daemon is exiting
                with self._lock:
                    self._refusals_waiting -= 1
                self._end(query)
        return False

    def _refuse_late(self, query: Any, data: bytes) -> None:
        with self._lock:
            self._refusals_waiting -= 1
        try:
            self._send_reply(query, data)
        except Exception:  # the session closed meanwhile: the querier gets no reply
            log.debug("zenoh: cannot refuse a query", exc_info=True)

    def _send_reply(self, query: Any, data: bytes) -> None:
        """Reply through the outbox (never waiting on Zenoh), or drop the query."""
        outbox = self._outbox
        if outbox is None or not outbox.put(partial(self._reply, query, data)):
            self._end(query)

    def _start_query(
        self, query: Any, op: str, body: bytes | RequestError, header: bytes | None
    ) -> None:
        if self._session is None:  # closing
            self._end(query)
            with self._lock:
                self._inflight -= 1
            return
        task = asyncio.get_running_loop().create_task(self._execute(query, op, body, header))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _execute(
        self, query: Any, op: str, body: bytes | RequestError, header: bytes | None = None
    ) -> None:
        self._queries += 1
        caller = Caller(self._queries, f"zenoh query {self._queries} (zenoh)", DISCARD)
        try:
            item: Request | RequestError
            if isinstance(body, RequestError):
                item = body
            elif len(body) >= DECODE_IN_WORKER_BYTES:
                item = await asyncio.get_running_loop().run_in_executor(
                    None, self.decode, op, body, self._max_bytes, header)
            else:
                item = self.decode(op, body, self._max_bytes, header)
            del body
            data = (await self._requests.answer(caller, item)).data
            if self._outbox is None or not self._outbox.put(partial(self._reply, query, data)):
                self._end(query)
        except asyncio.CancelledError:
            self._end(query)
            raise
        except Exception:  # answer never raises; Zenoh's drop might
            log.exception("zenoh: query %d failed", caller.number)
        finally:
            with self._lock:
                self._inflight -= 1

    @staticmethod
    def decode(
        op: str, body: bytes, max_message_bytes: int, header: bytes | None = None
    ) -> Request | RequestError:
        """A query's request: the body read as a socket message (the same errors), with the key
        expression's ``op``; with a binary frame's ``header`` (the request line, from the
        query's attachment: :func:`split_attachment`), the body is the frame's raw bytes.
        Never raises: every problem is returned as a value."""
        if header is not None:
            if not header.strip():
                return RequestError(BAD_FRAME, "the query's attachment ends with a newline "
                                    "but holds no request line after the token")
            frames = MessageDecoder(max_message_bytes)
            # A payload shorter than the header says leaves the frame waiting: end() names it.
            items = frames.feed(header + b"\n" + body + b"\n") or frames.end()
            obj: dict[str, Any] | RequestError = items[0] if items else {}
        elif not body.strip():
            obj = {}
        else:
            # One message: JSON allows a newline wherever it allows a space (and nowhere
            # else), so the body is one NDJSON line once its newlines are spaces.
            items = MessageDecoder(max_message_bytes).feed(
                body.replace(b"\r", b" ").replace(b"\n", b" ") + b"\n")
            obj = items[0] if items else {}
        if isinstance(obj, RequestError):
            return obj
        rid = obj.get("id") if isinstance(obj.get("id"), (int, str)) else None
        if "op" in obj and obj["op"] != op:
            return RequestError(
                BAD_REQUEST,
                f"op: the body says {obj['op']!r}, the key expression rpc/{op}; leave op out "
                "of the body",
                rid,
            )
        if op in NOT_OVER_ZENOH:
            return RequestError(BAD_REQUEST, f"{op} is not served over Zenoh: "
                                f"{NOT_OVER_ZENOH[op]}", rid)
        try:
            return parse_request({**obj, "op": op})
        except RequestError as exc:
            return exc

    def stats(self) -> dict[str, Any]:
        """Counters for logs and tests."""
        outbox = self._outbox
        return {
            "prefix": self.prefix,
            "queries": self._queries,
            "busy": self.busy,
            "unauthorized": self.unauthorized,
            "releases": self.releases,
            "published": self.published,
            "dropped": 0 if outbox is None else outbox.dropped,
            "lost": 0 if outbox is None else outbox.lost,
        }
