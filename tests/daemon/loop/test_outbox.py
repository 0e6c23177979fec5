"""The loop's outbox (jtc_hw.daemon.loop.outbox.Outbox): never blocks, keeps order, coalesces state.

Each test writes into a real socketpair (``multiprocessing.Pipe``) whose send buffer is shrunk
so that it fills after a few kilobytes, and reads the other end with the API process's
non-blocking ``Inbox``, or with ``Connection.recv`` in a thread (the wire format is
``multiprocessing``'s).
"""

from __future__ import annotations

import multiprocessing
import socket
from collections.abc import Iterator
from multiprocessing.connection import Connection
from typing import Any

import pytest

from jtc_hw.daemon.channel.pipe import Inbox
from jtc_hw.daemon.loop.outbox import Outbox

pytestmark = pytest.mark.usefixtures("no_leaks")

SMALL_BUFFER = 4096  # the kernel doubles it, and accounts per-message overhead against it


class Clock:
    """A settable monotonic clock, ns."""

    def __init__(self) -> None:
        self.now = 1_000_000_000

    def __call__(self) -> int:
        return self.now


@pytest.fixture
def pipe() -> Iterator[tuple[Connection, Connection]]:
    writer, reader = multiprocessing.Pipe(duplex=True)
    with socket.socket(fileno=writer.fileno()) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SMALL_BUFFER)
        sock.detach()  # the connection owns the descriptor
    try:
        yield writer, reader
    finally:
        writer.close()
        reader.close()


@pytest.fixture
def clock() -> Clock:
    return Clock()


def fill(outbox: Outbox, tag: str = "fill") -> int:
    """Queue ordered messages until a flush leaves some waiting; how many were queued."""
    n = 0
    while outbox.flush():
        outbox.put((tag, n, b"x" * 500))
        n += 1
        assert n < 10_000, "the socket never filled"
    return n


def read_all(reader: Connection, outbox: Outbox) -> list[Any]:
    """Read (as the API process does, never blocking) while flushing, until the outbox is
    empty and nothing is left in the socket. (``Connection.recv`` would block here on a message
    the outbox has written in part, waiting for a flush that only this thread can do.)"""
    got: list[Any] = []
    inbox = Inbox(reader, 1 << 16, framed=False)
    try:
        for _ in range(1_000_000):
            done = outbox.flush()
            inbox.pump()
            while (message := inbox.pop()) is not None:
                got.append(message)
            if done and not reader.poll(0):
                return got
    finally:
        inbox.close()
    raise AssertionError(f"still not drained; {len(got)} messages read")


def test_messages_arrive_whole_and_in_order_across_partial_writes(
    pipe: tuple[Connection, Connection], clock: Clock
) -> None:
    writer, reader = pipe
    outbox = Outbox(writer, 1 << 20, clock)
    try:
        # Sizes around the buffer's, so that writes stop in the middle of messages.
        sent = [("m", i, b"%d" % i * (1 + (i * 977) % 7000)) for i in range(200)]
        for message in sent:
            outbox.put(message)
        assert outbox.flush() is False  # the socket took only part of it: no waiting
        assert 0 < outbox.pending_bytes < sum(len(m[2]) for m in sent)
        assert outbox.full_flushes == 1
        assert read_all(reader, outbox) == sent
        assert outbox.empty and outbox.pending_bytes == 0 and outbox.ordered_bytes == 0
        assert outbox.oldest_ns() is None
    finally:
        outbox.close()


def test_the_api_side_inbox_reads_the_outbox_format(
    pipe: tuple[Connection, Connection], clock: Clock
) -> None:
    writer, reader = pipe
    outbox = Outbox(writer, 1 << 20, clock)
    inbox = Inbox(reader, 1000, framed=False)  # small budget: messages split across pumps
    try:
        sent = [("m", i, "y" * (i * 131 % 5000)) for i in range(100)]
        for message in sent:
            outbox.put(message)
        got: list[Any] = []
        while len(got) < len(sent):
            outbox.flush()
            inbox.pump()
            while (arrived := inbox.pop()) is not None:
                got.append(arrived)
        assert got == sent
    finally:
        inbox.close()
        outbox.close()


def test_state_is_coalesced_to_the_newest_and_never_overtakes_earlier_messages(
    pipe: tuple[Connection, Connection], clock: Clock
) -> None:
    writer, reader = pipe
    outbox = Outbox(writer, 1 << 20, clock)
    try:
        filled = fill(outbox)
        outbox.put(("state", 1), key="state")
        outbox.put(("state", 2), key="state")  # last in the queue: replaced in place
        outbox.put(("events", "A"))
        outbox.put(("state", 3), key="state")  # state 2 is dropped, 3 goes after A
        outbox.put(("status", "s1"), key="status")
        outbox.put(("reply", 7))
        outbox.put(("status", "s2"), key="status")
        assert outbox.flush() is False
        got = read_all(reader, outbox)
    finally:
        outbox.close()
    assert [m for m in got if m[0] == "fill"] == [("fill", i, b"x" * 500) for i in range(filled)]
    tail = [m for m in got if m[0] != "fill"]
    assert tail == [("events", "A"), ("state", 3), ("reply", 7), ("status", "s2")]
    assert outbox.dropped == 3  # state 1, state 2, status s1
    assert outbox.messages == filled + 7


