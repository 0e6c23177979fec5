"""One YAML file configures a robot: the controller, its hardware and the daemon.

The controller's part is read by :func:`jtc_hw.config.reading.load_config` (either
layout); this module adds two top-level sections that ``load_config`` skips::

    hardware:                 # optional; default: one mirror component with every joint
      - name: arm             # unique
        kind: mirror          # a registry kind (see jtc_hw.hardware.available_hardware)
        joints: [joint1, joint2]
        params: {lag_s: 0.0}  # kind-specific, checked by the kind's PARAMS when created
    daemon:                   # optional, every key optional
      socket: /run/jtc-hw/jtc-hw.sock
      socket_mode: 0o660
      socket_group: robot     # default: the daemon's group
      tcp: {host: 127.0.0.1, port: 0, token: "at least sixteen characters", max_clients: 8,
            max_unauthenticated: 16, auth_timeout_s: 1.0, auth_failure_delay_s: 0.5}
      max_clients: 16
      idle_timeout_s: 300
      max_message_bytes: 4194304
      realtime: {priority: 0, lock_memory: false, cpu_affinity: []}
      api_stall_s: 0.5
      log_level: info
      foxglove: {host: 127.0.0.1, port: 8765, rate: null}   # live view, off when absent
      flight_recorder_s: 10          # 0: off
      flight_recorder_dir: /var/lib/jtc-hw/flight
      flight_recorder_keep: 20
      record: /var/lib/jtc-hw/runs   # optional: record every run from its start
      zenoh: {prefix: jtc/lab/arm1, connect: [tcp/10.0.0.2:7447]}  # off when absent

The keys, types, defaults and ranges of both sections live in the schema tables below
(:data:`HARDWARE_KEYS`, :data:`DAEMON_PARAMETERS`, :data:`TCP_PARAMETERS`,
:data:`REALTIME_PARAMETERS`); errors name the dotted path (``hardware[1].joints``,
``daemon.tcp.host``). Component parameters are checked when the hardware is created
(:func:`create_hardware_set`): checking them earlier would import optional driver SDKs.
"""

from __future__ import annotations

import ipaddress
import math
import os
import re
import stat
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Final

from ..api.paths import SOCKET_NAME, default_socket_path
from ..config.controller import ControllerConfig
from ..config.reading import load_config, read_source
from ..config.values import describe, did_you_mean, fmt_list
from ..errors import ConfigurationError
from ..hardware import (
    MIN_WATCHDOG_PERIODS,
    HardwareSet,
    HardwareSpec,
    ParamKind,
    ParamSpec,
    check_hardware_kind,
    create_hardware,
    param_table,
    validate_params,
)
from .zenoh_config import ZENOH_PARAMETERS, ZenohSettings, zenoh_settings

__all__ = [
    "DAEMON_PARAMETERS",
    "DEFAULT_API_STALL_S",
    "DEFAULT_HARDWARE_NAME",
    "FOXGLOVE_PARAMETERS",
    "HARDWARE_KEYS",
    "LOG_LEVELS",
    "REALTIME_PARAMETERS",
    "SOCKET_NAME",
    "TCP_PARAMETERS",
    "DaemonSettings",
    "FoxgloveSettings",
    "RealtimeSettings",
    "RobotConfig",
    "TcpSettings",
    "create_hardware_set",
    "default_socket_path",
    "joint_position_limits",
    "load_robot",
    "security_warnings",
]

DEFAULT_HARDWARE_NAME: Final = "mirror"
"""Name of the mirror component used when the ``hardware`` section is absent."""
LOG_LEVELS: Final = ("debug", "info", "warning", "error")
MIN_TOKEN_LENGTH: Final = 16
DEFAULT_API_STALL_S: Final = 0.5
"""Default ``daemon.api_stall_s``."""
MIN_API_STALL_S: Final = 0.05
"""Smallest ``daemon.api_stall_s``: the API process is a normally scheduled Python process; a
garbage collection or a busy moment must not end goals."""
MAX_SOCKET_PATH_BYTES: Final = 107
"""``sun_path`` holds 108 bytes including the terminating NUL."""

