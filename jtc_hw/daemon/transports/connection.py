"""One client connection of the socket server (:class:`Connection`), the peer's identity, and
the slots beyond a transport's limit. The queue's bounds are the daemon's settings
(``client_queue_size``, ``client_queue_hard_cap``).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import os
import socket
import struct
from typing import Any

from ..core.requests import Caller
from ..settings import DaemonSettings

__all__ = [
    "OVER_LIMIT_CLIENTS",
    "OVER_LIMIT_DEADLINE_S",
    "RESERVED_UNIX_CLIENTS",
    "Connection",
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


class Connection:
    """One client: its streams, bounded outgoing queue (droppable ``state`` / ``feedback``,
    never-dropped replies and results up to a hard cap), deadlines and counters; the ``Outlet``
    of its ``caller`` (the request layer's record of it: subscription, goals, drop counters)."""

    def __init__(
        self,
        number: int,
        kind: str,
        peer: str,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        settings: DaemonSettings,
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
        """Queue a message that must not be dropped; False if it cannot be sent (a client whose
        queue reaches the hard cap is disconnected here)."""
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
    """A label for the log; on the unix socket, the peer's uid (``SO_PEERCRED``: the kernel's
    record of who connected, which the peer cannot forge); on TCP, its address. Never raises: an
    unknown peer is labelled by its transport, its uid ``None``."""
    sock = writer.get_extra_info("socket")
    if kind == "tcp":
        address = writer.get_extra_info("peername")
        if not address:
            return "tcp", None, ""
        return f"tcp {address[0]}:{address[1]}", None, str(address[0])
    peercred = getattr(socket, "SO_PEERCRED", None)
    if sock is not None and peercred is not None:
        with contextlib.suppress(OSError):
            pid, uid, _gid = struct.unpack(
                "3i", sock.getsockopt(socket.SOL_SOCKET, peercred, struct.calcsize("3i"))
            )
            return f"unix pid {pid} uid {uid}", uid, ""
    return "unix", None, ""


def is_privileged(uid: int | None) -> bool:
    """The daemon's own user or root (may use the reserved unix slots)."""
    return uid is not None and (uid == 0 or uid == os.geteuid())
