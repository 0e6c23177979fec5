"""Hardware interfaces: the lifecycle contract, a set of components, and the registry.

Theory of operation
-------------------
A :class:`HardwareInterface` is one component (a bus, a motor group, a simulator) serving some
joints in SI units. It follows ros2_control's ``SystemInterface`` lifecycle::

    UNCONFIGURED --configure()--> INACTIVE --activate()--> ACTIVE
    UNCONFIGURED <--cleanup()---- INACTIVE <--deactivate()- ACTIVE
    any state --shutdown()--> FINALIZED

``read`` is allowed while INACTIVE or ACTIVE (the daemon shows positions of a disarmed robot),
``write`` only while ACTIVE. The base class owns the policy, as python-can's ``BusABC`` does:
the transition guard (:data:`TRANSITIONS`, one table), parameter validation against the kind's
:attr:`HardwareInterface.PARAMS` schema, wrapping of foreign exceptions in
:class:`~jtc_hw.errors.HardwareError` naming the component, fault bookkeeping and counters.
Drivers implement the underscore primitives (``_read``, ``_write`` and, if they need them,
``_configure``, ``_activate``, ``_deactivate``, ``_cleanup``).

A failed ``configure``/``activate`` leaves the state unchanged. A failed ``deactivate`` or
``cleanup`` still leaves the state it aims at: the component stops accepting writes (the safe
side for us) and the error reports that the device may not have performed its safe action.

A :class:`HardwareSet` joins components whose joints together are the controller's joints; it
maps between the controller's joint order and each component's with index arrays computed once.

Kinds are found through a lazy registry: built-in ``"module:Class"`` strings, the
``jtc_hw.hardware`` entry-point group, and :func:`register_hardware`. Importing a kind's module
happens only when it is created, so a missing optional SDK only matters to whoever uses it, and
then the error names the ``pip install`` extra.
"""

from __future__ import annotations

import importlib
import logging
import math
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from importlib import metadata
from types import MappingProxyType
from typing import Any, ClassVar, Final

import numpy as np
from numpy.typing import NDArray

from .config import (
    COMMAND_INTERFACE_TYPES,
    STATE_INTERFACE_TYPES,
    _coerce_bool,
    _coerce_string_array,
    _describe,
    _did_you_mean,
)
from .errors import ConfigurationError, ControllerStateError, HardwareError, JtcHwError
from .joints import JointCommand, JointState

__all__ = [
    "BUILTIN_HARDWARE",
    "COMMON_PARAMS",
    "ENTRY_POINT_GROUP",
    "TRANSITIONS",
    "HardwareInterface",
    "HardwareSet",
    "HardwareSpec",
    "JOINT_MAPPING_PARAMS",
    "LifecycleState",
    "ParamKind",
    "ParamSpec",
    "SafeAction",
    "available_hardware",
    "check_hardware_kind",
    "create_hardware",
    "hardware_class",
    "param_table",
    "register_hardware",
    "unregister_hardware",
    "validate_params",
]

_log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


# --------------------------------------------------------------------------------------------
# Lifecycle
# --------------------------------------------------------------------------------------------


class LifecycleState(Enum):
    """Lifecycle state of a hardware component (ros2_control's primary states)."""

    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FINALIZED = "finalized"


class SafeAction(Enum):
    """What ``deactivate`` leaves the joints doing (the ``safe_action`` parameter)."""

    HOLD = "hold"
    """Keep torque on and hold the last position."""
    TORQUE_OFF = "torque_off"
    """Switch the drives off; the joints are free (and hold no command any more)."""


_U, _I, _A, _F = (
    LifecycleState.UNCONFIGURED,
    LifecycleState.INACTIVE,
    LifecycleState.ACTIVE,
    LifecycleState.FINALIZED,
)

TRANSITIONS: Final[Mapping[tuple[LifecycleState, str], LifecycleState]] = MappingProxyType({
    (_U, "configure"): _I,
    (_I, "activate"): _A,
    (_A, "deactivate"): _I,
    (_I, "cleanup"): _U,
})
"""The lifecycle transitions: (state, method) -> state left on success."""

_ALLOWED: Final[Mapping[str, frozenset[LifecycleState]]] = MappingProxyType({
    **{method: frozenset({state}) for (state, method) in TRANSITIONS},
    "read": frozenset({_I, _A}),
    "write": frozenset({_A}),
    "recover": frozenset({_I}),
})


def _steps_to(state: LifecycleState, targets: frozenset[LifecycleState]) -> list[str] | None:
    """Shortest list of transition methods leading from ``state`` into ``targets``."""
    queue: deque[tuple[LifecycleState, list[str]]] = deque([(state, [])])
    seen = {state}
    while queue:
        current, steps = queue.popleft()
        if current in targets:
            return steps
        for (source, method), target in TRANSITIONS.items():
            if source is current and target not in seen:
                seen.add(target)
                queue.append((target, [*steps, method]))
    return None


def _lifecycle_error(owner: str, method: str, state: LifecycleState) -> ControllerStateError:
    steps = _steps_to(state, _ALLOWED[method])
    if not steps:
        hint = "it was shut down; create a new instance"
    else:
        hint = "call " + " and ".join(f"{step}()" for step in steps) + " first"
    return ControllerStateError(f"{owner}: cannot call {method}() while {state.value}; {hint}")


# --------------------------------------------------------------------------------------------
# Parameter schema (shared with robot.py)
# --------------------------------------------------------------------------------------------


class ParamKind(Enum):
    """Value type of a parameter; the value is the wording used in error messages."""

    FLOAT = "a number"
    INT = "an integer"
    BOOL = "true or false"
    STRING = "a string"
    STRINGS = "a list of strings"
    INTS = "a list of integers"
    RANGE = "a [min, max] pair of numbers"
    SECTION = "a mapping"


_PER_JOINT_KINDS: Final = frozenset(
    {ParamKind.FLOAT, ParamKind.INT, ParamKind.BOOL, ParamKind.STRING, ParamKind.RANGE}
)


@dataclass(frozen=True)
class ParamSpec:
    """One row of a parameter schema table.

    Attributes:
        name: parameter name (last component of its dotted path).
        kind: value type.
        default: value used when the parameter is not given (for ``per_joint``: the value of
            each joint not given).
        description: one-line description.
        minimum: inclusive lower bound for numbers (each element for lists and ranges).
        maximum: inclusive upper bound for numbers.
        choices: allowed values for strings and integers.
        required: the parameter must be given.
        nullable: an explicit ``null`` means "use the default".
        unique: list without duplicates.
        non_empty: list that must have at least one element.
        per_joint: one value per joint, given as one value for every joint, a list in the
            component's joint order, or a mapping ``{joint: value}`` (joints not named get the
            default). Normalised to a tuple in joint order. For ``RANGE`` a ``null`` entry
            means unlimited.
        fields: for ``SECTION``: the schema of the nested mapping (``None``: any mapping with
            string keys, kept as given).
        coerce: custom check replacing the standard one: ``coerce(value, path)`` returns the
            normalised value or raises :class:`ConfigurationError`.
    """

    name: str
    kind: ParamKind
    default: Any
    description: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[str, ...] | tuple[int, ...] = ()
    required: bool = False
    nullable: bool = False
    unique: bool = False
    non_empty: bool = False
    per_joint: bool = False
    fields: Mapping[str, ParamSpec] | None = None
    coerce: Callable[[Any, str], Any] | None = None


