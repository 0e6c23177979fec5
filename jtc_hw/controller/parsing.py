"""Reading configuration values: strict YAML, and checks whose errors say what to write.

Shared by the controller's parameters, the hardware parameter schema and the robot file, so
that every configuration error reads the same way: the key path, what was found, and a hint
("did you mean", "write true without quotes").

YAML is read with a safe loader that refuses a key given twice and bounds what aliases may
add: a few lines of nested anchors (``&a``) and aliases (``*a``) can stand for a billion nodes
(an "alias bomb"), which anything walking the result, down to an error message quoting it,
would expand. Such a document is refused before it is built.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Hashable, Iterable, Mapping
from typing import Any

import yaml

from ..errors import ConfigurationError

__all__ = [
    "closest",
    "coerce_bool",
    "coerce_string_array",
    "describe",
    "did_you_mean",
    "fmt_list",
    "load_yaml",
    "MAX_ALIAS_NODES",
    "read_source",
]

MAX_ALIAS_NODES = 1_000_000
"""Most nodes that aliases may add to a YAML document, counted as if each alias were a copy of
what it names (a 10,000-point goal file that repeats one velocity list by alias adds 70,000)."""


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


class AliasExpansionError(yaml.YAMLError):
    """A YAML document whose aliases expand it beyond ``MAX_ALIAS_NODES``, or infinitely."""


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [item for pair in node.value for item in pair]
    return []


def _check_alias_expansion(root: yaml.Node, limit: int = MAX_ALIAS_NODES) -> None:
    """Refuse a document whose aliases add more than ``limit`` nodes, or that contains itself.

    The composed document is a graph in which an alias is the node it names, shared; its
    size as a tree (what a walk of the loaded data visits) is computed per distinct node,
    so this costs as much as the document's text, not as its expansion.

    Raises:
        AliasExpansionError: says by how much, or that an anchor is used inside itself.
    """
    size: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, finished = stack.pop()
        key = id(node)
        if finished:
            size[key] = 1 + sum(size[id(child)] for child in _children(node))
            on_path.discard(key)
            continue
        if key in size:
            continue
        on_path.add(key)
        stack.append((node, True))
        for child in _children(node):
            if id(child) in on_path:
                mark = child.start_mark
                raise AliasExpansionError(
                    f"an anchor is used inside itself (line {mark.line + 1}, column "
                    f"{mark.column + 1}): the document would be infinite"
                )
            if id(child) not in size:
                stack.append((child, False))
    added = size[id(root)] - len(size)
    if added > limit:
        raise AliasExpansionError(
            f"its aliases (*name) expand it by {added:,} nodes, more than the {limit:,} "
            "allowed (an alias bomb?); write the repeated values out, or nest fewer aliases"
        )


class _StrictLoader(yaml.SafeLoader):
    """Safe YAML loader that refuses a key given twice in one mapping, and a document whose
    aliases expand it beyond ``MAX_ALIAS_NODES`` nodes."""

    def construct_document(self, node: yaml.Node) -> Any:
        _check_alias_expansion(node)
        return super().construct_document(node)


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


def load_yaml(text: str, name: str) -> Any:
    """Parse one YAML document strictly (no duplicate keys, alias expansion bounded).

    Args:
        text: the document.
        name: what it is, for errors (a file name).

    Raises:
        ConfigurationError: not valid YAML, or an alias bomb; the path is ``name``.
    """
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader
    except AliasExpansionError as exc:
        raise ConfigurationError(str(exc), name) from None
    except yaml.YAMLError as exc:
        raise ConfigurationError(f"not valid YAML: {exc}", name) from None


def read_source(source: str | os.PathLike[str] | Mapping[str, Any]) -> Mapping[Any, Any]:
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
    except AliasExpansionError as exc:
        raise ConfigurationError(f"configuration file {filename}: {exc}", "", filename) from None
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
