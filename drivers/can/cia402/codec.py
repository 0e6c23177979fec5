"""CiA 402 (CANopen drive profile) codec: controlword / statusword, the state machine, PDO
payloads, COB-IDs and unit conversion. Pure functions, no I/O; the driver and the drive
emulator share them.

Theory of operation
-------------------
A CiA 402 drive runs a state machine (:class:`State`) commanded by the controlword (0x6040)
and reported by the statusword (0x6041). The device side of the machine is one table,
:data:`DRIVE_TRANSITIONS` ((state, command) -> next state); the host side is
:data:`PATH_TO_OPERATION_ENABLED` (which command moves a drive one step closer to Operation
Enabled) and :func:`expected_after` (which state a command must lead to: every transition the
driver asks for is checked against it).

Cyclic data travels in PDOs whose layout (:class:`PdoLayout`, a tuple of mapped objects) is
written to the drive's mapping parameters (0x1600.. / 0x1A00..) at configuration time; the
same layout encodes and decodes the 8-byte payloads (little endian, as CANopen is):

=========  ========  ===========================================================
PDO        COB-ID    content (bits)
=========  ========  ===========================================================
RPDO1 CSP  0x200+n   controlword 0x6040 (16), target position 0x607A (32)
RPDO1 CSV  0x200+n   controlword 0x6040 (16), target velocity 0x60FF (32)
TPDO1      0x180+n   statusword 0x6041 (16), position actual 0x6064 (32),
                     torque actual 0x6077 (16)
TPDO2      0x280+n   velocity actual 0x606C (32), error code 0x603F (16),
                     modes of operation display 0x6061 (8)
=========  ========  ===========================================================

All PDOs use transmission type 1 (synchronous): an RPDO takes effect at the next SYNC
(COB-ID 0x080, no data) and the drive sends its TPDOs in answer to every SYNC.

The master's watchdog is CiA 301's heartbeat: the producer sends COB-ID 0x700 + its node id
with one byte, its NMT state (:func:`encode_heartbeat`), every producer time (0x1017); a
consumer entry (0x1016 sub-index 1..n, :func:`encode_consumer_entry`: node id in bits 16-23,
time in ms in bits 0-15) makes a drive watch that node from its first heartbeat on. When no
heartbeat came for the consumer time, the drive signals a heartbeat event (EMCY
:data:`EMCY_HEARTBEAT` 0x8130, :func:`encode_emcy`) and applies 0x6007, the abort connection
option code (:class:`AbortConnection`): a quick stop (0x605A, :func:`quick_stop_reaction`,
decelerating with 0x6085), a fault (0x605E, :func:`fault_reaction`) or Disable Voltage.

Units: positions are drive counts (``counts_per_revolution`` per motor turn), velocities
counts/s (or rpm, see :class:`JointScale`). The joint conversion, symmetric for commands, is::

    motor_rad = 2*pi * counts / counts_per_revolution
    joint     = direction * motor_rad / gear_ratio + offset
    counts    = round((joint - offset) * direction * gear_ratio * counts_per_revolution / (2*pi))
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum, IntEnum
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Final

from jtc_hw.errors import ProtocolError

DEFAULT_EDS: Final = Path(
    str(resources.files("jtc_hw.drivers.can.cia402").joinpath("jtc_hw_drive.eds"))
)
"""The EDS of the emulated drive, shipped with the package (the driver's default)."""

__all__ = [
    "ABORT_CONNECTION_OPTION",
    "CONSUMER_HEARTBEAT_TIME",
    "CONTROLWORD",
    "CONTROLWORD_VALUES",
    "DEFAULT_EDS",
    "DEVICE_TYPE",
    "DRIVE_TRANSITIONS",
    "EMCY_HEARTBEAT",
    "ERROR_CODE",
    "ERROR_DESCRIPTIONS",
    "ERROR_REGISTER",
    "FAULT_REACTION_OPTION",
    "HEARTBEAT_BASE",
    "MODES_OF_OPERATION",
    "MODES_OF_OPERATION_DISPLAY",
    "NMT_ENTER_PRE_OPERATIONAL",
    "NMT_RESET_COMMUNICATION",
    "NMT_RESET_NODE",
    "NMT_START",
    "NMT_STOP",
    "OBJECTS",
    "PATH_TO_OPERATION_ENABLED",
    "POSITION_ACTUAL",
    "PRODUCER_HEARTBEAT_TIME",
    "PROFILE_DECELERATION",
    "QUICK_STOP_DECELERATION",
    "QUICK_STOP_OPTION",
    "RPDO_CSP",
    "RPDO_CSV",
    "STATUSWORD",
    "STATUSWORD_VALUES",
    "SYNC_COB_ID",
    "TARGET_POSITION",
    "TARGET_VELOCITY",
    "TORQUE_ACTUAL",
    "TPDO_FEEDBACK",
    "TPDO_STATUS",
    "VELOCITY_ACTUAL",
    "AbortConnection",
    "Command",
    "JointScale",
    "Mode",
    "NmtState",
    "PdoEntry",
    "PdoLayout",
    "Ramp",
    "State",
    "bootup_cob_id",
    "decode_consumer_entry",
    "decode_controlword",
    "decode_emcy",
    "decode_heartbeat",
    "decode_mapping",
    "decode_nmt",
    "decode_statusword",
    "describe_error",
    "emcy_cob_id",
    "encode_consumer_entry",
    "encode_controlword",
    "encode_emcy",
    "encode_heartbeat",
    "encode_mapping",
    "encode_nmt",
    "encode_statusword",
    "expected_after",
    "fault_reaction",
    "quick_stop_reaction",
    "rpdo_cob_id",
    "tpdo_cob_id",
]

# -- object dictionary indices ------------------------------------------------------------------

DEVICE_TYPE: Final = 0x1000
ERROR_REGISTER: Final = 0x1001
CONSUMER_HEARTBEAT_TIME: Final = 0x1016
PRODUCER_HEARTBEAT_TIME: Final = 0x1017
ABORT_CONNECTION_OPTION: Final = 0x6007
ERROR_CODE: Final = 0x603F
CONTROLWORD: Final = 0x6040
STATUSWORD: Final = 0x6041
QUICK_STOP_OPTION: Final = 0x605A
FAULT_REACTION_OPTION: Final = 0x605E
MODES_OF_OPERATION: Final = 0x6060
MODES_OF_OPERATION_DISPLAY: Final = 0x6061
POSITION_ACTUAL: Final = 0x6064
VELOCITY_ACTUAL: Final = 0x606C
TORQUE_ACTUAL: Final = 0x6077
TARGET_POSITION: Final = 0x607A
PROFILE_DECELERATION: Final = 0x6084
QUICK_STOP_DECELERATION: Final = 0x6085
TARGET_VELOCITY: Final = 0x60FF

OBJECTS: Final[Mapping[int, tuple[int, bool]]] = MappingProxyType({
    ERROR_CODE: (16, False),
    CONTROLWORD: (16, False),
    STATUSWORD: (16, False),
    MODES_OF_OPERATION: (8, True),
    MODES_OF_OPERATION_DISPLAY: (8, True),
    POSITION_ACTUAL: (32, True),
    VELOCITY_ACTUAL: (32, True),
    TORQUE_ACTUAL: (16, True),
    TARGET_POSITION: (32, True),
    TARGET_VELOCITY: (32, True),
})
"""The mappable CiA 402 objects used here: index -> (bits, signed)."""

# -- COB-IDs and NMT --------------------------------------------------------------------------

SYNC_COB_ID: Final = 0x080
NMT_START: Final = 0x01
NMT_STOP: Final = 0x02
NMT_ENTER_PRE_OPERATIONAL: Final = 0x80
NMT_RESET_NODE: Final = 0x81
NMT_RESET_COMMUNICATION: Final = 0x82

_TPDO_BASE: Final = (0x180, 0x280, 0x380, 0x480)
_RPDO_BASE: Final = (0x200, 0x300, 0x400, 0x500)


def _check_node(node_id: int) -> None:
    if not 1 <= node_id <= 127:
        raise ValueError(f"CANopen node id must be 1..127, got {node_id!r}")


def tpdo_cob_id(number: int, node_id: int) -> int:
    """Default COB-ID of TPDO ``number`` (1..4) of ``node_id``.

    Raises:
        ValueError: number or node id out of range.
    """
    _check_node(node_id)
    if not 1 <= number <= 4:
        raise ValueError(f"PDO number must be 1..4, got {number!r}")
    return _TPDO_BASE[number - 1] + node_id


def rpdo_cob_id(number: int, node_id: int) -> int:
    """Default COB-ID of RPDO ``number`` (1..4) of ``node_id``.

    Raises:
        ValueError: number or node id out of range.
    """
    _check_node(node_id)
    if not 1 <= number <= 4:
        raise ValueError(f"PDO number must be 1..4, got {number!r}")
    return _RPDO_BASE[number - 1] + node_id


def emcy_cob_id(node_id: int) -> int:
    """COB-ID of the drive's emergency messages.

    Raises:
        ValueError: node id out of range.
    """
    _check_node(node_id)
    return 0x080 + node_id


def bootup_cob_id(node_id: int) -> int:
    """COB-ID of the drive's boot-up / heartbeat messages (NMT error control).

    Raises:
        ValueError: node id out of range.
    """
    _check_node(node_id)
    return 0x700 + node_id


def encode_nmt(command: int, node_id: int) -> bytes:
    """Payload of an NMT command frame (COB-ID 0): command byte, node id (0: all nodes).

    Raises:
        ValueError: node id out of range.
    """
    if not 0 <= node_id <= 127:
        raise ValueError(f"NMT node id must be 0..127, got {node_id!r}")
    return bytes((command & 0xFF, node_id))


def decode_nmt(data: bytes) -> tuple[int, int]:
    """(command, node id) of an NMT command frame.

    Raises:
        ProtocolError: not two bytes.
    """
    if len(data) != 2:
        raise ProtocolError(f"NMT command must be 2 bytes, got {bytes(data).hex()}")
    return data[0], data[1]


# -- heartbeat (CiA 301 NMT error control) ------------------------------------------------------

HEARTBEAT_BASE: Final = 0x700
"""Heartbeat / boot-up COB-IDs are 0x700 + the producer's node id."""


class NmtState:
    """NMT states, as a heartbeat's one data byte carries them (bit 7, the node-guarding
    toggle bit, is 0 in a heartbeat)."""

    INITIALISING = 0x00  # the boot-up message
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


def encode_heartbeat(state: int) -> bytes:
    """Payload of a heartbeat frame reporting NMT ``state`` (one byte).

    Raises:
        ValueError: not a 7-bit state.
    """
    if not 0 <= state <= 0x7F:
        raise ValueError(f"NMT state must be 0..127, got {state!r}")
    return bytes((state,))


def decode_heartbeat(cob_id: int, data: bytes) -> tuple[int, int] | None:
    """(producer node id, NMT state) of a heartbeat or boot-up frame; None for other frames."""
    node_id = cob_id - HEARTBEAT_BASE
    if not 1 <= node_id <= 127 or len(data) != 1:
        return None
    return node_id, data[0] & 0x7F


def encode_consumer_entry(node_id: int, time_ms: int) -> int:
    """A consumer heartbeat time entry (0x1016 sub-index 1..n, UNSIGNED32): the producer's
    node id in bits 16-23, the time in ms in bits 0-15 (0: the entry is not used).

    Raises:
        ValueError: node id outside 1..127 or time outside 0..65535 ms.
    """
    _check_node(node_id)
    if not 0 <= time_ms <= 0xFFFF:
        raise ValueError(f"consumer heartbeat time must be 0..65535 ms, got {time_ms!r}")
    return (node_id << 16) | time_ms


def decode_consumer_entry(value: int) -> tuple[int, int] | None:
    """(producer node id, time in ms) of a 0x1016 entry; None if the entry is not used
    (time 0, node id 0 or above 127, as CiA 301 says)."""
    node_id, time_ms = (value >> 16) & 0xFF, value & 0xFFFF
    if time_ms == 0 or not 1 <= node_id <= 127:
        return None
    return node_id, time_ms


# -- the state machine ------------------------------------------------------------------------


class State(Enum):
    """The CiA 402 power state machine's states."""

    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"


class Command(Enum):
    """Controlword device-control commands (bits 0-3 and 7)."""

    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    DISABLE_OPERATION = "disable operation"
    ENABLE_OPERATION = "enable operation"
    FAULT_RESET = "fault reset"


class Mode(IntEnum):
    """Modes of operation (0x6060 / 0x6061) supported here."""

    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9


# (mask, value) of the statusword bits 0-3, 5, 6 for each state.
_STATUS_PATTERNS: Final[tuple[tuple[int, int, State], ...]] = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State.SWITCHED_ON),
    (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State.FAULT),
)

