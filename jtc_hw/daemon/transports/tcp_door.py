"""The TCP endpoint's door: who may wait to authenticate, and how fast a wrong token is answered.

Theory of operation
-------------------
Loopback is open to every local user, so a TCP client's first request must be ``auth`` with the
token; this module keeps the room where connections wait to do so, the server
(``jtc_hw.daemon.transports.server``) runs the handshake. Only a token holder reaches the
second room, so strangers can fill the first one only (docs/protocol.md, "A stop always gets
through")::

    connect --> [ handshake: at most max_unauthenticated waiting ] --auth--> [ max_clients ]
                  | full: the oldest waiting connection (open for at
                  |       least HANDSHAKE_GRACE_S) is dropped for the newcomer;
                  |       nobody is refused at the door
                  | failed handshake: answered after the peer's delay, then closed
                  | no auth within auth_timeout_s: closed

The newcomer always gets its chance: when ``max_unauthenticated`` connections wait, the one
waiting longest goes (it had the most time to authenticate), never one younger than
``HANDSHAKE_GRACE_S`` (up to ``HANDSHAKE_HARD_CAP``). A client with the token sends ``auth`` as
it connects, so it is read before it can become the oldest: however many strangers connect,
the operator's ``stop`` gets in. A newcomer is never refused: refusing would let a flood keep
the operator out for as long as it lasts, whereas dropping the oldest only shortens the
strangers' wait.

**Wrong tokens are slowed per peer** (its IP address): a failed handshake (a wrong token, or a
first request that is not ``auth``) is answered ``tcp.auth_failure_delay_s`` after the previous
one of the same address, however many connections it opens, and then closed. The right token
is never delayed (an operator on the same address as a guesser is not slowed). The first
failure of an address is logged, then one line per ``FAILURE_LOG_EVERY_S``.

No I/O and no clock: the server passes the time and closes what this module names.
"""

from __future__ import annotations

import collections
import logging
from dataclasses import dataclass
from typing import Any, Protocol

__all__ = [
    "FAILURE_LOG_EVERY_S",
    "HANDSHAKE_GRACE_S",
    "HANDSHAKE_HARD_CAP",
    "TcpDoor",
]

log = logging.getLogger("jtc_hw.server")

HANDSHAKE_GRACE_S = 0.25
"""A waiting connection younger than this is never dropped to make room: its ``auth``, sent as
it connected, is read first."""
HANDSHAKE_HARD_CAP = 4
"""The handshake room grows past ``max_unauthenticated`` (only with connections younger than
``HANDSHAKE_GRACE_S``) up to this many times it; there the oldest goes, however young."""
FAILURE_LOG_EVERY_S = 10.0
"""Failed handshakes of one address are logged at most once per this many seconds."""
_PEERS_KEPT = 256
"""Addresses whose failures are remembered; past it, those whose delay has run out go."""


class Waiting(Protocol):
    """What the door needs to know of a connection (``Connection`` has it)."""

    number: int
    opened: float


@dataclass
class _Failures:
    """One address's failed handshakes."""

    answer_at: float = 0.0  # when its last failure was (or will be) answered
    total: int = 0
    unlogged: int = 0  # failures since the last log line
    logged_at: float = float("-inf")


class TcpDoor:
    """The handshake room of the TCP endpoint and the failures per address.

    Args:
        max_unauthenticated: connections that may wait to authenticate at once.
        auth_failure_delay_s: the spacing of failed-handshake answers per address.
    """

    def __init__(self, max_unauthenticated: int, auth_failure_delay_s: float) -> None:
        self.max_unauthenticated = max_unauthenticated
        self.auth_failure_delay_s = auth_failure_delay_s
        self._waiting: collections.OrderedDict[int, Waiting] = collections.OrderedDict()
        self._failures: dict[str, _Failures] = {}
        self.dropped = 0  # waiting connections dropped to make room
        self.failed = 0  # failed handshakes, every address

    @property
    def waiting(self) -> int:
        return len(self._waiting)

    def enter(self, conn: Waiting, now: float) -> list[Waiting]:
        """Let ``conn`` wait to authenticate: the connections to drop for it (the caller
        closes them)."""
        out: list[Waiting] = []
        hard_cap = HANDSHAKE_HARD_CAP * self.max_unauthenticated
        while len(self._waiting) >= self.max_unauthenticated:
            oldest = next(iter(self._waiting.values()))
            if now - oldest.opened < HANDSHAKE_GRACE_S and len(self._waiting) < hard_cap:
                break
            del self._waiting[oldest.number]
            out.append(oldest)
        self.dropped += len(out)
        self._waiting[conn.number] = conn
        return out

    def leave(self, conn: Waiting) -> None:
        """``conn`` authenticated or closed: it waits no more. Idempotent."""
        self._waiting.pop(conn.number, None)

    def failure(self, host: str, now: float) -> float:
        """Record a failed handshake from ``host``: the delay before it may be answered."""
        self.failed += 1
        record = self._failures.get(host)
        if record is None:
            if len(self._failures) >= _PEERS_KEPT:
                self._forget(now)
            record = self._failures[host] = _Failures()
        record.total += 1
        record.unlogged += 1
        record.answer_at = max(now, record.answer_at) + self.auth_failure_delay_s
        if now - record.logged_at >= FAILURE_LOG_EVERY_S:
            if record.logged_at == float("-inf"):
                log.warning(
                    "tcp %s: failed authentication; its failures are now answered one per "
                    "%g s (tcp.auth_failure_delay_s), logged every %g s",
                    host,
                    self.auth_failure_delay_s,
                    FAILURE_LOG_EVERY_S,
                )
            else:
                log.warning(
                    "tcp %s: %d failed authentication(s) in the last %.0f s (%d in all)",
                    host,
                    record.unlogged,
                    now - record.logged_at,
                    record.total,
                )
            record.logged_at = now
            record.unlogged = 0
        return record.answer_at - now

    def _forget(self, now: float) -> None:
        for host in [h for h, r in self._failures.items() if r.answer_at < now]:
            del self._failures[host]

    def stats(self) -> dict[str, Any]:
        """The door's part of the server's ``get_status``."""
        return {
            "max_unauthenticated": self.max_unauthenticated,
            "waiting": len(self._waiting),
            "dropped_waiting": self.dropped,
            "failed_auth": self.failed,
            "auth_failure_delay_s": self.auth_failure_delay_s,
        }