_OCTAL_MODE = re.compile(r"(?:0o|0)?([0-7]{1,4})")


def _parse_socket_mode(value: Any, path: str) -> int:
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


# --------------------------------------------------------------------------------------------
# Schema
# --------------------------------------------------------------------------------------------

HARDWARE_KEYS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("name", ParamKind.STRING, "", "unique component name", required=True),
    ParamSpec("kind", ParamKind.STRING, "", "hardware kind, from the registry", required=True),
    ParamSpec("joints", ParamKind.STRINGS, (), "the controller joints this component serves",
              required=True, unique=True, non_empty=True),
    ParamSpec("params", ParamKind.SECTION, MappingProxyType({}),
              "kind-specific parameters", nullable=True),
)
"""Keys of one ``hardware[]`` entry."""

TCP_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("host", ParamKind.STRING, "127.0.0.1", "loopback address to listen on"),
    ParamSpec("port", ParamKind.INT, 0, "TCP port (0: any free port)", minimum=0,
              maximum=65535),
    ParamSpec("token", ParamKind.STRING, "",
              f"shared secret clients must present (at least {MIN_TOKEN_LENGTH} characters)",
              required=True),
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
              coerce=_parse_socket_mode),
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
    ParamSpec("max_message_bytes", ParamKind.INT, 4_194_304, "largest accepted message",
              minimum=1024),
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
)
"""``daemon.*``."""


def default_flight_recorder_dir() -> str:
    """Where the flight recorder writes without ``daemon.flight_recorder_dir``: systemd's
    ``StateDirectory``, else the XDG state directory (a user's daemon)."""
    state = os.environ.get("STATE_DIRECTORY")
    if state:
        return os.path.join(state.split(":")[0], "flight")
    xdg = os.environ.get("XDG_STATE_HOME") or os.path.expanduser("~/.local/state")
    return os.path.join(xdg, "jtc-hw", "flight")


# --------------------------------------------------------------------------------------------
# Result types
# --------------------------------------------------------------------------------------------


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class TcpSettings:
    """``daemon.tcp``: a TCP endpoint next to the Unix socket.

    Raises:
        ConfigurationError: ``host`` is not a loopback address, ``port`` is out of range, or
            ``token`` is shorter than 16 characters (at construction).
    """

    host: str = "127.0.0.1"
    port: int = 0
    token: str = field(default="", repr=False)
    max_clients: int = 8
    max_unauthenticated: int = 16
    auth_timeout_s: float = 1.0
    auth_failure_delay_s: float = 0.5

    def __post_init__(self) -> None:
        if not isinstance(self.host, str) or not _is_loopback(self.host):
            raise ConfigurationError(
                f"{self.host!r} is not a loopback address (127.0.0.0/8, ::1 or localhost): the "
                "endpoint is protected by a token only, without encryption; reach it from "
                "another machine through an SSH tunnel",
                "daemon.tcp.host",
                self.host,
            )
        if not isinstance(self.port, int) or not 0 <= self.port <= 65535:
            raise ConfigurationError(
                f"must be between 0 and 65535, got {self.port!r}", "daemon.tcp.port", self.port
            )
        if isinstance(self.max_clients, bool) or not isinstance(self.max_clients, int) or (
            self.max_clients < 1
        ):
            raise ConfigurationError(
                f"must be an integer >= 1, got {self.max_clients!r}",
                "daemon.tcp.max_clients",
                self.max_clients,
            )
        if not isinstance(self.token, str) or len(self.token) < MIN_TOKEN_LENGTH:
            raise ConfigurationError(
                f"must be at least {MIN_TOKEN_LENGTH} characters long, got "
                f"{len(self.token) if isinstance(self.token, str) else describe(self.token)}"
                "; generate one with: python -c 'import secrets; print(secrets.token_hex(16))'",
                "daemon.tcp.token",
                None,  # never echo a secret
            )


