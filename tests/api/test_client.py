"""The Python client against the real server (in a thread with its own asyncio loop) and the
stand-in backend of test_server."""

from __future__ import annotations

import os
import shutil
import socket
import tempfile
from pathlib import Path
from typing import Any

import pytest
from helpers.fake_backend import TOKEN, ServerThread

from jtc_hw import GoalRejected, JointTolerance, JointTrajectory, TrajectoryPoint
from jtc_hw.api.calls import UNTRUSTED, ClientConnectionError
from jtc_hw.api.client import Client
from jtc_hw.api.framing import RequestError
from jtc_hw.api.handles import GoalHandle
from jtc_hw.daemon.settings import DaemonSettings, TcpSettings
from jtc_hw.errors import ProtocolError

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

S = 1_000_000_000




def trajectory(positions: tuple[float, float] = (0.5, -0.5), t: float = 1.0) -> JointTrajectory:
    return JointTrajectory(["j1", "j2"], [TrajectoryPoint(t, list(positions))])


def test_connect_hello_and_close(daemon: ServerThread, sock: Path) -> None:
    with Client.connect(sock) as client:
        assert client.info["protocol_version"] == 2  # binary frames (version 2)
        assert client.joint_names == ["j1", "j2"]
        hello = client.hello()
        assert hello["now_ns"] == daemon.backend.t and hello["update_rate"] == 100.0
    with pytest.raises(ClientConnectionError, match="client was closed"):
        client.hello()
    client.close()  # idempotent


def test_goal_feedback_and_result(daemon: ServerThread, client: Client) -> None:
    seen: list[dict[str, Any]] = []
    goal = client.send_goal(
        trajectory(),
        goal_tolerance=[JointTolerance("j1", position=0.01), {"name": "j2", "position": 0.01}],
        on_feedback=seen.append,
    )
    assert isinstance(goal, GoalHandle) and not goal.done and goal.result is None
    daemon.call(daemon.backend.step, 1.5)
    result = goal.wait(timeout_s=5.0)
    assert result["status"] == "succeeded" and result["error_code"] == 0
    assert goal.done and goal.result == result
    feedback = list(goal.feedback(timeout_s=5.0))  # ends with the result
    assert feedback and all(f["goal_id"] == goal.goal_id for f in feedback)
    assert seen == feedback
    assert feedback[-1]["time_from_start"] > feedback[0]["time_from_start"]


def test_a_failing_feedback_callback_is_logged_not_fatal(
    daemon: ServerThread, client: Client, caplog: pytest.LogCaptureFixture
) -> None:
    def broken(message: dict[str, Any]) -> None:
        raise RuntimeError("oops")

    goal = client.send_goal(trajectory(), on_feedback=broken)
    daemon.call(daemon.backend.step, 1.5)
    assert goal.wait(5.0)["status"] == "succeeded"
    assert client.hello()["ok"]
    assert f"goal {goal.goal_id}: the feedback callback failed" in caplog.text


def test_goal_from_a_dict_with_start_in(daemon: ServerThread, client: Client) -> None:
    wire = {
        "joint_names": ["j1", "j2"],
        "points": [{"time_from_start": 0.5, "positions": [0.1, 0.1]}],
    }
    goal = client.send_goal(wire, start_in=0.5, goal_time_tolerance=1.0)
    state = client.query_state(in_s=0.4)
    assert state["positions"] == [0.0, 0.0]  # not started yet
    daemon.call(daemon.backend.step, 1.5)
    assert goal.wait(5.0)["status"] == "succeeded"
    with pytest.raises(ValueError, match="start_time_ns or start_in"):
        client.send_goal(wire | {"start_time_ns": 5}, start_in=1.0)


def test_rejection_raises_goal_rejected_with_code(client: Client) -> None:
    with pytest.raises(GoalRejected) as info:
        client.send_goal(JointTrajectory(["j1", "elbow"], [TrajectoryPoint(1.0, [0.0, 0.0])]))
    assert info.value.error_code == -2 and "elbow" in str(info.value)
    with pytest.raises(RequestError) as bad:
        client.send_goal({"joint_names": ["j1", "j2"], "points": [{"positions": [0, 0]}]})
    assert bad.value.code == "bad_request" and isinstance(bad.value, ProtocolError)
    assert "trajectory.points[0]: missing required field 'time_from_start'" in str(bad.value)


def test_cancel(daemon: ServerThread, client: Client) -> None:
    goal = client.send_goal(trajectory(t=5.0))
    assert goal.cancel()["canceling"] is True
    daemon.call(daemon.backend.step, 0.05)
    assert goal.wait(5.0)["status"] == "canceled"
    with pytest.raises(RequestError) as info:
        client.cancel(goal.goal_id)
    assert info.value.code == "not_found"


