"""The registry of hardware kinds: built-in, entry points, and :func:`register_hardware`.

Kinds are found lazily: built-in ``"module:Class"`` strings, the ``jtc_hw.hardware``
entry-point group, and :func:`register_hardware`. Importing a kind's module happens only when it
is created, so a missing optional SDK only matters to whoever uses it, and then the error names
the ``pip install`` extra.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import metadata
from types import MappingProxyType
from typing import Any, Final

from ..config.schema import freeze, join
from ..config.values import describe, did_you_mean
from ..errors import ConfigurationError, HardwareError, JtcHwError
from .interface import HardwareInterface

__all__ = [
    "BUILTIN_HARDWARE",
    "ENTRY_POINT_GROUP",
    "HardwareSpec",
    "available_hardware",
    "check_hardware_kind",
    "create_hardware",
    "hardware_class",
    "register_hardware",
    "unregister_hardware",
]

_log = logging.getLogger("jtc_hw.hardware")

ENTRY_POINT_GROUP: Final = "jtc_hw.hardware"
"""Entry-point group through which third-party packages add hardware kinds."""

BUILTIN_HARDWARE: Final[Mapping[str, str]] = MappingProxyType({
    "mirror": "jtc_hw.hardware.mirror:MirrorHardware",
    "dynamixel": "jtc_hw.drivers.dynamixel.hardware:DynamixelHardware",
    "feetech": "jtc_hw.drivers.feetech.hardware:FeetechHardware",
    "can-mit": "jtc_hw.drivers.can.mit.hardware:MitHardware",
    "can-cia402": "jtc_hw.drivers.can.cia402.hardware:Cia402Hardware",
})
"""Built-in kinds, as lazy ``"module:Class"`` strings."""

_BUILTIN_EXTRAS: Final[Mapping[str, str]] = MappingProxyType({
    "dynamixel": "dynamixel",
    "feetech": "feetech",
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
        raise ConfigurationError(f"expected a non-empty kind, got {describe(kind)}", "kind", kind)
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


def _entry(kind: Any, path: str) -> _Entry:
    """The registration of ``kind`` (unknown: a ConfigurationError listing the known ones)."""
    entries = _entries()
    if not isinstance(kind, str) or kind not in entries:
        kinds = sorted(entries)
        raise ConfigurationError(
            f"unknown hardware kind {kind!r}; available kinds: {', '.join(kinds)}"
            f"{did_you_mean(str(kind), kinds)}",
            path,
            kind,
        )
    return entries[kind]


def check_hardware_kind(kind: Any, path: str = "kind") -> None:
    """Check that ``kind`` names a known hardware kind, without importing it.

    Raises:
        ConfigurationError: unknown kind; the message lists the available kinds.
    """
    _entry(kind, path)


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
    return _import_factory(kind, _entry(kind, path), path)


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
            object.__setattr__(self, "params", freeze(self.params))


def _prefixed(exc: ConfigurationError, prefix: str) -> ConfigurationError:
    """The same error with ``prefix`` put in front of its path."""
    message = str(exc)
    if exc.path and message.startswith(f"{exc.path}: "):
        message = message[len(exc.path) + 2:]
    return ConfigurationError(message, join(prefix, exc.path), exc.value)


def create_hardware(spec: HardwareSpec) -> HardwareInterface:
    """Create one component from its spec (UNCONFIGURED).

    Raises:
        ConfigurationError: unknown kind, missing optional dependency, or invalid joints,
            interfaces or parameters; the path starts with ``spec.path``.
        HardwareError: the driver's constructor failed otherwise.
    """
    cls = hardware_class(spec.kind, join(spec.path, "kind"))
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
