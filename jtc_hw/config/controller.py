"""Controller parameters: read, check and freeze the ``joint_trajectory_controller`` settings.

The parameter names, types, defaults and ranges are those of the upstream controller's
parameter list; they live in one schema table per level (:data:`PARAMETERS`,
:data:`CONSTRAINT_PARAMETERS`, :data:`JOINT_CONSTRAINT_PARAMETERS`, :data:`GAIN_PARAMETERS`).
The rows are :class:`~jtc_hw.config.schema.ParamSpec` rows of the one schema engine, checked by
it; the tables drive validation, the dataclass defaults, :data:`DEFAULTS`,
:func:`~jtc_hw.config.controller_file.config_to_dict` and the runtime parameters
(``read_only``, ``effect``). No I/O.

Two source layouts are accepted by :func:`~jtc_hw.config.reading.load_config`:

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

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from types import MappingProxyType
from typing import Any, Final, TypeVar

from ..errors import ConfigurationError
from .limits import JointLimits, check_joint_limits
from .schema import (
    Effect,
    ParamKind,
    ParamSpec,
    check_fields,
    check_key,
    check_value,
    expect_mapping,
    freeze,
    join,
    param_table,
)
from .values import describe, did_you_mean, fmt_list

__all__ = [
    "ALLOWED_COMMAND_INTERFACE_COMBINATIONS",
    "ALLOWED_STATE_INTERFACE_COMBINATIONS",
    "COMMAND_INTERFACE_TYPES",
    "CONSTRAINT_PARAMETERS",
    "CONTROLLER_TYPE",
    "ControllerConfig",
    "Constraints",
    "CONTROLLER_MANAGER",
    "DEFAULTS",
    "DEFAULT_CONTROLLER_NAME",
    "GAIN_PARAMETERS",
    "Gains",
    "JOINT_CONSTRAINT_PARAMETERS",
    "JointConstraints",
    "LIMITS_PARAMETERS",
    "MAX_SCALING_CEILING",
    "PARAMETERS",
    "PID_TERMS",
    "SECTIONS",
    "SPEED_SCALING_PARAMETERS",
    "STATE_INTERFACE_TYPES",
    "SpeedScaling",
    "ROS_PARAMETERS",
    "RESERVED_TOP_LEVEL_KEYS",
    "not_a_joint",
]

DEFAULT_CONTROLLER_NAME: Final = "joint_trajectory_controller"
"""Controller name used for the plain-mapping form when no name is given."""

CONTROLLER_TYPE: Final = "joint_trajectory_controller/JointTrajectoryController"
"""The only controller type this project implements (``controller_manager`` ``type`` entry)."""

CONTROLLER_MANAGER: Final = "controller_manager"
ROS_PARAMETERS: Final = "ros__parameters"
MAX_SECONDS: Final = (2**63 - 1) / 1_000_000_000
"""Longest duration a time parameter may have: the controller counts in int64 nanoseconds (a
``cmd_timeout`` of 1e308 s crashed the control loop at its next activation, found by the
protocol fuzz)."""
RESERVED_TOP_LEVEL_KEYS: Final = frozenset({"hardware", "daemon", "limits"})
"""Top-level keys that are not controller parameters: :func:`load_config` skips ``hardware``
and ``daemon`` (the daemon's) and reads ``limits`` itself (the joint limits, issue 12)."""

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

SECTIONS: Final = ("constraints", "gains", "speed_scaling")
PID_TERMS: Final = ("p", "i", "d", "i_clamp", "ff_velocity_scale")


# -- Schema ---------------------------------------------------------------------------------------


_F, _B, _S, _A = ParamKind.FLOAT, ParamKind.BOOL, ParamKind.STRING, ParamKind.STRINGS
_CYCLE, _ACTIVATION = Effect.NEXT_CYCLE, Effect.NEXT_ACTIVATION

def _seconds(spec: ParamSpec, value: Any, path: str) -> float:
    """A duration: the standard check (a number >= 0), then at most :data:`MAX_SECONDS`."""
    number: float = check_value(spec, value, path)
    if number > MAX_SECONDS:
        raise ConfigurationError(
            f"must be at most {MAX_SECONDS:.6g} s (int64 nanoseconds), got {value!r}", path,
            value)
    return number


PARAMETERS_SECONDS: Final = {
    "cmd_timeout": ParamSpec("cmd_timeout", _F, 0.0, "seconds", minimum=0.0),
    "goal_time": ParamSpec("goal_time", _F, 0.0, "seconds", minimum=0.0),
}
"""The standard checks of the durations :func:`_seconds` bounds."""


PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("joints", _A, (), "joint names to control and listen to",
              required=True, unique=True, non_empty=True, read_only=True),
    ParamSpec("command_joints", _A, (),
              "joint names to control, if they differ from the state joints (controller chains)",
              unique=True, read_only=True),
    ParamSpec("command_interfaces", _A, (), "command interfaces provided for all joints",
              choices=COMMAND_INTERFACE_TYPES, required=True, unique=True, non_empty=True,
              read_only=True),
    ParamSpec("state_interfaces", _A, (), "state interfaces provided for all joints",
              choices=STATE_INTERFACE_TYPES, required=True, unique=True, non_empty=True,
              read_only=True),
    ParamSpec("allow_partial_joints_goal", _B, False,
              "allow goals defining a trajectory for only some joints"),
    ParamSpec("open_loop_control", _B, False,
              "use the last commands instead of the states as the start of new trajectories",
              read_only=True),
    ParamSpec("allow_integration_in_goal_trajectories", _B, False,
              "accept goals without positions (or velocities) and integrate them"),
    ParamSpec("state_publish_rate", _F, 50.0, "rate the controller state is published, Hz",
              minimum=0.1, effect=_CYCLE),
    ParamSpec("set_last_command_interface_value_as_state_on_activation", _B, True,
              "on activation, use the last command interface values as current and commanded state",
              effect=_ACTIVATION),
    ParamSpec("action_monitor_rate", _F, 20.0, "rate action goals are monitored, Hz", minimum=0.1,
              read_only=True),
    ParamSpec("interpolation_method", _S, "splines", "type of interpolation, if any",
              choices=("splines", "none"), read_only=True),
    ParamSpec("allow_nonzero_velocity_at_trajectory_end", _B, True,
              "if false, goals whose last point has a non-zero velocity are rejected"),
    ParamSpec("cmd_timeout", _F, 0.0,
              "seconds after the last point after which the command is stale (0: off)", minimum=0.0,
              effect=_ACTIVATION, coerce=lambda v, p: _seconds(PARAMETERS_SECONDS["cmd_timeout"],
                                                                v, p)),
    ParamSpec("start_with_holding", _B, True,
              "hold the position after activation (otherwise command nothing until a trajectory)",
              effect=_ACTIVATION),
    ParamSpec("update_rate", _F, 100.0, "control loop rate, Hz (the controller manager's setting)",
              minimum=0.1, read_only=True),
)
"""Top-level controller parameters (``constraints`` and ``gains`` are sections, below)."""

