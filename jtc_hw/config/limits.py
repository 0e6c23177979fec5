"""Joint limits: what each joint can do (position range, velocity, acceleration, jerk, effort).

These are the controller's limits (issue 12), distinct from a hardware driver's
``position_limits``, which stay the last line of defence in the driver. ``ControllerConfig.limits``
maps a joint name to its :class:`JointLimits`; a joint that is absent (or a field that is
``None``) is unlimited. Where they come from (a ``limits:`` section of the robot YAML, or a URDF's
``<limit>`` / ``<safety_controller>``) is the parser's business (:mod:`.controller_file`,
:mod:`.reading`); this module only defines the value and checks it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ..errors import ConfigurationError

__all__ = ["LIMIT_FIELDS", "JointLimits", "check_joint_limits"]

LIMIT_FIELDS = ("position", "velocity", "acceleration", "jerk", "effort")
"""The fields of :class:`JointLimits`, in the order the YAML and the docs list them."""


@dataclass(frozen=True)
class JointLimits:
    """Limits of one joint, SI units (rad or m; per second, per second squared, ...).

    Attributes:
        position: ``(min, max)`` with ``min < max``, or ``None`` (unlimited, e.g. continuous).
        velocity: maximum ``|velocity|`` (> 0), or ``None``.
        acceleration: maximum ``|acceleration|`` (> 0), or ``None``.
        jerk: maximum ``|jerk|`` (> 0), or ``None``.
        effort: maximum ``|effort|`` (> 0), or ``None``.
    """

    position: tuple[float, float] | None = None
    velocity: float | None = None
    acceleration: float | None = None
    jerk: float | None = None
    effort: float | None = None

    @property
    def empty(self) -> bool:
        """Whether no field limits anything."""
        return all(getattr(self, name) is None for name in LIMIT_FIELDS)


def _positive(value: Any, path: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigurationError(f"expected a number, got {value!r}", path, value)
    number = float(value)
    if not math.isfinite(number) or number <= 0.0:
        raise ConfigurationError(f"must be a finite number > 0, got {value!r}", path, value)
    return number


def check_joint_limits(limits: Any, path: str) -> JointLimits:
    """Check one joint's limits (types, ranges) and return them normalised to floats.

    Raises:
        ConfigurationError: not a ``JointLimits``, a non-positive or non-finite bound, or a
            position range whose minimum is not below its maximum.
    """
    if not isinstance(limits, JointLimits):
        raise ConfigurationError(f"expected a JointLimits instance, got {limits!r}", path, limits)
    position = limits.position
    if position is not None:
        try:
            low, high = (float(v) for v in position)
        except (TypeError, ValueError):
            raise ConfigurationError(
                f"expected [min, max], got {position!r}", f"{path}.position", position
            ) from None
        if not (math.isfinite(low) and math.isfinite(high)) or not low < high:
            raise ConfigurationError(
                f"expected finite [min, max] with min < max, got {position!r}",
                f"{path}.position",
                position,
            )
        position = (low, high)
    values = {
        name: None if getattr(limits, name) is None else _positive(
            getattr(limits, name), f"{path}.{name}"
        )
        for name in LIMIT_FIELDS[1:]
    }
    return JointLimits(position, **values)
