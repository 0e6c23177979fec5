"""The servos' health: read at a low rate inside the cycle, reported with the status.

Theory of operation
-------------------
Health is one register block, the same addresses on every servo of a series::

    STS/SMS  Present Voltage (62) .. Present Current (69..70): voltage, temperature, Status,
             Moving, current
    SCS      Present Voltage (62) .. Moving (66): no current register

Every ``health_period_s``, after the cycle's write (a Sync Write has no reply, so the bus is
free and the command is already out), one group read of that block of every servo: no cycle
pays more than this one extra transaction. A failed health read is counted, not raised: the
next cycle's read is the one that decides about the bus. The Status bits come with every reply
anyway (each status packet's error byte), so an overload is seen by the cycle's own read; this
block adds the temperature, voltage and current behind it.

A block read more than two ``health_period_s`` ago, or never, gives unknown values (``None``,
``stale`` true), not the last ones heard. No thread and no clock beyond stamping a read.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any, Final

from .bus import FeetechBus, ServoCommunicationError
from .codec import decode_value, status_error_text
from .control_table import Model, Series

__all__ = ["FIRST", "ServoHealth"]

FIRST: Final = "present_voltage"
_LAST: Final = {"sts_sms": "present_current", "scs": "moving"}
#: The report's keys that come from the block (unknown while it is stale).
_KEYS: Final = ("temperature_c", "voltage_v", "current_a", "moving", "status")


def _block(series: Series) -> tuple[int, int]:
    """``(address, size)`` of the health block of ``series``."""
    start = series.register(FIRST).address
    last = series.register(_LAST[series.name.value])
    return start, last.address + last.size - start


class ServoHealth:
    """The health readings of the servos of one bus (see the module docstring).

    Args:
        ids, joints, models: the servos, their joints and models, in the same order.
        period_s: ``health_period_s``.

    Attributes:
        firmware: servo id -> ``"major.minor"`` (the hardware fills it at configure).
        read_errors: health reads that failed.
    """

    def __init__(self, ids: Sequence[int], joints: Sequence[str], models: Sequence[Model],
                 period_s: float) -> None:
        self._ids = tuple(ids)
        self._joints = tuple(joints)
        self._models = tuple(models)
        self._series = models[0].series
        self._start, self._size = _block(self._series)
        self._period_ns = max(1, round(period_s * 1e9))
        self.firmware: dict[int, str] = {}
        self.read_errors = 0
        self._values: dict[int, dict[str, int]] = {i: {} for i in self._ids}
        self._read_at: int | None = None
        self._next_ns: int | None = None

    def due(self, now_ns: int) -> bool:
        """Whether the cycle at ``now_ns`` reads the block; asking moves the schedule on."""
        if self._next_ns is not None and now_ns < self._next_ns:
            return False
        self._next_ns = now_ns + self._period_ns
        return True

    def read(self, bus: FeetechBus) -> None:
        """One group read of the block of every servo; a failure is counted."""
        try:
            result = bus.group_read(self._ids, self._start, self._size)
        except ServoCommunicationError:
            self.read_errors += 1
            return
        self._read_at = time.monotonic_ns()
        order = self._series.byte_order
        for servo_id in self._ids:
            block = result.data[servo_id]
            values = self._values[servo_id]
            for name, reg in self._series.registers.items():
                offset = reg.address - self._start
                if 0 <= offset and offset + reg.size <= self._size:
                    values[name] = decode_value(reg, block[offset:offset + reg.size], order)

    def report(self, torque: Mapping[int, bool | None], latched: Mapping[int, int],
               last_fault: Mapping[int, str]) -> list[dict[str, Any]]:
        """Each servo's health as last read.

        Args:
            torque: servo id -> whether its torque is on, as last known (``None``: unknown).
            latched: servo id -> the fault bits the hardware latched.
            last_fault: servo id -> the last fault the hardware saw on it.
        """
        now = time.monotonic_ns()
        fresh = self._read_at is not None and now - self._read_at <= 2 * self._period_ns
        motors: list[dict[str, Any]] = []
        for servo_id, joint, model in zip(self._ids, self._joints, self._models, strict=True):
            v = self._values[servo_id] if fresh else {}
            status = v.get("status", 0) | latched.get(servo_id, 0)
            volts = v.get("present_voltage")
            current = v.get("present_current")
            motors.append({
                "motor": servo_id,
                "joint": joint,
                "model": model.name,
                "firmware": self.firmware.get(servo_id),
                "mode": "position",
                "torque_enabled": torque.get(servo_id),
                "temperature_c": v.get("present_temperature"),
                "voltage_v": None if volts is None else volts / 10.0,
                "current_a": (None if current is None or model.current_unit_a is None
                              else round(current * model.current_unit_a, 4)),
                "moving": None if "moving" not in v else bool(v["moving"]),
                "status": None if "status" not in v else status_error_text(v["status"]),
                "age_s": (None if self._read_at is None
                          else round((now - self._read_at) / 1e9, 3)),
                "stale": not fresh,
                "unknown": [] if fresh else list(_KEYS),
                "errors": [f"status: {status_error_text(status)}"] if status else [],
                "last_fault": last_fault.get(servo_id),
            })
        return motors