CONSTRAINT_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("stopped_velocity_tolerance", _F, 0.01,
              "velocity below which the system counts as stopped at the trajectory end",
              minimum=0.0),
    ParamSpec("goal_time", _F, 0.0,
              "time tolerance for reaching the goal, seconds (0: wait indefinitely)", minimum=0.0,
              coerce=lambda v, p: _seconds(PARAMETERS_SECONDS["goal_time"], v, p)),
    ParamSpec("decelerate_on_cancel", _B, False,
              "stop by decelerating to rest (cancel, aborts, cmd_timeout, stop, shutdown) "
              "instead of holding on the spot", read_only=True),
)
"""``constraints.*`` parameters other than the per-joint entries."""

JOINT_CONSTRAINT_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("trajectory", _F, 0.0, "position tolerance during the motion (0: not checked)",
              minimum=0.0),
    ParamSpec("goal", _F, 0.0, "position tolerance at the goal (0: not checked)", minimum=0.0),
    ParamSpec("max_deceleration_on_cancel", _F, 0.0,
              "deceleration of a decelerating stop, per second squared (0: derived from the "
              "joint's limits)", minimum=0.0, read_only=True),
)
"""``constraints.<joint>.*`` parameters."""

GAIN_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("p", _F, 0.0, "proportional gain", effect=_CYCLE),
    ParamSpec("i", _F, 0.0, "integral gain", effect=_CYCLE),
    ParamSpec("d", _F, 0.0, "derivative gain", effect=_CYCLE),
    ParamSpec("i_clamp", _F, 0.0, "symmetric integral clamp", minimum=0.0, effect=_CYCLE),
    ParamSpec("ff_velocity_scale", _F, 0.0, "velocity feed-forward scale", effect=_CYCLE),
    # Whether a joint wraps is fixed at configuration upstream (read from the URDF at init;
    # these flags, where they exist, at configure): splices and errors depend on it.
    ParamSpec("normalize_error", _B, False,
              "(deprecated) normalise the position error to [-pi, pi]", read_only=True),
    ParamSpec("angle_wraparound", _B, False,
              "continuous joint: normalise the position error to [-pi, pi]", read_only=True),
)
"""``gains.<joint>.*`` parameters."""

