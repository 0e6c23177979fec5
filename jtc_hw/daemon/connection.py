"""One client connection of the socket server, and the settings that bound them all.

:class:`ServerSettings` is where and how the server listens (the robot file's ``daemon``
fields); :class:`Connection` is one client: its streams, its bounded outgoing queue (droppable
``state`` / ``feedback``, never-dropped replies and results up to a hard cap), its deadlines
(authentication, idleness) and its counters. It is the request layer's ``Outlet`` for its
client, whose ``Caller`` (subscription, goals, drop counters) it holds.
"""

from __future__ import annotations

import asyncio
import collections
import ipaddress
import os
import socket
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

from ..api.framing import DEFAULT_MAX_MESSAGE_BYTES
from ..errors import (
    ConfigurationError,
)
from .requests import Caller

__all__ = [
    "OVER_LIMIT_CLIENTS",
    "OVER_LIMIT_DEADLINE_S",
    "RESERVED_UNIX_CLIENTS",
    "Connection",
    "ServerSettings",
    "TcpEndpoint",
    "is_privileged",
    "peer_identity",
]

RESERVED_UNIX_CLIENTS = 2
"""Unix connections allowed beyond ``max_clients`` to peers whose uid (``SO_PEERCRED``) is the
daemon's or root's: the operator gets in when other users' clients hold every slot."""
OVER_LIMIT_CLIENTS = 4
"""Connections over a transport's limit that are each given ``OVER_LIMIT_DEADLINE_S`` to send a
``stop`` (per transport); more are refused at once."""
OVER_LIMIT_DEADLINE_S = 2.0
"""How long a connection over the limit may take to send its ``stop`` (and, on TCP, its ``auth``
first) before it gets ``busy``."""


@dataclass(frozen=True)
class TcpEndpoint:
    """The optional loopback TCP endpoint (the robot file's ``daemon.tcp``).

    Attributes:
        host: a loopback address (``127.0.0.1``, ``::1`` or ``localhost``).
        port: TCP port (0: any free port, see ``Server.tcp_address``).
        token: every TCP client must first send ``{"op": "auth", "token": ...}`` with it.
        max_clients: simultaneous authenticated TCP connections (the unix socket has its own
            limit); more get ``busy`` unless their request, after ``auth``, is ``stop``.
        max_unauthenticated: connections that may wait to authenticate at once, apart from
            ``max_clients``; a newcomer beyond it takes the place of the one waiting longest
            (``jtc_hw.daemon.tcp_door``).
        auth_timeout_s: how long a connection may take, from its opening, to authenticate
            (sending bytes without completing a request does not extend it).
        auth_failure_delay_s: failed authentications are answered at most one per this long
            per peer address, each at least this long after it came.
    """

    host: str = "127.0.0.1"
    port: int = 0
    token: str = field(default="", repr=False)
    max_clients: int = 8
    max_unauthenticated: int = 16
    auth_timeout_s: float = 1.0
    auth_failure_delay_s: float = 0.5