@dataclass(frozen=True)
class RealtimeSettings:
    """``daemon.realtime``: scheduling of the control loop's process.

    Attributes:
        priority: SCHED_FIFO priority 1..99, or 0 for normal scheduling.
        lock_memory: lock the process's memory (``mlockall``).
        cpu_affinity: CPUs the loop may run on; empty: any.
    """

    priority: int = 0
    lock_memory: bool = False
    cpu_affinity: tuple[int, ...] = ()


@dataclass(frozen=True)
class FoxgloveSettings:
    """``daemon.foxglove``: the live view (``jtc_hw.daemon.liveview``).

    Attributes:
        host: address to listen on; the protocol has no authentication, so a non-loopback
            address shows the robot's state to anyone who can reach it (``security_warnings``).
        port: TCP port (0: any free port).
        rate: states published per second, Hz (None: every state the loop publishes).

    Raises:
        ConfigurationError: ``host`` is not an IP address or ``localhost`` (at construction).
    """

    host: str = "127.0.0.1"
    port: int = 8765
    rate: float | None = None

    def __post_init__(self) -> None:
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
    """``daemon``: how the daemon serves clients and runs its loop.

    Attributes:
        socket: absolute path of the Unix socket.
        socket_mode: permission bits of the socket file.
        socket_group: group of the socket file (name or gid), or ``None``: the daemon's.
        tcp: the optional TCP endpoint.
        max_clients: simultaneous unix socket connections (and 2 more for the daemon's user
            and root).
        idle_timeout_s: close a connection idle for this long (0: never).
        max_message_bytes: largest accepted message.
        realtime: scheduling of the loop.
        api_stall_s: how long the loop's ordered messages (results, replies) may wait for the
            API process to read them before the loop ends the active goal and holds.
        log_level: one of :data:`LOG_LEVELS`.
        foxglove: the live view, or None (off).
        flight_recorder_s: seconds the flight recorder keeps before a trigger (0: off).
        flight_recorder_dir: absolute directory of its bags.
        flight_recorder_keep: how many of its bags are kept.
        record: absolute directory where each run is recorded from its start, or ``None``.
        zenoh: the Zenoh interface, or None (off).

    Raises:
        ConfigurationError: the socket path is relative, empty or too long, or
            ``api_stall_s`` is below :data:`MIN_API_STALL_S` (at construction).
    """

    socket: str = field(default_factory=default_socket_path)
    socket_mode: int = 0o660
    socket_group: str | None = None
    tcp: TcpSettings | None = None
    max_clients: int = 16
    idle_timeout_s: float = 300.0
    max_message_bytes: int = 4_194_304
    realtime: RealtimeSettings = field(default_factory=RealtimeSettings)
    api_stall_s: float = DEFAULT_API_STALL_S
    log_level: str = "info"
    foxglove: FoxgloveSettings | None = None
    flight_recorder_s: float = 10.0
    flight_recorder_dir: str = field(default_factory=default_flight_recorder_dir)
    flight_recorder_keep: int = 20
    record: str | None = None
    zenoh: ZenohSettings | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.socket, str) or not os.path.isabs(self.socket):
            raise ConfigurationError(
                f"expected an absolute path, got {describe(self.socket)}",
                "daemon.socket",
                self.socket,
            )
        size = len(os.fsencode(self.socket))
        if size > MAX_SOCKET_PATH_BYTES:
            raise ConfigurationError(
                f"is {size} bytes long; a Unix socket path holds at most "
                f"{MAX_SOCKET_PATH_BYTES}: choose a shorter directory",
                "daemon.socket",
                self.socket,
            )
        stall = self.api_stall_s
        if (
            isinstance(stall, bool)
            or not isinstance(stall, (int, float))
            or not MIN_API_STALL_S <= stall < float("inf")
        ):
            raise ConfigurationError(
                f"must be a number of seconds >= {MIN_API_STALL_S:g}, got {describe(stall)}",
                "daemon.api_stall_s",
                stall,
            )