LIMITS_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("time_scaling", _S, "reject",
              "a goal beyond the joint limits: 'reject' it, or 'fit': slow it down until it fits",
              choices=("reject", "fit")),
)
"""``limits.*`` parameters other than the per-joint limits (not upstream's: upstream does not
check goals against limits)."""

MAX_SCALING_CEILING: Final = 10.0
"""The largest ``speed_scaling.max_scaling_factor`` a configuration may give: a factor runs
trajectories that much faster than their author planned them, so the range stays small and
finite (an unbounded factor once made every later goal fail with an overflow, issue 21)."""


def _max_scaling_factor(value: Any, path: str) -> float:
    """``speed_scaling.max_scaling_factor``: a finite number in [1, MAX_SCALING_CEILING], its
    range written as an interval, as the factor's own (``[0, max_scaling_factor]``)."""
    number: float = check_value(_FACTOR, value, path)
    if not 1.0 <= number <= MAX_SCALING_CEILING:
        raise ConfigurationError(
            f"must be in [1, {MAX_SCALING_CEILING:g}], got {value!r}", path, value
        )
    return number


_FACTOR: Final = ParamSpec("max_scaling_factor", _F, 1.0, "a speed scaling factor")

SPEED_SCALING_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("initial_scaling_factor", _F, 1.0,
              "speed scaling factor at activation (1: as planned, 0: paused), in "
              "[0, max_scaling_factor]", minimum=0.0, read_only=True),
    # Not upstream's: upstream's factor is in [0, 1]; a robot whose goals are planned slow may
    # allow more here (read-only: a client cannot raise its own bound).
    ParamSpec("max_scaling_factor", _F, 1.0,
              "largest speed scaling factor accepted (1: upstream's bound; above 1 lets "
              "set_speed_scaling run trajectories faster than planned)", minimum=1.0,
              maximum=MAX_SCALING_CEILING, read_only=True, coerce=_max_scaling_factor),
    # Upstream's fully qualified interface names: here a hardware component's scalar
    # interface, "<component>/<interface>" (the syntax checked in _validate, the name when the
    # hardware is created: HardwareSet.scalar_interface).
    ParamSpec("state_interface", _S, "",
              "scalar state interface the factor is read from each cycle, "
              "'<component>/<interface>' (\"\": none)", read_only=True),
    ParamSpec("command_interface", _S, "",
              "scalar command interface the factor asked for is written to each cycle, "
              "'<component>/<interface>' (\"\": none)", read_only=True),
    # Not upstream's: how fast the factor moves when no acceleration limit bounds it.
    ParamSpec("ramp_time", _F, 0.5,
              "seconds a change of factor by 1 takes when no acceleration limit bounds it "
              "(0: step)", minimum=0.0, effect=_CYCLE),
)
"""``speed_scaling.*`` parameters (jtc_upstream_behaviour.md sections 1 and 13)."""


def _defaults_of(table: Mapping[str, ParamSpec]) -> dict[str, Any]:
    return {name: p.default for name, p in table.items()}


DEFAULTS: Final[Mapping[str, Any]] = freeze({
    **_defaults_of(PARAMETERS),
    "constraints": {
        **_defaults_of(CONSTRAINT_PARAMETERS),
        JOINTS_PLACEHOLDER: _defaults_of(JOINT_CONSTRAINT_PARAMETERS),
    },
    "gains": {JOINTS_PLACEHOLDER: _defaults_of(GAIN_PARAMETERS)},
    "speed_scaling": _defaults_of(SPEED_SCALING_PARAMETERS),
})
"""Every default, nested like the parameter file (``<joints>`` stands for each joint)."""


