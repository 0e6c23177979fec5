"""CiA 402 codec: exact controlword / statusword values, the state machine table, PDO bytes."""

from __future__ import annotations

import math

import pytest

from jtc_hw.drivers.can.cia402 import codec as c4
from jtc_hw.drivers.can.cia402.codec import Command, State
from jtc_hw.errors import ProtocolError

# -- statusword ----------------------------------------------------------------------------------

STATUSWORDS = [
    # (statusword as a drive sends it, state)
    (0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x0250, State.SWITCH_ON_DISABLED),  # remote + voltage enabled bits set
    (0x0040, State.SWITCH_ON_DISABLED),
    (0x0060, State.SWITCH_ON_DISABLED),  # bit 5 is "don't care" here
    (0x0221, State.READY_TO_SWITCH_ON),
    (0x0231, State.READY_TO_SWITCH_ON),
    (0x0233, State.SWITCHED_ON),
    (0x0237, State.OPERATION_ENABLED),
    (0x1637, State.OPERATION_ENABLED),  # following + target reached + remote
    (0x0217, State.QUICK_STOP_ACTIVE),
    (0x021F, State.FAULT_REACTION_ACTIVE),
    (0x0218, State.FAULT),
    (0x0238, State.FAULT),
]


@pytest.mark.parametrize(("word", "state"), STATUSWORDS)
def test_decode_statusword(word: int, state: State) -> None:
    assert c4.decode_statusword(word) is state


def test_statusword_that_matches_no_state_is_a_protocol_error() -> None:
    with pytest.raises(ProtocolError, match="0x0001"):
        c4.decode_statusword(0x0001)


@pytest.mark.parametrize("state", list(State))
def test_encode_statusword_round_trips(state: State) -> None:
    assert c4.decode_statusword(c4.encode_statusword(state)) is state


def test_encode_statusword_flags() -> None:
    assert c4.encode_statusword(State.OPERATION_ENABLED) == 0x0237
    assert c4.encode_statusword(State.OPERATION_ENABLED, following=True) == 0x1237
    assert c4.encode_statusword(State.FAULT) == 0x0218
    assert c4.encode_statusword(State.SWITCH_ON_DISABLED, voltage_enabled=False) == 0x0240
    assert c4.encode_statusword(State.SWITCHED_ON, remote=False, warning=True) == 0x00B3


# -- controlword ---------------------------------------------------------------------------------

CONTROLWORDS = [
    (Command.SHUTDOWN, 0x0006),
    (Command.SWITCH_ON, 0x0007),
    (Command.DISABLE_VOLTAGE, 0x0000),
    (Command.QUICK_STOP, 0x0002),
    (Command.DISABLE_OPERATION, 0x0007),
    (Command.ENABLE_OPERATION, 0x000F),
    (Command.FAULT_RESET, 0x0080),
]


@pytest.mark.parametrize(("command", "word"), CONTROLWORDS)
def test_encode_controlword(command: Command, word: int) -> None:
    assert c4.encode_controlword(command) == word


@pytest.mark.parametrize(
    ("word", "command"),
    [
        (0x0006, Command.SHUTDOWN),
        (0x000E, Command.SHUTDOWN),  # bit 3 don't care
        (0x0007, Command.SWITCH_ON),
        (0x000F, Command.ENABLE_OPERATION),
        (0x0000, Command.DISABLE_VOLTAGE),
        (0x000D, Command.DISABLE_VOLTAGE),  # bit 1 clear
        (0x0002, Command.QUICK_STOP),
        (0x000B, Command.QUICK_STOP),
        (0x0080, Command.FAULT_RESET),
        (0x008F, Command.FAULT_RESET),
    ],
)
def test_decode_controlword(word: int, command: Command) -> None:
    assert c4.decode_controlword(word) is command


# -- the state machine ----------------------------------------------------------------------------


def test_path_to_operation_enabled_uses_only_table_transitions() -> None:
    state = State.SWITCH_ON_DISABLED
    words = []
    while state is not State.OPERATION_ENABLED:
        command = c4.PATH_TO_OPERATION_ENABLED[state]
        words.append(c4.encode_controlword(command))
        nxt = c4.expected_after(state, command)
        assert nxt is not state
        state = nxt
    assert words == [0x0006, 0x0007, 0x000F]


