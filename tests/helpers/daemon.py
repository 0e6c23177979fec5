"""The daemon as a subprocess, and clients of it, for end-to-end tests of every layer.

``DaemonProcess`` runs ``python -m jtc_hw run CONFIG`` in its own session and waits on
conditions (a log line, the socket accepting, the process state) with deadlines; every daemon
started is remembered so that the ``daemon_log_on_failure`` fixture (conftest) can print its log.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml

from jtc_hw.api.client import Client
from jtc_hw.api.handles import StateSubscription
from jtc_hw.daemon.loop.cycle import LOOP_PROCESS_NAME

from conftest import ROOT, make_robot_config

MS = 1_000_000


JOINTS = [f"joint{i}" for i in range(1, 7)]


PATH_TOL = 0.05


GOAL_TOL = 0.01


START_TIMEOUT_S = 30.0


STOP_TIMEOUT_S = float(os.environ.get("JTC_HW_TEST_STOP_TIMEOUT_S", "20"))
"""Bound on waiting for a daemon to exit after SIGTERM (an upper bound, never a claim of speed).
tools/vcan-hil raises it: under software emulation beside busy processes a daemon's stop, which
writes its pending flight-recorder bags, took more than 20 s."""


WAIT_S = 10.0  # generous bound on waiting for a message that should come promptly


def robot_config(
    socket_path: Path, controller: dict[str, Any] | None = None, **daemon: Any
) -> dict[str, Any]:
    """Six joints at 500 Hz on ideal simulated hardware, path and goal tolerances set;
    ``controller`` adds controller parameters."""
    hardware = [{"name": "arm", "kind": "mirror", "joints": JOINTS, "params": {"lag_s": 0.0}}]
    return make_robot_config(socket_path, JOINTS, hardware, path_tolerance=PATH_TOL,
                             goal_tolerance=GOAL_TOL, controller=controller, **daemon)


def daemon_env(**extra: str) -> dict[str, str]:
    """The test's environment without anything that changes how the daemon talks to its
    supervisor (systemd notification, journald log format), plus this checkout on the path."""
    env = dict(os.environ)
    for key in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "JOURNAL_STREAM"):
        env.pop(key, None)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    env.update(extra)
    return env


def _session_members(sid: int) -> dict[int, str]:
    """Live (non-zombie) processes of session ``sid``: pid -> command name."""
    members = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        name = stat[stat.find("(") + 1 : stat.rfind(")")]
        fields = stat[stat.rfind(")") + 2 :].split()  # state ppid pgrp session ...
        if int(fields[3]) == sid and fields[0] != "Z":
            members[int(entry)] = name
    return members


def loop_process(daemon: DaemonProcess) -> int:
    """The pid of the daemon's control-loop process (it names itself ``jtc-hw-loop``)."""
    members = _session_members(daemon.pid)
    loops = [pid for pid, name in members.items() if name == LOOP_PROCESS_NAME]
    assert len(loops) == 1, f"expected one {LOOP_PROCESS_NAME} process in {members}"
    return loops[0]


