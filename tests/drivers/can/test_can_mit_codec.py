"""MIT-mode codec: exact byte vectors, range edges and clamping, wire bits; and the emulator
(a peer on a python-can virtual bus) agreeing with the codec in both directions."""

from __future__ import annotations

import math
import time
import uuid
from collections.abc import Iterator

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jtc_hw.drivers.can.bus import wire_bits, wire_time_s
from jtc_hw.drivers.can.mit.codec import (
    DAMIAO_REGISTERS,
    ENTER_MOTOR_MODE,
    EXIT_MOTOR_MODE,
    MODEL_PRESETS,
    REGISTER_READ,
    REGISTER_STORE,
    REGISTER_WRITE,
    SET_ZERO,
    CommandEncoder,
    MitCommand,
    MitLimits,
    MitReply,
    RegisterFrame,
    decode_command,
    decode_register_frame,
    decode_reply,
    encode_command,
    encode_register_frame,
    encode_reply,
    float_to_uint,
    quantum,
    reply_motor_id,
    special_command,
    timeout_register_value,
    uint_to_float,
)
from jtc_hw.drivers.can.mit.emulator import MitBusEmulator

AK80 = MODEL_PRESETS["AK80-9"]  # p 12.5, v 50, t 18, kp 500, kd 5
DM = MODEL_PRESETS["DM4310"]  # p 12.5, v 30, t 10, Damiao reply


