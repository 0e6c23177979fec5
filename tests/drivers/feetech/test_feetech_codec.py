"""Feetech codec and control table: byte vectors, sign-magnitude, byte orders, units."""

from __future__ import annotations

import math

import pytest

from jtc_hw.drivers.feetech import codec as fc
from jtc_hw.drivers.feetech import control_table as ct

STS3215 = ct.MODELS["STS3215"]
SCS0009 = ct.MODELS["SCS0009"]


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# -- control table --------------------------------------------------------------------------------


def test_the_model_numbers_are_lerobots() -> None:
    assert {m.name: m.model_number for m in ct.MODELS.values()} == {
        "STS3215": 777, "STS3250": 2825, "SCS0009": 1284}
    assert ct.model_by_number(777) is STS3215
    assert ct.model_by_number(1) is None
    assert ct.model_by_name(" sts3215 ") is STS3215
    with pytest.raises(ct.UnknownModelError, match="known models: STS3215"):
        ct.model_by_name("STS9999")


def test_the_series_differ_where_the_issue_says() -> None:
    sts, scs = ct.STS_SMS, ct.SCS
    assert (sts.byte_order, scs.byte_order) == (ct.ByteOrder.LITTLE, ct.ByteOrder.BIG)
    assert (sts.sdk_protocol_end, scs.sdk_protocol_end) == (0, 1)
    assert (sts.lock_address, scs.lock_address) == (55, 48)
    assert (sts.sync_read, sts.broadcast_ping) == (True, True)
    assert (scs.sync_read, scs.broadcast_ping) == (False, False)
    signs = {name: r.sign_bit for name, r in sts.registers.items() if r.sign_bit is not None}
    assert signs == {"homing_offset": 11, "goal_position": 15, "goal_velocity": 15,
                     "present_position": 15, "present_velocity": 15, "present_load": 10}
    assert all(r.sign_bit is None for r in scs.registers.values())


def test_registers_know_their_area_and_limits() -> None:
    sts = ct.STS_SMS
    assert sts.register("homing_offset").eeprom
    assert not sts.register("lock").eeprom
    assert sts.register("present_position").address == 56
    assert not sts.register("present_position").writable
    assert sts.register("present_load").limits == (-1023, 1023)
    assert sts.register("goal_position").limits == (-32767, 32767)
    assert sts.register("max_torque_limit").limits == (0, 65535)
    with pytest.raises(ct.UnknownRegisterError, match="did you mean 'present_position'"):
        sts.register("present_positon")
    # No two registers of a series overlap.
    for series in (ct.STS_SMS, ct.SCS):
        spans = sorted((r.address, r.address + r.size) for r in series.registers.values())
        assert all(a_end <= b_start for (_, a_end), (b_start, _) in zip(spans, spans[1:]))


def test_position_and_speed_units_per_model() -> None:
    assert STS3215.rad_per_step == pytest.approx(2 * math.pi / 4096)
    assert SCS0009.rad_per_step == pytest.approx(math.radians(300 / 1024))
    # 50 steps/s is 0.732 rev/min on a 4096-step servo (Feetech's table).
    assert 50 * STS3215.speed_unit_rad_s * 60 / (2 * math.pi) == pytest.approx(0.732, abs=1e-3)
    assert SCS0009.speed_unit_rad_s == pytest.approx(0.059 * 2 * math.pi / 60)


# -- sign-magnitude and words ---------------------------------------------------------------------


@pytest.mark.parametrize(("value", "bit", "raw"), [
    (0, 15, 0x0000), (1, 15, 0x0001), (-1, 15, 0x8001), (32767, 15, 0x7FFF),
    (-32767, 15, 0xFFFF), (-1000, 10, 0x07E8), (1023, 10, 0x03FF), (-2047, 11, 0x0FFF),
])
def test_sign_magnitude_round_trips(value: int, bit: int, raw: int) -> None:
    assert fc.encode_sign_magnitude(value, bit) == raw
    assert fc.decode_sign_magnitude(raw, bit) == value


def test_minus_zero_decodes_to_zero_and_overflow_is_refused() -> None:
    assert fc.decode_sign_magnitude(0x8000, 15) == 0
    assert fc.decode_sign_magnitude(0x0400, 10) == 0
    with pytest.raises(ValueError, match="sign in bit 15"):
        fc.encode_sign_magnitude(32768, 15)
    with pytest.raises(ValueError, match="sign in bit 10"):
        fc.encode_sign_magnitude(-1024, 10)


