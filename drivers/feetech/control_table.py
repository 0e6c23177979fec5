"""Feetech STS/SMS and SCS memory tables: addresses, sizes, areas, signs, units, models.

Theory of operation
-------------------
A Feetech servo exposes a byte-addressed *memory table*. Addresses 0..39 are EEPROM (kept over
power cycles; a write is only stored while the *lock* register reads 0), 40 and up are RAM. The
two families this driver knows share the layout of the common registers but differ in three
ways that matter on the wire::

                       STS / SMS (STS3215, STS3250)      SCS (SCS0009)
    word byte order    little endian (SDK end 0)         big endian (SDK end 1)
    negative values    sign-magnitude, see below         none (no register carries a sign)
    lock register      55                                48
    sync read (0x82)   yes                               no: read servo by servo
    broadcast ping     yes                               no: ping id by id

Sign-magnitude (STS/SMS only): bit ``k`` of the raw value is the sign and the bits below it the
magnitude; ``k`` is 15 for positions and speeds, 10 for present load, 11 for the homing offset.
``-0`` (the sign bit alone) decodes to 0. :attr:`Register.sign_bit` holds ``k`` (``None``: plain
unsigned); :mod:`.codec` does the arithmetic.

Units. Positions count encoder steps: 4096 per output turn on STS3215/STS3250, 1024 over 300
degrees on SCS0009. The STS/SMS speed registers count steps/s (Feetech's SMS_STS examples drive
``V=2400`` "steps/s"; 50 steps/s = 0.732 rev/min on a 4096-step servo), acceleration 100
steps/s^2 per count. The SCS speed registers count 0.059 rev/min (Feetech's SCSCL examples,
``V=1500*0.059=88.5rpm``, tested on an SCS15; not confirmed on an SCS0009 manual). Present
load is 0.1 % of full output (sign bit 10), present current 6.5 mA (STS/SMS), voltage 0.1 V,
temperature 1 degC. The STS/SMS Phase byte (18) bit 2 switches the speed unit (0: the default
above) and bit 4 the angle feedback to multi-turn; the driver expects both clear (multi-turn /
step mode is out of scope; LeRobot clears bit 4 on STS3215 so that positions stay in
0..4095, commit a656a982 "fix(feetech): motor position readings overflow").

Where the sources differ
------------------------
- Baud Rate register values 5..7: Feetech's SDK headers (SMS_STS.h, SCSCL.h) say 76800, 57600,
  38400; LeRobot's ``*_BAUDRATE_TABLE`` says 57600, 38400, 19200. 0..4 agree (1M, 500k, 250k,
  128k, 115200). :data:`BAUD_RATES` follows Feetech.
- STS/SMS address 24: LeRobot reads Minimum_Startup_Force as 2 bytes (24..25); a transcription
  of Feetech's STS table gives it 1 byte and puts an integral limit at 25. Kept as LeRobot has
  it (the driver never writes it).
- Hts (83) is valid from SMS firmware 2.54 on, 0 before (LeRobot's table comment).
- SCS registers: LeRobot lists no sign-magnitude register for the SCS series and no present
  current; followed here.

Notes for the SDK wrapper (``scservo_sdk``, PyPI ``feetech-servo-sdk`` 1.0.0)
-------------------------------------------------------------------------
**The packet timeout.** The PyPI SDK's ``PortHandler.setPacketTimeout(n)`` allows
``tx_time_per_byte * n + LATENCY_TIMER * 2 + 2`` ms with ``LATENCY_TIMER = 16``: the wire time
of the expected status bytes plus a fixed 34 ms (it is the Dynamixel SDK's formula, where 16 ms
is an FTDI adapter's default USB latency timer). LeRobot replaces the method on its port
instance (``patch_setPacketTimeout`` in ``src/lerobot/motors/feetech/feetech.py``) with
``tx_time_per_byte * n + tx_time_per_byte * 3 + 50`` ms, citing Feetech's issue
gitee.com/ftservo/SCServoSDK/issues/IBY2S6 and saying that the fix exists in Feetech's own
FTServo_Python, which is not on PyPI. Feetech's fixed ``port_handler.py`` (ftservo/FTServo_Python
commit cb07f766) indeed allows ``tx_time_per_byte * (n + 3) + LATENCY_TIMER + 20`` ms with
``LATENCY_TIMER = 50``, i.e. 70 ms, and its ``writePort`` now flushes (waits for the bytes to
leave) and drops the adapter's echo before the timer starts. Read together (an inference:
the issue page itself was not reachable from here), the reasons are: the timer starts when
``writePort`` returns, before the instruction has left the USB adapter, and the 34 ms
allowance does not cover a servo's reply (notably after an EEPROM write) plus the adapter's
latency; the status byte count also omits the reply's framing. A reply that arrives after the
deadline is reported as ``COMM_RX_TIMEOUT`` (nothing read) or ``COMM_RX_CORRUPT`` (part read)
and its tail is left in the input buffer for the next transaction. The wrapper should
therefore install its own deadline, computed from the wire time of both packets, the return
delay register and an adapter latency allowance, and clear the input buffer after a failed
transaction.

**Byte order is process-global.** ``PacketHandler(end)`` stores ``end`` in a module global of
``scservo_def`` (``SCS_SETEND``) that every word packing helper reads, so creating an SCS
handler (end 1) flips the byte order of an STS handler already made in the same process. The
wrapper must pack words itself (:func:`.codec.pack_word`) or allow one series per process.

**The status packet's error byte.** ``rxPacket`` rejects a status whose error byte exceeds
0x7F as junk, and the ``getRxPacketError`` text reports only the first set bit.

**Wall clock.** The SDK times packets with ``time.time()`` (milliseconds), so a clock step
during a transaction shortens or stretches its timeout.

Sources
-------
- LeRobot ``huggingface/lerobot`` at 7427f31801f944f5ec9ce53cda02862ce7d1638b:
  ``src/lerobot/motors/feetech/tables.py`` (addresses, sizes, sign bits, model numbers,
  resolutions, SDK protocol end per model, which links Feetech's STS/SMS and SCSCL e-manuals at
  doc.feetech.cn), ``src/lerobot/motors/feetech/feetech.py`` (no sync read / broadcast ping on
  protocol 1, the Lock writes around torque, the timeout patch), ``docs/source/so101.mdx``
  (STS3215 gear ratios 1/345, 1/191, 1/147).
- ``feetech-servo-sdk`` 1.0.0 from PyPI: ``scservo_sdk/protocol_packet_handler.py`` (packet
  layout, checksum, error bits, ping reads the model number at 3), ``scservo_def.py``
  (``SCS_SETEND``, word packing), ``port_handler.py`` (the timeout).
- ``ftservo/FTServo_Python`` at cb07f7668e2507408c97f35f4994c32ed3c9475b:
  ``scservo_sdk/port_handler.py`` (the fixed timeout).
- Feetech's SCServo library headers ``SMS_STS.h`` / ``SCSCL.h`` (lock at 55 / 48, baud values)
  and its examples (speed units), as vendored in many repositories; a transcription of
  Feetech's STS/SMS memory table (units, Phase and Status bits; repository not named by the
  index it came from).
- Waveshare's SC09 page (www.waveshare.com/wiki/SC09_Servo): 300 degrees over 0..1023.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum, IntEnum
from types import MappingProxyType

from ..lookup import NamedKeyError, did_you_mean

__all__ = [
    "BAUD_RATES",
    "EEPROM_END",
    "MODELS",
    "SCS",
    "SO101_GEAR_RATIOS",
    "STS_SMS",
    "ByteOrder",
    "Model",
    "Register",
    "Series",
    "SeriesName",
    "UnknownModelError",
    "UnknownRegisterError",
    "model_by_name",
    "model_by_number",
]

#: The first RAM address: 0..39 are EEPROM.
EEPROM_END = 40

#: Baud Rate register value -> bit/s (Feetech's SDK headers; see "Where the sources differ").
BAUD_RATES: Mapping[int, int] = MappingProxyType(
    {0: 1_000_000, 1: 500_000, 2: 250_000, 3: 128_000, 4: 115_200, 5: 76_800, 6: 57_600,
     7: 38_400}
)

#: The internal gear ratios of the STS3215 variants in an SO-101 (LeRobot's so101.mdx): the
#: follower uses 345 on all joints; the leader 191, 345, 191, 147, 147, 147 from the base up.
#: They change torque and speed, not the encoder (it reads the output shaft).
SO101_GEAR_RATIOS: tuple[int, ...] = (345, 191, 147)


class ByteOrder(IntEnum):
    """Byte order of a word; the value is the SDK's ``PacketHandler(protocol_end)`` argument."""

    LITTLE = 0
    BIG = 1


