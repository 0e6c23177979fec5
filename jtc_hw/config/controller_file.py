"""The controller's part of a configuration file, in and out (no I/O: :mod:`.reading` reads).

:func:`select_controller` finds the controller's parameters in either source layout (the
upstream ``ros__parameters`` file, with the controller found by name or by type, or a plain
mapping; see :mod:`jtc_hw.config.controller`), :func:`build_config` checks them through the
schema tables and returns a frozen :class:`~jtc_hw.config.controller.ControllerConfig`, and
:func:`config_to_dict` gives back plain data that they read again (``set_parameters`` builds a
changed configuration that way, so a bad value gives the file's message).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from ..errors import ConfigurationError
from .controller import (
    CONSTRAINT_PARAMETERS,
    CONTROLLER_MANAGER,
    CONTROLLER_TYPE,
    DEFAULT_CONTROLLER_NAME,
    GAIN_PARAMETERS,
    JOINT_CONSTRAINT_PARAMETERS,
    LIMITS_PARAMETERS,
    PARAMETERS,
    RESERVED_TOP_LEVEL_KEYS,
    ROS_PARAMETERS,
    SECTIONS,
    SPEED_SCALING_PARAMETERS,
    Constraints,
    ControllerConfig,
    Gains,
    JointConstraints,
    SpeedScaling,
    not_a_joint,
)
from .limits import LIMIT_FIELDS, JointLimits
from .schema import check_key, check_keys, check_value, expect_mapping
from .values import closest, coerce_string_array, describe, did_you_mean

__all__ = [
    "URDF_KEY",
    "UrdfReader",
    "build_config",
    "config_to_dict",
    "limits_to_dict",
    "select_controller",
]

UrdfReader = Callable[[str, Sequence[str]], dict[str, JointLimits]]
"""Reads ``limits.urdf`` (the path as written) for the given joints: :mod:`.reading`'s."""


# -- In: the source layouts -----------------------------------------------------------------------


def _is_section(value: Any) -> bool:
    return isinstance(value, Mapping) and ROS_PARAMETERS in value


def _controller_manager(data: Mapping[str, Any]) -> tuple[float | None, dict[str, Any]]:
    """Return the controller manager's update rate and declared controller types."""
    if CONTROLLER_MANAGER not in data:
        return None, {}
    section = data[CONTROLLER_MANAGER]
    if not _is_section(section):
        raise ConfigurationError(
            f"expected a mapping with a {ROS_PARAMETERS!r} entry, got {describe(section)}",
            CONTROLLER_MANAGER,
            section,
        )
    prefix = f"{CONTROLLER_MANAGER}.{ROS_PARAMETERS}"
    params = section[ROS_PARAMETERS]
    if params is None:
        return None, {}
    params = expect_mapping(params, prefix)
    update_rate = None
    if "update_rate" in params:
        update_rate = check_value(
            PARAMETERS["update_rate"], params["update_rate"], f"{prefix}.update_rate"
        )
    types = {
        name: entry["type"]
        for name, entry in params.items()
        if isinstance(entry, Mapping) and "type" in entry
    }
    return update_rate, types


def select_controller(
    data: Mapping[Any, Any], controller_name: str | None
) -> tuple[str, Mapping[Any, Any], float | None]:
    """Return (name, raw parameters, controller manager update rate or None)."""
    for key in data:
        check_key(key, "")
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
        hint = did_you_mean(key, [*sections, CONTROLLER_MANAGER, *RESERVED_TOP_LEVEL_KEYS])
        if isinstance(value, Mapping):
            close = closest(ROS_PARAMETERS, [str(k) for k in value])
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
                f"configuration: {', '.join(sections)}{did_you_mean(controller_name, sections)}",
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
    return name, expect_mapping(params, f"{name}.{ROS_PARAMETERS}"), cm_update_rate


def _parse_constraints(raw: Any, joints: Sequence[str]) -> Constraints:
    mapping = expect_mapping(raw, "constraints")
    scalars: dict[str, Any] = {}
    per_joint: dict[str, JointConstraints] = {}
    for key, value in mapping.items():
        check_key(key, "constraints")
        if key in CONSTRAINT_PARAMETERS:
            scalars[key] = value
        elif key in joints:
            entry = expect_mapping(value, f"constraints.{key}")
            check_keys(entry, JOINT_CONSTRAINT_PARAMETERS, f"constraints.{key}")
            per_joint[key] = JointConstraints(**entry)
        else:
            raise not_a_joint(key, "constraints", joints, tuple(CONSTRAINT_PARAMETERS))
    return Constraints(**scalars, joints=per_joint)