@pytest.mark.parametrize(("order", "two", "four"), [
    (ct.ByteOrder.LITTLE, h("34 12"), h("78 56 34 12")),
    (ct.ByteOrder.BIG, h("12 34"), h("56 78 12 34")),
])
def test_words_follow_the_series_byte_order(order: ct.ByteOrder, two: bytes,
                                            four: bytes) -> None:
    assert fc.pack_word(0x1234, 2, order) == two
    assert fc.unpack_word(two, order) == 0x1234
    # A 4-byte value is the low word first, each word in the series' order (the SDK's way).
    assert fc.pack_word(0x12345678, 4, order) == four
    assert fc.unpack_word(four, order) == 0x12345678
    assert fc.pack_word(0xAB, 1, order) == h("AB")
    with pytest.raises(ValueError):
        fc.pack_word(0x10000, 2, order)
    with pytest.raises(ValueError):
        fc.unpack_word(b"\x00\x00\x00", order)


def test_register_values_combine_sign_and_order() -> None:
    sts, scs = ct.STS_SMS, ct.SCS
    goal = sts.register("goal_position")
    assert fc.encode_value(goal, -5, sts.byte_order) == h("05 80")
    assert fc.decode_value(goal, h("05 80"), sts.byte_order) == -5
    load = sts.register("present_load")
    assert fc.decode_value(load, h("F4 05"), sts.byte_order) == -500  # 0x05F4: bit 10 + 500
    scs_goal = scs.register("goal_position")
    assert fc.encode_value(scs_goal, 1000, scs.byte_order) == h("03 E8")
    assert fc.decode_value(scs_goal, h("03 E8"), scs.byte_order) == 1000
    with pytest.raises(ValueError, match="outside"):
        fc.encode_value(scs_goal, -1, scs.byte_order)
    with pytest.raises(ValueError, match="2 bytes"):
        fc.decode_value(goal, h("05"), sts.byte_order)


# -- joint units ----------------------------------------------------------------------------------


def test_joint_scale_round_trips_whole_steps() -> None:
    scale = fc.JointScale(STS3215, direction=-1, gear=2.0, offset=0.3)
    for steps in (0, 1, 2048, 4095, -17):
        assert scale.rad_to_steps(scale.steps_to_rad(steps)) == steps
    assert scale.steps_to_rad(0) == pytest.approx(0.3)
    assert scale.steps_to_rad(4096) == pytest.approx(0.3 - math.pi)  # half a joint turn
    for counts in (0, 1, -3400, 2400):
        assert scale.rad_s_to_speed(scale.speed_to_rad_s(counts)) == counts
    assert scale.load_fraction(500) == pytest.approx(-0.5)
    with pytest.raises(ValueError, match="non-finite"):
        scale.rad_to_steps(math.nan)
    with pytest.raises(ValueError, match="direction"):
        fc.JointScale(STS3215, direction=0)
    with pytest.raises(ValueError, match="gear"):
        fc.JointScale(STS3215, gear=0.0)


# -- status byte ----------------------------------------------------------------------------------


def test_status_error_text_names_every_bit() -> None:
    assert fc.status_error_text(0) == "no error"
    assert fc.status_error_text(0x24) == "overheating, overload"
    assert fc.status_error_text(0x0B) == ("input voltage out of range, angle sensor error, "
                                          "overcurrent")
    assert fc.status_error_text(0x10) == "reserved bits 0x10"


# -- packets --------------------------------------------------------------------------------------

PING_1 = h("FF FF 01 02 01 FB")  # Feetech's manual example: ~(01+02+01) = FB
READ_1_POS = h("FF FF 01 04 02 38 02 BE")  # read 2 bytes at 56 from id 1
STATUS_1_2048 = h("FF FF 01 04 00 00 08 F2")  # id 1 answers 00 08 (2048, little endian)


def test_the_checksum_is_the_inverted_low_byte_of_the_sum() -> None:
    assert fc.checksum(h("01 02 01")) == 0xFB
    assert fc.checksum(bytes(200 * [0xFF])) == (~(200 * 0xFF)) & 0xFF


