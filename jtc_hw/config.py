"""Controller parameters: read, check and freeze the ``joint_trajectory_controller`` settings.

The parameter names, types, defaults and ranges are those of the upstream controller's
parameter list; they live in one schema table per level (:data:`PARAMETERS`,
:data:`CONSTRAINT_PARAMETERS`, :data:`JOINT_CONSTRAINT_PARAMETERS`, :data:`GAIN_PARAMETERS`).
The tables drive validation, the dataclass defaults, :data:`DEFAULTS` and
:func:`config_to_dict`.

Two source layouts are accepted by :func:`load_config`:

* the upstream ROS 2 parameter file::

      controller_manager:
        ros__parameters:
          update_rate: 100
          joint_trajectory_controller:
            type: joint_trajectory_controller/JointTrajectoryController
      joint_trajectory_controller:
        ros__parameters:
          joints: [joint1, joint2]
          command_interfaces: [position]
          state_interfaces: [position, velocity]

* a plain mapping holding the controller's parameters directly (plus ``update_rate``).

The result is an immutable :class:`ControllerConfig`. Constructing one directly runs the same
checks, so every instance is valid (including copies made with :func:`dataclasses.replace`).
"""

from __future__ import annotations

import difflib
import math
import os
from collections.abc import Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from types import MappingProxyType
from typing import Any, Final

import yaml

from .errors import ConfigurationError

__all__ = [
    "ALLOWED_COMMAND_INTERFACE_COMBINATIONS",
    "ALLOWED_STATE_INTERFACE_COMBINATIONS",
    "COMMAND_INTERFACE_TYPES",
    "CONSTRAINT_PARAMETERS",
    "CONTROLLER_TYPE",
    "ControllerConfig",
    "Constraints",
    "DEFAULTS",
    "DEFAULT_CONTROLLER_NAME",
    "GAIN_PARAMETERS",
    "Gains",
    "JOINT_CONSTRAINT_PARAMETERS",
    "JointConstraints",
    "Kind",
    "PARAMETERS",
    "Param",
    "STATE_INTERFACE_TYPES",
    "config_to_dict",
    "explain",
    "load_config",
]

DEFAULT_CONTROLLER_NAME: Final = "joint_trajectory_controller"
"""Controller name used for the plain-mapping form when no name is given."""

CONTROLLER_TYPE: Final = "joint_trajectory_controller/JointTrajectoryController"
"""The only controller type this project implements (``controller_manager`` ``type`` entry)."""

CONTROLLER_MANAGER: Final = "controller_manager"
ROS_PARAMETERS: Final = "ros__parameters"
RESERVED_TOP_LEVEL_KEYS: Final = frozenset({"hardware", "daemon"})
"""Top-level keys that belong to the daemon; :func:`load_config` skips them."""

JOINTS_PLACEHOLDER: Final = "<joints>"
"""Placeholder key used by the reference's example parameter file."""

COMMAND_INTERFACE_TYPES: Final = ("position", "velocity", "acceleration", "effort")
STATE_INTERFACE_TYPES: Final = ("position", "velocity", "acceleration")

ALLOWED_COMMAND_INTERFACE_COMBINATIONS: Final[tuple[tuple[str, ...], ...]] = (
    ("position",),
    ("position", "velocity"),
    ("position", "velocity", "acceleration"),
    ("velocity",),
    ("effort",),
)
"""Supported command interface sets (order in the configuration does not matter)."""

ALLOWED_STATE_INTERFACE_COMBINATIONS: Final[tuple[tuple[str, ...], ...]] = (
    ("position",),
    ("position", "velocity"),
    ("position", "velocity", "acceleration"),
)
"""Supported state interface sets (order in the configuration does not matter)."""

_SECTIONS: Final = ("constraints", "gains")
_PID_TERMS: Final = ("p", "i", "d", "i_clamp", "ff_velocity_scale")


# --------------------------------------------------------------------------------------------
# Schema
# --------------------------------------------------------------------------------------------


class Kind(Enum):
    """Value type of a parameter; the value is the wording used in error messages."""

    FLOAT = "a number"
    BOOL = "true or false"
    STRING = "a string"
    STRING_ARRAY = "a list of strings"


@dataclass(frozen=True)
class Param:
    """One row of a schema table.

    Attributes:
        name: parameter name (last component of its dotted path).
        kind: value type.
        default: default value (a tuple for string arrays).
        description: one-line description, from the reference.
        minimum: inclusive lower bound for numbers, if any.
        choices: allowed values for strings / string-array elements, if restricted.
        required: the parameter must be given (no usable default).
        unique: string array without duplicates.
        non_empty: string array that must have at least one element.
    """

    name: str
    kind: Kind
    default: float | bool | str | tuple[str, ...]
    description: str
    minimum: float | None = None
    choices: tuple[str, ...] = ()
    required: bool = False
    unique: bool = False
    non_empty: bool = False


def _table(*params: Param) -> Mapping[str, Param]:
    return MappingProxyType({p.name: p for p in params})


