"""One daemon per hardware: exclusive ``flock`` locks on lock files, one per device and socket.

Theory of operation
-------------------
Before the loop process configures any hardware it locks every device its components name
(``HardwareInterface.devices()``); before the API process starts the loop it locks its socket
path. A lock is ``flock(LOCK_EX | LOCK_NB)`` on a lock file, so it is held exactly as long as
the process that took it lives (the kernel releases it when the process dies, even by
SIGKILL: no stale lock can block a restart), and the file records the holder (the daemon's
pid and its configuration file) for the error a second daemon prints: "/dev/ttyUSB0 is
already driven by pid 4242 (/etc/jtc-hw/robot.yaml), user jtc-hw; stop that daemon first".
A second daemon stops there, before it has sent anything (who holds a lock the file does not
name: :func:`_find_owner`).

What a lock names: the device, not its spelling. A :class:`~jtc_hw.hardware.DeviceName` has
a canonical ``key`` (a serial port's real path, a SocketCAN interface's index, a socketcand
server's resolved address and port; on a CAN bus one key per motor id or node id, and one
for a bus-wide role such as the CANopen master: see the drivers' ``devices()``) that names
the file, and a ``label`` for messages. A plain string is both.

Where the files are, and who may use them (docs/decisions.md 25)
-----------------------------------------------------------------
Two duties: (a) two daemons on one device never both run, whoever runs them, and (b) a
stranger (a user who runs no daemon) cannot deny a start, as one could by taking a device's
lock file first in a directory every user may write. So the directory is the daemons' only:

- devices: ``/run/jtc-hw-locks`` (:data:`LOCK_DIR`; in ``/run`` only root can create it),
  made by the systemd unit as root or by a daemon that finds it missing, mode 3770 (setgid:
  the daemons of its group can take over a file another left behind; sticky: one cannot
  remove another's held file; daemons of several users: ``install -d -m 3770 -g <their
  group> /run/jtc-hw-locks``). If it is missing and cannot be created, the fallback is
  ``jtc-hw-lock`` in the temporary directory, with a warning: daemons that use different
  directories do not see each other. A directory that exists but cannot be used is an error,
  never a reason to fall back (another daemon may hold its locks there). ``JTC_HW_LOCK_DIR``
  overrides both (all daemons of a machine must agree on it).
- Every start checks the directory and the path above it before it locks anything
  (:func:`check_directory`), and refuses one that another user could use to deny a start,
  naming the directory, its owner and its mode. Lock files are created mode 0660.
- A file is named after its device's key (:func:`lock_file_name`): ``/dev/ttyUSB0`` ->
  ``dev-ttyUSB0.lock``.
- the socket: next to it, ``<socket>.lock``: whoever can use the socket path can use its
  directory, which is the socket's own (``RuntimeDirectory=`` under systemd, mode 0750).

Not done: ``flock`` on the serial device itself (pyserial's ``exclusive=True``): finding out
would mean opening the port, which alone resets some boards (docs/decisions.md 15), exactly the
touch this lock must prevent. The driver that opens the port may still lock it that way.

A released lock file is removed while still locked; a daemon that opened it meanwhile finds,
once it holds its lock, that the path no longer names its file, and starts over.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import stat
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

from ..api.paths import account_name
from ..errors import HardwareError
from ..hardware import DeviceName

__all__ = [
    "LOCK_DIR",
    "LOCK_DIR_ENV",
    "DeviceBusy",
    "DeviceLock",
    "acquire",
    "check_directory",
    "held_by",
    "lock_devices",
    "lock_directory",
    "lock_file_name",
    "socket_lock_path",
]

log = logging.getLogger("jtc_hw.locks")

LOCK_DIR: Final = "/run/jtc-hw-locks"
"""Where device lock files live (see the module docstring for the fallback)."""
LOCK_DIR_ENV: Final = "JTC_HW_LOCK_DIR"
"""Environment variable overriding :data:`LOCK_DIR` (every daemon of a machine must agree)."""
LOCK_DIR_MODE: Final = 0o3770
"""The mode a daemon creates the lock directory with: owner and group only, sticky, setgid."""
LOCK_FILE_MODE: Final = 0o660
"""The mode of a lock file: its group's daemons take over a file another left behind."""
_SAFE = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.+@,=")