STATUSWORD_VALUES: Final[Mapping[State, int]] = MappingProxyType({
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021,
    State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027,
    State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: 0x0008,
})
"""The state bits of the statusword for each state (bit 5 quick stop = 1 where it is defined
as "don't care", bit 4 voltage enabled and the other flags clear)."""

SW_VOLTAGE_ENABLED: Final = 1 << 4
SW_WARNING: Final = 1 << 7
SW_REMOTE: Final = 1 << 9
SW_TARGET_REACHED: Final = 1 << 10
SW_INTERNAL_LIMIT: Final = 1 << 11
SW_FOLLOWING: Final = 1 << 12  # CSP/CSV: drive follows the command value


def decode_statusword(statusword: int) -> State:
    """The state a statusword reports.

    Raises:
        ProtocolError: the bits match no state (not a CiA 402 statusword).
    """
    for mask, value, state in _STATUS_PATTERNS:
        if statusword & mask == value:
            return state
    raise ProtocolError(f"statusword 0x{statusword:04X} matches no CiA 402 state")


def encode_statusword(
    state: State,
    *,
    voltage_enabled: bool = True,
    warning: bool = False,
    remote: bool = True,
    target_reached: bool = False,
    internal_limit: bool = False,
    following: bool = False,
) -> int:
    """A statusword reporting ``state`` with the given flags."""
    word = STATUSWORD_VALUES[state]
    for on, bit in (
        (voltage_enabled, SW_VOLTAGE_ENABLED),
        (warning, SW_WARNING),
        (remote, SW_REMOTE),
        (target_reached, SW_TARGET_REACHED),
        (internal_limit, SW_INTERNAL_LIMIT),
        (following, SW_FOLLOWING),
    ):
        if on:
            word |= bit
    return word


