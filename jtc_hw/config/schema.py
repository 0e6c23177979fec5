"""The one schema engine: declare a parameter once, get it checked, defaulted and frozen.

Every parameter of the project is a row of a schema table: the controller's upstream parameters
(:mod:`jtc_hw.config.controller`), each hardware kind's ``params`` (a driver's ``PARAMS``), the
robot file's ``hardware:`` and ``daemon:`` sections. A table is a :func:`param_table` of
:class:`ParamSpec` rows (name, kind, default, description, bounds, choices, per joint, and for a
runtime parameter whether it is read-only and when a change takes effect).
:func:`validate_params` checks a mapping against a table and returns an immutable mapping with
the defaults filled in; :func:`check_value` checks one value against one row. Every error is a
:class:`~jtc_hw.errors.ConfigurationError` that names the dotted key path and says what was
expected, with a "did you mean" where a name is close to a known one. No I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from types import MappingProxyType
from typing import Any, Final

from ..errors import ConfigurationError
from .values import coerce_bool, coerce_string_array, describe, did_you_mean, fmt_list

__all__ = [
    "Effect",
    "ParamKind",
    "ParamSpec",
    "check_fields",
    "check_key",
    "check_keys",
    "check_value",
    "expect_mapping",
    "freeze",
    "join",
    "param_table",
    "unknown_parameter",
    "validate_params",
]


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


class Effect(Enum):
    """When a parameter changed at runtime (``set_parameters``) takes effect: upstream's timing.

    Upstream re-reads its parameters at the start of the next ``update``: gains apply from that
    cycle, the default tolerances and the goal checks from the next command, and what it reads
    only in ``on_activate`` (``cmd_timeout``, the activation seeding) from the next activation.
    """

    NEXT_CYCLE = "next cycle"
    NEXT_COMMAND = "next goal or trajectory"
    NEXT_ACTIVATION = "next activation"


_PER_JOINT_KINDS: Final = frozenset(
    {ParamKind.FLOAT, ParamKind.INT, ParamKind.BOOL, ParamKind.STRING, ParamKind.RANGE}
)


@dataclass(frozen=True)
class ParamSpec:
    """One row of a schema table.

    Attributes:
        name: parameter name (last component of its dotted path).
        kind: value type.
        default: value used when the parameter is not given (for ``per_joint``: the value of
            each joint not given; for ``STRINGS``: a tuple).
        description: one-line description.
        minimum: inclusive lower bound for numbers (each element for lists and ranges).
        maximum: inclusive upper bound for numbers.
        choices: allowed values for strings and integers; for ``STRINGS``, the allowed
            elements (only the controller's interface lists restrict theirs, and the message
            calls them interface types).
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
        read_only: a runtime parameter fixed once the controller is configured (upstream's
            ``read_only``, or read only at configuration there); ``set_parameters`` refuses it.
        effect: when a change at runtime takes effect (ignored when ``read_only``).
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
    read_only: bool = False
    effect: Effect = Effect.NEXT_COMMAND


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


def join(prefix: str, key: str) -> str:
    """The dotted path of ``key`` inside ``prefix`` (``prefix`` empty: ``key``)."""
    return f"{prefix}.{key}" if prefix else key


def check_key(key: Any, path: str) -> str:
    """``key`` if it is a string (YAML reads ``1:`` or ``yes:`` as other types).

    Raises:
        ConfigurationError: not a string; the hint says to quote it.
    """
    if not isinstance(key, str):
        raise ConfigurationError(f"keys must be strings, got {describe(key)}; quote it", path, key)
    return key


def unknown_parameter(
    key: str, known: Iterable[str], prefix: str = "", of: str = ""
) -> ConfigurationError:
    """The error for a key no row of the table names: a close name, the dotted form's
    nesting, or the known names (``of``: whose parameters, e.g. `` of component 0``)."""
    known = list(known)
    head = key.split(".", 1)[0]
    if "." in key and head in known:
        hint = f"; dotted names are not expanded: nest it under '{head}'"
    else:
        hint = did_you_mean(key, known) or (
            f"; known parameters: {', '.join(known)}" if known else "; it takes none"
        )
    return ConfigurationError(f"unknown parameter {key!r}{of}{hint}", join(prefix, key), key)


def expect_mapping(value: Any, path: str, of: str = "") -> Mapping[Any, Any]:
    """``value`` if it is a mapping.

    Raises:
        ConfigurationError: it is not (``of``: whose, e.g. `` of component 0``).
    """
    if not isinstance(value, Mapping):
        raise ConfigurationError(f"expected a mapping{of}, got {describe(value)}", path, value)
    return value


