"""Dynamixel Protocol 2.0 codec: packets, CRC, byte stuffing, group instructions. No I/O.

Theory of operation
-------------------
Every packet on the bus has the same frame (multi-byte fields little endian)::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | [ERR] PARAMS... | CRC_L CRC_H

``LEN`` counts the bytes after itself: instruction, (error,) parameters *as sent* (after
stuffing) and the two CRC bytes. An instruction packet carries ``INST`` and parameters; a status
packet carries ``INST = 0x55``, then the error byte, then its parameters. The CRC is the
e-Manual's CRC-16 (polynomial 0x8005, initial value 0, no reflection, no final xor) over every
byte from the header to the last parameter, computed on the stuffed bytes.

Byte stuffing keeps the header unique: in the instruction / error / parameter area every
``FF FF FD`` is followed by an extra ``FD`` on the wire; the receiver drops the ``FD`` after each
``FF FF FD``. A body therefore never contains ``FF FF FD 00``, so a :class:`Decoder` that lost
sync can resynchronise on the next header. The Fast Sync Read / Fast Bulk Read status packet is
the exception (the e-Manual says it is not stuffed); :func:`parse_fast_status` reads it from the
raw frame.

The :class:`Decoder` is incremental: :meth:`Decoder.feed` takes any chunk of bytes and returns the
complete packets found so far. It skips junk before a header, waits for split packets, and reports
a frame with a bad CRC as a :class:`Packet` with ``crc_ok=False`` (then resumes one byte later,
so a corrupted length field cannot swallow the next good packet).

Group instructions (Sync Read / Write, Bulk Read / Write, Fast Sync Read) have builders
(``encode_*``) and parameter parsers (``parse_*``); the Fast Sync Read status packet has
:func:`fast_status_parts` (the per-servo pieces, as each servo sends its own piece in turn) and
:func:`parse_fast_status`. The size helpers at the end give bytes on the wire for benchmarks.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum

from ..framing import StreamBuffer

__all__ = [
    "ALERT_BIT",
    "BROADCAST_ID",
    "HEADER",
    "MAX_ID",
    "STATUS_OVERHEAD",
    "BulkReadEntry",
    "Decoder",
    "ErrorNumber",
    "FastStatusEntry",
    "Instruction",
    "Packet",
    "bulk_read_cycle_bytes",
    "bulk_write_bytes",
    "crc16",
    "encode_bulk_read",
    "encode_bulk_write",
    "encode_fast_status",
    "encode_instruction",
    "encode_status",
    "encode_sync_read",
    "encode_sync_write",
    "error_text",
    "fast_status_parts",
    "packet_size",
    "parse_bulk_read",
    "parse_bulk_write",
    "parse_fast_status",
    "parse_sync_read",
    "parse_sync_write",
    "status_packet_size",
    "stuff",
    "sync_read_cycle_bytes",
    "sync_write_bytes",
    "unstuff",
    "wire_time_s",
]

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
#: Largest unicast id.
MAX_ID = 252
#: The error byte's "hardware alert" bit: the servo has a latched hardware error.
ALERT_BIT = 0x80
#: Bytes of a packet around its parameters: header 4, id 1, length 2, instruction 1, CRC 2.
PACKET_OVERHEAD = 10
#: Bytes of a status packet around its data (the packet overhead plus the error byte).
STATUS_OVERHEAD = 11
_PREFIX = 7  # header + id + length


class Instruction(IntEnum):
    """Instruction byte values."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93
    FAST_BULK_READ = 0x9A


class ErrorNumber(IntEnum):
    """The status packet's error number (the error byte without :data:`ALERT_BIT`)."""

    NONE = 0
    RESULT_FAIL = 1
    INSTRUCTION = 2
    CRC = 3
    DATA_RANGE = 4
    DATA_LENGTH = 5
    DATA_LIMIT = 6
    ACCESS = 7


