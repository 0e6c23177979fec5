"""The controller's parameters at runtime, and what ``jtc-hw check`` warns of. No I/O.

Runtime parameters: :func:`get_parameters` and :func:`set_parameters` name parameters as ROS
does (``cmd_timeout``, ``constraints.goal_time``, ``constraints.<joint>.goal``,
``gains.<joint>.p``). A change is checked by building the whole configuration again from the
current one with the new values, through the same parser as a configuration file
(:func:`~jtc_hw.config.controller_file.build_config`), so a bad value gives the file's message;
read-only parameters (the schema's ``read_only``) are refused. :func:`explain` lists settings
that are valid but probably not what was meant.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from ..config.controller import (
    CONSTRAINT_PARAMETERS,
    GAIN_PARAMETERS,
    JOINT_CONSTRAINT_PARAMETERS,
    LIMITS_PARAMETERS,
    PARAMETERS,
    PID_TERMS,
    SECTIONS,
    SPEED_SCALING_PARAMETERS,
    ControllerConfig,
    not_a_joint,
)
from ..config.controller_file import build_config, config_to_dict
from ..config.schema import Effect, ParamSpec, unknown_parameter
from ..config.values import describe, fmt_list
from ..errors import ConfigurationError
from .stopping import stop_unavailable_reason

__all__ = [
    "ParameterChange",
    "explain",
    "get_parameters",
    "lookup_parameter",
    "parameter_names",
    "parameters_report",
    "read_only_differences",
    "set_parameters",
]


def explain(cfg: ControllerConfig) -> list[str]:
    """Settings of ``cfg`` that are valid but probably not what was meant: one human-readable
    warning per finding, each starting with the dotted key path; empty if nothing looks
    suspicious."""
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
            changed = [t for t in PID_TERMS if getattr(g, t) != GAIN_PARAMETERS[t].default]
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


# -- Runtime parameters ---------------------------------------------------------------------------

_SECTION_TABLES: dict[str, Mapping[str, ParamSpec]] = {
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
        """The ``set_parameters`` reply's fields (``docs/protocol.md``)."""
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


def lookup_parameter(cfg: ControllerConfig, name: Any) -> tuple[tuple[str, ...], ParamSpec]:
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
            raise unknown_parameter(rest, SPEED_SCALING_PARAMETERS, section)
        return (section, rest), SPEED_SCALING_PARAMETERS[rest]
    if section not in _SECTION_TABLES:
        raise unknown_parameter(name, [*PARAMETERS, *SECTIONS])
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
        raise not_a_joint(rest, section, cfg.joints, others)
    if joint not in cfg.joints:
        raise not_a_joint(joint, section, cfg.joints, others)
    if field not in table:
        raise unknown_parameter(field, table, f"{section}.{joint}")
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
    """Check a runtime change of parameters; the configuration with it applied, the changed
    values and when each takes effect.

    All or nothing: the names are looked up, read-only ones refused, then the configuration is
    built again from ``cfg`` with the new values by the configuration file's parser.

    Args:
        cfg: the configuration in effect.
        changes: new values by ROS-style name (``{"gains.j1.p": 10.0}``), as YAML or JSON
            would give them.

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
    new = build_config(cfg.name, params, None, params.pop("limits"))
    before = set(explain(cfg))
    return ParameterChange(
        new,
        get_parameters(new, changes),
        {name: param.effect for name, (_, param) in found.items()},
        tuple(w for w in explain(new) if w not in before),
    )