def h(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


# -- fixed-point ---------------------------------------------------------------------------------


def test_float_to_uint_edges_and_clamping() -> None:
    assert float_to_uint(-12.5, -12.5, 12.5, 16) == 0
    assert float_to_uint(12.5, -12.5, 12.5, 16) == 0xFFFF
    assert float_to_uint(0.0, -12.5, 12.5, 16) == 0x8000  # 32767.5 rounds up
    assert float_to_uint(1e9, -12.5, 12.5, 16) == 0xFFFF
    assert float_to_uint(-math.inf, -12.5, 12.5, 16) == 0
    assert float_to_uint(0.0, 0.0, 500.0, 12) == 0
    assert float_to_uint(500.0, 0.0, 500.0, 12) == 0xFFF
    assert uint_to_float(0xFFF, 0.0, 500.0, 12) == 500.0
    assert uint_to_float(0, -50.0, 50.0, 12) == -50.0
    with pytest.raises(ValueError, match="NaN"):
        float_to_uint(math.nan, 0.0, 1.0, 12)


# -- commands ------------------------------------------------------------------------------------


def test_command_zero() -> None:
    # p 0 -> 0x8000, v 0 -> 0x800, kp 0, kd 0, t 0 -> 0x800
    assert encode_command(MitCommand(0, 0, 0, 0, 0), AK80) == h("80 00 80 00 00 00 08 00")


def test_command_mid_values() -> None:
    # p 1.0: 0.54 * 65535 = 35388.9 -> 35389 = 0x8A3D; v -2.0: 0.48 * 4095 = 1965.6 -> 0x7AE;
    # kp 50: 409.5 -> 0x19A; kd 1: 819 = 0x333; t 0.5: 2104.375 -> 0x838.
    data = encode_command(MitCommand(1.0, -2.0, 50.0, 1.0, 0.5), AK80)
    assert data == h("8A 3D 7A E1 9A 33 38 38")
    back = decode_command(data, AK80)
    q = quantum(AK80)
    assert back.position == pytest.approx(1.0, abs=q.position / 2)
    assert back.velocity == pytest.approx(-2.0, abs=q.velocity / 2)
    assert back.kp == pytest.approx(50.0, abs=q.kp / 2)
    assert back.kd == pytest.approx(1.0, abs=q.kd / 2)
    assert back.torque == pytest.approx(0.5, abs=q.torque / 2)


def test_command_range_edges_and_clamping() -> None:
    assert encode_command(MitCommand(-12.5, -50, 0, 0, -18), AK80) == h("00 00 00 00 00 00 00 00")
    # Beyond every edge: clamped to the edge.
    assert encode_command(MitCommand(100, -100, -1, 10, -50), AK80) == h("FF FF 00 00 00 FF F0 00")
    assert encode_command(MitCommand(-100, 100, 1e6, -3, 50), AK80) == h("00 00 FF FF FF 00 0F FF")
    with pytest.raises(ValueError):
        encode_command(MitCommand(math.nan, 0, 0, 0, 0), AK80)


def test_special_commands() -> None:
    assert ENTER_MOTOR_MODE == h("FF FF FF FF FF FF FF FC")
    assert EXIT_MOTOR_MODE == h("FF FF FF FF FF FF FF FD")
    assert SET_ZERO == h("FF FF FF FF FF FF FF FE")
    assert special_command(ENTER_MOTOR_MODE) == "enter"
    assert special_command(EXIT_MOTOR_MODE) == "exit"
    assert special_command(SET_ZERO) == "zero"
    assert special_command(h("80 00 80 00 00 00 08 00")) is None
    with pytest.raises(ValueError, match="special"):
        decode_command(ENTER_MOTOR_MODE, AK80)


def test_a_set_point_never_encodes_as_a_special_command() -> None:
    # p, v, kp, kd at their maxima and t one step under: FF..FC would enter motor mode.
    t = uint_to_float(0xFFC, -18.0, 18.0, 12)
    data = encode_command(MitCommand(12.5, 50.0, 500.0, 5.0, t), AK80)
    assert special_command(data) is None
    assert data == h("FF FF FF FF FF FF FF FA")  # torque two steps lower, documented


def test_ranges_come_from_the_model() -> None:
    small = MitLimits(p_max=4.0, v_max=10.0, t_max=2.0, kp_max=100.0, kd_max=1.0)
    # The same physical command packs differently under another model's ranges.
    assert encode_command(MitCommand(4.0, 10.0, 100.0, 1.0, 2.0), small) == h("FF" * 8)
    assert encode_command(MitCommand(4.0, 10.0, 100.0, 1.0, 2.0), AK80) != h("FF" * 8)
    with pytest.raises(ValueError):
        MitLimits(p_max=0.0, v_max=1.0, t_max=1.0)


_FIELD = st.one_of(
    st.floats(allow_nan=False, min_value=-600.0, max_value=600.0),
    st.sampled_from([math.inf, -math.inf, 0.0, -0.0, 12.5, -12.5, 50.0, 500.0, 5.0, 18.0]),
)


@settings(max_examples=400, deadline=None)
@given(st.tuples(_FIELD, _FIELD, _FIELD, _FIELD, _FIELD),
       st.sampled_from(sorted(MODEL_PRESETS)))
def test_command_encoder_gives_encode_commands_bytes(
    values: tuple[float, float, float, float, float], model: str
) -> None:
    """The driver's per-cycle encoder is encode_command, byte for byte, clamping included."""
    limits = MODEL_PRESETS[model]
    assert CommandEncoder(limits)(*values) == encode_command(MitCommand(*values), limits)


def test_command_encoder_on_a_special_command_and_nan() -> None:
    t = uint_to_float(0xFFC, -18.0, 18.0, 12)
    assert CommandEncoder(AK80)(12.5, 50.0, 500.0, 5.0, t) == h("FF FF FF FF FF FF FF FA")
    for i in range(5):
        values = [0.0] * 5
        values[i] = math.nan
        with pytest.raises(ValueError, match="NaN"):
            CommandEncoder(AK80)(*values)


# -- replies -------------------------------------------------------------------------------------


def test_ak_reply_bytes() -> None:
    data = encode_reply(MitReply(3, 0.0, 0.0, 0.0), AK80)
    assert data == h("03 80 00 80 08 00")
    assert reply_motor_id(data, "ak") == 3
    edge = encode_reply(MitReply(7, 99.0, -99.0, 99.0), AK80)
    assert edge == h("07 FF FF 00 0F FF")
    r = decode_reply(edge, AK80)
    assert (r.motor_id, r.position, r.velocity, r.torque) == (7, 12.5, -50.0, 18.0)
    assert r.error_code is None and r.temperature is None


def test_damiao_reply_bytes() -> None:
    data = encode_reply(MitReply(1, 0.0, 0.0, 0.0, error_code=1, temperature=40,
                                 rotor_temperature=35), DM)
    assert data == h("11 80 00 80 08 00 28 23")
    fault = encode_reply(MitReply(2, 0.0, 0.0, 0.0, error_code=0xB, temperature=120), DM)
    assert fault[0] == 0xB2 and fault[6] == 120
    r = decode_reply(fault, DM)
    assert (r.motor_id, r.error_code, r.temperature) == (2, 0xB, 120)
    assert reply_motor_id(fault, "damiao") == 2
    assert reply_motor_id(h("03 80 00 80 08 00"), "damiao") is None
    with pytest.raises(ValueError):
        decode_reply(h("03 80 00 80 08 00"), DM)


# -- Damiao register protocol --------------------------------------------------------------------


def test_register_requests_bytes() -> None:
    # id low, id high, command, rid, value little-endian.
    read = encode_register_frame(RegisterFrame(1, REGISTER_READ, 9))
    assert read == h("01 00 33 09 00 00 00 00")
    # TIMEOUT (uint32, 50 us units): 100 ms = 2000 = 0x7D0.
    write = encode_register_frame(RegisterFrame(1, REGISTER_WRITE, 9, 2000))
    assert write == h("01 00 55 09 D0 07 00 00")
    # PMAX (float32): 12.5 = 0x41480000; an id above one byte spans bytes 0..1.
    pmax = encode_register_frame(RegisterFrame(0x102, REGISTER_WRITE, 21, 12.5))
    assert pmax == h("02 01 55 15 00 00 48 41")
    store = encode_register_frame(RegisterFrame(3, REGISTER_STORE, 1))
    assert store == h("03 00 AA 01 00 00 00 00")


def test_register_replies_decode_per_type() -> None:
    assert decode_register_frame(h("01 00 33 07 11 00 00 00")) == RegisterFrame(1, 0x33, 7, 0x11)
    assert decode_register_frame(h("01 00 55 09 D0 07 00 00")).value == 2000
    f = decode_register_frame(h("02 01 33 15 00 00 48 41"))
    assert (f.motor_id, f.rid, f.value) == (0x102, 21, 12.5)
    assert DAMIAO_REGISTERS[9].name == "TIMEOUT" and DAMIAO_REGISTERS[9].kind == "u32"
    assert DAMIAO_REGISTERS[9].writable and not DAMIAO_REGISTERS[80].writable
    for frame in (RegisterFrame(5, REGISTER_WRITE, 9, 0xFFFF_FFFF),
                  RegisterFrame(5, REGISTER_WRITE, 23, -7.25),
                  RegisterFrame(0x7FF, REGISTER_READ, 80)):
        assert decode_register_frame(encode_register_frame(frame)) == frame


def test_register_frame_errors() -> None:
    with pytest.raises(ValueError, match="8 bytes"):
        decode_register_frame(h("01 00 33 09 00 00 00"))
    with pytest.raises(ValueError, match="not a register command"):
        decode_register_frame(h("01 00 34 09 00 00 00 00"))
    with pytest.raises(ValueError, match="uint32"):
        encode_register_frame(RegisterFrame(1, REGISTER_WRITE, 9, 2**32))
    with pytest.raises(ValueError, match="uint32"):
        encode_register_frame(RegisterFrame(1, REGISTER_WRITE, 9, 0.5))
    with pytest.raises(ValueError, match="finite float"):
        encode_register_frame(RegisterFrame(1, REGISTER_WRITE, 21, math.nan))
    with pytest.raises(ValueError, match="0..0x7FF"):
        encode_register_frame(RegisterFrame(0x800, REGISTER_READ, 9))
    with pytest.raises(ValueError, match="0x33, 0x55 or 0xAA"):
        encode_register_frame(RegisterFrame(1, 0x11, 9))


def test_timeout_register_value() -> None:
    assert timeout_register_value(0.1) == 2000
    assert timeout_register_value(0.0) == 0
    assert timeout_register_value(74e-6) == 1  # rounded to the 50 us step
    assert timeout_register_value(0.0015) == 30
    with pytest.raises(ValueError, match=">= 0"):
        timeout_register_value(-0.1)
    with pytest.raises(ValueError, match="range"):
        timeout_register_value(1e6)


# -- wire bits -----------------------------------------------------------------------------------


def test_wire_bits() -> None:
    # 8-byte standard frame: 34 + 64 = 98 stuffable bits, + 13 fixed; worst case 24 stuff bits.
    frame = can.Message(arbitration_id=1, is_extended_id=False, data=bytes(8))
    assert wire_bits(frame, "none") == 111
    assert wire_bits(frame, "worst") == 111 + 24
    exact = wire_bits(frame, "exact")
    # Counted by hand: SOF + the id's ten leading zeros -> 2 stuff bits; the run of zeros from
    # RTR/IDE/r0 ... DLC's low bits through the 64 data bits -> 13; the CRC (001111101000000)
    # continues the zeros and holds five ones and six zeros -> 2. 17 in all.
    assert exact == 111 + 17
    reply = can.Message(arbitration_id=0, is_extended_id=False, data=h("01 80 00 80 08 00"))
    assert wire_bits(reply, "none") == 34 + 48 + 13
    ext = can.Message(arbitration_id=0x1234567, is_extended_id=True, data=b"")
    assert wire_bits(ext, "none") == 54 + 13
    assert wire_time_s([frame, reply], 1_000_000) == pytest.approx(
        (wire_bits(frame) + wire_bits(reply)) / 1e6)
    with pytest.raises(ValueError):
        wire_bits(frame, "sometimes")


def test_stuffing_known_frame() -> None:
    # id 0x7FF (eleven 1s after SOF): 1 stuff bit after the first five 1s, another after the
    # next five (the stuff bit starts a new run of 0... then RTR=0 etc.); at least 2.
    frame = can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"")
    assert wire_bits(frame, "exact") - wire_bits(frame, "none") >= 2