_ERROR_TEXT = {
    ErrorNumber.NONE: "no error",
    ErrorNumber.RESULT_FAIL: "result fail (the instruction could not be processed)",
    ErrorNumber.INSTRUCTION: "instruction error (undefined instruction, or ACTION without "
    "REG_WRITE)",
    ErrorNumber.CRC: "CRC error (the servo received a corrupted packet)",
    ErrorNumber.DATA_RANGE: "data range error (the value is outside the register's range)",
    ErrorNumber.DATA_LENGTH: "data length error (shorter than the register)",
    ErrorNumber.DATA_LIMIT: "data limit error (the value exceeds a limit register)",
    ErrorNumber.ACCESS: "access error (read-only register, or EEPROM while torque is on)",
}


def error_text(error: int) -> str:
    """A readable description of a status packet's error byte (alert bit included)."""
    number = error & 0x7F
    try:
        text = _ERROR_TEXT[ErrorNumber(number)]
    except ValueError:
        text = f"unknown error number {number}"
    if error & ALERT_BIT:
        text += "; hardware alert (read hardware_error_status, reboot to clear)"
    return text


# -- CRC ------------------------------------------------------------------------------------------


def _make_crc_table() -> tuple[int, ...]:
    # MSB-first CRC-16 with polynomial 0x8005: entry i is the CRC of the byte i shifted in.
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


def _make_crc_table16(table: tuple[int, ...]) -> tuple[int, ...]:
    # Two bytes at a time: shifting the 16-bit word w into a 16-bit CRC register c leaves a
    # function of c ^ w alone, entry x = two steps of the byte table from register x.
    rows: list[int] = []
    for high in range(256):
        t = table[high]
        keep, fold = (t & 0xFF) << 8, t >> 8
        rows += [keep ^ table[low ^ fold] for low in range(256)]
    return tuple(rows)


_CRC_TABLE = _make_crc_table()
_CRC_TABLE16 = _make_crc_table16(_CRC_TABLE)  # 65,536 entries, built in ~5 ms at import


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """The Protocol 2.0 CRC-16 of ``data``, continuing from ``crc`` (0 for a new packet).

    Two bytes per step (``_CRC_TABLE16``), the odd last byte with the byte table: the driver
    computes one for every packet it sends or receives, 1.2 against 3.3 us for a cycle's
    42-byte Sync Write.
    """
    data = bytes(data)
    table = _CRC_TABLE16
    half = len(data) >> 1
    for word in struct.unpack_from(f">{half}H", data):
        crc = table[crc ^ word]
    if len(data) & 1:
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE[((crc >> 8) ^ data[-1]) & 0xFF]
    return crc


# -- stuffing -------------------------------------------------------------------------------------


def stuff(body: bytes | bytearray) -> bytes:
    """Insert an ``FD`` after every ``FF FF FD`` of an instruction/error/parameter area."""
    if b"\xff\xff\xfd" not in body:
        return bytes(body)
    out = bytearray()
    for i, byte in enumerate(body):
        out.append(byte)
        if byte == 0xFD and i >= 2 and body[i - 1] == 0xFF and body[i - 2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes | bytearray) -> bytes:
    """Drop the ``FD`` after every ``FF FF FD`` (the inverse of :func:`stuff`)."""
    if b"\xff\xff\xfd\xfd" not in body:
        return bytes(body)
    out = bytearray()
    i, n = 0, len(body)
    while i < n:
        byte = body[i]
        out.append(byte)
        if byte == 0xFD and i >= 2 and body[i - 1] == 0xFF and body[i - 2] == 0xFF:
            if i + 1 < n and body[i + 1] == 0xFD:
                i += 1  # the stuffed byte
        i += 1
    return bytes(out)


# -- packets --------------------------------------------------------------------------------------


def _check_id(packet_id: int) -> None:
    if not 0 <= packet_id <= 0xFF or packet_id in (0xFF, 0xFD):
        raise ValueError(f"invalid Dynamixel id {packet_id} (0..252, or 254 for broadcast)")