_F, _B, _S, _A = Kind.FLOAT, Kind.BOOL, Kind.STRING, Kind.STRING_ARRAY

PARAMETERS: Final[Mapping[str, Param]] = _table(
    Param("joints", _A, (), "joint names to control and listen to",
          required=True, unique=True, non_empty=True),
    Param("command_joints", _A, (),
          "joint names to control, if they differ from the state joints (controller chains)",
          unique=True),
    Param("command_interfaces", _A, (), "command interfaces provided for all joints",
          choices=COMMAND_INTERFACE_TYPES, required=True, unique=True, non_empty=True),
    Param("state_interfaces", _A, (), "state interfaces provided for all joints",
          choices=STATE_INTERFACE_TYPES, required=True, unique=True, non_empty=True),
    Param("allow_partial_joints_goal", _B, False,
          "allow goals defining a trajectory for only some joints"),
    Param("open_loop_control", _B, False,
          "use the last commands instead of the states as the start of new trajectories"),
    Param("allow_integration_in_goal_trajectories", _B, False,
          "accept goals without positions (or velocities) and integrate them"),
    Param("state_publish_rate", _F, 50.0, "rate the controller state is published, Hz",
          minimum=0.1),
    Param("set_last_command_interface_value_as_state_on_activation", _B, True,
          "on activation, use the last command interface values as current and commanded state"),
    Param("action_monitor_rate", _F, 20.0, "rate action goals are monitored, Hz", minimum=0.1),
    Param("interpolation_method", _S, "splines", "type of interpolation, if any",
          choices=("splines", "none")),
    Param("allow_nonzero_velocity_at_trajectory_end", _B, True,
          "if false, goals whose last point has a non-zero velocity are rejected"),
    Param("cmd_timeout", _F, 0.0,
          "seconds after the last point after which the command is stale (0: off)", minimum=0.0),
    Param("start_with_holding", _B, True,
          "hold the position after activation (otherwise command nothing until a trajectory)"),
    Param("update_rate", _F, 100.0, "control loop rate, Hz (the controller manager's setting)",
          minimum=0.1),
)
"""Top-level controller parameters (``constraints`` and ``gains`` are sections, below)."""

CONSTRAINT_PARAMETERS: Final[Mapping[str, Param]] = _table(
    Param("stopped_velocity_tolerance", _F, 0.01,
          "velocity below which the system counts as stopped at the trajectory end",
          minimum=0.0),
    Param("goal_time", _F, 0.0,
          "time tolerance for reaching the goal, seconds (0: wait indefinitely)", minimum=0.0),
)
"""``constraints.*`` parameters other than the per-joint entries."""

JOINT_CONSTRAINT_PARAMETERS: Final[Mapping[str, Param]] = _table(
    Param("trajectory", _F, 0.0, "position tolerance during the motion (0: not checked)",
          minimum=0.0),
    Param("goal", _F, 0.0, "position tolerance at the goal (0: not checked)", minimum=0.0),
)
"""``constraints.<joint>.*`` parameters."""

GAIN_PARAMETERS: Final[Mapping[str, Param]] = _table(
    Param("p", _F, 0.0, "proportional gain"),
    Param("i", _F, 0.0, "integral gain"),
    Param("d", _F, 0.0, "derivative gain"),
    Param("i_clamp", _F, 0.0, "symmetric integral clamp", minimum=0.0),
    Param("ff_velocity_scale", _F, 0.0, "velocity feed-forward scale"),
    Param("normalize_error", _B, False, "(deprecated) normalise the position error to [-pi, pi]"),
    Param("angle_wraparound", _B, False,
          "continuous joint: normalise the position error to [-pi, pi]"),
)
"""``gains.<joint>.*`` parameters."""


def _freeze(value: Any) -> Any:
    if isinstance(value, Mapping):
        return MappingProxyType({k: _freeze(v) for k, v in value.items()})
    return value


def _defaults_of(table: Mapping[str, Param]) -> dict[str, Any]:
    return {name: p.default for name, p in table.items()}


DEFAULTS: Final[Mapping[str, Any]] = _freeze({
    **_defaults_of(PARAMETERS),
    "constraints": {
        **_defaults_of(CONSTRAINT_PARAMETERS),
        JOINTS_PLACEHOLDER: _defaults_of(JOINT_CONSTRAINT_PARAMETERS),
    },
    "gains": {JOINTS_PLACEHOLDER: _defaults_of(GAIN_PARAMETERS)},
})
"""Every default, nested like the parameter file (``<joints>`` stands for each joint)."""


def _float_default(table: Mapping[str, Param], name: str) -> float:
    value = table[name].default
    if not isinstance(value, float):  # pragma: no cover - guards the tables above
        raise TypeError(f"schema default of {name} is not a float")
    return value


def _bool_default(table: Mapping[str, Param], name: str) -> bool:
    value = table[name].default
    if not isinstance(value, bool):  # pragma: no cover - guards the tables above
        raise TypeError(f"schema default of {name} is not a bool")
    return value


