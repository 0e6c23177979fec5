"""Changing a few parameters of a robot file's hardware component, leaving the rest as written.

A calibration (``jtc-hw calibrate feetech``) writes ``offset``, ``direction`` and
``position_limits`` into the robot file the user maintains by hand, with its comments, its
order and its other components. Loading the file and dumping it again would lose all of that,
so :func:`set_component_params` edits the text: it finds each parameter's value with the YAML
composer's marks and replaces exactly that span (a missing parameter gets a new line at the top
of ``params``). Nothing here opens a file.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import yaml

from ..errors import ConfigurationError

__all__ = ["flow_text", "hardware_components", "set_component_params"]


def flow_text(value: Any) -> str:
    """``value`` (a number, a string, or lists of them) as one line of flow-style YAML."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(round(value, 6))
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return yaml.safe_dump(value, default_flow_style=True).splitlines()[0]
    if isinstance(value, Sequence):
        return "[" + ", ".join(flow_text(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as a parameter")


def _mapping_get(node: yaml.Node, key: str) -> tuple[yaml.Node, yaml.Node] | None:
    if not isinstance(node, yaml.MappingNode):
        return None
    for k, v in node.value:
        if isinstance(k, yaml.ScalarNode) and k.value == key:
            return k, v
    return None


def hardware_components(text: str, name: str) -> list[tuple[str, str, yaml.MappingNode]]:
    """Each hardware component of a robot file: ``(name, kind, node)``.

    Raises:
        ConfigurationError: not YAML, or no ``hardware`` list.
    """
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise ConfigurationError(f"{name}: not valid YAML: {exc}") from None
    found = _mapping_get(root, "hardware") if root is not None else None
    if found is None or not isinstance(found[1], yaml.SequenceNode):
        raise ConfigurationError(f"{name}: no 'hardware' list; start from "
                                 "config/so101-follower.yaml")
    components = []
    for node in found[1].value:
        if not isinstance(node, yaml.MappingNode):
            continue
        fields = {k.value: v.value for k, v in node.value
                  if isinstance(k, yaml.ScalarNode) and isinstance(v, yaml.ScalarNode)}
        components.append((str(fields.get("name", "")), str(fields.get("kind", "")), node))
    return components


def set_component_params(
    text: str, name: str, component: yaml.MappingNode, values: Mapping[str, Any]
) -> str:
    """``text`` with ``values`` as the ``params`` of ``component`` (a node of
    :func:`hardware_components` of the same ``text``); everything else as it was.

    A value written in block style (one ``- item`` a line) stays in block style, one item a line
    at the same indentation; others are written in flow style (``[a, b]``). A comment after a
    replaced scalar is kept; comments inside a replaced block list are not.

    Raises:
        ConfigurationError: the component has no ``params`` mapping in block style.
    """
    found = _mapping_get(component, "params")
    if found is None or not isinstance(found[1], yaml.MappingNode) or found[1].flow_style:
        raise ConfigurationError(
            f"{name}: the hardware component has no 'params' mapping written one key a line; "
            "add one (see config/so101-follower.yaml)")
    params = found[1]
    edits: list[tuple[int, int, str]] = []
    missing: list[str] = []
    for key, value in values.items():
        item = _mapping_get(params, key)
        if item is None:
            missing.append(f"{key}: {flow_text(value)}")
            continue
        node = item[1]
        start, end = node.start_mark.index, node.end_mark.index
        end = start + len(text[start:end].rstrip())
        if (isinstance(node, yaml.SequenceNode) and not node.flow_style
                and isinstance(value, Sequence) and not isinstance(value, str)):
            indent = "\n" + " " * node.start_mark.column
            new = indent.join(f"- {flow_text(v)}" for v in value)
        else:
            new = flow_text(value)
        edits.append((start, end, new))
    if missing:
        first_key = params.value[0][0]
        line_start = first_key.start_mark.index - first_key.start_mark.column
        indent = " " * first_key.start_mark.column
        edits.append((line_start, line_start, "".join(f"{indent}{m}\n" for m in missing)))
    for start, end, new in sorted(edits, reverse=True):
        text = text[:start] + new + text[end:]
    return text