def test_a_half_written_droppable_message_is_finished_not_replaced(
    pipe: tuple[Connection, Connection], clock: Clock
) -> None:
    writer, reader = pipe
    outbox = Outbox(writer, 1 << 20, clock)
    try:
        big = ("state", 1, b"s" * 100_000)
        outbox.put(big, key="state")
        assert outbox.flush() is False  # part of it is in the socket
        outbox.put(("state", 2), key="state")
        got = read_all(reader, outbox)
    finally:
        outbox.close()
    assert got == [big, ("state", 2)]
    assert outbox.dropped == 0


def test_waiting_ordered_messages_tell_how_long_the_reader_has_stalled(
    pipe: tuple[Connection, Connection], clock: Clock
) -> None:
    writer, reader = pipe
    outbox = Outbox(writer, 1 << 20, clock)
    try:
        assert outbox.oldest_ns() is None
        fill(outbox)
        first_waiting = outbox.oldest_ns()
        assert first_waiting == clock.now
        clock.now += 300_000_000
        outbox.put(("events", "later"))
        outbox.put(("state", 1), key="state")
        outbox.flush()
        assert outbox.oldest_ns() == first_waiting  # the oldest, not the newest
        assert outbox.snapshot()["oldest_ms"] == 300.0
        read_all(reader, outbox)
        assert outbox.oldest_ns() is None
    finally:
        outbox.close()


def test_droppable_messages_alone_are_not_a_stall(
    pipe: tuple[Connection, Connection], clock: Clock
) -> None:
    writer, reader = pipe
    outbox = Outbox(writer, 1 << 20, clock)
    try:
        outbox.put(("state", 0, b"s" * 100_000), key="state")
        assert outbox.flush() is False
        for i in range(1, 1000):
            outbox.put(("state", i), key="state")
            outbox.flush()
        assert outbox.oldest_ns() is None
        assert not outbox.empty
        got = read_all(reader, outbox)
        assert [m[1] for m in got] == [0, 999]
    finally:
        outbox.close()


def test_overflow_when_ordered_bytes_exceed_the_capacity(
    pipe: tuple[Connection, Connection], clock: Clock
) -> None:
    writer, reader = pipe
    outbox = Outbox(writer, 10_000, clock)
    try:
        fill(outbox)
        assert not outbox.overflow
        for i in range(30):
            outbox.put(("events", i, b"e" * 500))
        outbox.flush()
        assert outbox.overflow and outbox.ordered_bytes > 10_000
        assert outbox.snapshot()["peak_bytes"] >= outbox.ordered_bytes
        read_all(reader, outbox)  # kept, not dropped: all of it arrives
        assert not outbox.overflow
    finally:
        outbox.close()


def test_a_closed_reader_ends_the_outbox_without_raising(
    pipe: tuple[Connection, Connection], clock: Clock
) -> None:
    writer, reader = pipe
    outbox = Outbox(writer, 1 << 20, clock)
    try:
        fill(outbox)
        reader.close()
        outbox.put(("events", "lost"))
        outbox.flush()
        assert outbox.closed and outbox.empty and outbox.oldest_ns() is None
        outbox.put(("events", "ignored"))
        assert outbox.flush() is True
        assert outbox.drain(0.1) is False
    finally:
        outbox.close()


def test_drain_waits_for_the_reader(pipe: tuple[Connection, Connection], clock: Clock) -> None:
    import threading

    writer, reader = pipe
    outbox = Outbox(writer, 1 << 20, clock)
    got: list[Any] = []
    try:
        fill(outbox)
        outbox.put(("exit", 0))

        def read() -> None:
            while not got or got[-1] != ("exit", 0):
                got.append(reader.recv())

        thread = threading.Thread(target=read)
        thread.start()
        assert outbox.drain(10.0) is True
        thread.join(10.0)
        assert not thread.is_alive()
    finally:
        outbox.close()
    assert got[-1] == ("exit", 0)


def test_flush_accounts_its_time_and_the_full_socket(
    pipe: tuple[Connection, Connection], clock: Clock
) -> None:
    writer, reader = pipe
    outbox = Outbox(writer, 1 << 20, clock)
    try:
        assert outbox.flush() is True  # nothing to do: not counted
        assert outbox.flushes == 0
        fill(outbox)
        full = outbox.full_flushes
        outbox.flush()
        snap = outbox.snapshot()
        assert snap["full_flushes"] == full + 1 and snap["flushes"] == outbox.flushes
        assert snap["pending_bytes"] == outbox.pending_bytes > 0
        assert set(snap["send_us"]) == {"max", "worst", "mean"}
        read_all(reader, outbox)
    finally:
        outbox.close()