def param_table(*params: ParamSpec) -> Mapping[str, ParamSpec]:
    """Build a read-only schema table keyed by parameter name.

    Raises:
        ValueError: two rows have the same name, or ``per_joint`` is set on a list or section.
    """
    table = {p.name: p for p in params}
    if len(table) != len(params):
        raise ValueError("duplicate parameter names in a schema table")
    for p in params:
        if p.per_joint and p.kind not in _PER_JOINT_KINDS:
            raise ValueError(f"parameter {p.name!r}: {p.kind.name} cannot be per joint")
    return MappingProxyType(table)


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _bounds(spec: ParamSpec) -> str:
    if spec.minimum is not None and spec.maximum is not None:
        return f"between {spec.minimum:g} and {spec.maximum:g}"
    if spec.minimum is not None:
        return f">= {spec.minimum:g}"
    return f"<= {spec.maximum:g}"


def _check_bounds(spec: ParamSpec, number: float, value: Any, path: str, what: str) -> None:
    low = spec.minimum is not None and number < spec.minimum
    high = spec.maximum is not None and number > spec.maximum
    if low or high:
        raise ConfigurationError(f"{what}must be {_bounds(spec)}, got {value!r}", path, value)


def _number(spec: ParamSpec, value: Any, path: str, what: str = "", finite: bool = True) -> float:
    if not _is_number(value):
        raise ConfigurationError(f"{what}expected a number, got {_describe(value)}", path, value)
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if math.isnan(number) or (finite and math.isinf(number)):
        raise ConfigurationError(f"{what}expected a finite number, got {value!r}", path, value)
    _check_bounds(spec, number, value, path, what)
    return number


def _integer(spec: ParamSpec, value: Any, path: str, what: str = "") -> int:
    if not isinstance(value, int) or isinstance(value, bool):
        raise ConfigurationError(
            f"{what}expected an integer, got {_describe(value)}", path, value
        )
    if spec.choices and value not in spec.choices:
        allowed = " or ".join(str(c) for c in spec.choices)
        raise ConfigurationError(f"{what}must be {allowed}, got {value}", path, value)
    _check_bounds(spec, value, value, path, what)
    return value


def _range(spec: ParamSpec, value: Any, path: str, what: str = "") -> tuple[float, float]:
    if (
        not isinstance(value, (list, tuple))
        or len(value) != 2
        or not all(_is_number(v) for v in value)
    ):
        raise ConfigurationError(
            f"{what}expected a [min, max] pair of numbers, got {_describe(value)}", path, value
        )
    low = _number(spec, value[0], path, what, finite=False)
    high = _number(spec, value[1], path, what, finite=False)
    if low > high:
        raise ConfigurationError(f"{what}min {low:g} is greater than max {high:g}", path, value)
    return (low, high)


def _string(spec: ParamSpec, value: Any, path: str, what: str = "") -> str:
    if not isinstance(value, str):
        raise ConfigurationError(f"{what}expected a string, got {_describe(value)}", path, value)
    if spec.choices and value not in spec.choices:
        names = [str(c) for c in spec.choices]
        raise ConfigurationError(
            f"{what}{value!r} is not allowed; allowed values: "
            f"{', '.join(repr(c) for c in spec.choices)}{_did_you_mean(value, names)}",
            path,
            value,
        )
    return value


def _scalar(spec: ParamSpec, value: Any, path: str, what: str = "") -> Any:
    """Check one value of kind FLOAT, INT, BOOL, STRING or RANGE."""
    if spec.kind is ParamKind.STRING:
        return _string(spec, value, path, what)
    if spec.kind is ParamKind.FLOAT:
        return _number(spec, value, path, what)
    if spec.kind is ParamKind.INT:
        return _integer(spec, value, path, what)
    if spec.kind is ParamKind.RANGE:
        if value is None and spec.per_joint:
            return spec.default
        return _range(spec, value, path, what)
    return _coerce_bool(value, path, what)


def _looks_like_one(spec: ParamSpec, value: Any) -> bool:
    """Whether ``value`` is one value for every joint (not a list / mapping of values)."""
    if spec.kind is ParamKind.RANGE:
        return isinstance(value, (list, tuple)) and len(value) == 2 and all(
            _is_number(v) for v in value
        )
    return not isinstance(value, (list, tuple, Mapping))


def _per_joint(spec: ParamSpec, value: Any, path: str, joints: Sequence[str]) -> tuple[Any, ...]:
    if _looks_like_one(spec, value):
        one = _scalar(spec, value, path)
        return tuple(one for _ in joints)
    if isinstance(value, Mapping):
        result = dict.fromkeys(joints, spec.default)
        for joint, item in value.items():
            if joint not in result:
                raise ConfigurationError(
                    f"{joint!r} is not one of this component's joints ({', '.join(joints)})"
                    f"{_did_you_mean(str(joint), joints)}",
                    f"{path}.{joint}",
                    joint,
                )
            result[joint] = _scalar(spec, item, f"{path}.{joint}")
        missing = [j for j in joints if j not in value]
        if spec.required and missing:
            raise ConfigurationError(
                f"gives no value for {', '.join(repr(j) for j in missing)}; this parameter "
                "is required for every joint",
                path,
                value,
            )
        return tuple(result[j] for j in joints)
    if len(value) != len(joints):
        raise ConfigurationError(
            f"has {len(value)} entries but the component has {len(joints)} joints "
            f"({', '.join(joints)}); give one per joint, one value for all, or a mapping "
            "{joint: value}",
            path,
            value,
        )
    return tuple(
        _scalar(spec, item, f"{path}[{i}]", f"(joint {joint!r}) ")
        for i, (item, joint) in enumerate(zip(value, joints, strict=True))
    )


def _strings(spec: ParamSpec, value: Any, path: str) -> tuple[str, ...]:
    # The same rules (and messages) as the controller's string-array parameters.
    return _coerce_string_array(value, path)


