"""The servos' health: read in turn inside the cycle, reported with the status.

Theory of operation
-------------------
Health is three register blocks, the same addresses on every X model::

    block 0  Torque Enable (64) .. Hardware Error Status (70)
    block 1  Moving (122) .. Moving Status (123)
    block 2  Present Input Voltage (144) .. Present Temperature (146)

``health_period_s`` is cut into one slot per block. In each slot, after the cycle's write (a
Sync Write has no reply, so the bus is free and the command is already out), one Sync Read of
the next block of every servo: no cycle pays more than this one extra transaction. A failed
health read is counted, not raised: the next cycle's read is the one that decides about the
bus.

Each block keeps the values of its last good read and when that was. In the report a block
read more than two ``health_period_s`` ago (the bus lost, the health reads failing, nothing
read while a watchdog may be armed), or never, gives unknown values (``None``, listed in
``unknown``; ``stale`` true), not the last ones heard; ``age_s`` is the age of the servo's
oldest block. No thread and no clock of its own beyond stamping a read (``time.monotonic_ns``).
"""

from __future__ import annotations

import time
from collections.abc import Collection, Mapping, Sequence
from types import MappingProxyType
from typing import Any, Final

from .bus import DynamixelBus, ServoCommunicationError
from .control_table import Model, hardware_error_text
from .params import SUPPLY_WARN

__all__ = ["ServoHealth"]

#: The health blocks (register names: first, last of each block), read one per slot in turn.
_HEALTH_BLOCKS: Final = (
    ("torque_enable", "hardware_error_status"),
    ("moving", "moving_status"),
    ("present_input_voltage", "present_temperature"),
)
#: Health key of each register read in _HEALTH_BLOCKS (the hardware error goes to ``errors``).
_HEALTH_KEYS: Final = MappingProxyType({
    "torque_enable": "torque_enabled", "moving": "moving", "moving_status": "moving_status",
    "present_input_voltage": "voltage_v", "present_temperature": "temperature_c",
})


class ServoHealth:
    """The health readings of the servos of one bus (see the module docstring).

    Args:
        ids, joints, models: the servos, their joints and models, in the same order.
        period_s: ``health_period_s``: every block of every servo is read once in it.
        voltage_range: ``voltage_range`` (V) or ``None``: :data:`~.params.SUPPLY_WARN` times
            each model's nominal voltage.

    Attributes:
        firmware: servo id -> Firmware Version (the hardware fills it at configure).
        read_errors: health reads that failed.
    """

    def __init__(
        self,
        ids: Sequence[int],
        joints: Sequence[str],
        models: Sequence[Model],
        period_s: float,
        voltage_range: Sequence[float] | None,
    ) -> None:
        self._ids = tuple(ids)
        self._joints = tuple(joints)
        self._models = tuple(models)
        self._voltage_range = voltage_range
        self.firmware: dict[int, int] = {}
        self.read_errors = 0
        self._values: dict[int, dict[str, int]] = {i: {} for i in self._ids}
        # When each block was last read, per servo (monotonic ns): older than two health
        # periods, its values are reported unknown (see report()).
        self._read_at: dict[int, dict[int, int]] = {i: {} for i in self._ids}
        self._stale_ns = 2 * round(period_s * 1e9)
        self._slot_ns = max(1, round(period_s * 1e9 / len(_HEALTH_BLOCKS)))
        self._next_ns: int | None = None
        self._block = 0

    def due(self, now_ns: int) -> int | None:
        """The block to read in the cycle at ``now_ns``, or ``None`` (not yet); asking for it
        moves the schedule on to the next slot and block."""
        if self._next_ns is None:
            self._next_ns = now_ns
        if now_ns < self._next_ns:
            return None
        self._next_ns = now_ns + self._slot_ns
        block_index = self._block
        self._block = (self._block + 1) % len(_HEALTH_BLOCKS)
        return block_index

    def read(self, bus: DynamixelBus, block_index: int) -> None:
        """One Sync Read of block ``block_index`` of every servo; a failure is counted."""
        first, last = _HEALTH_BLOCKS[block_index]
        model = self._models[0]
        start = model.register(first).address
        end_reg = model.register(last)
        size = end_reg.address + end_reg.size - start
        try:
            result = bus.sync_read(self._ids, start, size)
        except ServoCommunicationError:
            self.read_errors += 1
            return
        read_at = time.monotonic_ns()
        for i, servo_id in enumerate(self._ids):
            block = result.data[servo_id]
            self._read_at[servo_id][block_index] = read_at
            values = self._values[servo_id]
            for name in (first, last):
                reg = self._models[i].register(name)
                values[name] = reg.decode(block[reg.address - start:reg.address - start + reg.size])

    def report(
        self,
        mode: str,
        latched: Mapping[int, int],
        watchdog_expired: Collection[int],
        last_fault: Mapping[int, str],
    ) -> list[dict[str, Any]]:
        """Each servo's health as last read (see the module docstring).

        Args:
            mode: the operating mode's name, as reported.
            latched: servo id -> the hardware error flags the hardware latched (reported when
                the block with Hardware Error Status is unknown).
            watchdog_expired: the servos whose Bus Watchdog the hardware found expired.
            last_fault: servo id -> the last fault the hardware saw on it.
        """
        now = time.monotonic_ns()
        motors: list[dict[str, Any]] = []
        for servo_id, joint, model in zip(self._ids, self._joints, self._models, strict=True):
            read_at = self._read_at[servo_id]
            fresh = {k for k, t in read_at.items() if now - t <= self._stale_ns}
            v = {name: value for name, value in self._values[servo_id].items()
                 if any(name in _HEALTH_BLOCKS[k] for k in fresh)}
            unknown = [_HEALTH_KEYS[name] for k, names in enumerate(_HEALTH_BLOCKS)
                       if k not in fresh for name in names if name in _HEALTH_KEYS]
            oldest = min(read_at.values()) if len(read_at) == len(_HEALTH_BLOCKS) else None
            errors: list[str] = []
            flags = v.get("hardware_error_status", latched.get(servo_id, 0))
            if flags:
                errors.append(f"hardware error: {hardware_error_text(flags)}")
            if servo_id in watchdog_expired:
                errors.append("bus watchdog expired")
            volts = v.get("present_input_voltage")
            torque = v.get("torque_enable")
            supply = self._voltage_range or tuple(
                round(f * model.nominal_voltage_v, 2) for f in SUPPLY_WARN)
            motors.append({
                "motor": servo_id,
                "joint": joint,
                "model": model.name,
                "firmware": self.firmware.get(servo_id),
                "mode": mode,
                "torque_enabled": None if torque is None else bool(torque),
                "temperature_c": v.get("present_temperature"),
                "voltage_v": None if volts is None else volts / 10.0,
                "voltage_range_v": list(supply),
                "moving": None if "moving" not in v else bool(v["moving"]),
                "moving_status": v.get("moving_status"),
                "age_s": None if oldest is None else round((now - oldest) / 1e9, 3),
                "stale": bool(unknown),
                "unknown": unknown,
                "errors": errors,
                "last_fault": last_fault.get(servo_id),
            })
        return motors
