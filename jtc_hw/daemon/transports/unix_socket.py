"""The daemon's unix socket file: its directory, binding it, replacing a stale one, removing it.

What the unix socket adds to the request layer, beside the framing and slots it shares with TCP
(``jtc_hw.daemon.transports.server``): the socket file, whose permissions say who may connect,
and the peer's uid (``SO_PEERCRED``, ``connection.peer_identity``) that lets the daemon's own
user and root into the reserved slots.

Nobody else may be able to put a socket where clients look for the daemon: a directory the
daemon creates is writable by its user only (others may only enter it, as ``socket_mode``
allows them to connect), and the default place is refused if someone else prepared it. A
socket file left by a dead daemon is replaced; one a live daemon listens on, or a file that is
not a socket, is refused. On close the file is removed only if it is still the one bound.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import stat
from pathlib import Path

from ...api.paths import default_socket_path, directory_problem, group_id
from ...errors import ConfigurationError

__all__ = ["bind_unix", "directory_mode", "make_socket_directory", "remove_socket_file"]

log = logging.getLogger("jtc_hw.server")

SocketIdentity = tuple[int, int]
"""``(st_dev, st_ino)`` of the socket file the daemon bound."""


def directory_mode(socket_mode: int) -> int:
    """Mode of a socket directory the daemon creates: only its user may write it (nobody
    else can replace the socket), and whoever ``socket_mode`` lets connect may enter it."""
    mode = 0o700
    if socket_mode & 0o070:
        mode |= 0o010
    if socket_mode & 0o007:
        mode |= 0o001
    return mode


def _gid(group: str | int | None) -> int:
    """The gid of ``daemon.socket_group`` (``None``: -1, the daemon's own).

    Raises:
        ConfigurationError: there is no such group; it names it.
    """
    if group is None:
        return -1
    found = group_id(group)
    if found is None:
        raise ConfigurationError(
            f"there is no group {group!r} on this system (getent group {group})",
            "socket_group",
            group,
        )
    return found


def make_socket_directory(
    directory: Path, socket_mode: int, group: str | int | None = None
) -> None:
    """Create the socket's ``directory`` and its missing parents with
    :func:`directory_mode` (``0710`` for the default ``0660``: nobody else can write it, nor
    list it), of ``group`` (``daemon.socket_group``) if given; leave a directory that exists
    as it is.

    Raises:
        ConfigurationError: the group is unknown, or a directory cannot be created; it names
            it and the reason.
    """
    mode = directory_mode(socket_mode)
    gid = _gid(group)
    missing: list[Path] = []
    for d in (directory, *directory.parents):
        if os.path.lexists(d):
            break
        missing.append(d)
    try:
        for d in reversed(missing):
            try:
                os.mkdir(d, mode)
            except FileExistsError:
                continue  # made meanwhile by someone else: examined below
            if gid >= 0:
                os.chown(d, -1, gid)  # the group socket_mode lets in may enter
            os.chmod(d, mode)  # mkdir's mode is reduced by the umask
            log.info("created the socket's directory %s (mode %04o)", d, mode)
    except OSError as exc:
        raise ConfigurationError(
            f"cannot create the socket's directory {directory}: {exc.strerror or exc}",
            "socket",
        ) from None


def bind_unix(
    path: Path, socket_mode: int, group: str | int | None = None
) -> tuple[socket.socket, SocketIdentity]:
    """Bind (not listen) a unix stream socket at ``path`` with ``socket_mode``, of ``group``
    (``daemon.socket_group``; ``None``: the daemon's own).

    Raises:
        ConfigurationError: the group is unknown, the directory cannot be made or is
            untrustworthy (the default place), a live daemon listens there, the path is not a
            socket, or binding (or giving it the group) fails; each names the path and what
            to do.
    """
    gid = _gid(group)
    make_socket_directory(path.parent, socket_mode, group)
    if os.path.normpath(path) == os.path.normpath(default_socket_path()):
        # The default place: check that no other user could have prepared it for us.
        problem = directory_problem(str(path.parent))
        if problem is not None:
            raise ConfigurationError(
                f"refusing the default socket directory: {problem}. Remove it (as root) "
                "and start again, or set daemon.socket to a path in a directory only this "
                "daemon's user can write",
                "socket",
            )
    _remove_stale(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(str(path))
        # Nobody can connect before listen(), which start_unix_server calls: no window.
        if gid >= 0:
            try:
                os.chown(path, -1, gid)
            except PermissionError:
                raise ConfigurationError(
                    f"cannot give the socket {path} the group {group}: the daemon's user is "
                    "not a member of it (add it: usermod -aG GROUP USER)",
                    "socket_group",
                    group,
                ) from None
        os.chmod(path, socket_mode)
        st = os.stat(path)
    except ConfigurationError:
        sock.close()
        raise
    except OSError as exc:
        sock.close()
        raise ConfigurationError(
            f"cannot bind the unix socket {path}: {exc.strerror or exc}", "socket"
        ) from None
    return sock, (st.st_dev, st.st_ino)


def _remove_stale(path: Path) -> None:
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(st.st_mode):
        raise ConfigurationError(
            f"{path} exists and is not a socket; refusing to replace it (remove it, or "
            "choose another socket path)",
            "socket",
        )
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(1.0)
    try:
        probe.connect(str(path))
    except (ConnectionRefusedError, FileNotFoundError):
        log.info("replacing stale socket %s (no daemon listening)", path)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        return
    except OSError as exc:
        raise ConfigurationError(
            f"cannot tell whether a daemon listens on {path} ({exc}); stop it or remove "
            "the file",
            "socket",
        ) from None
    finally:
        probe.close()
    raise ConfigurationError(
        f"another daemon is listening on {path}; stop it first or choose another socket",
        "socket",
    )


def remove_socket_file(path: Path, identity: SocketIdentity) -> None:
    """Remove ``path`` if it is still the socket bound (``identity``); log otherwise."""
    try:
        st = os.stat(path)
        if (st.st_dev, st.st_ino) == identity:
            os.unlink(path)
        else:
            log.warning("%s was replaced by someone else; leaving it", path)
    except FileNotFoundError:
        pass
    except OSError as exc:
        log.warning("cannot remove %s: %s", path, exc)
