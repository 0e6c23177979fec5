"""Where the daemon's socket is when nobody says, and whether a place for it can be trusted.

One rule for the daemon and its clients (docs/protocol.md, "Socket file"). The default socket
lives in a directory only the daemon's user (or root) can write, so that no other local user can
put a socket there first and have clients talk to it ("squatting"): ``$RUNTIME_DIRECTORY``
(systemd's ``RuntimeDirectory=``), ``$XDG_RUNTIME_DIR`` (the login session's, mode 0700),
``/run/jtc-hw`` for root, else a private directory ``/tmp/jtc-hw-<uid>/`` that the daemon
creates 0700 and that both sides check (owner, mode) before use. The checks here do not raise:
they return what is wrong, and the daemon and the client each turn it into their own error.

Whatever the path, named or found, a client talks only to a daemon it can trust: the process
listening (``SO_PEERCRED``, which cannot be forged) must run as the client's own user, as root,
or as a member of the configuration's ``daemon.socket_group`` (:func:`listener_problem`); a
socket named in a directory anyone can write, such as ``/tmp``, is otherwise anyone's.

When nothing is where a daemon of its own user would be, a client looks at the system service's
socket ``/run/jtc-hw/jtc-hw.sock`` (docs/systemd.md; from a login shell ``$XDG_RUNTIME_DIR`` is
set, so the per-user place alone would never find it). Only root can create an entry in
``/run``, so that place cannot be squatted either, and a client trusts the user root gave it to
(:func:`service_uid`) besides its own and root's.

A user the socket's mode keeps out gets ``EACCES`` from ``connect``; :func:`permission_problem`
says which file or directory, whose it is and what would let them in.
"""

from __future__ import annotations

import grp
import os
import pwd
import socket
import stat
import struct
from collections.abc import Mapping
from typing import Final

__all__ = [
    "ROOT_SOCKET_DIR",
    "SOCKET_NAME",
    "account_name",
    "client_socket_path",
    "default_socket_path",
    "directory_problem",
    "group_id",
    "listener_problem",
    "peer_pid",
    "peer_problem",
    "permission_problem",
    "private_fallback_dir",
    "socket_problem",
    "trusted_uid",
]

SOCKET_NAME: Final = "jtc-hw.sock"
ROOT_SOCKET_DIR = "/run/jtc-hw"
"""The default directory of a daemon run by root without a runtime directory, and the systemd
unit's ``RuntimeDirectory=`` (``$RUNTIME_DIRECTORY``): where clients look last."""


def private_fallback_dir(uid: int | None = None) -> str:
    """``/tmp/jtc-hw-<uid>``: the last resort, for a user without a runtime directory."""
    return f"/tmp/jtc-hw-{os.geteuid() if uid is None else uid}"


def default_socket_path(environ: Mapping[str, str] | None = None, uid: int | None = None) -> str:
    """Where the socket goes when ``daemon.socket`` is not given.

    ``$RUNTIME_DIRECTORY/jtc-hw.sock`` (systemd's ``RuntimeDirectory=``; the first one if it
    lists several), else ``$XDG_RUNTIME_DIR/jtc-hw.sock``, else ``/run/jtc-hw/jtc-hw.sock`` for
    root, else ``/tmp/jtc-hw-<uid>/jtc-hw.sock``. No I/O.

    Args:
        environ: the environment to look in (default: ``os.environ``).
        uid: whose default (default: this process's effective uid).
    """
    env = os.environ if environ is None else environ
    runtime = env.get("RUNTIME_DIRECTORY", "").split(":")[0]
    if runtime:
        return os.path.join(runtime, SOCKET_NAME)
    xdg = env.get("XDG_RUNTIME_DIR", "")
    if xdg:
        return os.path.join(xdg, SOCKET_NAME)
    uid = os.geteuid() if uid is None else uid
    if uid == 0:
        return os.path.join(ROOT_SOCKET_DIR, SOCKET_NAME)
    return os.path.join(private_fallback_dir(uid), SOCKET_NAME)


def _may_exist(path: str) -> bool:
    """Whether something may be at ``path``: it is there, or it cannot be seen for lack of
    permission (a directory on its way that this user may not search)."""
    try:
        os.lstat(path)
    except PermissionError:
        return True
    except OSError:
        return False
    return True


def client_socket_path(environ: Mapping[str, str] | None = None, uid: int | None = None) -> str:
    """Where a client looks when no socket is named: :func:`default_socket_path`, or the
    system service's ``/run/jtc-hw/jtc-hw.sock`` when nothing is at the former and something
    is at the latter (a login shell's ``$XDG_RUNTIME_DIR`` is not the service's directory), or
    may be: a user kept out of ``/run/jtc-hw`` is told so when connecting, not that nothing
    listens at their own place.
    """
    own = default_socket_path(environ, uid)
    service = os.path.join(ROOT_SOCKET_DIR, SOCKET_NAME)
    if own != service and not os.path.lexists(own) and _may_exist(service):
        return service
    return own