def _str_default(table: Mapping[str, Param], name: str) -> str:
    value = table[name].default
    if not isinstance(value, str):  # pragma: no cover - guards the tables above
        raise TypeError(f"schema default of {name} is not a str")
    return value


def _empty_mapping() -> Mapping[str, Any]:
    return MappingProxyType({})


# --------------------------------------------------------------------------------------------
# Result types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class JointConstraints:
    """Default tolerances of one joint (``constraints.<joint>``); 0 means "not checked"."""

    trajectory: float = _float_default(JOINT_CONSTRAINT_PARAMETERS, "trajectory")
    goal: float = _float_default(JOINT_CONSTRAINT_PARAMETERS, "goal")


@dataclass(frozen=True)
class Constraints:
    """Default tolerances (``constraints``).

    Inside a :class:`ControllerConfig`, ``joints`` has one entry for every configured joint.
    """

    stopped_velocity_tolerance: float = _float_default(
        CONSTRAINT_PARAMETERS, "stopped_velocity_tolerance"
    )
    goal_time: float = _float_default(CONSTRAINT_PARAMETERS, "goal_time")
    joints: Mapping[str, JointConstraints] = field(default_factory=_empty_mapping)

    def __post_init__(self) -> None:
        if isinstance(self.joints, Mapping) and not isinstance(self.joints, MappingProxyType):
            object.__setattr__(self, "joints", MappingProxyType(dict(self.joints)))


@dataclass(frozen=True)
class Gains:
    """PID gains of one joint (``gains.<joint>``)."""

    p: float = _float_default(GAIN_PARAMETERS, "p")
    i: float = _float_default(GAIN_PARAMETERS, "i")
    d: float = _float_default(GAIN_PARAMETERS, "d")
    i_clamp: float = _float_default(GAIN_PARAMETERS, "i_clamp")
    ff_velocity_scale: float = _float_default(GAIN_PARAMETERS, "ff_velocity_scale")
    normalize_error: bool = _bool_default(GAIN_PARAMETERS, "normalize_error")
    angle_wraparound: bool = _bool_default(GAIN_PARAMETERS, "angle_wraparound")

    @property
    def wraps(self) -> bool:
        """Whether the position error wraps (``angle_wraparound`` or ``normalize_error``)."""
        return self.angle_wraparound or self.normalize_error


@dataclass(frozen=True, kw_only=True)
class ControllerConfig:
    """Validated, immutable controller configuration.

    Construction checks every value (types, ranges, interface combinations, joint names in
    ``constraints``/``gains``) and fills ``constraints.joints`` and ``gains`` with defaults for
    every configured joint. Lists become tuples, mappings become read-only.

    Raises:
        ConfigurationError: on any invalid value (at construction).
    """

    name: str = DEFAULT_CONTROLLER_NAME
    joints: tuple[str, ...]
    command_joints: tuple[str, ...] = ()
    command_interfaces: tuple[str, ...]
    state_interfaces: tuple[str, ...]
    allow_partial_joints_goal: bool = _bool_default(PARAMETERS, "allow_partial_joints_goal")
    open_loop_control: bool = _bool_default(PARAMETERS, "open_loop_control")
    allow_integration_in_goal_trajectories: bool = _bool_default(
        PARAMETERS, "allow_integration_in_goal_trajectories"
    )
    state_publish_rate: float = _float_default(PARAMETERS, "state_publish_rate")
    set_last_command_interface_value_as_state_on_activation: bool = _bool_default(
        PARAMETERS, "set_last_command_interface_value_as_state_on_activation"
    )
    action_monitor_rate: float = _float_default(PARAMETERS, "action_monitor_rate")
    interpolation_method: str = _str_default(PARAMETERS, "interpolation_method")
    allow_nonzero_velocity_at_trajectory_end: bool = _bool_default(
        PARAMETERS, "allow_nonzero_velocity_at_trajectory_end"
    )
    cmd_timeout: float = _float_default(PARAMETERS, "cmd_timeout")
    start_with_holding: bool = _bool_default(PARAMETERS, "start_with_holding")
    constraints: Constraints = field(default_factory=Constraints)
    gains: Mapping[str, Gains] = field(default_factory=_empty_mapping)
    update_rate: float = _float_default(PARAMETERS, "update_rate")

    def __post_init__(self) -> None:
        _validate(self)

    def has_command(self, iface: str) -> bool:
        """Whether ``iface`` is one of the command interfaces."""
        return iface in self.command_interfaces

    def has_state(self, iface: str) -> bool:
        """Whether ``iface`` is one of the state interfaces."""
        return iface in self.state_interfaces

    @property
    def use_pid(self) -> bool:
        """Whether commands come from the PID loop (effort, or velocity alone in closed loop)."""
        return "effort" in self.command_interfaces or (
            self.command_interfaces == ("velocity",) and not self.open_loop_control
        )

    @property
    def effective_cmd_timeout(self) -> float:
        """``cmd_timeout`` if active, else 0: it must be greater than ``constraints.goal_time``."""
        if self.cmd_timeout > 0.0 and self.cmd_timeout > self.constraints.goal_time:
            return self.cmd_timeout
        return 0.0

    @property
    def wraparound(self) -> tuple[bool, ...]:
        """Per joint (in ``joints`` order): whether its position error wraps to [-pi, pi]."""
        return tuple(self.gains[j].wraps for j in self.joints)


