"""Protocol 2.0 codec and control table: exact byte vectors from the ROBOTIS e-Manual."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jtc_hw.drivers.dynamixel import control_table as ct
from jtc_hw.drivers.dynamixel import packets as pk


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# -- e-Manual examples (Protocol 2.0 page) ----------------------------------------------------

PING_1 = h("FF FF FD 00 01 03 00 01 19 4E")
# Status of ID 1: model number 1030 (0x0406), firmware 0x26.
PING_1_STATUS = h("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")
# READ ID 1 Present Position (132, 4 bytes) -> 166.
READ_1 = h("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15")
READ_1_STATUS = h("FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0")
# WRITE ID 1 Goal Position (116) = 512.
WRITE_1 = h("FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89")
WRITE_1_STATUS = h("FF FF FD 00 01 04 00 55 00 A1 0C")
# Fast Sync Read of Present Position from ids 3, 7, 4 (166, 2079, 1023).
FAST_SYNC_READ = h("FF FF FD 00 FE 0A 00 8A 84 00 04 00 03 07 04 20 F2")
FAST_SYNC_STATUS = h(
    "FF FF FD 00 FE 19 00 55 00 03 A6 00 00 00 84 08"
    " 00 07 1F 08 00 00 16 CA"
    " 00 04 FF 03 00 00 D1 9E"
)
# Bulk Read: ID 1 Present Input Voltage (144, 2), ID 2 Present Temperature (146, 1).
BULK_READ = h("FF FF FD 00 FE 0D 00 92 01 90 00 02 00 02 92 00 01 00 1A 05")
BULK_READ_STATUS_1 = h("FF FF FD 00 01 06 00 55 00 77 00 C3 69")
BULK_READ_STATUS_2 = h("FF FF FD 00 02 05 00 55 00 24 8B A9")
# Bulk Write: ID 1 Max Voltage Limit (32, 2) = 160, ID 2 Temperature Limit (31, 1) = 80.
BULK_WRITE = h("FF FF FD 00 FE 10 00 93 01 20 00 02 00 A0 00 02 1F 00 01 00 50 B7 68")


def test_ping_and_status_vectors() -> None:
    assert pk.encode_instruction(1, pk.Instruction.PING) == PING_1
    assert pk.encode_status(1, 0, h("06 04 26")) == PING_1_STATUS


def test_read_write_vectors() -> None:
    assert pk.encode_instruction(1, pk.Instruction.READ, h("84 00 04 00")) == READ_1
    assert pk.encode_status(1, 0, (166).to_bytes(4, "little")) == READ_1_STATUS
    assert pk.encode_instruction(1, pk.Instruction.WRITE, h("74 00 00 02 00 00")) == WRITE_1
    assert pk.encode_status(1, 0) == WRITE_1_STATUS


def test_crc_of_known_vectors() -> None:
    for frame in (PING_1, PING_1_STATUS, READ_1, WRITE_1, BULK_WRITE, FAST_SYNC_READ):
        assert pk.crc16(frame[:-2]) == frame[-2] | frame[-1] << 8
    assert pk.crc16(b"") == 0
    # Continuing a CRC equals computing it in one go.
    assert pk.crc16(PING_1[4:8], pk.crc16(PING_1[:4])) == pk.crc16(PING_1[:8])


def _crc_bitwise(data: bytes, crc: int = 0) -> int:
    """CRC-16, polynomial 0x8005, MSB first, one bit at a time (the e-Manual's definition)."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def test_crc_two_bytes_at_a_time_equals_the_bitwise_definition() -> None:
    rng = np.random.default_rng(24)
    for length in [*range(0, 8), 21, 42, 43, 300, 301]:
        for _ in range(20):
            data = rng.integers(0, 256, length, dtype=np.uint8).tobytes()
            start = int(rng.integers(0, 1 << 16))
            assert pk.crc16(data, start) == _crc_bitwise(data, start), (length, start)
            assert pk.crc16(bytearray(data)) == pk.crc16(memoryview(data)) == _crc_bitwise(data)


def test_decoder_reads_the_examples() -> None:
    dec = pk.Decoder()
    packets = dec.feed(READ_1 + READ_1_STATUS)
    assert [(p.id, p.instruction, p.crc_ok) for p in packets] == [(1, 0x02, True), (1, 0x55, True)]
    assert packets[0].params == h("84 00 04 00")
    assert packets[1].is_status and packets[1].error == 0
    assert packets[1].data == (166).to_bytes(4, "little")
    assert packets[0].raw == READ_1


def test_stuffing_round_trip() -> None:
    params = h("74 00 FF FF FD 01 FF FF FD")
    frame = pk.encode_instruction(3, pk.Instruction.WRITE, params)
    # Each FF FF FD of the body gets an extra FD; LENGTH counts the stuffed bytes.
    assert frame[7:-2] == h("03 74 00 FF FF FD FD 01 FF FF FD FD")
    assert frame[5] | frame[6] << 8 == len(frame) - 7
    [packet] = pk.Decoder().feed(frame)
    assert packet.crc_ok and packet.params == params
    assert pk.unstuff(pk.stuff(params)) == params
    assert pk.stuff(h("01 02")) == h("01 02")


def test_stuffed_status_round_trip() -> None:
    data = h("FF FF FD 00")
    frame = pk.encode_status(5, 0, data)
    [packet] = pk.Decoder().feed(frame)
    assert packet.crc_ok and packet.data == data and packet.id == 5


def test_decoder_resyncs_on_junk_and_split_feeds() -> None:
    dec = pk.Decoder()
    stream = h("00 12 FF FF 34") + PING_1 + h("FF") + WRITE_1 + h("FF FF FD")
    out = []
    for i in range(0, len(stream), 3):  # split everywhere, headers included
        out += dec.feed(stream[i : i + 3])
    assert [p.raw for p in out] == [PING_1, WRITE_1]
    assert dec.pending == 3  # a possible header start is kept
    assert dec.junk_bytes == 6
    out = dec.feed(READ_1[3:])
    assert [p.raw for p in out] == [READ_1]


def test_decoder_reports_crc_errors_and_recovers() -> None:
    dec = pk.Decoder()
    bad = PING_1[:-1] + bytes((PING_1[-1] ^ 0x01,))
    out = dec.feed(bad + READ_1)
    assert [p.crc_ok for p in out] == [False, True]
    assert out[0].id == 1 and out[1].raw == READ_1
    assert dec.crc_errors == 1


def test_decoder_survives_a_corrupted_length() -> None:
    dec = pk.Decoder()
    bad = bytearray(PING_1)
    bad[5] = 0x09  # claims 6 more bytes than there are: swallows part of the next packet
    out = dec.feed(bytes(bad) + READ_1 + WRITE_1)
    good = [p.raw for p in out if p.crc_ok]
    assert WRITE_1 in good
    assert dec.crc_errors >= 1


def test_decoder_rejects_absurd_lengths() -> None:
    dec = pk.Decoder(max_length=64)
    out = dec.feed(h("FF FF FD 00 01 FF 7F") + PING_1)
    assert [p.raw for p in out] == [PING_1]


def test_sync_read_layout() -> None:
    frame = pk.encode_sync_read(132, 4, [3, 7, 4], fast=True)
    assert frame == FAST_SYNC_READ
    [p] = pk.Decoder().feed(pk.encode_sync_read(126, 10, [1, 2]))
    assert p.id == pk.BROADCAST_ID and p.instruction == pk.Instruction.SYNC_READ
    assert pk.parse_sync_read(p.params) == (126, 10, [1, 2])
    with pytest.raises(ValueError):
        pk.encode_sync_read(126, 10, [1, 1])


def test_sync_write_layout() -> None:
    frame = pk.encode_sync_write(116, 4, {1: (150).to_bytes(4, "little"), 2: bytes(4)})
    [p] = pk.Decoder().feed(frame)
    assert p.instruction == pk.Instruction.SYNC_WRITE
    assert p.params == h("74 00 04 00 01 96 00 00 00 02 00 00 00 00")
    assert pk.parse_sync_write(p.params) == (116, 4, [(1, h("96 00 00 00")), (2, bytes(4))])
    assert len(frame) == pk.sync_write_bytes(2, 4)
    with pytest.raises(ValueError):
        pk.encode_sync_write(116, 4, {1: b"\x00"})
    with pytest.raises(ValueError):
        pk.parse_sync_write(h("74 00 04 00 01 96"))


def test_bulk_read_and_write_layouts() -> None:
    assert pk.encode_bulk_read([(1, 144, 2), (2, 146, 1)]) == BULK_READ
    [p] = pk.Decoder().feed(BULK_READ)
    assert pk.parse_bulk_read(p.params) == [
        pk.BulkReadEntry(1, 144, 2),
        pk.BulkReadEntry(2, 146, 1),
    ]
    assert pk.encode_status(1, 0, h("77 00")) == BULK_READ_STATUS_1
    assert pk.encode_status(2, 0, h("24")) == BULK_READ_STATUS_2
    assert pk.encode_bulk_write([(1, 32, h("A0 00")), (2, 31, h("50"))]) == BULK_WRITE
    [p] = pk.Decoder().feed(BULK_WRITE)
    assert pk.parse_bulk_write(p.params) == [(1, 32, h("A0 00")), (2, 31, h("50"))]
    with pytest.raises(ValueError):
        pk.parse_bulk_write(h("01 20 00 05 00 A0"))


def test_fast_sync_read_status_layout() -> None:
    entries = [
        (3, 0, (166).to_bytes(4, "little")),
        (7, 0, (2079).to_bytes(4, "little")),
        (4, 0, (1023).to_bytes(4, "little")),
    ]
    parts = pk.fast_status_parts(entries)
    assert b"".join(parts) == FAST_SYNC_STATUS == pk.encode_fast_status(entries)
    assert [len(x) for x in parts] == [16, 8, 8]
    # The decoder sees one ordinary packet whose CRC is the last block's.
    [p] = pk.Decoder().feed(FAST_SYNC_STATUS)
    assert p.crc_ok and p.id == pk.BROADCAST_ID
    blocks = pk.parse_fast_status(p, [4, 4, 4])
    assert [(b.id, b.error, int.from_bytes(b.data, "little"), b.crc_ok) for b in blocks] == [
        (3, 0, 166, True),
        (7, 0, 2079, True),
        (4, 0, 1023, True),
    ]
    corrupt = bytearray(FAST_SYNC_STATUS)
    corrupt[10] ^= 0xFF
    assert [b.crc_ok for b in pk.parse_fast_status(bytes(corrupt), [4, 4, 4])] == [
        False,
        False,
        False,
    ]
    with pytest.raises(ValueError):
        pk.parse_fast_status(FAST_SYNC_STATUS, [4, 4])


def test_sizes_and_wire_time() -> None:
    assert pk.packet_size(0) == len(PING_1)
    assert pk.status_packet_size(4) == len(READ_1_STATUS)
    sent, received = pk.sync_read_cycle_bytes(3, 4, fast=True)
    assert (sent, received) == (len(FAST_SYNC_READ), len(FAST_SYNC_STATUS))
    sent, received = pk.sync_read_cycle_bytes(2, 10, fast=False)
    assert sent == len(pk.encode_sync_read(126, 10, [1, 2]))
    assert received == 2 * len(pk.encode_status(1, 0, bytes(10)))
    assert pk.bulk_read_cycle_bytes([2, 1]) == (
        len(BULK_READ),
        len(BULK_READ_STATUS_1) + len(BULK_READ_STATUS_2),
    )
    assert pk.bulk_write_bytes([2, 1]) == len(BULK_WRITE)
    assert pk.wire_time_s(100, 1_000_000) == pytest.approx(1e-3)


def test_error_text() -> None:
    assert "access" in pk.error_text(7)
    assert "hardware alert" in pk.error_text(0x80 | 4)


# -- control table ------------------------------------------------------------------------------


def test_models_and_registers() -> None:
    xm = ct.model_by_name("XM430-W350")
    assert xm.model_number == 1020 and ct.model_by_number(1020) is xm
    assert ct.model_by_number(1060) is ct.MODELS["XL430-W250"]
    assert ct.model_by_name("xm540-w270-r").model_number == 1120
    assert ct.MODELS["XC330-T288"].model_number == 1220
    assert ct.model_by_number(9999) is None
    gp = xm.register("goal_position")
    assert (gp.address, gp.size, gp.signed, gp.writable, gp.eeprom) == (116, 4, True, True, False)
    assert xm.register("baud_rate").eeprom and not xm.register("present_position").writable
    with pytest.raises(KeyError, match="goal_position"):
        xm.register("goal_pos")
    with pytest.raises(KeyError, match="XM430-W350"):
        ct.model_by_name("XM430-W35")
    xl = ct.MODELS["XL430-W250"]
    assert not xl.has_register("goal_current") and xl.register("present_load").address == 126
    assert xl.present_block_names[0] == "present_load"
    assert ct.OperatingMode.CURRENT not in xl.operating_modes
    # The present block is contiguous on every model.
    for model in ct.MODELS.values():
        regs = [model.register(n) for n in model.present_block_names]
        assert regs[0].address == ct.PRESENT_BLOCK_ADDRESS
        assert sum(r.size for r in regs) == ct.PRESENT_BLOCK_SIZE
        assert all(a.end == b.address for a, b in zip(regs, regs[1:]))
    assert 7 not in ct.MODELS["XC330-T288"].baud_rates and xm.baud_rates[7] == 4_500_000


def test_conversions() -> None:
    xm = ct.MODELS["XM430-W350"]
    assert xm.ticks_to_rad(2048) == pytest.approx(math.pi)
    assert xm.rad_to_ticks(math.pi) == 2048 and xm.rad_to_ticks(-math.pi) == -2048
    assert xm.velocity_to_rad_s(1) == pytest.approx(0.229 * 2 * math.pi / 60)
    assert xm.rad_s_to_velocity(xm.velocity_to_rad_s(-123)) == -123
    assert xm.current_to_a(1000) == pytest.approx(2.69)
    assert xm.a_to_current(2.69) == 1000
    ticks = np.array([0, 1024, -4096])
    assert np.allclose(xm.ticks_to_rad(ticks), [0.0, math.pi / 2, -2 * math.pi])
    back = xm.rad_to_ticks(xm.ticks_to_rad(ticks))
    assert back.dtype == np.int64 and list(back) == [0, 1024, -4096]
    with pytest.raises(ValueError):
        ct.MODELS["XL430-W250"].current_to_a(1)
    with pytest.raises(ValueError):
        xm.rad_to_ticks(float("nan"))


def test_register_encode_decode_and_defaults() -> None:
    xm = ct.MODELS["XM430-W350"]
    reg = xm.register("goal_velocity")
    assert reg.decode(reg.encode(-5)) == -5
    with pytest.raises(ValueError):
        xm.register("led").encode(256)
    table = xm.defaults()
    assert table[0] | table[1] << 8 == 1020
    assert table[xm.register("return_delay_time").address] == 250
    assert table[xm.register("operating_mode").address] == ct.OperatingMode.POSITION