def test_instruction_byte_vectors() -> None:
    assert fc.encode_ping(1) == PING_1
    assert fc.encode_read(1, 56, 2) == READ_1_POS
    assert fc.encode_status(1, 0, h("00 08")) == STATUS_1_2048
    assert fc.encode_write(1, 42, h("00 08")) == h("FF FF 01 05 03 2A 00 08 C4")
    assert fc.encode_reg_write(2, 42, h("00 08")) == h("FF FF 02 05 04 2A 00 08 C2")
    assert fc.encode_action() == h("FF FF FE 02 05 FA")
    assert fc.encode_sync_read(56, 2, [1, 2]) == h("FF FF FE 06 82 38 02 01 02 3C")
    assert fc.encode_sync_write(42, 2, {1: h("00 08"), 2: h("FF 0F")}) == h(
        "FF FF FE 0A 83 2A 02 01 00 08 02 FF 0F 2F")


def test_builders_refuse_what_the_bus_cannot_carry() -> None:
    with pytest.raises(ValueError, match="invalid Feetech id"):
        fc.encode_ping(255)
    with pytest.raises(ValueError, match="broadcast"):
        fc.encode_status(fc.BROADCAST_ID)
    with pytest.raises(ValueError, match="duplicate"):
        fc.encode_sync_read(56, 2, [1, 1])
    with pytest.raises(ValueError, match="at least one id"):
        fc.encode_sync_read(56, 2, [])
    with pytest.raises(ValueError, match="expected 2"):
        fc.encode_sync_write(42, 2, {1: h("00")})
    with pytest.raises(ValueError, match="too long"):
        fc.encode_write(1, 0, bytes(245))
    with pytest.raises(ValueError, match="one byte"):
        fc.encode_read(1, 256, 2)


def test_parsers_invert_the_builders() -> None:
    assert fc.parse_read(h("38 02")) == (56, 2)
    assert fc.parse_write(h("2A 00 08")) == (42, h("00 08"))
    assert fc.parse_sync_read(h("38 02 01 02 03")) == (56, 2, [1, 2, 3])
    assert fc.parse_sync_write(h("2A 02 01 00 08 02 FF 0F")) == (
        42, 2, [(1, h("00 08")), (2, h("FF 0F"))])
    with pytest.raises(ValueError):
        fc.parse_sync_write(h("2A 02 01 00"))
    with pytest.raises(ValueError):
        fc.parse_read(h("38"))


def test_the_decoder_reads_split_and_back_to_back_frames() -> None:
    decoder = fc.Decoder(status=False)
    stream = PING_1 + READ_1_POS
    got = [p for i in range(len(stream)) for p in decoder.feed(stream[i : i + 1])]
    assert [(p.id, p.code, p.params, p.checksum_ok) for p in got] == [
        (1, fc.Instruction.PING, b"", True), (1, fc.Instruction.READ, h("38 02"), True)]
    assert decoder.pending == 0 and decoder.junk_bytes == 0


def test_the_decoder_skips_junk_and_resyncs_after_a_bad_checksum() -> None:
    decoder = fc.Decoder(status=True)
    corrupt = STATUS_1_2048[:-1] + b"\x00"
    packets = decoder.feed(h("00 FF 13") + corrupt + STATUS_1_2048)
    assert [p.checksum_ok for p in packets] == [False, True]
    assert packets[1].params == h("00 08") and packets[1].error == fc.StatusError(0)
    assert decoder.checksum_errors == 1
    assert decoder.pending == 0


def test_the_status_decoder_rejects_what_the_sdk_rejects() -> None:
    decoder = fc.Decoder(status=True)
    # An error byte above 0x7F, then a broadcast id: neither is a status; the good one is found.
    junk = h("FF FF 01 02 80 7C") + h("FF FF FE 02 00 FF")
    status = fc.encode_status(3, fc.StatusError.OVERLOAD | fc.StatusError.OVERHEAT)
    packets = decoder.feed(junk + status)
    assert [(p.id, p.error) for p in packets] == [
        (3, fc.StatusError.OVERLOAD | fc.StatusError.OVERHEAT)]
    assert fc.Decoder(status=False).feed(fc.encode_action())[0].id == fc.BROADCAST_ID
