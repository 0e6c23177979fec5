"""sd_notify against a real AF_UNIX datagram socket standing in for systemd (daemon.sdnotify)."""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from jtc_hw.daemon.sdnotify import Notifier


@pytest.fixture
def listener(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(5.0)
    try:
        yield sock, path
    finally:
        sock.close()


@pytest.fixture
def abstract_listener() -> Iterator[tuple[socket.socket, str]]:
    name = f"jtc-hw-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(5.0)
    try:
        yield sock, "@" + name
    finally:
        sock.close()


def received(sock: socket.socket) -> bytes:
    return sock.recv(4096)


def test_ready_with_status_is_one_exact_datagram(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready("running at 100 Hz") is True
    assert received(sock) == b"READY=1\nSTATUS=running at 100 Hz"
    assert n.ready() is True
    assert received(sock) == b"READY=1"


def test_each_message_exact_bytes(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.watchdog()
    assert received(sock) == b"WATCHDOG=1"
    assert n.stopping()
    assert received(sock) == b"STOPPING=1"
    assert n.stopping("holding position")
    assert received(sock) == b"STOPPING=1\nSTATUS=holding position"
    assert n.status("goal 3 active")
    assert received(sock) == b"STATUS=goal 3 active"
    assert n.send("ERRNO=5")
    assert received(sock) == b"ERRNO=5"


def test_status_is_kept_on_one_line_and_utf8(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.status("joint1 fault:\noverload\r\nµ")
    assert received(sock) == "STATUS=joint1 fault: overload  µ".encode()


def test_abstract_namespace_socket(abstract_listener: tuple[socket.socket, str]) -> None:
    sock, name = abstract_listener
    n = Notifier({"NOTIFY_SOCKET": name})
    assert n.address == b"\0" + name[1:].encode()
    assert n.ready("up")
    assert received(sock) == b"READY=1\nSTATUS=up"


def test_send_from_many_threads_delivers_every_datagram_whole(
    listener: tuple[socket.socket, str],
) -> None:
    # The receiver drains concurrently: the kernel's datagram queue is short
    # (net.unix.max_dgram_qlen, 10 by default), and a full queue fails a non-blocking send.
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    got: set[bytes] = set()
    drain = threading.Thread(target=lambda: got.update(received(sock) for _ in range(40)))
    drain.start()
    results: list[bool] = []

    def ping(i: int) -> None:
        for j in range(10):
            while not n.status(f"t{i}-{j}"):
                time.sleep(0.001)  # queue momentarily full: retry, as a caller may
            results.append(True)

    threads = [threading.Thread(target=ping, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    drain.join()
    assert len(results) == 40
    assert got == {f"STATUS=t{i}-{j}".encode() for i in range(4) for j in range(10)}


def test_without_notify_socket_everything_is_a_no_op() -> None:
    n = Notifier({})
    assert not n.enabled
    assert n.address is None
    assert n.watchdog_interval_s is None
    assert n.ready("x") is False
    assert n.status("x") is False
    assert n.watchdog() is False
    assert n.stopping() is False


def test_default_environment_is_os_environ(
    listener: tuple[socket.socket, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    sock, path = listener
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    n = Notifier()
    assert n.watchdog_interval_s == 1.0
    assert n.ready()
    assert received(sock) == b"READY=1"


def test_relative_notify_socket_disables_with_warning(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="jtc_hw.sdnotify"):
        n = Notifier({"NOTIFY_SOCKET": "relative/notify.sock"})
    assert not n.enabled
    assert n.ready() is False
    assert "NOTIFY_SOCKET" in caplog.text


def test_send_failure_never_raises_and_warns_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens.sock")})
    with caplog.at_level(logging.DEBUG, logger="jtc_hw.sdnotify"):
        assert n.ready() is False
        assert n.watchdog() is False
        assert n.watchdog() is False
    levels = [r.levelno for r in caplog.records if r.name == "jtc_hw.sdnotify"]
    assert levels == [logging.WARNING, logging.DEBUG, logging.DEBUG]
    assert "nobody-listens.sock" in caplog.records[0].getMessage()


def test_full_receive_queue_fails_without_blocking(
    listener: tuple[socket.socket, str], caplog: pytest.LogCaptureFixture
) -> None:
    _sock, path = listener  # never read: its queue fills up
    n = Notifier({"NOTIFY_SOCKET": path})
    deadline = time.monotonic() + 30.0
    with caplog.at_level(logging.WARNING, logger="jtc_hw.sdnotify"):
        while n.status("x" * 1000):
            assert time.monotonic() < deadline, "the receive queue never filled"
    assert len(caplog.records) == 1


def test_send_after_listener_closed(tmp_path: Path) -> None:
    path = str(tmp_path / "gone.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    n = Notifier({"NOTIFY_SOCKET": path})
    sock.close()
    assert n.watchdog() is False


@pytest.mark.parametrize(
    ("usec", "interval"),
    [("2000000", 1.0), ("1", 0.0000005), ("500000", 0.25), ("3000001", 1.5000005)],
)
def test_watchdog_interval_is_half_the_timeout(usec: str, interval: float) -> None:
    n = Notifier({"WATCHDOG_USEC": usec})
    assert n.watchdog_interval_s == pytest.approx(interval, rel=0, abs=1e-12)
    own = Notifier({"WATCHDOG_USEC": usec, "WATCHDOG_PID": str(os.getpid())})
    assert own.watchdog_interval_s == n.watchdog_interval_s


def test_watchdog_for_another_pid_is_not_ours() -> None:
    other = os.getppid() if os.getppid() != os.getpid() else os.getpid() + 1
    n = Notifier({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(other)})
    assert n.watchdog_interval_s is None


@pytest.mark.parametrize("env", [{}, {"WATCHDOG_USEC": ""}, {"WATCHDOG_USEC": "0"}])
def test_watchdog_unset_or_zero(env: dict[str, str]) -> None:
    assert Notifier(env).watchdog_interval_s is None


@pytest.mark.parametrize(
    "env",
    [
        {"WATCHDOG_USEC": "-5"},
        {"WATCHDOG_USEC": "2s"},
        {"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "self"},
    ],
)
def test_malformed_watchdog_is_disabled_with_warning(
    env: dict[str, str], caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="jtc_hw.sdnotify"):
        assert Notifier(env).watchdog_interval_s is None
    assert "WATCHDOG" in caplog.text