class DeviceBusy(HardwareError):
    """A device or socket is locked by another process.

    Attributes:
        name: the device (its label) or socket path.
        pid: the holder's pid as its lock file records it, or as ``/proc/locks`` shows it.
        config: the holder's configuration file as recorded, if any.
        user: the holder's user name (or uid), if found.
    """

    def __init__(self, message: str, name: str, pid: int | None, config: str | None,
                 user: str | None = None) -> None:
        super().__init__(message)
        self.name = name
        self.pid = pid
        self.config = config
        self.user = user


@dataclass(frozen=True)
class _Owner:
    pid: int | None
    config: str | None
    user: str | None = None
    user_is_file_owner: bool = False


def lock_file_name(name: str) -> str:
    """The lock file's name for a device: injective, readable, safe in a shared directory.

    An absolute path loses its leading ``/``; ``/`` becomes ``-``; any other character but
    letters, digits and ``_.+@,=`` (and ``:`` in a non-path name) becomes ``%XX``, ``-`` and
    ``%`` included, so two devices never share a file: ``/dev/ttyUSB0`` -> ``dev-ttyUSB0.lock``,
    ``can:socketcand:127.0.0.1:29536:can0`` -> ``can:socketcand:127.0.0.1:29536:can0.lock``.
    A non-path name keeps its ``:``, which is escaped in paths; one without any ``:``, or
    starting with one, gets a leading ``:``, so that it can never equal a path's name nor
    another non-path name's.
    """
    is_path = name.startswith("/")
    if is_path:
        text = name[1:]
    elif ":" not in name or name.startswith(":"):
        text = ":" + name
    else:
        text = name
    out = []
    for char in text:
        if char in _SAFE or (char == ":" and not is_path):
            out.append(char)
        elif char == "/" and is_path:
            out.append("-")
        else:
            out.extend(f"%{byte:02X}" for byte in char.encode("utf-8"))
    escaped = "".join(out)
    if escaped.startswith("."):  # never a hidden file, never "." or ".."
        escaped = "%2E" + escaped[1:]
    return escaped + ".lock"


def lock_directory() -> str:
    """The directory for device lock files, created (mode 3770) if missing, and checked.

    Raises:
        HardwareError: ``JTC_HW_LOCK_DIR`` or :data:`LOCK_DIR` names a directory that cannot
            be used or that another user could use to deny a start (:func:`check_directory`),
            or no candidate can be created (names them and what to do).
    """
    override = os.environ.get(LOCK_DIR_ENV)
    if override:
        _prepare(override, f"{LOCK_DIR_ENV}={override}")
        return override
    try:
        _prepare(LOCK_DIR, LOCK_DIR)
    except _CannotCreate as exc:
        problem = str(exc)
    else:
        return LOCK_DIR
    fallback = os.path.join(tempfile.gettempdir(), "jtc-hw-lock")
    try:
        _prepare(fallback, fallback)
    except _CannotCreate as exc:
        raise HardwareError(
            f"no directory for the device locks: {problem}; {exc}; create {LOCK_DIR} "
            f"(install -d -m 3770 -g <the daemons' group> {LOCK_DIR}) or set {LOCK_DIR_ENV}"
        ) from None
    log.warning(
        "device locks in %s: %s; daemons using %s do not see these locks (create it, e.g. "
        "tmpfiles.d 'd %s 3770 root jtc-hw -')",
        fallback, problem, LOCK_DIR, LOCK_DIR,
    )
    return fallback


class _CannotCreate(HardwareError):
    """The lock directory does not exist and cannot be created: the one case that falls back."""