def check_keys(
    mapping: Mapping[Any, Any], schema: Collection[str], path: str, of: str = ""
) -> None:
    """Every key of ``mapping`` is a string that ``schema`` names (a table, or the names).

    Raises:
        ConfigurationError: a key that is not a string, or unknown (see
            :func:`unknown_parameter`).
    """
    for key in mapping:
        if check_key(key, path) not in schema:
            raise unknown_parameter(key, schema, path, of)


def freeze(value: Any) -> Any:
    """Deep read-only copy: mappings become MappingProxyType, lists become tuples."""
    if isinstance(value, Mapping):
        return MappingProxyType({k: freeze(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)):
        return tuple(freeze(v) for v in value)
    return value


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


def _is_pair(value: Any) -> bool:
    return isinstance(value, (list, tuple)) and len(value) == 2 and all(map(_is_number, value))


def _range(spec: ParamSpec, value: Any, path: str, what: str = "") -> tuple[float, float]:
    if not _is_pair(value):
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
        return _is_pair(value)
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


def _list_checks(spec: ParamSpec, items: tuple[Any, ...], path: str, value: Any) -> None:
    if spec.non_empty and not items:
        required = "required: " if spec.required else ""
        raise ConfigurationError(
            f"must not be empty ({required}{spec.description})", path, value
        )
    if spec.unique:
        seen: set[Any] = set()
        for item in items:
            if item in seen:
                raise ConfigurationError(
                    f"contains {item!r} more than once (duplicates are not allowed)", path, item
                )
            seen.add(item)


def _strings(spec: ParamSpec, value: Any, path: str) -> tuple[str, ...]:
    items = coerce_string_array(value, path)
    _list_checks(spec, items, path, value)
    if spec.choices:
        allowed = [str(c) for c in spec.choices]
        for item in items:
            if item not in allowed:
                raise ConfigurationError(
                    f"{item!r} is not an allowed interface type; allowed: "
                    f"{fmt_list(allowed)}{did_you_mean(item, allowed)}",
                    path,
                    item,
                )
    return items


def check_value(spec: ParamSpec, value: Any, path: str, joints: Sequence[str] = ()) -> Any:
    """``value`` checked against the row ``spec`` and normalised (numbers as float or int,
    lists as tuples, per-joint values as tuples in the order of ``joints``, sections as
    read-only mappings).

    Raises:
        ConfigurationError: wrong type, out of range, not an allowed choice, duplicate or
            empty where not allowed; the error's path is ``path`` (or below it).
    """
    if spec.coerce is not None:
        return spec.coerce(value, path)
    kind = spec.kind
    if spec.per_joint:
        return _per_joint(spec, value, path, joints)
    if kind is ParamKind.STRINGS:
        return _strings(spec, value, path)
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
            for key in expect_mapping(value, path):
                check_key(key, path)
            return freeze(value)
        return validate_params(spec.fields, value, path, joints=joints)
    return _scalar(spec, value, path)


def check_fields(obj: Any, schema: Mapping[str, ParamSpec], path: str) -> None:
    """Check and normalise, in place, the fields of a frozen dataclass its table declares.

    A settings dataclass calls it from ``__post_init__``, so that an instance built directly is
    checked by the same rows, with the same messages, as one read from a file. A ``None`` of a
    ``nullable`` row stays ``None``; a ``SECTION`` row holds a dataclass that checked itself.

    Raises:
        ConfigurationError: as :func:`check_value`; the path is ``path.<field>``.
    """
    for name, spec in schema.items():
        value = getattr(obj, name)
        if spec.kind is ParamKind.SECTION or (value is None and spec.nullable):
            continue
        object.__setattr__(obj, name, check_value(spec, value, join(path, name)))


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
    of = f" of {owner}" if owner else ""
    raw = expect_mapping({} if raw is None else raw, path, of)
    check_keys(raw, schema, path, of)
    result: dict[str, Any] = {}
    for name, spec in schema.items():
        key_path = join(path, name)
        value = raw.get(name)
        if name not in raw or (value is None and spec.nullable):
            if spec.required:
                raise ConfigurationError(
                    f"missing required parameter {name!r}{of} ({spec.description})", key_path
                )
            result[name] = _default(spec, key_path, joints)
        else:
            result[name] = check_value(spec, value, key_path, joints)
    return MappingProxyType(result)
