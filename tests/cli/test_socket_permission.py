"""A user the daemon socket's mode keeps out (issue 22, point 3): every client command says in
one line whose socket (or directory) it is, its owner, group and mode, and what to do, and
exits 2; not "is it running?" with exit 3.

The tests run as root, which no file mode keeps out, so each command runs in a forked child
that drops to user nobody (65534, no supplementary group) and calls the CLI's ``main``: the
interpreter may live where nobody cannot read (a root-only pyenv), so the child imports the
CLI's modules before it drops.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import socket
import sys
import tempfile
import traceback
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from helpers.daemon import WAIT_S, DaemonProcess, robot_config

from jtc_hw.api import paths
from jtc_hw.cli.parser import build_parser

NOBODY = 65534

pytestmark = pytest.mark.skipif(
    os.geteuid() != 0, reason="keeps a user out by file modes and runs as nobody: needs root"
)

CLIENTS = {  # every client command, with the arguments it needs besides the connection
    "send": ["GOAL"], "cancel": ["1"], "state": [], "query": ["0"], "stop": [], "rearm": [],
    "speed": ["0.5"], "pause": [], "resume": [], "param": ["get"], "status": [],
    "hardware": [], "record": ["OUT"],
}
HINT = "join its group (sudo usermod -aG root $USER, then log in again)"


def as_nobody(argv: list[str], groups: tuple[int, ...] = ()) -> tuple[int, str, str]:
    """``jtc-hw ARGV`` as user nobody (with supplementary ``groups``): exit status, stdout,
    stderr. An exception escaping ``main`` is printed as the console script would (a
    traceback) and exits 99."""
    import jtc_hw.api.client  # noqa: F401 - everything the commands import, before the drop
    import jtc_hw.cli.parser  # every command module
    import jtc_hw.daemon.robot  # noqa: F401
    import jtc_hw.rec.bag  # noqa: F401

    jtc_hw.cli.parser.build_parser()
    out_r, out_w = os.pipe()
    err_r, err_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child, as nobody; never returns
        code = 98
        try:
            os.close(out_r)
            os.close(err_r)
            signal.alarm(120)  # an upper bound on a hung child, not a timing assertion
            sys.stdout = os.fdopen(out_w, "w")
            sys.stderr = os.fdopen(err_w, "w")
            os.setgroups(list(groups))
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            try:
                code = int(jtc_hw.cli.main(argv))
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
            except BaseException:
                traceback.print_exc()
                code = 99
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    os.close(out_w)
    os.close(err_w)
    with os.fdopen(out_r) as out, os.fdopen(err_r) as err:
        stdout = out.read()
        stderr = err.read()
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status), stdout, stderr


class Listener:
    """A root-owned unix socket listening at ``path`` (mode 0660, group root), closed on
    exit: nobody's ``connect`` fails before a byte is exchanged."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.bind(str(path))
        os.chown(path, 0, 0)
        path.chmod(0o660)
        self.sock.listen()

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def shared() -> Iterator[Path]:
    """A directory nobody may enter (pytest's tmp_path is root's alone), holding ``open/``
    (0755: the socket file decides) and ``door/`` (0710, group root: nobody is kept out of
    the directory, as from a daemon's 0710 directory of a group they are not in)."""
    base = Path(tempfile.mkdtemp(prefix="jtc-hw-perm-"))
    base.chmod(0o755)
    (base / "goal.yaml").write_text(
        "joint_names: [j1]\npoints:\n- {positions: [0.1], time_from_start: 1.0}\n")
    (base / "goal.yaml").chmod(0o644)
    for name, mode in (("open", 0o755), ("door", 0o710)):
        (base / name).mkdir()
        os.chown(base / name, 0, 0)
        (base / name).chmod(mode)
    listeners = [Listener(base / "open" / "jtc-hw.sock"), Listener(base / "door" / "jtc-hw.sock")]
    try:
        yield base
    finally:
        for listener in listeners:
            listener.close()
        shutil.rmtree(base)


def _args(command: str, base: Path) -> list[str]:
    extra = CLIENTS[command]
    return [command, *(str(base / "goal.yaml") if a == "GOAL" else str(base / "bag-out")
                       if a == "OUT" else a for a in extra)]


def _one_line(code: int, stdout: str, stderr: str) -> str:
    assert "Traceback" not in stderr, stderr
    assert stderr.count("\n") == 1 and stderr.endswith("\n"), stderr
    assert code == 2, (code, stdout, stderr)
    return stderr.removesuffix("\n")


@pytest.mark.parametrize("command", sorted(CLIENTS))
def test_every_client_command_names_the_socket_that_keeps_the_user_out(
    command: str, shared: Path
) -> None:
    """Mode 0660 root:root on the socket file, its directory open: the line names the file,
    its owner, group and mode, and how to get in; exit 2."""
    sock = shared / "open" / "jtc-hw.sock"
    code, stdout, stderr = as_nobody([*_args(command, shared), "--socket", str(sock),
                                      "--timeout", "5"])
    line = _one_line(code, stdout, stderr)
    assert line.startswith(
        f"error: permission denied on the daemon socket {sock} (owner root, group root, "
        f"mode 0660): {HINT}, or set daemon.socket_group"), line
    assert "daemon.socket_mode" in line
    assert "running" not in line  # it may well run: not the "is it running?" of a dead one