def _parse_gains(raw: Any, joints: Sequence[str]) -> dict[str, Gains]:
    mapping = expect_mapping(raw, "gains")
    gains: dict[str, Gains] = {}
    for key, value in mapping.items():
        check_key(key, "gains")
        if key not in joints:
            raise not_a_joint(key, "gains", joints)
        entry = expect_mapping(value, f"gains.{key}")
        check_keys(entry, GAIN_PARAMETERS, f"gains.{key}")
        gains[key] = Gains(**entry)
    return gains


def build_config(
    name: str,
    params: Mapping[Any, Any],
    cm_update_rate: float | None,
    limits: Any = None,
    read_urdf: UrdfReader | None = None,
) -> ControllerConfig:
    """Check the controller's raw parameters (and the top-level ``limits`` section) and freeze
    them.

    Args:
        name: the controller's name.
        params: its parameters as the file gives them.
        cm_update_rate: the controller manager's ``update_rate``, if the file has one.
        limits: the ``limits`` section, if any.
        read_urdf: what reads ``limits.urdf`` (``None``: a ``urdf`` key is refused; a
            configuration written back by :func:`config_to_dict` has none).

    Raises:
        ConfigurationError: an unknown key, a missing required parameter, a value of the wrong
            type or range; the message names the dotted key path.
    """
    check_keys(params, [*PARAMETERS, *SECTIONS], "")
    for param in PARAMETERS.values():
        if param.required and param.name not in params:
            raise ConfigurationError(
                f"missing required parameter {param.name!r} ({param.description})",
                param.name,
            )
    joints = coerce_string_array(params["joints"], "joints")
    kwargs: dict[str, Any] = {k: v for k, v in params.items() if k in PARAMETERS}
    if cm_update_rate is not None:
        if "update_rate" in params:
            own = check_value(PARAMETERS["update_rate"], params["update_rate"], "update_rate")
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
    if limits is not None:
        kwargs["limits"], scaling = _parse_limits(limits, joints, read_urdf)
        if scaling is not None:
            kwargs["time_scaling"] = scaling
    speed = expect_mapping(params.get("speed_scaling", {}), "speed_scaling")
    check_keys(speed, SPEED_SCALING_PARAMETERS, "speed_scaling")
    kwargs["speed_scaling"] = SpeedScaling(**speed)
    return ControllerConfig(name=name, **kwargs)


# -- Joint limits: the ``limits`` section ---------------------------------------------------------

URDF_KEY = "urdf"
"""``limits.urdf``: a URDF file whose joint limits are read (relative to the YAML file)."""