@dataclass(frozen=True)
class RobotConfig:
    """A whole robot: controller, hardware components and daemon settings (see module doc).

    Attributes:
        controller: the validated controller configuration.
        hardware: one spec per component, with the controller's interfaces; together their
            joints are the controller's joints, each exactly once.
        daemon: the daemon's settings, defaults filled in.
        source_path: absolute path of the file read, or ``None`` for a mapping.
    """

    controller: ControllerConfig
    hardware: tuple[HardwareSpec, ...]
    daemon: DaemonSettings
    source_path: str | None = None


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------


def _parse_hardware(raw: Any, controller: ControllerConfig) -> tuple[HardwareSpec, ...]:
    joints = controller.joints
    interfaces = (controller.command_interfaces, controller.state_interfaces)
    if raw is None:
        return (HardwareSpec(DEFAULT_HARDWARE_NAME, "mirror", joints, *interfaces, {}, "hardware"),)
    if not isinstance(raw, (list, tuple)):
        raise ConfigurationError(
            f"expected a list of components (each with name, kind, joints, params), got "
            f"{describe(raw)}",
            "hardware",
            raw,
        )
    if not raw:
        raise ConfigurationError(
            "lists no component; list at least one, or remove the key for the default "
            "mirror of every joint",
            "hardware",
            raw,
        )
    specs: list[HardwareSpec] = []
    names: dict[str, str] = {}
    owners: dict[str, tuple[str, str]] = {}
    for index, entry in enumerate(raw):
        path = f"hardware[{index}]"
        values = validate_params(HARDWARE_KEYS, entry, path, owner=f"component {index}")
        name = values["name"]
        if not name.strip():
            raise ConfigurationError("expected a non-empty name", f"{path}.name", name)
        if name in names:
            raise ConfigurationError(
                f"{name!r} is already the name of {names[name]}; component names must be unique",
                f"{path}.name",
                name,
            )
        names[name] = path
        check_hardware_kind(values["kind"], f"{path}.kind")
        for joint in values["joints"]:
            if joint not in joints:
                raise ConfigurationError(
                    f"{joint!r} is not a controller joint (joints: {', '.join(joints)})"
                    f"{did_you_mean(joint, joints)}",
                    f"{path}.joints",
                    joint,
                )
            if joint in owners:
                other, other_path = owners[joint]
                raise ConfigurationError(
                    f"{joint!r} is already provided by {other!r} ({other_path}); each joint "
                    "belongs to exactly one component",
                    f"{path}.joints",
                    joint,
                )
            owners[joint] = (name, path)
        specs.append(
            HardwareSpec(name, values["kind"], values["joints"], *interfaces, values["params"],
                         path)
        )
    missing = [j for j in joints if j not in owners]
    if missing:
        plural = "s" if len(missing) > 1 else ""
        raise ConfigurationError(
            f"controller joint{plural} {', '.join(repr(j) for j in missing)} not provided by "
            "any component; add each to the joints of one component",
            "hardware",
            missing[0],
        )
    return tuple(specs)


def _parse_daemon(raw: Any, base_dir: str) -> DaemonSettings:
    values = validate_params(DAEMON_PARAMETERS, raw, "daemon")
    socket = values["socket"]
    if socket is None:
        socket = default_socket_path()
    elif not socket.strip():
        raise ConfigurationError(
            "is empty; give a path, or remove the key for the default", "daemon.socket", socket
        )
    else:
        socket = os.path.normpath(os.path.join(base_dir, os.path.expanduser(socket)))
    tcp = values["tcp"]
    realtime = values["realtime"]
    return DaemonSettings(
        socket=socket,
        socket_mode=values["socket_mode"],
        socket_group=values["socket_group"],
        tcp=None if tcp is None else TcpSettings(**tcp),
        max_clients=values["max_clients"],
        idle_timeout_s=values["idle_timeout_s"],
        max_message_bytes=values["max_message_bytes"],
        realtime=RealtimeSettings(**realtime),
        api_stall_s=values["api_stall_s"],
        log_level=values["log_level"],
        foxglove=None if values["foxglove"] is None else FoxgloveSettings(**values["foxglove"]),
        flight_recorder_s=values["flight_recorder_s"],
        flight_recorder_dir=_flight_recorder_dir(values["flight_recorder_dir"], base_dir),
        flight_recorder_keep=values["flight_recorder_keep"],
        record=None if values["record"] is None else _directory(values["record"], base_dir,
                                                                 "daemon.record"),
        zenoh=None if values["zenoh"] is None else zenoh_settings(values["zenoh"], base_dir),
    )


