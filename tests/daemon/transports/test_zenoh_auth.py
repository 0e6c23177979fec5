"""The Zenoh door's credential (issue 21, point 3): commands need ``daemon.zenoh.token``.

On loopback every local user reaches the daemon's Zenoh endpoint, so the tests meet it as such a
user would: a plain Zenoh session (Zenoh's own API, nothing of ours) sends a goal, a parameter
change and a stop without the token, and with a wrong one; each is refused ``unauthorized`` and
the robot does not move (asserted on the daemon's state, not on the replies only). With the
token the same queries work; watching (hello, status, the state stream) needs none. The daemon
is a subprocess on mirror joints listening on its own loopback port (``helpers.zenoh``).
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import WAIT_S, DaemonProcess, daemon_env, next_state, traj
from helpers.zenoh import TOKEN, ZenohDaemon, session_config, started, write_config

pytest.importorskip("zenoh", reason="the Zenoh interface needs jtc_hw[zenoh]")

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

from jtc_hw.api.client import Client  # noqa: E402
from jtc_hw.api.framing import RequestError  # noqa: E402
from jtc_hw.api.zenoh_client import open_session  # noqa: E402

from conftest import ROOT  # noqa: E402

WRONG = "not the token of this daemon"


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[ZenohDaemon]:
    d = started(ZenohDaemon(tmp_path / "a", "a"))
    try:
        yield d
    finally:
        assert d.shutdown() == 0


def _query(session: Any, d: ZenohDaemon, op: str, body: dict[str, Any],
           token: str | None) -> dict[str, Any]:
    """One query as any Zenoh peer sends it; its one reply."""
    replies = list(session.get(f"{d.prefix}/rpc/{op}", payload=json.dumps(body).encode(),
                               attachment=token, timeout=WAIT_S))
    assert len(replies) == 1 and replies[0].ok is not None, replies
    return dict(json.loads(replies[0].ok.payload.to_bytes()))


def _refused(reply: dict[str, Any], op: str) -> None:
    assert reply["ok"] is False, reply
    assert reply["error"]["code"] == "unauthorized"
    message = reply["error"]["message"]
    assert op in message and "token" in message and "\n" not in message


def test_without_the_token_a_local_peer_cannot_move_reconfigure_or_stop_the_robot(
        daemon: ZenohDaemon) -> None:
    goal = traj([0.5] * 6, t=0.5)
    session = open_session(session_config(daemon.endpoint))
    watcher = Client.connect(str(daemon.socket), timeout_s=WAIT_S)  # the robot's truth
    try:
        before = _query(session, daemon, "get_parameters",
                        {"names": ["constraints.goal_time"]}, None)
        p_before = before["parameters"]["constraints.goal_time"]
        for token in (None, WRONG):
            _refused(_query(session, daemon, "send_goal", {"trajectory": goal}, token),
                     "send_goal")
            _refused(_query(session, daemon, "send_trajectory", {"trajectory": goal}, token),
                     "send_trajectory")
            _refused(_query(session, daemon, "set_parameters",
                            {"parameters": {"constraints.goal_time": p_before + 7.0}}, token),
                     "set_parameters")
        with watcher.subscribe_state() as sub:
            # A state stamped after every refusal: nothing moved, nothing runs.
            state = next_state(sub, lambda s: s["time_ns"] > 0)
            state = next_state(sub, lambda s, t=state["time_ns"]: s["time_ns"] > t)
        assert state["active_goal"] is None
        assert state["desired"]["positions"] == pytest.approx([0.0] * 6)
        assert state["actual"]["positions"] == pytest.approx([0.0] * 6)
        after = watcher.get_parameters(["constraints.goal_time"])
        assert after["parameters"]["constraints.goal_time"] == p_before

        # A stop without the token does not end an operator's goal.
        accepted = _query(session, daemon, "send_goal",
                          {"trajectory": traj([0.4] * 6, t=1.5)}, TOKEN)
        assert accepted["ok"] is True, accepted
        for token in (None, WRONG):
            _refused(_query(session, daemon, "stop", {}, token), "stop")
            _refused(_query(session, daemon, "cancel_goal",
                            {"goal_id": accepted["goal_id"]}, token), "cancel_goal")
        with watcher.subscribe_state() as sub:
            done = next_state(sub, lambda s: s["active_goal"] is None)
        assert done["actual"]["positions"] == pytest.approx([0.4] * 6, abs=0.02)  # it ran on

        # With the token the same queries work.
        changed = _query(session, daemon, "set_parameters",
                         {"parameters": {"constraints.goal_time": p_before + 7.0}}, TOKEN)
        assert changed["ok"] is True, changed
        assert watcher.get_parameters(["constraints.goal_time"])["parameters"][
            "constraints.goal_time"] == p_before + 7.0
        long = _query(session, daemon, "send_goal", {"trajectory": traj([-1.0] * 6, t=20.0)},
                      TOKEN)
        assert long["ok"] is True, long
        stopped = _query(session, daemon, "stop", {}, TOKEN)
        assert stopped["ok"] is True and stopped["stopped"] is True, stopped
        with watcher.subscribe_state() as sub:
            held = next_state(sub, lambda s: s["active_goal"] is None)
        assert held["actual"]["positions"][0] > -1.0 + 0.1  # stopped on the way

        # Watching needs no token; the refusals are counted.
        hello = _query(session, daemon, "hello", {}, None)
        assert hello["ok"] is True
        status = _query(session, daemon, "get_status", {}, None)
        assert status["zenoh"]["unauthorized"] == 10
    finally:
        watcher.close()
        session.close()
    assert "zenoh: refused rpc/send_goal with no token" in daemon.log()
    assert "zenoh: refused rpc/send_goal with a wrong token" in daemon.log()


def test_the_client_and_the_cli_pass_the_token_and_watch_without_it(
        daemon: ZenohDaemon, tmp_path: Path) -> None:
    watching = daemon.client(token=None)
    try:
        assert watching.get_status()["zenoh"]["prefix"] == daemon.prefix
        with pytest.raises(RequestError) as refused:
            watching.send_goal(traj([0.3] * 6, t=0.3))
        assert refused.value.code == "unauthorized"
    finally:
        watching.close()
    config = write_config(tmp_path / "c.json5", daemon.endpoint)
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")

    def cli(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "jtc_hw", *args, "--zenoh", daemon.prefix,
             "--zenoh-config", str(config)],
            capture_output=True, text=True, cwd=ROOT, env=daemon_env(**env), timeout=60)

    result = cli("stop")
    assert result.returncode != 0
    assert "unauthorized" in result.stderr or "token" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert cli("status").returncode == 0  # watching
    assert cli("stop", "--zenoh-token-file", str(token_file)).returncode == 0
    assert cli("stop", JTC_HW_ZENOH_TOKEN=TOKEN).returncode == 0
    client = daemon.client()
    try:
        assert client.get_status()["zenoh"]["unauthorized"] == 2  # the send_goal, the stop
    finally:
        client.close()


def test_a_zenoh_section_without_a_token_refuses_to_start(tmp_path: Path) -> None:
    d = DaemonProcess(tmp_path / "d", zenoh={"prefix": "jtc/test/open",
                                             "listen": ["tcp/127.0.0.1:0"]})
    for command in ("check", "run"):
        result = subprocess.run([sys.executable, "-m", "jtc_hw", command, str(d.config_path)],
                                capture_output=True, text=True, cwd=ROOT, env=daemon_env(),
                                timeout=60)
        assert result.returncode == 2, result
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
        assert "daemon.zenoh.token" in lines[0] and "secrets.token_hex" in lines[0]
    assert not d.socket.exists()
