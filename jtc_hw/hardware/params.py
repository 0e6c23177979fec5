"""The parameter schema of hardware kinds: declare a table once, get checked, frozen values.

A kind declares its parameters as a :func:`param_table` of :class:`ParamSpec` rows (name, kind,
default, help, bounds, choices, per-joint); :func:`validate_params` checks a YAML mapping against
it and returns an immutable mapping with defaults filled in. Every error names the key path and
says what was expected. The robot file's ``hardware:`` and ``daemon:`` sections use the same
engine (:mod:`jtc_hw.daemon.robot`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from types import MappingProxyType
from typing import Any, Final

from ..controller.parsing import coerce_bool, coerce_string_array, describe, did_you_mean
from ..errors import ConfigurationError

__all__ = [
    "ParamKind",
    "ParamSpec",
    "param_table",
    "validate_params",
]

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
        raise ConfigurationError(f"{what}expected a number, got {describe(value)}", path, value)
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
            f"{what}expected an integer, got {describe(value)}", path, value
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
            f"{what}expected a [min, max] pair of numbers, got {describe(value)}", path, value
        )
    low = _number(spec, value[0], path, what, finite=False)
    high = _number(spec, value[1], path, what, finite=False)
    if low > high:
        raise ConfigurationError(f"{what}min {low:g} is greater than max {high:g}", path, value)
    return (low, high)


def _string(spec: ParamSpec, value: Any, path: str, what: str = "") -> str:
    if not isinstance(value, str):
        raise ConfigurationError(f"{what}expected a string, got {describe(value)}", path, value)
    if spec.choices and value not in spec.choices:
        names = [str(c) for c in spec.choices]
        raise ConfigurationError(
            f"{what}{value!r} is not allowed; allowed values: "
            f"{', '.join(repr(c) for c in spec.choices)}{did_you_mean(value, names)}",
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
    return coerce_bool(value, path, what)


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
                    f"{did_you_mean(str(joint), joints)}",
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
    return coerce_string_array(value, path)


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
                f"expected a list of integers, got {describe(value)}", path, value
            )
        items = tuple(
            _integer(spec, item, path, f"element {i}: ") for i, item in enumerate(value)
        )
        _list_checks(spec, items, path, value)
        return items
    if kind is ParamKind.SECTION:
        if spec.fields is None:
            if not isinstance(value, Mapping):
                raise ConfigurationError(f"expected a mapping, got {describe(value)}", path, value)
            for key in value:
                _check_key(key, path)
            return _freeze(value)
        return validate_params(spec.fields, value, path, joints=joints)
    return _scalar(spec, value, path)


def _check_key(key: Any, path: str) -> str:
    if not isinstance(key, str):
        raise ConfigurationError(f"keys must be strings, got {describe(key)}; quote it", path, key)
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
        raise ConfigurationError(f"expected a mapping{of}, got {describe(raw)}", path, raw)
    for key in raw:
        if _check_key(key, path) not in schema:
            known = list(schema)
            hint = did_you_mean(key, known) or (
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

