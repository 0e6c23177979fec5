"""Every shell command of README.md and docs/*.md runs here as written, or says why it cannot.

Theory of operation. The commands of a page are the lines of its fenced code blocks that a
reader would type:

- ``sh``, ``bash``, ``shell`` blocks: every line that is not blank and not a ``#`` comment;
- ``console`` and unlabeled blocks: the lines starting with the prompt ``$ `` (dropped), and in
  an unlabeled block also lines that start like a command (``jtc-hw``, ``python``,
  ``.venv/bin/...``, ``pip``, ``tools/x``, ``bench/x``, ``sudo``, ``systemctl``); their other
  lines are a command's output or input, and ``yaml``, ``json``, ``python``, ``text`` ...
  blocks are illustrations, not commands.

A trailing ``# ...`` comment is dropped from the command. A command is **marked** when that
comment says ``needs: REASON`` (a real robot, root, the network, minutes), or when the last
line before its block is ``<!-- doc-example: skip (REASON) -->``; a marked command is not run.
Every other command must be one this test runs: ``jtc-hw ...`` (or ``.venv/bin/jtc-hw``),
``python bench/...`` or ``export NAME=VALUE``, without a shell operator (``&&``, ``|``, ``;``,
``$(``, redirections), and the configs it names must exist; a ``--config CONFIG`` client
command needs ``jtc-hw run CONFIG`` earlier on the same page. A new command that breaks this
rule fails ``test_every_command_runs_here_or_is_marked``, naming its file and line.

``test_doc_commands_run_as_written`` runs a page's unmarked runnable commands (never another) in
order, as a user would with a second terminal at hand:

- ``jtc-hw run CONFIG`` and ``jtc-hw emulate ...`` start in the background (ready at the
  daemon's ``ready:`` log line, at the emulator's first line) and run until the end of the
  module; the same command on another page reuses the running process, so one daemon serves
  each config;
- a command whose comment says ``meanwhile`` runs while the command before it does: that one
  is started in the background (ready at its first line) and must exit 0 afterwards;
- a ``--watch`` command gets SIGINT (a user's Ctrl-C) once it has printed, and must exit 0;
- ``export NAME=VALUE`` sets the environment of the page's commands after it;
- every other command must exit 0. No command may print a traceback.

Isolation: the commands run in a copy of ``config/`` and ``examples/`` in the test's own
directory, every ``/tmp/jtc-hw`` path (sockets, the emulator's link) moved under it in the
copies and the commands alike, with ``XDG_RUNTIME_DIR`` and ``XDG_STATE_HOME`` there too, and
the emulated CAN configs' socketcand port 29536 replaced by a free one, so that two suites side
by side, or a user's daemon, never share a socket or a port with the test.
``.venv/bin/`` and ``python`` are this test's interpreter's. Every wait is an upper bound.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^\s*```(\S*)\s*$")
SKIP_BLOCK = re.compile(r"^\s*<!--\s*doc-example:\s*skip\s*\((.+)\)\s*-->\s*$")
NEEDS = re.compile(r"\bneeds:\s*(\S.*)$")
SHELL_BLOCKS = {"sh", "bash", "shell"}
PROMPT_BLOCKS = {"console", ""}
COMMAND_START = re.compile(
    r"^(jtc-hw\b|python3?\s|\.venv/bin/\S|pip3?\s|tools/\S|bench/\S|sudo\s|systemctl\s)")
RUNNABLE = re.compile(r"^(export \w+=\S+$|(\.venv/bin/)?jtc-hw(\s|$)|python3? bench/\S)")
OPERATOR = re.compile(r"&&|\|\||[|;<>`]|\$\(")
CLIENT_EXEMPT = {"check", "run", "demo", "emulate"}  # --config without a running daemon
SOCKETCAND_PORT = "29536"  # the emulated CAN configs' port: each run takes a free one
WAIT_S = 120.0  # upper bound on any one wait; never an assertion of speed


@dataclass(frozen=True)
class Command:
    """One command a page shows: where, the text as written (prompt and comment dropped)."""

    page: str
    line: int
    text: str
    comment: str
    skip: str | None  # the marker's reason; None: the test must run it

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}: {self.text!r}"


def split_comment(line: str) -> tuple[str, str]:
    """``line`` as (command, trailing comment), the comment's ``#`` outside any quotes."""
    for hash_mark in re.finditer(r"\s#", line):
        head = line[:hash_mark.start()]
        try:
            shlex.split(head)
        except ValueError:  # the '#' is inside a quoted word
            continue
        return head.strip(), line[hash_mark.end():].strip()
    return line.strip(), ""


