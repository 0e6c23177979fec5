"""One daemon per hardware: exclusive ``flock`` locks on lock files, one per device and socket.

Theory of operation
-------------------
Before the loop process configures any hardware it locks every device its components name
(``HardwareInterface.devices()``: a serial port's resolved path, ``can:<interface>:<channel>``);
before the API process starts the loop it locks its socket path. A lock is ``flock(LOCK_EX |
LOCK_NB)`` on a lock file, so it is held exactly as long as the process that took it lives
(the kernel releases it when the process dies, even by SIGKILL: no stale lock can block a
restart), and the file records the holder (the daemon's pid and its configuration file) for
the error a second daemon prints: "/dev/ttyUSB0 is already driven by pid 4242
(/etc/jtc-hw/robot.yaml)". A second daemon stops there, before it has sent anything.

Where the files are:

- devices: ``/run/lock/jtc-hw/`` (``/run/lock`` is the FHS place for lock files: a tmpfs that
  every user may write on common distributions, emptied at boot), created mode 1777 so that
  daemons of different users see each other's locks. If it cannot be used (``/run/lock`` not
  writable by this user), the fallback is ``jtc-hw-lock`` in the temporary directory, with a
  warning: daemons that use different directories do not see each other, so give the service
  ``/run/lock/jtc-hw`` (tmpfiles.d ``d /run/lock/jtc-hw 1777 root root -`` and
  ``ReadWritePaths=/run/lock/jtc-hw`` under ``ProtectSystem=strict``). ``JTC_HW_LOCK_DIR``
  overrides both (all daemons of a machine must agree on it). A file is named after its device
  (:func:`lock_file_name`): ``/dev/ttyUSB0`` -> ``dev-ttyUSB0.lock``.
- the socket: next to it, ``<socket>.lock``: whoever can use the socket path can use its
  directory, which is the socket's own (``RuntimeDirectory=`` under systemd).

Not done: ``flock`` on the serial device itself (pyserial's ``exclusive=True``, which other
tools honour) would need the second daemon to *open* the port to find out, and opening a tty
raises DTR/RTS and closing it drops them (``HUPCL``), which alone resets some boards: exactly
the touch this lock must prevent. The driver that opens the port may still lock it that way.

A released lock file is removed while still locked; a daemon that opened it meanwhile finds,
once it holds its lock, that the path no longer names its file, and starts over.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import stat
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

from ..errors import HardwareError

__all__ = [
    "LOCK_DIR",
    "LOCK_DIR_ENV",
    "DeviceBusy",
    "DeviceLock",
    "acquire",
    "lock_devices",
    "lock_directory",
    "lock_file_name",
    "socket_lock_path",
]

log = logging.getLogger("jtc_hw.locks")

LOCK_DIR: Final = "/run/lock/jtc-hw"
"""Where device lock files live (see the module docstring for the fallback)."""
LOCK_DIR_ENV: Final = "JTC_HW_LOCK_DIR"
"""Environment variable overriding :data:`LOCK_DIR` (every daemon of a machine must agree)."""
_SAFE = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.+@,=")


class DeviceBusy(HardwareError):
    """A device or socket is locked by another process.

    Attributes:
        name: the device (lock name) or socket path.
        pid: the holder's pid as its lock file records it, if it does.
        config: the holder's configuration file as recorded, if any.
    """

    def __init__(self, message: str, name: str, pid: int | None, config: str | None) -> None:
        super().__init__(message)
        self.name = name
        self.pid = pid
        self.config = config


@dataclass(frozen=True)
class _Owner:
    pid: int | None
    config: str | None


def lock_file_name(name: str) -> str:
    """The lock file's name for a device: injective, readable, safe in a shared directory.

    An absolute path loses its leading ``/``; ``/`` becomes ``-``; any other character but
    letters, digits and ``_.+@,=`` (and ``:`` in a non-path name) becomes ``%XX``, ``-`` and
    ``%`` included, so two devices never share a file: ``/dev/ttyUSB0`` -> ``dev-ttyUSB0.lock``,
    ``can:socketcand:127.0.0.1:29536:can0`` -> ``can:socketcand:127.0.0.1:29536:can0.lock``.
    A non-path name keeps its ``:``, which is escaped in paths; one without any ``:``, or
    starting with one, gets a leading ``:``, so that it can never equal a path's name nor
    another non-path name's.

    Raises:
        Nothing.
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
    """The directory for device lock files, created (mode 1777) if missing.

    Raises:
        HardwareError: ``JTC_HW_LOCK_DIR`` names a directory that cannot be used, or none of
            the candidates can (names them and what to check).
    """
    override = os.environ.get(LOCK_DIR_ENV)
    if override:
        problem = _usable(override)
        if problem:
            raise HardwareError(f"{LOCK_DIR_ENV}={override}: {problem}")
        return override
    problem = _usable(LOCK_DIR)
    if not problem:
        return LOCK_DIR
    fallback = os.path.join(tempfile.gettempdir(), "jtc-hw-lock")
    second = _usable(fallback)
    if second:
        raise HardwareError(
            f"no directory for the device locks: {LOCK_DIR}: {problem}; {fallback}: {second}; "
            f"create {LOCK_DIR} (mode 1777) or set {LOCK_DIR_ENV}"
        )
    log.warning(
        "device locks in %s: %s %s; daemons using %s do not see these locks (create it with "
        "mode 1777, e.g. tmpfiles.d 'd %s 1777 root root -')",
        fallback, LOCK_DIR, problem, LOCK_DIR, LOCK_DIR,
    )
    return fallback


