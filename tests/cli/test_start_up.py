"""``jtc-hw send`` shows its progress bar before it loads what takes time (issue 24: within
100 ms of the command's start for a 20,000-point CSV; ``bench/send_start.py`` measures it).

What is checked here is what makes that possible, not a time: a command builds only its own
group's parser, and the same one as the whole parser; the modules ``send`` imports before its
bar is up load neither numpy nor the client; the bar shows the stages before the goal runs on a
terminal (and nothing of them in a pipe); and on a pseudo-terminal, the bar is up before the
goal is accepted.
"""

from __future__ import annotations

import argparse
import io
import os
import pty
import select
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers.daemon import ConfiguredDaemon, DaemonProcess, daemon_env

from jtc_hw.cli.common import Progress
from jtc_hw.cli.demo import demo_config
from jtc_hw.cli.parser import GROUPS, build_parser

from conftest import ROOT

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise AssertionError("no subcommands")


def test_each_command_alone_parses_and_helps_as_in_the_whole_parser() -> None:
    whole = _commands(build_parser())
    assert sorted(whole) == sorted(c for commands in GROUPS.values() for c in commands)
    for name, expected in whole.items():
        alone = _commands(build_parser(name))
        group = next(commands for commands in GROUPS.values() if name in commands)
        assert sorted(alone) == sorted(group), name
        assert alone[name].format_help() == expected.format_help(), name


def _python(code: str) -> subprocess.CompletedProcess[str]:
    """``code`` run by a fresh interpreter (nothing imported yet), its output captured."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True, env=daemon_env(), timeout=60)


def test_send_loads_neither_numpy_nor_the_client_before_its_bar() -> None:
    code = (
        "import sys\n"
        "from jtc_hw.cli.parser import build_parser\n"
        "build_parser('send')\n"
        "import jtc_hw.cli.goals\n"
        "loaded = sorted(m for m in ('numpy', 'jtc_hw.api', 'jtc_hw.controller', 'yaml')"
        " if m in sys.modules)\n"
        "print(loaded)\n"
    )
    out = _python(code)
    assert out.stdout.strip() == "[]", out.stderr


def test_the_package_loads_its_names_when_first_used() -> None:
    code = (
        "import sys, jtc_hw\n"
        "before = 'numpy' in sys.modules\n"
        "from jtc_hw import JointTrajectory, load_config\n"
        "missing = sorted(set(jtc_hw.__all__) - set(dir(jtc_hw)))\n"
        "print(before, JointTrajectory.__module__, load_config.__module__, missing)\n"
    )
    out = _python(code)
    assert out.stdout.split() == [
        "False", "jtc_hw.controller.messages", "jtc_hw.config.reading", "[]"
    ], out.stderr
    with pytest.raises(ImportError, match="no_such_name"):
        exec("from jtc_hw import no_such_name", {})


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_stages_show_the_empty_bar_on_a_terminal_and_nothing_in_a_pipe() -> None:
    terminal = _Terminal()
    bar = Progress(0.0, stream=terminal, width=4)
    bar.stage("reading goal.csv")
    assert terminal.getvalue() == "\r[....] reading goal.csv"
    bar.stage("sending")  # shorter: the rest of the line before it is blanked
    assert terminal.getvalue().endswith("\r[....] sending" + " " * 9)
    bar.clear()
    assert terminal.getvalue().endswith("\r" + " " * 14 + "\r")
    bar.total_s = 2.0
    bar.update({"time_from_start": 1.0, "error": {"positions": [0.001, -0.002]}})
    assert terminal.getvalue().endswith("\r[##..]   1.00/2.00 s  max |error| 0.0020")

    pipe = io.StringIO()
    quiet = Progress(0.0, stream=pipe)
    quiet.stage("reading goal.csv")
    quiet.clear()
    assert pipe.getvalue() == ""


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    """The daemon ``jtc-hw demo`` starts (its configuration, simulated joints)."""
    d = ConfiguredDaemon(tmp_path_factory.mktemp("start-up"), lambda sock: demo_config(str(sock)))
    with d.serving():
        yield d


def test_on_a_terminal_send_shows_the_bar_before_the_goal_is_accepted(
    demo: DaemonProcess, tmp_path: Path
) -> None:
    goal = tmp_path / "goal.csv"
    rows = [f"{i * 0.01:.2f}," + ",".join(["0.001"] * 6) for i in range(1, 51)]
    goal.write_text("time_from_start," + ",".join(f"joint{i}" for i in range(1, 7)) + "\n"
                    + "\n".join(rows) + "\n")
    master, slave = pty.openpty()
    process = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "send", str(goal), "--socket", str(demo.socket)],
        stdin=slave, stdout=slave, stderr=slave, cwd=ROOT, env=daemon_env(),
    )
    os.close(slave)
    output = b""
    try:
        while True:
            if not select.select([master], [], [], 60)[0]:
                raise AssertionError(f"no output for 60 s: {output!r}")
            try:
                chunk = os.read(master, 65536)
            except OSError:  # the command exited: its terminal is closed
                break
            if not chunk:
                break
            output += chunk
        assert process.wait(timeout=60) == 0, (output, demo.log())
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        os.close(master)
    text = output.decode()
    reading = text.index(f"] reading {goal}")
    sending = text.index("] sending 50 points")
    accepted = text.index("goal ")
    assert reading < sending < accepted, text
    assert "accepted: 50 points" in text
    assert "succeeded (error_code 0)" in text
    # The stages are blanked before the accepted line: it starts on an empty line.
    line = text[text.rindex("\r", 0, accepted):accepted]
    assert line.strip() == "", text