def _frame(packet_id: int, body: bytes) -> bytes:
    """Header, id, length, ``body`` (instruction onward, unstuffed), CRC."""
    _check_id(packet_id)
    stuffed = stuff(body)
    length = len(stuffed) + 2
    if length > 0xFFFF:
        raise ValueError(f"packet too long ({length} bytes)")
    head = HEADER + bytes((packet_id, length & 0xFF, length >> 8))
    frame = head + stuffed
    crc = crc16(frame)
    return frame + bytes((crc & 0xFF, crc >> 8))


def encode_instruction(packet_id: int, instruction: int, params: bytes | bytearray = b"") -> bytes:
    """An instruction packet, stuffed, with its CRC.

    Raises:
        ValueError: invalid id / instruction, or a packet longer than the length field allows.
    """
    if not 0 <= instruction <= 0xFF:
        raise ValueError(f"invalid instruction {instruction}")
    return _frame(packet_id, bytes((instruction,)) + bytes(params))


def encode_status(packet_id: int, error: int, params: bytes | bytearray = b"") -> bytes:
    """A status packet (instruction 0x55), stuffed, with its CRC.

    Raises:
        ValueError: invalid id / error byte, or a packet too long.
    """
    if not 0 <= error <= 0xFF:
        raise ValueError(f"invalid error byte {error}")
    return _frame(packet_id, bytes((Instruction.STATUS, error)) + bytes(params))


@dataclass(frozen=True)
class Packet:
    """One decoded packet.

    Attributes:
        id: the packet id.
        instruction: the instruction byte (0x55 for a status packet).
        params: the bytes after the instruction, unstuffed (for a status packet the error byte
            comes first: see :attr:`error` and :attr:`data`).
        crc_ok: whether the CRC matched (when ``False`` the other fields are unreliable).
        raw: the whole frame as received (stuffed), header to CRC.
    """

    id: int
    instruction: int
    params: bytes
    crc_ok: bool
    raw: bytes

    @property
    def is_status(self) -> bool:
        """Whether this is a status packet."""
        return self.instruction == Instruction.STATUS

    @property
    def error(self) -> int:
        """A status packet's error byte (0 when there is none)."""
        return self.params[0] if self.is_status and self.params else 0

    @property
    def data(self) -> bytes:
        """A status packet's parameters after the error byte; an instruction's parameters."""
        return self.params[1:] if self.is_status else self.params


class Decoder(StreamBuffer):
    """Incremental packet decoder (see the module docstring).

    Args:
        max_length: the largest LEN field accepted; a larger one is taken for junk.

    Attributes:
        crc_errors: frames whose CRC did not match.
        junk_bytes: bytes skipped while looking for a header.
        packets: frames decoded (CRC good or bad).
    """

    def __init__(self, max_length: int = 4096) -> None:
        super().__init__()
        self.max_length = max_length
        self.crc_errors = 0
        self.packets = 0

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        """Add received bytes; return the packets completed by them, in order."""
        buf = self._buf
        buf += data
        out: list[Packet] = []
        while True:
            start = buf.find(HEADER)
            if start < 0:
                # Keep a tail that may be the start of a header split across feeds.
                keep = 0
                for k in (3, 2, 1):
                    if len(buf) >= k and buf[-k:] == HEADER[:k]:
                        keep = k
                        break
                self.junk_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                return out
            if start:
                self.junk_bytes += start
                del buf[:start]
            if len(buf) < _PREFIX:
                return out
            length = buf[5] | (buf[6] << 8)
            if length < 3 or length > self.max_length:
                self.junk_bytes += 1
                del buf[:1]
                continue
            total = _PREFIX + length
            if len(buf) < total:
                return out
            frame = bytes(buf[:total])
            crc_ok = crc16(frame[:-2]) == (frame[-2] | (frame[-1] << 8))
            self.packets += 1
            if not crc_ok:
                self.crc_errors += 1
                out.append(Packet(frame[4], frame[7], unstuff(frame[8:-2]), False, frame))
                del buf[:1]  # resync: the next header may be inside this bogus frame
                continue
            body = unstuff(frame[7:-2])
            out.append(Packet(frame[4], body[0], body[1:], True, frame))
            del buf[:total]