# --------------------------------------------------------------------------------------------
# Value checks
# --------------------------------------------------------------------------------------------


def _describe(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})"


def _fmt(items: Iterable[str]) -> str:
    return "[" + ", ".join(items) + "]"


def _closest(word: str, candidates: Iterable[str]) -> str | None:
    matches = difflib.get_close_matches(word, list(candidates), n=1, cutoff=0.6)
    return matches[0] if matches else None


def _did_you_mean(word: str, candidates: Iterable[str]) -> str:
    best = _closest(word, candidates)
    return f"; did you mean '{best}'?" if best is not None else ""


def _coerce_string_array(value: Any, path: str) -> tuple[str, ...]:
    """Type-check a string array: a list of strings, or the literal '{}' / '[]' (empty)."""
    if isinstance(value, str):
        if value.strip() in ("{}", "[]"):
            return ()
        raise ConfigurationError(
            f"expected a list of strings, got {_describe(value)}; write a YAML list, "
            f"e.g. [{value}]",
            path,
            value,
        )
    if not isinstance(value, (list, tuple)):
        raise ConfigurationError(f"expected a list of strings, got {_describe(value)}", path, value)
    for index, item in enumerate(value):
        if not isinstance(item, str):
            raise ConfigurationError(
                f"expected a list of strings, but element {index} is {_describe(item)}",
                path,
                item,
            )
        if not item.strip():
            raise ConfigurationError(f"element {index} is an empty name", path, item)
    return tuple(value)


def _coerce_bool(value: Any, path: str, prefix: str = "") -> bool:
    """``value`` if it is a YAML boolean; a quoted "true"/"false" gets a hint.

    Raises:
        ConfigurationError: not a boolean.
    """
    if not isinstance(value, bool):
        hint = ""
        if isinstance(value, str) and value.strip().lower() in ("true", "false"):
            hint = f"; write {value.strip().lower()} without quotes"
        raise ConfigurationError(
            f"{prefix}expected true or false, got {_describe(value)}{hint}", path, value
        )
    return value


def _coerce(param: Param, value: Any, path: str) -> Any:
    """Check ``value`` against ``param`` and return it normalised (float, tuple, ...).

    Raises:
        ConfigurationError: wrong type, out of range, not an allowed choice, duplicate or
            empty where not allowed.
    """
    if param.kind is Kind.FLOAT:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigurationError(f"expected a number, got {_describe(value)}", path, value)
        try:
            number = float(value)
        except OverflowError:
            number = math.inf
        if not math.isfinite(number):
            raise ConfigurationError(f"expected a finite number, got {value!r}", path, value)
        if param.minimum is not None and number < param.minimum:
            raise ConfigurationError(
                f"must be >= {param.minimum:g}, got {value!r}", path, value
            )
        return number
    if param.kind is Kind.BOOL:
        return _coerce_bool(value, path)
    if param.kind is Kind.STRING:
        if not isinstance(value, str):
            raise ConfigurationError(f"expected a string, got {_describe(value)}", path, value)
        if param.choices and value not in param.choices:
            raise ConfigurationError(
                f"{value!r} is not allowed; allowed values: "
                f"{', '.join(repr(c) for c in param.choices)}{_did_you_mean(value, param.choices)}",
                path,
                value,
            )
        return value
    items = _coerce_string_array(value, path)
    if param.non_empty and not items:
        raise ConfigurationError(
            f"must not be empty (required: {param.description})", path, value
        )
    if param.unique:
        seen: set[str] = set()
        for item in items:
            if item in seen:
                raise ConfigurationError(
                    f"contains {item!r} more than once (duplicates are not allowed)", path, item
                )
            seen.add(item)
    if param.choices:
        for item in items:
            if item not in param.choices:
                raise ConfigurationError(
                    f"{item!r} is not an allowed interface type; allowed: "
                    f"{_fmt(param.choices)}{_did_you_mean(item, param.choices)}",
                    path,
                    item,
                )
    return items


def _command_combination_reason(interfaces: frozenset[str]) -> str:
    if "effort" in interfaces:
        return "'effort' has to be the only command interface"
    if "velocity" in interfaces and "position" not in interfaces:
        return "'velocity' can only be used alone or together with 'position'"
    return "'acceleration' can only be used together with 'position' and 'velocity'"


def _state_combination_reason(interfaces: frozenset[str]) -> str:
    if "acceleration" in interfaces and not {"position", "velocity"} <= interfaces:
        return (
            "the acceleration state interface cannot be used if position and velocity "
            "interfaces are not present"
        )
    if "velocity" in interfaces and "position" not in interfaces:
        return "the velocity state interface cannot be used if the position interface is missing"
    return "the controller expects at least position feedback"  # pragma: no cover


