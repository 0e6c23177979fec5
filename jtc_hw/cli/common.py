"""What several ``jtc-hw`` commands share: exit statuses, the client options, the connection to
a daemon, and the lines they print the same way.

Every client command takes :func:`client_options` and opens its connection with
:func:`connect`, which picks the transport (``--zenoh PREFIX``, ``--tcp [HOST:PORT]``, else the
unix socket) and turns every "nobody answers" into :class:`NoDaemon` (exit status
:data:`EXIT_NO_DAEMON`), and a socket that is not trusted or not permitted into
:class:`~jtc_hw.errors.ConfigurationError` (exit status :data:`EXIT_BAD_INPUT`): a daemon may
well run there. :mod:`.parser` maps the exceptions to the exit statuses.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Final

from ..errors import ConfigurationError, JtcHwError

if TYPE_CHECKING:
    from ..api.client import Client

__all__ = [
    "CLIENT_EXIT_HELP", "EXIT_BAD_INPUT", "EXIT_GOAL_FAILED", "EXIT_NO_DAEMON", "EXIT_OK",
    "EXIT_WRITE_FAILED", "TOKEN_ENV", "NoDaemon", "Progress", "client_options", "connect",
    "fmt", "goal_result", "print_warnings", "zenoh_token",
]

EXIT_OK, EXIT_GOAL_FAILED, EXIT_BAD_INPUT, EXIT_NO_DAEMON = 0, 1, 2, 3
EXIT_WRITE_FAILED: Final = 4
"""``record`` only: writing the bag failed (it is closed with what it holds)."""

CLIENT_EXIT_HELP = (
    "Exit status: 0 success; 2 bad input (an unreadable --config or --zenoh-config), the "
    "socket is not served by a daemon you trust or you may not connect to it (permission "
    "denied), or the daemon answered and refused the request; 3 no daemon answers."
)
"""The exit statuses of the client commands that start or wait for no goal (no exit 1)."""

TOKEN_ENV: Final = "JTC_HW_ZENOH_TOKEN"
"""Where a client command finds the Zenoh token without ``--zenoh-token-file`` (never on the
command line: every local user can read another's arguments in ``ps``)."""


class NoDaemon(Exception):
    """No daemon answers (none running, no reply): exit status :data:`EXIT_NO_DAEMON`."""


# -- the connection ---------------------------------------------------------------------------


def client_options(p: argparse.ArgumentParser, func: Callable[[argparse.Namespace], int]) -> None:
    """Add the options of every client command (where the daemon is, how long to wait), and
    make ``func`` the command ``p`` runs."""
    p.add_argument("--socket", help="the daemon's Unix socket path")
    p.add_argument("--config", help="find the socket path in this robot configuration")
    p.add_argument("--tcp", nargs="?", const="", metavar="HOST:PORT",
                   help="reach the daemon over its TCP endpoint (default: --config's "
                   "daemon.tcp), with --config's token or $JTC_HW_TOKEN")
    p.add_argument("--zenoh", metavar="PREFIX",
                   help="reach the daemon over Zenoh at this key prefix (docs/zenoh.md)")
    p.add_argument("--zenoh-config", metavar="FILE",
                   help="Zenoh configuration for --zenoh (default: connect to a router "
                   "on tcp/127.0.0.1:7447)")
    p.add_argument("--zenoh-token-file", metavar="FILE",
                   help="file holding the daemon's daemon.zenoh.token, needed with --zenoh "
                   "to command (default: $JTC_HW_ZENOH_TOKEN; watching needs none)")
    p.add_argument(
        "--timeout",
        type=float,
        default=10.0,
        help="seconds to wait for the daemon's answers (default 10)",
    )
    p.set_defaults(func=func)


def _robot(args: argparse.Namespace) -> Any:
    """``--config``'s robot file, read (``None`` without ``--config``)."""
    if not getattr(args, "config", None):
        return None
    from ..daemon.robot import load_robot  # start-up time: the robot file's schemas, drivers

    return load_robot(args.config)


def _socket(args: argparse.Namespace, robot: Any) -> tuple[str, bool]:
    """The daemon's socket, and whether it was named (not found by the default rule);
    ``robot``: ``--config``'s robot file, or ``None``."""
    if getattr(args, "socket", None):
        return str(args.socket), True
    from ..api.client import default_socket_path  # start-up time: see connect()
    from ..api.paths import client_socket_path
    from ..api.paths import default_socket_path as default_rule

    if robot is not None:
        path = robot.daemon.socket
        if path == default_rule():  # not in the file: the default place, or the service's
            return client_socket_path(), False
        return path, True
    return default_socket_path(), bool(os.environ.get("JTC_HW_SOCKET"))


def _tcp(args: argparse.Namespace) -> tuple[tuple[str, int], str]:
    """``--tcp``'s address (else ``--config``'s ``daemon.tcp``) and the token (``--config``'s,
    else ``$JTC_HW_TOKEN``).

    Raises:
        ConfigurationError: no address or port, or no token; names what to give.
    """
    robot = _robot(args)
    tcp = robot.daemon.tcp if robot is not None else None
    host, port = (tcp.host, tcp.port) if tcp is not None else ("127.0.0.1", 0)
    if args.tcp:
        host, _, number = str(args.tcp).rpartition(":")
        if not host or not number.isdigit() or not 0 < int(number) < 65536:
            raise ConfigurationError(f"--tcp {args.tcp}: expected HOST:PORT, e.g. 127.0.0.1:7400")
        host, port = host.strip("[]"), int(number)
    if not port:
        raise ConfigurationError(
            "--tcp: no port: give --tcp HOST:PORT (the daemon logs 'listening on tcp ...'), or "
            "--config of a daemon whose daemon.tcp.port is set"
        )
    token = tcp.token if tcp is not None else os.environ.get("JTC_HW_TOKEN", "")
    if not token:
        raise ConfigurationError(
            "--tcp: no token: give --config FILE (its daemon.tcp.token) or set JTC_HW_TOKEN"
        )
    return (host, port), token


def zenoh_token(args: argparse.Namespace) -> str | None:
    """The token of ``--zenoh-token-file FILE`` (its first line), else ``$JTC_HW_ZENOH_TOKEN``,
    else ``None`` (the command may only watch).

    Raises:
        NoDaemon: the file cannot be read or is empty (the message names it).
    """
    path = getattr(args, "zenoh_token_file", None)
    if path is None:
        return os.environ.get(TOKEN_ENV) or None
    try:
        with open(path, encoding="utf-8") as f:
            token = f.readline().strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise NoDaemon(f"cannot read the Zenoh token from {path}: "
                       f"{getattr(exc, 'strerror', None) or exc}") from None
    if not token:
        raise NoDaemon(f"{path} is empty: put the daemon's daemon.zenoh.token on its first line")
    return token


def connect(args: argparse.Namespace, hello: bool = True) -> Client:
    """The client of a command's daemon, from its :func:`client_options`.

    Raises:
        NoDaemon: nobody answers there (the message says how to start or find the daemon);
            with ``--zenoh``, also eclipse-zenoh missing or an unreadable token file.
        ConfigurationError: an unreadable ``--config``/``--zenoh-config``, a bad ``--tcp``,
            or a socket not served by a daemon you trust or that you may not connect to.
    """
    # Start-up time: the client (and numpy, the controller's messages) load here, once the
    # command has shown that it started (send's progress bar), not when the command's module
    # is imported.
    from ..api.calls import PERMISSION, UNTRUSTED, ClientConnectionError
    from ..api.client import Client

    if getattr(args, "zenoh", None):
        token = zenoh_token(args)
        try:
            return Client.connect(f"zenoh:{args.zenoh}", zenoh_config=args.zenoh_config,
                                  timeout_s=args.timeout, hello=hello, token=token)
        except ValueError as exc:  # an unreadable configuration: bad input, said as such
            raise ConfigurationError(str(exc), "--zenoh-config") from None
        except (ClientConnectionError, TimeoutError) as exc:
            raise NoDaemon(f"{exc}") from exc
    if getattr(args, "tcp", None) is not None:
        address, token = _tcp(args)
        try:
            return Client.connect(tcp=address, token=token, timeout_s=args.timeout, hello=hello)
        except ClientConnectionError as exc:
            raise NoDaemon(str(exc)) from exc
    robot = _robot(args)  # also with --socket: its daemon.socket_group is trusted
    path, named = _socket(args, robot)
    try:
        return Client.connect(path, timeout_s=args.timeout, hello=hello, check_owner=not named,
                              trusted_group=robot.daemon.socket_group if robot else None)
    except ClientConnectionError as exc:
        if exc.code in (UNTRUSTED, PERMISSION):  # a daemon may run: not "is it running?"
            raise ConfigurationError(str(exc)) from exc
        # The client's message ends with its own "is the daemon running?": say it once.
        raise _unreachable(path, str(exc).removesuffix("; is the daemon running?")) from exc
    except (OSError, JtcHwError) as exc:
        raise _unreachable(path, str(exc)) from exc


def _unreachable(path: str, reason: str) -> NoDaemon:
    return NoDaemon(
        f"cannot reach a jtc-hw daemon at {path}: {reason}. Is it running "
        "('jtc-hw run CONFIG', or 'systemctl status jtc-hw')? Use --socket to point at it."
    )


# -- what commands print the same way ---------------------------------------------------------


def fmt(values: Sequence[float | None] | None, width: int = 9) -> str:
    """Numbers in fixed columns (``nan`` for a missing one; ``-`` for no values at all)."""
    if values is None:
        return "-"
    return " ".join(f"{v:{width}.4f}" if v is not None else f"{'nan':>{width}}" for v in values)


def print_warnings(warnings: Sequence[str], stream: Any = None) -> None:
    """One ``warning: ...`` line each, on ``stream`` (default stdout)."""
    # Under systemd, stderr goes to the journal: "<4>" gives the line warning priority.
    prefix = "<4>" if os.environ.get("JOURNAL_STREAM") and stream is sys.stderr else ""
    for warning in warnings:
        print(f"{prefix}warning: {warning}", file=stream or sys.stdout)


class Progress:
    """A one-line progress bar: time along the trajectory and the tracking error.

    On a terminal, :meth:`stage` shows the bar empty with what happens before the goal runs
    (reading the file, sending it), as soon as the command starts: a 20,000-point goal takes
    a second or more to read and send, which a user would otherwise watch as a silent prompt.
    Elsewhere (a pipe, a log) stages print nothing and the bar prints a line every 0.5 s.
    """

    def __init__(self, total_s: float, stream: Any = None, width: int = 30) -> None:
        self.total_s = max(total_s, 1e-9)
        self.stream = stream or sys.stdout
        self.width = width
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._last_print = 0.0
        self._shown = 0  # the length of the line on the terminal (stages are cleared)

    def stage(self, text: str) -> None:
        """Show the empty bar with ``text`` (a terminal only)."""
        if self.tty:
            self._show(f"[{'.' * self.width}] {text}")

    def clear(self) -> None:
        """Take a stage off the terminal's line, so the next print starts on an empty line."""
        if self.tty and self._shown:
            self.stream.write("\r" + " " * self._shown + "\r")
            self.stream.flush()
            self._shown = 0

    def update(self, feedback: dict[str, Any]) -> None:
        t = max(0.0, float(feedback.get("time_from_start") or 0.0))
        errors = [
            abs(e) for e in (feedback.get("error", {}).get("positions") or []) if e is not None
        ]
        worst = max(errors, default=0.0)
        frac = min(t / self.total_s, 1.0)
        filled = round(frac * self.width)
        line = (
            f"[{'#' * filled}{'.' * (self.width - filled)}] {t:6.2f}/{self.total_s:.2f} s"
            f"  max |error| {worst:.4f}"
        )
        if self.tty:
            self._show(line)
        elif time.monotonic() - self._last_print >= 0.5:
            self._last_print = time.monotonic()
            print(line, file=self.stream)

    def finish(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self._shown = 0

    def _show(self, line: str) -> None:
        pad = " " * max(0, self._shown - len(line))  # the rest of a longer line before it
        self.stream.write("\r" + line + pad)
        self.stream.flush()
        self._shown = len(line)


def goal_result(
    handle: Any, total_s: float, quiet: bool, timeout_s: float, progress: Progress | None = None
) -> int:
    """Watch a sent goal to its result (``send``, ``demo``): the progress bar unless ``quiet``
    (``progress``: the one already showing the stages before, else a new one), Ctrl-C cancels
    it; print the result; :data:`EXIT_OK` if it succeeded, else :data:`EXIT_GOAL_FAILED`."""
    if quiet:
        progress = None
    elif progress is None:
        progress = Progress(total_s)
    else:
        progress.total_s = max(total_s, 1e-9)
    try:
        for feedback in handle.feedback(timeout_s=timeout_s):
            if progress is not None:
                progress.update(feedback)
        result = handle.wait(timeout_s=timeout_s)
    except KeyboardInterrupt:
        if progress is not None:
            progress.finish()
        print("interrupted: canceling the goal", file=sys.stderr)
        result = handle.cancel(timeout_s=timeout_s)
        result = handle.wait(timeout_s=timeout_s)
    if progress is not None:
        progress.finish()
    text = result["error_string"]  # empty for a cancel, as upstream's
    print(
        f"goal {result['goal_id']} {result['status']} (error_code {result['error_code']})"
        + (f": {text}" if text else "")
    )
    if result.get("details"):  # a daemon before issue 11 sends none
        print(f"  {result['details']}")
    return EXIT_OK if result["status"] == "succeeded" else EXIT_GOAL_FAILED
