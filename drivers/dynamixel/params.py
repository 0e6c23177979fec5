"""The parameters of the ``dynamixel`` hardware kind: one table, read by the schema engine.

:data:`PARAMS` is ``DynamixelHardware.PARAMS``: each parameter's type, default, range and help
line, declared once; the hardware contract's schema engine (``jtc_hw.hardware.params``)
validates a robot file's ``params`` against it. What a parameter does is said where it is used:
the hardware (:mod:`.hardware`) and its health reads (:mod:`.health`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Final

from jtc_hw.errors import ConfigurationError
from jtc_hw.hardware import (
    JOINT_MAPPING_PARAMS,
    WATCHDOG_PARAM,
    ParamKind,
    ParamSpec,
    health_params,
    param_table,
)

from .control_table import BAUD_RATES

__all__ = ["GAINS", "PARAMS", "SUPPLY_WARN"]

_SDK_BAUD_RATES: Final = tuple(sorted(b for b in BAUD_RATES.values() if b <= 4_000_000))
#: The gain registers a robot file may set per joint (null: the servo's own).
GAINS: Final = (
    "position_p_gain", "position_i_gain", "position_d_gain", "velocity_p_gain", "velocity_i_gain"
)
#: Default supply warning range, as factors of the model's nominal voltage (12 V: 10.2 .. 15 V,
#: inside the 12 V X models' recommended 10 .. 14.8 V at the top, and their 9.5 .. 16 V Min/Max
#: Voltage Limit defaults, at which the servo itself raises its Input Voltage Error).
SUPPLY_WARN: Final = (0.85, 1.25)


def _coerce_baud(value: Any, path: str) -> int:
    if value not in _SDK_BAUD_RATES or isinstance(value, bool):
        raise ConfigurationError(
            f"baud rate must be one of {', '.join(str(b) for b in _SDK_BAUD_RATES)} bit/s, "
            f"got {value!r}",
            path,
            value,
        )
    return int(value)


PARAMS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("port", ParamKind.STRING, None,
              "serial device of the bus (e.g. /dev/ttyUSB0 or /dev/serial/by-id/...)",
              required=True),
    ParamSpec("baud_rate", ParamKind.INT, 57600,
              "bus bit rate (bit/s); the X series' factory default is 57600",
              coerce=_coerce_baud),
    ParamSpec("ids", ParamKind.INT, None, "per joint servo id (0..252, unique)",
              minimum=0, maximum=252, per_joint=True, required=True),
    ParamSpec("model", ParamKind.STRING, "XM430-W350", "per joint servo model",
              per_joint=True),
    *JOINT_MAPPING_PARAMS,
    ParamSpec("position_limits", ParamKind.RANGE, (-math.inf, math.inf),
              "per joint [min, max] joint position, rad (null: the servo's limit registers)",
              per_joint=True, nullable=True),
    ParamSpec("extended_position", ParamKind.BOOL, False,
              "position interface: Extended Position mode (multi-turn) instead of Position"),
    ParamSpec("return_delay_time_us", ParamKind.INT, 0,
              "Return Delay Time written to every servo, us (0..508, in 2 us steps)",
              minimum=0, maximum=508),
    ParamSpec("profile_velocity", ParamKind.FLOAT, 0.0,
              "per joint Profile Velocity, rad/s at the joint (0: none)", minimum=0.0,
              per_joint=True),
    ParamSpec("profile_acceleration", ParamKind.FLOAT, 0.0,
              "per joint Profile Acceleration, rad/s^2 at the joint (0: none)", minimum=0.0,
              per_joint=True),
    *(
        ParamSpec(gain, ParamKind.INT, None,
                  f"per joint {gain.replace('_', ' ')} register (null: the servo's)",
                  minimum=0, maximum=16383, nullable=True, per_joint=True)
        for gain in GAINS
    ),
    ParamSpec("fast_sync_read", ParamKind.BOOL, False,
              "use Fast Sync Read (one combined reply; firmware 45+)"),
    ParamSpec("timeout_ms", ParamKind.FLOAT, 5.0,
              "allowance beyond the wire time before a reply counts as missing, ms",
              minimum=0.1, maximum=1000.0),
    ParamSpec("max_retries", ParamKind.INT, 1,
              "retries of a failed read (Sync Read, register read, ping), at once, before it is "
              "a fault",
              minimum=0, maximum=10),
    ParamSpec("reboot_timeout_s", ParamKind.FLOAT, 2.0,
              "how long recover() waits for a rebooted servo to answer, s",
              minimum=0.01, maximum=30.0),
    ParamSpec("latency_timer_warn", ParamKind.BOOL, True,
              "warn when the USB serial adapter's latency timer is above 1 ms"),
    WATCHDOG_PARAM,
    ParamSpec("health_period_s", ParamKind.FLOAT, 0.5,
              "how often every servo's temperature, voltage, hardware error and moving "
              "status are read, s (one extra Sync Read in every third of it, after a write)",
              minimum=0.01, maximum=60.0),
    # The Temperature Limit (which shuts an X servo down) is 70 or 80 degC.
    *health_params(65.0, None),
    ParamSpec("voltage_range", ParamKind.RANGE, None,
              "[min, max] supply voltage, V: a servo reporting one outside raises a warning "
              f"(null: {SUPPLY_WARN[0]:g} .. {SUPPLY_WARN[1]:g} x each model's nominal "
              "voltage, e.g. 10.2 .. 15 V for a 12 V servo)", nullable=True),
)