def _check_interfaces(command: tuple[str, ...], state: tuple[str, ...]) -> None:
    command_set = frozenset(command)
    allowed_command = [frozenset(c) for c in ALLOWED_COMMAND_INTERFACE_COMBINATIONS]
    if command_set not in allowed_command:
        raise ConfigurationError(
            f"combination {_fmt(command)} is not supported: "
            f"{_command_combination_reason(command_set)}; allowed combinations: "
            + ", ".join(_fmt(c) for c in ALLOWED_COMMAND_INTERFACE_COMBINATIONS),
            "command_interfaces",
            command,
        )
    state_set = frozenset(state)
    if state_set not in [frozenset(c) for c in ALLOWED_STATE_INTERFACE_COMBINATIONS]:
        raise ConfigurationError(
            f"combination {_fmt(state)} is not supported: {_state_combination_reason(state_set)}"
            "; allowed combinations: "
            + ", ".join(_fmt(c) for c in ALLOWED_STATE_INTERFACE_COMBINATIONS),
            "state_interfaces",
            state,
        )
    needs_velocity_state = (
        command_set == {"velocity"} or "effort" in command_set or "acceleration" in command_set
    )
    if needs_velocity_state and not {"position", "velocity"} <= state_set:
        raise ConfigurationError(
            f"with command_interfaces {_fmt(command)} the state interfaces must include "
            f"position and velocity, got {_fmt(state)}",
            "state_interfaces",
            state,
        )


def _check_key(key: Any, path: str) -> str:
    if not isinstance(key, str):
        raise ConfigurationError(
            f"keys must be strings, got {_describe(key)}; quote it", path, key
        )
    return key


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _unknown_parameter(key: str, known: Iterable[str], prefix: str = "") -> ConfigurationError:
    known = list(known)
    head = key.split(".", 1)[0]
    if "." in key and head in known:
        hint = f"; dotted names are not expanded: nest it under '{head}'"
    else:
        hint = _did_you_mean(key, known) or f"; known parameters: {', '.join(known)}"
    return ConfigurationError(f"unknown parameter {key!r}{hint}", _join(prefix, key), key)


def _not_a_joint(
    key: str, section: str, joints: Sequence[str], others: Sequence[str] = ()
) -> ConfigurationError:
    listed = ", ".join(joints) if joints else "none"
    path = f"{section}.{key}"
    if key == JOINTS_PLACEHOLDER:
        return ConfigurationError(
            f"{JOINTS_PLACEHOLDER!r} is a placeholder from the reference's example file; "
            f"replace it with a joint name (configured joints: {listed})",
            path,
            key,
        )
    also = f" nor one of {', '.join(others)}" if others else ""
    return ConfigurationError(
        f"{key!r} is not a configured joint{also} (joints: {listed})"
        f"{_did_you_mean(key, [*joints, *others])}",
        path,
        key,
    )


def _check_keys(mapping: Mapping[Any, Any], table: Mapping[str, Param], prefix: str) -> None:
    for key in mapping:
        if _check_key(key, prefix) not in table:
            raise _unknown_parameter(key, table, prefix)


def _expect_mapping(value: Any, path: str) -> Mapping[Any, Any]:
    if not isinstance(value, Mapping):
        raise ConfigurationError(f"expected a mapping, got {_describe(value)}", path, value)
    return value


def _checked_fields(obj: Any, table: Mapping[str, Param], prefix: str) -> dict[str, Any]:
    return {name: _coerce(p, getattr(obj, name), _join(prefix, name)) for name, p in table.items()}


def _validate(cfg: ControllerConfig) -> None:
    """Check and normalise every field of ``cfg`` in place (it is frozen, hence setattr)."""

    def put(name: str, value: Any) -> None:
        object.__setattr__(cfg, name, value)

    if not isinstance(cfg.name, str) or not cfg.name:
        raise ConfigurationError(
            f"expected a non-empty controller name, got {_describe(cfg.name)}", "name", cfg.name
        )
    for name, value in _checked_fields(cfg, PARAMETERS, "").items():
        put(name, value)
    joints = cfg.joints
    if cfg.command_joints and len(cfg.command_joints) != len(joints):
        raise ConfigurationError(
            f"has {len(cfg.command_joints)} names but joints has {len(joints)}; give one "
            "command joint per joint, or leave command_joints empty",
            "command_joints",
            cfg.command_joints,
        )
    _check_interfaces(cfg.command_interfaces, cfg.state_interfaces)

    constraints = cfg.constraints
    if not isinstance(constraints, Constraints):
        raise ConfigurationError(
            f"expected a Constraints instance, got {_describe(constraints)}",
            "constraints",
            constraints,
        )
    per_joint = _expect_mapping(constraints.joints, "constraints")
    for key in per_joint:
        if _check_key(key, "constraints") not in joints:
            raise _not_a_joint(key, "constraints", joints, tuple(CONSTRAINT_PARAMETERS))
    joint_constraints: dict[str, JointConstraints] = {}
    for joint in joints:
        given = per_joint.get(joint, JointConstraints())
        if not isinstance(given, JointConstraints):
            raise ConfigurationError(
                f"expected a JointConstraints instance, got {_describe(given)}",
                f"constraints.{joint}",
                given,
            )
        checked = _checked_fields(given, JOINT_CONSTRAINT_PARAMETERS, f"constraints.{joint}")
        joint_constraints[joint] = JointConstraints(**checked)
    put(
        "constraints",
        Constraints(
            **_checked_fields(constraints, CONSTRAINT_PARAMETERS, "constraints"),
            joints=MappingProxyType(joint_constraints),
        ),
    )

    gains = _expect_mapping(cfg.gains, "gains")
    for key in gains:
        if _check_key(key, "gains") not in joints:
            raise _not_a_joint(key, "gains", joints)
    joint_gains: dict[str, Gains] = {}
    for joint in joints:
        given_gains = gains.get(joint, Gains())
        if not isinstance(given_gains, Gains):
            raise ConfigurationError(
                f"expected a Gains instance, got {_describe(given_gains)}",
                f"gains.{joint}",
                given_gains,
            )
        checked_gains = _checked_fields(given_gains, GAIN_PARAMETERS, f"gains.{joint}")
        joint_gains[joint] = Gains(**checked_gains)
    put("gains", MappingProxyType(joint_gains))


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------


