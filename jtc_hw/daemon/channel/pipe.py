"""The pipe between the API process and the loop process: framing, and both ends' non-blocking
reader and writer.

Theory of operation
-------------------
The two processes share one ``multiprocessing`` duplex connection (a Unix stream socketpair).
Neither ever waits for the other:

- **API -> loop** (:class:`PlanWriter`, :func:`send_framed`): records of a 9-byte header (a
  kind and a length) and a payload. A request is one ``WHOLE`` record (its pickle). A plan's
  arrays travel out of band: a ``HEAD`` record (the pickle without them, and their sizes),
  then ``CHUNK`` records of at most :data:`CHUNK_BYTES` that the loop's :class:`Inbox` reads
  straight into the arrays' memory, a bounded amount per cycle. A plan whose arrays are
  :data:`SHARED_MIN_BYTES` or more travels in shared memory instead (:func:`prepare`, and
  :mod:`.shared` for the regions and their reuse): its arrays are copied into a sealed
  ``memfd`` in a worker thread of the API process, and one ``SHARED`` record passes the
  descriptor (``SCM_RIGHTS``); the loop maps it and copies nothing, so a plan of any size
  arrives in one cycle. Once the loop has unmapped it, it says so (``Released``). The API
  process writes without blocking, requests before the rest of a plan: a stop never waits
  behind a plan still to be written, only behind what the socket already holds.
- **loop -> API** (:class:`~.outbox.Outbox`, which never waits for the API process, see
  there): ``multiprocessing``'s wire format (:func:`encode_message`: a 4-byte big-endian
  length, or -1 and an 8-byte length, then the pickle); the API process reads it with an
  :class:`Inbox` too (unframed), so a message the loop has written only in part never blocks
  the API's event loop either.

Both ends use a duplicate of the connection's socket with per-call ``MSG_DONTWAIT``: setting
``O_NONBLOCK`` would change the shared file description, and with it the other direction's
blocking sends.
"""

from __future__ import annotations

import array
import collections
import ctypes
import fcntl
import mmap
import os
import pickle
import select
import socket
import struct
import sys
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..realtime import libc_function
from .shared import SEALS, SHARED_AVAILABLE, Region, SharedPool, layout, new_memfd

__all__ = [
    "Inbox", "Outgoing", "PlanWriter", "SHARED_MIN_BYTES", "encode_message", "prepare",
    "send_framed",
]

_HEADER = struct.Struct("!i")
_LONG_HEADER = struct.Struct("!Q")

_RECORD = struct.Struct("<BQ")
"""API -> loop record header: kind, payload length."""
WHOLE, HEAD, CHUNK, SHARED = 1, 2, 3, 4
"""Record kinds: a whole message (its pickle); the head of a message whose buffers follow
(``_COUNT`` count, then each buffer's size, then the pickle); a piece of those buffers; a
message whose buffers are in the shared memory whose descriptor comes with the record (its
pool's token, ``_TOKEN``, then as a HEAD's payload; the buffers at ``shared.layout``'s
offsets)."""
_TOKEN = struct.Struct("<Q")
_COUNT = struct.Struct("<I")
_SIZE = struct.Struct("<Q")

CHUNK_BYTES = 256 << 10
"""Largest ``CHUNK`` record: what a request may have to wait behind at the writer, and the
most one read of the loop's inbox copies (~0.1 ms)."""
SHARED_MIN_BYTES = CHUNK_BYTES
"""A message whose out-of-band buffers add up to this or more travels in shared memory (when
the system has ``memfd_create``): below it, copying through the socket costs less than the
mapping's system calls."""
_FD_SPACE = socket.CMSG_SPACE(16 * array.array("i").itemsize)
"""Room for the descriptors one read may bring (one per SHARED record; too little would
close the extra ones: the record would then find none and the inbox close)."""
_TIMED_READ_BYTES = 4096
"""Reads of at least this much are followed by a look at the clock (:meth:`Inbox.pump`)."""


