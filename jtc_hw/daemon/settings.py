"""The robot file's ``daemon:`` section: its schema tables and the frozen settings they make.

Declared with the one schema engine (:mod:`jtc_hw.config.schema`), like the controller's
parameters and each hardware kind's (``daemon.zenoh``'s in :mod:`.zenoh_config`). A row gives a
setting's type, default, range and, where a rule needs more, its check (the TCP host's loopback
rule, the token's length, the socket's mode), so each rule is written once.
:func:`daemon_settings` reads the section; each settings dataclass checks its fields against the
same rows when built (:func:`~jtc_hw.config.schema.check_fields`), so an instance a program
builds directly (the tests' servers) is as valid as one read from a file.
:class:`DaemonSettings` is what the server and the transports take.
"""

from __future__ import annotations

import ipaddress
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Final

from ..api.framing import DEFAULT_MAX_MESSAGE_BYTES
from ..api.paths import default_socket_path
from ..config.schema import (
    ParamKind,
    ParamSpec,
    check_fields,
    check_value,
    param_table,
    validate_params,
)
from ..config.values import describe
from ..errors import ConfigurationError
from .ros2_config import ROS2_PARAMETERS, Ros2Settings, ros2_settings
from .zenoh_config import (
    MIN_TOKEN_LENGTH,
    TOKEN_HINT,
    ZENOH_PARAMETERS,
    ZenohSettings,
    is_loopback,
    zenoh_settings,
)

__all__ = [
    "DAEMON_PARAMETERS",
    "DEFAULT_API_STALL_S",
    "FOXGLOVE_PARAMETERS",
    "LOG_LEVELS",
    "MIN_API_STALL_S",
    "MIN_TOKEN_LENGTH",
    "REALTIME_PARAMETERS",
    "SERVER_PARAMETERS",
    "TCP_PARAMETERS",
    "DaemonSettings",
    "FoxgloveSettings",
    "RealtimeSettings",
    "TcpSettings",
    "daemon_settings",
    "default_flight_recorder_dir",
    "is_loopback",
]

LOG_LEVELS: Final = ("debug", "info", "warning", "error")
DEFAULT_API_STALL_S: Final = 0.5
"""Default ``daemon.api_stall_s``."""
MIN_API_STALL_S: Final = 0.05
"""Smallest ``daemon.api_stall_s``: the API process is a normally scheduled Python process; a
garbage collection or a busy moment must not end goals."""
MAX_SOCKET_PATH_BYTES: Final = 107
"""``sun_path`` holds 108 bytes including the terminating NUL."""

_OCTAL_MODE = re.compile(r"(?:0o|0)?([0-7]{1,4})")
_A_STRING: Final = ParamSpec("string", ParamKind.STRING, "", "a string")


# -- The checks a row's kind does not cover ----------------------------------------------------


def _loopback_host(value: Any, path: str) -> str:
    """``daemon.tcp.host``: the TCP endpoint is protected by a token only, so loopback only."""
    host: str = check_value(_A_STRING, value, path)
    if not is_loopback(host):
        raise ConfigurationError(
            f"{host!r} is not a loopback address (127.0.0.0/8, ::1 or localhost): the "
            "endpoint is protected by a token only, without encryption; reach it from "
            "another machine through an SSH tunnel",
            path,
            host,
        )
    return host


def _token(value: Any, path: str) -> str:
    """``daemon.tcp.token``: at least :data:`MIN_TOKEN_LENGTH` characters, never echoed."""
    token: str = check_value(_A_STRING, value, path)
    if len(token) < MIN_TOKEN_LENGTH:
        raise ConfigurationError(
            f"must be at least {MIN_TOKEN_LENGTH} characters long, got {len(token)}; "
            f"{TOKEN_HINT}",
            path,
            None,  # never echo a secret
        )
    return token