# -- group instructions ---------------------------------------------------------------------------


def _u16(value: int) -> bytes:
    if not 0 <= value <= 0xFFFF:
        raise ValueError(f"{value} does not fit 16 bits")
    return bytes((value & 0xFF, value >> 8))


def _get_u16(data: bytes, offset: int) -> int:
    return data[offset] | (data[offset + 1] << 8)


def _check_ids(ids: Iterable[int]) -> list[int]:
    ids = list(ids)
    for i in ids:
        if not 0 <= i <= MAX_ID:
            raise ValueError(f"invalid servo id {i} in a group instruction (0..{MAX_ID})")
    if len(set(ids)) != len(ids):
        raise ValueError(f"duplicate ids in a group instruction: {ids}")
    return ids


def encode_sync_read(address: int, length: int, ids: Sequence[int], *, fast: bool = False) -> bytes:
    """A Sync Read (or Fast Sync Read) instruction packet, broadcast.

    Raises:
        ValueError: bad ids (duplicates, out of range), or address / length out of 16 bits.
    """
    params = _u16(address) + _u16(length) + bytes(_check_ids(ids))
    inst = Instruction.FAST_SYNC_READ if fast else Instruction.SYNC_READ
    return encode_instruction(BROADCAST_ID, inst, params)


def parse_sync_read(params: bytes) -> tuple[int, int, list[int]]:
    """``(address, length, ids)`` of Sync Read / Fast Sync Read parameters.

    Raises:
        ValueError: fewer than 5 parameter bytes.
    """
    if len(params) < 5:
        raise ValueError(f"sync read needs >= 5 parameter bytes, got {len(params)}")
    return _get_u16(params, 0), _get_u16(params, 2), list(params[4:])


def encode_sync_write(
    address: int, length: int, data: Mapping[int, bytes] | Sequence[tuple[int, bytes]]
) -> bytes:
    """A Sync Write instruction packet: the same ``length`` bytes at ``address`` for each id.

    Raises:
        ValueError: a data item not ``length`` bytes long, bad ids, or values out of range.
    """
    items = list(data.items()) if isinstance(data, Mapping) else list(data)
    _check_ids(i for i, _ in items)
    params = bytearray(_u16(address) + _u16(length))
    for servo_id, chunk in items:
        if len(chunk) != length:
            raise ValueError(
                f"sync write data for id {servo_id} is {len(chunk)} bytes, expected {length}"
            )
        params.append(servo_id)
        params += chunk
    return encode_instruction(BROADCAST_ID, Instruction.SYNC_WRITE, params)


def parse_sync_write(params: bytes) -> tuple[int, int, list[tuple[int, bytes]]]:
    """``(address, length, [(id, data), ...])`` of Sync Write parameters.

    Raises:
        ValueError: the parameters are not a whole number of ``1 + length`` records.
    """
    if len(params) < 4:
        raise ValueError(f"sync write needs >= 4 parameter bytes, got {len(params)}")
    address, length = _get_u16(params, 0), _get_u16(params, 2)
    body = params[4:]
    step = 1 + length
    if length == 0 or len(body) % step:
        raise ValueError(f"sync write body of {len(body)} bytes is not a multiple of {step}")
    return (
        address,
        length,
        [(body[i], bytes(body[i + 1 : i + step])) for i in range(0, len(body), step)],
    )


@dataclass(frozen=True)
class BulkReadEntry:
    """One servo's part of a Bulk Read: ``length`` bytes from ``address``."""

    id: int
    address: int
    length: int