def _usable(directory: str) -> str | None:
    """Why ``directory`` cannot hold lock files (created if missing), or ``None``."""
    try:
        os.mkdir(directory, 0o777)
    except FileExistsError:
        pass
    except OSError as exc:
        return f"cannot create it ({exc.strerror})"
    else:
        try:
            # The umask narrowed the mode; other users' daemons must add their files too.
            os.chmod(directory, 0o1777)
        except OSError:
            pass
    try:
        st = os.stat(directory)
    except OSError as exc:
        return f"cannot read it ({exc.strerror})"
    if not stat.S_ISDIR(st.st_mode):
        return "is not a directory"
    if not os.access(directory, os.W_OK | os.X_OK):
        return "is not writable by this user"
    return None


def socket_lock_path(socket_path: str) -> str:
    """The lock file of a socket path: ``<socket>.lock``, next to it.

    Raises:
        Nothing.
    """
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
        """Remove the lock file (while still holding it) and unlock. Idempotent.

        Raises:
            Nothing: a file that cannot be removed (another user's, in a sticky directory)
            stays; it is unlocked anyway.
        """
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if _same_file(fd, self.path):
                os.unlink(self.path)
        except OSError:
            pass
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
            configuration as recorded.
        HardwareError: the lock file cannot be created or opened (names it and why).
    """
    while True:
        fd = _open(name, path)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = _read_owner(fd)
            os.close(fd)
            by = f"pid {owner.pid}" if owner.pid is not None else "another process"
            where = f" ({owner.config})" if owner.config else ""
            raise DeviceBusy(
                f"{name} is already {what} by {by}{where}; stop that daemon first (lock file "
                f"{path})",
                name,
                owner.pid,
                owner.config,
            ) from None
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
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, record, 0)
    except OSError:
        pass  # opened read-only (another user's file): locked, owner not recorded
    return DeviceLock(name, path, fd)


def lock_devices(names: Sequence[str], *, config: str | None, pid: int | None = None
                 ) -> list[DeviceLock]:
    """Lock every device of ``names`` (duplicates once) in :func:`lock_directory`.

    All or nothing: if one is busy, those already locked are released before raising.

    Raises:
        DeviceBusy: a device is locked by another daemon (the message names it, its pid and
            configuration).
        HardwareError: no usable lock directory, or a lock file cannot be opened.
    """
    unique = list(dict.fromkeys(names))
    if not unique:
        return []
    directory = lock_directory()
    held: list[DeviceLock] = []
    try:
        for name in unique:
            held.append(
                acquire(name, os.path.join(directory, lock_file_name(name)), config=config,
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
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | flags, 0o666)
        except FileExistsError:
            continue  # created meanwhile by another daemon: open that one
        except OSError as exc:
            raise HardwareError(f"{name}: cannot create the lock file {path}: "
                                f"{exc.strerror}") from None
        try:
            os.fchmod(fd, 0o666)  # whoever locks it next records its own pid, whatever the umask
        except OSError:
            pass
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