def _prepare(directory: str, what: str) -> None:
    """Create ``directory`` (:data:`LOCK_DIR_MODE`) if missing, then :func:`check_directory`.

    Raises:
        _CannotCreate: it does not exist and cannot be created.
        HardwareError: it exists but cannot be used, or is not safe.
    """
    try:
        os.mkdir(directory, 0o700)
    except FileExistsError:
        pass
    except OSError as exc:
        raise _CannotCreate(f"{what}: cannot create it ({exc.strerror})") from None
    else:
        try:
            os.chmod(directory, LOCK_DIR_MODE)  # the umask narrowed it; mkdir drops S_ISVTX
        except OSError as exc:
            raise HardwareError(f"{what}: cannot set its mode ({exc.strerror})") from None
    problem = check_directory(directory)
    if problem:
        raise HardwareError(f"{what}: {problem}")


def check_directory(directory: str) -> str | None:
    """Why ``directory`` cannot hold device locks (naming its owner and mode), or ``None``: owner
    root or this user up the whole path; the directory grants others nothing; group-writable
    only with the sticky bit; a directory above that others may write is sticky; and this user
    may write it."""
    uid = os.geteuid()
    path = os.path.abspath(directory)
    try:
        st = os.stat(path)
    except OSError as exc:
        return f"cannot read it ({exc.strerror})"
    if not stat.S_ISDIR(st.st_mode):
        return "is not a directory"
    mode = stat.S_IMODE(st.st_mode)
    if st.st_uid not in (0, uid):
        return (f"belongs to user {account_name(st.st_uid)} (mode {mode:04o}), who could deny or "
                f"allow any start: it must be root's or this user's ({account_name(uid)})")
    if mode & 0o007:
        return (f"mode {mode:04o} lets every user in (any of them could lock a device's file "
                f"and deny a start): chmod o= {path}")
    if mode & stat.S_IWGRP and not mode & stat.S_ISVTX:
        return (f"mode {mode:04o}: a group-writable lock directory must be sticky (else one "
                f"daemon's user can remove another's held lock file): chmod +t {path}")
    parent = os.path.dirname(path)
    while True:
        try:
            up = os.stat(parent)
        except OSError as exc:
            return f"cannot read {parent} ({exc.strerror})"
        up_mode = stat.S_IMODE(up.st_mode)
        if up.st_uid not in (0, uid):
            return (f"{parent} belongs to user {account_name(up.st_uid)}, who could replace "
                    f"the lock directory: use a directory under root's or this user's")
        if up_mode & (stat.S_IWGRP | stat.S_IWOTH) and not up_mode & stat.S_ISVTX:
            return (f"{parent} (mode {up_mode:04o}) lets other users replace the lock "
                    "directory: use a directory under one they cannot write")
        if parent == "/":
            break
        parent = os.path.dirname(parent)
    if not os.access(path, os.W_OK | os.X_OK):
        group = account_name(st.st_gid, group=True)
        return (f"is not writable by this user ({account_name(uid)}; it is "
                f"{account_name(st.st_uid)}:{group} {mode:04o}): add the daemon's user to group "
                f"{group}")
    return None


def socket_lock_path(socket_path: str) -> str:
    """The lock file of a socket path: ``<socket>.lock``, next to it."""
    return socket_path + ".lock"