def _empty_mapping() -> Mapping[str, Any]:
    return MappingProxyType({})


# -- Result types ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class JointConstraints:
    """Default tolerances of one joint (``constraints.<joint>``); 0 means "not checked"."""

    trajectory: float = JOINT_CONSTRAINT_PARAMETERS["trajectory"].default
    goal: float = JOINT_CONSTRAINT_PARAMETERS["goal"].default
    max_deceleration_on_cancel: float = (
        JOINT_CONSTRAINT_PARAMETERS["max_deceleration_on_cancel"].default
    )


@dataclass(frozen=True)
class Constraints:
    """Default tolerances (``constraints``).

    Inside a :class:`ControllerConfig`, ``joints`` has one entry for every configured joint.
    """

    stopped_velocity_tolerance: float = CONSTRAINT_PARAMETERS["stopped_velocity_tolerance"].default
    goal_time: float = CONSTRAINT_PARAMETERS["goal_time"].default
    decelerate_on_cancel: bool = CONSTRAINT_PARAMETERS["decelerate_on_cancel"].default
    joints: Mapping[str, JointConstraints] = field(default_factory=_empty_mapping)

    def __post_init__(self) -> None:
        if isinstance(self.joints, Mapping) and not isinstance(self.joints, MappingProxyType):
            object.__setattr__(self, "joints", MappingProxyType(dict(self.joints)))

    def __reduce__(self) -> tuple[Any, ...]:
        return _reduce(self)


@dataclass(frozen=True)
class Gains:
    """PID gains of one joint (``gains.<joint>``)."""

    p: float = GAIN_PARAMETERS["p"].default
    i: float = GAIN_PARAMETERS["i"].default
    d: float = GAIN_PARAMETERS["d"].default
    i_clamp: float = GAIN_PARAMETERS["i_clamp"].default
    ff_velocity_scale: float = GAIN_PARAMETERS["ff_velocity_scale"].default
    normalize_error: bool = GAIN_PARAMETERS["normalize_error"].default
    angle_wraparound: bool = GAIN_PARAMETERS["angle_wraparound"].default

    @property
    def wraps(self) -> bool:
        """Whether the position error wraps (``angle_wraparound`` or ``normalize_error``)."""
        return self.angle_wraparound or self.normalize_error


@dataclass(frozen=True)
class SpeedScaling:
    """Speed scaling settings (``speed_scaling``; :data:`SPEED_SCALING_PARAMETERS`)."""

    initial_scaling_factor: float = SPEED_SCALING_PARAMETERS["initial_scaling_factor"].default
    max_scaling_factor: float = SPEED_SCALING_PARAMETERS["max_scaling_factor"].default
    state_interface: str = SPEED_SCALING_PARAMETERS["state_interface"].default
    command_interface: str = SPEED_SCALING_PARAMETERS["command_interface"].default
    ramp_time: float = SPEED_SCALING_PARAMETERS["ramp_time"].default


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
    allow_partial_joints_goal: bool = PARAMETERS["allow_partial_joints_goal"].default
    open_loop_control: bool = PARAMETERS["open_loop_control"].default
    allow_integration_in_goal_trajectories: bool = (
        PARAMETERS["allow_integration_in_goal_trajectories"].default
    )
    state_publish_rate: float = PARAMETERS["state_publish_rate"].default
    set_last_command_interface_value_as_state_on_activation: bool = (
        PARAMETERS["set_last_command_interface_value_as_state_on_activation"].default
    )
    action_monitor_rate: float = PARAMETERS["action_monitor_rate"].default
    interpolation_method: str = PARAMETERS["interpolation_method"].default
    allow_nonzero_velocity_at_trajectory_end: bool = (
        PARAMETERS["allow_nonzero_velocity_at_trajectory_end"].default
    )
    cmd_timeout: float = PARAMETERS["cmd_timeout"].default
    start_with_holding: bool = PARAMETERS["start_with_holding"].default
    constraints: Constraints = field(default_factory=Constraints)
    gains: Mapping[str, Gains] = field(default_factory=_empty_mapping)
    update_rate: float = PARAMETERS["update_rate"].default
    limits: Mapping[str, JointLimits] = field(default_factory=_empty_mapping)
    """Per joint, the controller's joint limits (issue 12; :mod:`.limits`); joints absent are
    unlimited. Not one of upstream's parameters (upstream reads limits from the URDF)."""
    time_scaling: str = LIMITS_PARAMETERS["time_scaling"].default
    """``limits.time_scaling``: what a goal beyond the limits gets by default, ``"reject"`` or
    ``"fit"`` (slowed down uniformly; :mod:`.limits_check`); a goal may ask for either."""
    speed_scaling: SpeedScaling = field(default_factory=SpeedScaling)

    def __post_init__(self) -> None:
        _validate(self)

    def __reduce__(self) -> tuple[Any, ...]:
        # Pickled as its checked fields and restored without checking again: the daemon's
        # API process validates a runtime change once and hands the result to the loop
        # process, where a full check would cost milliseconds of a cycle's spare time.
        return _reduce(self)

    def has_command(self, iface: str) -> bool:
        return iface in self.command_interfaces

    def has_state(self, iface: str) -> bool:
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