def test_every_path_step_is_a_drive_transition() -> None:
    for state, command in c4.PATH_TO_OPERATION_ENABLED.items():
        assert (state, command) in c4.DRIVE_TRANSITIONS


@pytest.mark.parametrize(
    ("state", "command", "after"),
    [
        (State.OPERATION_ENABLED, Command.DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),
        (State.OPERATION_ENABLED, Command.QUICK_STOP, State.QUICK_STOP_ACTIVE),
        (State.OPERATION_ENABLED, Command.SHUTDOWN, State.READY_TO_SWITCH_ON),
        (State.OPERATION_ENABLED, Command.SWITCH_ON, State.SWITCHED_ON),
        (State.FAULT, Command.FAULT_RESET, State.SWITCH_ON_DISABLED),
        (State.FAULT, Command.ENABLE_OPERATION, State.FAULT),  # no way out but a reset
        (State.SWITCH_ON_DISABLED, Command.ENABLE_OPERATION, State.SWITCH_ON_DISABLED),
    ],
)
def test_drive_transitions(state: State, command: Command, after: State) -> None:
    assert c4.expected_after(state, command) is after


# -- PDO payloads ---------------------------------------------------------------------------------


def test_rpdo_csp_bytes() -> None:
    assert c4.RPDO_CSP.size == 6
    assert c4.RPDO_CSP.encode(0x000F, 0x12345678) == bytes.fromhex("0f00 78563412")
    assert c4.RPDO_CSP.encode(0x0006, -1) == bytes.fromhex("0600 ffffffff")
    assert c4.RPDO_CSP.decode(bytes.fromhex("0f00 00800000")) == (0x000F, 0x8000)


def test_rpdo_csv_bytes() -> None:
    assert c4.RPDO_CSV.encode(0x000F, -1000) == bytes.fromhex("0f00 18fcffff")


def test_tpdo_status_bytes() -> None:
    data = bytes.fromhex("3712 00000200 9cff")
    assert c4.TPDO_STATUS.decode(data) == (0x1237, 0x20000, -100)
    assert c4.TPDO_STATUS.encode(0x1237, 0x20000, -100) == data


def test_tpdo_feedback_bytes() -> None:
    data = bytes.fromhex("00f0ffff 1043 08")
    assert c4.TPDO_FEEDBACK.decode(data) == (-4096, 0x4310, 8)
    assert c4.TPDO_FEEDBACK.size == 7


def test_pdo_wraps_out_of_range_values() -> None:
    assert c4.RPDO_CSP.encode(0x1000F, 1 << 32) == bytes.fromhex("0f00 00000000")


def test_pdo_payload_length_mismatch_is_a_protocol_error() -> None:
    with pytest.raises(ProtocolError, match="expects 8"):
        c4.TPDO_STATUS.decode(b"\x00" * 6)


def test_mapping_values() -> None:
    assert c4.RPDO_CSP.mapping() == (0x60400010, 0x607A0020)
    assert c4.TPDO_STATUS.mapping() == (0x60410010, 0x60640020, 0x60770010)
    assert c4.TPDO_FEEDBACK.mapping() == (0x606C0020, 0x603F0010, 0x60610008)
    assert c4.decode_mapping(0x607A0020) == (0x607A, 0, 32)


def test_layout_over_64_bits_is_rejected() -> None:
    with pytest.raises(ValueError, match="64 bits"):
        c4.PdoLayout.of(c4.POSITION_ACTUAL, c4.VELOCITY_ACTUAL, c4.STATUSWORD)


def test_cob_ids_and_nmt() -> None:
    assert c4.tpdo_cob_id(1, 5) == 0x185
    assert c4.tpdo_cob_id(2, 5) == 0x285
    assert c4.rpdo_cob_id(1, 5) == 0x205
    assert c4.emcy_cob_id(5) == 0x085
    assert c4.bootup_cob_id(5) == 0x705
    assert c4.encode_nmt(c4.NMT_RESET_COMMUNICATION, 5) == bytes.fromhex("8205")
    assert c4.encode_nmt(c4.NMT_START, 0) == bytes.fromhex("0100")
    assert c4.decode_nmt(bytes.fromhex("0105")) == (1, 5)
    with pytest.raises(ValueError):
        c4.tpdo_cob_id(1, 0)
    with pytest.raises(ProtocolError):
        c4.decode_nmt(b"\x01")


# -- heartbeat, EMCY, reactions --------------------------------------------------------------------


