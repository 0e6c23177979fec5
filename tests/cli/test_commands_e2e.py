"""``jtc-hw`` as a user runs it, against the demo's daemon (a subprocess): every goal file in
``examples/`` succeeds, exit codes say who answered, ``state``/``status`` print what they
promise, and a closed pipe ends ``state`` quietly."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers.daemon import ConfiguredDaemon, DaemonProcess, daemon_env

from jtc_hw.cli.demo import demo_config

from conftest import ROOT

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

EXAMPLES = sorted((ROOT / "examples").glob("*.*"))
JOINTS = [f"joint{i}" for i in range(1, 7)]


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    """The daemon ``jtc-hw demo`` starts (its configuration, simulated joints)."""
    d = ConfiguredDaemon(tmp_path_factory.mktemp("cli"), lambda sock: demo_config(str(sock)))
    with d.serving():
        yield d


def jtc_hw(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "jtc_hw", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=daemon_env(),
        timeout=60,
        stdin=subprocess.DEVNULL,
    )


def test_examples_hold_each_goal_format() -> None:
    names = {p.name for p in EXAMPLES}
    assert {"joint_trajectory_echo.yaml", "follow_joint_trajectory_goal.yaml", "goal.yaml",
            "goal.json", "goal.csv"} <= names


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_every_example_goal_succeeds_on_the_demo(demo: DaemonProcess, path: Path) -> None:
    sent = jtc_hw("send", str(path), "--socket", str(demo.socket), "--quiet")
    assert sent.returncode == 0, (sent.stdout, sent.stderr, demo.log())
    assert "succeeded (error_code 0)" in sent.stdout
    assert sent.stderr == ""


def test_exit_codes_say_who_answered(demo: DaemonProcess, tmp_path: Path) -> None:
    # Rejected by the daemon (a joint it does not have): 2.
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text(
        "joint_names: [elbow]\npoints: [{time_from_start: 1, positions: [0.1]}]\n"
    )
    rejected = jtc_hw("send", str(unknown), "--socket", str(demo.socket))
    assert rejected.returncode == 2, (rejected.stdout, rejected.stderr)
    assert "rejected" in rejected.stderr and "Traceback" not in rejected.stderr
    # A request the daemon refuses as malformed (a tolerance without a name): 2, it answered.
    malformed = tmp_path / "malformed.yaml"
    malformed.write_text(
        "trajectory: {joint_names: [joint1], points: [{time_from_start: 1, positions: [0.1]}]}\n"
        "goal_tolerance: [{position: 0.1}]\n"
    )
    bad = jtc_hw("send", str(malformed), "--socket", str(demo.socket))
    assert bad.returncode == 2, (bad.stdout, bad.stderr)
    assert "goal_tolerance[0]" in bad.stderr and "Traceback" not in bad.stderr
    # A goal id it does not know (the daemon answered "not executing"): 2, it refused.
    cancel = jtc_hw("cancel", "12345", "--socket", str(demo.socket))
    assert cancel.returncode == 2 and "goal 12345 is not executing" in cancel.stderr
    # Nobody at the socket: 3, and only then.
    nobody = jtc_hw("state", "--socket", str(tmp_path / "nobody.sock"))
    assert nobody.returncode == 3 and "cannot reach a jtc-hw daemon" in nobody.stderr
    assert nobody.stderr.count("running") == 1 and "Traceback" not in nobody.stderr


def test_state_header_shows_wall_time_and_json_streams_ndjson(demo: DaemonProcess) -> None:
    table = jtc_hw("state", "--socket", str(demo.socket))
    assert table.returncode == 0, table.stderr
    header = table.stdout.splitlines()[0].split()
    assert header[:5] == ["joint", "desired", "actual", "error", "velocity"]
    # date and time of this machine: YYYY-MM-DD HH:MM:SS.mmm
    assert len(header) == 7 and header[5].count("-") == 2 and header[6].count(":") == 2

    watch = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "state", "--watch", "--json",
         "--socket", str(demo.socket)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=daemon_env(),
    )
    try:
        assert watch.stdout is not None
        lines = [watch.stdout.readline() for _ in range(3)]
    finally:
        watch.terminate()
        watch.communicate(timeout=30)
    messages = [json.loads(line) for line in lines]
    assert [m["event"] for m in messages] == ["state"] * 3
    assert all(m["joint_names"] == JOINTS for m in messages)
    assert messages[0]["time_ns"] < messages[1]["time_ns"] < messages[2]["time_ns"]


def test_state_into_a_closed_pipe_exits_quietly(demo: DaemonProcess) -> None:
    """``jtc-hw state --watch | head -1``: the reader leaves; state ends with 0, no traceback."""
    state = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "state", "--watch", "--socket", str(demo.socket)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, env=daemon_env(),
    )
    assert state.stdout is not None and state.stderr is not None
    assert state.stdout.readline().startswith(b"joint ")
    state.stdout.close()  # what head does after its line
    err = state.stderr.read()
    assert state.wait(timeout=30) == 0, err
    state.stderr.close()
    assert err == b""


def test_state_piped_to_head_in_a_shell_exits_zero(demo: DaemonProcess) -> None:
    shell = subprocess.run(
        ["bash", "-o", "pipefail", "-c",
         f"{sys.executable} -m jtc_hw state --socket {demo.socket} | head -1"],
        capture_output=True, text=True, cwd=ROOT, env=daemon_env(), timeout=60,
    )
    assert shell.returncode == 0, shell.stderr
    assert shell.stdout.startswith("joint ") and "Traceback" not in shell.stderr


def test_status_is_a_table_and_json_is_the_reply_without_its_wrapper(
    demo: DaemonProcess,
) -> None:
    table = jtc_hw("status", "--socket", str(demo.socket))
    assert table.returncode == 0, table.stderr
    lines = table.stdout.splitlines()
    assert lines[0].startswith("daemon        jtc-hw ")
    assert any(line.startswith("controller    active, ") for line in lines)
    assert any(line.startswith("loop          500 Hz, ") for line in lines)
    assert any(line.startswith("  arm         mirror, active, joints joint1") for line in lines)
    assert "{" not in table.stdout  # not the raw reply
    raw = jtc_hw("status", "--json", "--socket", str(demo.socket))
    reply = json.loads(raw.stdout)
    assert "id" not in reply and "ok" not in reply
    assert reply["controller"]["active"] is True and reply["loop"]["rate_hz"] == 500.0