def _list_checks(spec: ParamSpec, items: tuple[Any, ...], path: str, value: Any) -> None:
    if spec.non_empty and not items:
        raise ConfigurationError(f"must not be empty ({spec.description})", path, value)
    if spec.unique:
        seen: set[Any] = set()
        for item in items:
            if item in seen:
                raise ConfigurationError(
                    f"contains {item!r} more than once (duplicates are not allowed)", path, item
                )
            seen.add(item)


def _coerce(spec: ParamSpec, value: Any, path: str, joints: Sequence[str]) -> Any:
    if spec.coerce is not None:
        return spec.coerce(value, path)
    kind = spec.kind
    if spec.per_joint:
        return _per_joint(spec, value, path, joints)
    if kind is ParamKind.STRING:
        return _string(spec, value, path)
    if kind is ParamKind.STRINGS:
        items: tuple[Any, ...] = _strings(spec, value, path)
        _list_checks(spec, items, path, value)
        return items
    if kind is ParamKind.INTS:
        if not isinstance(value, (list, tuple)):
            raise ConfigurationError(
                f"expected a list of integers, got {_describe(value)}", path, value
            )
        items = tuple(
            _integer(spec, item, path, f"element {i}: ") for i, item in enumerate(value)
        )
        _list_checks(spec, items, path, value)
        return items
    if kind is ParamKind.SECTION:
        if spec.fields is None:
            if not isinstance(value, Mapping):
                raise ConfigurationError(f"expected a mapping, got {_describe(value)}", path, value)
            for key in value:
                _check_key(key, path)
            return _freeze(value)
        return validate_params(spec.fields, value, path, joints=joints)
    return _scalar(spec, value, path)


def _check_key(key: Any, path: str) -> str:
    if not isinstance(key, str):
        raise ConfigurationError(f"keys must be strings, got {_describe(key)}; quote it", path, key)
    return key


def _freeze(value: Any) -> Any:
    """Deep read-only copy: mappings become MappingProxyType, lists become tuples."""
    if isinstance(value, Mapping):
        return MappingProxyType({k: _freeze(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)):
        return tuple(_freeze(v) for v in value)
    return value


def _default(spec: ParamSpec, path: str, joints: Sequence[str]) -> Any:
    if spec.per_joint:
        return tuple(spec.default for _ in joints)
    if spec.kind is ParamKind.SECTION and spec.fields is not None and spec.default is not None:
        return validate_params(spec.fields, spec.default, path, joints=joints)
    return spec.default


def validate_params(
    schema: Mapping[str, ParamSpec],
    raw: Mapping[str, Any] | None,
    path: str = "",
    *,
    joints: Sequence[str] = (),
    owner: str = "",
) -> Mapping[str, Any]:
    """Check a mapping of parameters against a schema table and fill in defaults.

    Args:
        schema: the table (see :func:`param_table`).
        raw: the given parameters (``None`` counts as empty).
        path: dotted path of the mapping, prefixed to error paths (e.g. ``params``).
        joints: joint names, for ``per_joint`` parameters.
        owner: who the parameters belong to, for messages (e.g. ``mirror hardware 'arm'``).

    Returns:
        A read-only mapping with every parameter of the table, normalised (numbers as float
        or int, lists as tuples, per-joint values as tuples in joint order).

    Raises:
        ConfigurationError: not a mapping, unknown key (with a suggestion), missing required
            key, wrong type, out of range; the error's path names the key.
    """
    if raw is None:
        raw = {}
    of = f" of {owner}" if owner else ""
    if not isinstance(raw, Mapping):
        raise ConfigurationError(f"expected a mapping{of}, got {_describe(raw)}", path, raw)
    for key in raw:
        if _check_key(key, path) not in schema:
            known = list(schema)
            hint = _did_you_mean(key, known) or (
                f"; known parameters: {', '.join(known)}" if known else "; it takes none"
            )
            raise ConfigurationError(f"unknown parameter {key!r}{of}{hint}", _join(path, key), key)
    result: dict[str, Any] = {}
    for name, spec in schema.items():
        key_path = _join(path, name)
        value = raw.get(name)
        if name not in raw or (value is None and spec.nullable):
            if spec.required:
                raise ConfigurationError(
                    f"missing required parameter {name!r}{of} ({spec.description})", key_path
                )
            result[name] = _default(spec, key_path, joints)
        else:
            result[name] = _coerce(spec, value, key_path, joints)
    return MappingProxyType(result)


COMMON_PARAMS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("safe_action", ParamKind.STRING, SafeAction.HOLD.value,
              "what deactivate() leaves the joints doing: hold the position, or torque off",
              choices=tuple(a.value for a in SafeAction)),
)
"""Parameters every hardware kind accepts (merged with the kind's ``PARAMS``)."""

JOINT_MAPPING_PARAMS: Final[tuple[ParamSpec, ...]] = (
    ParamSpec("offset", ParamKind.FLOAT, 0.0,
              "per joint: joint position at motor zero, rad "
              "(joint = direction * motor / gear_ratio + offset)", per_joint=True),
    ParamSpec("direction", ParamKind.INT, 1,
              "per joint: 1 or -1, the joint's sense against the motor's",
              choices=(1, -1), per_joint=True),
    ParamSpec("gear_ratio", ParamKind.FLOAT, 1.0,
              "per joint: motor turns per joint turn (external gearing)",
              minimum=1e-9, per_joint=True),
)
"""How a motor's position maps to its joint's, for drivers to include in their ``PARAMS``
(``param_table(*JOINT_MAPPING_PARAMS, ...)``): one convention for every kind."""


# --------------------------------------------------------------------------------------------
# The contract
# --------------------------------------------------------------------------------------------


def _check_joint_names(value: Any, path: str) -> tuple[str, ...]:
    spec = ParamSpec(path, ParamKind.STRINGS, (), "the joints of the component",
                     unique=True, non_empty=True)
    names: tuple[str, ...] = _coerce(spec, value, path, ())
    return names


def _check_interfaces(
    value: Any, path: str, supported: Sequence[str], owner: str
) -> tuple[str, ...]:
    spec = ParamSpec(path, ParamKind.STRINGS, (), f"{path.replace('_', ' ')}",
                     unique=True, non_empty=True)
    names: tuple[str, ...] = _coerce(spec, value, path, ())
    for name in names:
        if name not in supported:
            raise ConfigurationError(
                f"{owner} does not support the {name!r} interface; it supports "
                f"[{', '.join(supported)}]{_did_you_mean(name, supported)}",
                path,
                name,
            )
    return names