def extract(path: Path, page: str) -> list[Command]:
    """Every command of the markdown file ``path`` (called ``page`` in messages)."""
    commands: list[Command] = []
    lang: str | None = None  # the open block's language; None outside a block
    block_skip: str | None = None
    previous = ""  # the last non-blank line outside a block
    for number, raw in enumerate(path.read_text().splitlines(), start=1):
        fence = FENCE.match(raw)
        if fence:
            if lang is None:
                lang = fence.group(1)
                marker = SKIP_BLOCK.match(previous)
                block_skip = marker.group(1).strip() if marker else None
            else:
                lang = None
                previous = ""
            continue
        if lang is None:
            if raw.strip():
                previous = raw
            continue
        line = raw.strip()
        if lang in PROMPT_BLOCKS and line.startswith("$ "):
            line = line[2:].strip()
        elif not (lang in SHELL_BLOCKS or (lang == "" and COMMAND_START.match(line))):
            continue
        if not line or line.startswith("#"):
            continue
        text, comment = split_comment(line)
        needs = NEEDS.search(comment)
        skip = needs.group(1).strip() if needs else block_skip
        commands.append(Command(page, number, text, comment, skip))
    return commands


def page_name(path: Path) -> str:
    return str(path.relative_to(ROOT))


def named_configs(argv: list[str]) -> list[str]:
    """The config files a ``jtc-hw`` command names (``--config X``, ``run X``, ``check X``)."""
    names = [argv[i + 1] for i, word in enumerate(argv[:-1]) if word == "--config"]
    if len(argv) > 2 and argv[1] in ("run", "check") and not argv[2].startswith("-"):
        names.append(argv[2])
    return names


def runnable(text: str) -> bool:
    """Whether this test may run the command: one of ours, no shell operator."""
    return bool(RUNNABLE.match(text)) and not OPERATOR.search(text)


def problems(commands: list[Command], root: Path = ROOT) -> list[str]:
    """One line per unmarked command that the test cannot run, and why."""
    found: list[str] = []
    started: set[str] = set()
    for command in commands:
        if command.skip is not None:
            continue
        if not runnable(command.text):
            found.append(f"{command.where}: cannot run here; run-able commands are jtc-hw, "
                         "python bench/..., export; else end the line with '# needs: REASON'")
            continue
        argv = shlex.split(command.text)
        if not argv[0].endswith("jtc-hw"):
            continue
        for config in named_configs(argv):
            if not (root / config).is_file():
                found.append(f"{command.where}: no file {config}; name a config of this "
                             "repository, or mark the line '# needs: REASON'")
        if len(argv) > 2 and argv[1] == "run":
            started.add(argv[2])
        elif len(argv) > 1 and argv[1] not in CLIENT_EXEMPT:
            for config in named_configs(argv):
                if config not in started:
                    found.append(f"{command.where}: no 'jtc-hw run {config}' before it on "
                                 "this page; show it, or mark the line '# needs: REASON'")
    return found


@pytest.mark.parametrize("path", DOCS, ids=page_name)
def test_every_command_runs_here_or_is_marked(path: Path) -> None:
    found = problems(extract(path, page_name(path)))
    assert not found, "\n".join(found)


def write_page(tmp_path: Path, text: str) -> list[Command]:
    page = tmp_path / "page.md"
    page.write_text(text)
    return extract(page, "page.md")


