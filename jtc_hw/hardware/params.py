"""The parameter rows shared by hardware kinds: the ones every kind accepts, and the ones
drivers include in their ``PARAMS`` (joint mapping, watchdog, health limits, miss rate).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Final

from ..config.schema import ParamKind, ParamSpec, param_table
from .lifecycle import SafeAction

COMMON_PARAMS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("safe_action", ParamKind.STRING, SafeAction.HOLD.value,
              "what deactivate() leaves the joints doing: hold the position, or torque off",
              choices=tuple(a.value for a in SafeAction)),
)
"""Parameters every hardware kind accepts (merged with the kind's ``PARAMS``)."""

JOINT_MAPPING_PARAMS: Final[tuple[ParamSpec, ...]] = (
    ParamSpec("offset", ParamKind.FLOAT, 0.0,
              "per joint: joint position at motor zero, rad "
              "(joint = direction * motor / gear_ratio + offset)", per_joint=True),
    ParamSpec("direction", ParamKind.INT, 1,
              "per joint: 1 or -1, the joint's sense against the motor's",
              choices=(1, -1), per_joint=True),
    ParamSpec("gear_ratio", ParamKind.FLOAT, 1.0,
              "per joint: motor turns per joint turn (external gearing)",
              minimum=1e-9, per_joint=True),
)
"""How a motor's position maps to its joint's, for drivers to include in their ``PARAMS``
(``param_table(*JOINT_MAPPING_PARAMS, ...)``): one convention for every kind."""

DEFAULT_WATCHDOG_S: Final = 0.1
"""Default device-side watchdog time, s."""

MIN_WATCHDOG_PERIODS: Final = 3
"""A watchdog must allow at least this many loop periods (one late cycle must not trip it)."""

WATCHDOG_PARAM: Final = ParamSpec(
    "watchdog_s", ParamKind.FLOAT, DEFAULT_WATCHDOG_S,
    "device-side watchdog, s: with no command for this long the motors stop by themselves "
    "(armed on activate, disarmed on a clean deactivate); at least 3 loop periods",
    minimum=0.001,
)
"""The ``watchdog_s`` row, for drivers whose devices have a watchdog to include in their
``PARAMS``; the robot file checks it against the loop period (:data:`MIN_WATCHDOG_PERIODS`)."""


def health_params(
    temperature_warn_c: float, voltage_range: tuple[float, float] | None
) -> tuple[ParamSpec, ...]:
    """The health limit rows, for drivers that report temperatures (and voltages) to include
    in their ``PARAMS`` with their motors' defaults.

    Args:
        temperature_warn_c: default warning temperature, degC.
        voltage_range: default [min, max] supply voltage, V, outside which a warning is raised;
            ``None``: the kind's motors report no voltage, so it has no such parameter.
    """
    rows = [
        ParamSpec("temperature_warn_c", ParamKind.FLOAT, float(temperature_warn_c),
                  "a motor at or above this temperature raises a warning in status and the "
                  "log, degC"),
    ]
    if voltage_range is not None:
        rows.append(ParamSpec(
            "voltage_range", ParamKind.RANGE, tuple(float(v) for v in voltage_range),
            "[min, max] supply voltage, V: a motor reporting one outside raises a warning"))
    return tuple(rows)


MISS_RATE_WINDOW: Final = 1000
"""Transactions a miss rate is judged over (at least; the window closes at the first
:meth:`HardwareInterface.health` call after that many): a few stragglers in a short window
are not a trend, and a rate over the whole run would hide a recent one."""


def miss_rate_param(default: float) -> ParamSpec:
    """The ``miss_rate_warn`` row, for drivers whose bus counts ``transactions`` and
    ``timeouts`` (replies that did not come in time), with the kind's default fraction."""
    return ParamSpec(
        "miss_rate_warn", ParamKind.FLOAT, float(default),
        "fraction of transactions whose reply did not come in time above which a warning is "
        "raised in status and the log, judged over windows of at least "
        f"{MISS_RATE_WINDOW} transactions (0: never warn)", minimum=0.0, maximum=1.0)