def _flight_recorder_dir(value: str | None, base_dir: str) -> str:
    if value is None:
        return default_flight_recorder_dir()
    return _directory(value, base_dir, "daemon.flight_recorder_dir")


def _directory(value: str, base_dir: str, path: str) -> str:
    if not value.strip():
        raise ConfigurationError("is empty; give a directory, or remove the key for the default",
                                 path, value)
    return os.path.normpath(os.path.join(base_dir, os.path.expanduser(value)))


def load_robot(
    source: str | os.PathLike[str] | Mapping[str, Any], controller_name: str | None = None
) -> RobotConfig:
    """Read, check and freeze a robot configuration.

    Args:
        source: path of a YAML file, or an already parsed mapping: a controller configuration
            in either layout :func:`~jtc_hw.config.reading.load_config` reads, plus optional
            top-level ``hardware`` and ``daemon`` sections (see the module docstring).
        controller_name: which controller section to use when there are several.

    Returns:
        The configuration. Without a ``hardware`` section: one ``mirror`` component named
        ``mirror`` serving every joint. A relative ``daemon.socket`` is taken relative to the
        file's directory (the current directory for a mapping).

    Raises:
        ConfigurationError: anything :func:`~jtc_hw.config.reading.load_config` rejects; a
            ``hardware`` entry with an unknown or missing key, an unknown kind (the message
            lists the kinds), a joint that is not the controller's or is given twice, a
            controller joint no component provides; ``command_joints`` naming other joints
            than ``joints`` (a controller chain); a ``daemon`` key that is unknown, of the
            wrong type or out of range, a TCP host that is not a loopback address, a token
            shorter than 16 characters. The message names the dotted key path.
        TypeError: ``source`` is neither a path nor a mapping.
    """
    data = read_source(source)
    if isinstance(source, Mapping):
        source_path = None
        base_dir = os.getcwd()
    else:
        source_path = os.path.abspath(os.fspath(source))
        base_dir = os.path.dirname(source_path)
    controller = load_config(data, controller_name, base_dir=base_dir)  # limits.urdf: relative
    _check_command_joints(controller)
    hardware = _parse_hardware(data.get("hardware"), controller)
    daemon = _parse_daemon(data.get("daemon"), base_dir)
    return RobotConfig(controller, hardware, daemon, source_path)


def _check_command_joints(controller: ControllerConfig) -> None:
    """The daemon drives its hardware joints directly: ``command_joints`` may leave some
    joints monitored only (a subset), but not rename them.

    Raises:
        ConfigurationError: as many command joints as joints with other names (upstream maps
            them by index onto another controller's interfaces in a chain, which the daemon
            does not have).
    """
    command, joints = controller.command_joints, controller.joints
    if len(command) == len(joints) and command != joints:
        raise ConfigurationError(
            f"{fmt_list(command)} names other joints than joints ({', '.join(joints)}); in "
            "ros2_control that chains to another controller's interfaces, but the daemon "
            "commands its hardware joints itself: leave command_joints empty, or list the "
            "joints to command (a subset of joints; the others are only monitored)",
            "command_joints",
            command,
        )


def _foxglove_warnings(robot: RobotConfig) -> list[str]:
    view = robot.daemon.foxglove
    if view is None or _is_loopback(view.host):
        return []
    return [
        f"daemon.foxglove.host {view.host} is not a loopback address: the live view has no "
        "authentication, so anyone who reaches that port sees the robot's state; prefer "
        "127.0.0.1 and an SSH tunnel (ssh -L 8765:127.0.0.1:8765 robot)"
    ]


