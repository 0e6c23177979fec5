"""Feetech serial protocol codec and register arithmetic. No I/O.

Theory of operation
-------------------
Every packet on the bus, instruction or status, has one frame::

    FF FF | ID | LEN | INST or ERR | PARAMS... | CHECKSUM

``LEN`` counts the bytes after itself: the instruction (or error) byte, the parameters and the
checksum, so ``LEN = len(PARAMS) + 2``. ``CHECKSUM = ~(ID + LEN + INST + sum(PARAMS)) & 0xFF``
(the header is not summed). There is no byte stuffing: a :class:`Decoder` that lost sync skips
to the next ``FF FF`` whose length byte is plausible, and a frame with a bad checksum is
reported (``checksum_ok=False``) and resynchronised one byte later, so a corrupted length cannot
swallow the next packet. A status packet has the servo's id and the error byte (the
:class:`StatusError` bits) where an instruction has its instruction byte; nothing in the frame
itself says which of the two it is: the direction does (the host sends instructions, servos
answer with status packets), so :meth:`Decoder.feed` is told which it reads.

Instructions (parameters after the instruction byte; address and length are one byte each)::

    PING        01  -                                  answers an empty status
    READ        02  addr, n                            answers n data bytes
    WRITE       03  addr, data...                      answers an empty status
    REG_WRITE   04  addr, data...                      held until ACTION
    ACTION      05  -                                  (usually broadcast: no answer)
    SYNC_READ   82  addr, n, id1, id2, ...             broadcast; each id answers in turn
    SYNC_WRITE  83  addr, n, id1, data1(n), id2, ...   broadcast: no answer

The broadcast id is 0xFE; 0..0xFD address one servo (the SDK's ``MAX_ID`` is 0xFC). A servo
answers a broadcast only for SYNC_READ (STS/SMS; SCS servos do not know SYNC_READ) and for a
broadcast PING (STS/SMS).

Register values (:func:`encode_value` / :func:`decode_value`): a word is packed in the series'
byte order (:class:`.control_table.ByteOrder`), and a register with a ``sign_bit`` holds
sign-magnitude (``-5`` with sign bit 15 is ``0x8005``; ``0x8000`` is ``-0`` and decodes to 0).
The joint conversions (:class:`JointScale`) turn steps, speed counts and load counts into joint
radians, rad/s and a signed fraction of full load.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum, IntFlag

from ..framing import StreamBuffer
from .control_table import ByteOrder, Model, Register

__all__ = [
    "BROADCAST_ID",
    "HEADER",
    "MAX_PACKET_LENGTH",
    "Decoder",
    "Instruction",
    "JointScale",
    "Packet",
    "StatusError",
    "checksum",
    "decode_sign_magnitude",
    "decode_value",
    "encode_action",
    "encode_instruction",
    "encode_ping",
    "encode_read",
    "encode_reg_write",
    "encode_sign_magnitude",
    "encode_status",
    "encode_sync_read",
    "encode_sync_write",
    "encode_value",
    "encode_write",
    "pack_word",
    "parse_read",
    "parse_sync_read",
    "parse_sync_write",
    "parse_write",
    "status_error_text",
    "unpack_word",
]

HEADER = b"\xff\xff"
BROADCAST_ID = 0xFE
#: The SDK's largest packet (TXPACKET_MAX_LEN / RXPACKET_MAX_LEN), header to checksum.
MAX_PACKET_LENGTH = 250
_MAX_LEN_FIELD = MAX_PACKET_LENGTH - 4  # header 2, id 1, length 1


class Instruction(IntEnum):
    """Instruction byte values (the SDK's ``INST_*``)."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83


class StatusError(IntFlag):
    """Bits of a status packet's error byte, the same as the Status register (65).

    Bits 4, 6 and 7 are reserved; the SDK discards a status whose error byte exceeds 0x7F.
    """

    VOLTAGE = 0x01
    ANGLE = 0x02  # the position sensor (encoder / potentiometer)
    OVERHEAT = 0x04
    OVERCURRENT = 0x08
    OVERLOAD = 0x20


_ERROR_WORDS = {
    StatusError.VOLTAGE: "input voltage out of range",
    StatusError.ANGLE: "angle sensor error",
    StatusError.OVERHEAT: "overheating",
    StatusError.OVERCURRENT: "overcurrent",
    StatusError.OVERLOAD: "overload",
}


def status_error_text(error: int) -> str:
    """An error byte as words (``"overheating, overload"``; ``"no error"`` for 0)."""
    words = [text for bit, text in _ERROR_WORDS.items() if error & bit]
    unknown = error & ~sum(_ERROR_WORDS) & 0xFF
    if unknown:
        words.append(f"reserved bits 0x{unknown:02x}")
    return ", ".join(words) if words else "no error"


# -- register values ------------------------------------------------------------------------------


def encode_sign_magnitude(value: int, sign_bit: int) -> int:
    """``value`` as sign-magnitude with the sign in bit ``sign_bit`` (0 encodes as 0).

    Raises:
        ValueError: ``|value|`` does not fit the ``sign_bit`` bits below the sign.
    """
    magnitude = abs(int(value))
    if magnitude >> sign_bit:
        raise ValueError(f"{value} does not fit sign-magnitude with the sign in bit {sign_bit}")
    return magnitude | (1 << sign_bit) if value < 0 else magnitude


def decode_sign_magnitude(raw: int, sign_bit: int) -> int:
    """The value of sign-magnitude ``raw`` (bits above ``sign_bit`` are ignored; -0 is 0)."""
    magnitude = raw & ((1 << sign_bit) - 1)
    return -magnitude if raw >> sign_bit & 1 else magnitude


def pack_word(value: int, size: int, order: ByteOrder) -> bytes:
    """The ``size`` (1, 2 or 4) bytes of unsigned ``value`` as the SDK lays them out.

    A 4-byte value is two words, low word first, each word in ``order`` (the SDK's
    ``SCS_LOBYTE(SCS_LOWORD(v)), SCS_HIBYTE(SCS_LOWORD(v)), ...``).

    Raises:
        ValueError: ``value`` is negative or does not fit ``size`` bytes, or a bad ``size``.
    """
    if size not in (1, 2, 4):
        raise ValueError(f"a word is 1, 2 or 4 bytes, not {size}")
    if not 0 <= value < 1 << (8 * size):
        raise ValueError(f"{value} does not fit {size} unsigned bytes")
    if size == 4:
        return pack_word(value & 0xFFFF, 2, order) + pack_word(value >> 16, 2, order)
    return int(value).to_bytes(size, "little" if order is ByteOrder.LITTLE else "big")


def unpack_word(data: bytes | bytearray | memoryview, order: ByteOrder) -> int:
    """The unsigned value of 1, 2 or 4 bytes packed by :func:`pack_word`.

    Raises:
        ValueError: ``data`` is not 1, 2 or 4 bytes long.
    """
    raw = bytes(data)
    if len(raw) == 4:
        return unpack_word(raw[:2], order) | unpack_word(raw[2:], order) << 16
    if len(raw) not in (1, 2):
        raise ValueError(f"a word is 1, 2 or 4 bytes, not {len(raw)}")
    return int.from_bytes(raw, "little" if order is ByteOrder.LITTLE else "big")


def encode_value(register: Register, value: int, order: ByteOrder) -> bytes:
    """The bytes of ``value`` in ``register`` (sign-magnitude where it has a sign bit).

    Raises:
        ValueError: ``value`` is outside :attr:`Register.limits`.
    """
    low, high = register.limits
    if not low <= value <= high:
        raise ValueError(f"{value} is outside register {register.name}'s {low}..{high}")
    raw = value if register.sign_bit is None else encode_sign_magnitude(value, register.sign_bit)
    return pack_word(raw, register.size, order)


def decode_value(register: Register, data: bytes | bytearray | memoryview,
                 order: ByteOrder) -> int:
    """The value ``register`` holds in ``data`` (exactly ``register.size`` bytes).

    Raises:
        ValueError: ``data`` has the wrong length.
    """
    if len(data) != register.size:
        raise ValueError(f"register {register.name} is {register.size} bytes, got {len(data)}")
    raw = unpack_word(data, order)
    return raw if register.sign_bit is None else decode_sign_magnitude(raw, register.sign_bit)


# -- joint units ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class JointScale:
    """One joint's conversions between register counts and joint units.

    With ``r`` = :attr:`.Model.rad_per_step`, ``d`` = direction, ``g`` = gear (servo turns per
    joint turn) and ``o`` = offset (the joint angle at step 0)::

        joint     = d * steps * r / g + o          steps = round(d * (joint - o) * g / r)
        joint_vel = d * counts * speed_unit / g    counts = round(d * joint_vel * g / speed_unit)
        load      = d * counts / 1000              (a signed fraction of full load)

    The same factors are used both ways, so whole steps survive a round trip.

    Attributes:
        model: the servo model.
        direction: +1 or -1.
        gear: servo turns per joint turn (> 0; 1 when the servo drives the joint directly).
        offset: the joint's position at step 0, rad.
    """

    model: Model
    direction: int = 1
    gear: float = 1.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        if self.direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {self.direction}")
        if not (math.isfinite(self.gear) and self.gear > 0):
            raise ValueError(f"gear must be a positive number, got {self.gear}")
        if not math.isfinite(self.offset):
            raise ValueError(f"offset must be finite, got {self.offset}")

    def steps_to_rad(self, steps: float) -> float:
        """Position steps -> joint rad."""
        return self.direction * steps * self.model.rad_per_step / self.gear + self.offset

    def rad_to_steps(self, joint: float) -> int:
        """Joint rad -> position steps, rounded to the nearest step (not clamped to the servo's
        range: the caller checks :attr:`.Model.position_max`).

        Raises:
            ValueError: a non-finite angle.
        """
        if not math.isfinite(joint):
            raise ValueError(f"cannot convert a non-finite angle: {joint!r}")
        return round(self.direction * (joint - self.offset) * self.gear / self.model.rad_per_step)

    def speed_to_rad_s(self, counts: float) -> float:
        """Speed register counts -> joint rad/s."""
        return self.direction * counts * self.model.speed_unit_rad_s / self.gear

    def rad_s_to_speed(self, joint_vel: float) -> int:
        """Joint rad/s -> speed register counts, rounded.

        Raises:
            ValueError: a non-finite velocity.
        """
        if not math.isfinite(joint_vel):
            raise ValueError(f"cannot convert a non-finite velocity: {joint_vel!r}")
        return round(self.direction * joint_vel * self.gear / self.model.speed_unit_rad_s)

    def load_fraction(self, counts: int) -> float:
        """Present load counts (0.1 % each) -> a signed fraction of full load in joint
        direction (``-1 .. 1``)."""
        return self.direction * counts / 1000.0


# -- packets --------------------------------------------------------------------------------------


def checksum(body: bytes | bytearray | Iterable[int]) -> int:
    """The checksum of ``ID LEN INST/ERR PARAMS...``: the inverted low byte of their sum."""
    return ~sum(body) & 0xFF


def _frame(packet_id: int, code: int, params: bytes | bytearray) -> bytes:
    if not 0 <= packet_id <= BROADCAST_ID:
        raise ValueError(f"invalid Feetech id {packet_id} (0..253, 254 for broadcast)")
    if not 0 <= code <= 0xFF:
        raise ValueError(f"invalid instruction / error byte {code}")
    length = len(params) + 2
    if length > _MAX_LEN_FIELD:
        raise ValueError(f"packet too long ({length + 4} bytes; the SDK takes at most "
                         f"{MAX_PACKET_LENGTH})")
    body = bytes((packet_id, length, code)) + bytes(params)
    return HEADER + body + bytes((checksum(body),))


def encode_instruction(packet_id: int, instruction: int,
                       params: bytes | bytearray = b"") -> bytes:
    """An instruction packet with its checksum.

    Raises:
        ValueError: invalid id or instruction, or a packet longer than the SDK accepts.
    """
    return _frame(packet_id, instruction, params)


def encode_status(packet_id: int, error: int = 0, data: bytes | bytearray = b"") -> bytes:
    """A status packet (what a servo answers) with its checksum.

    Raises:
        ValueError: invalid id or error byte, or a packet too long.
    """
    if packet_id == BROADCAST_ID:
        raise ValueError("a status packet carries the answering servo's id, not broadcast")
    return _frame(packet_id, error, data)


def _byte(value: int, what: str) -> int:
    if not 0 <= value <= 0xFF:
        raise ValueError(f"{what} {value} does not fit one byte")
    return value


def encode_ping(packet_id: int) -> bytes:
    """PING ``packet_id`` (broadcast: every STS/SMS servo answers)."""
    return encode_instruction(packet_id, Instruction.PING)


def encode_read(packet_id: int, address: int, length: int) -> bytes:
    """READ ``length`` bytes from ``address`` of one servo."""
    params = bytes((_byte(address, "address"), _byte(length, "length")))
    return encode_instruction(packet_id, Instruction.READ, params)


def encode_write(packet_id: int, address: int, data: bytes | bytearray) -> bytes:
    """WRITE ``data`` at ``address`` (a register's bytes from :func:`encode_value`)."""
    return encode_instruction(packet_id, Instruction.WRITE,
                              bytes((_byte(address, "address"),)) + bytes(data))


def encode_reg_write(packet_id: int, address: int, data: bytes | bytearray) -> bytes:
    """REG_WRITE: like WRITE, but held by the servo until an ACTION."""
    return encode_instruction(packet_id, Instruction.REG_WRITE,
                              bytes((_byte(address, "address"),)) + bytes(data))


def encode_action(packet_id: int = BROADCAST_ID) -> bytes:
    """ACTION: apply the held REG_WRITEs (broadcast unless told otherwise)."""
    return encode_instruction(packet_id, Instruction.ACTION)


def _check_ids(ids: Iterable[int]) -> list[int]:
    checked = list(ids)
    for servo_id in checked:
        if not 0 <= servo_id < BROADCAST_ID:
            raise ValueError(f"invalid servo id {servo_id} in a group instruction (0..253)")
    if len(set(checked)) != len(checked):
        raise ValueError(f"duplicate ids in a group instruction: {checked}")
    return checked


def encode_sync_read(address: int, length: int, ids: Sequence[int]) -> bytes:
    """SYNC_READ ``length`` bytes at ``address`` from each of ``ids`` (STS/SMS only).

    Raises:
        ValueError: no ids, duplicates, ids out of range, or address / length beyond a byte.
    """
    checked = _check_ids(ids)
    if not checked:
        raise ValueError("a sync read needs at least one id")
    params = bytes((_byte(address, "address"), _byte(length, "length"), *checked))
    return encode_instruction(BROADCAST_ID, Instruction.SYNC_READ, params)


def encode_sync_write(address: int, length: int,
                      data: Mapping[int, bytes] | Sequence[tuple[int, bytes]]) -> bytes:
    """SYNC_WRITE the same ``length`` bytes at ``address`` of each servo: ``{id: bytes}``.

    Raises:
        ValueError: a chunk that is not ``length`` bytes, bad ids, or a packet too long.
    """
    items = list(data.items()) if isinstance(data, Mapping) else list(data)
    _check_ids(servo_id for servo_id, _ in items)
    params = bytearray((_byte(address, "address"), _byte(length, "length")))
    for servo_id, chunk in items:
        if len(chunk) != length:
            raise ValueError(f"sync write data for id {servo_id} is {len(chunk)} bytes, "
                             f"expected {length}")
        params.append(servo_id)
        params += chunk
    return encode_instruction(BROADCAST_ID, Instruction.SYNC_WRITE, params)


def parse_read(params: bytes) -> tuple[int, int]:
    """``(address, length)`` of READ parameters.

    Raises:
        ValueError: not exactly 2 parameter bytes.
    """
    if len(params) != 2:
        raise ValueError(f"a read has 2 parameter bytes, got {len(params)}")
    return params[0], params[1]


def parse_write(params: bytes) -> tuple[int, bytes]:
    """``(address, data)`` of WRITE / REG_WRITE parameters.

    Raises:
        ValueError: no data after the address.
    """
    if len(params) < 2:
        raise ValueError(f"a write has an address and data, got {len(params)} bytes")
    return params[0], bytes(params[1:])


def parse_sync_read(params: bytes) -> tuple[int, int, list[int]]:
    """``(address, length, ids)`` of SYNC_READ parameters.

    Raises:
        ValueError: fewer than 3 parameter bytes (no id).
    """
    if len(params) < 3:
        raise ValueError(f"a sync read has >= 3 parameter bytes, got {len(params)}")
    return params[0], params[1], list(params[2:])


def parse_sync_write(params: bytes) -> tuple[int, int, list[tuple[int, bytes]]]:
    """``(address, length, [(id, data), ...])`` of SYNC_WRITE parameters.

    Raises:
        ValueError: the records after address and length are not whole ``1 + length`` records.
    """
    if len(params) < 2:
        raise ValueError(f"a sync write has >= 2 parameter bytes, got {len(params)}")
    address, length = params[0], params[1]
    records = params[2:]
    step = length + 1
    if length == 0 or not records or len(records) % step:
        raise ValueError(f"sync write records of {len(records)} bytes are not whole "
                         f"{step}-byte records")
    return address, length, [
        (records[i], bytes(records[i + 1 : i + step])) for i in range(0, len(records), step)
    ]


@dataclass(frozen=True)
class Packet:
    """One decoded frame.

    Attributes:
        id: the packet's id.
        code: the instruction byte (instruction packets) or the error byte (status packets).
        params: the bytes between ``code`` and the checksum.
        checksum_ok: whether the checksum matched (if not, the other fields are unreliable).
        raw: the whole frame, header to checksum.
    """

    id: int
    code: int
    params: bytes
    checksum_ok: bool
    raw: bytes

    @property
    def error(self) -> StatusError:
        """A status packet's error bits."""
        return StatusError(self.code & 0x7F)


class Decoder(StreamBuffer):
    """Incremental frame decoder for one direction of the bus (see the module docstring).

    Args:
        status: ``True`` to read servo answers (the code byte is an error byte, ids up to 253,
            error bytes above 0x7F are junk as in the SDK), ``False`` to read instructions
            (ids up to 254).

    Attributes:
        checksum_errors: frames whose checksum did not match.
        junk_bytes: bytes skipped while looking for a frame.
    """

    def __init__(self, *, status: bool) -> None:
        super().__init__()
        self.status = status
        self.checksum_errors = 0

    def _plausible(self, buf: bytearray) -> bool:
        max_id = BROADCAST_ID - 1 if self.status else BROADCAST_ID
        if buf[2] > max_id or not 2 <= buf[3] <= _MAX_LEN_FIELD:
            return False
        return not (self.status and buf[4] > 0x7F)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        """Add received bytes; return the frames they complete, in order."""
        buf = self._buf
        buf += data
        found: list[Packet] = []
        while True:
            start = buf.find(HEADER)
            if start < 0:
                self._skip(len(buf) - (1 if buf[-1:] == b"\xff" else 0))
                return found
            self._skip(start)
            if len(buf) < 5:
                return found
            if not self._plausible(buf):
                self._skip(1)
                continue
            total = buf[3] + 4
            if len(buf) < total:
                return found
            frame = bytes(buf[:total])
            good = checksum(frame[2:-1]) == frame[-1]
            found.append(Packet(frame[2], frame[4], frame[5:-1], good, frame))
            if good:
                del buf[:total]
            else:
                self.checksum_errors += 1
                self._skip(1)