class SeriesName(str, Enum):
    """The register families."""

    STS_SMS = "sts_sms"
    SCS = "scs"


class UnknownRegisterError(NamedKeyError):
    """A register name that the series does not have."""


class UnknownModelError(NamedKeyError):
    """A model name that is not in :data:`MODELS`."""


@dataclass(frozen=True)
class Register:
    """One memory-table entry.

    Attributes:
        name: snake_case name (``present_position``).
        address: first byte.
        size: 1 or 2 bytes (in the series' byte order).
        writable: RW (``False``: read only).
        sign_bit: the sign-magnitude sign bit, or ``None`` for an unsigned value.
        unit: one count, e.g. ``"1 step/s"`` (empty when dimensionless).
    """

    name: str
    address: int
    size: int
    writable: bool = True
    sign_bit: int | None = None
    unit: str = ""

    def __post_init__(self) -> None:
        if self.size not in (1, 2):
            raise ValueError(f"register {self.name}: a Feetech register is 1 or 2 bytes")
        if self.sign_bit is not None and not 0 < self.sign_bit < 8 * self.size:
            raise ValueError(f"register {self.name}: sign bit {self.sign_bit} outside the word")

    @property
    def eeprom(self) -> bool:
        """Whether the register is in EEPROM (stored only while the lock register reads 0)."""
        return self.address < EEPROM_END

    @property
    def limits(self) -> tuple[int, int]:
        """The smallest and largest value the register can hold (after sign decoding)."""
        if self.sign_bit is None:
            return 0, (1 << (8 * self.size)) - 1
        magnitude = (1 << self.sign_bit) - 1
        return -magnitude, magnitude


