"""Fail-safe, end to end (issue 10): the daemon as a subprocess, signals sent to its processes.

- SIGSTOP of the API process: the loop keeps cycling (its own statistics count the cycles it
  ran with messages waiting), ends the goal ABORTED naming the stall, and serves again after
  SIGCONT.
- SIGKILL of the loop process: the client gets exactly one ABORTED result, the daemon exits
  non-zero.
- A second daemon on the same device or socket exits with "already driven / served by pid N
  (config)" and never configures its hardware (a test kind journals every lifecycle step,
  loaded through the real entry-point group).

Waits are on conditions (a log line, a message, the daemon's own clock) with deadlines; the
one deliberate wait is how long the API process stays stopped, the scenario itself.
Assertions are about counts and messages, never about how long something took.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers.daemon import (
    JOINTS,
    MS,
    WAIT_S,
    DaemonProcess,
    RecordingClient,
    connect,
    daemon_env,
    settle,
    traj,
)
from helpers.recording_hardware import component, install_entry_point, journal_lines

from conftest import ROOT, make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")

RATE = 500  # helpers.daemon.robot_config
API_STALL_S = 0.5
STOP_S = 3.0  # how long the API process stays stopped (the scenario)


@pytest.fixture
def started(tmp_path: Path) -> Iterator[list[DaemonProcess]]:
    """Daemons a test starts; each is stopped (and checked for leftovers) afterwards."""
    daemons: list[DaemonProcess] = []
    yield daemons
    for d in daemons:
        if d.proc is not None:
            d.shutdown()


def one_result(client: RecordingClient, goal_id: int) -> dict[str, Any]:
    results = client.received("result", goal_id)
    assert len(results) == 1, f"goal {goal_id}: {len(results)} results: {results}"
    return results[0]


# -- the API process stops reading -------------------------------------------------------------


def test_sigstop_of_the_api_process_ends_the_goal_and_the_loop_keeps_cycling(
    tmp_path: Path, started: list[DaemonProcess]
) -> None:
    d = DaemonProcess(tmp_path / "d", api_stall_s=API_STALL_S)
    started.append(d)
    d.start()
    d.wait_ready()
    client = connect(d)
    with client, client.subscribe_state() as sub:
        goal = client.send_goal(traj([0.8] * 6, 20.0))
        next(goal.feedback(timeout_s=WAIT_S))  # executing
        settle(sub, client.hello()["now_ns"] + 600 * MS)  # a status of the moving goal
        before = client.get_status()["loop"]
        assert before["api_stalls"] == 0 and before["api_stalled"] is False

        os.kill(d.pid, signal.SIGSTOP)
        stopped_at = time.monotonic()
        try:
            # The loop, which the stop does not concern, says so on its own stderr.
            line = d.wait_log("has not read the control loop's messages")
            time.sleep(max(0.0, STOP_S - (time.monotonic() - stopped_at)))
        finally:
            os.kill(d.pid, signal.SIGCONT)
        assert f"daemon.api_stall_s: {API_STALL_S:g} s" in line

        result = goal.wait(timeout_s=WAIT_S)
        assert (result["status"], result["error_code"]) == ("aborted", -1), result
        assert "the daemon's API process has not read the control loop's messages" in (
            result["error_string"]
        )
        assert result["error_string"].endswith(": holding position")
        # The statistics the loop publishes after it caught up (2 Hz, daemon time).
        settle(sub, client.hello()["now_ns"] + 600 * MS)
        after = client.get_status()["loop"]
        assert after["api_stalls"] == 1 and after["api_stalled"] is False
        cycles = after["cycles"] - before["cycles"]
        # It ran, with messages waiting, for at least the stall bound (a loop blocked in a
        # send would not have flushed again): at least half of api_stall_s worth of cycles,
        # leaving room for deadlines a busy machine makes it skip.
        waiting = after["outbox"]["full_flushes"] - before["outbox"]["full_flushes"]
        assert waiting >= API_STALL_S * RATE / 2, (waiting, after["outbox"])
        # The States of the stop went by in the cycle ring (it keeps the newest 16): not
        # delivered late as if new.
        assert client.get_status()["states_lost"] >= STOP_S * 50 - 2 * 16
        # No deadline was missed because of the stall: a blocked loop skips every deadline
        # while it waits. (Tolerant of the shared machine's own noise.)
        overruns = after["overruns"] - before["overruns"]
        assert overruns < cycles / 4, (overruns, cycles)

        # Serving resumes: a new goal runs to success.
        status = client.get_status()["controller"]
        assert status["active"] is True and status["fault"] is None
        back = client.send_goal(traj([0.0] * 6, 0.5)).wait(timeout_s=WAIT_S)
        assert back["status"] == "succeeded", back
    one_result(client, goal.goal_id)
    assert d.shutdown() == 0


# -- the loop process dies ---------------------------------------------------------------------


def test_sigkill_of_the_loop_gives_one_aborted_result_and_the_daemon_exits_nonzero(
    tmp_path: Path, started: list[DaemonProcess]
) -> None:
    d = DaemonProcess(tmp_path / "d")
    started.append(d)
    d.start()
    d.wait_ready()
    client, watcher = connect(d), connect(d)
    with client, watcher:
        goal = client.send_goal(traj([0.8] * 6, 20.0))
        next(goal.feedback(timeout_s=WAIT_S))
        loop_pid = client.get_status()["loop_pid"]
        assert isinstance(loop_pid, int) and loop_pid != d.pid
        os.kill(loop_pid, signal.SIGKILL)
        result = goal.wait(timeout_s=WAIT_S)
        assert (result["status"], result["error_code"]) == ("aborted", -1), result
        assert result["error_string"] == "control loop died: killed by SIGKILL"
        assert d.wait_exit() == 1
    one_result(client, goal.goal_id)
    assert watcher.received("result") == []  # the result went to its goal's client only
    log = d.log()
    assert "control loop died: killed by SIGKILL" in log
    assert "the service manager restarts the daemon" in log
    assert "Traceback" not in log
    assert not d.socket.exists()
    assert d.leftovers() == {}


# -- one daemon per hardware -------------------------------------------------------------------


class RecordingDaemon(DaemonProcess):
    """A daemon whose one component is the journaling test kind on ``device``."""

    def __init__(self, directory: Path, device: str, journal: Path, socket: Path | None = None
                 ) -> None:
        super().__init__(directory)
        if socket is not None:
            self.socket = socket
        config = make_robot_config(self.socket, JOINTS, [component(device, journal, JOINTS)])
        self.config_path.write_text(yaml.safe_dump(config, sort_keys=False))


@pytest.fixture
def kind_env(tmp_path: Path) -> dict[str, str]:
    """The daemon's environment with the test kind's entry point on its path."""
    site = install_entry_point(tmp_path / "site")
    return daemon_env(PYTHONPATH=os.pathsep.join([str(site), str(ROOT / "tests"), str(ROOT)]))


def test_a_second_daemon_on_the_same_device_exits_before_touching_it(
    tmp_path: Path, started: list[DaemonProcess], kind_env: dict[str, str]
) -> None:
    device = f"test:{tmp_path.name}:{os.getpid()}"  # unique: tests run in parallel
    journal = tmp_path / "journal"
    first = RecordingDaemon(tmp_path / "first", device, journal)
    started.append(first)
    first.start(kind_env)
    first.wait_ready()
    steps = journal_lines(journal)
    assert [s.split()[0] for s in steps] == ["configure", "activate"]

    second = RecordingDaemon(tmp_path / "second", device, journal)  # another socket
    started.append(second)
    second.start(kind_env)
    assert second.wait_exit() == 2
    assert journal_lines(journal) == steps  # never configured, nothing sent
    log = second.log()
    expected = f"{device} is already driven by pid {first.pid} ({first.config_path})"
    assert f"cannot start: {expected}" in log, log
    assert "Traceback" not in log
    assert second.leftovers() == {}
    assert not second.socket.exists()

    # Once the first has stopped, the device is free.
    assert first.shutdown() == 0
    third = RecordingDaemon(tmp_path / "third", device, journal)
    started.append(third)
    third.start(kind_env)
    third.wait_ready()
    assert [s.split()[0] for s in journal_lines(journal)[len(steps):]] == [
        "deactivate", "cleanup", "configure", "activate",
    ]


def test_a_second_daemon_on_the_same_socket_exits_before_starting_its_loop(
    tmp_path: Path, started: list[DaemonProcess], kind_env: dict[str, str]
) -> None:
    journal = tmp_path / "journal"
    first = RecordingDaemon(tmp_path / "first", f"test:{tmp_path.name}:a", journal)
    started.append(first)
    first.start(kind_env)
    first.wait_ready()
    steps = journal_lines(journal)
    # Another device, the same socket: refused at the socket, before any loop process.
    second = RecordingDaemon(tmp_path / "second", f"test:{tmp_path.name}:b", journal,
                             socket=first.socket)
    started.append(second)
    second.start(kind_env)
    assert second.wait_exit() == 2
    assert journal_lines(journal) == steps
    log = second.log()
    assert f"cannot start: {first.socket} is already served by pid {first.pid} " in log, log
    assert f"({first.config_path})" in log
    assert "jtc_hw.loop" not in log  # no loop process was started
    assert first.accepts_connections()  # and the first daemon's socket is untouched
    assert first.shutdown() == 0