def service_uid(directory: str) -> int | None:
    """The owner of ``directory`` if it is the service's (:data:`ROOT_SOCKET_DIR`) and only
    root could have made it: its parent is root's and nobody else can write there. That owner
    was given it by root (systemd's ``RuntimeDirectory=`` with ``User=``). Else ``None``,
    also for a directory that cannot be examined.
    """
    if os.path.normpath(directory) != os.path.normpath(ROOT_SOCKET_DIR):
        return None
    try:
        st = os.lstat(directory)
        parent = os.stat(os.path.dirname(os.path.normpath(directory)))
    except OSError:
        return None
    if not stat.S_ISDIR(st.st_mode) or parent.st_uid != 0 or parent.st_mode & 0o022:
        return None
    return st.st_uid


def trusted_uid(owner: int, uid: int | None = None) -> bool:
    """Whether a file or peer of ``owner`` may be trusted by ``uid``: itself or root."""
    return owner in (0, os.geteuid() if uid is None else uid)


def group_id(group: str | int) -> int | None:
    """The gid of ``group`` (a name, or a number as an int or a string), or ``None`` if this
    system has no such group.
    """
    if isinstance(group, int) or group.isdigit():
        try:
            return grp.getgrgid(int(group)).gr_gid
        except (KeyError, OverflowError):
            return None
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        return None


def _in_group(uid: int, gid: int) -> bool:
    try:
        user = pwd.getpwuid(uid)
    except KeyError:
        return False
    if user.pw_gid == gid:
        return True
    try:
        return user.pw_name in grp.getgrgid(gid).gr_mem
    except KeyError:
        return False


def listener_problem(
    pid: int, uid: int, group: str | int | None = None, me: int | None = None
) -> str | None:
    """What makes the process ``pid`` (running as ``uid``) listening on a socket
    untrustworthy for user ``me``, or ``None``: it must run as ``me``, as root, or as a member
    of ``group`` (``daemon.socket_group``; a member by its primary group or the group's list;
    a group unknown here trusts nobody).
    """
    me = os.geteuid() if me is None else me
    if trusted_uid(uid, me):
        return None
    gid = None if group is None else group_id(group)
    if gid is not None and _in_group(uid, gid):
        return None
    who = f"uid {me} or root" if group is None else f"uid {me}, root or a member of group {group}"
    return f"the process listening on it (pid {pid}) runs as uid {uid}, not as {who}"


def directory_problem(directory: str, uid: int | None = None) -> str | None:
    """What makes ``directory`` unfit to hold the daemon's socket for ``uid``, or ``None``.

    Fit: a real directory (not a symbolic link) owned by ``uid`` or root (or the service's
    directory, :func:`service_uid`) that no one else can write. Anyone who can write it can
    replace the socket with their own. A missing directory is fit (the daemon creates it,
    0700); one that cannot be examined is reported as the problem.
    """
    uid = os.geteuid() if uid is None else uid
    try:
        st = os.lstat(directory)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"{directory} cannot be examined: {exc.strerror or exc}"
    if stat.S_ISLNK(st.st_mode):
        return f"{directory} is a symbolic link, not a directory of its own"
    if not stat.S_ISDIR(st.st_mode):
        return f"{directory} is not a directory"
    if not trusted_uid(st.st_uid, uid) and st.st_uid != service_uid(directory):
        return (
            f"{directory} belongs to uid {st.st_uid}, not to uid {uid} or root: another user "
            "may have created it to put a socket of theirs in the daemon's place"
        )
    if st.st_mode & 0o022:
        return (
            f"{directory} has mode {stat.S_IMODE(st.st_mode):04o}: users other than its owner "
            "can write it and so replace the daemon's socket (it must not be group- or "
            "world-writable)"
        )
    return None


def socket_problem(path: str, uid: int | None = None) -> str | None:
    """What makes the socket file ``path`` untrustworthy for ``uid``, or ``None``.

    The file must be a socket owned by ``uid`` or root (the daemon's socket, made by a daemon
    of this user or by a system service), or in the service's directory by its owner
    (:func:`service_uid`), in a directory fit for it (:func:`directory_problem`).
    A missing file is not a problem here (connecting will say nobody listens), nor one this
    user may not see (connecting will say whose directory keeps them out).
    """
    uid = os.geteuid() if uid is None else uid
    problem = directory_problem(os.path.dirname(path) or ".", uid)
    if problem is not None:
        return problem
    try:
        st = os.lstat(path)
    except (FileNotFoundError, PermissionError):
        # Nothing there, or the fit directory keeps this user out: connecting will say so
        # (nobody listens; permission denied, :func:`permission_problem`).
        return None
    except OSError as exc:
        return f"{path} cannot be examined: {exc.strerror or exc}"
    if not stat.S_ISSOCK(st.st_mode):
        return f"{path} is not a socket"
    if not trusted_uid(st.st_uid, uid) and st.st_uid != service_uid(os.path.dirname(path)):
        return (
            f"the socket {path} belongs to uid {st.st_uid}, not to uid {uid} or root: another "
            "user may have created it to impersonate the daemon"
        )
    return None


