"""What reads files: strict YAML, a URDF's joint limits, and :func:`load_config`.

The only module of :mod:`jtc_hw.config` that opens a file; what it reads is handed to the
checks of :mod:`.controller_file` (and the robot file's, :mod:`jtc_hw.daemon.robot`) as plain
data, and the controller gets a frozen :class:`~jtc_hw.config.controller.ControllerConfig`.

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

import math
import os
from collections.abc import Hashable, Mapping, Sequence
from typing import Any
from xml.etree import ElementTree

import yaml

from ..errors import ConfigurationError
from .controller import ControllerConfig
from .controller_file import build_config, select_controller
from .limits import JointLimits

__all__ = [
    "MAX_ALIAS_NODES",
    "MAX_DEPTH",
    "decode_text",
    "load_config",
    "load_yaml",
    "read_source",
    "read_urdf_limits",
]

MAX_ALIAS_NODES = 1_000_000
"""Most nodes that aliases may add to a YAML document, counted as if each alias were a copy of
what it names (a 10,000-point goal file that repeats one velocity list by alias adds 70,000)."""

MAX_DEPTH = 100
"""Most levels of nesting (mappings and lists inside each other) a YAML document may have: a
robot file or a goal file needs fewer than ten; the parser recurses once per level."""


# -- Strict YAML ----------------------------------------------------------------------------------


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


# -- URDF joint limits ----------------------------------------------------------------------------


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
        rates: dict[str, float | None] = {"velocity": None, "effort": None}
        if limit is not None:
            for attribute in rates:
                value = _urdf_float(limit, attribute, filename, name)
                if value is not None and value < 0.0:
                    raise _urdf_error(
                        filename,
                        f"joint {name!r}: <limit {attribute}={limit.get(attribute)!r}> must "
                        "not be negative",
                    )
                rates[attribute] = value or None  # 0: URDF's "not given"
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
        found = JointLimits(position, rates["velocity"], None, None, rates["effort"])
        if not found.empty:
            limits[name] = found
    return limits


# -- The controller's configuration ---------------------------------------------------------------


def load_config(
    source: str | os.PathLike[str] | Mapping[str, Any],
    controller_name: str | None = None,
    *,
    base_dir: str | os.PathLike[str] | None = None,
) -> ControllerConfig:
    """Read, check and freeze a controller configuration, with defaults filled for every joint.

    Args:
        source: path of a YAML file, or an already parsed mapping, in either layout
            (:mod:`jtc_hw.config.controller`). Top-level ``hardware`` and ``daemon`` keys are
            skipped (they configure the daemon); a top-level ``limits`` section gives the
            joint limits (per joint, or ``urdf``: a URDF file's) and ``time_scaling``.
        controller_name: which controller section to use when there are several (without
            it: the only one, or the only one the controller manager declares with the
            joint_trajectory_controller type); for the plain layout, the resulting name
            (default ``joint_trajectory_controller``).
        base_dir: the directory a relative ``limits.urdf`` is relative to (default: the
            file's directory, or the current directory for a mapping).

    Raises:
        ConfigurationError: the file cannot be read or parsed, a key is unknown, a required
            parameter is missing, a value has the wrong type or range, or the interfaces
            form an unsupported combination. The message names the dotted key path.
        TypeError: ``source`` is neither a path nor a mapping.
    """
    data = read_source(source)
    name, params, cm_update_rate = select_controller(data, controller_name)
    if base_dir is None and not isinstance(source, Mapping):
        base_dir = os.path.dirname(os.path.abspath(os.fspath(source)))
    directory = os.getcwd() if base_dir is None else os.fspath(base_dir)

    def read_urdf(urdf: str, joints: Sequence[str]) -> dict[str, JointLimits]:
        return read_urdf_limits(os.path.join(directory, os.path.expanduser(urdf)), joints)

    return build_config(name, params, cm_update_rate, data.get("limits"), read_urdf)
