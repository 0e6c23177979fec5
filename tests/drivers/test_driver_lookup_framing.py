"""The pieces the serial-servo drivers share: name lookup errors and the decoders' buffer."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from jtc_hw.drivers.dynamixel import control_table as dxl
from jtc_hw.drivers.dynamixel import packets as dxl_packets
from jtc_hw.drivers.feetech import codec as fee_codec
from jtc_hw.drivers.feetech import control_table as fee
from jtc_hw.drivers.lookup import NamedKeyError, did_you_mean


def test_did_you_mean_names_the_closest_known_name() -> None:
    hint = did_you_mean("goal_positon", ["goal_position", "id"])
    assert hint == " (did you mean 'goal_position'?)"
    assert did_you_mean("zzz", ["goal_position"]) == ""


@pytest.mark.parametrize(("lookup", "text"), [
    (lambda: dxl.model_by_name("XM430-W35"), "unknown Dynamixel model 'XM430-W35' (did you mean"),
    (lambda: dxl.MODELS["XM430-W350"].register("goal_positon"), "(did you mean 'goal_position'?)"),
    (lambda: fee.model_by_name("STS3251"), "unknown Feetech model 'STS3251' (did you mean"),
    (lambda: fee.STS_SMS.register("lok"), "no register 'lok' (did you mean 'lock'?)"),
])
def test_both_drivers_raise_a_key_error_that_reads_as_a_sentence(
    lookup: Callable[[], object], text: str
) -> None:
    with pytest.raises(KeyError) as caught:
        lookup()
    assert isinstance(caught.value, NamedKeyError)
    assert text in str(caught.value)
    assert not str(caught.value).startswith("'")


@pytest.mark.parametrize("decoder", [dxl_packets.Decoder(), fee_codec.Decoder(status=False)],
                         ids=["dynamixel", "feetech"])
def test_both_decoders_hold_a_partial_frame_and_count_a_reset_as_junk(
    decoder: dxl_packets.Decoder | fee_codec.Decoder,
) -> None:
    frame = (dxl_packets.encode_instruction(1, dxl_packets.Instruction.PING)
             if isinstance(decoder, dxl_packets.Decoder) else fee_codec.encode_ping(1))
    assert decoder.feed(frame[:-2]) == []
    assert decoder.pending == len(frame) - 2
    decoder.reset()
    assert (decoder.pending, decoder.junk_bytes) == (0, len(frame) - 2)
    assert len(decoder.feed(frame)) == 1
    assert decoder.junk_bytes == len(frame) - 2
