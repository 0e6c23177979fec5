"""The default socket path and the checks that keep another local user from squatting it
(jtc_hw.api.paths). Files "of another user" are made by chown to uid 65534 (the tests run as
root)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from jtc_hw.api.paths import (
    default_socket_path,
    directory_problem,
    private_fallback_dir,
    socket_problem,
    trusted_uid,
)

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