def _reduce(obj: Any) -> tuple[Any, ...]:
    """``__reduce__`` of a frozen config dataclass holding read-only mappings (not picklable)."""
    state = {
        f.name: dict(value) if isinstance(value := getattr(obj, f.name), Mapping) else value
        for f in fields(obj)
    }
    return (_restore, (type(obj), state))


def _restore(cls: type[Any], state: dict[str, Any]) -> Any:
    """Rebuild what :func:`_reduce` took apart (its values were checked when it was made)."""
    obj = object.__new__(cls)
    for name, value in state.items():
        if isinstance(value, dict):
            value = MappingProxyType(value)
        object.__setattr__(obj, name, value)
    return obj


# -- Value checks ---------------------------------------------------------------------------------


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
    for path, given, allowed, reason in (
        ("command_interfaces", command, ALLOWED_COMMAND_INTERFACE_COMBINATIONS,
         _command_combination_reason),
        ("state_interfaces", state, ALLOWED_STATE_INTERFACE_COMBINATIONS,
         _state_combination_reason),
    ):
        if frozenset(given) not in [frozenset(c) for c in allowed]:
            raise ConfigurationError(
                f"combination {fmt_list(given)} is not supported: "
                f"{reason(frozenset(given))}; allowed combinations: "
                + ", ".join(fmt_list(c) for c in allowed),
                path,
                given,
            )
    command_set, state_set = frozenset(command), frozenset(state)
    needs_velocity_state = (
        command_set == {"velocity"} or "effort" in command_set or "acceleration" in command_set
    )
    if needs_velocity_state and not {"position", "velocity"} <= state_set:
        raise ConfigurationError(
            f"with command_interfaces {fmt_list(command)} the state interfaces must include "
            f"position and velocity, got {fmt_list(state)}",
            "state_interfaces",
            state,
        )


def _check_command_joints(command_joints: tuple[str, ...], joints: tuple[str, ...]) -> None:
    """Upstream's rule (jtc_upstream_behaviour.md sections 1 and 3): empty means ``joints``;
    the same length maps by index (names may differ: a controller chain); shorter must be a
    subset of ``joints`` (mapped by name); longer is an error.

    Raises:
        ConfigurationError: longer than ``joints``, or shorter and naming a joint that is not
            in ``joints``.
    """
    if len(command_joints) > len(joints):
        raise ConfigurationError(
            f"has {len(command_joints)} names but joints has only {len(joints)}; list at most "
            "one command joint per joint (or leave command_joints empty to command every joint)",
            "command_joints",
            command_joints,
        )
    if command_joints and len(command_joints) < len(joints):
        unknown = [name for name in command_joints if name not in joints]
        if unknown:
            raise ConfigurationError(
                f"names {fmt_list(unknown)}, which {'is' if len(unknown) == 1 else 'are'} not "
                f"in joints ({', '.join(joints)}); with fewer command joints than joints, "
                "command_joints must be a subset of joints (the other joints are monitored "
                "only)" + did_you_mean(unknown[0], joints),
                "command_joints",
                unknown[0],
            )


def not_a_joint(
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
        f"{did_you_mean(key, [*joints, *others])}",
        path,
        key,
    )