def wait_gone(pid: int, timeout_s: float = WAIT_S) -> None:
    """Until ``pid`` is dead (gone, or a zombie its parent has not reaped)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            return
        if stat[stat.rfind(")") + 2 :].split()[0] == "Z":
            return
        assert time.monotonic() < deadline, f"process {pid} still alive after {timeout_s} s"
        time.sleep(0.005)  # polling /proc for another process's end


_DAEMONS: list[DaemonProcess] = []


class DaemonProcess:
    """``python -m jtc_hw run`` in its own session, stderr to a file."""

    def __init__(
        self, directory: Path, controller: dict[str, Any] | None = None, **daemon_settings: Any
    ) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.socket = directory / "d.sock"
        assert len(os.fsencode(self.socket)) < 100, f"socket path too long: {self.socket}"
        self.config_path = directory / "robot.yaml"
        self.config_path.write_text(
            yaml.safe_dump(
                robot_config(self.socket, controller, **daemon_settings), sort_keys=False
            )
        )
        self.stderr_path = directory / "daemon.stderr"
        self.proc: subprocess.Popen[bytes] | None = None
        _DAEMONS.append(self)

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def start(self, env: dict[str, str] | None = None) -> None:
        with open(self.stderr_path, "wb") as stderr:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "jtc_hw", "run", str(self.config_path)],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=stderr,
                cwd=ROOT,
                # The flight recorder's bags in the test's directory, not the user's.
                env=env or daemon_env(XDG_STATE_HOME=str(self.config_path.parent / "state")),
                start_new_session=True,  # its own process group: a last-resort kill finds all
            )

    def log(self) -> str:
        try:
            return self.stderr_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def accepts_connections(self) -> bool:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            probe.settimeout(2.0)
            try:
                probe.connect(str(self.socket))
            except OSError:
                return False
            return True

    def wait_ready(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Until the socket accepts a connection; fails at once if the process exits."""
        assert self.proc is not None
        deadline = time.monotonic() + timeout_s
        while not self.accepts_connections():
            code = self.proc.poll()
            if code is not None:
                raise AssertionError(f"the daemon exited ({code}) before listening:\n{self.log()}")
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"the daemon did not listen within {timeout_s} s:\n{self.log()}"
                )
            time.sleep(0.02)  # polling two conditions (process, socket); nothing to block on
        # The daemon and its control-loop process (the leak check at the end looks for these).
        assert len(_session_members(self.pid)) >= 2, _session_members(self.pid)

    def wait_log(self, fragment: str, timeout_s: float = WAIT_S) -> str:
        """The first stderr line containing ``fragment``, waiting for it to be written."""
        deadline = time.monotonic() + timeout_s
        while True:
            for line in self.log().splitlines():
                if fragment in line:
                    return line
            if time.monotonic() > deadline:
                raise AssertionError(f"no log line with {fragment!r} within {timeout_s} s")
            time.sleep(0.02)  # polling a file that another process appends to

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> int:
        """SIGTERM (unless it already exited), then ``wait_exit``."""
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        return self.wait_exit(timeout_s)

    def wait_exit(self, timeout_s: float = STOP_TIMEOUT_S) -> int:
        """The exit status; SIGKILL to the whole session as a last resort (then fails).

        After a test's own SIGTERM, wait with this rather than ``stop``: a second SIGTERM
        during the last moments of the exit finds the default disposition restored and kills
        the process (status -15).
        """
        assert self.proc is not None
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(self.pid, signal.SIGKILL)
            self.proc.wait(timeout=10)
            raise AssertionError(
                f"the daemon did not exit within {timeout_s} s; killed\n{self.log()}"
            ) from None

    def leftovers(self, timeout_s: float = WAIT_S) -> dict[int, str]:
        """Processes of the daemon's session still alive once it has exited (should be none:
        the loop process and multiprocessing's helper exit with it)."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = _session_members(self.pid)
            if not left or time.monotonic() > deadline:
                return left
            time.sleep(0.02)  # polling /proc for processes of another parent to exit

    @contextmanager
    def serving(self) -> Iterator[None]:
        """Started and ready inside the block; afterwards stopped, nothing of it left, and its
        exit status 0 (a module's shared daemon: ``with d.serving(): yield d``)."""
        self.start()
        try:
            self.wait_ready()
            yield
        finally:
            code = self.shutdown()
        assert code == 0, f"the daemon exited with {code}:\n{self.log()}"

    def shutdown(self) -> int | None:
        """Stop if still running and make sure nothing of it is left; the exit status."""
        if self.proc is None:
            return None
        code = self.stop()
        left = self.leftovers()
        if left:
            os.killpg(self.pid, signal.SIGKILL)
            raise AssertionError(f"the daemon left processes running (killed): {left}")
        return code


class RecordingClient(Client):
    """The real client, also recording every event it receives, in order, so that a second
    ``result`` for a goal (which the Client itself would ignore) can be seen."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.events: list[dict[str, Any]] = []  # before the reader thread starts
        self._events_lock = threading.Lock()
        super().__init__(*args, **kwargs)

    def _dispatch_event(self, event: str, message: dict[str, Any]) -> None:
        with self._events_lock:
            self.events.append(message)
        super()._dispatch_event(event, message)

    def received(self, event: str, goal_id: int | None = None) -> list[dict[str, Any]]:
        with self._events_lock:
            return [
                m
                for m in self.events
                if m["event"] == event and (goal_id is None or m.get("goal_id") == goal_id)
            ]


def connect(d: DaemonProcess) -> RecordingClient:
    client = RecordingClient.connect(d.socket, timeout_s=WAIT_S)
    assert isinstance(client, RecordingClient)
    return client


def next_state(
    sub: StateSubscription, pred: Callable[[dict[str, Any]], bool], timeout_s: float = WAIT_S
) -> dict[str, Any]:
    """The next ``state`` message satisfying ``pred``."""
    deadline = time.monotonic() + timeout_s
    while True:
        state = sub.get(timeout_s=max(0.0, deadline - time.monotonic()))
        if pred(state):
            return state


def settle(sub: StateSubscription, after_ns: int) -> dict[str, Any]:
    """Wait for a state stamped at least ``after_ns`` on ``sub``'s connection.

    The loop publishes a cycle's goal events before its state, and the daemon queues both for a
    connection in order: once this state has arrived, every event of earlier cycles has too.
    """
    return next_state(sub, lambda s: s["time_ns"] >= after_ns)


def skipped_deadlines_until_now(client: Client, timeout_s: float = WAIT_S) -> int:
    """The deadlines the loop has skipped since it started (``loop.overruns``), from a status
    report made after this call began: everything before now is counted.

    The loop reports its statistics at 2 Hz, so the status at hand may predate a moment the
    caller cares about; the next report that differs from it (the cycle count moved) was made
    later. A test derives what a busy host may cost from this count (a skipped deadline is a
    cycle that never ran) rather than from a fixed share.
    """
    deadline = time.monotonic() + timeout_s
    first = client.get_status()["loop"]
    while True:
        loop = client.get_status()["loop"]
        if loop["cycles"] != first["cycles"]:
            return int(loop["overruns"])
        assert time.monotonic() < deadline, f"no new loop statistics within {timeout_s} s"
        time.sleep(0.05)  # polling the daemon's 2 Hz report; nothing to block on


def traj(positions: Sequence[float], t: float = 1.0, **extra: Any) -> dict[str, Any]:
    """One point at ``t`` s, at rest."""
    return {
        "joint_names": JOINTS,
        "points": [{"time_from_start": t, "positions": list(positions), "velocities": [0.0] * 6}],
        **extra,
    }




class ConfiguredDaemon(DaemonProcess):
    """A daemon whose robot file is ``config(socket_path)``: a robot of the test's own (the
    driver tests' emulated hardware)."""

    def __init__(self, directory: Path, config: Callable[[Path], dict[str, Any]]) -> None:
        super().__init__(directory)
        self.config_path.write_text(yaml.safe_dump(config(self.socket), sort_keys=False))