class PlanWriter:
    """The API process's writer to the loop: never blocks, requests before the rest of a plan.

    :meth:`flush` writes what the socket takes now (``sendmsg(MSG_DONTWAIT)``, a plan's arrays
    from their own memory: no copy); the owner calls it again when the socket is writable.

    Args:
        conn: the connection (its socket is duplicated; the connection stays open).
        shared_min_bytes: a bulk message given to :meth:`put` unprepared travels in shared
            memory from this many bytes of buffers (:func:`prepare`; ``None``: never).
    """

    def __init__(
        self, conn: Connection, shared_min_bytes: int | None = SHARED_MIN_BYTES
    ) -> None:
        self._sock = socket.socket(fileno=os.dup(conn.fileno()))
        self._shared_min_bytes = shared_min_bytes
        self._urgent: collections.deque[bytes] = collections.deque()
        self._bulk: collections.deque[Outgoing] = collections.deque()
        self._current: list[bytes | memoryview] = []  # the record being written, its parts
        self._fd: int | None = None  # the descriptor that goes with its first byte
        self._written = 0  # bytes of it already written
        self.closed = False
        """Writing failed for good (the loop process is gone)."""

    def close(self) -> None:
        """Release the duplicated socket (the connection itself stays open) and the shared
        memory of what was not written."""
        self._sock.close()
        self._drop()

    def _drop(self) -> None:
        self._urgent.clear()
        for outgoing in self._bulk:
            outgoing.close()
        self._bulk.clear()
        self._current = []
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    @property
    def pending(self) -> bool:
        """Something waits to be written."""
        return bool(self._current or self._urgent or self._bulk)

    def put(self, message: object, bulk: bool = False) -> None:
        """Queue ``message``; :meth:`flush` writes it. ``bulk`` (a plan): after every request,
        its buffers out of band; an :class:`Outgoing` (already prepared) is bulk, and the
        writer owns it from now on.

        Raises:
            pickle.PicklingError: ``message`` cannot be pickled (a programming error).
        """
        if isinstance(message, Outgoing):
            if self.closed:
                message.close()
            else:
                self._bulk.append(message)
            return
        if self.closed:
            return
        if not bulk:
            payload = pickle.dumps(message, protocol=5)
            self._urgent.append(_RECORD.pack(WHOLE, len(payload)) + payload)
            return
        self._bulk.append(prepare(message, self._shared_min_bytes))

    def flush(self) -> bool:
        """Write what the socket takes now, never blocking; True if nothing is left to write.
        Never raises: a failing socket (the loop exited) sets :attr:`closed` and drops the queue.
        """
        while not self.closed:
            if not self._current and not self._next():
                return True
            parts = self._current
            if self._written:
                parts = _skip(parts, self._written)
            fds = () if self._fd is None else [
                (socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", [self._fd]))
            ]
            try:
                sent = self._sock.sendmsg(parts, fds, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                return False
            except OSError:
                self.closed = True
                self._drop()
                return False
            if self._fd is not None and sent:  # it went with these bytes: the reader has it
                os.close(self._fd)
                self._fd = None
            self._written += sent
            if self._written == sum(len(part) for part in self._current):
                self._current = []
                self._written = 0
        return False

    def _next(self) -> bool:
        """Make the next record current: a request first, else the next piece of a plan."""
        if self._urgent:
            self._current = [self._urgent.popleft()]
            return True
        while self._bulk:
            outgoing = self._bulk[0]
            records = outgoing.records
            if records:
                header = records.popleft()
                if header[0] == SHARED:
                    self._fd, outgoing.fd = outgoing.fd, None
                self._current = [header] if header[0] != CHUNK else [header, records.popleft()]
                return True
            self._bulk.popleft()
        return False


class Outgoing:
    """A message made ready to write (:func:`prepare`): its records, and the shared memory's
    descriptor that goes with its SHARED record (owned: :meth:`close` releases it, and gives
    the region back to its pool, if it was not handed on)."""

    __slots__ = ("fd", "records", "region")

    def __init__(
        self,
        records: list[bytes | memoryview],
        fd: int | None = None,
        region: tuple[SharedPool, Region] | None = None,
    ) -> None:
        self.records = collections.deque(records)
        self.fd = fd
        self.region = region

    def close(self) -> None:
        """Release the descriptor if it was not handed on."""
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
            if self.region is not None:
                pool, region = self.region
                pool.unsent(region)


def prepare(
    message: object,
    shared_min_bytes: int | None = SHARED_MIN_BYTES,
    pool: SharedPool | None = None,
) -> Outgoing:
    """``message`` as records: its pickle without its buffers (protocol 5), and the buffers in
    shared memory (a SHARED record, from ``shared_min_bytes`` of them; ``None``: never) or as
    CHUNK records after a HEAD. A HEAD or SHARED record is one item (header and payload), a
    CHUNK two (its header, then the memory it carries: no copy). The shared memory is a region
    of ``pool`` (reused: the loop's ``Released`` gives it back), or without one a memory of
    its own that the loop's unmapping frees (tests, tools).

    Writing shared memory copies the buffers (1.7 ms for 24 MB into a reused region, 8 ms into
    new memory): call it where that may take a while, not in an event loop.

    Raises:
        pickle.PicklingError: ``message`` cannot be pickled (a programming error).
        OSError: the shared memory could not be made (out of memory).
    """
    buffers: list[pickle.PickleBuffer] = []
    head = pickle.dumps(message, protocol=5, buffer_callback=buffers.append)
    raws = [buffer.raw() for buffer in buffers]
    sizes = [raw.nbytes for raw in raws]
    payload = _COUNT.pack(len(raws)) + b"".join(_SIZE.pack(size) for size in sizes) + head
    if (
        shared_min_bytes is not None
        and SHARED_AVAILABLE
        and sum(sizes) >= shared_min_bytes
    ):
        return _shared(raws, sizes, payload, pool)
    out: list[bytes | memoryview] = [_RECORD.pack(HEAD, len(payload)) + payload]
    for raw in raws:
        for start in range(0, raw.nbytes, CHUNK_BYTES):
            piece = raw[start : start + CHUNK_BYTES]
            out.append(_RECORD.pack(CHUNK, piece.nbytes))
            out.append(piece)
    return Outgoing(out)


def _shared(
    raws: list[memoryview], sizes: list[int], payload: bytes, pool: SharedPool | None
) -> Outgoing:
    """The SHARED record of a message whose buffers ``raws`` (of ``sizes`` bytes) are copied
    into shared memory."""
    offsets, total = layout(sizes)
    if pool is None:
        fd = new_memfd(total)
        try:
            for raw, at in zip(raws, offsets, strict=True):
                done = 0
                while done < raw.nbytes:  # pwrite may write less than asked (signals, > 2 GiB)
                    done += os.pwrite(fd, raw[done:], at + done)
        except BaseException:
            os.close(fd)
            raise
        body = _TOKEN.pack(0) + payload
        return Outgoing([_RECORD.pack(SHARED, len(body)) + body], fd)
    region = pool.acquire(total)
    try:
        for raw, at in zip(raws, offsets, strict=True):
            region.write(at, raw)
        fd = os.dup(region.fd)
    except BaseException:
        pool.unsent(region)
        raise
    body = _TOKEN.pack(region.token) + payload
    return Outgoing([_RECORD.pack(SHARED, len(body)) + body], fd, (pool, region))


def _skip(parts: list[bytes | memoryview], count: int) -> list[bytes | memoryview]:
    """``parts`` without their first ``count`` bytes."""
    out = []
    for part in parts:
        if count >= len(part):
            count -= len(part)
            continue
        out.append(memoryview(part)[count:] if count else part)
        count = 0
    return out


def send_framed(
    conn: Connection,
    message: object,
    bulk: bool = True,
    shared_min_bytes: int | None = SHARED_MIN_BYTES,
) -> None:
    """Send ``message`` as :class:`PlanWriter` does, waiting until it is written (tests, tools).

    Raises:
        OSError: the connection is closed (the peer exited).
    """
    writer = PlanWriter(conn, shared_min_bytes)
    try:
        writer.put(message, bulk)
        poller = select.poll()
        poller.register(writer._sock.fileno(), select.POLLOUT)
        while not writer.flush():
            if writer.closed:
                raise BrokenPipeError("the connection to the loop is closed")
            poller.poll()
    finally:
        writer.close()


def encode_message(message: Any) -> bytes:
    """``message`` in ``multiprocessing``'s wire format (what ``Connection.send`` writes).

    Raises:
        pickle.PicklingError: ``message`` cannot be pickled.
    """
    payload = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    size = len(payload)
    if size > 0x7FFFFFFF:
        return _HEADER.pack(-1) + _LONG_HEADER.pack(size) + payload
    return _HEADER.pack(size) + payload


_Buffer = bytearray | memoryview | mmap.mmap

LARGE_MESSAGE_BYTES = 1 << 20
"""A plan's array from this size on is received into memory that is not zero-filled."""

RETURNED_MESSAGE_BYTES = 8 << 20
"""A plan's array from this size on gets memory of its own, returned to the system once
released (smaller ones reuse the heap, which the loop process keeps: ``keep_freed_memory``)."""

RELEASE_CHUNK_BYTES = 2 << 20
"""Memory of a large array returned to the system per :meth:`Inbox.release` (0.2-0.35 ms
measured)."""


def _receive_buffer(size: int) -> _Buffer:
    """A buffer to receive one of a plan's arrays (``size`` bytes) into.

    ``bytearray(size)`` writes ``size`` zero bytes at once: 42 ms for the 90 MB plan of a
    75,000-point goal, in one cycle (19 deadlines missed at 500 Hz). A large array gets an
    uninitialised buffer instead: its pages are first touched by the reads, a bounded amount
    per pump. A very large one is an anonymous mapping of its own, so that the memory goes
    back to the system after it (:meth:`Inbox.release`), a chunk at a time.
    """
    if size >= RETURNED_MESSAGE_BYTES:
        # Private: MADV_DONTNEED then frees the pages at once (a shared anonymous mapping keeps
        # them until the unmap, which then costs 20 ms for 90 MB).
        return mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    if size >= LARGE_MESSAGE_BYTES:
        return np.empty(size, dtype=np.uint8).data
    return bytearray(size)


def _munlock(address: int, length: int) -> None:
    """``munlock`` a range of this process's memory (errors ignored: best effort)."""
    munlock = libc_function("munlock")
    if munlock is None:
        return
    munlock.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
    munlock(address, length)


class _Mapped:
    """A message buffer of its own mapping, to unmap once nothing uses it, a chunk at a time.

    The unpickled arrays are made from ``array`` (a view of the whole mapping): each keeps a
    reference to it (through the memoryview numpy takes of it), so while its (CPython)
    reference count is above our own, something made from the message is alive and the
    memory stays. The mapping's own exports are no evidence: ``array`` holds them, not the
    unpickled arrays.
    """

    def __init__(self, mapping: mmap.mmap, token: int = 0) -> None:
        self.mapping = mapping
        self.array: NDArray[np.uint8] | None = np.frombuffer(mapping, dtype=np.uint8)
        self.address = self.array.ctypes.data
        self.returned = 0  # bytes given back so far
        self.token = token
        """Shared memory: its pool's token (0: none), reported once unmapped. Its
        ``MADV_DONTNEED`` only removes the page-table entries: the pool keeps the pages."""

    def unused(self) -> bool:
        """Whether nothing made from the message (e.g. a plan's reference) is left."""
        if self.array is not None:
            if sys.getrefcount(self.array) > 2:  # ours and getrefcount's argument
                return False
            self.array = None  # its view of the mapping goes with it
        return True

    def give_back(self, limit: int) -> bool:
        """Return at most ``limit`` more bytes to the system; True once all is unmapped."""
        size = len(self.mapping)
        if self.returned < size:
            length = min(limit, size - self.returned)
            try:
                self.mapping.madvise(mmap.MADV_DONTNEED, self.returned, length)
            except OSError:
                # Locked pages (the loop process's lock_memory: mlockall) refuse it (EINVAL):
                # unlock the chunk first, then they can go.
                _munlock(self.address + self.returned, length)
                try:
                    self.mapping.madvise(mmap.MADV_DONTNEED, self.returned, length)
                except OSError:
                    pass  # left to the unmap at the end
            self.returned += length
            if self.returned < size:
                return False
        self.mapping.close()  # nothing left in it: cheap
        return True


class Inbox:
    """Messages read without ever blocking, a bounded amount at a time.

    In the loop process, a receiving thread would compete with the loop thread for the
    interpreter lock (measured: cycles stretched by milliseconds, docs/decisions.md 12), so the
    loop process has one thread, and :meth:`pump` reads what has arrived, at most ``budget``
    bytes (and not past a time it is given), straight into the memory of what is being received
    (``MSG_DONTWAIT``: the connection stays blocking for sends): a plan's arrays are read where
    they will stay, a chunk record at a time. A 2,000-point plan then arrives over one or two
    cycles, each paying a bounded copy. In the API process it lets the event loop read the
    loop's messages (``multiprocessing``'s format) without waiting for the rest of one the loop
    wrote in part. How a plan's large arrays are received and given back:
    :func:`_receive_buffer`.

    Args:
        conn: the connection (its socket is duplicated; the connection stays open).
        budget: bytes read per :meth:`pump` at most.
        framed: the API -> loop records of :class:`PlanWriter`; ``False``: each message is
            one pickle in ``multiprocessing``'s format (:class:`~.outbox.Outbox`,
            ``Connection.send``).
    """

    def __init__(self, conn: Connection, budget: int, *, framed: bool = True) -> None:
        self._sock = socket.socket(fileno=os.dup(conn.fileno()))
        self._poll = select.poll()
        self._poll.register(self._sock.fileno(), select.POLLIN)
        self._budget = budget
        self._framed = framed
        self._queue: collections.deque[Any] = collections.deque()
        self.closed = False
        """The peer closed its end (or the socket failed, or the stream made no sense);
        what arrived before is queued."""
        self._header = bytearray(_RECORD.size if framed else _HEADER.size)
        self._body: bytearray | None = None  # the record or message being received
        self._view = memoryview(self._header)
        self._filled = 0
        self._long = False  # unframed: a -1 header announced an 8-byte length
        self._kind = 0  # framed: the record being received (0: its header)
        self._head: bytes | None = None  # framed: the pickle whose buffers are arriving
        self._buffers: list[_Buffer] = []  # ... those buffers
        self._target = 0  # ... the one being filled
        self._offset = 0  # ... and how much of it is
        self._record_left = 0  # bytes of the current CHUNK record not read yet
        self._mapped: list[_Mapped] = []  # large messages' memory, to give back once unused
        self._fds: collections.deque[int] = collections.deque()  # arrived, for SHARED records
        self.released: list[int] = []
        """Tokens of shared memory unmapped by :meth:`release`, for the owner to report."""

    def close(self) -> None:
        """Release the duplicated socket (the connection itself stays open) and descriptors
        that arrived for records not read yet."""
        self._sock.close()
        while self._fds:
            os.close(self._fds.popleft())

    def pump(self, until_ns: int | None = None) -> None:
        """Read what has arrived, at most ``budget`` bytes (and, with ``until_ns``, no more once
        that time on the monotonic clock has passed, checked after each read of a plan's memory:
        headers and requests are read whatever the time); never blocks. Never raises: a failing
        socket sets :attr:`closed`."""
        if not self._poll.poll(0):
            # Nothing arrived (most cycles): a poll costs 0.6 us, a recv that fails with
            # EAGAIN 1.5 us (the exception). A closed or failed socket reports an event.
            return
        budget = self._budget
        while budget > 0 and not self.closed:
            want = min(len(self._view) - self._filled, budget)
            try:
                if self._framed:  # a SHARED record's descriptor comes with its first byte
                    got, fds, _, _ = self._sock.recvmsg_into(
                        [self._view[self._filled : self._filled + want]], _FD_SPACE,
                        socket.MSG_DONTWAIT | socket.MSG_CMSG_CLOEXEC,
                    )
                    if fds:
                        self._take_fds(fds)
                else:
                    got = self._sock.recv_into(
                        self._view[self._filled :], want, socket.MSG_DONTWAIT
                    )
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.closed = True
                return
            if got == 0:
                self.closed = True
                return
            budget -= got
            self._filled += got
            if self._filled == len(self._view):
                if self._framed:
                    self._advance_framed()
                else:
                    self._advance()
            if got >= _TIMED_READ_BYTES and until_ns is not None:
                if time.monotonic_ns() >= until_ns:
                    return

    # -- API -> loop records ----------------------------------------------------------------

    def _take_fds(self, ancillary: list[tuple[int, int, bytes]]) -> None:
        for level, kind, data in ancillary:
            if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
                fds = array.array("i")
                fds.frombytes(data[: len(data) - len(data) % fds.itemsize])
                self._fds.extend(fds)

    def _expect_record(self) -> None:
        self._kind = 0
        self._view = memoryview(self._header)
        self._filled = 0

    def _advance_framed(self) -> None:
        kind = self._kind
        if kind == 0:
            kind, size = _RECORD.unpack(self._header)
            if kind == CHUNK and self._head is not None and 0 < size:
                self._kind = CHUNK
                self._record_left = size
                self._chunk_view()
            elif size > 0 and (
                kind == WHOLE or (kind in (HEAD, SHARED) and self._head is None)
            ):
                # (a request may come between the chunks of a plan: it overtook their rest)
                self._kind = kind
                self._body = bytearray(size)
                self._view = memoryview(self._body)
                self._filled = 0
            else:  # a bug on the writing side: nothing after this can be trusted
                self.closed = True
            return
        if kind == CHUNK:
            got = len(self._view)
            self._record_left -= got
            self._offset += got
            self._skip_full()
            if self._record_left:
                if self._target == len(self._buffers):
                    self.closed = True  # more bytes than the head announced
                    return
                self._chunk_view()
                return
            self._expect_record()
            if self._target == len(self._buffers):
                self._complete()
            return
        body, self._body = self._body, None
        assert body is not None
        self._expect_record()
        if kind == WHOLE:
            self._queue.append(pickle.loads(body))
            return
        token = 0
        if kind == SHARED:
            (token,) = _TOKEN.unpack_from(body)
            body = body[_TOKEN.size :]
        (count,) = _COUNT.unpack_from(body)
        at = _COUNT.size
        sizes = []
        for _ in range(count):
            sizes.append(_SIZE.unpack_from(body, at)[0])
            at += _SIZE.size
        if kind == SHARED:
            self._map_shared(token, sizes, bytes(memoryview(body)[at:]))
            return
        self._head = bytes(memoryview(body)[at:])
        self._buffers = [_receive_buffer(size) for size in sizes]
        self._target = self._offset = 0
        self._skip_full()
        if self._target == len(self._buffers):
            self._complete()

    def _map_shared(self, token: int, sizes: list[int], head: bytes) -> None:
        """Map the shared memory that came with a SHARED record and queue its message, made
        from views of it (nothing copied). A record without its descriptor, or memory that
        could shrink or is too small, is a bug on the writing side: the inbox closes."""
        if not self._fds:
            self.closed = True
            return
        fd = self._fds.popleft()
        try:
            offsets, total = layout(sizes)
            if (fcntl.fcntl(fd, fcntl.F_GET_SEALS) & SEALS != SEALS
                    or os.fstat(fd).st_size < total):
                self.closed = True
                return
            # Read-only: the plan's arrays are never written, and nothing here can change the
            # API process's region.
            mapping = mmap.mmap(fd, total, flags=mmap.MAP_SHARED, prot=mmap.PROT_READ)
        except OSError:
            self.closed = True
            return
        finally:
            os.close(fd)  # the mapping keeps the memory
        mapped = _Mapped(mapping, token)
        self._mapped.append(mapped)
        whole = mapped.array
        assert whole is not None  # a new one is in use until released
        views = [whole[at : at + size].data for at, size in zip(offsets, sizes, strict=True)]
        self._queue.append(pickle.loads(head, buffers=views))

    def _skip_full(self) -> None:
        """Move past the buffers filled completely (and empty ones)."""
        buffers = self._buffers
        while self._target < len(buffers) and self._offset == len(buffers[self._target]):
            self._target += 1
            self._offset = 0

    def _chunk_view(self) -> None:
        buffer = self._buffers[self._target]
        end = min(len(buffer), self._offset + self._record_left)
        self._view = memoryview(buffer)[self._offset : end]
        self._filled = 0

    def _complete(self) -> None:
        buffers: list[Any] = list(self._buffers)
        for i, buffer in enumerate(buffers):
            if isinstance(buffer, mmap.mmap):
                mapped = _Mapped(buffer)
                self._mapped.append(mapped)
                assert mapped.array is not None  # a new one is in use until released
                buffers[i] = mapped.array.data
        head, self._head, self._buffers = self._head, None, []
        assert head is not None
        self._queue.append(pickle.loads(head, buffers=buffers))

    # -- loop -> API messages (multiprocessing's format) ------------------------------------

    def _advance(self) -> None:
        if self._body is None:
            if self._long:
                (size,) = _LONG_HEADER.unpack(self._header)
                self._long = False
            else:
                (size,) = _HEADER.unpack(self._header)
                if size == -1:
                    self._long = True
                    self._header = bytearray(_LONG_HEADER.size)
                    self._view = memoryview(self._header)
                    self._filled = 0
                    return
            self._body = bytearray(size)
            self._view = memoryview(self._body)
            self._filled = 0
            if size:
                return
        body, self._body = self._body, None
        self._header = bytearray(_HEADER.size)
        self._view = memoryview(self._header)
        self._filled = 0
        self._queue.append(pickle.loads(body))

    def release(self) -> bool:
        """Give back a chunk of the memory of the large messages nothing uses any more; whether
        there was something to give back. Call in spare time: costs at most one ``madvise`` of
        :data:`RELEASE_CHUNK_BYTES`."""
        for mapped in self._mapped:
            if mapped.unused():
                if mapped.give_back(RELEASE_CHUNK_BYTES):
                    self._mapped.remove(mapped)
                    if mapped.token:
                        self.released.append(mapped.token)
                return True
        return False

    @property
    def waiting(self) -> int:
        """Completed messages not popped yet."""
        return len(self._queue)

    def pop(self) -> Any | None:
        """The oldest completed message, or ``None``."""
        queue = self._queue
        # Tested, not caught: the queue is empty in most cycles, and an IndexError raised and
        # caught costs ten times the test.
        return queue.popleft() if queue else None