class HardwareInterface(ABC):
    """A hardware component serving some joints, with the ros2_control lifecycle.

    Subclasses declare :attr:`kind` and :attr:`PARAMS` and implement ``_read`` and ``_write``
    (plus ``_configure``, ``_activate``, ``_deactivate``, ``_cleanup`` if they need them). The
    public methods guard the lifecycle, wrap foreign exceptions and count; see the module
    docstring for the state machine.

    Args:
        name: component name, unique within a robot (used in every message).
        joints: the component's joints, in the order its arrays use.
        command_interfaces: the controller's command interfaces (all joints take them).
        state_interfaces: the controller's state interfaces; must include ``position``.
        params: kind-specific parameters, checked against ``COMMON_PARAMS`` + ``PARAMS``.

    Raises:
        ConfigurationError: bad name, joints, interfaces (or one the kind does not support),
            or parameters; the path is ``name``, ``joints``, ``command_interfaces``,
            ``state_interfaces`` or ``params.<key>``.
        TypeError: the subclass does not declare ``kind``.
    """

    kind: ClassVar[str]
    """Registry name of the hardware kind (e.g. ``"mirror"``)."""

    PARAMS: ClassVar[Mapping[str, ParamSpec]] = MappingProxyType({})
    """Kind-specific parameter schema (see :func:`param_table`)."""

    COMMAND_INTERFACES: ClassVar[tuple[str, ...]] = COMMAND_INTERFACE_TYPES
    """Command interfaces the kind can serve."""

    STATE_INTERFACES: ClassVar[tuple[str, ...]] = STATE_INTERFACE_TYPES
    """State interfaces the kind can serve."""

    def __init__(
        self,
        name: str,
        joints: Sequence[str],
        command_interfaces: Sequence[str],
        state_interfaces: Sequence[str],
        params: Mapping[str, Any],
    ) -> None:
        kind = getattr(type(self), "kind", None)
        if not isinstance(kind, str) or not kind:
            raise TypeError(f"{type(self).__name__} must declare a non-empty 'kind' class variable")
        if not isinstance(name, str) or not name.strip():
            raise ConfigurationError(
                f"expected a non-empty component name, got {_describe(name)}", "name", name
            )
        self.name: str = name
        owner = self._owner()
        self.joints: tuple[str, ...] = _check_joint_names(joints, "joints")
        self.command_interfaces: tuple[str, ...] = _check_interfaces(
            command_interfaces, "command_interfaces", type(self).COMMAND_INTERFACES, owner
        )
        self.state_interfaces: tuple[str, ...] = _check_interfaces(
            state_interfaces, "state_interfaces", type(self).STATE_INTERFACES, owner
        )
        if "position" not in self.state_interfaces:
            raise ConfigurationError(
                f"{owner}: the state interfaces must include 'position', got "
                f"[{', '.join(self.state_interfaces)}]",
                "state_interfaces",
                self.state_interfaces,
            )
        self.params: Mapping[str, Any] = validate_params(
            self.schema(), params, "params", joints=self.joints, owner=owner
        )
        self.safe_action: SafeAction = SafeAction(self.params["safe_action"])
        self._state = LifecycleState.UNCONFIGURED
        self._shape = (len(self.joints),)
        self._velocity_state = "velocity" in self.state_interfaces
        self._acceleration_state = "acceleration" in self.state_interfaces
        self._last_fault: str | None = None
        self._reads = 0
        self._writes = 0
        self._read_errors = 0
        self._write_errors = 0
        self._activations = 0

    @classmethod
    def schema(cls) -> Mapping[str, ParamSpec]:
        """The full parameter schema of the kind: ``COMMON_PARAMS`` then ``PARAMS``."""
        return MappingProxyType({**COMMON_PARAMS, **cls.PARAMS})

    @property
    def state(self) -> LifecycleState:
        """The current lifecycle state."""
        return self._state

    @property
    def last_fault(self) -> str | None:
        """Message of the last error raised by this component, if any."""
        return self._last_fault

    def __repr__(self) -> str:
        return (
            f"<{type(self).__name__} {self.name!r} ({self.kind}) {self._state.value} "
            f"joints=[{', '.join(self.joints)}]>"
        )

    # -- public lifecycle ---------------------------------------------------------------------

    def configure(self) -> None:
        """Open the device and check it (e.g. ping every motor).

        Leaves INACTIVE on success; stays UNCONFIGURED if it fails.

        Raises:
            ControllerStateError: not UNCONFIGURED.
            HardwareError: the device could not be configured.
        """
        self._guard("configure")
        self._call("configure", self._configure)
        self._state = LifecycleState.INACTIVE

    def activate(self, now_ns: int) -> JointCommand:
        """Enable the drives so that writes take effect.

        Args:
            now_ns: the loop's time, integer nanoseconds.

        Returns:
            The command values the hardware holds (for the controller's
            ``set_last_command_interface_value_as_state_on_activation``): an array for each
            configured command interface, ``NaN`` where the hardware holds none; ``None`` for
            interfaces not configured.

        Leaves ACTIVE on success; stays INACTIVE if it fails.

        Raises:
            ControllerStateError: not INACTIVE.
            HardwareError: the drives could not be enabled, or the driver returned arrays of
                the wrong size.
        """
        self._guard("activate")
        held = self._call("activate", self._activate, now_ns)
        try:
            command = self._held_command(held)
        except HardwareError as exc:
            self._last_fault = str(exc)
            try:
                self._deactivate(now_ns, self.safe_action)
            except Exception as rollback:  # noqa: BLE001 - reported as a note
                exc.add_note(f"undoing the activation failed too: {rollback!r}")
            raise
        self._state = LifecycleState.ACTIVE
        self._activations += 1
        return command

    def read(self, now_ns: int) -> JointState:
        """Read the joints' state: one bus transaction.

        Args:
            now_ns: the loop's time, integer nanoseconds.

        Returns:
            The state in this component's joint order, with velocities / accelerations when
            those state interfaces are configured.

        Leaves the state unchanged (INACTIVE or ACTIVE); an error does not change it either:
        the caller decides (typically ``deactivate``).

        Raises:
            ControllerStateError: not INACTIVE or ACTIVE.
            HardwareError: the device did not answer (``CommunicationError``), reported a
                fault (``MotorFault``), or the driver returned arrays of the wrong size.
        """
        state = self._state
        if state is not LifecycleState.ACTIVE and state is not LifecycleState.INACTIVE:
            raise _lifecycle_error(self._owner(), "read", state)
        try:
            result = self._read(now_ns)
        except JtcHwError as exc:
            self._read_errors += 1
            self._last_fault = str(exc)
            raise
        except Exception as exc:
            self._read_errors += 1
            raise self._wrapped("read", exc) from exc
        if (
            result.positions.shape != self._shape
            or (self._velocity_state and (
                result.velocities is None or result.velocities.shape != self._shape))
            or (self._acceleration_state and (
                result.accelerations is None or result.accelerations.shape != self._shape))
        ):
            self._read_errors += 1
            error = HardwareError(
                f"{self._owner()}: read() returned a state that does not match its "
                f"{len(self.joints)} joints and state interfaces "
                f"[{', '.join(self.state_interfaces)}]; this is a driver bug"
            )
            self._last_fault = str(error)
            raise error
        self._reads += 1
        return result

    def write(self, now_ns: int, command: JointCommand) -> None:
        """Write the commands: one bus transaction.

        ``NaN`` entries mean "do not write that joint's interface": the device keeps the
        value it holds.

        Args:
            now_ns: the loop's time, integer nanoseconds.
            command: arrays in this component's joint order, one per configured interface.

        Leaves ACTIVE (an error does not change the state; the caller decides).

        Raises:
            ControllerStateError: not ACTIVE.
            HardwareError: the device did not accept the command.
        """
        state = self._state
        if state is not LifecycleState.ACTIVE:
            raise _lifecycle_error(self._owner(), "write", state)
        try:
            self._write(now_ns, command)
        except JtcHwError as exc:
            self._write_errors += 1
            self._last_fault = str(exc)
            raise
        except Exception as exc:
            self._write_errors += 1
            raise self._wrapped("write", exc) from exc
        self._writes += 1

    def deactivate(self, now_ns: int) -> None:
        """Stop taking commands and perform the ``safe_action`` (hold, or torque off).

        Leaves INACTIVE, even if the safe action fails: no further writes are accepted, and
        the error tells the caller the device may not be in its safe state.

        Raises:
            ControllerStateError: not ACTIVE.
            HardwareError: the safe action could not be performed.
        """
        self._guard("deactivate")
        try:
            self._call("deactivate", self._deactivate, now_ns, self.safe_action)
        finally:
            self._state = LifecycleState.INACTIVE

    def recover(self) -> None:
        """Clear the device's latched faults: reboot a faulted servo, reset a drive's fault.

        The daemon calls it on a client's explicit re-arm request, after ``configure`` and
        before ``activate`` (which seeds the command from the measured position, so re-arming
        never jumps). Devices that latch nothing do nothing.

        Leaves INACTIVE (also when it fails: the caller keeps the controller stopped).

        Raises:
            ControllerStateError: not INACTIVE.
            HardwareError: the fault could not be cleared (the message names the motor and
                what to check).
        """
        self._guard("recover")
        self._call("recover", self._recover)
        self._last_fault = None

    def cleanup(self) -> None:
        """Release the device (close the port / bus).

        Leaves UNCONFIGURED, even if releasing fails.

        Raises:
            ControllerStateError: not INACTIVE.
            HardwareError: releasing failed.
        """
        self._guard("cleanup")
        try:
            self._call("cleanup", self._cleanup)
        finally:
            self._state = LifecycleState.UNCONFIGURED

    def shutdown(self, now_ns: int) -> None:
        """Whatever the state, deactivate and clean up as needed; final.

        Leaves FINALIZED (every later call except ``shutdown`` and ``status`` raises). Calling
        it again does nothing.

        Raises:
            HardwareError: deactivating or cleaning up failed (both are attempted; the first
                error is raised, the other attached as a note).
        """
        errors: list[HardwareError] = []
        if self._state is LifecycleState.ACTIVE:
            try:
                self.deactivate(now_ns)
            except HardwareError as exc:
                errors.append(exc)
        if self._state is LifecycleState.INACTIVE:
            try:
                self.cleanup()
            except HardwareError as exc:
                errors.append(exc)
        self._state = LifecycleState.FINALIZED
        _raise_first(errors)

    def status(self) -> dict[str, Any]:
        """A JSON-able summary for clients and logs.

        Returns:
            ``name``, ``kind``, ``state``, ``joints``, ``command_interfaces``,
            ``state_interfaces``, ``safe_action``, ``last_fault`` (message or ``None``),
            ``counters`` (reads, writes, read_errors, write_errors, activations) and
            ``details`` (whatever the driver reports, see ``_details``).
        """
        return {
            "name": self.name,
            "kind": self.kind,
            "state": self._state.value,
            "joints": list(self.joints),
            "command_interfaces": list(self.command_interfaces),
            "state_interfaces": list(self.state_interfaces),
            "safe_action": self.safe_action.value,
            "last_fault": self._last_fault,
            "counters": {
                "reads": self._reads,
                "writes": self._writes,
                "read_errors": self._read_errors,
                "write_errors": self._write_errors,
                "activations": self._activations,
            },
            "details": dict(self._details()),
        }

    def nan_command(self) -> JointCommand:
        """A command holding ``NaN`` for every configured interface (``None`` for the others)."""
        n = len(self.joints)
        fields = [
            np.full(n, np.nan) if iface in self.command_interfaces else None
            for iface in COMMAND_INTERFACE_TYPES
        ]
        return JointCommand(*fields)

    # -- primitives ---------------------------------------------------------------------------

    def _configure(self) -> None:  # noqa: B027 - optional primitive, no-op by default
        """Open and check the device. Default: nothing to do."""

    def _activate(self, now_ns: int) -> JointCommand:
        """Enable the drives; return the held command values. Default: ``nan_command()``."""
        return self.nan_command()

    @abstractmethod
    def _read(self, now_ns: int) -> JointState:
        """Return the state of ``self.joints`` (one bus transaction)."""

    @abstractmethod
    def _write(self, now_ns: int, command: JointCommand) -> None:
        """Write the non-NaN entries of ``command`` (one bus transaction)."""

    def _deactivate(self, now_ns: int, action: SafeAction) -> None:  # noqa: B027
        """Perform ``action`` (hold the position, or torque off). Default: nothing to do."""

    def _recover(self) -> None:  # noqa: B027 - optional primitive, no-op by default
        """Clear latched device faults (reboot, fault reset). Default: nothing to do."""

    def _cleanup(self) -> None:  # noqa: B027 - optional primitive, no-op by default
        """Release the device. Default: nothing to do."""

    def _details(self) -> Mapping[str, Any]:
        """Driver-specific JSON-able status entries (bus statistics, temperatures, ...)."""
        return {}

    # -- helpers ------------------------------------------------------------------------------

    def _owner(self) -> str:
        return f"{self.kind} hardware {self.name!r}"

    def _guard(self, method: str) -> None:
        if self._state not in _ALLOWED[method]:
            raise _lifecycle_error(self._owner(), method, self._state)

    def _wrapped(self, method: str, exc: BaseException) -> HardwareError:
        error = HardwareError(f"{self._owner()}: {method} failed: {type(exc).__name__}: {exc}")
        self._last_fault = str(error)
        return error

    def _call(self, method: str, function: Callable[..., Any], *args: Any) -> Any:
        try:
            return function(*args)
        except JtcHwError as exc:
            self._last_fault = str(exc)
            raise
        except Exception as exc:
            raise self._wrapped(method, exc) from exc

    def _held_command(self, held: Any) -> JointCommand:
        if not isinstance(held, JointCommand):
            raise HardwareError(
                f"{self._owner()}: activate() must return a JointCommand, got "
                f"{type(held).__name__}; this is a driver bug"
            )
        fields: list[F64 | None] = []
        for iface, values in zip(
            COMMAND_INTERFACE_TYPES,
            (held.positions, held.velocities, held.accelerations, held.effort),
            strict=True,
        ):
            if iface not in self.command_interfaces:
                fields.append(None)
            elif values is None:
                fields.append(np.full(self._shape, np.nan))
            elif values.shape != self._shape:
                raise HardwareError(
                    f"{self._owner()}: activate() returned {values.size} {iface} values for "
                    f"{len(self.joints)} joints; this is a driver bug"
                )
            else:
                fields.append(values)
        return JointCommand(*fields)