def security_warnings(robot: RobotConfig) -> list[str]:
    """What in ``robot``'s file is exposed to other users (``jtc-hw check`` and ``run`` print
    it): a socket mode that lets every user connect; a TCP or Zenoh token in a file that group
    or others may read; a live view (which has no authentication) on a non-loopback address.

    Raises:
        Nothing: a file that cannot be examined gives no warning.
    """
    return [*_socket_mode_warnings(robot), *_token_warnings(robot), *_foxglove_warnings(robot)]


def _socket_mode_warnings(robot: RobotConfig) -> list[str]:
    """The socket's mode is its only lock: any bit for others lets every local user in. The
    group's bits are the intended door (0660, ``daemon.socket_group``)."""
    mode = robot.daemon.socket_mode
    if not mode & 0o007:
        return []
    return [
        f"daemon.socket_mode {mode:04o} lets every user of this machine connect to the "
        f"daemon's socket ({robot.daemon.socket}) and command the robot. Use 0660 and let "
        "in those who may, through the socket's group (daemon.socket_group)"
    ]


def _token_warnings(robot: RobotConfig) -> list[str]:
    path = robot.source_path
    doors = [name for name, on in (("TCP", robot.daemon.tcp is not None),
                                   ("Zenoh", robot.daemon.zenoh is not None)) if on]
    if not doors or path is None:
        return []
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        return []
    if not mode & 0o044:
        return []
    who = " and ".join(
        name for bit, name in ((0o040, "its group"), (0o004, "every user")) if mode & bit
    )
    return [
        f"{path} holds the {' and '.join(doors)} token"
        f" ({', '.join(f'daemon.{d.lower()}.token' for d in doors)}) and is readable by {who}"
        f" (mode {mode:04o}): whoever reads it can command the robot over"
        f" {' and '.join(doors)}. Make it private: "
        f"chmod 600 {path} (owned by the daemon's user)"
    ]


def create_hardware_set(robot: RobotConfig) -> HardwareSet:
    """Create every component of ``robot`` (UNCONFIGURED) and join them.

    Raises:
        ConfigurationError: a component's kind cannot be loaded (e.g. a missing optional
            dependency: the message names the ``pip install``) or its parameters are invalid
            (path ``hardware[<i>].params.<key>``), including a ``watchdog_s`` shorter than
            three loop periods.
        HardwareError: a driver's constructor failed otherwise.
    """
    components = [create_hardware(spec) for spec in robot.hardware]
    period_s = 1.0 / robot.controller.update_rate
    for index, component in enumerate(components):
        watchdog_s = component.params.get("watchdog_s")
        if watchdog_s is not None and watchdog_s < MIN_WATCHDOG_PERIODS * period_s - 1e-12:
            raise ConfigurationError(
                f"{watchdog_s * 1e3:g} ms is shorter than {MIN_WATCHDOG_PERIODS} loop periods "
                f"({MIN_WATCHDOG_PERIODS * period_s * 1e3:g} ms at {robot.controller.update_rate:g}"
                " Hz): one late cycle would stop the motors; raise watchdog_s or update_rate",
                f"hardware[{index}].params.watchdog_s",
                watchdog_s,
            )
    return HardwareSet(components, robot.controller.joints)


def joint_position_limits(robot: RobotConfig) -> dict[str, tuple[float, float]]:
    """Each joint's finite ``position_limits`` from its hardware component (no I/O).

    The components are created (which validates their parameters) and dropped; joints whose
    component has no ``position_limits`` parameter, or an unlimited one, are left out.

    Raises:
        ConfigurationError, HardwareError: as :func:`create_hardware_set`.
    """
    limits: dict[str, tuple[float, float]] = {}
    for spec in robot.hardware:
        component = create_hardware(spec)
        ranges = component.params.get("position_limits")
        if ranges is None:
            continue
        for joint, (low, high) in zip(component.joints, ranges, strict=True):
            low = -math.inf if low is None else float(low)
            high = math.inf if high is None else float(high)
            if math.isfinite(low) or math.isfinite(high):
                limits[joint] = (low, high)
    return limits