def test_an_unmarked_command_that_cannot_run_is_named_by_file_and_line(tmp_path: Path) -> None:
    """The check cannot pass vacuously: the extraction rules and the markers, on a page."""
    commands = write_page(tmp_path, "\n".join([
        "```sh",
        "# a comment",
        "systemctl restart jtc-hw",                                     # 3: unmarked
        "sudo ip link set up can0   # needs: root",                     # 4: marked
        "jtc-hw status   # '#' in 'quotes' # needs: a daemon",          # 5: marked
        "```",
        "```console",
        "$ jtc-hw state --watch",                                       # 8
        "PREFIX  JOINTS",                                               # output
        "```",
        "```",
        "jtc-hw send examples/goal.yaml | tee out",                     # 12: an operator
        "tools/    vcan-hil (a layout listing, not a command)",
        "```",
        "<!-- doc-example: skip (needs a robot) -->",
        "```bash",
        "jtc-hw run config/nowhere.yaml",                               # 17: marked
        "```",
        "```sh",
        "jtc-hw send goal.yaml --config config/mirror-arm.yaml",        # 20: no run before
        "```",
        "```yaml",
        "jtc-hw: not a command",
        "```",
    ]))
    assert [(c.line, c.text, c.skip) for c in commands] == [
        (3, "systemctl restart jtc-hw", None),
        (4, "sudo ip link set up can0", "root"),
        (5, "jtc-hw status", "a daemon"),
        (8, "jtc-hw state --watch", None),
        (12, "jtc-hw send examples/goal.yaml | tee out", None),
        (17, "jtc-hw run config/nowhere.yaml", "needs a robot"),
        (20, "jtc-hw send goal.yaml --config config/mirror-arm.yaml", None),
    ]
    found = problems(commands)
    assert [line.split(":")[1] for line in found] == ["3", "12", "20"], found
    assert found[0].startswith("page.md:3: 'systemctl restart jtc-hw': cannot run here")
    assert "no 'jtc-hw run config/mirror-arm.yaml' before it" in found[2]


def test_readme_runs_the_mirror_arm_session() -> None:
    """The runner is not vacuous: README's daemon commands are extracted and left unmarked."""
    texts = {c.text for c in extract(ROOT / "README.md", "README.md") if c.skip is None}
    assert {"jtc-hw run config/mirror-arm.yaml", "jtc-hw param set gains.joint1.p 12",
            "jtc-hw run config/dynamixel-arm-emulated.yaml"} <= texts


class Background:
    """A command running beside the page's others, its output drained by a thread."""

    def __init__(self, where: str, argv: list[str], cwd: Path, env: dict[str, str],
                 ready: str) -> None:
        self.where = where
        self.proc = subprocess.Popen(argv, cwd=cwd, env=env, text=True,
                                     stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT)
        self.output: list[str] = []
        self._ready_text = ready
        self._ready = threading.Event()  # set at the ready line, or at EOF
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line)
            if self._ready_text in line:
                self._ready.set()
        self._ready.set()

    def tail(self) -> str:
        return "".join(self.output[-5:]).strip()

    def wait_ready(self) -> None:
        if not self._ready.wait(WAIT_S) or self.proc.poll() is not None:
            pytest.fail(f"{self.where}: did not start (exit {self.proc.poll()}): {self.tail()}")

    def join(self) -> int:
        """Wait for its own end; its exit status."""
        try:
            status = self.proc.wait(WAIT_S)
        except subprocess.TimeoutExpired:
            self.stop()
            pytest.fail(f"{self.where}: still running after {WAIT_S:.0f} s")
        self._reader.join(WAIT_S)
        return status

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(30)
        self._reader.join(30)


