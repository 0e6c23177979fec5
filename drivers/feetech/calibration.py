"""Calibration of Feetech servos as SO-101 owners do it: each joint's zero and range by hand.

Theory of operation
-------------------
``jtc-hw calibrate feetech`` (:mod:`jtc_hw.cli.calibrate`) runs what LeRobot's
``lerobot-calibrate`` asks of the user, through :class:`~.bus.FeetechBus`:

1. Every servo's torque goes off (Torque Enable 0), so the joints can be turned by hand.
2. **The middle.** The user puts the arm in the middle of its range and presses Enter:
   :func:`read_positions` reads each servo's Present Position there; that pose becomes joint 0.
   With ``--write-eeprom`` (:func:`write_homing_offsets`) each servo's Homing Offset is set so
   that this pose reads the middle step (2047 on a 4096-step servo, as LeRobot's half-turn
   homing does), through the EPROM lock (0 to open, written, 1 to close: register 55 on
   STS/SMS); otherwise nothing is written to the servos and the middle stays in the file's
   ``offset`` alone. SCS servos have no Homing Offset register.
3. **The ranges.** The user moves every joint through its whole range and presses Enter:
   :func:`record_ranges` reads the positions until then and keeps each joint's extremes.
4. :func:`joint_values` turns the middles and ranges into the hardware kind's ``offset``,
   ``direction`` and ``position_limits``, in its units (joint = direction * steps * rad_per_step
   / gear_ratio + offset; :mod:`.hardware`).

STS/SMS positions wrap at 4096 steps (single-turn). A reading is unwrapped to within half a turn
of the joint's middle, so a joint whose range crosses the wrap is still measured; but the
hardware maps steps 0..4095 linearly, so such a range cannot be expressed by ``offset`` alone:
:func:`joint_values` refuses it and says to run again with ``--write-eeprom``, which moves the
wrap half a turn away from the middle.

Direction cannot be seen by hand (a joint turned one way is not "positive" by itself): it is
the file's, or given.

:func:`from_lerobot` reads a LeRobot calibration JSON (the ``so101_follower`` form: per motor
name ``id``, ``drive_mode``, ``homing_offset``, ``range_min``, ``range_max``). LeRobot writes
``homing_offset`` into each servo's EEPROM at calibration, after which the middle pose reads
the middle step; the ranges are in those readings. So the import makes the middle step joint
0, ``drive_mode`` 1 a direction of -1, and needs no bus: it assumes the servos still hold
LeRobot's homing offsets.

Nothing here reads a clock: :func:`record_ranges` waits on the caller's event between reads.
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from jtc_hw.errors import ConfigurationError

from .codec import decode_value, encode_value
from .control_table import Model, Series

if TYPE_CHECKING:  # the SDK is optional: --from-lerobot needs neither it nor a bus
    from .bus import FeetechBus

__all__ = [
    "LEROBOT_KEYS",
    "MIN_TRAVEL_STEPS",
    "JointRange",
    "describe",
    "from_lerobot",
    "joint_values",
    "read_positions",
    "record_ranges",
    "torque_off",
    "write_homing_offsets",
]

MIN_TRAVEL_STEPS = 20
"""Least range (steps, about 1.8 degrees on an STS3215) that counts as a joint moved by hand:
less is a joint the user forgot, whose limits would pin it in place."""

LEROBOT_KEYS = ("id", "drive_mode", "homing_offset", "range_min", "range_max")
"""The fields of one motor in a LeRobot calibration JSON."""


@dataclasses.dataclass(frozen=True)
class JointRange:
    """What a calibration measured of one servo, in its Present Position steps.

    Attributes:
        servo_id: the servo.
        middle: the step at the middle pose (joint 0).
        low: the lowest step reached (unwrapped: may be below 0 if the range crosses the wrap).
        high: the highest step reached (unwrapped: may exceed the last step likewise).
    """

    servo_id: int
    middle: int
    low: int
    high: int


def _write(bus: FeetechBus, servo_id: int, name: str, value: int) -> None:
    reg = bus.series.register(name)
    bus.write_bytes(servo_id, reg.address, encode_value(reg, value, bus.series.byte_order))


def _read(bus: FeetechBus, servo_id: int, name: str) -> int:
    reg = bus.series.register(name)
    data = bus.read_bytes(servo_id, reg.address, reg.size)
    return decode_value(reg, data, bus.series.byte_order)


def torque_off(bus: FeetechBus, ids: Sequence[int]) -> None:
    """Switch every servo's torque off, so that its joint turns by hand.

    Raises:
        ServoCommunicationError: a servo did not answer (the message names it).
    """
    for servo_id in ids:
        _write(bus, servo_id, "torque_enable", 0)


def read_positions(bus: FeetechBus, ids: Sequence[int]) -> dict[int, int]:
    """Each servo's Present Position, steps (one group read).

    Raises:
        ServoCommunicationError: a servo did not answer (the message names it).
    """
    reg = bus.series.register("present_position")
    result = bus.group_read(ids, reg.address, reg.size)
    order = bus.series.byte_order
    return {i: decode_value(reg, result.data[i], order) for i in ids}


def write_homing_offsets(bus: FeetechBus, middles: Mapping[int, int], model: Model) -> dict[
        int, int]:
    """Store each servo's Homing Offset in its EEPROM so that the pose it stands in now, which
    reads ``middles[id]``, reads the middle step; the offsets written.

    Each write is bracketed by the EPROM lock (0: open, then 1: closed again), also when a write
    fails, so that nothing else stays writable.

    Raises:
        ConfigurationError: the series has no Homing Offset register (SCS).
        ServoCommunicationError: a servo did not answer (the message names it).
    """
    series: Series = bus.series
    if "homing_offset" not in series.registers:
        raise ConfigurationError(
            f"{model.name} servos have no Homing Offset register: calibrate without "
            "--write-eeprom (the middle is kept in the file's offset)")
    turn = model.position_max + 1
    centre = model.position_max // 2
    magnitude = series.register("homing_offset").limits[1]
    written: dict[int, int] = {}
    for servo_id, middle in middles.items():
        current = _read(bus, servo_id, "homing_offset")
        # Present = shaft - offset (wrapped): the new offset moves this pose to the centre.
        offset = (current + middle - centre + turn // 2) % turn - turn // 2
        offset = max(-magnitude, min(magnitude, offset))
        _write(bus, servo_id, series.lock_register, 0)
        try:
            _write(bus, servo_id, "homing_offset", offset)
        finally:
            _write(bus, servo_id, series.lock_register, 1)
        written[servo_id] = offset
    return written


def record_ranges(
    bus: FeetechBus,
    middles: Mapping[int, int],
    model: Model,
    stop: threading.Event,
    period_s: float = 0.02,
    on_sample: Callable[[Mapping[int, JointRange]], None] | None = None,
) -> dict[int, JointRange]:
    """Read the positions every ``period_s`` until ``stop`` is set (the user pressed Enter);
    each servo's range, unwrapped to within half a turn of its middle (STS/SMS).

    ``on_sample`` is called after every read with the ranges so far (a live display; a test
    that plays the user's hand waits on it).

    Raises:
        ServoCommunicationError: a servo did not answer (the message names it).
    """
    ids = list(middles)
    turn = model.position_max + 1
    wraps = bus.series.sync_read  # STS/SMS are single-turn and wrap; SCS stops at its ends
    ranges = {i: JointRange(i, m, m, m) for i, m in middles.items()}
    while True:
        for servo_id, steps in read_positions(bus, ids).items():
            r = ranges[servo_id]
            if wraps:
                steps = r.middle + (steps - r.middle + turn // 2) % turn - turn // 2
            if steps < r.low or steps > r.high:
                ranges[servo_id] = dataclasses.replace(r, low=min(r.low, steps),
                                                       high=max(r.high, steps))
        if on_sample is not None:
            on_sample(dict(ranges))
        if stop.wait(period_s):
            return ranges


def joint_values(
    joints: Sequence[str],
    ranges: Sequence[JointRange],
    model: Model,
    directions: Sequence[int],
    gear_ratios: Sequence[float],
    margin_rad: float = 0.0,
) -> dict[str, list[Any]]:
    """The hardware's ``offset``, ``direction`` and ``position_limits`` (one entry per joint)
    from measured ranges: the middle is joint 0, the limits are the range inset by
    ``margin_rad`` at each end (so that a goal at a limit does not push against the stop).

    Raises:
        ConfigurationError: a joint did not move (less than :data:`MIN_TRAVEL_STEPS`), or its
            range crosses the servo's wrap (the message says what to do).
    """
    still = [f"{j} (servo {r.servo_id})" for j, r in zip(joints, ranges, strict=True)
             if r.high - r.low < MIN_TRAVEL_STEPS]
    if still:
        raise ConfigurationError(
            f"{', '.join(still)} did not move during the range step: move every joint by hand "
            "from one end of its travel to the other before pressing Enter")
    offsets, limits = [], []
    for joint, r, d, g in zip(joints, ranges, directions, gear_ratios, strict=True):
        if r.low < 0 or r.high > model.position_max:
            raise ConfigurationError(
                f"{joint} (servo {r.servo_id}): its range, steps {r.low}..{r.high}, crosses "
                f"the servo's wrap between {model.position_max} and 0, which an offset in the "
                "file cannot undo; run the calibration again with --write-eeprom (it stores a "
                "homing offset in the servo that puts the middle pose at the middle step)")
        scale = d * model.rad_per_step / g
        offsets.append(-r.middle * scale)
        ends = sorted(((r.low - r.middle) * scale, (r.high - r.middle) * scale))
        inset = min(margin_rad, (ends[1] - ends[0]) / 4.0)
        limits.append([ends[0] + inset, ends[1] - inset])
    return {"offset": offsets, "direction": list(directions), "position_limits": limits}


def from_lerobot(
    text: str, name: str, joints: Sequence[str], ids: Sequence[int] | None, model: Model,
    gear_ratios: Sequence[float], margin_rad: float = 0.0,
) -> dict[str, list[Any]]:
    """``offset``, ``direction`` and ``position_limits`` for ``joints`` from a LeRobot
    calibration JSON (see the module docstring), whose motors are named as the joints.

    Raises:
        ConfigurationError: not that JSON form, a joint it lacks, or an id that differs from the
            file's ``ids``.
    """
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigurationError(f"{name}: not JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigurationError(f"{name}: expected LeRobot's calibration object (motor name -> "
                                 "{id, drive_mode, homing_offset, range_min, range_max})")
    middle = model.position_max // 2
    ranges, directions = [], []
    for k, joint in enumerate(joints):
        motor = data.get(joint)
        if not isinstance(motor, dict) or any(
                not isinstance(motor.get(key), int) for key in LEROBOT_KEYS):
            raise ConfigurationError(
                f"{name}: no motor {joint!r} with integer {', '.join(LEROBOT_KEYS)} (its motors: "
                f"{', '.join(map(str, data)) or 'none'}); LeRobot names the SO-101's motors as "
                "the joints of config/so101-follower.yaml")
        if ids is not None and motor["id"] != ids[k]:
            raise ConfigurationError(
                f"{name}: motor {joint!r} is servo {motor['id']} there but servo {ids[k]} in the "
                "robot file's ids; fix whichever is wrong")
        directions.append(-1 if motor["drive_mode"] else 1)
        ranges.append(JointRange(motor["id"], middle, motor["range_min"], motor["range_max"]))
    return joint_values(joints, ranges, model, directions, gear_ratios, margin_rad)


def describe(values: Mapping[str, Sequence[Any]], joints: Sequence[str]) -> list[str]:
    """One line per joint of what a calibration writes, in degrees beside radians."""
    lines = []
    for j, joint in enumerate(joints):
        lo, hi = values["position_limits"][j]
        lines.append(
            f"  {joint:<14} offset {values['offset'][j]:+.4f} rad  direction "
            f"{values['direction'][j]:+d}  limits [{lo:+.4f}, {hi:+.4f}] rad "
            f"([{math.degrees(lo):+.1f}, {math.degrees(hi):+.1f}] deg)")
    return lines