@pytest.mark.parametrize("command", ["status", "send", "stop", "state"])
def test_a_directory_that_keeps_the_user_out_is_named(command: str, shared: Path) -> None:
    """The socket's directory is 0710 root:root: ``connect`` fails on the directory, and the
    line names that directory's owner, group and mode."""
    sock = shared / "door" / "jtc-hw.sock"
    code, stdout, stderr = as_nobody([*_args(command, shared), "--socket", str(sock),
                                      "--timeout", "5"])
    line = _one_line(code, stdout, stderr)
    assert line.startswith(
        f"error: permission denied on the daemon socket {sock}: its directory "
        f"{shared / 'door'} (owner root, group root, mode 0710): {HINT}"), line


def test_a_mode_without_group_access_asks_for_the_configuration(shared: Path) -> None:
    """Joining a group would not help a 0600 socket: the line says what the daemon's
    configuration must set instead."""
    sock = shared / "open" / "jtc-hw.sock"
    sock.chmod(0o600)
    code, stdout, stderr = as_nobody(["status", "--socket", str(sock), "--timeout", "5"])
    line = _one_line(code, stdout, stderr)
    assert f"{sock} (owner root, group root, mode 0600) lets no group in" in line, line
    assert "daemon.socket_mode 0660" in line and "usermod" not in line


def test_a_member_not_yet_in_this_login_is_told_to_log_in_again(
    shared: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A user already listed in the group (as after ``usermod -aG``) whose login predates it:
    log in again, not "join"."""
    monkeypatch.setattr(paths, "_in_group", lambda uid, gid: uid == NOBODY and gid == 0)
    sock = shared / "open" / "jtc-hw.sock"
    code, stdout, stderr = as_nobody(["stop", "--socket", str(sock), "--timeout", "5"])
    line = _one_line(code, stdout, stderr)
    assert line.endswith(
        "(owner root, group root, mode 0660): you are in group root, but this login is not "
        "yet: log in again (or run 'newgrp root')"), line


def test_the_service_socket_found_by_default_is_reported_not_the_users_own(
    shared: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No socket named, nothing at the user's own place, and /run/jtc-hw (0710, a group the
    user is not in) cannot be looked into: the client still goes for the service's socket
    and says who keeps the user out, rather than "no such file" at the user's own place."""
    run = shared / "run"
    run.mkdir(0o755)
    service = run / "jtc-hw"
    service.mkdir()
    service.chmod(0o710)
    listener = Listener(service / "jtc-hw.sock")
    xdg = shared / "xdg"
    xdg.mkdir(0o700)
    os.chown(xdg, NOBODY, NOBODY)
    monkeypatch.setattr(paths, "ROOT_SOCKET_DIR", str(service))
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(xdg))
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.delenv("JTC_HW_SOCKET", raising=False)
    try:
        code, stdout, stderr = as_nobody(["status", "--timeout", "5"])
    finally:
        listener.close()
    line = _one_line(code, stdout, stderr)
    assert line.startswith(
        f"error: permission denied on the daemon socket {service / 'jtc-hw.sock'}: its "
        f"directory {service} (owner root, group root, mode 0710): {HINT}"), line


@pytest.mark.usefixtures("no_leaks")
def test_a_daemons_own_directory_keeps_out_a_stranger_and_lets_in_its_group(
    shared: Path,
) -> None:
    """A real daemon creates its socket's directory 0710 (default socket_mode 0660) of its
    group: nobody outside it gets the directory named, exit 2; nobody in it (what the hint
    says to do) reaches the daemon."""
    directory = shared / "d"
    daemon = DaemonProcess(directory)
    daemon.socket = shared / "d" / "sock" / "jtc-hw.sock"
    daemon.config_path.write_text(yaml.safe_dump(robot_config(daemon.socket), sort_keys=False))
    directory.chmod(0o755)
    daemon.start()
    try:
        daemon.wait_ready()
        outside = as_nobody(["status", "--socket", str(daemon.socket), "--timeout", str(WAIT_S)])
        member = as_nobody(["status", "--socket", str(daemon.socket), "--timeout", str(WAIT_S)],
                           groups=(0,))
    finally:
        daemon.shutdown()
    line = _one_line(*outside)
    assert line.startswith(
        f"error: permission denied on the daemon socket {daemon.socket}: its directory "
        f"{daemon.socket.parent} (owner root, group root, mode 0710): {HINT}"), line
    assert member[0] == 0, member
    assert "controller" in member[1]


def test_every_client_commands_help_says_exit_2_covers_permission_denied() -> None:
    """The exit-status text of each client command's --help puts "permission denied" under
    2, not under 3."""
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    wrong = []
    for name in CLIENTS:
        command = sub.choices[name]
        text = " ".join(f"{command.description or ''} {command.epilog or ''}".split())
        section = text.split("Exit status: ", 1)[-1]
        two = re.search(r"(?:^|[;,] )2 (.*?)[;,] 3 ", section)
        if two is None or "permission denied" not in two.group(1):
            wrong.append(f"{name}: {section}")
    assert not wrong, "\n".join(wrong)
