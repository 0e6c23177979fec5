"""The default socket path and the checks that keep another local user from squatting it
(jtc_hw.api.paths). Files "of another user" are made by chown to uid 65534 (the tests run as
root)."""

from __future__ import annotations

import grp
import os
import pwd
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import yaml
from helpers.daemon import WAIT_S, DaemonProcess, connect, robot_config

from jtc_hw.api import paths
from jtc_hw.api.paths import (
    client_socket_path,
    default_socket_path,
    directory_problem,
    listener_problem,
    private_fallback_dir,
    socket_problem,
    trusted_uid,
)
from jtc_hw.cli import main

from conftest import ROOT, make_robot_config

NOBODY = 65534

as_root = pytest.mark.skipif(
    os.geteuid() != 0, reason="makes files of another user (chown): needs root"
)


def test_default_socket_path_rule() -> None:
    assert default_socket_path({"RUNTIME_DIRECTORY": "/run/a:/run/b"}) == "/run/a/jtc-hw.sock"
    assert default_socket_path({"XDG_RUNTIME_DIR": "/run/user/7"}, uid=7) == (
        "/run/user/7/jtc-hw.sock"
    )
    assert default_socket_path({}, uid=0) == "/run/jtc-hw/jtc-hw.sock"
    assert default_socket_path({}, uid=1000) == "/tmp/jtc-hw-1000/jtc-hw.sock"
    assert private_fallback_dir(1000) == "/tmp/jtc-hw-1000"


def test_trusted_owners_are_oneself_and_root() -> None:
    assert trusted_uid(0, 1000) and trusted_uid(1000, 1000)
    assert not trusted_uid(NOBODY, 1000)


@as_root
def test_a_directory_is_fit_only_if_no_one_else_can_write_it(tmp_path: Path) -> None:
    mine = tmp_path / "mine"
    mine.mkdir(0o700)
    assert directory_problem(str(mine)) is None
    assert directory_problem(str(tmp_path / "missing")) is None  # the daemon will create it
    mine.chmod(0o750)
    assert directory_problem(str(mine)) is None  # group may enter, not write
    mine.chmod(0o770)
    problem = directory_problem(str(mine))
    assert problem is not None and "mode 0770" in problem and "replace" in problem
    mine.chmod(0o700)
    os.chown(mine, NOBODY, -1)
    problem = directory_problem(str(mine))
    assert problem == (
        f"{mine} belongs to uid {NOBODY}, not to uid 0 or root: another user may have "
        "created it to put a socket of theirs in the daemon's place"
    )
    assert directory_problem(str(mine), uid=NOBODY) is None  # it is nobody's own
    link = tmp_path / "link"
    link.symlink_to(tmp_path)
    assert "symbolic link" in (directory_problem(str(link)) or "")
    plain = tmp_path / "plain"
    plain.write_text("")
    assert "not a directory" in (directory_problem(str(plain)) or "")


@as_root
def test_a_socket_is_trusted_only_if_it_is_ours_or_roots(tmp_path: Path) -> None:
    directory = tmp_path / "run"
    directory.mkdir(0o700)
    path = directory / "jtc-hw.sock"
    assert socket_problem(str(path)) is None  # nothing there: connecting will say so
    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(path))
        assert socket_problem(str(path)) is None
        os.chown(path, NOBODY, -1)
        assert socket_problem(str(path)) == (
            f"the socket {path} belongs to uid {NOBODY}, not to uid 0 or root: another user "
            "may have created it to impersonate the daemon"
        )
    path.unlink()
    path.write_text("")
    assert socket_problem(str(path)) == f"{path} is not a socket"
    os.chown(directory, NOBODY, -1)
    assert "belongs to uid 65534" in (socket_problem(str(path)) or "")



def test_a_listener_is_trusted_if_it_runs_as_me_root_or_the_configured_group() -> None:
    assert listener_problem(10, 1000, me=1000) is None
    assert listener_problem(10, 0, me=1000) is None
    assert listener_problem(10, NOBODY, me=1000) == (
        f"the process listening on it (pid 10) runs as uid {NOBODY}, not as uid 1000 or root"
    )
    nogroup = grp.getgrgid(pwd.getpwuid(NOBODY).pw_gid).gr_name  # nobody's primary group
    assert listener_problem(10, NOBODY, nogroup, me=1000) is None
    assert listener_problem(10, NOBODY, str(grp.getgrnam(nogroup).gr_gid), me=1000) is None
    assert listener_problem(10, NOBODY, "root", me=1000) == (
        f"the process listening on it (pid 10) runs as uid {NOBODY}, not as uid 1000, root or "
        "a member of group root"
    )
    assert listener_problem(10, NOBODY, "no-such-group-jtc", me=1000) is not None