class _StrictLoader(yaml.SafeLoader):
    """Safe YAML loader that refuses a key given twice in one mapping."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode) -> dict[Hashable, Any]:
    loader.flatten_mapping(node)
    result: dict[Hashable, Any] = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if key in result:
            raise yaml.constructor.ConstructorError(
                "while constructing a mapping",
                node.start_mark,
                f"found duplicate key {key!r}",
                key_node.start_mark,
            )
        result[key] = loader.construct_object(value_node, deep=True)
    return result


_StrictLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping
)


def _read_source(source: str | os.PathLike[str] | Mapping[str, Any]) -> Mapping[Any, Any]:
    if isinstance(source, Mapping):
        return source
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(
            f"source must be a path or a mapping, got {type(source).__name__}"
        )
    filename = os.fspath(source)
    try:
        with open(filename, encoding="utf-8") as stream:
            data = yaml.load(stream, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader
    except OSError as exc:
        raise ConfigurationError(
            f"cannot read configuration file {filename}: {exc.strerror or exc}", "", filename
        ) from exc
    except yaml.YAMLError as exc:
        raise ConfigurationError(
            f"configuration file {filename} is not valid YAML: {exc}", "", filename
        ) from exc
    if data is None:
        raise ConfigurationError(f"configuration file {filename} is empty", "", filename)
    if not isinstance(data, Mapping):
        raise ConfigurationError(
            f"configuration file {filename} must hold a mapping at the top level, got "
            f"{type(data).__name__}",
            "",
            filename,
        )
    return data


def _is_section(value: Any) -> bool:
    return isinstance(value, Mapping) and ROS_PARAMETERS in value


def _controller_manager(data: Mapping[str, Any]) -> tuple[float | None, dict[str, Any]]:
    """Return the controller manager's update rate and declared controller types."""
    if CONTROLLER_MANAGER not in data:
        return None, {}
    section = data[CONTROLLER_MANAGER]
    if not _is_section(section):
        raise ConfigurationError(
            f"expected a mapping with a {ROS_PARAMETERS!r} entry, got {_describe(section)}",
            CONTROLLER_MANAGER,
            section,
        )
    prefix = f"{CONTROLLER_MANAGER}.{ROS_PARAMETERS}"
    params = section[ROS_PARAMETERS]
    if params is None:
        return None, {}
    params = _expect_mapping(params, prefix)
    update_rate = None
    if "update_rate" in params:
        update_rate = _coerce(
            PARAMETERS["update_rate"], params["update_rate"], f"{prefix}.update_rate"
        )
    types = {
        name: entry["type"]
        for name, entry in params.items()
        if isinstance(entry, Mapping) and "type" in entry
    }
    return update_rate, types


