"""The parameters of the ``feetech`` hardware kind: one table, read by the schema engine.

:data:`PARAMS` is ``FeetechHardware.PARAMS``: each parameter's type, default, range and help
line, declared once; the hardware contract's schema engine validates a robot file's ``params``
against it. What a parameter does is said where it is used (:mod:`.hardware`, :mod:`.health`).
There is no ``watchdog_s``: these servos have no bus watchdog (see :mod:`.hardware`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Final

from jtc_hw.errors import ConfigurationError
from jtc_hw.hardware import (
    JOINT_MAPPING_PARAMS,
    ParamKind,
    ParamSpec,
    health_params,
    miss_rate_param,
    param_table,
)

__all__ = ["BAUD_RATES", "PARAMS"]

#: The servos' baud rates that Feetech's SDK can also set (its ``getCFlagBaud`` lacks 76800);
#: the same list as ``bus.SDK_BAUD_RATES``, which this table may not import (the SDK is optional).
BAUD_RATES: Final = (38_400, 57_600, 115_200, 128_000, 250_000, 500_000, 1_000_000)


def _coerce_baud(value: Any, path: str) -> int:
    if value not in BAUD_RATES or isinstance(value, bool):
        raise ConfigurationError(
            f"baud rate must be one of {', '.join(str(b) for b in BAUD_RATES)} bit/s (the "
            f"servos' factory rate is 1000000), got {value!r}", path, value)
    return int(value)


PARAMS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("port", ParamKind.STRING, None,
              "serial device of the bus (e.g. /dev/ttyACM0 or /dev/serial/by-id/...)",
              required=True),
    ParamSpec("baud_rate", ParamKind.INT, 1_000_000,
              "bus bit rate (bit/s); the servos leave the factory at 1000000",
              coerce=_coerce_baud),
    ParamSpec("ids", ParamKind.INT, None, "per joint servo id (0..252, unique)",
              minimum=0, maximum=252, per_joint=True, required=True),
    ParamSpec("model", ParamKind.STRING, "STS3215",
              "per joint servo model (STS3215, STS3250, SCS0009; one series per bus)",
              per_joint=True),
    *JOINT_MAPPING_PARAMS,
    ParamSpec("position_limits", ParamKind.RANGE, (-math.inf, math.inf),
              "per joint [min, max] joint position, rad: commands are clamped to it and to the "
              "servo's own limit registers (null: the servo's only)",
              per_joint=True, nullable=True),
    ParamSpec("return_delay_time_us", ParamKind.INT, 0,
              "Return Delay Time set on every servo for the session, us (0..508, 2 us steps; "
              "factory 500; not stored in the servo's EEPROM)", minimum=0, maximum=508),
    ParamSpec("timeout_ms", ParamKind.FLOAT, 20.0,
              "allowance beyond a transaction's wire time and return delays before a reply "
              "counts as missing, ms (the USB adapter's latency: an FTDI's is 16 ms unless "
              "lowered)", minimum=0.1, maximum=1000.0),
    ParamSpec("max_retries", ParamKind.INT, 1,
              "retries of a failed read (the cycle's read, a register read, a ping), at once, "
              "before it is a fault", minimum=0, maximum=10),
    ParamSpec("health_period_s", ParamKind.FLOAT, 0.5,
              "how often every servo's voltage, temperature, status, moving and current are "
              "read, s (one extra group read, after a write)", minimum=0.01, maximum=60.0),
    # The servos switch their torque off above Max Temperature Limit (70 degC from the factory).
    *health_params(60.0, None),
    ParamSpec("voltage_range", ParamKind.RANGE, None,
              "[min, max] supply voltage, V: a servo reporting one outside raises a warning "
              "(null: only the servo's own voltage bit; the STS3215 comes in 7.4 V and 12 V "
              "versions with one model number)", nullable=True),
    miss_rate_param(0.01),
)