@dataclass(frozen=True)
class Series:
    """A register family and the protocol features its servos have.

    Attributes:
        name: which family.
        byte_order: order of the two bytes of a word register.
        registers: snake_case name -> :class:`Register`.
        lock_register: the name of the EPROM lock (0: EEPROM writes are stored, 1: locked).
        sync_read: whether the servos answer Sync Read (0x82).
        broadcast_ping: whether the servos answer a ping to the broadcast id.
    """

    name: SeriesName
    byte_order: ByteOrder
    registers: Mapping[str, Register]
    lock_register: str
    sync_read: bool
    broadcast_ping: bool

    def __post_init__(self) -> None:
        object.__setattr__(self, "registers", MappingProxyType(dict(self.registers)))

    def register(self, name: str) -> Register:
        """The register called ``name``.

        Raises:
            UnknownRegisterError: (a ``KeyError``) no such register in this series; the message
                suggests the closest name.
        """
        try:
            return self.registers[name]
        except KeyError:
            raise UnknownRegisterError(
                f"the {self.name.value} series has no register {name!r}"
                + did_you_mean(name, self.registers)
            ) from None

    @property
    def lock_address(self) -> int:
        """The EPROM lock's address (55 on STS/SMS, 48 on SCS)."""
        return self.registers[self.lock_register].address

    @property
    def sdk_protocol_end(self) -> int:
        """The argument of ``scservo_sdk.PacketHandler`` for this series."""
        return int(self.byte_order)


@dataclass(frozen=True)
class Model:
    """One servo model.

    Attributes:
        name: catalogue name (``"STS3215"``).
        model_number: what the model number register (address 3) reads.
        series: its register family.
        steps_per_rev: position steps per output turn (SCS0009: 1024 steps span 300 degrees,
            so 1228.8).
        position_max: the largest position step (4095 or 1023).
        speed_unit_rad_s: one count of the speed registers, rad/s.
        acceleration_unit_rad_s2: one count of the acceleration register, rad/s^2 (``None``
            where unknown).
        current_unit_a: one count of present current, A (``None``: not read).
    """

    name: str
    model_number: int
    series: Series
    steps_per_rev: float
    position_max: int
    speed_unit_rad_s: float
    acceleration_unit_rad_s2: float | None
    current_unit_a: float | None

    @property
    def rad_per_step(self) -> float:
        """One position step, rad."""
        return 2.0 * math.pi / self.steps_per_rev


def _table(*entries: Register) -> dict[str, Register]:
    return {r.name: r for r in sorted(entries, key=lambda r: r.address)}


_R = Register
_STEP = "1 step (0.088 deg)"
_STEP_S = "1 step/s"

_COMMON = (
    _R("firmware_major", 0, 1, writable=False),
    _R("firmware_minor", 1, 1, writable=False),
    _R("model_number", 3, 2, writable=False),
    _R("id", 5, 1),
    _R("baud_rate", 6, 1),
    _R("return_delay_time", 7, 1, unit="2 us"),
    _R("response_status_level", 8, 1),
    _R("min_position_limit", 9, 2, unit=_STEP),
    _R("max_position_limit", 11, 2, unit=_STEP),
    _R("max_temperature_limit", 13, 1, unit="1 degC"),
    _R("max_voltage_limit", 14, 1, unit="0.1 V"),
    _R("min_voltage_limit", 15, 1, unit="0.1 V"),
    _R("max_torque_limit", 16, 2, unit="0.1 %"),
    _R("phase", 18, 1),
    _R("unloading_condition", 19, 1),
    _R("led_alarm_condition", 20, 1),
    _R("p_coefficient", 21, 1),
    _R("d_coefficient", 22, 1),
    _R("i_coefficient", 23, 1),
    _R("minimum_startup_force", 24, 2, unit="0.1 %"),
    _R("cw_dead_zone", 26, 1, unit=_STEP),
    _R("ccw_dead_zone", 27, 1, unit=_STEP),
    _R("torque_enable", 40, 1),
    _R("acceleration", 41, 1),
    _R("present_voltage", 62, 1, writable=False, unit="0.1 V"),
    _R("present_temperature", 63, 1, writable=False, unit="1 degC"),
    _R("status", 65, 1, writable=False),
    _R("moving", 66, 1, writable=False),
)