def test_wait_times_out_explicitly(daemon: ServerThread, client: Client) -> None:
    goal = client.send_goal(trajectory(t=5.0))
    with pytest.raises(TimeoutError, match=f"goal {goal.goal_id}: no result within 0.05 s"):
        goal.wait(timeout_s=0.05)
    with pytest.raises(TimeoutError):
        next(iter(goal.feedback(timeout_s=0.05)))


def test_query_state(daemon: ServerThread, client: Client) -> None:
    client.send_goal(trajectory((1.0, 2.0)))
    t = daemon.backend.t
    assert client.query_state(time_ns=t + 2 * S)["positions"] == [1.0, 2.0]
    assert client.query_state(in_s=0.5)["time_ns"] == t + S // 2
    with pytest.raises(ValueError):
        client.query_state(in_s=1.0, time_ns=5)
    daemon.call(daemon.backend.ctrl.deactivate, daemon.backend.t)
    with pytest.raises(RequestError) as info:
        client.query_state(in_s=0.0)
    assert info.value.code == "not_active"


def test_subscribe_state(daemon: ServerThread, client: Client) -> None:
    with client.subscribe_state(timeout_s=5.0) as states:
        for seq in range(3):
            daemon.call(daemon.backend.publish_state, seq)
        assert [next(states)["seq"] for _ in range(3)] == [0, 1, 2]
        with pytest.raises(TimeoutError):
            states.get(timeout_s=0.05)
        me = client.get_status()["server"]
        assert me["clients"][0]["subscribed"] is True
    assert client.get_status()["server"]["clients"][0]["subscribed"] is False
    assert list(states) == []  # a closed subscription iterates no more


def test_status_config_sim_and_topic(daemon: ServerThread, client: Client) -> None:
    assert client.get_status()["loop"] == {"cycles": 0}
    assert client.get_config()["controller"]["joints"] == ["j1", "j2"]
    assert client.sim("mirror", True)["frozen"] is True and daemon.backend.mirror.frozen
    with pytest.raises(RequestError) as info:
        client.sim("arm", True)
    assert info.value.code == "bad_request" and "'arm'" in str(info.value)
    assert client.send_trajectory(trajectory(), start_in=0.1)["stopping"] is False
    assert client.send_trajectory({"joint_names": [], "points": []})["stopping"] is True


def test_stop(daemon: ServerThread, client: Client) -> None:
    goal = client.send_goal(trajectory(t=5.0))
    assert daemon.call(lambda: daemon.backend.ctrl.active_goal) == goal.goal_id
    stopped = client.stop()
    assert stopped["ok"] is True and stopped["stopped"] is True and "message" not in stopped
    daemon.call(daemon.backend.step, 0.02)
    assert goal.wait(timeout_s=5.0)["status"] == "canceled"
    assert client.stop()["stopped"] is True  # holding: stopping again is harmless
    daemon.call(lambda: daemon.backend.ctrl.deactivate(daemon.backend.t, "test"))
    nothing = client.stop()
    assert nothing["stopped"] is False and "not active" in nothing["message"]


def test_tcp_with_token(tmp_path: Path) -> None:
    srv = ServerThread(DaemonSettings(socket=str(tmp_path / "d.sock"),
                                      tcp=TcpSettings("127.0.0.1", 0, TOKEN)))
    try:
        address = srv.server.tcp_address
        assert address is not None
        with Client.connect(tcp=address, token=TOKEN) as client:
            assert client.joint_names == ["j1", "j2"]
        with pytest.raises(RequestError) as info:
            Client.connect(tcp=address, token="wrong")
        assert info.value.code == "unauthorized"
        with pytest.raises(ValueError, match="token"):
            Client.connect(tcp=address)
    finally:
        srv.close()


def test_busy_and_missing_daemon(sock: Path, tmp_path: Path) -> None:
    srv = ServerThread(DaemonSettings(socket=str(sock), max_clients=1))
    try:
        # One slot and the two reserved for the daemon's user, which this test runs as.
        with Client.connect(sock), Client.connect(sock), Client.connect(sock):
            with pytest.raises(ClientConnectionError) as info:
                Client.connect(sock)
            assert info.value.code == "busy" and "max_clients" in str(info.value)
            # Over the limit, a stop sent first still gets through.
            with Client.connect(sock, hello=False) as operator:
                assert operator.stop()["stopped"] is True
                with pytest.raises(ClientConnectionError):  # served, then closed
                    operator.hello()
    finally:
        srv.close()
    with pytest.raises(ClientConnectionError, match="is the daemon running"):
        Client.connect(tmp_path / "nobody.sock")


