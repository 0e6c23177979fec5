"""The loop's messages to the API process: queued, coalesced, written without ever blocking.

The loop never waits for the API process (see :mod:`.pipe` for the wire format, which is
``multiprocessing``'s, and for the API process's reading end). A cycle queues its messages
(:meth:`Outbox.put`) and writes them once, at its end (:meth:`Outbox.flush`): all pending
messages in one ``sendmsg(MSG_DONTWAIT)``, a partial write resumed where it stopped.
Droppable messages (``State``, the periodic ``Status``) are coalesced while the queue is not
empty, the newest kept; every other message is kept in order. If the API process stops
reading, the age of the oldest kept message tells the loop how long it has been stalled
(:meth:`Outbox.oldest_ns`).
"""

from __future__ import annotations

import collections
import os
import select
import socket
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from ..channel.pipe import encode_message

__all__ = ["Outbox"]

_IOV_MAX = 64
"""Messages handed to one ``sendmsg`` (Linux allows 1024; a cycle queues a handful)."""


class _Entry:
    """One queued message: its bytes, its coalescing key (droppable) or enqueue time."""

    __slots__ = ("data", "key", "queued_ns")

    def __init__(self, data: bytes, key: object | None, queued_ns: int) -> None:
        self.data = data
        self.key = key
        self.queued_ns = queued_ns