def _raise_first(errors: Sequence[BaseException]) -> None:
    """Raise the first error, the others attached as notes."""
    if not errors:
        return
    first = errors[0]
    for other in errors[1:]:
        first.add_note(f"also: {type(other).__name__}: {other}")
    raise first


# --------------------------------------------------------------------------------------------
# Several components forming the controller's joints
# --------------------------------------------------------------------------------------------

_RANK: Final = {_U: 0, _I: 1, _A: 2}


def _take(values: F64 | None, index: NDArray[np.intp]) -> F64 | None:
    return None if values is None else values[index]


class HardwareSet:
    """Components whose joints together are the controller's joints.

    Reads and writes fan out to each component once, mapping between the controller's joint
    order and each component's with index arrays computed here. Lifecycle methods fan out in
    component order; a failed ``configure``/``activate`` rolls back the components already
    transitioned (in reverse order), so the set is never half configured or half active.

    Args:
        components: the components (unique names, same command and state interfaces).
        joints: the controller's joints, in its order.

    Raises:
        ConfigurationError: no component, duplicate component names, components with
            different interfaces, a controller joint provided by no component or by two, or a
            component joint the controller does not have.
    """

    def __init__(self, components: Sequence[HardwareInterface], joints: Sequence[str]) -> None:
        self._components = tuple(components)
        self.joints: tuple[str, ...] = tuple(joints)
        if not self._components:
            raise ConfigurationError("a hardware set needs at least one component", "hardware")
        self._by_name: dict[str, HardwareInterface] = {}
        for comp in self._components:
            if comp.name in self._by_name:
                raise ConfigurationError(
                    f"two components are named {comp.name!r}; names must be unique",
                    "hardware",
                    comp.name,
                )
            self._by_name[comp.name] = comp
        first = self._components[0]
        self.command_interfaces: tuple[str, ...] = first.command_interfaces
        self.state_interfaces: tuple[str, ...] = first.state_interfaces
        for comp in self._components[1:]:
            if set(comp.command_interfaces) != set(first.command_interfaces) or set(
                comp.state_interfaces
            ) != set(first.state_interfaces):
                raise ConfigurationError(
                    f"component {comp.name!r} has interfaces command "
                    f"[{', '.join(comp.command_interfaces)}] / state "
                    f"[{', '.join(comp.state_interfaces)}] but {first.name!r} has command "
                    f"[{', '.join(first.command_interfaces)}] / state "
                    f"[{', '.join(first.state_interfaces)}]; all take the controller's",
                    "hardware",
                    comp.name,
                )
        position = {joint: i for i, joint in enumerate(self.joints)}
        owner: dict[str, str] = {}
        indices: list[NDArray[np.intp]] = []
        for comp in self._components:
            for joint in comp.joints:
                if joint not in position:
                    raise ConfigurationError(
                        f"component {comp.name!r} provides {joint!r}, which is not a controller "
                        f"joint (joints: {', '.join(self.joints)})"
                        f"{_did_you_mean(joint, self.joints)}",
                        "hardware",
                        joint,
                    )
                if joint in owner:
                    raise ConfigurationError(
                        f"joint {joint!r} is provided by both {owner[joint]!r} and "
                        f"{comp.name!r}; each joint belongs to exactly one component",
                        "hardware",
                        joint,
                    )
                owner[joint] = comp.name
            indices.append(np.array([position[j] for j in comp.joints], dtype=np.intp))
        missing = [j for j in self.joints if j not in owner]
        if missing:
            listing = "; ".join(f"{c.name}: [{', '.join(c.joints)}]" for c in self._components)
            raise ConfigurationError(
                f"controller joint{'s' if len(missing) > 1 else ''} "
                f"{', '.join(repr(j) for j in missing)} not provided by any component "
                f"({listing})",
                "hardware",
                missing[0],
            )
        self._pairs = tuple(zip(self._components, indices, strict=True))
        self._n = len(self.joints)
        self._identity = len(self._components) == 1 and first.joints == self.joints
        self._velocity_state = "velocity" in self.state_interfaces
        self._acceleration_state = "acceleration" in self.state_interfaces
        self._command_fields = tuple(i in self.command_interfaces for i in COMMAND_INTERFACE_TYPES)

    @property
    def components(self) -> tuple[HardwareInterface, ...]:
        """The components, in the order given."""
        return self._components

    def component(self, name: str) -> HardwareInterface:
        """The component called ``name``.

        Raises:
            ConfigurationError: no component has that name (the message lists them).
        """
        found = self._by_name.get(name)
        if found is None:
            raise ConfigurationError(
                f"no hardware component named {name!r}; components: "
                f"{', '.join(self._by_name)}{_did_you_mean(str(name), self._by_name)}",
                "hardware",
                name,
            )
        return found

    @property
    def state(self) -> LifecycleState:
        """The components' common state (FINALIZED if any is; else the least advanced)."""
        states = [c.state for c in self._components]
        if _F in states:
            return _F
        return min(states, key=_RANK.__getitem__)

    def __repr__(self) -> str:
        return f"<HardwareSet {self.state.value} [{', '.join(c.name for c in self._components)}]>"

    def configure(self) -> None:
        """Configure every component; if one fails, clean up those already configured.

        Leaves INACTIVE on success; UNCONFIGURED if it fails.

        Raises:
            ControllerStateError: a component is not UNCONFIGURED (nothing was done).
            HardwareError: a component failed to configure (rollback errors attached as notes).
        """
        self._guard("configure")
        done: list[HardwareInterface] = []
        for comp in self._components:
            try:
                comp.configure()
            except BaseException as exc:
                for other in reversed(done):
                    try:
                        other.cleanup()
                    except Exception as rollback:  # noqa: BLE001 - reported as a note
                        exc.add_note(f"rolling back {other.name!r} failed: {rollback}")
                raise
            done.append(comp)

    def activate(self, now_ns: int) -> JointCommand:
        """Activate every component; if one fails, deactivate those already active.

        Returns:
            The merged held commands in the controller's joint order (``NaN`` where none).

        Leaves ACTIVE on success; INACTIVE if it fails.

        Raises:
            ControllerStateError: a component is not INACTIVE (nothing was done).
            HardwareError: a component failed to activate (rollback errors attached as notes).
        """
        self._guard("activate")
        held = [np.full(self._n, np.nan) if on else None for on in self._command_fields]
        done: list[HardwareInterface] = []
        for comp, index in self._pairs:
            try:
                command = comp.activate(now_ns)
            except BaseException as exc:
                for other in reversed(done):
                    try:
                        other.deactivate(now_ns)
                    except Exception as rollback:  # noqa: BLE001 - reported as a note
                        exc.add_note(f"rolling back {other.name!r} failed: {rollback}")
                raise
            done.append(comp)
            values = (command.positions, command.velocities, command.accelerations, command.effort)
            for merged, part in zip(held, values, strict=True):
                if merged is not None and part is not None:
                    merged[index] = part
        return JointCommand(*held)

    def read(self, now_ns: int) -> JointState:
        """Read every component once; return the state in the controller's joint order.

        Raises:
            ControllerStateError: a component is not INACTIVE or ACTIVE.
            HardwareError: a component's read failed (the others after it are not read).
        """
        if self._identity:
            return self._components[0].read(now_ns)
        n = self._n
        positions = np.full(n, np.nan)
        velocities = np.full(n, np.nan) if self._velocity_state else None
        accelerations = np.full(n, np.nan) if self._acceleration_state else None
        for comp, index in self._pairs:
            part = comp.read(now_ns)
            positions[index] = part.positions
            if velocities is not None and part.velocities is not None:
                velocities[index] = part.velocities
            if accelerations is not None and part.accelerations is not None:
                accelerations[index] = part.accelerations
        return JointState(positions, velocities, accelerations)

    def write(self, now_ns: int, command: JointCommand) -> None:
        """Split the command by component and write each once.

        Raises:
            ControllerStateError: a component is not ACTIVE.
            HardwareError: a component's write failed (the others after it are not written).
        """
        if self._identity:
            self._components[0].write(now_ns, command)
            return
        for comp, index in self._pairs:
            comp.write(
                now_ns,
                JointCommand(
                    _take(command.positions, index),
                    _take(command.velocities, index),
                    _take(command.accelerations, index),
                    _take(command.effort, index),
                ),
            )

    def deactivate(self, now_ns: int) -> None:
        """Deactivate every component (each performs its safe action), even if one fails.

        Leaves INACTIVE.

        Raises:
            ControllerStateError: a component is not ACTIVE (nothing was done).
            HardwareError: a component's safe action failed (first error raised, others
                attached as notes).
        """
        self._guard("deactivate")
        self._fan_out(lambda comp: comp.deactivate(now_ns))

    def recover(self) -> None:
        """Clear every component's latched faults (see :meth:`HardwareInterface.recover`).

        Leaves INACTIVE.

        Raises:
            ControllerStateError: a component is not INACTIVE (nothing was done).
            HardwareError: a component could not clear its fault (every one is attempted).
        """
        self._guard("recover")
        self._fan_out(lambda comp: comp.recover())

    def cleanup(self) -> None:
        """Clean up every component, even if one fails.

        Leaves UNCONFIGURED.

        Raises:
            ControllerStateError: a component is not INACTIVE (nothing was done).
            HardwareError: a component failed to release its device.
        """
        self._guard("cleanup")
        self._fan_out(lambda comp: comp.cleanup())

    def shutdown(self, now_ns: int) -> None:
        """Shut every component down, whatever its state. Leaves FINALIZED.

        Raises:
            HardwareError: a component failed to deactivate or clean up.
        """
        self._fan_out(lambda comp: comp.shutdown(now_ns))

    def status(self) -> dict[str, Any]:
        """A JSON-able summary: ``state``, ``joints`` and each component's ``status()``."""
        return {
            "state": self.state.value,
            "joints": list(self.joints),
            "components": [c.status() for c in self._components],
        }

    def _guard(self, method: str) -> None:
        for comp in self._components:
            if comp.state not in _ALLOWED[method]:
                raise _lifecycle_error(f"hardware set (component {comp.name!r})", method,
                                       comp.state)

    def _fan_out(self, action: Callable[[HardwareInterface], None]) -> None:
        errors: list[BaseException] = []
        for comp in self._components:
            try:
                action(comp)
            except JtcHwError as exc:
                errors.append(exc)
        _raise_first(errors)


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------

