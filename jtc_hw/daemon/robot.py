"""One YAML file configures a robot: the controller, its hardware and the daemon.

The controller's part is read by :func:`jtc_hw.config.reading.load_config` (either
layout); this module adds two top-level sections that ``load_config`` skips::

    hardware:                 # optional; default: one mirror component with every joint
      - name: arm             # unique
        kind: mirror          # a registry kind (see jtc_hw.hardware.available_hardware)
        joints: [joint1, joint2]
        params: {lag_s: 0.0}  # kind-specific, checked by the kind's PARAMS when created
    daemon:                   # optional, every key optional (each with its default:
      socket: /run/jtc-hw/jtc-hw.sock           # settings.DAEMON_PARAMETERS)
      tcp: {host: 127.0.0.1, port: 0, token: "at least sixteen characters"}
      realtime: {priority: 0, lock_memory: false, cpu_affinity: []}
      foxglove: {host: 127.0.0.1, port: 8765}   # live view, off when absent
      zenoh: {prefix: jtc/lab/arm1, connect: [tcp/10.0.0.2:7447]}  # off when absent

The keys, types, defaults and ranges of both sections live in schema tables of the one engine
(:data:`HARDWARE_KEYS` here; ``daemon``'s in :mod:`.settings`, which makes the frozen
:class:`~.settings.DaemonSettings`); errors name the dotted path (``hardware[1].joints``,
``daemon.tcp.host``). Component parameters are checked when the hardware is created
(:func:`create_hardware_set`): checking them earlier would import optional driver SDKs.
"""

from __future__ import annotations

import math
import os
import stat
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Final

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
from .settings import DaemonSettings, daemon_settings, is_loopback

__all__ = [
    "DEFAULT_HARDWARE_NAME",
    "HARDWARE_KEYS",
    "DaemonSettings",
    "RobotConfig",
    "create_hardware_set",
    "joint_position_limits",
    "load_robot",
    "security_warnings",
]

DEFAULT_HARDWARE_NAME: Final = "mirror"
"""Name of the mirror component used when the ``hardware`` section is absent."""


# -- Schema ------------------------------------------------------------------------------------

HARDWARE_KEYS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("name", ParamKind.STRING, "", "unique component name", required=True),
    ParamSpec("kind", ParamKind.STRING, "", "hardware kind, from the registry", required=True),
    ParamSpec("joints", ParamKind.STRINGS, (), "the controller joints this component serves",
              required=True, unique=True, non_empty=True),
    ParamSpec("params", ParamKind.SECTION, MappingProxyType({}),
              "kind-specific parameters", nullable=True),
)
"""Keys of one ``hardware[]`` entry."""


# -- Result types ------------------------------------------------------------------------------


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


# -- Loading -----------------------------------------------------------------------------------


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


def load_robot(
    source: str | os.PathLike[str] | Mapping[str, Any], controller_name: str | None = None
) -> RobotConfig:
    """Read, check and freeze a robot configuration. Without a ``hardware`` section: one
    ``mirror`` component named ``mirror`` serving every joint. A relative ``daemon.socket`` is
    taken relative to the file's directory (the current directory for a mapping).

    Args:
        source: path of a YAML file, or an already parsed mapping (the module docstring
            says what it holds).
        controller_name: which controller section to use when there are several.

    Raises:
        ConfigurationError: anything :func:`~jtc_hw.config.reading.load_config` rejects; a
            ``hardware`` entry with an unknown or missing key, an unknown kind (the message
            lists the kinds), a joint that is not the controller's or is given twice, a
            controller joint no component provides; ``command_joints`` naming other joints
            than ``joints`` (a controller chain); what :func:`~.settings.daemon_settings`
            refuses. The message names the dotted key path.
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
    daemon = daemon_settings(data.get("daemon"), base_dir)
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
    if view is None or is_loopback(view.host):
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
    Never raises: a file that cannot be examined gives no warning."""
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
        ConfigurationError: ``speed_scaling.state_interface`` or ``command_interface`` is
            not a scalar interface of a component (:meth:`HardwareSet.scalar_interface`).
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
    hardware = HardwareSet(components, robot.controller.joints)
    scaling = robot.controller.speed_scaling
    for kind, name in (("state", scaling.state_interface), ("command", scaling.command_interface)):
        if name:
            hardware.scalar_interface(name, kind)
    return hardware


def joint_position_limits(robot: RobotConfig) -> dict[str, tuple[float, float]]:
    """Each joint's finite ``position_limits`` from its hardware component (no I/O).

    The components are created (which validates their parameters) and dropped; joints whose
    component has no ``position_limits`` parameter, or an unlimited one, are left out. Raises
    as :func:`create_hardware_set`.
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
