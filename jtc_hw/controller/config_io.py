"""Controller configuration in and out: ``load_config``, ``config_to_dict``, ``explain``.

:func:`load_config` reads either source layout (the upstream ``ros__parameters`` file, with the
controller found by name or by type, or a plain mapping; see :mod:`jtc_hw.controller.config`)
and returns a checked, immutable :class:`~jtc_hw.controller.config.ControllerConfig`;
:func:`config_to_dict` gives back plain data that it reads again, and :func:`explain` the
human summary that ``jtc-hw check`` prints.

Runtime parameters: :func:`get_parameters` and :func:`set_parameters` name parameters as ROS
does (``cmd_timeout``, ``constraints.goal_time``, ``constraints.<joint>.goal``,
``gains.<joint>.p``). A change is checked by building the whole configuration again from the
current one with the new values, through the same parser as a configuration file, so a bad
value gives the file's message; read-only parameters (the schema's ``read_only``) are refused.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any
from xml.etree import ElementTree

from ..errors import ConfigurationError
from .config import (
    _PID_TERMS,
    _SECTIONS,
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
    SPEED_SCALING_PARAMETERS,
    Constraints,
    ControllerConfig,
    Effect,
    Gains,
    JointConstraints,
    Param,
    SpeedScaling,
    _check_key,
    _check_keys,
    _coerce,
    _expect_mapping,
    _not_a_joint,
    _unknown_parameter,
)
from .limits import LIMIT_FIELDS, JointLimits
from .parsing import (
    closest,
    coerce_string_array,
    describe,
    did_you_mean,
    fmt_list,
    read_source,
)
from .stopping import stop_unavailable_reason

__all__ = [
    "ParameterChange",
    "config_to_dict",
    "explain",
    "get_parameters",
    "limits_to_dict",
    "load_config",
    "lookup_parameter",
    "parameter_names",
    "parameters_report",
    "read_only_differences",
    "read_urdf_limits",
    "set_parameters",
]

# Loading
# --------------------------------------------------------------------------------------------


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


def _build(
    name: str,
    params: Mapping[Any, Any],
    cm_update_rate: float | None,
    limits: Any = None,
    base_dir: str | None = None,
) -> ControllerConfig:
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
    joints = coerce_string_array(params["joints"], "joints")
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
    if limits is not None:
        kwargs["limits"], scaling = _parse_limits(limits, joints, base_dir or os.getcwd())
        if scaling is not None:
            kwargs["time_scaling"] = scaling
    speed = _expect_mapping(params.get("speed_scaling", {}), "speed_scaling")
    _check_keys(speed, SPEED_SCALING_PARAMETERS, "speed_scaling")
    kwargs["speed_scaling"] = SpeedScaling(**speed)
    return ControllerConfig(name=name, **kwargs)


# Joint limits: the ``limits`` section, and URDF files
# --------------------------------------------------------------------------------------------

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
    entry = _expect_mapping(raw, path)
    values: dict[str, Any] = {
        name: None if base is None else getattr(base, name) for name in LIMIT_FIELDS
    }
    for key, value in entry.items():
        if _check_key(key, path) not in LIMIT_FIELDS:
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
    raw: Any, joints: Sequence[str], base_dir: str
) -> tuple[dict[str, JointLimits], str | None]:
    """The ``limits`` section: per-joint limits (over those of ``urdf``, field by field)
    and ``time_scaling``.

    Raises:
        ConfigurationError: an unknown key or joint, a bad value, or a URDF that cannot be
            read (the message names the file, the joint and the attribute).
    """
    section = _expect_mapping(raw, "limits")
    limits: dict[str, JointLimits] = {}
    if URDF_KEY in section:
        urdf = section[URDF_KEY]
        if not isinstance(urdf, str) or not urdf:
            raise ConfigurationError(
                f"expected the path of a URDF file, got {describe(urdf)}", "limits.urdf", urdf
            )
        limits = read_urdf_limits(os.path.join(base_dir, os.path.expanduser(urdf)), joints)
    scaling = None
    others = (URDF_KEY, *LIMITS_PARAMETERS)
    for key, value in section.items():
        _check_key(key, "limits")
        if key == URDF_KEY:
            continue
        if key in LIMITS_PARAMETERS:
            scaling = _coerce(LIMITS_PARAMETERS[key], value, f"limits.{key}")
        elif key in joints:
            entry = _parse_joint_limits(value, f"limits.{key}", limits.get(key))
            limits[key] = entry
        else:
            raise _not_a_joint(key, "limits", joints, others)
    return {joint: lim for joint, lim in limits.items() if not lim.empty}, scaling


def _urdf_error(filename: str, message: str) -> ConfigurationError:
    return ConfigurationError(f"URDF {filename}: {message}", "limits.urdf", filename)


def _urdf_float(
    element: Any, attribute: str, filename: str, joint: str
) -> float | None:
    text = element.get(attribute)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise _urdf_error(
            filename,
            f"joint {joint!r}: <{element.tag} {attribute}={text!r}> is not a finite number",
        )
    return value


def read_urdf_limits(filename: str, joints: Sequence[str]) -> dict[str, JointLimits]:
    """The limits a URDF file gives the joints ``joints`` (others are skipped).

    ``<limit lower upper velocity effort>`` of revolute and prismatic joints give the position
    range (narrowed by ``<safety_controller soft_lower_limit soft_upper_limit>``), continuous
    joints only velocity and effort; a velocity or effort of 0 (URDF's "not given") is no
    limit. The file is read with the standard library's XML parser; a document type
    declaration is refused, so no entity is ever expanded.

    Raises:
        ConfigurationError: the file cannot be read, is not well-formed, has a DOCTYPE, has
            no ``<robot>`` root, or a joint's attribute is not a number, negative where it
            must not be, or a range whose lower end is not below its upper end.
    """
    try:
        with open(filename, "rb") as stream:
            data = stream.read()
    except OSError as exc:
        raise _urdf_error(filename, f"cannot read it: {exc.strerror or exc}") from None
    if b"<!DOCTYPE" in data.upper() or b"<!ENTITY" in data.upper():
        raise _urdf_error(
            filename,
            "has a document type declaration (<!DOCTYPE ...> or <!ENTITY ...>), which is "
            "refused so that no entity is expanded; a URDF needs none: remove it",
        )
    try:
        root = ElementTree.fromstring(data)
    except ElementTree.ParseError as exc:
        raise _urdf_error(filename, f"is not well-formed XML: {exc}") from None
    if root.tag != "robot":
        raise _urdf_error(filename, f"the root element is <{root.tag}>, not <robot>")
    wanted = set(joints)
    limits: dict[str, JointLimits] = {}
    for element in root.iter("joint"):
        name = element.get("name")
        kind = element.get("type")
        if name not in wanted or kind not in ("revolute", "prismatic", "continuous"):
            continue
        limit = element.find("limit")
        safety = element.find("safety_controller")
        position = None
        velocity = effort = None
        if limit is not None:
            for attribute in ("velocity", "effort"):
                value = _urdf_float(limit, attribute, filename, name)
                if value is not None and value < 0.0:
                    raise _urdf_error(
                        filename,
                        f"joint {name!r}: <limit {attribute}={limit.get(attribute)!r}> must "
                        "not be negative",
                    )
                if value:
                    if attribute == "velocity":
                        velocity = value
                    else:
                        effort = value
            if kind != "continuous":
                lower = _urdf_float(limit, "lower", filename, name)
                upper = _urdf_float(limit, "upper", filename, name)
                if lower is not None or upper is not None:
                    low = 0.0 if lower is None else lower
                    high = 0.0 if upper is None else upper
                    if safety is not None:
                        soft_low = _urdf_float(safety, "soft_lower_limit", filename, name)
                        soft_high = _urdf_float(safety, "soft_upper_limit", filename, name)
                        low = low if soft_low is None else max(low, soft_low)
                        high = high if soft_high is None else min(high, soft_high)
                    if not low < high:
                        raise _urdf_error(
                            filename,
                            f"joint {name!r}: the position range [{low:g}, {high:g}] (from "
                            "<limit lower upper> and <safety_controller soft_lower_limit "
                            "soft_upper_limit>) is empty",
                        )
                    position = (low, high)
        found = JointLimits(position, velocity, None, None, effort)
        if not found.empty:
            limits[name] = found
    return limits


def load_config(
    source: str | os.PathLike[str] | Mapping[str, Any],
    controller_name: str | None = None,
    *,
    base_dir: str | os.PathLike[str] | None = None,
) -> ControllerConfig:
    """Read, check and freeze a controller configuration.

    Args:
        source: path of a YAML file, or an already parsed mapping. Either the upstream
            layout (``<name>: {ros__parameters: {...}}`` plus an optional
            ``controller_manager`` section whose ``update_rate`` is used), or the parameters
            directly at the top level (plus an optional ``update_rate``). Top-level
            ``hardware`` and ``daemon`` keys are skipped (they configure the daemon); a
            top-level ``limits`` section gives the joint limits (per joint, or ``urdf``: a
            URDF file's) and ``time_scaling``.
        controller_name: which controller section to use when there are several. Without
            it, the only section is used, or the only one the controller manager declares
            with the joint_trajectory_controller type. For the plain layout it is the
            resulting name (default ``joint_trajectory_controller``).
        base_dir: the directory a relative ``limits.urdf`` is relative to (default: the
            file's directory, or the current directory for a mapping).

    Returns:
        The validated configuration, with defaults filled for every joint.

    Raises:
        ConfigurationError: the file cannot be read or parsed, a key is unknown, a required
            parameter is missing, a value has the wrong type or range, or the interfaces
            form an unsupported combination. The message names the dotted key path.
        TypeError: ``source`` is neither a path nor a mapping.
    """
    data = read_source(source)
    name, params, cm_update_rate = _select_controller(data, controller_name)
    if base_dir is None and not isinstance(source, Mapping):
        base_dir = os.path.dirname(os.path.abspath(os.fspath(source)))
    directory = None if base_dir is None else os.fspath(base_dir)
    return _build(name, params, cm_update_rate, data.get("limits"), directory)


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
    limits = limits_to_dict(cfg)
    params["speed_scaling"] = {
        name: getattr(cfg.speed_scaling, name) for name in SPEED_SCALING_PARAMETERS
    }
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
    out: dict[str, Any] = {name: getattr(cfg, name) for name in LIMITS_PARAMETERS}
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
    moving = [i for i in ("velocity", "effort") if i in cfg.command_interfaces]
    if cfg.allow_nonzero_velocity_at_trajectory_end and moving and not cfg.effective_cmd_timeout:
        # Past its last point the reference keeps that point's velocity (upstream): on a
        # velocity or effort interface the joints keep moving until a new command arrives.
        warnings.append(
            "allow_nonzero_velocity_at_trajectory_end: a trajectory ending with a velocity "
            f"keeps the joints moving (command interface {' and '.join(moving)}) until the "
            "next command, and cmd_timeout is off; set cmd_timeout (seconds, greater than "
            "constraints.goal_time) to stop them when commands stop coming"
        )
    shaped = [j for j, lim in cfg.limits.items() if lim.position is not None or any(
        v is not None for v in (lim.velocity, lim.acceleration, lim.jerk)
    )]
    if cfg.time_scaling == "fit" and not any(
        lim.velocity or lim.acceleration or lim.jerk for lim in cfg.limits.values()
    ):
        warnings.append(
            "limits.time_scaling: 'fit' slows goals down to the velocity, acceleration and jerk "
            "limits, but no joint has one"
            + (" (only position ranges, which slowing cannot fix)" if shaped else "")
        )
    if cfg.constraints.decelerate_on_cancel:
        why_not = stop_unavailable_reason(cfg)
        if why_not is not None:
            warnings.append(
                "constraints.decelerate_on_cancel: stops hold on the spot instead (upstream's "
                f"fall-back): {why_not}"
            )
    if cfg.speed_scaling.initial_scaling_factor == 0.0:
        warnings.append(
            "speed_scaling.initial_scaling_factor: is 0: the controller starts paused and "
            "goals wait until the factor is raised ('jtc-hw resume' or 'jtc-hw speed 1')"
        )
    output = "effort" if "effort" in cfg.command_interfaces else "velocity"
    if cfg.command_interfaces == ("velocity",):
        why = "open_loop_control disables the PID loop"
    else:
        why = (
            f"with command_interfaces {fmt_list(cfg.command_interfaces)} commands are forwarded; "
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


# --------------------------------------------------------------------------------------------
# Runtime parameters
# --------------------------------------------------------------------------------------------

_SECTION_TABLES: dict[str, Mapping[str, Param]] = {
    "constraints": JOINT_CONSTRAINT_PARAMETERS,
    "gains": GAIN_PARAMETERS,
}


@dataclass(frozen=True)
class ParameterChange:
    """A checked runtime change (what :func:`set_parameters` returns).

    Attributes:
        config: the configuration with the change applied.
        values: each changed parameter's new value, as :func:`get_parameters` gives it.
        effects: when each changed parameter takes effect.
        warnings: :func:`explain` findings the change introduced.
    """

    config: ControllerConfig
    values: Mapping[str, Any]
    effects: Mapping[str, Effect]
    warnings: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        """The ``set_parameters`` reply's fields (``docs/protocol.md``).

        Raises:
            Nothing.
        """
        return {
            "parameters": dict(self.values),
            "takes_effect": {name: effect.value for name, effect in self.effects.items()},
            "warnings": list(self.warnings),
        }


def parameter_names(cfg: ControllerConfig) -> list[str]:
    """Every parameter's name, ROS style (``gains.<joint>.p``), in the schema's order."""
    return [
        *PARAMETERS,
        *(f"constraints.{name}" for name in CONSTRAINT_PARAMETERS),
        *(f"limits.{name}" for name in LIMITS_PARAMETERS),
        *(
            f"{section}.{joint}.{name}"
            for section, table in _SECTION_TABLES.items()
            for joint in cfg.joints
            for name in table
        ),
        *(f"speed_scaling.{name}" for name in SPEED_SCALING_PARAMETERS),
    ]


def lookup_parameter(cfg: ControllerConfig, name: Any) -> tuple[tuple[str, ...], Param]:
    """Where parameter ``name`` sits in :func:`config_to_dict`'s mapping, and its schema row.

    Raises:
        ConfigurationError: not a parameter of ``cfg``; the message says what is close or
            which joints exist, as for a configuration file.
    """
    if not isinstance(name, str):
        raise ConfigurationError(
            f"parameter names are strings such as 'gains.<joint>.p', got {describe(name)}",
            "",
            name,
        )
    if name in PARAMETERS:
        return (name,), PARAMETERS[name]
    section, _, rest = name.partition(".")
    if section == "limits":
        if rest in LIMITS_PARAMETERS:
            return (section, rest), LIMITS_PARAMETERS[rest]
        runtime = ", ".join(f"limits.{p}" for p in LIMITS_PARAMETERS)
        raise ConfigurationError(
            "the joint limits are fixed when the configuration is loaded (the robot file's "
            "limits section or its URDF); change them there and restart the daemon; the "
            f"runtime parameters of this section are {runtime}",
            name,
            name,
        )
    if section == "speed_scaling":
        if rest not in SPEED_SCALING_PARAMETERS:
            raise _unknown_parameter(rest, SPEED_SCALING_PARAMETERS, section)
        return (section, rest), SPEED_SCALING_PARAMETERS[rest]
    if section not in _SECTION_TABLES:
        raise _unknown_parameter(name, [*PARAMETERS, *_SECTIONS])
    if not rest:
        example = "goal_time" if section == "constraints" else f"{cfg.joints[0]}.p"
        raise ConfigurationError(
            f"is a section, not a parameter; name one of its parameters, e.g. "
            f"'{section}.{example}'",
            section,
            name,
        )
    if section == "constraints" and rest in CONSTRAINT_PARAMETERS:
        return (section, rest), CONSTRAINT_PARAMETERS[rest]
    joint, dot, field = rest.rpartition(".")  # joint names may contain dots
    table = _SECTION_TABLES[section]
    others = tuple(CONSTRAINT_PARAMETERS) if section == "constraints" else ()
    if not dot:
        if rest in cfg.joints:
            raise ConfigurationError(
                f"is a joint's entry, not a parameter; name one of its parameters: "
                f"{', '.join(f'{name}.{p}' for p in table)}",
                name,
                name,
            )
        raise _not_a_joint(rest, section, cfg.joints, others)
    if joint not in cfg.joints:
        raise _not_a_joint(joint, section, cfg.joints, others)
    if field not in table:
        raise _unknown_parameter(field, table, f"{section}.{joint}")
    return (section, joint, field), table[field]


def _get(params: Mapping[str, Any], path: tuple[str, ...]) -> Any:
    value: Any = params
    for key in path:
        value = value[key]
    return value


def get_parameters(cfg: ControllerConfig, names: Iterable[str] | None = None) -> dict[str, Any]:
    """Parameter values by ROS-style name (all of them, or ``names`` in their order).

    Raises:
        ConfigurationError: a name is not a parameter (see :func:`lookup_parameter`).
    """
    params = config_to_dict(cfg)
    wanted = parameter_names(cfg) if names is None else list(names)
    return {name: _get(params, lookup_parameter(cfg, name)[0]) for name in wanted}


def parameters_report(
    cfg: ControllerConfig, names: Iterable[str] | None = None
) -> dict[str, Any]:
    """The ``get_parameters`` reply's fields: the values (:func:`get_parameters`) and which of
    them are read-only.

    Raises:
        ConfigurationError: a name is not a parameter.
    """
    values = get_parameters(cfg, names)
    return {
        "parameters": values,
        "read_only": [name for name in values if lookup_parameter(cfg, name)[1].read_only],
    }


def read_only_differences(old: ControllerConfig, new: ControllerConfig) -> list[str]:
    """The read-only parameters whose values differ between ``old`` and ``new``.

    Cheap (no full comparison): the control loop calls it before switching configurations.
    """
    names = [
        name for name, p in PARAMETERS.items()
        if p.read_only and getattr(old, name) != getattr(new, name)
    ]
    if old.name != new.name:
        names.append("name")
    if old.limits != new.limits:
        names.append("limits")
    names.extend(
        f"constraints.{name}" for name, p in CONSTRAINT_PARAMETERS.items()
        if p.read_only and getattr(old.constraints, name) != getattr(new.constraints, name)
    )
    names.extend(
        f"speed_scaling.{name}" for name, p in SPEED_SCALING_PARAMETERS.items()
        if p.read_only and getattr(old.speed_scaling, name) != getattr(new.speed_scaling, name)
    )
    if names:  # a different joint list: the per-joint entries are moot
        return names
    for section, table in _SECTION_TABLES.items():
        fixed = [name for name, p in table.items() if p.read_only]
        if not fixed:
            continue
        entries = old.constraints.joints if section == "constraints" else old.gains
        others = new.constraints.joints if section == "constraints" else new.gains
        for joint in old.joints:
            names.extend(
                f"{section}.{joint}.{name}"
                for name in fixed
                if getattr(entries[joint], name) != getattr(others[joint], name)
            )
    return names


def set_parameters(cfg: ControllerConfig, changes: Mapping[str, Any]) -> ParameterChange:
    """Check a runtime change of parameters and return the configuration with it applied.

    All or nothing: the names are looked up, read-only ones refused, then the configuration is
    built again from ``cfg`` with the new values by the configuration file's parser.

    Args:
        cfg: the configuration in effect.
        changes: new values by ROS-style name (``{"gains.j1.p": 10.0}``), as YAML or JSON
            would give them.

    Returns:
        The new configuration, the changed values and when each takes effect.

    Raises:
        ConfigurationError: nothing to change, an unknown name, read-only parameters (all of
            them named), or a value the configuration file would refuse (the same message).
    """
    if not isinstance(changes, Mapping) or not changes:
        raise ConfigurationError(
            "give at least one parameter and its new value, e.g. {'gains.<joint>.p': 10.0}",
            "",
            changes,
        )
    found = {name: lookup_parameter(cfg, name) for name in changes}
    fixed = [name for name, (_, param) in found.items() if param.read_only]
    if fixed:
        refusal = ConfigurationError(
            f"read-only parameter{'s' if len(fixed) > 1 else ''} {', '.join(fixed)} cannot be "
            "changed while the controller runs (upstream declares them read-only, or reads "
            "them only when it is configured); change the configuration file and restart the "
            "daemon"
        )
        refusal.path, refusal.value = fixed[0], changes[fixed[0]]
        raise refusal
    params = config_to_dict(cfg)
    for name, value in changes.items():
        *parents, key = found[name][0]
        _get(params, tuple(parents))[key] = value
    new = _build(cfg.name, params, None, params.pop("limits"))
    before = set(explain(cfg))
    return ParameterChange(
        new,
        get_parameters(new, changes),
        {name: param.effect for name, (_, param) in found.items()},
        tuple(w for w in explain(new) if w not in before),
    )