def _select_controller(
    data: Mapping[Any, Any], controller_name: str | None
) -> tuple[str, Mapping[Any, Any], float | None]:
    """Return (name, raw parameters, controller manager update rate or None)."""
    for key in data:
        _check_key(key, "")
    if not any(_is_section(v) for v in data.values()):
        params = {k: v for k, v in data.items() if k not in RESERVED_TOP_LEVEL_KEYS}
        return controller_name or DEFAULT_CONTROLLER_NAME, params, None

    cm_update_rate, declared = _controller_manager(data)
    sections = {
        k: v for k, v in data.items() if k != CONTROLLER_MANAGER and _is_section(v)
    }
    for key, value in data.items():
        if key in sections or key == CONTROLLER_MANAGER or key in RESERVED_TOP_LEVEL_KEYS:
            continue
        hint = _did_you_mean(key, [*sections, CONTROLLER_MANAGER, *RESERVED_TOP_LEVEL_KEYS])
        if isinstance(value, Mapping):
            close = _closest(ROS_PARAMETERS, [str(k) for k in value])
            if close is not None:
                hint = f"; did you mean {ROS_PARAMETERS!r} instead of {close!r}?"
        raise ConfigurationError(
            f"top-level key {key!r} is not a controller section (a mapping with a "
            f"{ROS_PARAMETERS!r} entry), {CONTROLLER_MANAGER!r} or one of "
            f"{', '.join(sorted(RESERVED_TOP_LEVEL_KEYS))}{hint}",
            key,
            key,
        )
    for name, section in sections.items():
        for key in section:
            if key != ROS_PARAMETERS:
                raise ConfigurationError(
                    f"unexpected key {key!r} next to {ROS_PARAMETERS!r}; the controller's "
                    f"parameters go under {ROS_PARAMETERS!r}",
                    f"{name}.{key}",
                    key,
                )

    if not sections:
        raise ConfigurationError(
            f"no controller section found: only {CONTROLLER_MANAGER!r} has "
            f"{ROS_PARAMETERS!r}; add '<controller_name>: {{{ROS_PARAMETERS}: {{joints: ...}}}}'",
            "",
            None,
        )
    if controller_name is not None:
        if controller_name not in sections:
            raise ConfigurationError(
                f"no controller section named {controller_name!r}; controllers in the "
                f"configuration: {', '.join(sections)}{_did_you_mean(controller_name, sections)}",
                "",
                controller_name,
            )
        name = controller_name
    elif len(sections) == 1:
        name = next(iter(sections))
    else:
        ours = [n for n in sections if declared.get(n) == CONTROLLER_TYPE]
        if len(ours) != 1:
            raise ConfigurationError(
                f"the configuration has several controllers ({', '.join(sections)}); "
                "choose one with controller_name",
                "",
                tuple(sections),
            )
        name = ours[0]
    declared_type = declared.get(name)
    if declared_type is not None and declared_type != CONTROLLER_TYPE:
        raise ConfigurationError(
            f"controller {name!r} is declared with type {declared_type!r}; only "
            f"{CONTROLLER_TYPE!r} is implemented",
            f"{CONTROLLER_MANAGER}.{ROS_PARAMETERS}.{name}.type",
            declared_type,
        )
    params = sections[name][ROS_PARAMETERS]
    if params is None:
        params = {}
    return name, _expect_mapping(params, f"{name}.{ROS_PARAMETERS}"), cm_update_rate


def _parse_constraints(raw: Any, joints: Sequence[str]) -> Constraints:
    mapping = _expect_mapping(raw, "constraints")
    scalars: dict[str, Any] = {}
    per_joint: dict[str, JointConstraints] = {}
    for key, value in mapping.items():
        _check_key(key, "constraints")
        if key in CONSTRAINT_PARAMETERS:
            scalars[key] = value
        elif key in joints:
            entry = _expect_mapping(value, f"constraints.{key}")
            _check_keys(entry, JOINT_CONSTRAINT_PARAMETERS, f"constraints.{key}")
            per_joint[key] = JointConstraints(**entry)
        else:
            raise _not_a_joint(key, "constraints", joints, tuple(CONSTRAINT_PARAMETERS))
    return Constraints(**scalars, joints=per_joint)


def _parse_gains(raw: Any, joints: Sequence[str]) -> dict[str, Gains]:
    mapping = _expect_mapping(raw, "gains")
    gains: dict[str, Gains] = {}
    for key, value in mapping.items():
        _check_key(key, "gains")
        if key not in joints:
            raise _not_a_joint(key, "gains", joints)
        entry = _expect_mapping(value, f"gains.{key}")
        _check_keys(entry, GAIN_PARAMETERS, f"gains.{key}")
        gains[key] = Gains(**entry)
    return gains


def _build(name: str, params: Mapping[Any, Any], cm_update_rate: float | None) -> ControllerConfig:
    known = [*PARAMETERS, *_SECTIONS]
    for key in params:
        if _check_key(key, "") not in known:
            raise _unknown_parameter(key, known)
    for param in PARAMETERS.values():
        if param.required and param.name not in params:
            raise ConfigurationError(
                f"missing required parameter {param.name!r} ({param.description})",
                param.name,
            )
    joints = _coerce_string_array(params["joints"], "joints")
    kwargs: dict[str, Any] = {k: v for k, v in params.items() if k in PARAMETERS}
    if cm_update_rate is not None:
        if "update_rate" in params:
            own = _coerce(PARAMETERS["update_rate"], params["update_rate"], "update_rate")
            if own != cm_update_rate:
                raise ConfigurationError(
                    f"{own:g} Hz differs from {CONTROLLER_MANAGER}.{ROS_PARAMETERS}.update_rate "
                    f"({cm_update_rate:g} Hz); the loop has one rate: give it once",
                    "update_rate",
                    params["update_rate"],
                )
        kwargs["update_rate"] = cm_update_rate
    kwargs["constraints"] = _parse_constraints(params.get("constraints", {}), joints)
    kwargs["gains"] = _parse_gains(params.get("gains", {}), joints)
    return ControllerConfig(name=name, **kwargs)


