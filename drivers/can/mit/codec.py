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

Damiao register protocol (Damiao motors only; AK motors have none over CAN). Requests go on
arbitration id ``0x7FF``, 8 bytes; the motor answers on its ``MST_ID`` (``master_id``) with
the same layout::

    byte 0        1        2        3    4..7
         id[7:0]  id[15:8] command  rid  value (little-endian uint32 or IEEE float32)

``command`` is ``0x33`` read (value bytes ignored; the reply carries the value), ``0x55``
write (the reply echoes the value written), ``0xAA`` store every register to flash (rid
``0x01``; only while disabled). A write takes effect at once but only in RAM: a power cycle
restores the stored (flash) values. :data:`DAMIAO_REGISTERS` lists the registers, their type
and whether they are writable. Register 9 (``TIMEOUT``, uint32, units of 50 us, 0 = off) is
the CAN communication timeout: an enabled motor that receives no frame for that long
disables itself (torque off) and reports state code ``0xD`` (communication lost) until the
error is cleared (``FB``). A register reply shares the state reply's arbitration id; it is
told apart by context (the host expects it after a request of its own).

Facts from the CubeMars AK-series manual (MIT mode section), the mini-cheetah motor-controller
firmware's CAN description and Damiao's DM-J4310 manual and register table; no code was copied.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final