class Outbox:
    """The loop's messages to the API process: queued, written without ever blocking.

    A message put with a ``key`` is droppable: while it waits, a newer message with the same key
    replaces it (in place if nothing was queued after it, otherwise the old one is dropped and
    the new one queued last, so that it still follows everything queued before it).

    The queue is bounded in two ways: droppable messages by their keys (one waiting per key),
    ordered ones by ``capacity_bytes``: beyond it :attr:`overflow` is true, and the owner is
    expected to stop producing them (the loop ends the active goal, whose feedback is the
    only steady stream of ordered messages). Either way :meth:`oldest_ns` says since when the
    oldest ordered message has been waiting: how long the reader has been stalled.

    Args:
        conn: the connection (its socket is duplicated; the connection stays open).
        capacity_bytes: ordered bytes waiting beyond which :attr:`overflow` is set.
        clock: the monotonic clock stamping ordered messages, ns.
    """

    def __init__(
        self,
        conn: Connection,
        capacity_bytes: int,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self._sock = socket.socket(fileno=os.dup(conn.fileno()))
        self.capacity_bytes = capacity_bytes
        self._clock = clock
        self._entries: collections.deque[_Entry] = collections.deque()
        self._latest: dict[object, _Entry] = {}  # the waiting droppable message of each key
        self._written = 0  # bytes of the first entry already written
        self._ordered: collections.deque[_Entry] = collections.deque()  # waiting, in order
        self.pending_bytes = 0
        self.ordered_bytes = 0
        self.closed = False
        """Writing failed for good (the reader is gone)."""
        # Statistics (see snapshot()).
        self.messages = 0
        self.dropped = 0
        self.peak_bytes = 0
        self.flushes = 0
        self.full_flushes = 0
        self._send_ns_max = 0
        self._send_ns_worst = 0
        self._send_ns_total = 0

    def close(self) -> None:
        """Release the duplicated socket (the connection itself stays open)."""
        self._sock.close()

    # -- queueing ----------------------------------------------------------------------------

    def put(self, message: Any, key: object | None = None) -> None:
        """Queue ``message``; with a ``key``, it replaces a waiting message of the same key.

        Raises:
            pickle.PicklingError: ``message`` cannot be pickled (a programming error).
        """
        if self.closed:
            return
        data = encode_message(message)
        self.messages += 1
        if key is None:
            entry = _Entry(data, None, self._clock())
            self._entries.append(entry)
            self._ordered.append(entry)
            self.ordered_bytes += len(data)
            self._grew(len(data))
            return
        old = self._latest.get(key)
        if old is not None and not (old is self._entries[0] and self._written):
            # Waiting and not half written: the newer message replaces it.
            self.dropped += 1
            if old is self._entries[-1]:
                self._grew(len(data) - len(old.data))
                old.data = data
                return
            self.pending_bytes -= len(old.data)
            old.data = b""
            old.key = None
        entry = _Entry(data, key, 0)
        self._latest[key] = entry
        self._entries.append(entry)
        self._grew(len(data))

    def _grew(self, size: int) -> None:
        self.pending_bytes += size
        if self.pending_bytes > self.peak_bytes:
            self.peak_bytes = self.pending_bytes

    @property
    def empty(self) -> bool:
        """Nothing waits to be written."""
        return not self._entries

    @property
    def overflow(self) -> bool:
        """More ordered bytes wait than ``capacity_bytes``."""
        return self.ordered_bytes > self.capacity_bytes

    def oldest_ns(self) -> int | None:
        """When the oldest waiting ordered message was queued (``None``: none waits)."""
        return self._ordered[0].queued_ns if self._ordered else None

    # -- writing -----------------------------------------------------------------------------

    def flush(self) -> bool:
        """Write what the socket takes now, never blocking; True if everything was written.
        Never raises: a failing socket (the reader exited) sets :attr:`closed` and clears the
        queue."""
        entries = self._entries
        if not entries:
            return True
        clock = self._clock
        begin = clock()
        sock = self._sock
        while entries:
            buffers: list[bytes | memoryview] = []
            for entry in entries:
                if entry.data:
                    buffers.append(entry.data)
                    if len(buffers) == _IOV_MAX:
                        break
            if not buffers:  # only dropped entries were left
                self._advance(0)
                break
            if self._written:
                buffers[0] = memoryview(buffers[0])[self._written :]
            try:
                sent = sock.sendmsg(buffers, (), socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._fail()
                break
            if not self._advance(sent):
                break  # a partial write: the socket is full
        took = clock() - begin
        self.flushes += 1
        self._send_ns_total += took
        if took > self._send_ns_max:
            self._send_ns_max = took
        if entries:
            self.full_flushes += 1
            return False
        return True

    def _advance(self, sent: int) -> bool:
        """Account ``sent`` bytes; True if every entry they cover was written whole."""
        entries = self._entries
        while entries:
            entry = entries[0]
            rest = len(entry.data) - self._written
            if sent < rest:
                self._written += sent
                self.pending_bytes -= sent
                if entry.key is None and entry.data:
                    self.ordered_bytes -= sent
                return False
            sent -= rest
            self.pending_bytes -= rest
            self._written = 0
            entries.popleft()
            if entry.key is not None:
                if self._latest.get(entry.key) is entry:
                    del self._latest[entry.key]
            elif entry.data:
                self.ordered_bytes -= rest
                self._ordered.popleft()
            if sent == 0 and (not entries or entries[0].data):
                return True
        return True

    def _fail(self) -> None:
        self.closed = True
        self._entries.clear()
        self._ordered.clear()
        self._latest.clear()
        self.pending_bytes = self.ordered_bytes = self._written = 0

    def drain(self, timeout_s: float) -> bool:
        """Write everything, waiting up to ``timeout_s`` for the reader (not for use in a cycle:
        it blocks); True if everything was written. Never raises: a failing socket sets
        :attr:`closed` (and returns False)."""
        deadline = time.monotonic() + timeout_s
        poller = select.poll()
        poller.register(self._sock.fileno(), select.POLLOUT)
        while not self.flush() and not self.closed:
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            poller.poll(max(1, int(left * 1000)))
        return not self.closed

    # -- statistics --------------------------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        """Counters for the loop's status (resets the window maximum).

        Keys: ``messages`` queued since start; ``dropped``, droppable messages replaced by a
        newer one before being written; ``flushes`` that had something to write, and
        ``full_flushes``, those that left something waiting (the socket was full);
        ``pending_bytes`` now, ``peak_bytes`` ever, ``capacity_bytes``; ``oldest_ms``, the age
        of the oldest waiting ordered message; ``send_us``: ``max`` of one flush since the
        previous snapshot, ``worst`` ever, ``mean`` over all flushes.
        """
        window, self._send_ns_max = self._send_ns_max, 0
        if window > self._send_ns_worst:
            self._send_ns_worst = window
        oldest = self.oldest_ns()
        return {
            "messages": self.messages,
            "dropped": self.dropped,
            "flushes": self.flushes,
            "full_flushes": self.full_flushes,
            "pending_bytes": self.pending_bytes,
            "peak_bytes": self.peak_bytes,
            "capacity_bytes": self.capacity_bytes,
            "oldest_ms": None if oldest is None else (self._clock() - oldest) / 1e6,
            "send_us": {
                "max": window / 1e3,
                "worst": self._send_ns_worst / 1e3,
                "mean": self._send_ns_total / self.flushes / 1e3 if self.flushes else None,
            },
        }