def test_an_idle_connection_closed_by_the_daemon_says_why(sock: Path) -> None:
    srv = ServerThread(DaemonSettings(socket=str(sock), idle_timeout_s=0.2))
    try:
        client = Client.connect(sock)
        try:
            client._reader.join(10.0)  # the reader ends when the daemon closes the connection
            assert not client._reader.is_alive()
            with pytest.raises(ClientConnectionError) as info:
                client.hello()
            assert "(idle: no request for 0.2 s, no subscription and no goal running" in str(
                info.value
            )
        finally:
            client.close()
    finally:
        srv.close()


def test_default_path_from_environment(
    daemon: ServerThread, sock: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("JTC_HW_SOCKET", str(sock))
    with Client.connect() as client:
        assert client.label == str(sock)


def test_server_closing_fails_waiters(sock: Path) -> None:
    srv = ServerThread(DaemonSettings(socket=str(sock)))
    client = Client.connect(sock)
    try:
        goal = client.send_goal(trajectory(t=5.0))
        with client.subscribe_state() as states:
            srv.close()
            with pytest.raises(ClientConnectionError, match="closed the connection"):
                goal.wait(timeout_s=5.0)
            with pytest.raises(ClientConnectionError):
                states.get()
        with pytest.raises(ClientConnectionError):
            client.hello()
    finally:
        client.close()


# -- the default socket path cannot be squatted --------------------------------------------------

NOBODY = 65534
as_root = pytest.mark.skipif(
    os.geteuid() != 0, reason="makes files and processes of another user: needs root"
)


@pytest.fixture
def runtime_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The default socket's directory for this test (``$XDG_RUNTIME_DIR``), 0700."""
    directory = tmp_path / "xdg"
    directory.mkdir(0o700)
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.delenv("JTC_HW_SOCKET", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(directory))
    return directory


def test_the_default_socket_is_used_when_it_is_ours(runtime_dir: Path) -> None:
    srv = ServerThread(DaemonSettings(socket=str(runtime_dir / "jtc-hw.sock")))
    try:
        with Client.connect() as client:
            assert client.label == str(runtime_dir / "jtc-hw.sock")
            assert client.joint_names == ["j1", "j2"]
    finally:
        srv.close()


@as_root
def test_a_squatted_default_socket_is_refused(runtime_dir: Path) -> None:
    """Another user's socket at the default path: the client says why it will not use it."""
    path = runtime_dir / "jtc-hw.sock"
    srv = ServerThread(DaemonSettings(socket=str(path)))
    try:
        os.chown(path, NOBODY, -1)
        with pytest.raises(ClientConnectionError) as info:
            Client.connect()
        assert info.value.code == UNTRUSTED
        assert str(info.value) == (
            f"refusing the daemon socket {path}: the socket {path} belongs to uid {NOBODY}, "
            "not to uid 0 or root: another user may have created it to impersonate the daemon. "
            "If it is stale, remove it; if you trust that daemon, name its socket explicitly "
            "(--socket PATH, or JTC_HW_SOCKET=PATH)"
        )
        with Client.connect(path) as named:  # named explicitly: trusted as named
            assert named.joint_names == ["j1", "j2"]
        os.chown(path, 0, -1)
        os.chown(runtime_dir, NOBODY, -1)  # their directory: they could swap the socket
        with pytest.raises(ClientConnectionError, match=f"{runtime_dir} belongs to uid"):
            Client.connect()
    finally:
        os.chown(runtime_dir, 0, -1)
        srv.close()


@as_root
def test_a_default_socket_served_by_another_user_is_refused(
    runtime_dir: Path, tmp_path: Path
) -> None:
    """The file looks right (ours), but the process listening on it is not: SO_PEERCRED."""
    shared = Path(tempfile.mkdtemp(prefix="jtc-hw-client-"))  # pytest's tmp_path is private
    shared.chmod(0o711)
    theirs = shared / "theirs"
    theirs.mkdir()
    os.chown(theirs, NOBODY, -1)
    ready, release = socket.socketpair()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child, as another user; never returns
        status = 1
        try:
            ready.close()
            os.setgroups([])
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            listener = socket.socket(socket.AF_UNIX)
            listener.bind(str(theirs / "s"))
            listener.listen()
            release.sendall(b"!")
            release.recv(1)  # until the test is done
            status = 0
        finally:
            os._exit(status)
    release.close()
    try:
        assert ready.recv(1) == b"!", "the other user's listener did not start"
        path = runtime_dir / "jtc-hw.sock"
        os.rename(theirs / "s", path)
        os.chown(path, 0, -1)
        with pytest.raises(ClientConnectionError) as info:
            Client.connect()
        assert info.value.code == UNTRUSTED
        assert f"runs as uid {NOBODY}, not as uid 0 or root: it is not your daemon" in str(
            info.value
        )
    finally:
        ready.close()
        _, status = os.waitpid(pid, 0)
        shutil.rmtree(shared)
    assert os.waitstatus_to_exitcode(status) == 0
