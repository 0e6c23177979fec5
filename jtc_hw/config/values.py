"""Checks of single configuration values whose errors say what to write.

Shared by every parameter (the controller's, each hardware kind's, the daemon's) and by the
protocol's and the CLI's own checks, so that every configuration error reads the same way: the
key path, what was found, and a hint ("did you mean", "write true without quotes"). No I/O.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from typing import Any

from ..errors import ConfigurationError

__all__ = [
    "closest",
    "coerce_bool",
    "coerce_string_array",
    "describe",
    "did_you_mean",
    "fmt_list",
]


def describe(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})"


def fmt_list(items: Iterable[str]) -> str:
    return "[" + ", ".join(items) + "]"


def closest(word: str, candidates: Iterable[str]) -> str | None:
    matches = difflib.get_close_matches(word, list(candidates), n=1, cutoff=0.6)
    return matches[0] if matches else None


def did_you_mean(word: str, candidates: Iterable[str]) -> str:
    best = closest(word, candidates)
    return f"; did you mean '{best}'?" if best is not None else ""


def coerce_string_array(value: Any, path: str) -> tuple[str, ...]:
    """Type-check a string array: a list of strings, or the literal '{}' / '[]' (empty)."""
    if isinstance(value, str):
        if value.strip() in ("{}", "[]"):
            return ()
        raise ConfigurationError(
            f"expected a list of strings, got {describe(value)}; write a YAML list, "
            f"e.g. [{value}]",
            path,
            value,
        )
    if not isinstance(value, (list, tuple)):
        raise ConfigurationError(f"expected a list of strings, got {describe(value)}", path, value)
    for index, item in enumerate(value):
        if not isinstance(item, str):
            raise ConfigurationError(
                f"expected a list of strings, but element {index} is {describe(item)}",
                path,
                item,
            )
        if not item.strip():
            raise ConfigurationError(f"element {index} is an empty name", path, item)
    return tuple(value)


def coerce_bool(value: Any, path: str, prefix: str = "") -> bool:
    """``value`` if it is a YAML boolean; a quoted "true"/"false" gets a hint.

    Raises:
        ConfigurationError: not a boolean.
    """
    if not isinstance(value, bool):
        hint = ""
        if isinstance(value, str) and value.strip().lower() in ("true", "false"):
            hint = f"; write {value.strip().lower()} without quotes"
        raise ConfigurationError(
            f"{prefix}expected true or false, got {describe(value)}{hint}", path, value
        )
    return value