def account_name(number: int, group: bool = False) -> str:
    """The name of user (or ``group``) ``number``; the number itself if it has none."""
    try:
        return grp.getgrgid(number).gr_name if group else pwd.getpwuid(number).pw_name
    except KeyError:
        return str(number)


def _access(path: str, mode: int) -> bool:
    return os.access(path, mode, effective_ids=os.access in os.supports_effective_ids)


def _ways_in(gid: int, group: str, uid: int | None = None) -> str:
    """What lets user ``uid`` in through group ``gid`` (whose bit allows it): joining it, or,
    already a member, a new login (a process's groups are fixed when the session starts)."""
    uid = os.geteuid() if uid is None else uid
    if _in_group(uid, gid) and gid != os.getegid() and gid not in os.getgroups():
        return (
            f"you are in group {group}, but this login is not yet: log in again "
            f"(or run 'newgrp {group}')"
        )
    return (
        f"join its group (sudo usermod -aG {group} $USER, then log in again), or set "
        "daemon.socket_group (a group of yours, with daemon.socket_mode 0660) in the daemon's "
        "configuration"
    )


def permission_problem(path: str) -> str:
    """Why this process may not connect to the unix socket ``path`` (``connect`` said
    ``EACCES``): the first directory on the way it may not search, else the socket file it may
    not write, named with its owner, group and mode, and what would let this user in.

    Returns, for example, ``"the daemon socket /run/jtc-hw/jtc-hw.sock (owner jtc-hw, group
    jtc-hw, mode 0660): join its group (sudo usermod -aG jtc-hw $USER, then log in again),
    or ..."``; without a cause in the file modes (a security module refused), what to check.
    What cannot be examined is left out.
    """
    full = os.path.abspath(path)
    ancestors = [os.path.dirname(full)]
    while ancestors[-1] != os.path.dirname(ancestors[-1]):
        ancestors.append(os.path.dirname(ancestors[-1]))
    blocker, bit, intro = full, stat.S_IWGRP, f"the daemon socket {path}"
    for directory in reversed(ancestors):
        if not _access(directory, os.X_OK):
            blocker, bit = directory, stat.S_IXGRP
            intro = f"the daemon socket {path}: its directory {directory}"
            break
    else:
        if _access(full, os.W_OK):
            return (
                f"the daemon socket {path}: its file modes would let you in (a security "
                "policy such as AppArmor or SELinux may refuse it; see the system log)"
            )
    try:
        st = os.stat(blocker)
    except OSError:
        return f"{intro}: check its permissions (ls -ld {blocker})"
    group = account_name(st.st_gid, group=True)
    what = (
        f"{intro} (owner {account_name(st.st_uid)}, group {group}, "
        f"mode {stat.S_IMODE(st.st_mode):04o})"
    )
    if st.st_mode & bit:
        return f"{what}: {_ways_in(st.st_gid, group)}"
    return (
        f"{what} lets no group in: set daemon.socket_group (a group of yours) and "
        "daemon.socket_mode 0660 in the daemon's configuration, then join that group"
    )


def _peer_credentials(sock: socket.socket) -> tuple[int, int] | None:
    """``(pid, uid)`` of the process listening on the unix socket ``sock`` is connected to
    (``SO_PEERCRED``, recorded by the kernel at its ``listen``: it cannot be forged); None off
    Linux.

    Raises:
        OSError: the kernel would not say.
    """
    peercred = getattr(socket, "SO_PEERCRED", None)
    if peercred is None:  # pragma: no cover - not Linux
        return None
    pid, uid, _gid = struct.unpack(
        "3i", sock.getsockopt(socket.SOL_SOCKET, peercred, struct.calcsize("3i"))
    )
    return int(pid), uid


def peer_pid(sock: socket.socket) -> int | None:
    """The pid of the process listening on the unix socket ``sock`` is connected to, or None
    if not known."""
    try:
        credentials = _peer_credentials(sock)
    except OSError:
        return None
    return None if credentials is None else credentials[0]


def peer_problem(sock: socket.socket, path: str, group: str | int | None) -> str | None:
    """Whether the process listening on ``sock`` is this user's, root's, ``group``'s, or the
    system service's user's at its socket ``path`` (off Linux the file owner check stands
    alone)."""
    try:
        credentials = _peer_credentials(sock)
    except OSError as exc:
        return f"the listening process cannot be identified ({exc})"
    if credentials is None:
        return None
    pid, uid = credentials
    if uid == service_uid(os.path.dirname(path)):
        return None
    problem = listener_problem(pid, uid, group)
    return None if problem is None else f"{problem}: it is not your daemon"
