"""Dynamixel X-series control tables (Protocol 2.0) and unit conversions.

Theory of operation
-------------------
Every X-series servo exposes a byte-addressed *control table*: an EEPROM area (addresses 0..63,
writable only while Torque Enable is 0) and a RAM area (64 and up). A :class:`Register` describes
one entry (address, size, signedness, access, static range, default, unit); a :class:`Model`
collects the registers of one servo model by snake_case name, with the physical figures the
driver and the emulator need (encoder resolution, velocity and current units, stall torque,
no-load speed, supported operating modes).

The register maps, ranges and defaults come from the ROBOTIS e-Manual pages of each model
(XM430-W350, XM540-W270, XL430-W250, XC330-*). Ranges that depend on other registers in the
e-Manual (Goal Position between the position limits, Goal Current within Current Limit, Goal
Velocity within Velocity Limit, Goal PWM within PWM Limit) carry here the widest static range
(the limit register's maximum); the emulator checks the dynamic limit on top.

Unit conversions are exact linear maps and work on Python numbers and numpy arrays alike
(``rad_to_ticks`` etc. round to the nearest integer; arrays come back as ``int64`` arrays).
Positions convert around tick 0: ``rad = ticks * 2*pi / ticks_per_rev``; the driver applies its
own joint offset on top.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag
from types import MappingProxyType
from typing import Any, overload

import numpy as np
import numpy.typing as npt

from ..lookup import NamedKeyError, did_you_mean

__all__ = [
    "BAUD_RATES",
    "BUS_WATCHDOG_FIRMWARE",
    "BUS_WATCHDOG_MAX",
    "BUS_WATCHDOG_UNIT_S",
    "MODELS",
    "PRESENT_BLOCK",
    "PRESENT_BLOCK_ADDRESS",
    "PRESENT_BLOCK_SIZE",
    "HardwareError",
    "Model",
    "OperatingMode",
    "Register",
    "UnknownModelError",
    "UnknownRegisterError",
    "hardware_error_text",
    "model_by_name",
    "model_by_number",
]


class OperatingMode(IntEnum):
    """Values of the Operating Mode register (address 11)."""

    CURRENT = 0
    VELOCITY = 1
    POSITION = 3
    EXTENDED_POSITION = 4
    CURRENT_BASED_POSITION = 5
    PWM = 16


class HardwareError(IntFlag):
    """Bits of the Hardware Error Status register (address 70) and of Shutdown (address 63)."""

    INPUT_VOLTAGE = 0x01
    OVERHEATING = 0x04
    MOTOR_ENCODER = 0x08
    ELECTRICAL_SHOCK = 0x10
    OVERLOAD = 0x20


def hardware_error_text(flags: int) -> str:
    """Hardware Error Status bits as words (``"overheating, overload"``), for messages."""
    names = [flag.name.lower().replace("_", " ")
             for flag in HardwareError if flags & flag and flag.name]
    return ", ".join(names) if names else f"unknown hardware error 0x{flags:02x}"


#: Baud Rate register value -> bit/s (the X series' common table; a model accepts the values up
#: to its ``baud_rate`` register's maximum: 7 on XM430/XM540/XL430, 6 on XC330).
BAUD_RATES: Mapping[int, int] = MappingProxyType(
    {
        0: 9600,
        1: 57600,
        2: 115200,
        3: 1_000_000,
        4: 2_000_000,
        5: 3_000_000,
        6: 4_000_000,
        7: 4_500_000,
    }
)

#: Bus Watchdog (address 98): one count is 20 ms; 1..127 arm it (0.02 .. 2.54 s), 0 disarms it
#: and clears its error, -1 is the error state the servo sets on expiry (e-Manual).
BUS_WATCHDOG_UNIT_S = 0.02
BUS_WATCHDOG_MAX = 127
#: The Bus Watchdog exists from this firmware version on ("available from firmware v38").
BUS_WATCHDOG_FIRMWARE = 38

#: Registers read every cycle, one contiguous block (addresses 126..135). On XL430 the first
#: entry is ``present_load`` (same address and size) instead of ``present_current``.
PRESENT_BLOCK: tuple[str, ...] = ("present_current", "present_velocity", "present_position")
PRESENT_BLOCK_ADDRESS = 126
PRESENT_BLOCK_SIZE = 10

_TWO_PI = 2.0 * math.pi
#: Profile Acceleration unit, rev/min^2 (velocity-based profile).
PROFILE_ACCELERATION_UNIT_RPM2 = 214.577


class UnknownRegisterError(NamedKeyError):
    """A register name that the model does not have."""


class UnknownModelError(NamedKeyError):
    """A model name that is not in :data:`MODELS`."""


@dataclass(frozen=True)
class Register:
    """One control-table entry.

    Attributes:
        name: snake_case name (``goal_position``).
        address: byte address.
        size: 1, 2 or 4 bytes, little endian.
        signed: two's complement value.
        writable: RW (``False``: read only).
        eeprom: in the EEPROM area (writable only while torque is off).
        minimum: smallest accepted value (static; see the module docstring).
        maximum: largest accepted value.
        default: value after power-on / reboot (0 where the e-Manual gives none).
        unit: unit of one count, e.g. ``"0.229 rev/min"`` (empty when dimensionless).
    """

    name: str
    address: int
    size: int
    signed: bool
    writable: bool
    eeprom: bool
    minimum: int
    maximum: int
    default: int
    unit: str = ""

    def __post_init__(self) -> None:
        if self.size not in (1, 2, 4):
            raise ValueError(f"register {self.name}: size must be 1, 2 or 4, got {self.size}")
        if not self.minimum <= self.default <= self.maximum:
            raise ValueError(f"register {self.name}: default {self.default} outside range")

    @property
    def end(self) -> int:
        """The address just past this register."""
        return self.address + self.size

    def encode(self, value: int) -> bytes:
        """The little-endian bytes of ``value``.

        Raises:
            ValueError: ``value`` does not fit in the register's size / signedness.
        """
        try:
            return int(value).to_bytes(self.size, "little", signed=self.signed)
        except OverflowError as exc:
            raise ValueError(f"{value} does not fit register {self.name}") from exc

    def decode(self, data: bytes | bytearray | memoryview) -> int:
        """The value held by ``data`` (exactly ``size`` bytes).

        Raises:
            ValueError: ``data`` has the wrong length.
        """
        if len(data) != self.size:
            raise ValueError(f"register {self.name} needs {self.size} bytes, got {len(data)}")
        return int.from_bytes(bytes(data), "little", signed=self.signed)


def _round_int(value: Any) -> Any:
    """Round half away from zero to int (an int64 array for array input)."""
    if isinstance(value, np.ndarray):
        return np.asarray(np.sign(value) * np.floor(np.abs(value) + 0.5), dtype=np.int64)
    return int(math.copysign(math.floor(abs(value) + 0.5), value))


def _as_float(value: Any) -> Any:
    # Python scalars first: the emulator converts a handful of them per servo and request, and
    # a numpy round trip costs ~50 times a float() call.
    if type(value) is float or type(value) is int:
        return float(value)
    if isinstance(value, np.ndarray):
        return value.astype(np.float64)
    return float(value)


@dataclass(frozen=True)
class Model:
    """One servo model: its registers and physical figures.

    Attributes:
        name: catalogue name, e.g. ``"XM430-W350"``.
        model_number: value of ``model_number`` (address 0).
        registers: snake_case name -> :class:`Register`.
        ticks_per_rev: encoder counts per output revolution.
        velocity_unit_rpm: one count of velocity registers, rev/min.
        current_unit_a: one count of current registers, A (``None``: no current sensing).
        torque_constant_nm_per_a: stall torque / stall current from the e-Manual.
        stall_torque_nm: stall torque at the nominal voltage, N*m.
        no_load_speed_rad_s: no-load speed at the nominal voltage, rad/s.
        operating_modes: the modes the model accepts.
        nominal_voltage_v: the voltage the figures above are given at, V.
    """

    name: str
    model_number: int
    registers: Mapping[str, Register]
    ticks_per_rev: int
    velocity_unit_rpm: float
    current_unit_a: float | None
    torque_constant_nm_per_a: float | None
    stall_torque_nm: float
    no_load_speed_rad_s: float
    operating_modes: frozenset[OperatingMode]
    nominal_voltage_v: float = 12.0
    _by_address: Mapping[int, Register] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "registers", MappingProxyType(dict(self.registers)))
        object.__setattr__(
            self,
            "_by_address",
            MappingProxyType({r.address: r for r in self.registers.values()}),
        )

    # -- registers ------------------------------------------------------------------------------

    def register(self, name: str) -> Register:
        """The register called ``name``.

        Raises:
            UnknownRegisterError: (a ``KeyError``) the model has no such register; the message
                names the model and lists the known names.
        """
        try:
            return self.registers[name]
        except KeyError:
            hint = did_you_mean(name, self.registers)
            raise UnknownRegisterError(
                f"{self.name} has no register {name!r}{hint}; known registers: "
                + ", ".join(sorted(self.registers, key=lambda n: self.registers[n].address))
            ) from None

    def has_register(self, name: str) -> bool:
        """Whether the model has a register called ``name``."""
        return name in self.registers

    def register_at(self, address: int) -> Register | None:
        """The register starting at ``address``, or ``None``."""
        return self._by_address.get(address)

    @property
    def table_size(self) -> int:
        """Bytes spanned by the known registers (addresses 0 .. last register's end)."""
        return max(r.end for r in self.registers.values())

    @property
    def present_block_names(self) -> tuple[str, ...]:
        """:data:`PRESENT_BLOCK` for this model (``present_load`` first on models without current
        sensing)."""
        if "present_current" in self.registers:
            return PRESENT_BLOCK
        return ("present_load",) + PRESENT_BLOCK[1:]

    @property
    def baud_rates(self) -> Mapping[int, int]:
        """Baud Rate register value -> bit/s for the values this model accepts."""
        top = self.register("baud_rate").maximum
        return MappingProxyType({k: v for k, v in BAUD_RATES.items() if k <= top})

    def defaults(self) -> bytearray:
        """A control table image holding every register's default value."""
        table = bytearray(self.table_size)
        for reg in self.registers.values():
            table[reg.address : reg.end] = reg.encode(reg.default)
        return table

    # -- conversions ------------------------------------------------------------------------------

    @overload
    def ticks_to_rad(self, ticks: int | float) -> float: ...
    @overload
    def ticks_to_rad(self, ticks: npt.NDArray[Any]) -> npt.NDArray[np.float64]: ...
    def ticks_to_rad(self, ticks: Any) -> Any:
        """Encoder ticks -> rad (tick 0 is 0 rad)."""
        return _as_float(ticks) * (_TWO_PI / self.ticks_per_rev)

    @overload
    def rad_to_ticks(self, rad: int | float) -> int: ...
    @overload
    def rad_to_ticks(self, rad: npt.NDArray[Any]) -> npt.NDArray[np.int64]: ...
    def rad_to_ticks(self, rad: Any) -> Any:
        """rad -> encoder ticks, rounded to the nearest integer.

        Raises:
            ValueError: a non-finite value.
        """
        _check_finite(rad)
        return _round_int(_as_float(rad) * (self.ticks_per_rev / _TWO_PI))

    @property
    def velocity_unit_rad_s(self) -> float:
        """One count of velocity registers in rad/s."""
        return self.velocity_unit_rpm * _TWO_PI / 60.0

    @overload
    def velocity_to_rad_s(self, raw: int | float) -> float: ...
    @overload
    def velocity_to_rad_s(self, raw: npt.NDArray[Any]) -> npt.NDArray[np.float64]: ...
    def velocity_to_rad_s(self, raw: Any) -> Any:
        """Velocity register counts -> rad/s."""
        return _as_float(raw) * self.velocity_unit_rad_s

    @overload
    def rad_s_to_velocity(self, rad_s: int | float) -> int: ...
    @overload
    def rad_s_to_velocity(self, rad_s: npt.NDArray[Any]) -> npt.NDArray[np.int64]: ...
    def rad_s_to_velocity(self, rad_s: Any) -> Any:
        """rad/s -> velocity register counts, rounded to the nearest integer.

        Raises:
            ValueError: a non-finite value.
        """
        _check_finite(rad_s)
        return _round_int(_as_float(rad_s) / self.velocity_unit_rad_s)

    @property
    def profile_acceleration_unit_rad_s2(self) -> float:
        """One count of Profile Acceleration in rad/s^2 (velocity-based profile)."""
        return PROFILE_ACCELERATION_UNIT_RPM2 * _TWO_PI / 3600.0

    def _current_unit(self) -> float:
        if self.current_unit_a is None:
            raise ValueError(
                f"{self.name} has no current sensing (it reports present_load instead)"
            )
        return self.current_unit_a

    @overload
    def current_to_a(self, raw: int | float) -> float: ...
    @overload
    def current_to_a(self, raw: npt.NDArray[Any]) -> npt.NDArray[np.float64]: ...
    def current_to_a(self, raw: Any) -> Any:
        """Current register counts -> A.

        Raises:
            ValueError: the model has no current sensing.
        """
        return _as_float(raw) * self._current_unit()

    @overload
    def a_to_current(self, a: int | float) -> int: ...
    @overload
    def a_to_current(self, a: npt.NDArray[Any]) -> npt.NDArray[np.int64]: ...
    def a_to_current(self, a: Any) -> Any:
        """A -> current register counts, rounded to the nearest integer.

        Raises:
            ValueError: the model has no current sensing, or a non-finite value.
        """
        unit = self._current_unit()
        _check_finite(a)
        return _round_int(_as_float(a) / unit)


def _check_finite(value: Any) -> None:
    # Scalar fast path (see _as_float); numpy handles arrays and numpy scalars.
    if type(value) is int:
        return
    if type(value) is float:
        finite = math.isfinite(value)
    else:
        finite = bool(np.all(np.isfinite(value)))
    if not finite:
        raise ValueError(f"cannot convert a non-finite value: {value!r}")


# -- building the tables ------------------------------------------------------------------------

_S32 = (-(2**31), 2**31 - 1)
_S16 = (-(2**15), 2**15 - 1)
#: Goal Position's range in extended position mode (+-256 revolutions).
_EXTENDED_POSITION = 1_048_575


def _r(
    name: str,
    address: int,
    size: int,
    *,
    signed: bool = False,
    rw: bool = True,
    lo: int = 0,
    hi: int | None = None,
    default: int = 0,
    unit: str = "",
) -> Register:
    if hi is None:
        hi = (1 << (8 * size)) - 1 if not signed else (1 << (8 * size - 1)) - 1
    return Register(name, address, size, signed, rw, address < 64, lo, hi, default, unit)


def _x_series_table(
    *,
    model_number: int,
    baud_max: int,
    drive_mode_max: int,
    protocol_range: tuple[int, int],
    temperature_limit: int,
    voltage_range: tuple[int, int],
    current_limit: int | None,
    current_unit: str,
    velocity_limit: int,
    velocity_limit_max: int,
    gains: tuple[int, int, int, int, int],
    firmware: int,
) -> dict[str, Register]:
    """The X-series Protocol 2.0 table with the per-model figures filled in.

    ``gains`` are the defaults of velocity I, velocity P, position D, position I, position P.
    """
    v_lo, v_hi = voltage_range
    vel_i, vel_p, pos_d, pos_i, pos_p = gains
    regs = [
        _r("model_number", 0, 2, rw=False, lo=model_number, hi=model_number, default=model_number),
        _r("model_information", 2, 4, rw=False),
        _r("firmware_version", 6, 1, rw=False, default=firmware),
        _r("id", 7, 1, hi=252, default=1),
        _r("baud_rate", 8, 1, hi=baud_max, default=1),
        _r("return_delay_time", 9, 1, hi=254, default=250, unit="2 us"),
        _r("drive_mode", 10, 1, hi=drive_mode_max, default=0),
        _r("operating_mode", 11, 1, hi=16, default=int(OperatingMode.POSITION)),
        _r("secondary_id", 12, 1, hi=255, default=255),
        _r("protocol_type", 13, 1, lo=protocol_range[0], hi=protocol_range[1], default=2),
        _r("homing_offset", 20, 4, signed=True, lo=-1_044_479, hi=1_044_479, unit="1 pulse"),
        _r("moving_threshold", 24, 4, hi=1023, default=10, unit="0.229 rev/min"),
        _r("temperature_limit", 31, 1, hi=100, default=temperature_limit, unit="1 degC"),
        _r("max_voltage_limit", 32, 2, lo=v_lo, hi=v_hi, default=v_hi, unit="0.1 V"),
        _r("min_voltage_limit", 34, 2, lo=v_lo, hi=v_hi, default=v_lo, unit="0.1 V"),
        _r("pwm_limit", 36, 2, hi=885, default=885, unit="0.113 %"),
        _r(
            "velocity_limit",
            44,
            4,
            hi=velocity_limit_max,
            default=velocity_limit,
            unit="0.229 rev/min",
        ),
        _r("max_position_limit", 48, 4, hi=4095, default=4095, unit="1 pulse"),
        _r("min_position_limit", 52, 4, hi=4095, default=0, unit="1 pulse"),
        _r("shutdown", 63, 1, hi=0x3F, default=52),
        _r("torque_enable", 64, 1, hi=1),
        _r("led", 65, 1, hi=1),
        _r("status_return_level", 68, 1, hi=2, default=2),
        _r("registered_instruction", 69, 1, rw=False, hi=1),
        _r("hardware_error_status", 70, 1, rw=False),
        _r("velocity_i_gain", 76, 2, hi=16383, default=vel_i),
        _r("velocity_p_gain", 78, 2, hi=16383, default=vel_p),
        _r("position_d_gain", 80, 2, hi=16383, default=pos_d),
        _r("position_i_gain", 82, 2, hi=16383, default=pos_i),
        _r("position_p_gain", 84, 2, hi=16383, default=pos_p),
        _r("feedforward_2nd_gain", 88, 2, hi=16383),
        _r("feedforward_1st_gain", 90, 2, hi=16383),
        # 1..127 (20 ms units), 0 disables and clears a trip; the servo itself sets -1 when the
        # watchdog trips (not writable).
        _r("bus_watchdog", 98, 1, signed=True, lo=0, hi=BUS_WATCHDOG_MAX, unit="20 ms"),
        _r("goal_pwm", 100, 2, signed=True, lo=-885, hi=885, unit="0.113 %"),
        _r(
            "goal_velocity",
            104,
            4,
            signed=True,
            lo=-velocity_limit_max,
            hi=velocity_limit_max,
            unit="0.229 rev/min",
        ),
        _r("profile_acceleration", 108, 4, hi=32767, unit="214.577 rev/min^2"),
        _r("profile_velocity", 112, 4, hi=32767, unit="0.229 rev/min"),
        _r(
            "goal_position",
            116,
            4,
            signed=True,
            lo=-_EXTENDED_POSITION,
            hi=_EXTENDED_POSITION,
            unit="1 pulse",
        ),
        _r("realtime_tick", 120, 2, rw=False, hi=32767, unit="1 ms"),
        _r("moving", 122, 1, rw=False, hi=1),
        _r("moving_status", 123, 1, rw=False),
        _r("present_pwm", 124, 2, signed=True, rw=False, lo=_S16[0], unit="0.113 %"),
        _r("present_velocity", 128, 4, signed=True, rw=False, lo=_S32[0], unit="0.229 rev/min"),
        _r("present_position", 132, 4, signed=True, rw=False, lo=_S32[0], unit="1 pulse"),
        _r("velocity_trajectory", 136, 4, signed=True, rw=False, lo=_S32[0], unit="0.229 rev/min"),
        _r("position_trajectory", 140, 4, signed=True, rw=False, lo=_S32[0], unit="1 pulse"),
        _r("present_input_voltage", 144, 2, rw=False, unit="0.1 V"),
        _r("present_temperature", 146, 1, rw=False, unit="1 degC"),
    ]
    if current_limit is not None:
        regs += [
            _r("current_limit", 38, 2, hi=current_limit, default=current_limit, unit=current_unit),
            _r(
                "goal_current",
                102,
                2,
                signed=True,
                lo=-current_limit,
                hi=current_limit,
                unit=current_unit,
            ),
            _r("present_current", 126, 2, signed=True, rw=False, lo=_S16[0], unit=current_unit),
        ]
    else:
        regs.append(
            _r("present_load", 126, 2, signed=True, rw=False, lo=-1000, hi=1000, unit="0.1 %")
        )
    regs.sort(key=lambda r: r.address)
    return {r.name: r for r in regs}


def _rpm(rpm: float) -> float:
    return rpm * _TWO_PI / 60.0


_ALL_MODES = frozenset(OperatingMode)
_NO_CURRENT_MODES = frozenset(
    {
        OperatingMode.VELOCITY,
        OperatingMode.POSITION,
        OperatingMode.EXTENDED_POSITION,
        OperatingMode.PWM,
    }
)


def _xc330(
    name: str, number: int, stall_nm: float, stall_a: float, rpm: float, volts: float
) -> Model:
    # XC330-T288 (e-Manual): current in 1 mA units (measured at the input supply), Current
    # Limit 0..910 (default 910), Velocity Limit default 320 (max 2047), baud up to 4 Mbit/s,
    # Drive Mode 0..5, Protocol Type 2..22, voltage limits 55..140, temperature limit 70.
    return Model(
        name=name,
        model_number=number,
        registers=_x_series_table(
            model_number=number,
            baud_max=6,
            drive_mode_max=5,
            protocol_range=(2, 22),
            temperature_limit=70,
            voltage_range=(55, 140),
            current_limit=910,
            current_unit="1 mA",
            velocity_limit=320,
            velocity_limit_max=2047,
            gains=(1200, 40, 0, 0, 900),
            firmware=50,
        ),
        ticks_per_rev=4096,
        velocity_unit_rpm=0.229,
        current_unit_a=0.001,
        torque_constant_nm_per_a=stall_nm / stall_a,
        stall_torque_nm=stall_nm,
        no_load_speed_rad_s=_rpm(rpm),
        operating_modes=_ALL_MODES,
        nominal_voltage_v=volts,
    )


def _build_models() -> dict[str, Model]:
    models = [
        # XM430-W350 (e-Manual): 4.1 N*m at 12.0 V and 2.3 A stall; 46 rev/min no load at 12 V.
        # Current unit 2.69 mA, Current Limit 0..1193, Velocity Limit default 200 (0..1023).
        Model(
            name="XM430-W350",
            model_number=1020,
            registers=_x_series_table(
                model_number=1020,
                baud_max=7,
                drive_mode_max=13,
                protocol_range=(1, 2),
                temperature_limit=80,
                voltage_range=(95, 160),
                current_limit=1193,
                current_unit="2.69 mA",
                velocity_limit=200,
                velocity_limit_max=1023,
                gains=(1920, 100, 0, 0, 800),
                firmware=48,
            ),
            ticks_per_rev=4096,
            velocity_unit_rpm=0.229,
            current_unit_a=0.00269,
            torque_constant_nm_per_a=4.1 / 2.3,
            stall_torque_nm=4.1,
            no_load_speed_rad_s=_rpm(46.0),
            operating_modes=_ALL_MODES,
            nominal_voltage_v=12.0,
        ),
        # XM540-W270 (e-Manual): 10.6 N*m at 12.0 V and 4.4 A stall; 30 rev/min no load at 12 V.
        # Current unit 2.69 mA, Current Limit 0..2047, Velocity Limit default 128 (0..1023).
        Model(
            name="XM540-W270",
            model_number=1120,
            registers=_x_series_table(
                model_number=1120,
                baud_max=7,
                drive_mode_max=5,
                protocol_range=(1, 2),
                temperature_limit=80,
                voltage_range=(95, 160),
                current_limit=2047,
                current_unit="2.69 mA",
                velocity_limit=128,
                velocity_limit_max=1023,
                gains=(1920, 100, 0, 0, 800),
                firmware=48,
            ),
            ticks_per_rev=4096,
            velocity_unit_rpm=0.229,
            current_unit_a=0.00269,
            torque_constant_nm_per_a=10.6 / 4.4,
            stall_torque_nm=10.6,
            no_load_speed_rad_s=_rpm(30.0),
            operating_modes=_ALL_MODES,
            nominal_voltage_v=12.0,
        ),
        # XL430-W250 (e-Manual): 1.4 N*m at 11.1 V and 1.3 A stall; 57 rev/min no load at
        # 11.1 V. No current sensing: Present Load (0.1 % of the maximum torque) at 126, no
        # Current Limit / Goal Current; modes velocity, position, extended position, PWM.
        Model(
            name="XL430-W250",
            model_number=1060,
            registers=_x_series_table(
                model_number=1060,
                baud_max=7,
                drive_mode_max=13,
                protocol_range=(1, 2),
                temperature_limit=72,
                voltage_range=(60, 140),
                current_limit=None,
                current_unit="",
                velocity_limit=265,
                velocity_limit_max=1023,
                gains=(1000, 100, 4000, 0, 640),
                firmware=46,
            ),
            ticks_per_rev=4096,
            velocity_unit_rpm=0.229,
            current_unit_a=None,
            torque_constant_nm_per_a=1.4 / 1.3,
            stall_torque_nm=1.4,
            no_load_speed_rad_s=_rpm(57.0),
            operating_modes=_NO_CURRENT_MODES,
            nominal_voltage_v=11.1,
        ),
        # XC330-T288 (e-Manual spec table, at the recommended 11.1 V).
        _xc330("XC330-T288", 1220, 0.92, 0.80, 65.0, 11.1),  # 0.92 N*m, 0.80 A, 65 rpm @ 11.1 V
        # The other XC330 variants differ in limits (M181/M288: 3.7-6 V, Current Limit 2352,
        # other velocity limits); add them with their own e-Manual tables when needed.
    ]
    return {m.name: m for m in models}


#: Catalogue name -> :class:`Model`.
MODELS: Mapping[str, Model] = MappingProxyType(_build_models())
_BY_NUMBER: Mapping[int, Model] = MappingProxyType({m.model_number: m for m in MODELS.values()})


def model_by_name(name: str) -> Model:
    """The model called ``name`` (case-insensitive; a ``-T``/``-R`` suffix is ignored).

    Raises:
        UnknownModelError: (a ``KeyError``) unknown name; the message lists the known names
            with a did-you-mean suggestion.
    """
    key = name.strip().upper()
    for suffix in ("-T", "-R"):
        if key.endswith(suffix) and key[: -len(suffix)] in MODELS:
            key = key[: -len(suffix)]
    if key in MODELS:
        return MODELS[key]
    hint = did_you_mean(key, MODELS)
    raise UnknownModelError(
        f"unknown Dynamixel model {name!r}{hint}; known models: {', '.join(MODELS)}"
    )


def model_by_number(number: int) -> Model | None:
    """The model whose ``model_number`` register reads ``number``, or ``None``."""
    return _BY_NUMBER.get(number)
