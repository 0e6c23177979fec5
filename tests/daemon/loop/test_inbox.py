"""The loop process's inbox (jtc_hw.daemon.channel.pipe.Inbox): framed messages read without
blocking, a bounded amount at a time."""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterator

import numpy as np
import pytest

from jtc_hw.daemon.channel.pipe import Inbox as _Inbox
from jtc_hw.daemon.channel.pipe import send_framed


@pytest.fixture
def pipe() -> Iterator[tuple[object, object]]:
    a, b = multiprocessing.Pipe(duplex=True)
    try:
        yield a, b
    finally:
        a.close()
        b.close()


def _drain(inbox: _Inbox, count: int, max_pumps: int = 100_000) -> list[object]:
    out: list[object] = []
    for _ in range(max_pumps):
        inbox.pump()
        while (message := inbox.pop()) is not None:
            out.append(message)
        if len(out) >= count:
            return out
    raise AssertionError(f"only {len(out)} of {count} messages after {max_pumps} pumps")


@pytest.mark.parametrize("shared", [None, 1 << 16], ids=["chunks", "shared"])
@pytest.mark.parametrize("budget", [1, 7, 4096, 1 << 20])
def test_messages_arrive_whole_and_in_order_whatever_the_budget(
    pipe: tuple[object, object], budget: int, shared: int | None
) -> None:
    sender, receiver = pipe
    big = np.arange(50_000, dtype=np.float64)  # 400 kB out of band (a separate frame)
    messages = [
        ("request", 1, "stop", {}),
        ("commit", 2, {"arrays": [big, np.zeros(0), np.ones((3, 4))], "name": "x" * 20_000}),
        ("request", 3, "cancel", {"goal_id": 7}),
    ]
    inbox = _Inbox(receiver, budget)  # type: ignore[arg-type]
    try:
        # Small budgets need many pumps: send from a thread so a full socket cannot block us.
        import threading

        def send_all() -> None:
            for message in messages:
                send_framed(sender, message, shared_min_bytes=shared)  # type: ignore[arg-type]

        thread = threading.Thread(target=send_all)
        thread.start()
        got = _drain(inbox, len(messages), max_pumps=5_000_000)
        thread.join(timeout=10)
        assert not thread.is_alive()
    finally:
        inbox.close()
    assert [m[0] for m in got] == ["request", "commit", "request"]  # type: ignore[index]
    payload = got[1][2]  # type: ignore[index]
    np.testing.assert_array_equal(payload["arrays"][0], big)
    assert payload["arrays"][1].size == 0 and payload["arrays"][2].shape == (3, 4)
    assert payload["name"] == "x" * 20_000
    assert got[2] == messages[2]


def test_pump_never_blocks_and_sees_the_end(pipe: tuple[object, object]) -> None:
    sender, receiver = pipe
    inbox = _Inbox(receiver, 1 << 16)  # type: ignore[arg-type]
    try:
        inbox.pump()  # nothing sent: returns at once
        assert inbox.pop() is None and not inbox.closed
        send_framed(sender, ("request", 1, "shutdown", {}))  # type: ignore[arg-type]
        sender.close()  # type: ignore[attr-defined]
        got = _drain(inbox, 1)
        assert got == [("request", 1, "shutdown", {})]
        for _ in range(10):
            inbox.pump()
        assert inbox.closed and inbox.waiting == 0
    finally:
        inbox.close()


def test_large_messages_get_memory_of_their_own_given_back_once_unused(
    pipe: tuple[object, object], monkeypatch: pytest.MonkeyPatch
) -> None:
    import mmap
    import threading

    from jtc_hw.daemon.channel import pipe as pipe_module

    monkeypatch.setattr(pipe_module, "RETURNED_MESSAGE_BYTES", 1 << 16)
    monkeypatch.setattr(pipe_module, "RELEASE_CHUNK_BYTES", 1 << 16)
    sender, receiver = pipe
    big = np.arange(100_000, dtype=np.float64)  # 800 kB: its own mapping, 13 chunks
    inbox = _Inbox(receiver, 1 << 20)  # type: ignore[arg-type]
    try:
        thread = threading.Thread(
            target=send_framed, args=(sender, ("commit", 1, {"a": big}), True, None)
        )
        thread.start()
        (message,) = _drain(inbox, 1)
        thread.join(timeout=10)
        (mapped,) = inbox._mapped
        assert isinstance(mapped.mapping, mmap.mmap)
        received = message[2]["a"]  # type: ignore[index]
        np.testing.assert_array_equal(received, big)
        del message
        view = received[5:9]
        del received
        for _ in range(3):  # a view of it is alive: nothing is given back
            assert not inbox.release()
        np.testing.assert_array_equal(view, big[5:9])
        del view
        chunks = 0
        while inbox.release():
            chunks += 1
        assert chunks == 13  # 800,000 bytes in 64 kB chunks, the last one unmapping it
        assert mapped.mapping.closed and not inbox._mapped
    finally:
        inbox.close()


