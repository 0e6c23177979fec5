"""The Python client over Zenoh: ``Client.connect("zenoh:<prefix>")`` (docs/zenoh.md).

Theory of operation
-------------------
:class:`ZenohClient` is a :class:`~jtc_hw.api.client.Client` whose transport is a Zenoh
session instead of a socket; every public method is the socket client's. A request is a Zenoh
query on ``<prefix>/rpc/<op>`` with the socket's request body as payload, waited for in the
caller's thread (Zenoh's ``get`` with the request's timeout); its reply is the socket's reply.
With a ``token``, every query carries it as its attachment (the daemon requires it for
commands, ``jtc_hw.daemon.transports.zenoh_iface``); without one, commands come back
``unauthorized``. A large trajectory goes as a binary frame, as on the socket: the raw bytes
are the payload, the attachment the token, a newline and the request line.

Events come from two subscribers declared at connection, called in Zenoh's threads:
``<prefix>/events`` (goal feedback and results, for every goal of the daemon: those of this
client's goals go to their ``GoalHandle``) and, while a ``StateSubscription`` is open,
``<prefix>/state``. A goal's first events may arrive before the query's ``accepted`` reply:
while a ``send_goal`` is in flight, events of unknown goals are held (bounded) and given to
the handle as soon as it exists, in order, before any later event (one lock orders both).

The daemon's liveliness token on ``<prefix>`` stands for the connection: the client checks it
at connection (no token: no daemon there) and watches it; when it is withdrawn (the daemon
stopped, was killed, or its session timed out) every waiting request, goal and subscription
gets a ``ClientConnectionError``, as when a socket closes.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import re
import threading
import time
from collections.abc import Mapping
from typing import Any, Final

from ..errors import ProtocolError
from .calls import ClientConnectionError, Pending
from .client import OPENERS, Client, Frame
from .framing import PROTOCOL_VERSION, encode, encode_frame

__all__ = [
    "DEFAULT_ZENOH_CONNECT",
    "ZENOH_SCHEME",
    "ZenohClient",
    "ZenohConfigLike",
    "client_config",
    "open_session",
]

log = logging.getLogger("jtc_hw.client")

ZENOH_SCHEME: Final = "zenoh:"
DEFAULT_ZENOH_CONNECT: Final = "tcp/127.0.0.1:7447"
"""Where a client connects without a configuration: a Zenoh router (or a daemon listening on
Zenoh's default port) on this machine."""
EARLY_GOALS: Final = 64
EARLY_EVENTS: Final = 256
INSTALL_HINT: Final = "pip install 'jtc_hw[zenoh]'"
_UNREADABLE: Final = object()

ZenohConfigLike = str | os.PathLike[str] | Mapping[str, Any] | Any
"""A Zenoh configuration file (JSON5), a mapping of configuration keys to values
(``{"connect/endpoints": ["tcp/10.0.0.2:7447"]}``), or a ``zenoh.Config``."""


def _zenoh() -> Any:
    try:
        import zenoh
    except ImportError:
        raise ClientConnectionError(
            f"Zenoh needs the eclipse-zenoh package: {INSTALL_HINT}") from None
    return zenoh


def client_config(zenoh_config: ZenohConfigLike | None = None) -> Any:
    """The ``zenoh.Config`` of a client session: peer mode, listening nowhere, multicast
    scouting off (unless the configuration sets them), connecting to
    :data:`DEFAULT_ZENOH_CONNECT` when nothing says where.

    Raises:
        ClientConnectionError: eclipse-zenoh is missing.
        ValueError: the configuration cannot be read (the message says why).
    """
    zenoh = _zenoh()
    default = zenoh.Config()
    if zenoh_config is None:
        config = zenoh.Config()
    elif isinstance(zenoh_config, zenoh.Config):
        config = zenoh_config
    elif isinstance(zenoh_config, Mapping):
        config = zenoh.Config()
        for key, value in zenoh_config.items():
            try:
                config.insert_json5(str(key), json.dumps(value))
            except Exception as exc:
                raise ValueError(f"zenoh configuration key {key!r}: {exc}") from None
    else:
        try:
            config = zenoh.Config.from_file(os.fspath(zenoh_config))
        except Exception as exc:
            # zenoh's message ends with the Rust source line it came from: not for users.
            reason = re.sub(r"\s+at \S+\.rs:\d+\.?$", "", " ".join(str(exc).split()))
            raise ValueError(f"{os.fspath(zenoh_config)}: not a Zenoh configuration: {reason}"
                             ) from None

    def get(key: str, of: Any = config) -> Any:
        return json.loads(of.get_json(key))

    if get("mode") is None:
        config.insert_json5("mode", '"peer"')
    if get("listen/endpoints") == get("listen/endpoints", default):
        config.insert_json5("listen/endpoints", "[]")  # not every interface (Zenoh's default)
    if get("scouting/multicast/enabled") is None:
        config.insert_json5("scouting/multicast/enabled", "false")
    if not get("connect/endpoints") and not get("scouting/multicast/enabled") and not get(
            "listen/endpoints"):
        config.insert_json5("connect/endpoints", json.dumps([DEFAULT_ZENOH_CONNECT]))
    return config


def open_session(zenoh_config: ZenohConfigLike | None = None) -> Any:
    """A Zenoh session for clients (:func:`client_config`).

    Raises:
        ClientConnectionError: eclipse-zenoh is missing, or the session cannot be opened.
        ValueError: the configuration cannot be read.
    """
    zenoh = _zenoh()
    config = client_config(zenoh_config)
    try:
        session = zenoh.open(config)
    except Exception as exc:
        raise ClientConnectionError(f"cannot open a Zenoh session: {exc}") from None
    endpoints = json.loads(config.get_json("connect/endpoints")) or []
    _wait_connected(session, len(endpoints), CONNECT_WAIT_S)
    return session


CONNECT_WAIT_S: Final = 1.0
"""How long a new client session waits for its connect endpoints' links (open returns while
some are still being set up; a query sent then would not reach their daemons)."""


def _wait_connected(session: Any, expected: int, timeout_s: float) -> None:
    """Until the session has ``expected`` peers or routers, or ``timeout_s`` has passed (an
    endpoint that is down: the caller's own check, e.g. the liveliness token, says so)."""
    deadline = time.monotonic() + timeout_s
    while True:
        info = session.info
        linked = len(info.peers_zid()) + len(info.routers_zid())
        if linked >= expected or time.monotonic() >= deadline:
            return
        time.sleep(0.01)  # Zenoh's Python API has no wait for a link: polled, bounded


class ZenohClient(Client):
    """A :class:`Client` over Zenoh (module docstring); create it with ``Client.connect(
    "zenoh:<prefix>", zenoh_config=...)`` or :meth:`open`.

    Attributes:
        prefix: the daemon's key prefix.
        info: the ``hello`` reply received at connection.
    """

    def __init__(self, session: Any, prefix: str, timeout_s: float, own_session: bool,
                 token: str | None = None) -> None:
        # Not Client.__init__: no socket and no reader thread; the same state otherwise.
        self._init_state(timeout_s, f"{ZENOH_SCHEME}{prefix}")
        self.prefix = prefix
        self._events_lock = threading.RLock()  # orders event delivery (module docstring)
        self._early: collections.OrderedDict[int, list[dict[str, Any]]] = (
            collections.OrderedDict())
        self._sending_goals = 0
        self._session = session
        self._own_session = own_session
        self._attachment = token.encode() if token else None
        self._state_sub: Any = None
        self._events_sub = session.declare_subscriber(f"{prefix}/events", self._on_event)
        self._alive_sub = session.liveliness().declare_subscriber(prefix, self._on_liveliness)

    @classmethod
    def open(
        cls,
        prefix: str,
        *,
        zenoh_config: ZenohConfigLike | None = None,
        session: Any = None,
        timeout_s: float = 5.0,
        hello: bool = True,
        token: str | None = None,
    ) -> ZenohClient:
        """Connect to the daemon at ``prefix`` and say ``hello``.

        Args:
            prefix: the daemon's key prefix (``jtc/<host>/<controller>``).
            zenoh_config: see :data:`ZenohConfigLike` (not with ``session``).
            session: an open Zenoh session to share (it stays open on ``close``).
            timeout_s: for finding the daemon and the default for every request.
            hello: fill ``info`` with the ``hello`` reply (the request is always made: see
                below).
            token: the daemon's ``daemon.zenoh.token``, sent with every query; without it
                the client may watch (state, status) but commands are ``unauthorized``.

        Raises:
            ClientConnectionError: eclipse-zenoh is missing, the session cannot be opened,
                or no daemon's liveliness token is at ``prefix`` within ``timeout_s``.
            ValueError: a prefix with wildcards, or an unreadable configuration.
            RequestError: the daemon refused the ``hello``.
            TimeoutError: no reply to ``hello`` within ``timeout_s``.
        """
        if not prefix or any(c in prefix for c in "*$?#") or prefix.strip("/") != prefix:
            raise ValueError(
                f"{prefix!r} is not a daemon's prefix: a key expression without wildcards, "
                "e.g. zenoh:jtc/lab/arm1 (jtc-hw fleet lists them)")
        own = session is None
        if own:
            session = open_session(zenoh_config)
        try:
            client = cls(session, prefix, timeout_s, own, token)
        except BaseException:
            if own:
                session.close()
            raise
        try:
            if not client._daemon_alive(timeout_s):
                raise ClientConnectionError(
                    f"no jtc-hw daemon at {client.label}: no liveliness token within "
                    f"{timeout_s:g} s. Is it running with daemon.zenoh.prefix {prefix}, and "
                    "does the Zenoh configuration reach it (connect endpoints, router)? "
                    "'jtc-hw fleet' lists the daemons this session sees")
            # Always a round trip: the daemon has this session's subscriptions (declared on
            # the same link before the query) once it answers, so no event of a goal sent
            # next can miss them. ``hello=False`` only leaves ``info`` empty.
            info = client._request("hello", {"protocol_version": PROTOCOL_VERSION}, timeout_s)
            if hello:
                client.info = info
        except BaseException:
            client.close()
            raise
        return client

    def _daemon_alive(self, timeout_s: float) -> bool:
        replies = self._session.liveliness().get(self.prefix, timeout=timeout_s)
        return any(reply.ok is not None for reply in replies)

    # -- transport ----------------------------------------------------------------------------

    def _request(
        self,
        op: str,
        fields: dict[str, Any],
        timeout_s: float | None,
        pending: Pending | None = None,
        frame: Frame | None = None,
    ) -> dict[str, Any]:
        timeout = self.timeout_s if timeout_s is None else timeout_s
        pending = pending or Pending(op, None, 0)
        request_id = next(self._ids)
        if op in ("subscribe_state", "unsubscribe_state"):
            return self._subscribe(request_id, op == "subscribe_state")
        with self._lock:
            self._check_open(op)
            if op == "send_goal":
                self._sending_goals += 1
        try:
            request = {"id": request_id, "op": op, **fields}
            if frame is None:
                body, attachment = encode(request), self._attachment
            else:
                # docs/protocol.md, "Binary frames": the raw bytes as the payload, the token,
                # a newline and the request line in the attachment.
                line, _, raw = encode_frame(request, *frame).partition(b"\n")
                body, attachment = raw[:-1], (self._attachment or b"") + b"\n" + line + b"\n"
            message = self._query(op, body, timeout, attachment)
            with self._events_lock:
                self._deliver(request_id, message, pending)
        finally:
            if op == "send_goal":
                with self._lock:
                    self._sending_goals -= 1
                    if not self._sending_goals:
                        self._early.clear()
        if pending.error is not None:
            raise pending.error
        assert pending.reply is not None
        return pending.reply

    def _query(
        self, op: str, body: bytes, timeout: float, attachment: bytes | None = None
    ) -> dict[str, Any]:
        try:
            replies = self._session.get(f"{self.prefix}/rpc/{op}", payload=body,
                                        attachment=attachment, timeout=timeout)
            for reply in replies:
                sample = reply.ok if reply.ok is not None else reply.err
                if sample is None:
                    continue
                data = sample.payload.to_bytes()
                try:
                    message = json.loads(data)
                except ValueError:
                    raise ProtocolError(f"{self.label} sent an unreadable reply to {op!r}: "
                                        f"{data[:200]!r}") from None
                if isinstance(message, dict):
                    return message
        except ProtocolError:
            raise
        except Exception as exc:  # zenoh's ZError: the session is closed
            with self._lock:
                lost = self._lost
            raise lost or ClientConnectionError(f"{op}: {self.label}: {exc}") from None
        with self._lock:
            lost = self._lost
        if lost is not None:
            raise lost
        raise TimeoutError(f"no reply to {op!r} from {self.label} within {timeout} s")

    def _deliver(self, request_id: int, message: dict[str, Any], pending: Pending) -> None:
        """The reply to its request (creating the goal's handle), then the goal's held events;
        with ``_events_lock`` held."""
        if message.get("id") != request_id:
            message = {**message, "id": request_id}  # e.g. "busy", sent before decoding
        with self._lock:
            self._pending[request_id] = pending
        self._dispatch(message)
        goal = pending.goal
        if goal is None:
            return
        with self._lock:
            held = self._early.pop(goal.goal_id, [])
        for event in held:
            self._dispatch_event(str(event["event"]), event)

    def _subscribe(self, request_id: int, on: bool) -> dict[str, Any]:
        with self._lock:
            if self._lost is not None:
                raise self._lost
            if self._closing:
                return {"id": request_id, "ok": True, "subscribed": False}
            if on and self._state_sub is None:
                self._state_sub = self._session.declare_subscriber(
                    f"{self.prefix}/state", self._on_state)
            elif not on and self._state_sub is not None:
                sub, self._state_sub = self._state_sub, None
                sub.undeclare()
        return {"id": request_id, "ok": True, "subscribed": on}

    # -- Zenoh's threads ----------------------------------------------------------------------

    def _decode(self, sample: Any, what: str) -> Any:
        """The sample's JSON payload; ``_UNREADABLE`` (logged) if it is not JSON."""
        try:
            return json.loads(sample.payload.to_bytes())
        except ValueError:
            log.warning("%s: unreadable %s; skipped", self.label, what)
            return _UNREADABLE

    def _on_state(self, sample: Any) -> None:
        message = self._decode(sample, "state message")
        if message is not _UNREADABLE:
            self._dispatch_event("state", message)

    def _on_event(self, sample: Any) -> None:
        message = self._decode(sample, "event")
        if not isinstance(message, dict):
            return
        event, goal_id = message.get("event"), message.get("goal_id")
        if event == "command":  # to subscriptions opened with commands=True, as on the socket
            self._dispatch_event("command", message)
            return
        if event not in ("feedback", "result") or not isinstance(goal_id, int):
            return  # fault events: for monitors (jtc-hw fleet)
        with self._events_lock:
            with self._lock:
                if goal_id not in self._goals:
                    if self._sending_goals:
                        self._hold(goal_id, message)
                    return
            self._dispatch_event(event, message)

    def _hold(self, goal_id: int, message: dict[str, Any]) -> None:
        events = self._early.get(goal_id)
        if events is None:
            if len(self._early) >= EARLY_GOALS:
                self._early.popitem(last=False)
            events = self._early[goal_id] = []
        if message["event"] == "result" or len(events) < EARLY_EVENTS:
            events.append(message)

    def _on_liveliness(self, sample: Any) -> None:
        if str(sample.kind).endswith("DELETE"):
            self._fail_all(ClientConnectionError(
                f"{self.label}: the daemon went away (its Zenoh liveliness token was "
                "withdrawn: it stopped, died, or its session timed out)"))

    # -- lifecycle ----------------------------------------------------------------------------

    def close(self) -> None:
        """Undeclare the subscribers and close the session (if it is this client's own).
        Idempotent. A goal still running goes on in the daemon.
        """
        with self._lock:
            if self._closing:
                return
            self._closing = True
            subs = [s for s in (self._state_sub, self._events_sub, self._alive_sub) if s]
            self._state_sub = None
        for sub in subs:
            try:
                sub.undeclare()
            except Exception:
                log.debug("undeclare failed", exc_info=True)
        if self._own_session:
            try:
                self._session.close()
            except Exception:
                log.debug("closing the session failed", exc_info=True)
        with self._lock:
            lost = self._lost
        if lost is None:
            self._fail_all(ClientConnectionError(f"{self.label}: the client was closed"))


OPENERS[ZENOH_SCHEME] = ZenohClient.open  # Client.connect("zenoh:<prefix>")