# -- emulator and codec agree --------------------------------------------------------------------


@pytest.fixture
def rig() -> Iterator[tuple[can.BusABC, MitBusEmulator]]:
    channel = f"frames-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    peer = can.Bus(interface="virtual", channel=channel)
    emulator = MitBusEmulator(peer, [5], "AK80-9")
    emulator.start()
    try:
        yield host, emulator
    finally:
        emulator.stop()
        peer.shutdown()
        host.shutdown()


def _exchange(host: can.BusABC, data: bytes) -> MitReply:
    host.send(can.Message(arbitration_id=5, is_extended_id=False, data=data))
    msg = host.recv(timeout=5.0)
    assert msg is not None
    return decode_reply(msg.data, AK80)


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    p=st.floats(-12.5, 12.5), v=st.floats(-50, 50), kp=st.floats(0, 500), kd=st.floats(0, 5),
    t=st.floats(-18, 18),
)
def test_emulator_decodes_what_the_codec_encodes(
    rig: tuple[can.BusABC, MitBusEmulator], p: float, v: float, kp: float, kd: float, t: float
) -> None:
    host, emulator = rig
    _exchange(host, ENTER_MOTOR_MODE)  # out of motor mode a set-point is answered, not taken
    _exchange(host, encode_command(MitCommand(p, v, kp, kd, t), AK80))
    got = emulator.last_command(5)
    q = quantum(AK80)
    assert abs(got.position - p) <= q.position
    assert abs(got.velocity - v) <= q.velocity
    assert abs(got.kp - kp) <= q.kp
    assert abs(got.kd - kd) <= q.kd
    assert abs(got.torque - t) <= q.torque


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(position=st.floats(-12.0, 12.0))
def test_codec_decodes_what_the_emulator_reports(
    rig: tuple[can.BusABC, MitBusEmulator], position: float
) -> None:
    host, emulator = rig
    emulator.set_position(5, position)
    reply = _exchange(host, EXIT_MOTOR_MODE)  # motor off: it stays where it was put
    assert reply.motor_id == 5
    assert abs(reply.position - position) <= quantum(AK80).position
    assert abs(reply.velocity) <= quantum(AK80).velocity


def test_paced_emulator_never_delivers_before_the_wire_would() -> None:
    # A lower bound only (pacing guarantees it); how late a reply comes is not asserted.
    channel = f"paced-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    peer = can.Bus(interface="virtual", channel=channel)
    emulator = MitBusEmulator(peer, [1, 2, 3, 4, 5, 6], "AK80-9", bitrate=125_000, pace=True)
    emulator.start()
    try:
        frames = [can.Message(arbitration_id=i, is_extended_id=False, data=EXIT_MOTOR_MODE)
                  for i in range(1, 7)]
        t0 = time.monotonic()
        for frame in frames:
            host.send(frame)
        replies = []
        for _ in frames:
            msg = host.recv(timeout=5.0)
            assert msg is not None
            replies.append(msg)
            # Reply k cannot come before commands 1..k and replies 1..k crossed the wire.
            k = len(replies)
            wire = wire_time_s([*frames[:k], *replies], 125_000)
            assert time.monotonic() - t0 >= wire
        assert sorted(r.data[0] for r in replies) == [1, 2, 3, 4, 5, 6]
    finally:
        emulator.stop()
        peer.shutdown()
        host.shutdown()