CONTROLWORD_VALUES: Final[Mapping[Command, int]] = MappingProxyType({
    Command.SHUTDOWN: 0x0006,
    Command.SWITCH_ON: 0x0007,
    Command.DISABLE_VOLTAGE: 0x0000,
    Command.QUICK_STOP: 0x0002,
    Command.DISABLE_OPERATION: 0x0007,
    Command.ENABLE_OPERATION: 0x000F,
    Command.FAULT_RESET: 0x0080,
})
"""The controlword sent for each command (bits 0-3, 7; the rest clear).

SWITCH_ON and DISABLE_OPERATION are the same bits: which one the drive performs depends on its
state (Switched On from Ready to Switch On, or back from Operation Enabled). FAULT_RESET acts
on the rising edge of bit 7: send another command first, then this one.
"""

CW_FAULT_RESET: Final = 1 << 7


def encode_controlword(command: Command) -> int:
    """The controlword of ``command`` (see :data:`CONTROLWORD_VALUES`)."""
    return CONTROLWORD_VALUES[command]


def decode_controlword(controlword: int) -> Command:
    """The device-control command a controlword carries (as a drive interprets bits 0-3, 7).

    Bit 7 set reads as FAULT_RESET (its edge is the drive's business). SWITCH_ON and
    DISABLE_OPERATION share a pattern; this returns SWITCH_ON.
    """
    if controlword & CW_FAULT_RESET:
        return Command.FAULT_RESET
    low = controlword & 0x0F
    if low & 0b0010 == 0:
        return Command.DISABLE_VOLTAGE  # xx0x
    if low & 0b0110 == 0b0010:
        return Command.QUICK_STOP  # x01x
    if low & 0b0111 == 0b0110:
        return Command.SHUTDOWN  # x110
    if low == 0b0111:
        return Command.SWITCH_ON
    return Command.ENABLE_OPERATION  # 1111