def test_receive_buffers_by_size() -> None:
    import mmap

    from jtc_hw.daemon.channel import pipe as pipe_module

    assert isinstance(pipe_module._receive_buffer(100), bytearray)
    assert isinstance(pipe_module._receive_buffer(pipe_module.LARGE_MESSAGE_BYTES), memoryview)
    mapping = pipe_module._receive_buffer(pipe_module.RETURNED_MESSAGE_BYTES)
    assert isinstance(mapping, mmap.mmap)
    mapping.close()


def test_a_request_overtakes_the_rest_of_a_plan_and_nothing_blocks(
    pipe: tuple[object, object],
) -> None:
    import socket

    from jtc_hw.daemon.channel.pipe import CHUNK_BYTES, PlanWriter

    sender, receiver = pipe
    with socket.socket(fileno=sender.fileno()) as sock:  # type: ignore[attr-defined]
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 65536)
        sock.detach()
    big = np.arange(1_000_000, dtype=np.float64)  # 8 MB: 31 chunks, far beyond the socket
    writer = PlanWriter(sender, shared_min_bytes=None)  # type: ignore[arg-type]
    inbox = _Inbox(receiver, 1 << 16)  # type: ignore[arg-type]
    try:
        writer.put(("commit", 1, {"a": big}), bulk=True)
        assert not writer.flush() and writer.pending  # the socket is full: returns, no wait
        writer.put(("request", 2, "stop", {}))
        got: list[object] = []
        for _ in range(100_000):
            inbox.pump()
            while (message := inbox.pop()) is not None:
                got.append(message)
            if len(got) == 2:
                break
            writer.flush()
        assert [m[0] for m in got] == ["request", "commit"]  # type: ignore[index]
        np.testing.assert_array_equal(got[1][2]["a"], big)  # type: ignore[index]
        assert not writer.pending
        assert big.nbytes > 2 * CHUNK_BYTES
    finally:
        inbox.close()
        writer.close()


def test_a_writer_whose_reader_is_gone_is_closed(pipe: tuple[object, object]) -> None:
    from jtc_hw.daemon.channel.pipe import PlanWriter

    sender, receiver = pipe
    receiver.close()  # type: ignore[attr-defined]
    writer = PlanWriter(sender)  # type: ignore[arg-type]
    try:
        writer.put(("request", 1, "stop", {}))
        assert not writer.flush()
        assert writer.closed and not writer.pending
        writer.put(("request", 2, "stop", {}))  # ignored once closed
        assert not writer.pending
    finally:
        writer.close()


def test_a_stream_that_makes_no_sense_closes_the_inbox(pipe: tuple[object, object]) -> None:
    from jtc_hw.daemon.channel.pipe import _RECORD, CHUNK

    sender, receiver = pipe
    inbox = _Inbox(receiver, 1 << 16)  # type: ignore[arg-type]
    try:
        import os

        os.write(sender.fileno(), _RECORD.pack(CHUNK, 10) + b"x" * 10)  # type: ignore[attr-defined]
        for _ in range(10):
            inbox.pump()
        assert inbox.closed and inbox.pop() is None
    finally:
        inbox.close()


# -- plans in shared memory -------------------------------------------------------------------


def _open_fds() -> set[int]:
    import os

    return {int(name) for name in os.listdir("/proc/self/fd")}