def load_config(
    source: str | os.PathLike[str] | Mapping[str, Any], controller_name: str | None = None
) -> ControllerConfig:
    """Read, check and freeze a controller configuration.

    Args:
        source: path of a YAML file, or an already parsed mapping. Either the upstream
            layout (``<name>: {ros__parameters: {...}}`` plus an optional
            ``controller_manager`` section whose ``update_rate`` is used), or the parameters
            directly at the top level (plus an optional ``update_rate``). Top-level
            ``hardware`` and ``daemon`` keys are skipped (they configure the daemon).
        controller_name: which controller section to use when there are several. Without
            it, the only section is used, or the only one the controller manager declares
            with the joint_trajectory_controller type. For the plain layout it is the
            resulting name (default ``joint_trajectory_controller``).

    Returns:
        The validated configuration, with defaults filled for every joint.

    Raises:
        ConfigurationError: the file cannot be read or parsed, a key is unknown, a required
            parameter is missing, a value has the wrong type or range, or the interfaces
            form an unsupported combination. The message names the dotted key path.
        TypeError: ``source`` is neither a path nor a mapping.
    """
    data = _read_source(source)
    name, params, cm_update_rate = _select_controller(data, controller_name)
    return _build(name, params, cm_update_rate)


# --------------------------------------------------------------------------------------------
# Output and diagnostics
# --------------------------------------------------------------------------------------------


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def config_to_dict(cfg: ControllerConfig, *, nested: bool = False) -> dict[str, Any]:
    """Return the configuration as plain data that :func:`load_config` reads back.

    Args:
        cfg: the configuration.
        nested: give the upstream layout (controller section under ``cfg.name`` and a
            ``controller_manager`` section with ``update_rate`` and the controller type)
            instead of the plain mapping. Only the nested layout keeps the name.

    Returns:
        A new dict of dicts, lists, strings, numbers and booleans (YAML-safe).
    """
    params: dict[str, Any] = {name: _plain(getattr(cfg, name)) for name in PARAMETERS}
    params["constraints"] = {
        **{name: getattr(cfg.constraints, name) for name in CONSTRAINT_PARAMETERS},
        **{
            joint: {name: getattr(jc, name) for name in JOINT_CONSTRAINT_PARAMETERS}
            for joint, jc in cfg.constraints.joints.items()
        },
    }
    params["gains"] = {
        joint: {name: getattr(g, name) for name in GAIN_PARAMETERS}
        for joint, g in cfg.gains.items()
    }
    if not nested:
        return params
    update_rate = params.pop("update_rate")
    if float(update_rate).is_integer():
        update_rate = int(update_rate)  # the controller manager declares it as an integer
    return {
        CONTROLLER_MANAGER: {
            ROS_PARAMETERS: {"update_rate": update_rate, cfg.name: {"type": CONTROLLER_TYPE}}
        },
        cfg.name: {ROS_PARAMETERS: params},
    }


def explain(cfg: ControllerConfig) -> list[str]:
    """List settings that are valid but probably not what was meant.

    Args:
        cfg: the configuration.

    Returns:
        One human-readable warning per finding, each starting with the dotted key path;
        empty if nothing looks suspicious.
    """
    warnings: list[str] = []
    goal_time = cfg.constraints.goal_time
    if cfg.cmd_timeout > 0.0 and cfg.cmd_timeout <= goal_time:
        warnings.append(
            f"cmd_timeout: {cfg.cmd_timeout:g} s is ignored: it must be greater than "
            f"constraints.goal_time ({goal_time:g} s)"
        )
    output = "effort" if "effort" in cfg.command_interfaces else "velocity"
    if cfg.command_interfaces == ("velocity",):
        why = "open_loop_control disables the PID loop"
    else:
        why = (
            f"with command_interfaces {_fmt(cfg.command_interfaces)} commands are forwarded; "
            "the PID loop only runs with effort, or velocity as the only command interface"
        )
    for joint in cfg.joints:
        g = cfg.gains[joint]
        path = f"gains.{joint}"
        if g.normalize_error:
            warnings.append(
                f"{path}.normalize_error: deprecated; use angle_wraparound instead"
            )
        if not cfg.use_pid:
            changed = [t for t in _PID_TERMS if getattr(g, t) != GAIN_PARAMETERS[t].default]
            if changed:
                warnings.append(
                    f"{path}: gains ({', '.join(changed)}) are ignored with these command "
                    f"interfaces: {why}"
                )
            continue
        if g.i != 0.0 and g.i_clamp == 0.0:
            warnings.append(
                f"{path}.i_clamp: is 0 while i is {g.i:g}: the integral term is clamped to "
                "zero; set i_clamp"
            )
        if g.p == 0.0 and g.i == 0.0 and g.d == 0.0 and g.ff_velocity_scale == 0.0:
            warnings.append(
                f"{path}: p, i, d and ff_velocity_scale are all 0: the {output} command of "
                f"{joint!r} is always 0"
            )
    return warnings