def encode_bulk_read(
    entries: Sequence[BulkReadEntry | tuple[int, int, int]], *, fast: bool = False
) -> bytes:
    """A Bulk Read (or Fast Bulk Read) instruction packet from ``(id, address, length)`` items.

    Raises:
        ValueError: bad or duplicate ids, or values out of 16 bits.
    """
    items = [e if isinstance(e, BulkReadEntry) else BulkReadEntry(*e) for e in entries]
    _check_ids(e.id for e in items)
    params = bytearray()
    for e in items:
        params.append(e.id)
        params += _u16(e.address) + _u16(e.length)
    inst = Instruction.FAST_BULK_READ if fast else Instruction.BULK_READ
    return encode_instruction(BROADCAST_ID, inst, params)


def parse_bulk_read(params: bytes) -> list[BulkReadEntry]:
    """The entries of Bulk Read parameters.

    Raises:
        ValueError: the parameters are not a whole number of 5-byte records.
    """
    if not params or len(params) % 5:
        raise ValueError(f"bulk read parameters of {len(params)} bytes are not 5-byte records")
    return [
        BulkReadEntry(params[i], _get_u16(params, i + 1), _get_u16(params, i + 3))
        for i in range(0, len(params), 5)
    ]


def encode_bulk_write(entries: Sequence[tuple[int, int, bytes]]) -> bytes:
    """A Bulk Write instruction packet from ``(id, address, data)`` items.

    Raises:
        ValueError: bad or duplicate ids, empty data, or values out of 16 bits.
    """
    _check_ids(i for i, _, _ in entries)
    params = bytearray()
    for servo_id, address, data in entries:
        if not data:
            raise ValueError(f"bulk write data for id {servo_id} is empty")
        params.append(servo_id)
        params += _u16(address) + _u16(len(data)) + bytes(data)
    return encode_instruction(BROADCAST_ID, Instruction.BULK_WRITE, params)


def parse_bulk_write(params: bytes) -> list[tuple[int, int, bytes]]:
    """``[(id, address, data), ...]`` of Bulk Write parameters.

    Raises:
        ValueError: a truncated record.
    """
    out = []
    i, n = 0, len(params)
    while i < n:
        if i + 5 > n:
            raise ValueError("bulk write parameters end inside a record header")
        servo_id, address, length = params[i], _get_u16(params, i + 1), _get_u16(params, i + 3)
        if length == 0 or i + 5 + length > n:
            raise ValueError(f"bulk write record for id {servo_id} is truncated or empty")
        out.append((servo_id, address, bytes(params[i + 5 : i + 5 + length])))
        i += 5 + length
    if not out:
        raise ValueError("bulk write without records")
    return out


# -- Fast Sync Read status ------------------------------------------------------------------------


@dataclass(frozen=True)
class FastStatusEntry:
    """One servo's block of a Fast Sync Read / Fast Bulk Read status packet.

    Attributes:
        id: servo id.
        error: its error byte.
        data: its data.
        crc_ok: whether the block's running CRC matched (always checked for the last block,
            whose CRC is the packet's).
    """

    id: int
    error: int
    data: bytes
    crc_ok: bool = True


def fast_status_parts(entries: Sequence[tuple[int, int, bytes]]) -> list[bytes]:
    """The pieces of a Fast Sync Read status packet, one per ``(id, error, data)`` entry.

    The first servo sends the header (id 0xFE, LEN for the whole packet, 0x55) and its block;
    each following servo sends ``ERR ID DATA CRC``. Each block ends with the CRC of the whole
    packet up to there, so the last block's CRC is the packet's. Not stuffed (e-Manual).

    Raises:
        ValueError: no entries, or an invalid id / error byte.
    """
    if not entries:
        raise ValueError("a fast status packet needs at least one entry")
    length = 1 + sum(4 + len(data) for _, _, data in entries)
    head = HEADER + bytes((BROADCAST_ID, length & 0xFF, length >> 8, Instruction.STATUS))
    parts: list[bytes] = []
    crc = crc16(head)
    for n, (servo_id, error, data) in enumerate(entries):
        if not 0 <= servo_id <= MAX_ID or not 0 <= error <= 0xFF:
            raise ValueError(f"invalid id {servo_id} or error {error} in a fast status block")
        block = bytes((error, servo_id)) + bytes(data)
        crc = crc16(block, crc)
        block += bytes((crc & 0xFF, crc >> 8))
        crc = crc16(block[-2:], crc)
        parts.append(head + block if n == 0 else block)
    return parts