ENTRY_POINT_GROUP: Final = "jtc_hw.hardware"
"""Entry-point group through which third-party packages add hardware kinds."""

BUILTIN_HARDWARE: Final[Mapping[str, str]] = MappingProxyType({
    "mirror": "jtc_hw.mirror:MirrorHardware",
    "dynamixel": "jtc_hw.drivers.dynamixel.hardware:DynamixelHardware",
    "can-mit": "jtc_hw.drivers.can.mit:MitHardware",
    "can-cia402": "jtc_hw.drivers.can.cia402:Cia402Hardware",
})
"""Built-in kinds, as lazy ``"module:Class"`` strings."""

_BUILTIN_EXTRAS: Final[Mapping[str, str]] = MappingProxyType({
    "dynamixel": "dynamixel",
    "can-mit": "can",
    "can-cia402": "can",
})
"""The ``pip install 'jtc_hw[<extra>]'`` extra holding each built-in kind's dependencies."""


@dataclass(frozen=True)
class _Entry:
    factory: str | type[HardwareInterface]
    extra: str | None
    origin: str


_registered: dict[str, _Entry] = {}


def _check_factory_string(factory: str) -> tuple[str, str]:
    module, sep, attr = factory.partition(":")
    if not sep or not module.strip() or not attr.strip():
        raise ConfigurationError(
            f"expected 'module:Class', got {factory!r}", "factory", factory
        )
    return module.strip(), attr.strip()


