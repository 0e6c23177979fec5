"""The daemon on Zenoh (``daemon.zenoh``, issue 14) end to end, on loopback.

Every daemon runs as a subprocess on simulated (mirror) joints and listens on its own
``tcp/127.0.0.1:<free port>``; every session (the daemons', the clients', ``jtc-hw fleet``'s)
has multicast scouting and gossip off and connects to the endpoints named, so nothing leaves
this machine and tests running in parallel never see each other's daemons. The clients are
the real ``Client`` over Zenoh and plain Zenoh sessions (to see the wire: the payloads are the
socket protocol's JSON).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import (
    JOINTS,
    WAIT_S,
    DaemonProcess,
    connect,
    daemon_env,
    loop_process,
    next_state,
    traj,
)
from helpers.zenoh import (
    QUIET,
    TOKEN,
    ZenohDaemon,
    free_port,
    session_config,
    started,
    write_config,
)

pytest.importorskip("zenoh", reason="the Zenoh interface needs jtc_hw[zenoh]")

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

from jtc_hw.api.calls import ClientConnectionError  # noqa: E402
from jtc_hw.api.zenoh_client import ZenohClient, open_session  # noqa: E402

from conftest import ROOT  # noqa: E402

STATE_RATE_HZ = 50.0  # make_robot_config's state_publish_rate
FLEET_BOUND_S = 2.0
"""Issue 14: a daemon killed with SIGKILL disappears from ``jtc-hw fleet`` within 2 s."""
LOADED_MARGIN_S = 1.0
"""Added to FLEET_BOUND_S when waiting: the kernel closes the killed daemon's TCP links at
once and the fleet redraws on the liveliness event, so the real delay is milliseconds; the
margin is for this shared 2-core machine, where the fleet process may not be scheduled for a
while under other engineers' test runs."""


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[ZenohDaemon]:
    d = started(ZenohDaemon(tmp_path / "a", "a"))
    try:
        yield d
    finally:
        assert d.shutdown() == 0


class Events:
    """A plain Zenoh session recording every message on ``<prefix>/events``, in order."""

    def __init__(self, d: ZenohDaemon) -> None:
        self.session = open_session(session_config(d.endpoint))
        self.cond = threading.Condition()
        self.messages: list[dict[str, Any]] = []
        self.sub = self.session.declare_subscriber(f"{d.prefix}/events", self._on)
        # A query after the declaration, on the same link: once its reply is here, the daemon
        # has the subscription, and no later event can miss it.
        assert _zenoh_reply(self.session, d, "hello", b"")["ok"]

    def _on(self, sample: Any) -> None:
        with self.cond:
            self.messages.append(json.loads(sample.payload.to_bytes()))
            self.cond.notify_all()

    def wait_for(self, pred: Any, timeout_s: float = WAIT_S) -> dict[str, Any]:
        with self.cond:
            assert self.cond.wait_for(lambda: any(pred(m) for m in self.messages), timeout_s), (
                f"no such event within {timeout_s} s: {self.messages[-5:]}")
            return next(m for m in self.messages if pred(m))

    def of_goal(self, goal_id: int, event: str) -> list[dict[str, Any]]:
        with self.cond:
            return [m for m in self.messages
                    if m.get("goal_id") == goal_id and m.get("event") == event]

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def _result(goal_id: int) -> Any:
    return lambda m: m.get("event") == "result" and m.get("goal_id") == goal_id


# -- goals ------------------------------------------------------------------------------------


def test_goal_accepted_with_feedback_and_exactly_one_result(daemon: ZenohDaemon) -> None:
    events = Events(daemon)
    client = daemon.client()
    try:
        assert isinstance(client, ZenohClient)
        assert client.joint_names == JOINTS
        goal = client.send_goal(traj([0.2] * 6, t=0.6))
        result = goal.wait(timeout_s=WAIT_S)
        assert result["status"] == "succeeded", result
        feedback = list(goal.feedback(timeout_s=0.0))
        assert feedback and all(f["goal_id"] == goal.goal_id for f in feedback)
        # A second goal's result is published after any straggler of the first on the same
        # key (one publisher, in order): once it is here, a duplicate would be too.
        second = client.send_goal(traj([0.0] * 6, t=0.3))
        assert second.goal_id != goal.goal_id
        assert second.wait(timeout_s=WAIT_S)["status"] == "succeeded"
        events.wait_for(_result(second.goal_id))
        results = events.of_goal(goal.goal_id, "result")
        assert len(results) == 1 and results[0] == result
        assert events.of_goal(goal.goal_id, "feedback")
    finally:
        client.close()
        events.close()