def encode_fast_status(entries: Sequence[tuple[int, int, bytes]]) -> bytes:
    """The whole Fast Sync Read status packet (see :func:`fast_status_parts`).

    Raises:
        ValueError: as :func:`fast_status_parts`.
    """
    return b"".join(fast_status_parts(entries))


def parse_fast_status(raw: bytes | Packet, lengths: Sequence[int]) -> list[FastStatusEntry]:
    """The blocks of a Fast Sync Read / Fast Bulk Read status frame.

    Args:
        raw: the whole frame (or a :class:`Packet`, whose ``raw`` is used: the frame is not
            stuffed, so the decoder's unstuffed ``params`` would be wrong).
        lengths: each block's data length, in the requested order.

    Raises:
        ValueError: not a status frame, or a length that does not match ``lengths``.
    """
    frame = raw.raw if isinstance(raw, Packet) else bytes(raw)
    if len(frame) < _PREFIX + 1 or frame[:4] != HEADER or frame[7] != Instruction.STATUS:
        raise ValueError("not a status frame")
    expected = _PREFIX + 1 + sum(4 + n for n in lengths)
    if len(frame) != expected:
        raise ValueError(f"fast status frame is {len(frame)} bytes, expected {expected}")
    out = []
    pos = _PREFIX + 1
    for n in lengths:
        error, servo_id = frame[pos], frame[pos + 1]
        data = frame[pos + 2 : pos + 2 + n]
        crc_at = pos + 2 + n
        ok = crc16(frame[:crc_at]) == _get_u16(frame, crc_at)
        out.append(FastStatusEntry(servo_id, error, data, ok))
        pos = crc_at + 2
    return out


# -- sizes and wire time --------------------------------------------------------------------------


def packet_size(n_params: int) -> int:
    """Bytes of an instruction packet with ``n_params`` parameter bytes (without stuffing)."""
    return PACKET_OVERHEAD + n_params


def status_packet_size(n_data: int) -> int:
    """Bytes of a status packet carrying ``n_data`` data bytes (without stuffing)."""
    return STATUS_OVERHEAD + n_data


def wire_time_s(n_bytes: int, baud: int) -> float:
    """Seconds ``n_bytes`` take on the wire at ``baud`` (8N1: 10 bits per byte)."""
    return n_bytes * 10.0 / baud


def sync_read_cycle_bytes(n_servos: int, data_len: int, fast: bool) -> tuple[int, int]:
    """``(bytes sent, bytes received)`` of one Sync Read (or Fast Sync Read) of ``n_servos``."""
    sent = packet_size(4 + n_servos)
    if fast:
        received = _PREFIX + 1 + n_servos * (4 + data_len)
    else:
        received = n_servos * status_packet_size(data_len)
    return sent, received


def sync_write_bytes(n_servos: int, data_len: int) -> int:
    """Bytes of one Sync Write of ``data_len`` bytes to ``n_servos``."""
    return packet_size(4 + n_servos * (1 + data_len))


def bulk_read_cycle_bytes(lengths: Sequence[int], fast: bool = False) -> tuple[int, int]:
    """``(bytes sent, bytes received)`` of one Bulk Read with one data length per servo."""
    sent = packet_size(5 * len(lengths))
    if fast:
        return sent, _PREFIX + 1 + sum(4 + n for n in lengths)
    return sent, sum(status_packet_size(n) for n in lengths)


def bulk_write_bytes(lengths: Sequence[int]) -> int:
    """Bytes of one Bulk Write with one data length per servo."""
    return packet_size(sum(5 + n for n in lengths))
