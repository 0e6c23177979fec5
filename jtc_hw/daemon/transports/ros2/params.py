"""The controller node's parameter services: rcl_interfaces' values and rclcpp's listing (pure).

Theory of operation
-------------------
``ros2 param get|set|list /<c> ...`` call the node's ``get_parameters``, ``set_parameters`` and
``list_parameters`` services (``rcl_interfaces/srv/...``). The transport answers them through
the request layer's ``get_parameters`` / ``set_parameters`` (upstream's dotted names:
``gains.<joint>.p``, ``constraints.goal_time``, ...); this module converts between our values and
``rcl_interfaces/msg/ParameterValue`` and lists names as rclcpp's ``list_parameters`` does:

- a value's ``type`` is ``ParameterType``'s: a bool is BOOL, an int INTEGER, a float DOUBLE, a
  string STRING, a list of one of those the matching array (a list of numbers with a float in
  it DOUBLE_ARRAY), ``None`` NOT_SET (a name we do not have reads NOT_SET, as rclcpp answers
  for an undeclared parameter);
- ``set_parameters`` sets each parameter on its own (rclcpp's service is not atomic), each with
  a ``SetParametersResult`` (``successful``, ``reason``: our refusal's message);
- ``list_parameters``: with no prefix every name, else the names equal to a prefix or under it
  (``prefix.``); ``depth`` (0: any) bounds the dots below the prefix; ``prefixes`` of the
  result are the listed names' parents.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any, Final

import numpy as np

__all__ = ["NOT_SET", "from_parameter_value", "list_names", "to_parameter_value"]

# rcl_interfaces/msg/ParameterType
NOT_SET: Final = 0
BOOL, INTEGER, DOUBLE, STRING, BYTE_ARRAY = 1, 2, 3, 4, 5
BOOL_ARRAY, INTEGER_ARRAY, DOUBLE_ARRAY, STRING_ARRAY = 6, 7, 8, 9


def to_parameter_value(value: Any) -> dict[str, Any]:
    """The fields of a ``ParameterValue`` holding ``value`` (module docstring)."""
    if value is None:
        return {"type": NOT_SET}
    if isinstance(value, bool):
        return {"type": BOOL, "bool_value": value}
    if isinstance(value, int):
        return {"type": INTEGER, "integer_value": value}
    if isinstance(value, float):
        return {"type": DOUBLE, "double_value": value}
    if isinstance(value, str):
        return {"type": STRING, "string_value": value}
    if isinstance(value, (list, tuple)):
        items = list(value)
        if all(isinstance(v, bool) for v in items) and items:
            return {"type": BOOL_ARRAY, "bool_array_value": np.array(items, dtype=bool)}
        if all(isinstance(v, str) for v in items) and items:
            return {"type": STRING_ARRAY, "string_array_value": items}
        if all(isinstance(v, int) and not isinstance(v, bool) for v in items) and items:
            return {"type": INTEGER_ARRAY, "integer_array_value": np.array(items, np.int64)}
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items):
            return {"type": DOUBLE_ARRAY, "double_array_value": np.array(items, np.float64)}
    return {"type": STRING, "string_value": str(value)}


def from_parameter_value(msg: Any) -> Any:
    """Our value of a ``ParameterValue`` message (``None`` for NOT_SET).

    Raises:
        ValueError: a type this controller has no parameter of (a byte array, an unknown
            type number).
    """
    kind = int(msg.type)
    if kind == NOT_SET:
        return None
    if kind == BOOL:
        return bool(msg.bool_value)
    if kind == INTEGER:
        return int(msg.integer_value)
    if kind == DOUBLE:
        return float(msg.double_value)
    if kind == STRING:
        return str(msg.string_value)
    if kind == BOOL_ARRAY:
        return [bool(v) for v in msg.bool_array_value]
    if kind == INTEGER_ARRAY:
        return [int(v) for v in msg.integer_array_value]
    if kind == DOUBLE_ARRAY:
        return [float(v) for v in msg.double_array_value]
    if kind == STRING_ARRAY:
        return [str(v) for v in msg.string_array_value]
    raise ValueError(f"parameter type {kind} is not one this controller has")


def list_names(names: Iterable[str], prefixes: Sequence[str], depth: int
               ) -> tuple[list[str], list[str]]:
    """``ListParametersResult``'s ``names`` and ``prefixes`` (module docstring)."""
    chosen = []
    for name in sorted(names):
        if not prefixes:
            if depth == 0 or name.count(".") < depth:
                chosen.append(name)
            continue
        for prefix in prefixes:
            if name == prefix or (name.startswith(prefix + ".") and (
                    depth == 0 or name[len(prefix) + 1:].count(".") < depth)):
                chosen.append(name)
                break
    parents = sorted({name.rsplit(".", 1)[0] for name in chosen if "." in name})
    return chosen, parents
