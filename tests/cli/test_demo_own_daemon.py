"""``jtc-hw demo --config`` moves only the daemon it starts (issue 22, point 1).

A daemon already running on a configuration (``jtc-hw run``, a subprocess) is never sent the
demo's wave: the demo refuses the configuration before it starts anything (the socket's lock is
held), and where nothing tells it beforehand (a process listening on the path without the
lock), its client checks the listener's pid (``SO_PEERCRED``) before its first request. Both
end with one error line and exit 2, as ``demo --help`` documents.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers.daemon import WAIT_S, DaemonProcess, daemon_env, robot_config

from jtc_hw.api.calls import NOT_EXPECTED, ClientConnectionError
from jtc_hw.api.client import Client

from conftest import ROOT

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

DEMO_TIMEOUT_S = 120.0  # an upper bound on waiting for the demo, never a claim of speed


def jtc_hw(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "jtc_hw", *args],
        capture_output=True, text=True, cwd=cwd, timeout=DEMO_TIMEOUT_S,
        env=daemon_env(XDG_STATE_HOME=str(cwd / "state")), stdin=subprocess.DEVNULL,
    )


@pytest.fixture(scope="module")
def running(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    """A daemon serving its configuration, as ``jtc-hw run`` would."""
    d = DaemonProcess(tmp_path_factory.mktemp("served"))
    with d.serving():
        yield d


def counters(d: DaemonProcess) -> dict[str, Any]:
    """What moves when a client sends a goal: the reference (bumped by every accepted
    command), the active goal, and the connections the daemon has ever accepted (this one
    included)."""
    deadline = time.monotonic() + WAIT_S
    with Client.connect(d.socket, timeout_s=WAIT_S) as client:
        status = client.get_status()
        # The loop's part of the status comes with its first report (2 Hz): until then the
        # status has no "controller". Asked again on the same connection, so the count of
        # connections moves by one per call.
        while "controller" not in status:
            assert time.monotonic() < deadline, f"no controller status within {WAIT_S} s"
            time.sleep(0.05)  # polling the daemon's 2 Hz status report; nothing to block on
            status = client.get_status()
    controller = status["controller"]
    return {
        "reference_version": controller["reference_version"],
        "active_goal": controller["active_goal"],
        "connections_total": status["server"]["connections_total"],
    }


def test_demo_refuses_a_config_whose_socket_a_running_daemon_serves(
    running: DaemonProcess,
) -> None:
    before = counters(running)
    done = jtc_hw("demo", "--config", str(running.config_path), cwd=running.config_path.parent)
    assert done.returncode == 2, done.stdout + done.stderr
    # One line, naming the daemon that serves it; nothing was started, so nothing else.
    (line,) = done.stderr.splitlines()
    assert line.startswith(f"error: jtc-hw demo --config {running.config_path} sends nothing: ")
    assert f"{running.socket} is already served by pid {running.pid}" in line
    assert "Traceback" not in done.stderr and "starting the daemon" not in done.stdout
    after = counters(running)
    # No goal, no command, and no connection but the two counters() made.
    assert after == {**before, "connections_total": before["connections_total"] + 1}
    assert before["active_goal"] is None
    assert "accepted" not in running.log()


def test_demo_help_documents_the_refusal() -> None:
    done = jtc_hw("demo", "--help")
    assert done.returncode == 0
    text = " ".join(done.stdout.split())
    assert "2 bad configuration, or --config's socket is already served by a running daemon" in (
        text
    )


class Stranger:
    """A process (this one) listening on a socket path without the daemon's lock, so the lock
    check before the start cannot see it; it accepts every connection and sends nothing."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(str(path))
        self._listener.listen(8)
        self._conns: list[socket.socket] = []
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return  # closed
            self._conns.append(conn)

    def close(self) -> bytes:
        """Stop listening; every byte the clients sent (call once they have exited: what they
        sent is then buffered, followed by end of file)."""
        self._listener.shutdown(socket.SHUT_RDWR)
        self._listener.close()
        self._thread.join(WAIT_S)
        received = b""
        for conn in self._conns:
            conn.settimeout(WAIT_S)
            while chunk := conn.recv(65536):
                received += chunk
            conn.close()
        self._conns.clear()
        return received


@pytest.fixture
def stranger(tmp_path: Path) -> Iterator[Stranger]:
    s = Stranger(tmp_path / "s.sock")
    try:
        yield s
    finally:
        if s._conns or s._thread.is_alive():
            s.close()


def test_demo_sends_nothing_to_a_socket_another_process_serves(
    tmp_path: Path, stranger: Stranger,
) -> None:
    config = tmp_path / "robot.yaml"
    config.write_text(yaml.safe_dump(robot_config(stranger.path), sort_keys=False))
    done = jtc_hw("demo", "--config", str(config), cwd=tmp_path)
    received = stranger.close()
    assert done.returncode == 2, done.stdout + done.stderr
    last = done.stderr.splitlines()[-1]
    assert last.startswith(f"error: jtc-hw demo --config {config} sends nothing: "), done.stderr
    assert f"{stranger.path} is served by pid {os.getpid()}, not by the expected pid" in last
    assert "Traceback" not in done.stderr and "accepted" not in done.stdout
    # The check on the listener's pid comes before any request: not even a hello.
    assert received == b""


def test_client_checks_the_listener_pid_before_any_request(running: DaemonProcess) -> None:
    before = counters(running)
    with pytest.raises(ClientConnectionError) as refused:
        Client.connect(running.socket, timeout_s=WAIT_S, expect_pid=running.pid + 1)
    assert refused.value.code == NOT_EXPECTED
    assert f"is served by pid {running.pid}, not by the expected pid {running.pid + 1}" in str(
        refused.value
    )
    with Client.connect(running.socket, timeout_s=WAIT_S, expect_pid=running.pid) as client:
        assert client.joint_names  # the hello went through: the expected daemon
    after = counters(running)
    # The refused connection sent nothing: the daemon saw it open and close, no request.
    assert after["connections_total"] == before["connections_total"] + 3
    assert running.wait_log("closed by the client (0 requests")