def test_a_large_plan_arrives_in_shared_memory_in_one_read_and_is_given_back(
    pipe: tuple[object, object], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Above SHARED_MIN_BYTES the arrays are not copied through the socket: one small record
    and a descriptor. The loop's arrays are views of the shared memory; once unused it is
    given back a chunk at a time (hole punched), then unmapped; no descriptor is left open."""
    from jtc_hw.daemon.channel import pipe as pipe_module
    from jtc_hw.daemon.channel.pipe import SHARED_MIN_BYTES, PlanWriter

    monkeypatch.setattr(pipe_module, "RELEASE_CHUNK_BYTES", 1 << 20)
    sender, receiver = pipe
    before = _open_fds()
    big = np.arange(1_000_000, dtype=np.float64)  # 8 MB, far beyond the socket's buffer
    small = np.arange(7, dtype=np.int8)
    writer = PlanWriter(sender)  # type: ignore[arg-type]
    inbox = _Inbox(receiver, 1 << 12)  # a 4 KiB budget: a copy would take 2,000 reads
    try:
        writer.put(("commit", 1, {"a": big, "b": small}), bulk=True)
        assert writer.flush() and not writer.pending  # one record: the socket took it
        inbox.pump()
        message = inbox.pop()
        assert message is not None and inbox.pop() is None
        payload = message[2]  # type: ignore[index]
        np.testing.assert_array_equal(payload["a"], big)
        np.testing.assert_array_equal(payload["b"], small)
        (mapped,) = inbox._mapped
        address = mapped.address
        assert address <= payload["a"].ctypes.data < address + len(mapped.mapping)
        assert payload["b"].ctypes.data % 64 == 0  # each buffer aligned
        assert big.nbytes >= SHARED_MIN_BYTES
        assert not inbox.release()  # in use
        del message, payload
        chunks = 0
        while inbox.release():
            chunks += 1
        assert chunks == 8  # 8 MB and a little in 1 MiB chunks, the last one unmapping it
        assert mapped.mapping.closed and not inbox._mapped
    finally:
        inbox.close()
        writer.close()
    assert _open_fds() == before


def test_small_plans_and_the_switch_off_go_through_the_socket(
    pipe: tuple[object, object],
) -> None:
    from jtc_hw.daemon.channel.pipe import HEAD, SHARED, SHARED_MIN_BYTES, prepare

    small = prepare(("commit", 1, {"a": np.zeros(SHARED_MIN_BYTES // 8 - 1)}))
    assert small.fd is None and small.records[0][0] == HEAD
    large = prepare(("commit", 1, {"a": np.zeros(SHARED_MIN_BYTES // 8)}))
    try:
        assert large.fd is not None and large.records[0][0] == SHARED
        assert len(large.records) == 1
    finally:
        large.close()
    off = prepare(("commit", 1, {"a": np.zeros(SHARED_MIN_BYTES)}), shared_min_bytes=None)
    assert off.fd is None and off.records[0][0] == HEAD


def test_shared_memory_not_written_is_released(pipe: tuple[object, object]) -> None:
    """A plan queued but never written (the loop is gone, the writer closed) leaves no
    descriptor behind."""
    from jtc_hw.daemon.channel.pipe import PlanWriter

    sender, receiver = pipe
    before = _open_fds()
    receiver.close()  # type: ignore[attr-defined]
    writer = PlanWriter(sender)  # type: ignore[arg-type]
    writer.put(("commit", 1, {"a": np.zeros(100_000)}), bulk=True)
    assert not writer.flush() and writer.closed
    writer.put(("commit", 2, {"a": np.zeros(100_000)}), bulk=True)  # ignored once closed
    writer.close()
    assert _open_fds() <= before


@pytest.mark.parametrize("fault", ["no descriptor", "not sealed", "too small"])
def test_a_shared_record_that_cannot_be_trusted_closes_the_inbox(
    pipe: tuple[object, object], fault: str
) -> None:
    """The loop never maps memory the writer could still shrink under it (a read past its end
    would kill the loop with SIGBUS), nor reads a record without its memory."""
    import array
    import os
    import socket

    from jtc_hw.daemon.channel.pipe import _COUNT, _RECORD, _SIZE, _TOKEN, SHARED

    sender, receiver = pipe
    payload = _TOKEN.pack(0) + _COUNT.pack(1) + _SIZE.pack(4096) + b"pickle"
    record = _RECORD.pack(SHARED, len(payload)) + payload
    fd = os.memfd_create("test", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    before = _open_fds()
    inbox = _Inbox(receiver, 1 << 16)  # type: ignore[arg-type]
    try:
        import fcntl

        os.ftruncate(fd, 1024 if fault == "too small" else 4096)
        if fault != "not sealed":
            fcntl.fcntl(fd, fcntl.F_ADD_SEALS,
                        fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL)
        with socket.socket(fileno=os.dup(sender.fileno())) as sock:  # type: ignore[attr-defined]
            fds = [] if fault == "no descriptor" else [
                (socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", [fd]))
            ]
            sock.sendmsg([record], fds)
        for _ in range(10):
            inbox.pump()
        assert inbox.closed and inbox.pop() is None
    finally:
        inbox.close()
        os.close(fd)
    assert _open_fds() <= before | {inbox._sock.fileno()}