class DeviceLock:
    """A held lock (from :func:`acquire`); :meth:`release` it, or let the process end."""

    def __init__(self, name: str, path: str, fd: int) -> None:
        self.name = name
        self.path = path
        self._fd: int | None = fd

    @property
    def held(self) -> bool:
        """Not released yet."""
        return self._fd is not None

    def release(self) -> None:
        """Remove the lock file (while still holding it) and unlock. Idempotent. Never raises: a
        file that cannot be removed (another user's, in a sticky directory) stays; it is
        unlocked anyway."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        with contextlib.suppress(OSError):
            if _same_file(fd, self.path):
                os.unlink(self.path)
        os.close(fd)  # the lock goes with the last descriptor of the open file

    def __enter__(self) -> DeviceLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def acquire(name: str, path: str, *, config: str | None, pid: int | None = None,
            what: str = "driven") -> DeviceLock:
    """Lock ``path`` for device (or socket) ``name`` without waiting, recording the owner.

    Args:
        name: what is locked, for messages (a device's lock name, a socket path).
        path: the lock file (its directory must exist).
        config: the configuration file of the daemon taking the lock (recorded).
        pid: the daemon's pid to record (default: this process's).
        what: the verb of the busy message: "<name> is already <what> by pid N (<config>)".

    Raises:
        DeviceBusy: another process holds the lock; the message names its pid and
            configuration as recorded (else the pid ``/proc/locks`` shows) and its user.
        HardwareError: the lock file cannot be created or opened (names it and why).
    """
    while True:
        fd = _open(name, path)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = _find_owner(fd)
            os.close(fd)
            raise _busy(name, path, what, owner) from None
        except OSError as exc:
            os.close(fd)
            raise HardwareError(f"{name}: cannot lock {path}: {exc.strerror}") from None
        # The previous holder removes the file while it still holds it: if the path no longer
        # names the file locked here, that happened between the open and the flock.
        try:
            same = _same_file(fd, path)
        except OSError as exc:
            os.close(fd)
            raise HardwareError(f"{name}: cannot check the lock file {path}: "
                                f"{exc.strerror}") from None
        if same:
            break
        os.close(fd)
    record = f"{os.getpid() if pid is None else pid}\n{config or ''}\n".encode()
    # OSError: opened read-only (another user's file): locked, owner not recorded
    with contextlib.suppress(OSError):
        os.ftruncate(fd, 0)
        os.pwrite(fd, record, 0)
    return DeviceLock(name, path, fd)


def held_by(name: str, path: str, *, what: str = "driven") -> DeviceBusy | None:
    """Whether another process holds the lock ``path`` (as :func:`acquire` would find), without
    locking, creating or changing anything: the busy error :func:`acquire` would raise, or None.

    For a client that must not touch what a running daemon serves (``jtc-hw demo --config``): it
    reads the holder from ``/proc/locks`` only, so a daemon starting at the same moment never
    finds the file locked by the one who asked. Where ``/proc/locks`` does not list it (not
    Linux), the answer is None: a check, not a guarantee; the caller must not rely on it alone.
    Never raises: a file that is missing or cannot be opened is not held by anyone it can see."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NOFOLLOW)
    except OSError:
        return None
    try:
        if _flock_holder(fd) is None:
            return None  # a file left by a daemon that was killed: free
        return _busy(name, path, what, _find_owner(fd))
    finally:
        os.close(fd)


def _busy(name: str, path: str, what: str, owner: _Owner) -> DeviceBusy:
    """The error for ``name`` (lock file ``path``) held by ``owner``."""
    by = f"pid {owner.pid}" if owner.pid is not None else "another process"
    where = f" ({owner.config})" if owner.config else ""
    who = ""
    if owner.user is not None:
        who = (f", lock file owned by user {owner.user}" if owner.user_is_file_owner
               else f", user {owner.user}")
    return DeviceBusy(
        f"{name} is already {what} by {by}{where}{who}; stop that daemon first (lock "
        f"file {path})",
        name,
        owner.pid,
        owner.config,
        owner.user,
    )


def lock_devices(names: Sequence[DeviceName | str], *, config: str | None,
                 pid: int | None = None) -> list[DeviceLock]:
    """Lock every device of ``names`` (the same key once) in :func:`lock_directory`.

    A :class:`~jtc_hw.hardware.DeviceName`'s key names the file and its label the messages; a
    plain string is both. All or nothing: if one is busy, those already locked are released
    before raising.

    Raises:
        DeviceBusy: a device is locked by another daemon (the message names it, its pid, user
            and configuration).
        HardwareError: no usable lock directory, or a lock file cannot be opened.
    """
    unique: dict[str, str] = {}
    for entry in names:
        key, label = (entry, entry) if isinstance(entry, str) else (entry.key, entry.label)
        unique.setdefault(key, label)
    if not unique:
        return []
    directory = lock_directory()
    held: list[DeviceLock] = []
    try:
        for key, label in unique.items():
            held.append(
                acquire(label, os.path.join(directory, lock_file_name(key)), config=config,
                        pid=pid)
            )
    except BaseException:
        for lock in reversed(held):
            lock.release()
        raise
    return held