def test_heartbeat_frames() -> None:
    # A master at node 127 reporting operational: COB-ID 0x77F, one byte 0x05.
    assert c4.bootup_cob_id(127) == 0x77F
    assert c4.encode_heartbeat(c4.NmtState.OPERATIONAL) == b"\x05"
    assert c4.decode_heartbeat(0x77F, b"\x05") == (127, 5)
    assert c4.decode_heartbeat(0x703, b"\x00") == (3, 0)  # a boot-up message
    assert c4.decode_heartbeat(0x700, b"\x05") is None  # node id 0 does not exist
    assert c4.decode_heartbeat(0x705, b"\x05\x00") is None  # not one byte
    assert c4.decode_heartbeat(0x185, b"\x05") is None
    with pytest.raises(ValueError):
        c4.encode_heartbeat(0x80)


def test_consumer_heartbeat_entry_layout() -> None:
    # CiA 301 0x1016 sub-index 1..n: node id in bits 16-23, time in ms in bits 0-15.
    assert c4.encode_consumer_entry(127, 100) == 0x007F0064
    assert c4.decode_consumer_entry(0x007F0064) == (127, 100)
    assert c4.decode_consumer_entry(0x007F0000) is None  # time 0: not used
    assert c4.decode_consumer_entry(0x00000064) is None  # node id 0: not used
    assert c4.decode_consumer_entry(0x00800064) is None  # node id above 127: not used
    with pytest.raises(ValueError):
        c4.encode_consumer_entry(127, 0x10000)
    with pytest.raises(ValueError):
        c4.encode_consumer_entry(0, 100)


def test_emcy_payload() -> None:
    data = c4.encode_emcy(c4.EMCY_HEARTBEAT, 0x11, b"\x7f")
    assert data == bytes.fromhex("3081117f00000000")
    assert c4.decode_emcy(data) == (0x8130, 0x11)
    with pytest.raises(ProtocolError):
        c4.decode_emcy(b"\x30\x81")
    with pytest.raises(ValueError):
        c4.encode_emcy(0x8130, 0x11, bytes(6))


def test_reaction_option_codes() -> None:
    assert [int(a) for a in c4.AbortConnection] == [0, 1, 2, 3]
    assert c4.quick_stop_reaction(0) == (c4.Ramp.COAST, False)
    assert c4.quick_stop_reaction(2) == (c4.Ramp.QUICK_STOP, False)
    assert c4.quick_stop_reaction(5) == (c4.Ramp.SLOW_DOWN, True)
    assert c4.quick_stop_reaction(6) == (c4.Ramp.QUICK_STOP, True)
    assert c4.quick_stop_reaction(7) == (c4.Ramp.CURRENT_LIMIT, True)
    assert c4.fault_reaction(0) is c4.Ramp.COAST
    assert c4.fault_reaction(2) is c4.Ramp.QUICK_STOP
    for bad in (-1, 9):
        with pytest.raises(ValueError, match="0x605A"):
            c4.quick_stop_reaction(bad)
    with pytest.raises(ValueError, match="0x605E"):
        c4.fault_reaction(5)


def test_describe_error() -> None:
    assert c4.describe_error(0x4310) == "0x4310 excess temperature drive"
    assert c4.describe_error(0x4999) == "0x4999 temperature error"


# -- units ---------------------------------------------------------------------------------------


def test_joint_scale_formula() -> None:
    scale = c4.JointScale(4096, gear_ratio=2.0, direction=-1, offset=0.5)
    # joint = direction * (2 pi counts / cpr) / gear + offset
    assert scale.position(4096) == pytest.approx(-math.pi + 0.5)
    assert scale.position_counts(-math.pi + 0.5) == 4096
    assert scale.position_counts(0.5) == 0
    assert scale.velocity(4096) == pytest.approx(-math.pi)
    assert scale.velocity_value(-math.pi) == 4096


def test_joint_scale_rpm_and_clamping() -> None:
    scale = c4.JointScale(131072, velocity_unit="rpm")
    assert scale.velocity(60) == pytest.approx(2 * math.pi)
    assert scale.velocity_value(2 * math.pi) == 60
    assert scale.position_counts(1e12) == (1 << 31) - 1
    with pytest.raises(ValueError):
        c4.JointScale(0)
    with pytest.raises(ValueError):
        c4.JointScale(10, direction=0)