def register_hardware(kind: str, factory: str | type, *, extra: str | None = None) -> None:
    """Add (or replace) a hardware kind.

    Registered kinds take precedence over built-in kinds and entry points.

    Args:
        kind: the name used in the ``hardware[].kind`` configuration key.
        factory: a :class:`HardwareInterface` subclass, or a lazy ``"module:Class"`` string
            imported when the kind is first created.
        extra: the ``jtc_hw`` extra holding the kind's optional dependencies, named in the
            error when one is missing (``pip install 'jtc_hw[<extra>]'``).

    Raises:
        ConfigurationError: ``kind`` is empty or ``factory`` is a string not of the form
            ``module:Class``.
        TypeError: ``factory`` is neither a string nor a HardwareInterface subclass.
    """
    if not isinstance(kind, str) or not kind.strip():
        raise ConfigurationError(f"expected a non-empty kind, got {_describe(kind)}", "kind", kind)
    if isinstance(factory, str):
        _check_factory_string(factory)
    elif not (isinstance(factory, type) and issubclass(factory, HardwareInterface)):
        raise TypeError(
            f"factory must be a HardwareInterface subclass or a 'module:Class' string, "
            f"got {factory!r}"
        )
    _registered[kind] = _Entry(factory, extra, "registered")


def unregister_hardware(kind: str) -> None:
    """Remove a kind added with :func:`register_hardware` (built-ins come back if shadowed).

    Raises:
        KeyError: ``kind`` was not registered with :func:`register_hardware`.
    """
    del _registered[kind]