def _socket_mode(value: Any, path: str) -> int:
    """An int (YAML ``0660`` is already 432) or an octal string: ``"0660"``, ``"0o660"``."""
    if isinstance(value, str):
        match = _OCTAL_MODE.fullmatch(value.strip())
        if match is None:
            raise ConfigurationError(
                f"expected an octal file mode such as \"0660\", got {value!r}", path, value
            )
        mode = int(match.group(1), 8)
    elif isinstance(value, int) and not isinstance(value, bool):
        mode = value
    else:
        raise ConfigurationError(
            f"expected a file mode (an integer, or an octal string such as \"0660\"), got "
            f"{describe(value)}",
            path,
            value,
        )
    if not 0 <= mode <= 0o777:
        raise ConfigurationError(
            f"{value!r} is not a permission mode (0 to 0o777); write it in octal: 0660 or "
            "\"0660\"",
            path,
            value,
        )
    if mode & 0o600 != 0o600:
        raise ConfigurationError(
            f"{oct(mode)} does not give the owner read and write permission (0o600): the "
            "daemon's own user could not connect",
            path,
            value,
        )
    return mode


# -- Schema ------------------------------------------------------------------------------------

TCP_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("host", ParamKind.STRING, "127.0.0.1", "loopback address to listen on",
              coerce=_loopback_host),
    ParamSpec("port", ParamKind.INT, 0, "TCP port (0: any free port)", minimum=0,
              maximum=65535),
    ParamSpec("token", ParamKind.STRING, "",
              f"shared secret clients must present (at least {MIN_TOKEN_LENGTH} characters)",
              required=True, coerce=_token),
    ParamSpec("max_clients", ParamKind.INT, 8,
              "simultaneous authenticated TCP connections (the unix socket has its own)",
              minimum=1),
    ParamSpec("max_unauthenticated", ParamKind.INT, 16,
              "TCP connections that may wait to authenticate at once, apart from max_clients "
              "(a newcomer beyond it replaces the one waiting longest)", minimum=1),
    ParamSpec("auth_timeout_s", ParamKind.FLOAT, 1.0,
              "a TCP connection is closed unless it authenticates this long after opening, s",
              minimum=0.05, maximum=60.0),
    ParamSpec("auth_failure_delay_s", ParamKind.FLOAT, 0.5,
              "failed authentications are answered at most one per this long per address, s",
              minimum=0.0, maximum=60.0),
)
"""``daemon.tcp.*``."""

REALTIME_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("priority", ParamKind.INT, 0,
              "SCHED_FIFO priority of the loop (0: normal scheduling)", minimum=0, maximum=99),
    ParamSpec("lock_memory", ParamKind.BOOL, False, "mlockall the loop's memory"),
    ParamSpec("cpu_affinity", ParamKind.INTS, (), "CPUs the loop may run on (empty: any)",
              minimum=0, unique=True),
)
"""``daemon.realtime.*``."""

FOXGLOVE_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("host", ParamKind.STRING, "127.0.0.1",
              "address the live view listens on (loopback: only this machine)"),
    ParamSpec("port", ParamKind.INT, 8765, "WebSocket port (0: any free port)", minimum=0,
              maximum=65535),
    ParamSpec("rate", ParamKind.FLOAT, None,
              "joint states and controller state published per second, Hz (default: the "
              "controller's state_publish_rate, which is also the most)", nullable=True,
              minimum=0.1),
)
"""``daemon.foxglove.*``."""

