"""Our packet bytes equal the ones Feetech's SDK (``scservo_sdk``) sends, and the SDK reads ours.

The SDK talks to a :class:`WirePort`: a test double of the serial port that implements the
``PortHandler`` methods the packet handler calls, records every write and serves queued
answers. The SDK itself runs unmodified.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from jtc_hw.drivers.feetech import codec as fc
from jtc_hw.drivers.feetech import control_table as ct

scs = pytest.importorskip("scservo_sdk", reason="feetech-servo-sdk (jtc_hw[feetech]) is missing")


class WirePort:
    """The serial port as the SDK sees it: writes are recorded, reads come from ``answers``."""

    def __init__(self, answers: bytes = b"") -> None:
        self.is_using = False
        self.written: list[bytes] = []
        self._rx = bytearray(answers)

    def clearPort(self) -> None:  # noqa: N802 (the SDK's name)
        pass

    def writePort(self, packet: list[int]) -> int:  # noqa: N802
        self.written.append(bytes(packet))
        return len(packet)

    def readPort(self, length: int) -> bytes:  # noqa: N802
        chunk = bytes(self._rx[:length])
        del self._rx[:length]
        return chunk

    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802
        pass

    def setPacketTimeoutMillis(self, msec: float) -> None:  # noqa: N802
        pass

    def isPacketTimeout(self) -> bool:  # noqa: N802
        return not self._rx  # nothing more will come


@pytest.fixture(params=[ct.STS_SMS, ct.SCS], ids=["sts", "scs"])
def series(request: pytest.FixtureRequest) -> ct.Series:
    result: ct.Series = request.param
    return result


@pytest.fixture
def handler(series: ct.Series) -> Iterator[Any]:
    # PacketHandler(end) sets a module global of the SDK: put the default back afterwards.
    yield scs.PacketHandler(series.sdk_protocol_end)
    scs.SCS_SETEND(0)


def test_ping_and_model_number_read(handler: Any, series: ct.Series) -> None:
    order = series.byte_order
    port = WirePort(fc.encode_status(3) + fc.encode_status(3, 0, fc.pack_word(777, 2, order)))
    model, result, error = handler.ping(port, 3)
    assert (model, result, error) == (777, scs.COMM_SUCCESS, 0)
    assert port.written == [fc.encode_ping(3), fc.encode_read(3, 3, 2)]


def test_read_word(handler: Any, series: ct.Series) -> None:
    register = series.register("present_position")
    port = WirePort(fc.encode_status(1, 0, fc.encode_value(register, 1000, series.byte_order)))
    value, result, error = handler.read2ByteTxRx(port, 1, register.address)
    assert (value, result, error) == (1000, scs.COMM_SUCCESS, 0)
    assert port.written == [fc.encode_read(1, register.address, 2)]


def test_the_sdk_hands_up_the_status_error_bits(handler: Any) -> None:
    port = WirePort(fc.encode_status(1, fc.StatusError.OVERLOAD, b"\x00"))
    _, result, error = handler.read1ByteTxRx(port, 1, 63)
    assert result == scs.COMM_SUCCESS
    assert error == fc.StatusError.OVERLOAD
    assert "Overload" in handler.getRxPacketError(error)


def test_a_bad_checksum_is_corrupt_for_the_sdk_too(handler: Any) -> None:
    good = fc.encode_status(1, 0, b"\x05")
    bad = good[:-1] + bytes((good[-1] ^ 0xFF,))
    assert handler.read1ByteTxRx(WirePort(bad), 1, 63)[1] == scs.COMM_RX_CORRUPT
    assert [p.checksum_ok for p in fc.Decoder(status=True).feed(bad)] == [False]


@pytest.mark.parametrize("value", [0, 2048, 4095, 513])
def test_write_and_reg_write_and_action(handler: Any, series: ct.Series, value: int) -> None:
    order = series.byte_order
    port = WirePort(fc.encode_status(2) * 2)
    handler.write2ByteTxRx(port, 2, 42, value)
    handler.regWriteTxRx(port, 2, 42, 2, list(fc.pack_word(value, 2, order)))
    handler.action(port, fc.BROADCAST_ID)
    data = fc.pack_word(value, 2, order)
    assert port.written == [fc.encode_write(2, 42, data), fc.encode_reg_write(2, 42, data),
                            fc.encode_action()]


def test_sync_write(handler: Any, series: ct.Series) -> None:
    order = series.byte_order
    goals = {1: 100, 2: 2048, 6: 4000}
    writer = scs.GroupSyncWrite(WirePort(), handler, 42, 2)
    for servo_id, goal in goals.items():
        assert writer.addParam(servo_id, list(fc.pack_word(goal, 2, order)))
    assert writer.txPacket() == scs.COMM_SUCCESS
    ours = fc.encode_sync_write(42, 2, {i: fc.pack_word(g, 2, order) for i, g in goals.items()})
    assert writer.port.written == [ours]


def test_sync_read_of_the_sts_present_block() -> None:
    handler = scs.PacketHandler(ct.STS_SMS.sdk_protocol_end)
    sts = ct.STS_SMS
    position, velocity = sts.register("present_position"), sts.register("present_velocity")
    answers = b"".join(
        fc.encode_status(i, 0, fc.encode_value(position, p, sts.byte_order)
                         + fc.encode_value(velocity, v, sts.byte_order))
        for i, p, v in ((1, 2048, -120), (2, 17, 3000)))
    port = WirePort(answers)
    reader = scs.GroupSyncRead(port, handler, position.address, 4)
    for servo_id in (1, 2):
        reader.addParam(servo_id)
    assert reader.txRxPacket() == scs.COMM_SUCCESS
    assert port.written == [fc.encode_sync_read(position.address, 4, [1, 2])]
    # The SDK hands up raw words; the sign is ours to decode.
    raw = reader.getData(1, velocity.address, 2)
    assert fc.decode_sign_magnitude(raw, 15) == -120
    assert reader.getData(2, position.address, 2) == 17
