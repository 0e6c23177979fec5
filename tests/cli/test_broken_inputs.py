"""Every ``jtc-hw`` command given broken inputs (issue 21): a missing file, a binary file, YAML
nested 5,000 levels deep, a dead daemon (no socket file; a stale one nobody listens on), a
foreign socket (a same-user unix listener that is no jtc-hw daemon: it closes at once, or
answers garbage), an unreadable Zenoh configuration. Each answers with exactly one line on
stderr, no traceback, and an exit status that its ``--help`` documents.

The commands run as subprocesses (``python -m jtc_hw``), several at a time. The list of
commands comes from the parser: a new command without broken inputs here fails the test.
"""

from __future__ import annotations

import argparse
import re
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from helpers.daemon import ROOT, daemon_env

from jtc_hw.cli.parser import build_parser

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

BAD_FILE, NO_DAEMON = 2, 3
CLIENTS = {  # client commands and the arguments they need besides the connection
    "send": ["GOAL"], "cancel": ["1"], "state": [], "query": ["0"], "stop": [], "rearm": [],
    "speed": ["0.5"], "pause": [], "resume": [], "param": ["get"], "status": [],
    "hardware": [], "record": ["OUT"],
}
FILES = ("missing.yaml", "binary.yaml", "deep.yaml")
SOCKETS = ("missing.sock", "stale.sock", "closes.sock", "garbage.sock")


class ForeignListener:
    """A unix socket listener that is not a jtc-hw daemon: it closes each connection at once
    (``garbage=False``) or first sends bytes that are no protocol message."""

    def __init__(self, path: Path, garbage: bool) -> None:
        self._server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._server.bind(str(path))
        self._server.listen(64)
        self._garbage = garbage
        self._thread = threading.Thread(target=self._serve, name=f"foreign {path.name}")
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self._server.accept()
            except OSError:  # shut down by close()
                return
            with conn:
                if self._garbage:
                    try:
                        conn.sendall(b"\x00\xff\xfeSSH-2.0-not-jtc-hw\r\n{\"op\": }\n")
                        conn.recv(65536)  # until the client gives up and closes
                    except OSError:
                        pass

    def close(self) -> None:
        self._server.shutdown(socket.SHUT_RDWR)  # wakes accept()
        self._server.close()
        self._thread.join(timeout=10.0)


@pytest.fixture
def inputs(tmp_path: Path) -> Iterator[Path]:
    """The broken files and sockets in ``tmp_path`` (short: socket paths are limited)."""
    (tmp_path / "binary.yaml").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "deep.yaml").write_text("[" * 5000 + "]" * 5000 + "\n")
    (tmp_path / "goal.yaml").write_text(
        "joint_names: [j1]\npoints:\n- {positions: [0.1], time_from_start: 1.0}\n")
    for name in ("missing", "binary", "deep"):  # bag directories for plot
        (tmp_path / f"bag-{name}").mkdir()
    (tmp_path / "bag-missing" / "bag-missing.mcap").write_bytes(b"")
    (tmp_path / "bag-binary" / "metadata.yaml").write_bytes(bytes(range(256)))
    (tmp_path / "bag-deep" / "metadata.yaml").write_text("[" * 5000 + "]" * 5000)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(tmp_path / "stale.sock"))  # a daemon killed with SIGKILL leaves this
    stale.close()
    listeners = [ForeignListener(tmp_path / "closes.sock", garbage=False),
                 ForeignListener(tmp_path / "garbage.sock", garbage=True)]
    try:
        yield tmp_path
    finally:
        for listener in listeners:
            listener.close()


def commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def cases(d: Path) -> list[tuple[list[str], int]]:
    """(arguments, the exit status they must give) for every command."""
    out: list[tuple[list[str], int]] = []
    for command, extra in CLIENTS.items():
        args = [command, *(str(d / "goal.yaml") if a == "GOAL" else str(d / "bag-out")
                           if a == "OUT" else a for a in extra)]
        out += [([*args, "--socket", str(d / s), "--timeout", "5"], NO_DAEMON)
                for s in SOCKETS]
        out += [([*args, "--config", str(d / f), "--timeout", "5"], BAD_FILE) for f in FILES]
        out += [([*args, "--zenoh", "jtc", "--zenoh-config", str(d / f), "--timeout", "5"],
                 BAD_FILE) for f in FILES]
    for f in FILES:
        out += [
            (["run", str(d / f)], BAD_FILE),
            (["check", str(d / f)], BAD_FILE),
            (["demo", "--config", str(d / f)], BAD_FILE),
            (["send", str(d / f), "--socket", str(d / "missing.sock")], BAD_FILE),
            (["plot", str(d / f)], BAD_FILE),
            (["plot", str(d / f"bag-{Path(f).stem}")], BAD_FILE),
            (["fleet", "--zenoh-config", str(d / f), "--timeout", "1"], BAD_FILE),
            (["emulate", "dynamixel", "--ids", "1", "--model", str(d / f)], BAD_FILE),
            (["calibrate", "feetech", str(d / f)], BAD_FILE),
        ]
    return out


def documented(parser: argparse.ArgumentParser, code: int) -> bool:
    """Whether the command's --help gives ``code`` in its exit statuses."""
    text = " ".join(f"{parser.description or ''} {parser.epilog or ''}".split())
    match = re.search(r"Exit (?:status|codes): (.*)", text)
    return match is not None and re.search(rf"(^|[;,] ){code} ", match.group(1)) is not None


GOAL_COMMANDS = {"send", "cancel", "demo"}
"""The commands whose exit status says how a goal ended (1); no other exits 1 for a goal."""


def test_each_command_help_gives_its_own_exit_statuses_once() -> None:
    # One exit-status section per --help (a second one, appended by the parser, contradicted
    # the first), and goal results only where the command runs or cancels a goal.
    wrong = []
    for name, parser in commands().items():
        text = " ".join(f"{parser.description or ''} {parser.epilog or ''}".split())
        sections = re.findall(r"Exit (?:status|codes): ", text)
        if len(sections) != 1:
            wrong.append(f"{name}: {len(sections)} exit-status sections")
            continue
        if ("goal" in text.split("Exit ", 1)[1]) != (name in GOAL_COMMANDS):
            wrong.append(f"{name}: {text.split('Exit ', 1)[1]}")
    assert not wrong, "\n".join(wrong)


def run(args: list[str]) -> tuple[list[str], int, str]:
    done = subprocess.run([sys.executable, "-m", "jtc_hw", *args], capture_output=True,
                          text=True, timeout=120, cwd=ROOT, env=daemon_env(),
                          stdin=subprocess.DEVNULL)
    return args, done.returncode, done.stderr


def test_every_command_answers_broken_inputs_in_one_line(inputs: Path) -> None:
    pytest.importorskip("zenoh")  # the --zenoh-config cases read the file with it
    parsers = commands()
    todo = cases(inputs)
    assert {args[0] for args, _ in todo} == set(parsers), "a command without broken inputs"
    with ThreadPoolExecutor(max_workers=4) as pool:
        results = list(pool.map(run, [args for args, _ in todo]))
    failures = []
    for (args, code, stderr), (_, expected) in zip(results, todo, strict=True):
        shown = " ".join(a.replace(f"{inputs}/", "") for a in args)
        lines = stderr.splitlines()
        if len(lines) != 1 or "Traceback" in stderr or code != expected:
            failures.append(f"{shown}: exit {code} (expected {expected}), stderr:\n{stderr}")
        elif args[0] in ("run", "check") and not args[1].endswith("missing.yaml") and (
            f"configuration file {args[1]}, line " not in stderr
        ):
            failures.append(f"{shown}: the line does not name the file and position: {stderr}")
        elif not documented(parsers[args[0]], code):
            failures.append(f"{shown}: exit {code} is not in 'jtc-hw {args[0]} --help'")
    assert not failures, f"{len(failures)} of {len(todo)}:\n" + "\n".join(failures)