DAEMON_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("socket", ParamKind.STRING, None,
              "Unix socket path (default: $RUNTIME_DIRECTORY, $XDG_RUNTIME_DIR or /tmp)",
              nullable=True),
    ParamSpec("socket_mode", ParamKind.INT, 0o660, "permissions of the socket file",
              coerce=_socket_mode),
    ParamSpec("socket_group", ParamKind.STRING, None,
              "group of the socket file (a name or gid; default: the daemon's): its members "
              "may connect (socket_mode 0660), and clients given this file trust a daemon "
              "run by one of them", nullable=True),
    ParamSpec("tcp", ParamKind.SECTION, None, "optional TCP endpoint on a loopback address",
              nullable=True, fields=TCP_PARAMETERS),
    ParamSpec("max_clients", ParamKind.INT, 16,
              "simultaneous unix socket connections (2 more for the daemon's user and root)",
              minimum=1),
    ParamSpec("idle_timeout_s", ParamKind.FLOAT, 300.0,
              "close a connection without a request, subscription or running goal for this "
              "long (0: never)", minimum=0.0),
    ParamSpec("max_message_bytes", ParamKind.INT, DEFAULT_MAX_MESSAGE_BYTES,
              "largest accepted message", minimum=1024),
    ParamSpec("realtime", ParamKind.SECTION, MappingProxyType({}),
              "scheduling of the control loop", nullable=True, fields=REALTIME_PARAMETERS),
    ParamSpec("api_stall_s", ParamKind.FLOAT, DEFAULT_API_STALL_S,
              "how long the control loop's messages may wait for the API process before the "
              "loop ends the active goal ABORTED and holds, s", minimum=MIN_API_STALL_S),
    ParamSpec("log_level", ParamKind.STRING, "info", "logging threshold", choices=LOG_LEVELS),
    ParamSpec("foxglove", ParamKind.SECTION, None,
              "live view over the Foxglove WebSocket protocol (off when absent; needs "
              "jtc_hw[foxglove])", nullable=True, fields=FOXGLOVE_PARAMETERS),
    ParamSpec("flight_recorder_s", ParamKind.FLOAT, 10.0,
              "seconds of state the flight recorder keeps and writes as a bag before an abort, "
              "fault, rearm or SIGTERM (0: off)", minimum=0.0, maximum=3600.0),
    ParamSpec("flight_recorder_dir", ParamKind.STRING, None,
              "directory of the flight recorder's bags (default: $STATE_DIRECTORY/flight, "
              "$XDG_STATE_HOME/jtc-hw/flight or ~/.local/state/jtc-hw/flight)", nullable=True),
    ParamSpec("flight_recorder_keep", ParamKind.INT, 20,
              "flight recorder bags kept (the oldest are removed)", minimum=1),
    ParamSpec("record", ParamKind.STRING, None,
              "directory where each run of the daemon is recorded as a bag from its start "
              "(default: not recorded)", nullable=True),
    ParamSpec("zenoh", ParamKind.SECTION, None,
              "the daemon on a Zenoh network (off when absent; needs jtc_hw[zenoh]; "
              "docs/zenoh.md)", nullable=True, fields=ZENOH_PARAMETERS),
    ParamSpec("ros2", ParamKind.SECTION, None,
              "the daemon as upstream's controller in a ROS 2 graph over rmw_zenoh (off when "
              "absent; needs jtc_hw[ros2]; docs/ros2.md)", nullable=True, fields=ROS2_PARAMETERS),
)
"""``daemon.*``."""

SERVER_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("client_queue_size", ParamKind.INT, 256,
              "queued outgoing messages per client above which state and feedback events are "
              "dropped for that client", minimum=1),
    ParamSpec("client_queue_hard_cap", ParamKind.INT, 4096,
              "queued messages at which a client is disconnected as too slow (at least "
              "client_queue_size)", minimum=1),
    ParamSpec("close_timeout_s", ParamKind.FLOAT, 1.0,
              "how long a closing connection may take to read its last messages, s",
              minimum=0.001),
)
"""The server's bounds on its clients' queues and on closing: a program's settings (the tests'
servers set them), not the robot file's."""


def default_flight_recorder_dir() -> str:
    """Where the flight recorder writes without ``daemon.flight_recorder_dir``: systemd's
    ``StateDirectory``, else the XDG state directory (a user's daemon)."""
    state = os.environ.get("STATE_DIRECTORY")
    if state:
        return os.path.join(state.split(":")[0], "flight")
    xdg = os.environ.get("XDG_STATE_HOME") or os.path.expanduser("~/.local/state")
    return os.path.join(xdg, "jtc-hw", "flight")