def _entries() -> dict[str, _Entry]:
    entries = {
        kind: _Entry(target, _BUILTIN_EXTRAS.get(kind), "built in")
        for kind, target in BUILTIN_HARDWARE.items()
    }
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in BUILTIN_HARDWARE:
            _log.warning(
                "entry point %r (%s) is ignored: %r is a built-in hardware kind",
                ep.name, ep.value, ep.name,
            )
            continue
        entries[ep.name] = _Entry(
            f"{ep.module}:{ep.attr}", None, f"entry point {ep.name!r} in group {ENTRY_POINT_GROUP}"
        )
    entries.update(_registered)
    return entries


def available_hardware() -> tuple[str, ...]:
    """The names of every known hardware kind, sorted (nothing is imported)."""
    return tuple(sorted(_entries()))


def _unknown_kind(kind: Any, path: str, kinds: Iterable[str]) -> ConfigurationError:
    kinds = sorted(kinds)
    return ConfigurationError(
        f"unknown hardware kind {kind!r}; available kinds: {', '.join(kinds)}"
        f"{_did_you_mean(str(kind), kinds)}",
        path,
        kind,
    )


def check_hardware_kind(kind: Any, path: str = "kind") -> None:
    """Check that ``kind`` names a known hardware kind, without importing it.

    Raises:
        ConfigurationError: unknown kind; the message lists the available kinds.
    """
    entries = _entries()
    if not isinstance(kind, str) or kind not in entries:
        raise _unknown_kind(kind, path, entries)


def _import_factory(kind: str, entry: _Entry, path: str) -> type[HardwareInterface]:
    if not isinstance(entry.factory, str):
        return entry.factory
    module_name, attr = _check_factory_string(entry.factory)
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = exc.name or "?"
        if missing.split(".")[0] == module_name.split(".")[0]:
            raise ConfigurationError(
                f"hardware kind {kind!r} ({entry.origin}) points at {entry.factory!r}, but "
                f"module {missing!r} does not exist; this installation does not provide it",
                path,
                kind,
            ) from exc
        if entry.extra is not None:
            how = f"pip install 'jtc_hw[{entry.extra}]'"
        else:
            how = f"install the distribution that provides the module {missing!r}"
        raise ConfigurationError(
            f"hardware kind {kind!r} needs the package {missing!r}, which is not installed: "
            f"{how}",
            path,
            kind,
        ) from exc
    except Exception as exc:
        raise ConfigurationError(
            f"hardware kind {kind!r}: importing {module_name!r} failed: "
            f"{type(exc).__name__}: {exc}",
            path,
            kind,
        ) from exc
    factory = getattr(module, attr, None)
    if factory is None:
        raise ConfigurationError(
            f"hardware kind {kind!r} ({entry.origin}): module {module_name!r} has no "
            f"attribute {attr!r}",
            path,
            kind,
        )
    if not (isinstance(factory, type) and issubclass(factory, HardwareInterface)):
        raise ConfigurationError(
            f"hardware kind {kind!r} ({entry.origin}): {entry.factory!r} is not a "
            "HardwareInterface subclass",
            path,
            kind,
        )
    return factory


def hardware_class(kind: str, path: str = "kind") -> type[HardwareInterface]:
    """Return the class of a hardware kind, importing its module if needed.

    Args:
        kind: the kind's name.
        path: configuration path used in errors.

    Raises:
        ConfigurationError: unknown kind (the message lists the available ones), a missing
            optional dependency (the message names the ``pip install`` to run), or a
            registration that does not lead to a HardwareInterface subclass.
    """
    entries = _entries()
    if not isinstance(kind, str) or kind not in entries:
        raise _unknown_kind(kind, path, entries)
    return _import_factory(kind, entries[kind], path)


@dataclass(frozen=True)
class HardwareSpec:
    """What is needed to create one hardware component (one ``hardware[]`` entry).

    Attributes:
        name: component name.
        kind: registry kind.
        joints: the component's joints.
        command_interfaces: the controller's command interfaces.
        state_interfaces: the controller's state interfaces.
        params: kind-specific parameters (validated when the component is created).
        path: where it was configured (e.g. ``hardware[1]``), prefixed to error paths.
    """

    name: str
    kind: str
    joints: tuple[str, ...]
    command_interfaces: tuple[str, ...]
    state_interfaces: tuple[str, ...]
    params: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    path: str = ""

    def __post_init__(self) -> None:
        for name in ("joints", "command_interfaces", "state_interfaces"):
            value = getattr(self, name)
            if isinstance(value, list):
                object.__setattr__(self, name, tuple(value))
        if isinstance(self.params, Mapping):
            object.__setattr__(self, "params", _freeze(self.params))


def _prefixed(exc: ConfigurationError, prefix: str) -> ConfigurationError:
    """The same error with ``prefix`` put in front of its path."""
    message = str(exc)
    if exc.path and message.startswith(f"{exc.path}: "):
        message = message[len(exc.path) + 2:]
    return ConfigurationError(message, _join(prefix, exc.path), exc.value)


def create_hardware(spec: HardwareSpec) -> HardwareInterface:
    """Create one component from its spec (UNCONFIGURED).

    Raises:
        ConfigurationError: unknown kind, missing optional dependency, or invalid joints,
            interfaces or parameters; the path starts with ``spec.path``.
        HardwareError: the driver's constructor failed otherwise.
    """
    cls = hardware_class(spec.kind, _join(spec.path, "kind"))
    try:
        return cls(
            spec.name, spec.joints, spec.command_interfaces, spec.state_interfaces, spec.params
        )
    except ConfigurationError as exc:
        if not spec.path:
            raise
        raise _prefixed(exc, spec.path) from exc
    except JtcHwError:
        raise
    except Exception as exc:
        raise HardwareError(
            f"{spec.kind} hardware {spec.name!r}: creating it failed: {type(exc).__name__}: {exc}"
        ) from exc
