"""MIT-mode CAN codec (mini-cheetah / CubeMars AK / Damiao DM): pure, no I/O.

Theory of operation
-------------------
A MIT-mode motor runs ``torque = kp * (p_des - p) + kd * (v_des - v) + t_ff`` itself; the host
sends the five set-points in one 8-byte frame on the motor's CAN id and the motor answers each
frame with its state. Values travel as unsigned fixed-point numbers spanning a range that
depends on the motor model (:class:`MitLimits`)::

    u = round((x - x_min) * (2**bits - 1) / (x_max - x_min))     x clamped to [x_min, x_max]
    x = u * (x_max - x_min) / (2**bits - 1) + x_min

(rounded to nearest, so decode(encode(x)) is within half a step; firmware that truncates is
within one step.) Ranges are symmetric for p, v, t (``-p_max..p_max``) and start at 0 for
kp, kd.

Command, 8 bytes, big-endian bit fields (p 16 bit, v/kp/kd/t 12 bit)::

    byte 0      1      2      3            4      5      6            7
         p[15:8] p[7:0] v[11:4] v[3:0]|kp[11:8] kp[7:0] kd[11:4] kd[3:0]|t[11:8] t[7:0]

Reply, format ``"ak"`` (mini-cheetah / CubeMars AK, 6 bytes; the motor id in byte 0)::

    byte 0   1       2      3        4               5
         id  p[15:8] p[7:0] v[11:4]  v[3:0]|t[11:8]  t[7:0]

Reply, format ``"damiao"`` (8 bytes): byte 0 is ``error_code << 4 | (id & 0x0F)``, bytes 1..5
as above, byte 6 the drive (MOSFET) temperature and byte 7 the rotor temperature, degC.
Damiao state codes: 0 disabled, 1 enabled, 8 over-voltage, 9 under-voltage, 0xA
over-current, 0xB MOSFET over-temperature, 0xC rotor over-temperature, 0xD communication
lost, 0xE overload. The ``"ak"`` reply carries no fault or temperature: a faulted AK motor
is seen only by its silence.

A set-point whose bytes equal a special command (every field at its maximum, torque within
four steps of it) is sent with the torque field 0xFFA instead, so it is never misread.

Special commands (8 bytes, ``FF FF FF FF FF FF FF xx``): ``FC`` enter motor mode, ``FD``
exit motor mode (torque off), ``FE`` set the current position as zero, ``FB`` clear the
error (Damiao). Motors answer special commands with a state reply too.

Facts from the CubeMars AK-series manual (MIT mode section), the mini-cheetah motor-controller
firmware's CAN description and Damiao's DM-J4310 manual; no code was copied.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final

__all__ = [
    "CLEAR_ERROR",
    "DAMIAO_STATES",
    "ENTER_MOTOR_MODE",
    "EXIT_MOTOR_MODE",
    "MODEL_PRESETS",
    "REPLY_FORMATS",
    "SET_ZERO",
    "SPECIAL_COMMANDS",
    "MitCommand",
    "MitLimits",
    "MitReply",
    "decode_command",
    "decode_reply",
    "encode_command",
    "encode_reply",
    "float_to_uint",
    "quantum",
    "reply_motor_id",
    "special_command",
    "uint_to_float",
]

ENTER_MOTOR_MODE: Final = bytes((0xFF,) * 7 + (0xFC,))
EXIT_MOTOR_MODE: Final = bytes((0xFF,) * 7 + (0xFD,))
SET_ZERO: Final = bytes((0xFF,) * 7 + (0xFE,))
CLEAR_ERROR: Final = bytes((0xFF,) * 7 + (0xFB,))
SPECIAL_COMMANDS: Final[Mapping[bytes, str]] = MappingProxyType({
    ENTER_MOTOR_MODE: "enter",
    EXIT_MOTOR_MODE: "exit",
    SET_ZERO: "zero",
    CLEAR_ERROR: "clear_error",
})
"""Special command payload -> its name."""

REPLY_FORMATS: Final = ("ak", "damiao")

DAMIAO_STATES: Final[Mapping[int, str]] = MappingProxyType({
    0x0: "disabled",
    0x1: "enabled",
    0x8: "over-voltage",
    0x9: "under-voltage",
    0xA: "over-current",
    0xB: "drive (MOSFET) over-temperature",
    0xC: "rotor over-temperature",
    0xD: "communication lost",
    0xE: "overload",
})
"""Damiao reply state codes (byte 0, high nibble); 8 and above are faults."""

_P_BITS, _V_BITS, _K_BITS, _T_BITS = 16, 12, 12, 12


@dataclass(frozen=True)
class MitLimits:
    """Value ranges of one motor model (output shaft, SI units).

    Attributes:
        p_max: position range is ``[-p_max, p_max]``, rad.
        v_max: velocity range ``[-v_max, v_max]``, rad/s.
        t_max: torque range ``[-t_max, t_max]``, N*m.
        kp_max: kp range ``[0, kp_max]``, N*m/rad.
        kd_max: kd range ``[0, kd_max]``, N*m*s/rad.
        reply: reply format, ``"ak"`` (6 bytes) or ``"damiao"`` (8 bytes).
    """

    p_max: float
    v_max: float
    t_max: float
    kp_max: float = 500.0
    kd_max: float = 5.0
    reply: str = "ak"

    def __post_init__(self) -> None:
        for name in ("p_max", "v_max", "t_max", "kp_max", "kd_max"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"MitLimits.{name} must be finite and > 0, got {value!r}")
        if self.reply not in REPLY_FORMATS:
            raise ValueError(f"MitLimits.reply must be one of {REPLY_FORMATS}, got {self.reply!r}")


MODEL_PRESETS: Final[Mapping[str, MitLimits]] = MappingProxyType({
    "AK80-9": MitLimits(p_max=12.5, v_max=50.0, t_max=18.0),
    "AK60-6": MitLimits(p_max=12.5, v_max=45.0, t_max=15.0),
    "AK70-10": MitLimits(p_max=12.5, v_max=50.0, t_max=25.0),
    "AK10-9": MitLimits(p_max=12.5, v_max=50.0, t_max=65.0),
    "DM4310": MitLimits(p_max=12.5, v_max=30.0, t_max=10.0, reply="damiao"),
})
"""MIT ranges of common models (manufacturer defaults; Damiao's are configurable on the motor
and must match the config)."""


@dataclass(frozen=True)
class MitCommand:
    """One MIT set-point (SI units): position, velocity, kp, kd, feed-forward torque."""

    position: float
    velocity: float
    kp: float
    kd: float
    torque: float


@dataclass(frozen=True)
class MitReply:
    """One state reply.

    Attributes:
        motor_id: the id in byte 0 (the low nibble for Damiao).
        position: rad. velocity: rad/s. torque: N*m.
        error_code: Damiao state code (``None`` for AK replies).
        temperature: Damiao drive temperature, degC (``None`` for AK).
        rotor_temperature: Damiao rotor temperature, degC (``None`` for AK).
    """

    motor_id: int
    position: float
    velocity: float
    torque: float
    error_code: int | None = None
    temperature: int | None = None
    rotor_temperature: int | None = None


def float_to_uint(x: float, x_min: float, x_max: float, bits: int) -> int:
    """Fixed-point encode ``x`` (clamped to ``[x_min, x_max]``) on ``bits`` bits.

    Raises:
        ValueError: ``x`` is NaN, or the range is empty.
    """
    if math.isnan(x):
        raise ValueError("cannot encode NaN")
    if not x_max > x_min:
        raise ValueError(f"empty range [{x_min}, {x_max}]")
    top = (1 << bits) - 1
    if x <= x_min:
        return 0
    if x >= x_max:
        return top
    # Non-negative here, so int() truncation of (v + 0.5) rounds to nearest.
    return min(top, int((x - x_min) * top / (x_max - x_min) + 0.5))


def uint_to_float(u: int, x_min: float, x_max: float, bits: int) -> float:
    """Fixed-point decode (see :func:`float_to_uint`)."""
    return u * (x_max - x_min) / ((1 << bits) - 1) + x_min


def quantum(limits: MitLimits) -> MitCommand:
    """One quantisation step of each field (the resolution of the model's ranges)."""
    return MitCommand(
        2 * limits.p_max / ((1 << _P_BITS) - 1),
        2 * limits.v_max / ((1 << _V_BITS) - 1),
        limits.kp_max / ((1 << _K_BITS) - 1),
        limits.kd_max / ((1 << _K_BITS) - 1),
        2 * limits.t_max / ((1 << _T_BITS) - 1),
    )


def encode_command(cmd: MitCommand, limits: MitLimits) -> bytes:
    """The 8-byte MIT command (values clamped to the model's ranges).

    Raises:
        ValueError: a field is NaN.
    """
    p = float_to_uint(cmd.position, -limits.p_max, limits.p_max, _P_BITS)
    v = float_to_uint(cmd.velocity, -limits.v_max, limits.v_max, _V_BITS)
    kp = float_to_uint(cmd.kp, 0.0, limits.kp_max, _K_BITS)
    kd = float_to_uint(cmd.kd, 0.0, limits.kd_max, _K_BITS)
    t = float_to_uint(cmd.torque, -limits.t_max, limits.t_max, _T_BITS)
    data = bytes((
        p >> 8, p & 0xFF,
        v >> 4, ((v & 0xF) << 4) | (kp >> 8),
        kp & 0xFF,
        kd >> 4, ((kd & 0xF) << 4) | (t >> 8),
        t & 0xFF,
    ))
    if data in SPECIAL_COMMANDS:
        # Every field at its maximum and t within 4 steps of it would read as a special
        # command: send t = 0xFFA instead (at most 5 steps lower, at the torque limit).
        data = data[:7] + b"\xfa"
    return data


def decode_command(data: bytes | bytearray, limits: MitLimits) -> MitCommand:
    """Decode an 8-byte MIT command (the emulator's side).

    Raises:
        ValueError: not 8 bytes, or a special command (check :func:`special_command` first).
    """
    if len(data) != 8:
        raise ValueError(f"a MIT command has 8 bytes, got {len(data)}")
    if bytes(data) in SPECIAL_COMMANDS:
        raise ValueError(f"{bytes(data).hex()} is a special command, not a set-point")
    p = (data[0] << 8) | data[1]
    v = (data[2] << 4) | (data[3] >> 4)
    kp = ((data[3] & 0xF) << 8) | data[4]
    kd = (data[5] << 4) | (data[6] >> 4)
    t = ((data[6] & 0xF) << 8) | data[7]
    return MitCommand(
        uint_to_float(p, -limits.p_max, limits.p_max, _P_BITS),
        uint_to_float(v, -limits.v_max, limits.v_max, _V_BITS),
        uint_to_float(kp, 0.0, limits.kp_max, _K_BITS),
        uint_to_float(kd, 0.0, limits.kd_max, _K_BITS),
        uint_to_float(t, -limits.t_max, limits.t_max, _T_BITS),
    )


def special_command(data: bytes | bytearray) -> str | None:
    """``"enter"``, ``"exit"``, ``"zero"``, ``"clear_error"`` or ``None`` (a set-point)."""
    return SPECIAL_COMMANDS.get(bytes(data))


def encode_reply(reply: MitReply, limits: MitLimits) -> bytes:
    """The state reply in the model's format (6 bytes ``ak``, 8 bytes ``damiao``).

    Raises:
        ValueError: a value is NaN, or the id does not fit the format.
    """
    p = float_to_uint(reply.position, -limits.p_max, limits.p_max, _P_BITS)
    v = float_to_uint(reply.velocity, -limits.v_max, limits.v_max, _V_BITS)
    t = float_to_uint(reply.torque, -limits.t_max, limits.t_max, _T_BITS)
    body = (p >> 8, p & 0xFF, v >> 4, ((v & 0xF) << 4) | (t >> 8), t & 0xFF)
    if limits.reply == "ak":
        if not 0 <= reply.motor_id <= 0xFF:
            raise ValueError(f"motor id {reply.motor_id} does not fit a byte")
        return bytes((reply.motor_id, *body))
    if not 0 <= reply.motor_id <= 0x0F:
        raise ValueError(f"Damiao replies carry ids 0..15, got {reply.motor_id}")
    code = 1 if reply.error_code is None else reply.error_code & 0x0F
    temps = (
        _byte(reply.temperature),
        _byte(reply.rotor_temperature),
    )
    return bytes(((code << 4) | reply.motor_id, *body, *temps))


def _byte(value: int | None) -> int:
    return 0 if value is None else min(255, max(0, int(value)))


def reply_motor_id(data: bytes | bytearray, reply_format: str) -> int | None:
    """The motor id of a reply, or ``None`` when ``data`` is not a reply of that format."""
    if reply_format == "ak":
        return data[0] if len(data) == 6 else None
    return data[0] & 0x0F if len(data) == 8 else None


def decode_reply(data: bytes | bytearray, limits: MitLimits) -> MitReply:
    """Decode a state reply in the model's format.

    Raises:
        ValueError: wrong length for the format.
    """
    want = 6 if limits.reply == "ak" else 8
    if len(data) != want:
        raise ValueError(f"a {limits.reply!r} MIT reply has {want} bytes, got {len(data)}")
    p = (data[1] << 8) | data[2]
    v = (data[3] << 4) | (data[4] >> 4)
    t = ((data[4] & 0xF) << 8) | data[5]
    position = uint_to_float(p, -limits.p_max, limits.p_max, _P_BITS)
    velocity = uint_to_float(v, -limits.v_max, limits.v_max, _V_BITS)
    torque = uint_to_float(t, -limits.t_max, limits.t_max, _T_BITS)
    if limits.reply == "ak":
        return MitReply(data[0], position, velocity, torque)
    return MitReply(data[0] & 0x0F, position, velocity, torque,
                    error_code=data[0] >> 4, temperature=data[6], rotor_temperature=data[7])