__all__ = [
    "CLEAR_ERROR",
    "DAMIAO_REGISTERS",
    "DAMIAO_STATES",
    "DAMIAO_TIMEOUT_RID",
    "DAMIAO_TIMEOUT_UNIT_S",
    "ENTER_MOTOR_MODE",
    "EXIT_MOTOR_MODE",
    "MODEL_PRESETS",
    "REGISTER_ID",
    "REGISTER_READ",
    "REGISTER_STORE",
    "REGISTER_WRITE",
    "REPLY_FORMATS",
    "SET_ZERO",
    "SPECIAL_COMMANDS",
    "CommandEncoder",
    "DamiaoRegister",
    "MitCommand",
    "MitLimits",
    "MitReply",
    "RegisterFrame",
    "decode_command",
    "decode_register_frame",
    "decode_reply",
    "encode_command",
    "encode_register_frame",
    "encode_reply",
    "float_to_uint",
    "quantum",
    "reply_motor_id",
    "special_command",
    "timeout_register_value",
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


class CommandEncoder:
    """:func:`encode_command` for one motor's ranges, from five floats: the same bytes, with
    the ranges' constants taken once and no :class:`MitCommand` built (the driver encodes a
    set-point per motor every cycle: 1.6 against 2.7 us of CPU an encoding).

    The arithmetic is :func:`float_to_uint`'s, operation for operation, so each field rounds
    exactly as there.
    """

    __slots__ = ("_p", "_v", "_kp", "_kd", "_t")

    def __init__(self, limits: MitLimits) -> None:
        def field(lo: float, hi: float, bits: int) -> tuple[float, float, int, float]:
            return (lo, hi, (1 << bits) - 1, hi - lo)

        self._p = field(-limits.p_max, limits.p_max, _P_BITS)
        self._v = field(-limits.v_max, limits.v_max, _V_BITS)
        self._kp = field(0.0, limits.kp_max, _K_BITS)
        self._kd = field(0.0, limits.kd_max, _K_BITS)
        self._t = field(-limits.t_max, limits.t_max, _T_BITS)

    def __call__(self, position: float, velocity: float, kp: float, kd: float,
                 torque: float) -> bytes:
        """The 8-byte command (values clamped to the ranges).

        Raises:
            ValueError: a value is NaN.
        """
        p = _fixed(position, *self._p)
        v = _fixed(velocity, *self._v)
        k = _fixed(kp, *self._kp)
        d = _fixed(kd, *self._kd)
        t = _fixed(torque, *self._t)
        data = bytes((
            p >> 8, p & 0xFF,
            v >> 4, ((v & 0xF) << 4) | (k >> 8),
            k & 0xFF,
            d >> 4, ((d & 0xF) << 4) | (t >> 8),
            t & 0xFF,
        ))
        if data in SPECIAL_COMMANDS:
            data = data[:7] + b"\xfa"  # as encode_command
        return data


def _fixed(x: float, lo: float, hi: float, top: int, span: float) -> int:
    """:func:`float_to_uint` with the range's constants given (``span = hi - lo > 0``)."""
    if x <= lo:
        return 0
    if x >= hi:
        return top
    if x != x:
        raise ValueError("cannot encode NaN")
    u = int((x - lo) * top / span + 0.5)
    return u if u < top else top


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


# --------------------------------------------------------------------------------------------
# Damiao register protocol
# --------------------------------------------------------------------------------------------

REGISTER_ID: Final = 0x7FF
"""Arbitration id of Damiao register requests (read / write / store)."""
REGISTER_READ: Final = 0x33
REGISTER_WRITE: Final = 0x55
REGISTER_STORE: Final = 0xAA
_REGISTER_COMMANDS: Final = (REGISTER_READ, REGISTER_WRITE, REGISTER_STORE)

DAMIAO_TIMEOUT_RID: Final = 9
"""The CAN timeout register (``TIMEOUT``): uint32, units of :data:`DAMIAO_TIMEOUT_UNIT_S`."""
DAMIAO_TIMEOUT_UNIT_S: Final = 50e-6
"""One count of the CAN timeout register, s (0 counts: no timeout)."""


@dataclass(frozen=True)
class DamiaoRegister:
    """One Damiao register: id, name, value type (``"u32"`` or ``"f32"``), writable."""

    rid: int
    name: str
    kind: str
    writable: bool


def _registers(*rows: tuple[int, str, str, bool]) -> Mapping[int, DamiaoRegister]:
    return MappingProxyType({rid: DamiaoRegister(rid, name, kind, rw)
                             for rid, name, kind, rw in rows})


DAMIAO_REGISTERS: Final[Mapping[int, DamiaoRegister]] = _registers(
    (0, "UV_Value", "f32", True), (1, "KT_Value", "f32", True), (2, "OT_Value", "f32", True),
    (3, "OC_Value", "f32", True), (4, "ACC", "f32", True), (5, "DEC", "f32", True),
    (6, "MAX_SPD", "f32", True), (7, "MST_ID", "u32", True), (8, "ESC_ID", "u32", True),
    (9, "TIMEOUT", "u32", True), (10, "CTRL_MODE", "u32", True),
    (11, "Damp", "f32", False), (12, "Inertia", "f32", False), (13, "hw_ver", "u32", False),
    (14, "sw_ver", "u32", False), (15, "SN", "u32", False), (16, "NPP", "u32", False),
    (17, "Rs", "f32", False), (18, "Ls", "f32", False), (19, "Flux", "f32", False),
    (20, "Gr", "f32", False), (21, "PMAX", "f32", True), (22, "VMAX", "f32", True),
    (23, "TMAX", "f32", True), (24, "I_BW", "f32", True), (25, "KP_ASR", "f32", True),
    (26, "KI_ASR", "f32", True), (27, "KP_APR", "f32", True), (28, "KI_APR", "f32", True),
    (29, "OV_Value", "f32", True), (30, "GREF", "f32", True), (31, "Deta", "f32", True),
    (32, "V_BW", "f32", True), (33, "IQ_c1", "f32", True), (34, "VL_c1", "f32", True),
    (35, "can_br", "u32", True), (36, "sub_ver", "u32", False),
    (50, "u_off", "f32", False), (51, "v_off", "f32", False), (52, "k1", "f32", False),
    (53, "k2", "f32", False), (54, "m_off", "f32", False), (55, "dir", "f32", False),
    (80, "p_m", "f32", False), (81, "xout", "f32", False),
)
"""The Damiao register table (id -> name, type, writable), from the manufacturer's list."""


@dataclass(frozen=True)
class RegisterFrame:
    """A Damiao register request or reply (the two share one layout).

    Attributes:
        motor_id: the motor's CAN id (``ESC_ID``), bytes 0..1.
        command: :data:`REGISTER_READ`, :data:`REGISTER_WRITE` or :data:`REGISTER_STORE`.
        rid: the register id (store: ``0x01``).
        value: the value bytes 4..7 decoded per the register's type (an unknown register as
            uint32); 0 in a read request or a store.
    """

    motor_id: int
    command: int
    rid: int
    value: int | float = 0


def _register_kind(rid: int) -> str:
    known = DAMIAO_REGISTERS.get(rid)
    return known.kind if known is not None else "u32"


def encode_register_frame(frame: RegisterFrame) -> bytes:
    """The 8 bytes of a register request or reply.

    Raises:
        ValueError: a motor id beyond 0x7FF, an unknown command, a rid beyond a byte, or a
            value that does not fit the register's type (uint32: 0..2**32-1; float32: finite).
    """
    if not 0 <= frame.motor_id <= 0x7FF:
        raise ValueError(f"motor id {frame.motor_id} out of range 0..0x7FF")
    if frame.command not in _REGISTER_COMMANDS:
        raise ValueError(f"register command must be 0x33, 0x55 or 0xAA, got {frame.command:#x}")
    if not 0 <= frame.rid <= 0xFF:
        raise ValueError(f"register id {frame.rid} does not fit a byte")
    if _register_kind(frame.rid) == "f32":
        value = float(frame.value)
        if not math.isfinite(value):
            raise ValueError(f"register {frame.rid} takes a finite float, got {value!r}")
        body = struct.pack("<f", value)
    else:
        if not (isinstance(frame.value, int) and 0 <= frame.value <= 0xFFFF_FFFF):
            raise ValueError(f"register {frame.rid} takes a uint32, got {frame.value!r}")
        body = struct.pack("<I", frame.value)
    return bytes((frame.motor_id & 0xFF, frame.motor_id >> 8, frame.command, frame.rid)) + body


def decode_register_frame(data: bytes | bytearray) -> RegisterFrame:
    """Decode a register request or reply.

    Raises:
        ValueError: not 8 bytes, or byte 2 is not a register command.
    """
    if len(data) != 8:
        raise ValueError(f"a register frame has 8 bytes, got {len(data)}")
    if data[2] not in _REGISTER_COMMANDS:
        raise ValueError(f"byte 2 ({data[2]:#04x}) is not a register command (0x33/0x55/0xAA)")
    rid = data[3]
    raw = bytes(data[4:8])
    value: int | float = (struct.unpack("<f", raw)[0] if _register_kind(rid) == "f32"
                          else struct.unpack("<I", raw)[0])
    return RegisterFrame(data[0] | (data[1] << 8), data[2], rid, value)


def timeout_register_value(timeout_s: float) -> int:
    """The ``TIMEOUT`` register value for ``timeout_s`` (rounded to 50 us; 0: no timeout).

    Raises:
        ValueError: negative, not finite, or beyond the register's range.
    """
    if not (math.isfinite(timeout_s) and timeout_s >= 0.0):
        raise ValueError(f"timeout must be finite and >= 0 s, got {timeout_s!r}")
    counts = round(timeout_s / DAMIAO_TIMEOUT_UNIT_S)
    if counts > 0xFFFF_FFFF:
        raise ValueError(f"timeout {timeout_s} s is beyond the register's range")
    return counts