def _open(name: str, path: str) -> int:
    flags = os.O_CLOEXEC | os.O_NOFOLLOW  # never follow a symlink planted in a shared dir
    while True:
        # Open an existing file without O_CREAT: with fs.protected_regular, O_CREAT on another
        # user's file in a sticky directory fails even when the file would open.
        for mode in (os.O_RDWR, os.O_RDONLY):
            try:
                return os.open(path, mode | flags)
            except FileNotFoundError:
                break
            except PermissionError:
                continue
            except OSError as exc:
                raise HardwareError(f"{name}: cannot open the lock file {path}: "
                                    f"{exc.strerror}") from None
        else:
            raise HardwareError(f"{name}: cannot open the lock file {path}: permission denied")
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | flags, LOCK_FILE_MODE)
        except FileExistsError:
            continue  # created meanwhile by another daemon: open that one
        except OSError as exc:
            raise HardwareError(f"{name}: cannot create the lock file {path}: "
                                f"{exc.strerror}") from None
        with contextlib.suppress(OSError):
            # Whoever of its group locks it next records its own pid, whatever the umask.
            os.fchmod(fd, LOCK_FILE_MODE)
        return fd


def _same_file(fd: int, path: str) -> bool:
    try:
        st = os.stat(path, follow_symlinks=False)
    except OSError as exc:
        if exc.errno in (errno.ENOENT, errno.ENOTDIR):
            return False
        raise
    own = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (own.st_dev, own.st_ino)


def _find_owner(fd: int) -> _Owner:
    """Who holds the lock on ``fd``'s file: the pid and configuration it recorded, else the
    pid ``/proc/locks`` shows; the user owning that process, else the file's owner."""
    recorded = _read_owner(fd)
    pid = recorded.pid
    if pid is None:
        pid = _flock_holder(fd)
    if pid is not None:
        try:
            uid = os.stat(f"/proc/{pid}").st_uid
        except OSError:
            pass  # gone meanwhile, or hidden (ProtectProc=invisible)
        else:
            return _Owner(pid, recorded.config, account_name(uid))
    try:
        file_owner = os.fstat(fd).st_uid
    except OSError:
        return _Owner(pid, recorded.config)
    return _Owner(pid, recorded.config, account_name(file_owner), user_is_file_owner=True)


def _flock_holder(fd: int) -> int | None:
    """The pid holding a ``flock`` on ``fd``'s file, from ``/proc/locks``, if listed.

    A line reads ``1: FLOCK  ADVISORY  WRITE 4242 fd:01:131090 0 EOF`` (the device's major
    and minor in hex, then the inode); a waiter's has ``->`` after the number.
    """
    try:
        st = os.fstat(fd)
        with open("/proc/locks", encoding="ascii", errors="replace") as table:
            lines = table.read().splitlines()
    except OSError:
        return None
    want = (os.major(st.st_dev), os.minor(st.st_dev), st.st_ino)
    for line in lines:
        fields = line.split()
        if len(fields) < 6 or fields[1] != "FLOCK":
            continue
        try:
            major, minor, inode = fields[5].split(":")
            if (int(major, 16), int(minor, 16), int(inode)) == want:
                return int(fields[4])
        except ValueError:
            continue
    return None


def _read_owner(fd: int) -> _Owner:
    try:
        text = os.pread(fd, 4096, 0).decode("utf-8", "replace")
    except OSError:
        return _Owner(None, None)
    lines = text.split("\n")
    try:
        pid: int | None = int(lines[0])
    except ValueError:
        pid = None  # the holder has not written it yet
    config = lines[1].strip() if len(lines) > 1 and lines[1].strip() else None
    return _Owner(pid, config)