class ForeignListener:
    """A unix socket listened on by a child process running as another user, in a directory
    anyone can write (as /tmp): it accepts one connection and reports what it read until the
    client closed (or 10 s passed), without ever answering."""

    def __init__(self, directory: Path) -> None:
        self.path = directory / "jtc-hw.sock"
        self._report, child = socket.socketpair()
        self.pid = os.fork()
        if self.pid == 0:  # pragma: no cover - the child, as another user; never returns
            status = 1
            try:
                self._report.close()
                os.setgroups([])
                os.setgid(NOBODY)
                os.setuid(NOBODY)
                listener = socket.socket(socket.AF_UNIX)
                listener.bind(str(self.path))
                listener.listen()
                child.sendall(b"!")
                listener.settimeout(10.0)
                conn, _ = listener.accept()
                conn.settimeout(10.0)
                read = b""
                try:
                    while chunk := conn.recv(4096):
                        read += chunk
                except TimeoutError:
                    pass
                child.sendall(read)
                status = 0
            finally:
                os._exit(status)
        child.close()
        assert self._report.recv(1) == b"!", "the other user's listener did not start"

    def read(self) -> bytes:
        """What the listener read (waits for the child to end)."""
        data = b""
        while chunk := self._report.recv(65536):
            data += chunk
        self._report.close()
        _, status = os.waitpid(self.pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        return data


@as_root
@pytest.mark.parametrize("named_by", ["--socket", "--config"])
def test_jtc_hw_stop_refuses_a_socket_named_in_tmp_that_another_user_listens_on(
    named_by: str, tmp_path: Path
) -> None:
    """`jtc-hw stop --socket X` (or --config naming X) where a stranger listens on X: one line,
    exit 2, and the stranger never receives the stop."""
    shared = Path(tempfile.mkdtemp(prefix="jtc-hw-stranger-"))  # pytest's tmp_path is private
    shared.chmod(0o1777)  # like /tmp: anyone may create a socket here
    try:
        listener = ForeignListener(shared)
        if named_by == "--socket":
            target = str(listener.path)
        else:
            config = tmp_path / "robot.yaml"
            config.write_text(yaml.safe_dump(make_robot_config(
                listener.path, ["j1"], [{"name": "a", "kind": "mirror", "joints": ["j1"]}])))
            target = str(config)
        stop = subprocess.run(
            [sys.executable, "-m", "jtc_hw", "stop", named_by, target, "--timeout", "5"],
            capture_output=True, text=True, cwd=ROOT, timeout=60, stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )
        read = listener.read()
    finally:
        shutil.rmtree(shared)
    assert read == b""  # connected, identified, closed: not a byte sent
    assert stop.returncode == 2, (stop.stdout, stop.stderr)
    assert stop.stdout == ""
    assert stop.stderr.count("\n") == 1 and "Traceback" not in stop.stderr
    assert stop.stderr.startswith(
        f"error: refusing the daemon socket {listener.path}: the process listening on it "
        f"(pid {listener.pid}) runs as uid {NOBODY}, not as uid 0 or root: it is not your "
        "daemon. "
    )
    assert "daemon.socket_group" in stop.stderr


@as_root
def test_a_config_naming_the_listeners_group_trusts_it(tmp_path: Path) -> None:
    """The same stranger, but the configuration says its group is the daemon's
    (daemon.socket_group): the stop is sent to it (it never answers: exit 3)."""
    shared = Path(tempfile.mkdtemp(prefix="jtc-hw-service-"))
    shared.chmod(0o1777)
    group = grp.getgrgid(pwd.getpwuid(NOBODY).pw_gid).gr_name
    try:
        listener = ForeignListener(shared)
        config = tmp_path / "robot.yaml"
        config.write_text(yaml.safe_dump(make_robot_config(
            listener.path, ["j1"], [{"name": "a", "kind": "mirror", "joints": ["j1"]}],
            socket_group=group)))
        stop = subprocess.run(
            [sys.executable, "-m", "jtc_hw", "stop", "--config", str(config), "--timeout", "1"],
            capture_output=True, text=True, cwd=ROOT, timeout=60, stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )
        read = listener.read()
    finally:
        shutil.rmtree(shared)
    assert b'"op":"stop"' in read.replace(b" ", b"")
    assert stop.returncode == 3, (stop.stdout, stop.stderr)


# -- the system service's socket (config/jtc-hw.service, docs/systemd.md) --------------------


@pytest.fixture
def service(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``/run/jtc-hw`` in ``tmp_path``: ``run`` (root's, 0755, as /run) holds ``jtc-hw``; a
    login shell's own runtime directory (``xdg``) is empty."""
    run = tmp_path / "run"
    run.mkdir()
    run.chmod(0o755)
    monkeypatch.setattr(paths, "ROOT_SOCKET_DIR", str(run / "jtc-hw"))
    (tmp_path / "xdg").mkdir(0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.delenv("JTC_HW_SOCKET", raising=False)
    return run / "jtc-hw"


def test_a_client_looks_at_the_service_socket_when_its_own_place_is_empty(
    service: Path, tmp_path: Path
) -> None:
    own = tmp_path / "xdg" / "jtc-hw.sock"
    assert client_socket_path() == str(own)  # nothing anywhere: its own (error names it)
    service.mkdir(0o750)
    with socket.socket(socket.AF_UNIX) as daemon:
        daemon.bind(str(service / "jtc-hw.sock"))
        assert client_socket_path() == str(service / "jtc-hw.sock")
        with socket.socket(socket.AF_UNIX) as mine:
            mine.bind(str(own))  # a daemon of the user's own comes first
            assert client_socket_path() == str(own)


@as_root
def test_the_service_users_socket_is_trusted_where_only_root_could_make_it(
    service: Path, tmp_path: Path
) -> None:
    """systemd makes /run/jtc-hw for User=jtc-hw (RuntimeDirectoryMode=0750): a user in its
    group trusts that daemon there, and nowhere else."""
    service.mkdir(0o750)
    os.chown(service, NOBODY, NOBODY)
    path = service / "jtc-hw.sock"
    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(path))
        os.chown(path, NOBODY, -1)
        assert socket_problem(str(path), uid=1000) is None
        service.parent.chmod(0o775)  # someone else could have made /run/jtc-hw
        assert "belongs to uid 65534" in (socket_problem(str(path), uid=1000) or "")
        service.parent.chmod(0o755)
        service.chmod(0o770)  # its group could swap the socket
        assert "mode 0770" in (socket_problem(str(path), uid=1000) or "")
    elsewhere = tmp_path / "other"  # the same owner anywhere else is a stranger
    elsewhere.mkdir(0o750)
    os.chown(elsewhere, NOBODY, NOBODY)
    assert "belongs to uid 65534" in (socket_problem(str(elsewhere / "x.sock"), uid=1000) or "")


def test_cli_finds_the_service(service: Path, tmp_path: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    """From a login shell (its own $XDG_RUNTIME_DIR) ``jtc-hw status`` reaches the daemon the
    unit runs at /run/jtc-hw/jtc-hw.sock, with no option and with ``--config`` of a file
    that names no socket (the real-robot examples)."""
    service.mkdir(0o750)
    daemon = DaemonProcess(tmp_path / "d")
    daemon.socket = service / "jtc-hw.sock"
    config = robot_config(daemon.socket)
    daemon.config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    del config["daemon"]["socket"]
    client_config = tmp_path / "robot.yaml"
    client_config.write_text(yaml.safe_dump(config, sort_keys=False))
    daemon.start()
    try:
        daemon.wait_ready()
        # The status has its controller section once the loop's first status is in, which
        # can come after the socket accepts on a busy machine (it failed in CI under load).
        with connect(daemon) as client, client.subscribe_state() as sub:
            while "controller" not in client.get_status():
                sub.get(timeout_s=WAIT_S)  # the loop's next cycle, then ask again
        for extra in ([], ["--config", str(client_config)]):
            assert main(["status", "--timeout", str(WAIT_S), *extra]) == 0, capsys.readouterr()
            assert "controller" in capsys.readouterr().out
    finally:
        daemon.shutdown()