# -- Result types: every default is its row's --------------------------------------------------

_TCP, _RT, _FOX, _D, _S = (
    TCP_PARAMETERS, REALTIME_PARAMETERS, FOXGLOVE_PARAMETERS, DAEMON_PARAMETERS, SERVER_PARAMETERS
)


@dataclass(frozen=True)
class TcpSettings:
    """``daemon.tcp``: the optional TCP endpoint next to the Unix socket; one field per row
    of :data:`TCP_PARAMETERS`, which says what each is. Every client first sends
    ``{"op": "auth", "token": ...}``; ``max_unauthenticated`` and ``auth_failure_delay_s`` are
    the door's (:mod:`jtc_hw.daemon.transports.tcp_door`); a port of 0 is any free one
    (``Server.tcp_address``).

    Raises:
        ConfigurationError: at construction, a value :data:`TCP_PARAMETERS` refuses.
    """

    host: str = _TCP["host"].default
    port: int = _TCP["port"].default
    token: str = field(default=_TCP["token"].default, repr=False)
    max_clients: int = _TCP["max_clients"].default
    max_unauthenticated: int = _TCP["max_unauthenticated"].default
    auth_timeout_s: float = _TCP["auth_timeout_s"].default
    auth_failure_delay_s: float = _TCP["auth_failure_delay_s"].default

    def __post_init__(self) -> None:
        check_fields(self, TCP_PARAMETERS, "daemon.tcp")


@dataclass(frozen=True)
class RealtimeSettings:
    """``daemon.realtime``: scheduling of the control loop's process (:mod:`.realtime`); one
    field per row of :data:`REALTIME_PARAMETERS`, which says what each is."""

    priority: int = _RT["priority"].default
    lock_memory: bool = _RT["lock_memory"].default
    cpu_affinity: tuple[int, ...] = _RT["cpu_affinity"].default

    def __post_init__(self) -> None:
        check_fields(self, REALTIME_PARAMETERS, "daemon.realtime")


@dataclass(frozen=True)
class FoxgloveSettings:
    """``daemon.foxglove``: the live view (``jtc_hw.daemon.transports.liveview``); one field per
    row of :data:`FOXGLOVE_PARAMETERS`. The protocol has no authentication, so a non-loopback
    ``host`` shows the robot's state to anyone who can reach it (``security_warnings``).

    Raises:
        ConfigurationError: ``host`` is not an IP address or ``localhost`` (at construction).
    """

    host: str = _FOX["host"].default
    port: int = _FOX["port"].default
    rate: float | None = _FOX["rate"].default

    def __post_init__(self) -> None:
        check_fields(self, FOXGLOVE_PARAMETERS, "daemon.foxglove")
        if self.host != "localhost":
            try:
                ipaddress.ip_address(self.host)
            except ValueError:
                raise ConfigurationError(
                    f"{self.host!r} is not an IP address; use 127.0.0.1 (this machine only) "
                    "or the address of one of this machine's interfaces",
                    "daemon.foxglove.host",
                    self.host,
                ) from None