def test_cancel_and_stop(daemon: ZenohDaemon) -> None:
    client = daemon.client()
    try:
        goal = client.send_goal(traj([1.0] * 6, t=20.0))
        reply = client.cancel(goal.goal_id)
        assert reply["canceling"] is True and reply["goal_id"] == goal.goal_id
        assert goal.wait(timeout_s=WAIT_S)["status"] == "canceled"

        goal = client.send_goal(traj([-1.0] * 6, t=20.0))
        next(iter(goal.feedback(timeout_s=WAIT_S)))  # executing
        assert client.stop()["stopped"] is True
        assert goal.wait(timeout_s=WAIT_S)["status"] == "canceled"
        with client.subscribe_state() as sub:
            state = next_state(sub, lambda s: s["active_goal"] is None)
        assert state["holding"]
    finally:
        client.close()


def test_state_stream_arrives_at_its_rate(daemon: ZenohDaemon) -> None:
    client = daemon.client()
    try:
        with client.subscribe_state() as sub:
            states = [sub.get(timeout_s=WAIT_S) for _ in range(40)]
    finally:
        client.close()
    assert all(s["event"] == "state" and s["joint_names"] == JOINTS for s in states)
    times = [s["time_ns"] for s in states]
    assert times == sorted(times)
    gaps = sorted(b - a for a, b in zip(times, times[1:], strict=False))
    period_ns = 1e9 / STATE_RATE_HZ
    # The loop's own stamps (its deadline grid), not arrival times: the median gap is the
    # publish period.
    assert gaps[len(gaps) // 2] == pytest.approx(period_ns, rel=0.05)
    # Every state the interface had is numbered: a gap is a loss, which the daemon accounts
    # for in the next message's "dropped" (its outbox was full); none is lost unaccounted.
    for before, after in zip(states, states[1:], strict=False):
        assert after["seq"] - before["seq"] - 1 == after["dropped"], (before, after)


def test_accepted_commands_reach_a_subscription_that_asks_for_them(daemon: ZenohDaemon) -> None:
    """``subscribe_state(commands=True)`` over Zenoh gets a ``command`` event for every accepted
    command, as on the socket (what ``jtc-hw record --zenoh`` writes to joint_trajectory);
    a plain subscription gets states only."""
    client = daemon.client()
    try:
        with client.subscribe_state(commands=True) as sub, client.subscribe_state() as plain:
            goal = client.send_goal(traj([0.3] * 6, t=0.3))
            command = next(m for m in iter(lambda: sub.get(timeout_s=WAIT_S), None)
                           if m["event"] == "command")
            assert goal.wait(timeout_s=WAIT_S)["status"] == "succeeded"
            assert command["goal_id"] == goal.goal_id
            assert command["trajectory"]["joint_names"] == JOINTS
            assert command["trajectory"]["points"][-1]["positions"] == [0.3] * 6
            # The plain subscription, read up to a state stamped after the command: no command.
            seen = [plain.get(timeout_s=WAIT_S)]
            while seen[-1]["event"] != "state" or seen[-1]["time_ns"] <= command["time_ns"]:
                seen.append(plain.get(timeout_s=WAIT_S))
            assert all(m["event"] == "state" for m in seen)
    finally:
        client.close()


def test_status_counts_the_zenoh_queries_on_the_socket_and_in_the_table(
    daemon: ZenohDaemon,
) -> None:
    """``get_status`` (any transport) carries the Zenoh interface's counters, and ``jtc-hw
    status`` prints them: queries answered grow with each query over Zenoh."""
    remote = daemon.client()
    try:
        remote.get_status()
        remote.get_status()
    finally:
        remote.close()
    with connect(daemon) as local:
        zenoh = local.get_status()["zenoh"]
    assert zenoh["prefix"] == daemon.prefix
    assert zenoh["queries"] >= 3  # hello and the two get_status, over Zenoh
    assert zenoh["busy"] == 0 and zenoh["lost"] == 0
    table = subprocess.run(
        [sys.executable, "-m", "jtc_hw", "status", "--socket", str(daemon.socket)],
        capture_output=True, text=True, timeout=60, env=daemon_env(), check=True).stdout
    line = next(x for x in table.splitlines() if x.startswith("zenoh"))
    assert daemon.prefix in line and "queries" in line, table


def test_a_vanished_clients_goal_still_gets_its_one_result(daemon: ZenohDaemon) -> None:
    events = Events(daemon)
    client = daemon.client()
    try:
        goal_id = client.send_goal(traj([0.1] * 6, t=0.4)).goal_id
    finally:
        client.close()  # before the goal ends: nobody waits on it at the daemon
    try:
        result = events.wait_for(_result(goal_id))
        assert result["status"] == "succeeded"
        after = daemon.client()
        try:  # the next goal's result comes after any duplicate of the first (in order)
            assert after.send_goal(traj([0.0] * 6, t=0.2)).wait(WAIT_S)["status"] == "succeeded"
        finally:
            after.close()
        assert len(events.of_goal(goal_id, "result")) == 1
    finally:
        events.close()


def test_daemon_stopping_gives_the_goal_its_result_then_goes_away(tmp_path: Path) -> None:
    d = started(ZenohDaemon(tmp_path / "d", "d"))
    client = d.client()
    try:
        goal = client.send_goal(traj([1.0] * 6, t=30.0))
        next(iter(goal.feedback(timeout_s=WAIT_S)))
        d.proc.send_signal(signal.SIGTERM) if d.proc is not None else None
        # The loop ends the goal before the Zenoh session closes: the result is published.
        assert goal.wait(timeout_s=WAIT_S)["status"] in ("canceled", "aborted")
        lost: ClientConnectionError | None = None
        deadline = time.monotonic() + WAIT_S
        while lost is None and time.monotonic() < deadline:  # until the token goes
            try:
                client.get_status(timeout_s=1.0)
            except ClientConnectionError as exc:
                lost = exc
            except TimeoutError:
                pass  # the queryable went first: no reply, the token's withdrawal follows
            time.sleep(0.05)  # polling a remote daemon's exit; no event to wait on here
        assert lost is not None and "went away" in str(lost)
    finally:
        client.close()
        assert d.wait_exit() == 0


def test_a_fault_and_its_rearm_are_published_on_events(daemon: ZenohDaemon) -> None:
    events = Events(daemon)
    client = daemon.client()
    try:
        client.sim("arm", fault="injected read fault")
        fault = events.wait_for(lambda m: m.get("event") == "fault" and m["fault"])
        assert "injected read fault" in fault["fault"]
        assert client.rearm()["rearmed"] is True
        cleared = events.wait_for(lambda m: m.get("event") == "fault" and m["fault"] is None)
        assert cleared["time_ns"] > fault["time_ns"]
    finally:
        client.close()
        events.close()


def test_the_loop_process_never_loads_zenoh(daemon: ZenohDaemon) -> None:
    """The robot file names a Zenoh configuration file (``ZenohDaemon``): the API process
    reads it with eclipse-zenoh; the loop process, which loads the same robot file, must not
    (the library starts a thread, and the loop process has none)."""
    library = f"{os.sep}zenoh{os.sep}zenoh."  # site-packages/zenoh/zenoh.abi3.so

    def maps(pid: int) -> str:
        return Path(f"/proc/{pid}/maps").read_text()

    assert library in maps(daemon.pid)  # the check below can see the library
    assert library not in maps(loop_process(daemon))


# -- errors -----------------------------------------------------------------------------------


def _socket_reply(d: ZenohDaemon, line: bytes) -> dict[str, Any]:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(WAIT_S)
        s.connect(str(d.socket))
        s.sendall(line + b"\n")
        data = b""
        while not data.endswith(b"\n"):
            chunk = s.recv(65536)
            assert chunk, "the daemon closed the socket"
            data += chunk
    return dict(json.loads(data.splitlines()[0]))


def _zenoh_reply(session: Any, d: ZenohDaemon, op: str, body: bytes) -> dict[str, Any]:
    replies = list(session.get(f"{d.prefix}/rpc/{op}", payload=body, attachment=TOKEN,
                               timeout=WAIT_S))
    assert len(replies) == 1 and replies[0].ok is not None, replies
    assert str(replies[0].ok.key_expr) == f"{d.prefix}/rpc/{op}"
    return dict(json.loads(replies[0].ok.payload.to_bytes()))


@pytest.mark.parametrize(("op", "body"), [
    ("send_goal", b'{"id": 7, "trajectory": 3}'),
    ("send_goal", b'{"id": 8, "trajectory": {"joint_names": ["nope"], "points": []}}'),
    ("send_goal", b'{"id": 9, "trajectory": {"joint_names": ["joint1"]}, "extra": 1}'),
    ("cancel_goal", b'{"goal_id": "x"}'),
    ("cancel_goal", b'{"goal_id": 12345}'),
    ("query_state", b'{"in": 0.1, "time_ns": 5}'),
    ("send_goal", b'{"trajectory": {'),
    ("get_status", b"[1, 2]"),
    ("frobnicate", b"{}"),
])
def test_malformed_request_gets_the_sockets_error(daemon: ZenohDaemon, op: str,
                                                  body: bytes) -> None:
    session = open_session(session_config(daemon.endpoint))
    try:
        got = _zenoh_reply(session, daemon, op, body)
    finally:
        session.close()
    try:
        obj = json.loads(body)
    except ValueError:
        line = body  # unreadable either way: the same bytes
    else:
        line = json.dumps({**obj, "op": op}).encode() if isinstance(obj, dict) else body
    assert got["ok"] is False
    assert got == _socket_reply(daemon, line)


def test_op_in_the_body_must_match_the_key(daemon: ZenohDaemon) -> None:
    session = open_session(session_config(daemon.endpoint))
    try:
        got = _zenoh_reply(session, daemon, "get_status", b'{"id": 1, "op": "stop"}')
        moving = _zenoh_reply(session, daemon, "subscribe_state", b"")
    finally:
        session.close()
    assert got["ok"] is False and got["error"]["code"] == "bad_request"
    assert "rpc/get_status" in got["error"]["message"] and "'stop'" in got["error"]["message"]
    assert moving["error"]["code"] == "bad_request"
    assert "<prefix>/state" in moving["error"]["message"]


# -- fleet ------------------------------------------------------------------------------------


def _fleet(config: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "fleet", "--zenoh-config", str(config), "--json",
         *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=daemon_env())


def test_two_daemons_listed_and_driven_independently(tmp_path: Path) -> None:
    a = started(ZenohDaemon(tmp_path / "a", "a"))
    b = started(ZenohDaemon(tmp_path / "b", "b"))
    try:
        config = write_config(tmp_path / "fleet.json5", a.endpoint, b.endpoint)
        fleet = _fleet(config)
        out, err = fleet.communicate(timeout=30)
        assert fleet.returncode == 0, err
        rows = {r["prefix"]: r for r in map(json.loads, out.splitlines())}
        assert set(rows) == {a.prefix, b.prefix}, out
        for row in rows.values():
            assert row["joints"] == 6 and row["loop_hz"] == 500.0 and row["fault"] is None

        ca, cb = a.client(), b.client()
        try:
            with cb.subscribe_state() as sub_b:
                goal = ca.send_goal(traj([0.3] * 6, t=0.5))
                assert goal.wait(timeout_s=WAIT_S)["status"] == "succeeded"
                state_b = next_state(sub_b, lambda s: s["time_ns"] > goal.result["time_ns"])
            assert state_b["active_goal"] is None
            assert state_b["actual"]["positions"] == pytest.approx([0.0] * 6)
            assert state_b["desired"]["positions"] == pytest.approx([0.0] * 6)
            assert ca.query_state(in_s=0.0)["positions"] == pytest.approx([0.3] * 6)
            assert cb.query_state(in_s=0.0)["positions"] == pytest.approx([0.0] * 6)
            # The CLI's --zenoh reaches the one named.
            cli = subprocess.run(
                [sys.executable, "-m", "jtc_hw", "stop", "--zenoh", b.prefix,
                 "--zenoh-config", str(write_config(tmp_path / "b.json5", b.endpoint))],
                capture_output=True, text=True, cwd=ROOT,
                env=daemon_env(JTC_HW_ZENOH_TOKEN=TOKEN), timeout=30)
            assert cli.returncode == 0, cli.stderr
        finally:
            ca.close()
            cb.close()
    finally:
        assert a.shutdown() == 0
        assert b.shutdown() == 0


def test_sigkilled_daemon_disappears_from_the_fleet(tmp_path: Path) -> None:
    a = started(ZenohDaemon(tmp_path / "a", "a"))
    b = started(ZenohDaemon(tmp_path / "b", "b"))
    fleet = _fleet(write_config(tmp_path / "fleet.json5", a.endpoint, b.endpoint), "--watch",
                   "--interval", "0.2")
    lines: list[dict[str, Any]] = []
    cond = threading.Condition()

    def read() -> None:
        assert fleet.stdout is not None
        for line in fleet.stdout:
            with cond:
                lines.append(json.loads(line))
                cond.notify_all()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()

    def wait_listed(prefixes: set[str], timeout_s: float, after: int = 0) -> int:
        """Index of the first redraw (from ``after``) listing exactly ``prefixes``."""
        def found() -> int | None:
            return next((i for i, m in enumerate(lines) if i >= after and {
                r["prefix"] for r in m["robots"]} == prefixes), None)
        with cond:
            assert cond.wait_for(lambda: found() is not None, timeout_s), (
                f"fleet never listed {prefixes} within {timeout_s} s: {lines[-3:]}")
            index = found()
            assert index is not None
            return index

    try:
        seen = wait_listed({a.prefix, b.prefix}, WAIT_S)
        os.kill(a.pid, signal.SIGKILL)  # the API process, holder of the Zenoh session
        with cond:
            after = len(lines)
        wait_listed({b.prefix}, FLEET_BOUND_S + LOADED_MARGIN_S, after=max(after, seen + 1))
    finally:
        fleet.send_signal(signal.SIGINT)
        try:
            fleet.wait(timeout=10)
        except subprocess.TimeoutExpired:
            fleet.kill()
            fleet.wait()
        reader.join(timeout=10)
        for pipe in (fleet.stdout, fleet.stderr):
            if pipe is not None:
                pipe.close()
        a.proc.wait(timeout=10) if a.proc is not None else None
        if a.leftovers(timeout_s=WAIT_S):
            os.killpg(a.pid, signal.SIGKILL)
        assert b.shutdown() == 0


# -- security ---------------------------------------------------------------------------------


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "jtc_hw", *args], capture_output=True,
                          text=True, cwd=ROOT, env=daemon_env(), timeout=60)


