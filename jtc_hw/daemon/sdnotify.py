"""The systemd notification protocol (``sd_notify``), without libsystemd.

Theory of operation: systemd passes ``NOTIFY_SOCKET`` (a filesystem path, or an abstract-namespace
name written with a leading ``@``) to a ``Type=notify`` service. The service reports its state by
sending one datagram of newline-separated ``KEY=VALUE`` assignments to that socket
(``READY=1``, ``STATUS=...``, ``WATCHDOG=1``, ``STOPPING=1``, ...). With ``WatchdogSec=`` set,
systemd also passes ``WATCHDOG_USEC`` (and ``WATCHDOG_PID``, the process meant to ping) and kills
the service unless ``WATCHDOG=1`` arrives within that time; pinging at half of it is the
documented practice.

Each message opens a fresh non-blocking ``AF_UNIX``/``SOCK_DGRAM`` socket, sends one datagram and
closes the socket, as libsystemd's ``sd_notify`` does: no descriptor is held between calls (nothing
to leak or to close), no lock is needed (every call owns its socket, so any thread may call), and
a stalled systemd can never block the caller (a full receive queue fails the send instead).

A notifier without ``NOTIFY_SOCKET`` (run by hand, in tests, under another supervisor) does
nothing and returns ``False``. A failed send never raises: the first failure is logged at warning
on logger ``jtc_hw.sdnotify``, later ones at debug, so a broken socket cannot flood the journal
from a loop pinging the watchdog.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

__all__ = ["Notifier"]

logger = logging.getLogger("jtc_hw.sdnotify")


class Notifier:
    """Sends state notifications to the service manager named by ``NOTIFY_SOCKET``.

    Every sending method returns ``True`` when the datagram was handed to the kernel and ``False``
    when notification is disabled or the send failed (module docstring).

    Attributes:
        address: the socket address (``bytes`` with a leading NUL for the abstract namespace,
            ``str`` for a path), or ``None`` when notification is disabled.
        watchdog_interval_s: how often to call :meth:`watchdog` (half of ``WATCHDOG_USEC``), or
            ``None`` when the watchdog is not enabled for this process.
    """

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        """Reads ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` from ``environ``
        (default ``os.environ``).

        The environment is read once, here; later changes to it are not seen. The variables are
        not removed from ``os.environ`` (child processes that must not notify should be started
        with an environment lacking ``NOTIFY_SOCKET``; ``NotifyAccess=main`` makes systemd
        ignore them anyway). Never raises: malformed values disable the feature concerned and
        are logged at warning.
        """
        env = os.environ if environ is None else environ
        self.address: str | bytes | None = _parse_address(env.get("NOTIFY_SOCKET", ""))
        self.watchdog_interval_s: float | None = _parse_watchdog(
            env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
        )
        self._warned = False

    @property
    def enabled(self) -> bool:
        """Whether a notification socket is configured (messages are actually sent)."""
        return self.address is not None

    def ready(self, status: str | None = None) -> bool:
        """Tells the service manager that start-up is complete (``READY=1``), with an optional
        one-line ``status`` for ``systemctl status``."""
        return self.send(_with_status("READY=1", status))

    def status(self, text: str) -> bool:
        """Updates the free-form status line (``STATUS=...``; newlines become spaces)."""
        return self.send("STATUS=" + _one_line(text))

    def watchdog(self) -> bool:
        """Pings the service watchdog (``WATCHDOG=1``); call every :attr:`watchdog_interval_s`."""
        return self.send("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        """Tells the service manager that an orderly shutdown has begun (``STOPPING=1``), with
        an optional one-line ``status`` (what the shutdown is waiting for)."""
        return self.send(_with_status("STOPPING=1", status))

    def send(self, message: str) -> bool:
        """Sends ``message`` (newline-separated ``KEY=VALUE`` lines, UTF-8 on the wire) as one
        datagram: the primitive behind the other methods (also ``ERRNO=5``, ``MAINPID=...``).
        A send fails with no listener, permission denied, a full queue, ...
        """
        if self.address is None:
            return False
        data = message.encode("utf-8")
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
                sock.setblocking(False)
                sock.sendto(data, self.address)
        except OSError as exc:
            self._log_failure(exc)
            return False
        return True

    def _log_failure(self, exc: OSError) -> None:
        # Only the first failure is worth a warning; the watchdog pings every ~second and would
        # otherwise repeat the same line forever.
        level = logging.DEBUG if self._warned else logging.WARNING
        self._warned = True
        logger.log(
            level,
            "sd_notify to %r failed (%s); systemd will not see this service's state "
            "(check NOTIFY_SOCKET and that the service manager is alive)",
            self.address,
            exc,
        )


def _parse_address(value: str) -> str | bytes | None:
    """``NOTIFY_SOCKET`` to a socket address; ``None`` when unset or unusable."""
    if not value:
        return None
    if value.startswith("@"):
        # Abstract namespace: Linux names these with a leading NUL instead of a path.
        return b"\0" + value[1:].encode("utf-8")
    if value.startswith("/"):
        return value
    # systemd also knows "vsock:" addresses (VMs); nothing here runs under one.
    logger.warning(
        "NOTIFY_SOCKET=%r is neither an absolute path nor an abstract name (@...); "
        "systemd notification disabled",
        value,
    )
    return None


def _parse_watchdog(usec_text: str, pid_text: str) -> float | None:
    """The watchdog ping interval in seconds (half the timeout), as ``sd_watchdog_enabled``."""
    if not usec_text:
        return None
    try:
        usec = int(usec_text)
    except ValueError:
        usec = 0
    if usec <= 0:
        logger.warning("WATCHDOG_USEC=%r is not a positive integer; watchdog disabled", usec_text)
        return None
    if pid_text:
        try:
            pid = int(pid_text)
        except ValueError:
            logger.warning("WATCHDOG_PID=%r is not a process id; watchdog disabled", pid_text)
            return None
        if pid != os.getpid():
            # The watchdog belongs to another process (e.g. we are a child of the service).
            return None
    return usec / 2_000_000


def _one_line(text: str) -> str:
    return text.replace("\r", " ").replace("\n", " ")


def _with_status(head: str, status: str | None) -> str:
    return head if status is None else f"{head}\nSTATUS={_one_line(status)}"
