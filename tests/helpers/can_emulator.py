"""The CAN emulator (``python -m jtc_hw.drivers.can.emulator``) in its own process: the line
it prints once it serves (how to connect), and the motors' enable/disable events it prints
with ``--events``. Killing it is a bus loss (no goodbye on the bus).

Emulators living in the test process instead (the daemon tests that inject faults by calling
them) are started with :func:`helpers.hardware_threads.start_as_hardware`, at the real-time
priority the emulator process takes.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

from helpers.daemon import START_TIMEOUT_S, WAIT_S, daemon_env

from conftest import ROOT


class EmulatorProcess:
    """One emulator process at a time; :meth:`spawn` again after :meth:`kill` restarts it."""

    def __init__(self, wait_s: float = WAIT_S) -> None:
        self.wait_s = wait_s
        """How long to wait for its lines and its exit (longer in an emulated machine)."""
        self.proc: subprocess.Popen[str] | None = None
        self._reader: threading.Thread | None = None
        self._changed = threading.Condition()
        self._first_line: str | None = None
        self._enabled: dict[int, bool] = {}

    def spawn(self, args: Sequence[str]) -> str:
        """Start the emulator with ``args``; wait for its first line, and return it.

        Raises:
            AssertionError: it printed nothing within ``wait_s`` (at least START_TIMEOUT_S).
        """
        self._first_line, self._enabled = None, {}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "jtc_hw.drivers.can.emulator", *args],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL,
            text=True, cwd=ROOT, env=daemon_env(),
        )
        self._reader = threading.Thread(target=self._read, args=(self.proc,),
                                        name="emulator-events")
        self._reader.start()
        with self._changed:
            # Its first line comes after an interpreter start and python-can's import: on a
            # busy host that takes as long as a daemon's start (issue 22).
            if not self._changed.wait_for(lambda: self._first_line is not None,
                                          max(self.wait_s, START_TIMEOUT_S)):
                raise AssertionError("the emulator process did not start")
            assert self._first_line is not None
            return self._first_line

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            with self._changed:
                if self._first_line is None:
                    self._first_line = line
                else:
                    event = json.loads(line)
                    if event["event"] in ("enabled", "disabled"):
                        self._enabled[event["id"]] = event["event"] == "enabled"
                self._changed.notify_all()

    def wait_enabled(self, ids: Sequence[int]) -> None:
        """Until every motor of ``ids`` reported it is in motor mode (since this start)."""
        with self._changed:
            if not self._changed.wait_for(
                    lambda: all(self._enabled.get(i) for i in ids), self.wait_s):
                raise AssertionError(f"motors enabled: {self._enabled}, expected {ids}")

    def kill(self) -> None:
        """SIGKILL, as a crash or a cut cable: the motors fall silent, no goodbye on the bus."""
        assert self.proc is not None and self._reader is not None and self.proc.stdout
        self.proc.kill()
        self.proc.wait(timeout=self.wait_s)
        self._reader.join(self.wait_s)
        self.proc.stdout.close()
        self.proc = None

    def close(self) -> None:
        if self.proc is not None:
            self.kill()


def control(path: Path, line: str, timeout_s: float = WAIT_S) -> str:
    """Send one command to an emulator's ``--control`` socket; its one-line answer."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(str(path))
        with sock.makefile("rw", encoding="utf-8", newline="\n") as stream:
            stream.write(line + "\n")
            stream.flush()
            return stream.readline().strip()