def _limit_number(value: Any, path: str, *, positive: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigurationError(f"expected a number, got {describe(value)}", path, value)
    number = float(value)
    if not math.isfinite(number) or (positive and number <= 0.0):
        wanted = "a finite number > 0" if positive else "a finite number"
        raise ConfigurationError(f"must be {wanted}, got {value!r}", path, value)
    return number


def _parse_joint_limits(raw: Any, path: str, base: JointLimits | None) -> JointLimits:
    """One joint's entry; fields it gives replace ``base``'s (the URDF's), ``null`` removes
    one."""
    entry = expect_mapping(raw, path)
    values: dict[str, Any] = {
        name: None if base is None else getattr(base, name) for name in LIMIT_FIELDS
    }
    for key, value in entry.items():
        if check_key(key, path) not in LIMIT_FIELDS:
            raise ConfigurationError(
                f"unknown limit {key!r}{did_you_mean(key, LIMIT_FIELDS)}; a joint's limits "
                f"are {', '.join(LIMIT_FIELDS)}",
                f"{path}.{key}",
                key,
            )
        where = f"{path}.{key}"
        if value is None:
            values[key] = None
        elif key == "position":
            if (
                isinstance(value, (str, bytes, Mapping))
                or not isinstance(value, Sequence)
                or len(value) != 2
            ):
                raise ConfigurationError(
                    f"expected [min, max], got {describe(value)}", where, value
                )
            low = _limit_number(value[0], where, positive=False)
            high = _limit_number(value[1], where, positive=False)
            if not low < high:
                raise ConfigurationError(
                    f"expected [min, max] with min < max, got {list(value)!r}", where, value
                )
            values[key] = (low, high)
        else:
            values[key] = _limit_number(value, where, positive=True)
    return JointLimits(**values)


def _parse_limits(
    raw: Any, joints: Sequence[str], read_urdf: UrdfReader | None
) -> tuple[dict[str, JointLimits], str | None]:
    """The ``limits`` section: per-joint limits (over those of ``urdf``, field by field)
    and ``time_scaling``.

    Raises:
        ConfigurationError: an unknown key or joint, a bad value, or a URDF that cannot be
            read (the message names the file, the joint and the attribute).
    """
    section = expect_mapping(raw, "limits")
    limits: dict[str, JointLimits] = {}
    if URDF_KEY in section:
        urdf = section[URDF_KEY]
        if not isinstance(urdf, str) or not urdf:
            raise ConfigurationError(
                f"expected the path of a URDF file, got {describe(urdf)}", "limits.urdf", urdf
            )
        if read_urdf is None:
            raise ConfigurationError(
                "a URDF is read when a file is loaded, not in a runtime change", "limits.urdf", urdf
            )
        limits = read_urdf(urdf, joints)
    scaling = None
    others = (URDF_KEY, *LIMITS_PARAMETERS)
    for key, value in section.items():
        check_key(key, "limits")
        if key == URDF_KEY:
            continue
        if key in LIMITS_PARAMETERS:
            scaling = check_value(LIMITS_PARAMETERS[key], value, f"limits.{key}")
        elif key in joints:
            entry = _parse_joint_limits(value, f"limits.{key}", limits.get(key))
            limits[key] = entry
        else:
            raise not_a_joint(key, "limits", joints, others)
    return {joint: lim for joint, lim in limits.items() if not lim.empty}, scaling


# -- Out: plain data that reads back --------------------------------------------------------------


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def _values(obj: Any, table: Mapping[str, Any]) -> dict[str, Any]:
    """The fields of ``obj`` that ``table`` names, by name, in the table's order."""
    return {name: getattr(obj, name) for name in table}


def config_to_dict(cfg: ControllerConfig, *, nested: bool = False) -> dict[str, Any]:
    """The configuration as plain data that :func:`load_config` reads back: a new dict of
    dicts, lists, strings, numbers and booleans (YAML-safe).

    Args:
        cfg: the configuration.
        nested: give the upstream layout (controller section under ``cfg.name`` and a
            ``controller_manager`` section with ``update_rate`` and the controller type)
            instead of the plain mapping. Only the nested layout keeps the name.
    """
    params = {name: _plain(value) for name, value in _values(cfg, PARAMETERS).items()}
    params["constraints"] = {**_values(cfg.constraints, CONSTRAINT_PARAMETERS), **{
        joint: _values(jc, JOINT_CONSTRAINT_PARAMETERS)
        for joint, jc in cfg.constraints.joints.items()
    }}
    params["gains"] = {joint: _values(g, GAIN_PARAMETERS) for joint, g in cfg.gains.items()}
    limits = limits_to_dict(cfg)
    params["speed_scaling"] = _values(cfg.speed_scaling, SPEED_SCALING_PARAMETERS)
    if not nested:
        params["limits"] = limits
        return params
    update_rate = params.pop("update_rate")
    if float(update_rate).is_integer():
        update_rate = int(update_rate)  # the controller manager declares it as an integer
    return {
        CONTROLLER_MANAGER: {
            ROS_PARAMETERS: {"update_rate": update_rate, cfg.name: {"type": CONTROLLER_TYPE}}
        },
        cfg.name: {ROS_PARAMETERS: params},
        "limits": limits,
    }


def limits_to_dict(cfg: ControllerConfig) -> dict[str, Any]:
    """The ``limits`` section of ``cfg``: ``time_scaling`` and, per limited joint (in the
    order of ``joints``), the fields it limits (a URDF's included, so no ``urdf`` key)."""
    out = _values(cfg, LIMITS_PARAMETERS)
    for joint in cfg.joints:
        lim = cfg.limits.get(joint)
        if lim is None:
            continue
        out[joint] = {
            name: _plain(getattr(lim, name))
            for name in LIMIT_FIELDS
            if getattr(lim, name) is not None
        }
    return out