@dataclass(frozen=True)
class DaemonSettings:
    """``daemon``: how the daemon serves clients and runs its loop; what the server and the
    transports take.

    One field per row of :data:`DAEMON_PARAMETERS` (which says what each is; ``socket`` and
    the directories are absolute here, ``socket_group`` a group name or gid or ``None`` for
    the daemon's, and the sections are their own settings or ``None``: off), then one per row
    of :data:`SERVER_PARAMETERS`; a client over a limit may still send ``stop``.

    Raises:
        ConfigurationError: at construction, a value the rows refuse, a socket path that is
            not a string, relative or too long, or a queue hard cap below the queue size.
    """

    socket: str = field(default_factory=default_socket_path)
    socket_mode: int = _D["socket_mode"].default
    socket_group: str | None = _D["socket_group"].default
    tcp: TcpSettings | None = None
    max_clients: int = _D["max_clients"].default
    idle_timeout_s: float = _D["idle_timeout_s"].default
    max_message_bytes: int = _D["max_message_bytes"].default
    realtime: RealtimeSettings = field(default_factory=RealtimeSettings)
    api_stall_s: float = _D["api_stall_s"].default
    log_level: str = _D["log_level"].default
    foxglove: FoxgloveSettings | None = None
    flight_recorder_s: float = _D["flight_recorder_s"].default
    flight_recorder_dir: str = field(default_factory=default_flight_recorder_dir)
    flight_recorder_keep: int = _D["flight_recorder_keep"].default
    record: str | None = None
    zenoh: ZenohSettings | None = None
    ros2: Ros2Settings | None = None
    client_queue_size: int = _S["client_queue_size"].default
    client_queue_hard_cap: int = _S["client_queue_hard_cap"].default
    close_timeout_s: float = _S["close_timeout_s"].default

    def __post_init__(self) -> None:
        check_fields(self, DAEMON_PARAMETERS, "daemon")
        check_fields(self, SERVER_PARAMETERS, "daemon")
        if not isinstance(self.socket, str) or not os.path.isabs(self.socket):
            raise ConfigurationError(
                f"expected an absolute path, got {describe(self.socket)}",
                "daemon.socket",
                self.socket,
            )
        if (size := len(os.fsencode(self.socket))) > MAX_SOCKET_PATH_BYTES:
            raise ConfigurationError(
                f"is {size} bytes long; a Unix socket path holds at most "
                f"{MAX_SOCKET_PATH_BYTES}: choose a shorter directory",
                "daemon.socket",
                self.socket,
            )
        if self.client_queue_hard_cap < self.client_queue_size:
            raise ConfigurationError(
                f"must be >= client_queue_size ({self.client_queue_size})",
                "daemon.client_queue_hard_cap",
                self.client_queue_hard_cap,
            )


# -- Reading the section -----------------------------------------------------------------------


def daemon_settings(raw: Any, base_dir: str) -> DaemonSettings:
    """The robot file's ``daemon`` section (``None``: absent), checked and frozen; relative
    paths are taken relative to ``base_dir`` (the file's directory).

    Raises:
        ConfigurationError: a key that is unknown, of the wrong type or out of range, a TCP
            host that is not a loopback address, a token shorter than 16 characters, an
            insecure Zenoh section; the message names the dotted key path.
    """
    values = validate_params(DAEMON_PARAMETERS, raw, "daemon")
    socket, record, flight_dir = values["socket"], values["record"], values["flight_recorder_dir"]
    return DaemonSettings(**{
        **values,
        "socket": default_socket_path() if socket is None
        else _absolute(socket, base_dir, "daemon.socket", "a path"),
        "tcp": None if values["tcp"] is None else TcpSettings(**values["tcp"]),
        "realtime": RealtimeSettings(**values["realtime"]),
        "foxglove": None if values["foxglove"] is None else FoxgloveSettings(**values["foxglove"]),
        "flight_recorder_dir": default_flight_recorder_dir() if flight_dir is None
        else _absolute(flight_dir, base_dir, "daemon.flight_recorder_dir"),
        "record": None if record is None else _absolute(record, base_dir, "daemon.record"),
        "zenoh": None if values["zenoh"] is None else zenoh_settings(values["zenoh"], base_dir),
        "ros2": None if values["ros2"] is None else ros2_settings(values["ros2"], base_dir),
    })


def _absolute(value: str, base_dir: str, path: str, what: str = "a directory") -> str:
    if not value.strip():
        raise ConfigurationError(f"is empty; give {what}, or remove the key for the default",
                                 path, value)
    return os.path.normpath(os.path.join(base_dir, os.path.expanduser(value)))