def _checked_fields(obj: Any, table: Mapping[str, ParamSpec], prefix: str) -> dict[str, Any]:
    return {
        name: check_value(p, getattr(obj, name), join(prefix, name)) for name, p in table.items()
    }


_T = TypeVar("_T")


def _instance(value: Any, cls: type[_T], path: str) -> _T:
    if not isinstance(value, cls):
        raise ConfigurationError(
            f"expected a {cls.__name__} instance, got {describe(value)}", path, value
        )
    return value


def _per_joint(
    entries: Any,
    joints: Sequence[str],
    cls: type[_T],
    table: Mapping[str, ParamSpec],
    section: str,
    others: Sequence[str] = (),
) -> Mapping[str, _T]:
    """``constraints.<joint>`` or ``gains.<joint>``: one checked ``cls`` per joint (the
    defaults for a joint not given); a key that is not a joint (nor one of ``others``) is an
    error."""
    for key in expect_mapping(entries, section):
        if check_key(key, section) not in joints:
            raise not_a_joint(key, section, joints, others)
    checked = {}
    for joint in joints:
        given = _instance(entries.get(joint, cls()), cls, f"{section}.{joint}")
        checked[joint] = cls(**_checked_fields(given, table, f"{section}.{joint}"))
    return MappingProxyType(checked)


def _validate(cfg: ControllerConfig) -> None:
    """Check and normalise every field of ``cfg`` in place (it is frozen, hence setattr)."""

    def put(name: str, value: Any) -> None:
        object.__setattr__(cfg, name, value)

    if not isinstance(cfg.name, str) or not cfg.name:
        raise ConfigurationError(
            f"expected a non-empty controller name, got {describe(cfg.name)}", "name", cfg.name
        )
    check_fields(cfg, PARAMETERS, "")
    joints = cfg.joints
    _check_command_joints(cfg.command_joints, joints)
    _check_interfaces(cfg.command_interfaces, cfg.state_interfaces)

    limits = expect_mapping(cfg.limits, "limits")
    checked_limits: dict[str, JointLimits] = {}
    for key, value in limits.items():
        if check_key(key, "limits") not in joints:
            raise not_a_joint(key, "limits", joints)
        checked_limits[key] = check_joint_limits(value, f"limits.{key}")
    put("limits", MappingProxyType(checked_limits))
    put(
        "time_scaling",
        check_value(LIMITS_PARAMETERS["time_scaling"], cfg.time_scaling, "limits.time_scaling"),
    )

    constraints = _instance(cfg.constraints, Constraints, "constraints")
    joint_constraints = _per_joint(
        constraints.joints, joints, JointConstraints, JOINT_CONSTRAINT_PARAMETERS, "constraints",
        tuple(CONSTRAINT_PARAMETERS),
    )
    put(
        "constraints",
        Constraints(
            **_checked_fields(constraints, CONSTRAINT_PARAMETERS, "constraints"),
            joints=joint_constraints,
        ),
    )
    put("gains", _per_joint(cfg.gains, joints, Gains, GAIN_PARAMETERS, "gains"))

    scaling = _instance(cfg.speed_scaling, SpeedScaling, "speed_scaling")
    checked_scaling = _checked_fields(scaling, SPEED_SCALING_PARAMETERS, "speed_scaling")
    for name in ("state_interface", "command_interface"):
        value = checked_scaling[name]
        component, _, interface = value.partition("/")
        if value and (not component or not interface or "/" in interface
                      or value != value.strip()):
            raise ConfigurationError(
                f"{value!r}: expected '<component>/<interface>', a scalar interface of one of "
                "the robot's hardware components (e.g. 'arm/speed_scaling_factor' on mirror "
                "hardware), or \"\" for none",
                f"speed_scaling.{name}",
                value,
            )
    initial, most = checked_scaling["initial_scaling_factor"], checked_scaling["max_scaling_factor"]
    if initial > most:
        raise ConfigurationError(
            f"must be in [0, {most:g}] (speed_scaling.max_scaling_factor allows more, up to "
            f"{MAX_SCALING_CEILING:g}), got {initial!r}",
            "speed_scaling.initial_scaling_factor",
            initial,
        )
    put("speed_scaling", SpeedScaling(**checked_scaling))