def test_non_loopback_listen_without_tls_or_auth_refuses_to_start(tmp_path: Path) -> None:
    d = DaemonProcess(tmp_path / "d", zenoh={"prefix": "jtc/test/open", "token": TOKEN,
                                             "listen": [f"tcp/0.0.0.0:{free_port()}"]})
    for command in ("check", "run"):
        result = _run(command, str(d.config_path))
        assert result.returncode == 2, result
        assert "daemon.zenoh.listen" in result.stderr
        assert "neither TLS nor authentication" in result.stderr
        assert "transport.auth.usrpwd" in result.stderr and "listen_certificate" in result.stderr
        assert "Traceback" not in result.stderr
    assert not d.socket.exists()

    # The same endpoint with user/password authentication in the Zenoh configuration file.
    auth = tmp_path / "auth.json5"
    auth.write_text(json.dumps({**QUIET, "transport": {"auth": {"usrpwd": {
        "user": "robot", "password": "a long secret", "dictionary_file": None}}}}))
    secured = DaemonProcess(tmp_path / "s", zenoh={
        "prefix": "jtc/test/secured", "listen": [f"tcp/0.0.0.0:{free_port()}"], "token": TOKEN,
        "config": str(auth)})
    result = _run("check", str(secured.config_path))
    assert result.returncode == 0, result.stderr
    assert "jtc/test/secured" in result.stdout