@dataclass
class Workspace:
    """The module's directory, environment and long-running commands (daemons, emulators)."""

    cwd: Path
    private: str  # what /tmp/jtc-hw becomes
    port: str  # what SOCKETCAND_PORT becomes
    env: dict[str, str]
    running: dict[str, Background]


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Workspace]:
    cwd = tmp_path_factory.mktemp("doc-examples")
    for name in ("config", "examples"):
        shutil.copytree(ROOT / name, cwd / name)
    private = str(cwd / "jtc-hw")
    with socket.socket() as probe:  # free now; the emulator binds it within seconds
        probe.bind(("127.0.0.1", 0))
        port = str(probe.getsockname()[1])
    for config in (cwd / "config").glob("*.yaml"):
        text = config.read_text().replace("/tmp/jtc-hw", private)
        config.write_text(text.replace(SOCKETCAND_PORT, port))
    bindir = Path(sys.executable).parent
    env = dict(os.environ, XDG_RUNTIME_DIR=str(cwd), XDG_STATE_HOME=str(cwd / "state"),
               PATH=f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}")
    env.pop("JTC_HW_SOCKET", None)
    space = Workspace(cwd, private, port, env, {})
    try:
        yield space
    finally:
        for process in reversed(list(space.running.values())):  # daemons before emulators
            process.stop()


def argv_of(text: str, space: Workspace) -> list[str]:
    """The argument vector of a command as written, with this test's paths."""
    text = text.replace("/tmp/jtc-hw", space.private).replace(SOCKETCAND_PORT, space.port)
    argv = shlex.split(text)
    if argv[0] in ("python", "python3"):
        argv[0] = sys.executable
    elif argv[0].startswith(".venv/bin/"):
        argv[0] = str(Path(sys.executable).parent / argv[0][len(".venv/bin/"):])
    return argv


def check_exit(where: str, status: int, output: str) -> None:
    assert status == 0 and "Traceback" not in output, (
        f"{where}: exit {status}: {output.strip()[-2000:]}")


@pytest.mark.parametrize("path", DOCS, ids=page_name)
def test_doc_commands_run_as_written(path: Path, workspace: Workspace) -> None:
    # Never anything else (an unmarked 'sudo ...' would run as whoever runs the suite): the
    # test above names the commands that are neither runnable nor marked.
    commands = [c for c in extract(path, page_name(path))
                if c.skip is None and runnable(c.text)]
    env = dict(workspace.env)
    for index, command in enumerate(commands):
        text = command.text
        if text.startswith("export "):
            key, _, value = text[len("export "):].partition("=")
            env[key] = value.replace("/tmp/jtc-hw", workspace.private)
            continue
        argv = argv_of(text, workspace)
        verb = argv[1] if argv[0].endswith("jtc-hw") and len(argv) > 1 else ""
        if verb in ("run", "emulate"):
            key = " ".join(argv)
            running = workspace.running.get(key)
            if running is None:
                running = Background(command.where, argv, workspace.cwd, env,
                                     "ready:" if verb == "run" else "")
                workspace.running[key] = running
                running.wait_ready()
            elif running.proc.poll() is not None:
                pytest.fail(f"{command.where}: exited ({running.proc.returncode}) since "
                            f"{running.where} started it: {running.tail()}")
            continue
        later = commands[index + 1:index + 2]
        meanwhile = [c for c in later if "meanwhile" in c.comment]
        if "--watch" in argv or meanwhile:
            beside = Background(command.where, argv, workspace.cwd, env, "")
            beside.wait_ready()
            if "--watch" in argv:
                beside.proc.send_signal(signal.SIGINT)
            for other in meanwhile:  # runs while this one does; then this one must succeed
                done = subprocess.run(argv_of(other.text, workspace), cwd=workspace.cwd,
                                      env=env, text=True, capture_output=True,
                                      timeout=WAIT_S)
                check_exit(other.where, done.returncode, done.stdout + done.stderr)
            check_exit(command.where, beside.join(), "".join(beside.output))
            continue
        if index > 0 and "meanwhile" in command.comment:
            continue  # ran beside the command before it
        done = subprocess.run(argv, cwd=workspace.cwd, env=env, text=True,
                              capture_output=True, timeout=WAIT_S)
        check_exit(command.where, done.returncode, done.stdout + done.stderr)
