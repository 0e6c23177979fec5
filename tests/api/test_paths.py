"""The default socket path and the checks that keep another local user from squatting it
(jtc_hw.api.paths). Files "of another user" are made by chown to uid 65534 (the tests run as
root)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest
import yaml
from helpers.daemon import WAIT_S, DaemonProcess, robot_config

from jtc_hw.api import paths
from jtc_hw.api.paths import (
    client_socket_path,
    default_socket_path,
    directory_problem,
    private_fallback_dir,
    socket_problem,
    trusted_uid,
)
from jtc_hw.cli import main

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
        for extra in ([], ["--config", str(client_config)]):
            assert main(["status", "--timeout", str(WAIT_S), *extra]) == 0, capsys.readouterr()
            assert "controller" in capsys.readouterr().out
    finally:
        daemon.shutdown()