_S = State
_C = Command

DRIVE_TRANSITIONS: Final[Mapping[tuple[State, Command], State]] = MappingProxyType({
    # Transition numbers of the CiA 402 state diagram in the comments.
    (_S.SWITCH_ON_DISABLED, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,  # 2
    (_S.READY_TO_SWITCH_ON, _C.SWITCH_ON): _S.SWITCHED_ON,  # 3
    (_S.READY_TO_SWITCH_ON, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,  # 3 + 4
    (_S.SWITCHED_ON, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,  # 4
    (_S.OPERATION_ENABLED, _C.SWITCH_ON): _S.SWITCHED_ON,  # 5 (disable operation)
    (_S.SWITCHED_ON, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,  # 6
    (_S.READY_TO_SWITCH_ON, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 7
    (_S.READY_TO_SWITCH_ON, _C.QUICK_STOP): _S.SWITCH_ON_DISABLED,  # 7
    (_S.OPERATION_ENABLED, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,  # 8
    (_S.OPERATION_ENABLED, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 9
    (_S.SWITCHED_ON, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 10
    (_S.SWITCHED_ON, _C.QUICK_STOP): _S.SWITCH_ON_DISABLED,  # 10
    (_S.OPERATION_ENABLED, _C.QUICK_STOP): _S.QUICK_STOP_ACTIVE,  # 11
    (_S.QUICK_STOP_ACTIVE, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 12
    (_S.QUICK_STOP_ACTIVE, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,  # 16
    (_S.FAULT, _C.FAULT_RESET): _S.SWITCH_ON_DISABLED,  # 15 (on the rising edge of bit 7)
})
"""The drive's state machine: (state, command) -> next state. Pairs not listed leave the state
unchanged. Transitions 0/1 (power-up to Switch On Disabled), 13 (any state -> Fault Reaction
Active on an error) and 14 (Fault Reaction Active -> Fault) are the drive's own."""

PATH_TO_OPERATION_ENABLED: Final[Mapping[State, Command]] = MappingProxyType({
    _S.SWITCH_ON_DISABLED: _C.SHUTDOWN,
    _S.READY_TO_SWITCH_ON: _C.SWITCH_ON,
    _S.SWITCHED_ON: _C.ENABLE_OPERATION,
    _S.QUICK_STOP_ACTIVE: _C.DISABLE_VOLTAGE,
})
"""The host's next command toward Operation Enabled from each state that has one (Fault needs
a fault reset, an explicit re-arm; Not Ready to Switch On and Fault Reaction Active are left by
the drive itself). Each step is a single transition of :data:`DRIVE_TRANSITIONS`."""


def expected_after(state: State, command: Command) -> State:
    """The state ``command`` leads to from ``state`` (unchanged if no transition applies)."""
    return DRIVE_TRANSITIONS.get((state, command), state)


# -- errors -----------------------------------------------------------------------------------

ERROR_DESCRIPTIONS: Final[Mapping[int, str]] = MappingProxyType({
    0x0000: "no error",
    0x2310: "continuous over-current",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "excess temperature device",
    0x4310: "excess temperature drive",
    0x5441: "enable input off",
    0x7305: "incremental sensor fault",
    0x8130: "life guard / heartbeat error (the drive lost the master's heartbeat)",
    0x8611: "following error",
    0x8700: "sync controller error (SYNC lost)",
})
"""Error codes (0x603F, EMCY) of the CiA 402 / 301 error code table that the emulator raises
or that are common; others are shown by their class."""

_ERROR_CLASSES: Final[Mapping[int, str]] = MappingProxyType({
    0x1: "generic error",
    0x2: "current",
    0x3: "voltage",
    0x4: "temperature",
    0x5: "device hardware",
    0x6: "device software",
    0x7: "additional modules",
    0x8: "monitoring / communication",
    0x9: "external error",
    0xF: "additional functions",
    0xFF: "device specific",
})


EMCY_HEARTBEAT: Final = 0x8130
"""Error code of a heartbeat event (a consumer's producer fell silent): "life guard error or
heartbeat error", in 0x603F and the EMCY message."""

ERROR_REGISTER_GENERIC: Final = 0x01
ERROR_REGISTER_COMMUNICATION: Final = 0x10


def encode_emcy(code: int, register: int, info: bytes = b"") -> bytes:
    """An EMCY payload: error code (16 bits), error register 0x1001 (8 bits), up to 5 bytes of
    manufacturer-specific information, zero-padded to 8 bytes.

    Raises:
        ValueError: more than 5 bytes of information.
    """
    if len(info) > 5:
        raise ValueError(f"EMCY information is at most 5 bytes, got {len(info)}")
    return struct.pack("<HB", code & 0xFFFF, register & 0xFF) + bytes(info).ljust(5, b"\0")


def decode_emcy(data: bytes) -> tuple[int, int]:
    """(error code, error register) of an EMCY payload (code 0x0000: error reset).

    Raises:
        ProtocolError: shorter than 3 bytes.
    """
    if len(data) < 3:
        raise ProtocolError(f"EMCY message must have at least 3 bytes, got {bytes(data).hex()}")
    code, register = struct.unpack_from("<HB", data)
    return int(code), int(register)


# -- reactions: abort connection, quick stop, fault reaction ------------------------------------


class AbortConnection(IntEnum):
    """0x6007 abort connection option code: what a drive does when it loses its master
    (heartbeat or life-guarding event, bus-off, NMT stopped / reset)."""

    NO_ACTION = 0
    FAULT = 1  # "fault signal": Fault Reaction Active (0x605E), then Fault
    DISABLE_VOLTAGE = 2  # the Disable Voltage command: Switch On Disabled, power stage off
    QUICK_STOP = 3  # the Quick Stop command: Quick Stop Active (0x605A)


class Ramp(Enum):
    """How a drive brings the motor to rest in a quick stop or fault reaction."""

    COAST = "disable drive function (coast, power stage off)"
    SLOW_DOWN = "slow down ramp (0x6084 profile deceleration)"
    QUICK_STOP = "quick stop ramp (0x6085 quick stop deceleration)"
    CURRENT_LIMIT = "current limit"
    VOLTAGE_LIMIT = "voltage limit"


_QUICK_STOP_RAMPS: Final = (
    Ramp.COAST, Ramp.SLOW_DOWN, Ramp.QUICK_STOP, Ramp.CURRENT_LIMIT, Ramp.VOLTAGE_LIMIT,
    Ramp.SLOW_DOWN, Ramp.QUICK_STOP, Ramp.CURRENT_LIMIT, Ramp.VOLTAGE_LIMIT,
)


def quick_stop_reaction(option: int) -> tuple[Ramp, bool]:
    """(ramp, stays in Quick Stop Active) of 0x605A quick stop option code ``option``.

    0: disable drive function; 1-4: slow down on the slow down ramp / quick stop ramp /
    current limit / voltage limit, then Switch On Disabled; 5-8: the same ramps, then stay in
    Quick Stop Active holding the position (the only codes from which Enable Operation
    returns to Operation Enabled, transition 16).

    Raises:
        ValueError: reserved or manufacturer-specific code (not 0..8).
    """
    if not 0 <= option <= 8:
        raise ValueError(f"quick stop option code 0x605A must be 0..8, got {option!r}")
    return _QUICK_STOP_RAMPS[option], option >= 5


def fault_reaction(option: int) -> Ramp:
    """The ramp of 0x605E fault reaction option code ``option`` (0: disable drive function,
    1: slow down ramp, 2: quick stop ramp, 3: current limit, 4: voltage limit); the drive
    then enters Fault (power stage off).

    Raises:
        ValueError: reserved or manufacturer-specific code (not 0..4).
    """
    if not 0 <= option <= 4:
        raise ValueError(f"fault reaction option code 0x605E must be 0..4, got {option!r}")
    return _QUICK_STOP_RAMPS[option]


def describe_error(code: int) -> str:
    """A short description of error code ``code`` (``0x4310 excess temperature drive``)."""
    text = ERROR_DESCRIPTIONS.get(code)
    if text is None:
        text = _ERROR_CLASSES.get(code >> 12, "unknown") + " error"
    return f"0x{code:04X} {text}"


# -- PDO layouts ------------------------------------------------------------------------------


@dataclass(frozen=True)
class PdoEntry:
    """One mapped object: index, subindex, size in bits, signedness."""

    index: int
    subindex: int
    bits: int
    signed: bool

    @classmethod
    def of(cls, index: int) -> PdoEntry:
        """The entry for a known CiA 402 object (see :data:`OBJECTS`).

        Raises:
            KeyError: unknown object.
        """
        bits, signed = OBJECTS[index]
        return cls(index, 0, bits, signed)


_FORMATS: Final[Mapping[tuple[int, bool], str]] = MappingProxyType({
    (8, False): "B", (8, True): "b", (16, False): "H", (16, True): "h",
    (32, False): "I", (32, True): "i",
})


@dataclass(frozen=True)
class PdoLayout:
    """The objects mapped into one PDO, in order (at most 64 bits)."""

    entries: tuple[PdoEntry, ...]

    def __post_init__(self) -> None:
        if sum(e.bits for e in self.entries) > 64:
            raise ValueError("a PDO carries at most 64 bits")
        for e in self.entries:
            if (e.bits, e.signed) not in _FORMATS:
                raise ValueError(f"unsupported PDO entry size {e.bits} bits")
        fmt = "<" + "".join(_FORMATS[(e.bits, e.signed)] for e in self.entries)
        object.__setattr__(self, "_struct", struct.Struct(fmt))

    @classmethod
    def of(cls, *indices: int) -> PdoLayout:
        """A layout of known objects (see :data:`OBJECTS`)."""
        return cls(tuple(PdoEntry.of(i) for i in indices))

    @property
    def size(self) -> int:
        """Payload length, bytes."""
        return int(self._struct.size)  # type: ignore[attr-defined]

    def encode(self, *values: int) -> bytes:
        """The payload carrying ``values`` (one per entry; wrapped to each entry's width).

        Raises:
            ValueError: not one value per entry.
        """
        if len(values) != len(self.entries):
            raise ValueError(f"expected {len(self.entries)} values, got {len(values)}")
        wrapped = [_wrap(v, e.bits, e.signed) for v, e in zip(values, self.entries, strict=True)]
        data: bytes = self._struct.pack(*wrapped)  # type: ignore[attr-defined]
        return data

    def decode(self, data: bytes | bytearray) -> tuple[int, ...]:
        """The values of a payload, one per entry.

        Raises:
            ProtocolError: the payload length does not match the layout.
        """
        if len(data) != self.size:
            raise ProtocolError(
                f"PDO payload {bytes(data).hex()} has {len(data)} bytes, the mapping "
                f"expects {self.size}"
            )
        values: tuple[int, ...] = self._struct.unpack(data)  # type: ignore[attr-defined]
        return values

    def mapping(self) -> tuple[int, ...]:
        """The mapping parameter values (0x1600/0x1A00 subindex 1..n) of this layout."""
        return tuple(encode_mapping(e) for e in self.entries)


def _wrap(value: int, bits: int, signed: bool) -> int:
    value = int(value) & ((1 << bits) - 1)
    if signed and value >= 1 << (bits - 1):
        value -= 1 << bits
    return value


def encode_mapping(entry: PdoEntry) -> int:
    """The 32-bit mapping parameter value: index << 16 | subindex << 8 | bits."""
    return (entry.index << 16) | (entry.subindex << 8) | entry.bits


def decode_mapping(value: int) -> tuple[int, int, int]:
    """(index, subindex, bits) of a 32-bit mapping parameter value."""
    return (value >> 16) & 0xFFFF, (value >> 8) & 0xFF, value & 0xFF


RPDO_CSP: Final = PdoLayout.of(CONTROLWORD, TARGET_POSITION)
"""RPDO1 in cyclic synchronous position mode."""
RPDO_CSV: Final = PdoLayout.of(CONTROLWORD, TARGET_VELOCITY)
"""RPDO1 in cyclic synchronous velocity mode."""
TPDO_STATUS: Final = PdoLayout.of(STATUSWORD, POSITION_ACTUAL, TORQUE_ACTUAL)
"""TPDO1: statusword, position actual, torque actual."""
TPDO_FEEDBACK: Final = PdoLayout.of(VELOCITY_ACTUAL, ERROR_CODE, MODES_OF_OPERATION_DISPLAY)
"""TPDO2: velocity actual, error code, modes of operation display."""


# -- units ------------------------------------------------------------------------------------

TWO_PI: Final = 2.0 * math.pi
_INT32_MIN: Final = -(1 << 31)
_INT32_MAX: Final = (1 << 31) - 1


@dataclass(frozen=True)
class JointScale:
    """Conversion between drive units and one joint's SI units (formula in the module doc).

    Attributes:
        counts_per_revolution: position counts per motor revolution (> 0).
        gear_ratio: motor turns per joint turn (> 0).
        direction: +1 or -1.
        offset: joint position at motor count 0, rad.
        velocity_unit: ``"counts_per_second"`` or ``"rpm"`` (motor revolutions per minute)
            for 0x606C / 0x60FF.
    """

    counts_per_revolution: int
    gear_ratio: float = 1.0
    direction: int = 1
    offset: float = 0.0
    velocity_unit: str = "counts_per_second"

    def __post_init__(self) -> None:
        if self.counts_per_revolution <= 0 or not self.gear_ratio > 0.0:
            raise ValueError("counts_per_revolution and gear_ratio must be > 0")
        if self.direction not in (1, -1):
            raise ValueError(f"direction must be 1 or -1, got {self.direction!r}")
        if self.velocity_unit not in ("counts_per_second", "rpm"):
            raise ValueError(f"unknown velocity unit {self.velocity_unit!r}")

    @property
    def rad_per_count(self) -> float:
        """Joint radians per drive count (unsigned)."""
        return TWO_PI / (self.counts_per_revolution * self.gear_ratio)

    @property
    def rad_s_per_velocity_unit(self) -> float:
        """Joint rad/s per velocity unit (unsigned)."""
        if self.velocity_unit == "rpm":
            return TWO_PI / 60.0 / self.gear_ratio
        return self.rad_per_count

    def position(self, counts: int) -> float:
        """Joint position, rad, of a drive position in counts."""
        return self.direction * counts * self.rad_per_count + self.offset

    def position_counts(self, position: float) -> int:
        """Drive counts of a joint position (rounded, clamped to int32)."""
        counts = round((position - self.offset) * self.direction / self.rad_per_count)
        return max(_INT32_MIN, min(_INT32_MAX, counts))

    def velocity(self, value: int) -> float:
        """Joint velocity, rad/s, of a drive velocity value."""
        return self.direction * value * self.rad_s_per_velocity_unit

    def velocity_value(self, velocity: float) -> int:
        """Drive velocity value of a joint velocity (rounded, clamped to int32)."""
        value = round(velocity * self.direction / self.rad_s_per_velocity_unit)
        return max(_INT32_MIN, min(_INT32_MAX, value))

