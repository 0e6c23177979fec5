"""Reading configuration values: strict YAML, and checks whose errors say what to write.

Shared by the controller's parameters, the hardware parameter schema and the robot file, so
that every configuration error reads the same way: the key path, what was found, and a hint
("did you mean", "write true without quotes").

YAML is read with a safe loader that refuses a key given twice and bounds what aliases may
add: a few lines of nested anchors (``&a``) and aliases (``*a``) can stand for a billion nodes
(an "alias bomb"), which anything walking the result, down to an error message quoting it,
would expand. Such a document is refused before it is built. So is one nested deeper than
:data:`MAX_DEPTH` (the composer and the constructor recurse once per level: 5,000 levels of
``[`` would exhaust the interpreter's stack), refused where the limit is crossed.

Every error is one line that names the file and, where known, the line and column
(``robot.yaml, line 3, column 7: ...``): a text that is not UTF-8 (the offset of the first bad
byte), a character YAML refuses, a syntax error, too deep a nesting, an alias bomb.
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
    "MAX_DEPTH",
    "decode_text",
    "read_source",
]

MAX_ALIAS_NODES = 1_000_000
"""Most nodes that aliases may add to a YAML document, counted as if each alias were a copy of
what it names (a 10,000-point goal file that repeats one velocity list by alias adds 70,000)."""

MAX_DEPTH = 100
"""Most levels of nesting (mappings and lists inside each other) a YAML document may have: a
robot file or a goal file needs fewer than ten; the parser recurses once per level."""


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


class NestingError(yaml.MarkedYAMLError):
    """A YAML document nested deeper than ``MAX_DEPTH`` (``problem_mark``: where)."""


class _StrictLoader(yaml.SafeLoader):
    """Safe YAML loader that refuses a key given twice in one mapping, a document whose
    aliases expand it beyond ``MAX_ALIAS_NODES`` nodes, and one nested deeper than
    ``MAX_DEPTH``."""

    _depth = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise NestingError(
                    problem=f"nested more than {MAX_DEPTH} levels deep; flatten it",
                    problem_mark=self.peek_event().start_mark,  # type: ignore[no-untyped-call]
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

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


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _yaml_problem(exc: yaml.YAMLError, text: str) -> tuple[str, str]:
    """Where a YAML error is in ``text`` (``", line L, column C"`` or ``""``) and what it
    is, one line."""
    if isinstance(exc, yaml.MarkedYAMLError):
        mark = exc.problem_mark or exc.context_mark
        where = "" if mark is None else f", line {mark.line + 1}, column {mark.column + 1}"
        what = "; ".join(_one_line(p) for p in (exc.context, exc.problem) if p)
        if not isinstance(exc, NestingError):
            what = f"not valid YAML: {what}"
        return where, what
    if isinstance(exc, yaml.reader.ReaderError):
        line = text.count("\n", 0, exc.position) + 1
        column = exc.position - (text.rfind("\n", 0, exc.position) + 1) + 1
        return (
            f", line {line}, column {column}",
            f"not valid YAML: the character #x{exc.character:04x} is not allowed in YAML "
            "(a binary file?)"
            if isinstance(exc.character, int)
            else f"not valid YAML: {_one_line(str(exc))}",
        )
    if isinstance(exc, AliasExpansionError):
        return "", _one_line(str(exc))
    return "", f"not valid YAML: {_one_line(str(exc))}"


def decode_text(data: bytes, name: str) -> str:
    """``data`` as UTF-8 text.

    Raises:
        ConfigurationError: not UTF-8; the message names ``name``, the line and column
            (counted in bytes) of the first bad byte, and says what to do.
    """
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        column = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise ConfigurationError(
            f"{name}, line {line}, column {column}: not UTF-8 text (byte "
            f"0x{data[exc.start]:02x} at offset {exc.start}; a binary file?); save it as UTF-8"
        ) from None


def _load(text: str) -> Any:
    """One document with :class:`_StrictLoader`.

    Raises:
        yaml.YAMLError: any refusal, including a stack exhausted anyway (a
            :class:`NestingError` without a position).
    """
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader
    except RecursionError:
        raise NestingError(
            problem="nested too deeply for the interpreter's stack; flatten it"
        ) from None


def load_yaml(text: str, name: str) -> Any:
    """Parse one YAML document strictly (no duplicate keys, alias expansion and nesting
    bounded).

    Args:
        text: the document.
        name: what it is, for errors (a file name).

    Raises:
        ConfigurationError: not valid YAML, an alias bomb or nested too deep; one line, the
            path is ``name`` and the position follows it where known.
    """
    try:
        return _load(text)
    except yaml.YAMLError as exc:
        where, what = _yaml_problem(exc, text)
        raise ConfigurationError(what, f"{name}{where}") from None


def read_source(source: str | os.PathLike[str] | Mapping[str, Any]) -> Mapping[Any, Any]:
    """The mapping ``source`` holds: itself, or the YAML file it names, read strictly.

    Raises:
        ConfigurationError: the file cannot be read, is not UTF-8, not valid YAML (nested
            deeper than :data:`MAX_DEPTH`, an alias bomb, ...), empty or not a mapping; one
            line naming the file and, where known, the line and column.
        TypeError: ``source`` is neither a path nor a mapping.
    """
    if isinstance(source, Mapping):
        return source
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(
            f"source must be a path or a mapping, got {type(source).__name__}"
        )
    filename = os.fspath(source)
    try:
        with open(filename, "rb") as stream:
            raw = stream.read()
    except OSError as exc:
        raise ConfigurationError(
            f"cannot read configuration file {filename}: {exc.strerror or exc}", "", filename
        ) from None
    text = decode_text(raw, f"configuration file {filename}")
    try:
        data = _load(text)
    except yaml.YAMLError as exc:
        where, what = _yaml_problem(exc, text)
        raise ConfigurationError(
            f"configuration file {filename}{where}: {what}", "", filename
        ) from None
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