STS_SMS = Series(
    name=SeriesName.STS_SMS,
    byte_order=ByteOrder.LITTLE,
    registers=_table(
        *_COMMON,
        _R("protection_current", 28, 2, unit="6.5 mA"),
        _R("angular_resolution", 30, 1),
        _R("homing_offset", 31, 2, sign_bit=11, unit=_STEP),
        _R("operating_mode", 33, 1),
        _R("protective_torque", 34, 1, unit="1 %"),
        _R("protection_time", 35, 1, unit="10 ms"),
        _R("overload_torque", 36, 1, unit="1 %"),
        _R("velocity_p_coefficient", 37, 1),
        _R("over_current_protection_time", 38, 1, unit="10 ms"),
        _R("velocity_i_coefficient", 39, 1),
        _R("goal_position", 42, 2, sign_bit=15, unit=_STEP),
        _R("goal_time", 44, 2),
        _R("goal_velocity", 46, 2, sign_bit=15, unit=_STEP_S),
        _R("torque_limit", 48, 2, unit="0.1 %"),
        _R("lock", 55, 1),
        _R("present_position", 56, 2, writable=False, sign_bit=15, unit=_STEP),
        _R("present_velocity", 58, 2, writable=False, sign_bit=15, unit=_STEP_S),
        _R("present_load", 60, 2, writable=False, sign_bit=10, unit="0.1 %"),
        _R("present_current", 69, 2, writable=False, unit="6.5 mA"),
    ),
    lock_register="lock",
    sync_read=True,
    broadcast_ping=True,
)

SCS = Series(
    name=SeriesName.SCS,
    byte_order=ByteOrder.BIG,
    registers=_table(
        *_COMMON,
        _R("protective_torque", 37, 1, unit="1 %"),
        _R("protection_time", 38, 1, unit="10 ms"),
        _R("goal_position", 42, 2, unit="1 step"),
        _R("running_time", 44, 2),
        _R("goal_velocity", 46, 2, unit="0.059 rev/min"),
        _R("lock", 48, 1),
        _R("present_position", 56, 2, writable=False, unit="1 step"),
        _R("present_velocity", 58, 2, writable=False, unit="0.059 rev/min"),
        _R("present_load", 60, 2, writable=False, unit="0.1 %"),
        _R("sync_write_flag", 64, 1, writable=False),
    ),
    lock_register="lock",
    sync_read=False,
    broadcast_ping=False,
)

_RPM = 2.0 * math.pi / 60.0


def _sts(name: str, number: int) -> Model:
    step = 2.0 * math.pi / 4096
    return Model(
        name=name,
        model_number=number,
        series=STS_SMS,
        steps_per_rev=4096.0,
        position_max=4095,
        speed_unit_rad_s=step,
        acceleration_unit_rad_s2=100.0 * step,
        current_unit_a=0.0065,
    )


#: Catalogue name -> :class:`Model`. STS3215 stands for every voltage (7.4 V, 12 V) and gear
#: (:data:`SO101_GEAR_RATIOS`) variant: they report the same model number.
MODELS: Mapping[str, Model] = MappingProxyType({
    "STS3215": _sts("STS3215", 777),
    "STS3250": _sts("STS3250", 2825),
    "SCS0009": Model(
        name="SCS0009",
        model_number=1284,
        series=SCS,
        steps_per_rev=1024 * 360 / 300,
        position_max=1023,
        speed_unit_rad_s=0.059 * _RPM,
        acceleration_unit_rad_s2=None,
        current_unit_a=None,
    ),
})
_BY_NUMBER: Mapping[int, Model] = MappingProxyType({m.model_number: m for m in MODELS.values()})


def model_by_name(name: str) -> Model:
    """The model called ``name`` (case-insensitive).

    Raises:
        UnknownModelError: (a ``KeyError``) unknown name; the message lists the known ones.
    """
    key = name.strip().upper()
    if key in MODELS:
        return MODELS[key]
    raise UnknownModelError(
        f"unknown Feetech model {name!r}{did_you_mean(key, MODELS)}; known models: "
        + ", ".join(MODELS)
    )


def model_by_number(number: int) -> Model | None:
    """The model whose model number register reads ``number``, or ``None``."""
    return _BY_NUMBER.get(number)