@dataclass(frozen=True)
class ServerSettings:
    """Where and how the server listens (field names as in the robot file's ``daemon``).

    Attributes:
        socket: the unix socket file (``None``: TCP only); its parent directory is created if
            missing.
        socket_mode: permission bits of the socket file (who may connect).
        socket_group: group (name or gid) given the socket file and a directory made for
            it; ``None``: the daemon's own.
        tcp: the optional loopback TCP endpoint (with its own ``max_clients``).
        max_clients: simultaneous unix socket connections; ``RESERVED_UNIX_CLIENTS`` more are
            allowed to the daemon's user and root. More get ``busy``, unless their request is
            ``stop``.
        max_message_bytes: longest request line accepted.
        client_queue_size: queued outgoing messages per client above which ``state`` and
            ``feedback`` events are dropped for that client.
        client_queue_hard_cap: queued messages at which a client is disconnected as too slow.
        close_timeout_s: how long a closing connection may take to read its last messages.
        idle_timeout_s: a connection without a request for this long, with no subscription
            and no goal running, is closed (``idle``); 0: never.
    """

    socket: str | os.PathLike[str] | None = None
    socket_mode: int = 0o660
    socket_group: str | int | None = None
    tcp: TcpEndpoint | None = None
    max_clients: int = 16
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    client_queue_size: int = 256
    client_queue_hard_cap: int = 4096
    close_timeout_s: float = 1.0
    idle_timeout_s: float = 300.0

    @classmethod
    def coerce(cls, settings: object) -> ServerSettings:
        """Settings from a ``ServerSettings``, a mapping of its fields, or any object with
        attributes of those names, such as ``RobotConfig.daemon`` (missing ones take the
        defaults; other attributes are ignored). ``tcp`` may likewise be a mapping or an
        object with ``host``, ``port`` and ``token``.

        Raises:
            ConfigurationError: an unknown key in a mapping, or invalid values (see ``check``).
        """
        if isinstance(settings, ServerSettings):
            out = settings
        else:
            names = [f.name for f in fields(cls)]
            values = _pick(settings, names, "")
            tcp = values.get("tcp")
            if tcp is not None and not isinstance(tcp, TcpEndpoint):
                values["tcp"] = TcpEndpoint(**_pick(tcp, _TCP_FIELDS, "tcp."))
            out = cls(**values)
        out.check()
        return out

    def check(self) -> None:
        """Validate the values.

        Raises:
            ConfigurationError: no endpoint, a non-loopback TCP host, TCP without a token,
                or a value out of range; names the setting.
        """
        if self.socket is None and self.tcp is None:
            raise ConfigurationError("no endpoint: set socket and/or tcp")
        mode = self.socket_mode
        if isinstance(mode, bool) or not isinstance(mode, int) or not 0 <= mode <= 0o777:
            raise ConfigurationError("expected permission bits 0..0o777", "socket_mode", mode)
        if self.tcp is not None:
            _check_loopback(self.tcp.host)
            if not isinstance(self.tcp.token, str) or not self.tcp.token:
                raise ConfigurationError(
                    "TCP needs a token: clients authenticate with it in their first request",
                    "tcp.token",
                )
            port = self.tcp.port
            if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
                raise ConfigurationError("expected a port 0..65535", "tcp.port", port)
            for name in ("max_clients", "max_unauthenticated"):
                limit = getattr(self.tcp, name)
                if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
                    raise ConfigurationError("expected an integer >= 1", f"tcp.{name}", limit)
            for name in ("auth_timeout_s", "auth_failure_delay_s"):
                value = getattr(self.tcp, name)
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                    value > 0 or (value == 0 and name == "auth_failure_delay_s")
                ):
                    raise ConfigurationError("expected seconds > 0", f"tcp.{name}", value)
        for name in ("max_clients", "max_message_bytes", "client_queue_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigurationError("expected an integer >= 1", name, value)
        if self.client_queue_hard_cap < self.client_queue_size:
            raise ConfigurationError(
                f"must be >= client_queue_size ({self.client_queue_size})",
                "client_queue_hard_cap",
                self.client_queue_hard_cap,
            )
        for name in ("close_timeout_s", "idle_timeout_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigurationError("expected a number of seconds", name, value)
            if not (value > 0 or (value == 0 and name == "idle_timeout_s")):
                what = "seconds >= 0 (0: never)" if name == "idle_timeout_s" else "seconds > 0"
                raise ConfigurationError(f"expected {what}", name, value)


_TCP_FIELDS = [f.name for f in fields(TcpEndpoint)]


def _pick(source: object, names: Sequence[str], prefix: str) -> dict[str, Any]:
    if isinstance(source, Mapping):
        for key in source:
            if key not in names:
                raise ConfigurationError(
                    f"unknown server setting (known: {', '.join(names)})", f"{prefix}{key}"
                )
        return {k: source[k] for k in names if k in source}
    return {k: getattr(source, k) for k in names if hasattr(source, k)}


def _check_loopback(host: str) -> None:
    if host == "localhost":
        return
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        raise ConfigurationError(
            "expected a loopback IP address such as 127.0.0.1 or ::1 (or 'localhost')",
            "tcp.host",
            host,
        ) from None
    if not address.is_loopback:
        raise ConfigurationError(
            f"{host} is not a loopback address; the TCP endpoint is for local tools only "
            "(reach it from elsewhere through an SSH tunnel)",
            "tcp.host",
            host,
        )


class Connection:
    """One client: its streams, outgoing queue and deadlines; the ``Outlet`` of its
    ``caller`` (the request layer's record of it: subscription, goals, drop counters)."""

    def __init__(
        self,
        number: int,
        kind: str,
        peer: str,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        settings: ServerSettings,
        uid: int | None = None,
        now: float = 0.0,
        host: str = "",
    ) -> None:
        self.number = number
        self.kind = kind
        self.peer = peer
        self.uid = uid
        self.host = host  # TCP: the peer's address (failed authentications are slowed per host)
        self.opened = now
        self.reserved = False  # admitted to one of the slots reserved for the daemon's user
        self.stop_only = False  # authenticated over tcp.max_clients: one stop, then closed
        auth_s = settings.tcp.auth_timeout_s if settings.tcp is not None else 0.0
        self.auth_deadline = now + auth_s  # on TCP; after auth over the limit: the stop's
        self.last_activity = now  # the last request (see ``activity``)
        self.reader = reader
        self.writer = writer
        self.queue: collections.deque[bytes] = collections.deque()
        self.queue_size = settings.client_queue_size
        self.hard_cap = settings.client_queue_hard_cap
        self.wake = asyncio.Event()
        self.authenticated = kind == "unix"
        self.closing = False  # reading stopped: flush the queue, then close
        self.gone = False  # the transport is closed: nothing can be sent any more
        self.close_reason = "closed by the client"
        self.requests = 0
        self.too_slow = False
        self.caller = Caller(number, self.label, self)

    @property
    def label(self) -> str:
        return f"client {self.number} ({self.peer})"

    @property
    def activity(self) -> float:
        """When it was last active: its last request, or the end of its last goal."""
        return max(self.last_activity, self.caller.goals_ended_at)

    def send(self, data: bytes) -> bool:
        """Queue a message that must not be dropped; False if it cannot be sent.

        A client whose queue reaches the hard cap is disconnected here.
        """
        if self.gone:
            return False
        if len(self.queue) >= self.hard_cap:
            self.too_slow = True
            self.abort(
                f"not reading: {len(self.queue)} messages queued (client_queue_hard_cap); "
                "disconnected"
            )
            return False
        self.queue.append(data)
        self.wake.set()
        return True

    def offer(self, data: bytes) -> bool:
        """Queue a droppable message (state, feedback) unless the queue is full."""
        if self.gone or len(self.queue) >= self.queue_size:
            return False
        self.queue.append(data)
        self.wake.set()
        return True

    def abort(self, reason: str) -> None:
        """Close at once, dropping whatever is queued."""
        if not self.gone:
            self.gone = True
            self.close_reason = reason
            self.queue.clear()
            self.writer.transport.abort()
        self.closing = True
        self.wake.set()

    def stats(self) -> dict[str, Any]:
        caller = self.caller
        return {
            "client": self.number,
            "transport": self.kind,
            "peer": self.peer,
            "authenticated": self.authenticated,
            "reserved_slot": self.reserved,
            "subscribed": caller.subscribed,
            "requests": self.requests,
            "queued": len(self.queue),
            "dropped_state": caller.dropped_state,
            "dropped_feedback": caller.dropped_feedback,
            "goals": sorted(caller.goals),
        }


def peer_identity(kind: str, writer: asyncio.StreamWriter) -> tuple[str, int | None, str]:
    """A label for the log; on the unix socket, the peer's uid (``SO_PEERCRED``: the
    kernel's record of who connected, which the peer cannot forge); on TCP, its address.

    Raises:
        Nothing: an unknown peer is labelled by its transport, its uid ``None``.
    """
    sock = writer.get_extra_info("socket")
    if kind == "tcp":
        address = writer.get_extra_info("peername")
        if not address:
            return "tcp", None, ""
        return f"tcp {address[0]}:{address[1]}", None, str(address[0])
    peercred = getattr(socket, "SO_PEERCRED", None)
    if sock is not None and peercred is not None:
        try:
            pid, uid, _gid = struct.unpack(
                "3i", sock.getsockopt(socket.SOL_SOCKET, peercred, struct.calcsize("3i"))
            )
            return f"unix pid {pid} uid {uid}", uid, ""
        except OSError:
            pass
    return "unix", None, ""


def is_privileged(uid: int | None) -> bool:
    """The daemon's own user or root (may use the reserved unix slots).

    Raises:
        Nothing.
    """
    return uid is not None and (uid == 0 or uid == os.geteuid())
