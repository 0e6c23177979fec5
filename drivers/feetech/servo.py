"""One emulated Feetech servo (STS/SMS or SCS): its memory, its position loop, its protections.

Theory of operation
-------------------
:class:`EmulatedServo` is what :class:`~jtc_hw.drivers.feetech.emulator.FeetechEmulator` keeps
per servo id. The emulator owns the pty, the packet dispatch, the timing and the lock; a servo
owns what one device remembers and how its shaft moves. No I/O, no lock and no clock here: every
method that moves time takes ``now`` (the emulator's ``time.monotonic()``), so a test steps a
servo on a simulated clock.

Memory. A servo keeps its memory table as the bytes the wire carries (:attr:`memory`, 256
bytes; what no register names reads 0): words in the series' byte order (little endian on
STS/SMS, big endian on SCS), sign-magnitude where the register has a sign bit (bit 15 for
positions and speeds, 10 for present load, 11 for the homing offset; none on SCS), all from
:mod:`.control_table` through :func:`.codec.encode_value`. A READ is a slice of it; the
present registers are rewritten from the motor when something reads them after a step.

Writes (WRITE, the held REG_WRITE at ACTION, SYNC_WRITE) store their bytes; bytes of read-only
registers are left as they are (the servo has no error bit to refuse them with, so the write
is acknowledged). Feetech servos have no range checks on the wire either; the servo's own rules
are applied where they matter:

- **The EPROM lock** (``lock``: 55 on STS/SMS, 48 on SCS). A write to the EEPROM area (0..39)
  takes effect at once, but it is *stored* (kept over a power cycle, :meth:`power_cycle`) only
  while the lock reads 0: "1: opens the write lock, and the value written to EPROM address is
  not saved after power-cycling" (the Lock comment of a community STS library forked from
  Waveshare's code, ``feetechsts``, as the index served it; Feetech's SCServo library brackets
  EEPROM writes with ``unLockEprom`` / ``LockEprom``, and LeRobot writes Lock 0 with the torque
  off and 1 with it on, ``feetech.py``). The lock reads 1 after power-on (emulator choice,
  matching that bracket: an unlocked default would make it pointless).
- **Torque enable** (40): 1 drives the shaft to the goal, anything else lets it coast.
  Switching it on copies Present Position into Goal Position so that nothing jumps, unless the
  same write carries a goal (emulator choice, as the Dynamixel emulator does). While a
  protection that unloads the servo (below) persists, the torque stays off.
- **Goal position** (42) is clamped to Min/Max Position Limit (9, 11) when Max > Min; the shaft
  turns at most at Goal Velocity (46; 0: the motor's no-load speed) and accelerates at most at
  Acceleration (41, 100 steps/s^2 per count on STS/SMS; 0: no ramp; SCS: none), through the
  shared :class:`~jtc_hw.drivers.motor_model.Motor` (its position mode: a profiled reference
  tracked by a stiff PD loop, the torque clamped to Torque Limit (48) * the stall torque).
  Goal Time / Running Time (44) and the Phase bits (18) are not emulated.
- **Position mapping** (STS/SMS): "Present_Position = Actual_Position - Homing_Offset"
  (LeRobot ``feetech.py``, ``_get_half_turn_homings``), wrapped into 0..4095 in single-turn
  mode (LeRobot commit a656a982); the shaft's target is Goal Position + Homing Offset. SCS has
  no homing offset.

Present registers: position (steps), velocity (steps/s on STS/SMS, 0.059 rev/min on SCS), load
(the motor's torque in 0.1 % of the stall torque; Feetech's SCSCL library calls it the share of
the supply voltage driven into the motor, which equals it at stall: an approximation while the
shaft turns), voltage (0.1 V), temperature (1 degC),
current (6.5 mA, STS/SMS: the torque's share of the stall current), Moving (66: 1 while
Present Velocity is not 0) and Status (65).

Signs on SCS: the control table gives no SCS register a sign (as LeRobot's tables), but
Feetech's own SCSCL library (``SCSCL::ReadSpeed`` / ``ReadLoad``, as vendored in many
repositories) reads Present Speed with a direction bit 15 and Present Load with bit 10; the
emulator encodes them so (:data:`SCS_DIRECTION_BITS`). Not checked on an SCS0009.

Status and protections
----------------------
The Status register (65) and every status packet's error byte carry the same bits
(:class:`.codec.StatusError`: voltage 0x01, angle sensor 0x02, overheat 0x04, overcurrent 0x08,
overload 0x20; the SDK's ``ERRBIT_*``). Unloading Condition (19) says which conditions switch
the torque off (a set bit: that protection unloads the servo); LED Alarm Condition (20) which
ones light the LED (not emulated). The protections, as Feetech's STS memory table describes its
registers:

- **Overload**: while the motor's torque exceeds Overload Torque (36, % of the stall torque)
  for Protection Time (35, 10 ms units) without a break, the servo enters overload
  protection: the overload bit is set; with the overload bit in Unloading Condition (the
  default) the torque goes off, else the torque is limited to Protective Torque (34, %).
  SCS servos have no Overload Torque register: 80 % is used (emulator choice, the STS default).
  The bit clears when the torque is switched on again (emulator choice).
- **Overheat**: a temperature above Max Temperature Limit (13) sets the overheat bit; with
  that bit in Unloading Condition (the default) the torque goes off and stays off until the
  servo has cooled below the limit. The bit follows the temperature.
- **Voltage**: a supply outside Min/Max Input Voltage (15, 14) sets the voltage bit (not in
  the default Unloading Condition: the servo keeps driving).
- **Angle sensor**: :attr:`EmulatedServo.angle_fault` sets the angle bit (not unloading by
  default).

Each protection entered is recorded as a :class:`ProtectionEvent` on the emulator's clock
(:attr:`EmulatedServo.events`), so a test judges when it happened from the servo's own stamps.

Defaults (:data:`DEFAULTS`): what the servo reads after power-on. Sourced: id 1, 1 Mbit/s
(Baud Rate 0; the STS memory-table transcriptions at wiki.aifitlab.com and wiki.juxitech.com,
"Feetech STS servo memory table analysis"), Response Status Level 1, position limits 0..4095,
Max Temperature Limit 70 degC (the same transcription), Return Delay Time 250 = 500 us
(LeRobot ``configure_motors``: "By default, Feetech motors have a 500us delay response
time"). Not confirmed on a servo (emulator choices with the usual STS3215 figures): Unloading
Condition 44 and LED Alarm Condition 47, the protection thresholds (34..38), the gains, the
voltage limits and the motor figures (:data:`PHYSICS`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from types import MappingProxyType

from ..motor_model import Motor, MotorParams
from ..pty_emulator import BusServo
from .codec import StatusError, decode_value, encode_value
from .control_table import EEPROM_END, Model, Register, Series, SeriesName

__all__ = ["DEFAULTS", "MEMORY_SIZE", "PHYSICS", "SCS_DIRECTION_BITS", "EmulatedServo", "Physics",
           "ProtectionEvent"]

#: Bytes of emulated memory (addresses are one byte on the wire).
MEMORY_SIZE = 256

#: SCS registers read with a direction bit by Feetech's SCSCL library (see the module docstring).
SCS_DIRECTION_BITS: Mapping[str, int] = MappingProxyType(
    {"present_velocity": 15, "present_load": 10})

#: Overload threshold of SCS servos (no Overload Torque register), % of the stall torque.
_SCS_OVERLOAD_PERCENT = 80


@dataclasses.dataclass(frozen=True)
class Physics:
    """The motor behind a model, at its nominal voltage (catalogue figures, approximate: they
    only shape the emulated motion).

    Attributes:
        stall_torque_nm: stall torque, N*m.
        no_load_speed_rad_s: no-load speed, rad/s.
        stall_current_a: stall current, A (present current scales with the torque).
        nominal_voltage_v: the supply the servo reports, V.
    """

    stall_torque_nm: float
    no_load_speed_rad_s: float
    stall_current_a: float
    nominal_voltage_v: float


_KG_CM = 9.80665 / 100.0  # N*m per kg*cm
_PER_60_DEG = math.pi / 3.0  # rad in 60 degrees

#: Model name -> :class:`Physics`. STS3215: the 12 V, 1/345 variant (30 kg*cm, 0.222 s/60 deg);
#: STS3250: 50 kg*cm, 0.15 s/60 deg at 12 V; SCS0009: 2.3 kg*cm, 0.1 s/60 deg at 6 V.
PHYSICS: Mapping[str, Physics] = MappingProxyType({
    "STS3215": Physics(30 * _KG_CM, _PER_60_DEG / 0.222, 2.7, 12.0),
    "STS3250": Physics(50 * _KG_CM, _PER_60_DEG / 0.15, 3.0, 12.0),
    "SCS0009": Physics(2.3 * _KG_CM, _PER_60_DEG / 0.1, 0.9, 6.0),
})

_COMMON_DEFAULTS = {
    "firmware_major": 3,
    "firmware_minor": 9,
    "id": 1,
    "baud_rate": 0,
    "return_delay_time": 250,
    "response_status_level": 1,
    "min_position_limit": 0,
    "max_temperature_limit": 70,
    "min_voltage_limit": 40,
    "max_torque_limit": 1000,
    "unloading_condition": 44,
    "led_alarm_condition": 47,
    "p_coefficient": 32,
    "d_coefficient": 32,
    "i_coefficient": 0,
    "minimum_startup_force": 16,
    "cw_dead_zone": 1,
    "ccw_dead_zone": 1,
    "lock": 1,
}

#: Series -> register -> value after power-on (model number, position limit and supply limit
#: follow the model; see the module docstring for the sources).
DEFAULTS: Mapping[SeriesName, Mapping[str, int]] = MappingProxyType({
    SeriesName.STS_SMS: MappingProxyType({
        **_COMMON_DEFAULTS,
        "max_position_limit": 4095,
        "max_voltage_limit": 140,
        "torque_limit": 1000,
        "protection_current": 500,
        "angular_resolution": 1,
        "protective_torque": 20,
        "protection_time": 200,
        "overload_torque": 80,
        "velocity_p_coefficient": 10,
        "over_current_protection_time": 200,
        "velocity_i_coefficient": 200,
    }),
    SeriesName.SCS: MappingProxyType({
        **_COMMON_DEFAULTS,
        "max_position_limit": 1023,
        "max_voltage_limit": 80,
        "protective_torque": 20,
        "protection_time": 200,
    }),
})

#: The present registers the motor drives, rewritten together by :meth:`EmulatedServo.refresh`.
_PRESENT = ("present_position", "present_velocity", "present_load", "present_voltage",
            "present_temperature", "status", "moving", "present_current")


_READ_ONLY: dict[SeriesName, frozenset[int]] = {}


def _read_only(series: Series) -> frozenset[int]:
    """The addresses of ``series``' read-only registers (built once per series)."""
    found = _READ_ONLY.get(series.name)
    if found is None:
        found = frozenset(at for reg in series.registers.values() if not reg.writable
                          for at in range(reg.address, reg.address + reg.size))
        _READ_ONLY[series.name] = found
    return found


@dataclasses.dataclass(frozen=True)
class ProtectionEvent:
    """A protection a servo entered, on the emulator's clock (``time.monotonic()``).

    Attributes:
        servo_id: the servo.
        error: the status bit (:class:`.codec.StatusError`).
        at_s: when it was entered: for an overload, the end of the Protection Time.
        torque_off: whether it switched the torque off (the bit is in Unloading Condition).
    """

    servo_id: int
    error: StatusError
    at_s: float
    torque_off: bool


class EmulatedServo(BusServo):
    """One emulated servo: its memory, motor, protections and injected faults.

    Args:
        model: the servo model.
        servo_id: its id (0..253).
        position_steps: where its shaft stands, in position steps (Present Position with no
            homing offset).
        now: the emulator's clock at power-on.
        supply_v: the supply voltage it reads (default: the model's nominal).
        notify: called (under the emulator's lock) when a protection is entered.
    """

    def __init__(
        self,
        model: Model,
        servo_id: int,
        position_steps: float,
        now: float,
        supply_v: float | None = None,
        notify: Callable[[], None] = lambda: None,
    ) -> None:
        super().__init__()  # the reply faults: drop, delay_s, corrupt, silent
        self.model = model
        self.series = model.series
        self._order = model.series.byte_order
        self.physics = PHYSICS[model.name]
        self.params = MotorParams(
            inertia=0.002 * max(self.physics.stall_torque_nm, 0.1),
            damping=0.02 * self.physics.stall_torque_nm / self.physics.no_load_speed_rad_s,
            torque_limit=self.physics.stall_torque_nm,
            velocity_limit=self.physics.no_load_speed_rad_s,
            servo_bandwidth_hz=20.0,
            max_step_s=0.0005,
        )
        self.motor = Motor(self.params, position_steps * model.rad_per_step)
        self.memory = bytearray(MEMORY_SIZE)
        for name, value in DEFAULTS[self.series.name].items():
            self.set(name, value)
        self.set("model_number", model.model_number)
        self.set("id", servo_id)
        self.stored = bytes(self.memory[:EEPROM_END])  # the EEPROM as kept over a power cycle
        self.last_step = now
        self.registered: tuple[int, bytes] | None = None  # a REG_WRITE waiting for ACTION
        self.temperature_c = 35.0
        self.supply_v = self.physics.nominal_voltage_v if supply_v is None else supply_v
        self.angle_fault = False
        self.blocked = False  # an obstacle holds the shaft (tests: overload)
        self.overloaded = False
        self._over_since: float | None = None  # when the torque last rose above the threshold
        self.events: list[ProtectionEvent] = []
        self.notify = notify
        self.stale = True
        self.set("goal_position", self.present_steps())
        self.refresh()

    # -- memory -----------------------------------------------------------------------------------

    @property
    def id(self) -> int:
        return self.memory[5]

    def _register(self, name: str) -> Register:
        """Register ``name`` with the sign bit the servo stores it with (on SCS: the SCSCL
        library's direction bits, :data:`SCS_DIRECTION_BITS`)."""
        reg = self.series.register(name)
        if self.series.name is SeriesName.SCS and name in SCS_DIRECTION_BITS:
            return dataclasses.replace(reg, sign_bit=SCS_DIRECTION_BITS[name])
        return reg

    def get(self, name: str) -> int:
        """The value register ``name`` holds (sign decoded).

        Raises:
            KeyError: the series has no such register (``UnknownRegisterError``).
        """
        reg = self._register(name)
        return decode_value(reg, self.memory[reg.address : reg.address + reg.size], self._order)

    def set(self, name: str, value: int) -> None:
        """Store ``value`` in register ``name``, clamped to what the register holds.

        Raises:
            KeyError: the series has no such register (``UnknownRegisterError``).
        """
        reg = self._register(name)
        low, high = reg.limits
        encoded = encode_value(reg, max(low, min(high, int(value))), self._order)
        self.memory[reg.address : reg.address + reg.size] = encoded

    def value(self, name: str) -> int:
        """The value register ``name`` holds now (sign decoded, present registers refreshed).

        Raises:
            KeyError: the series has no such register (``UnknownRegisterError``).
        """
        self.refresh()
        return self.get(name)

    def stored_value(self, name: str) -> int:
        """What register ``name`` will read after a power cycle (EEPROM: what was stored).

        Raises:
            KeyError: the series has no such register (``UnknownRegisterError``).
        """
        reg = self._register(name)
        if not reg.eeprom:
            return DEFAULTS[self.series.name].get(name, 0)
        return decode_value(reg, self.stored[reg.address : reg.address + reg.size], self._order)

    def read(self, address: int, length: int) -> bytes:
        """``length`` bytes from ``address`` (present registers refreshed; beyond the memory:
        zeros)."""
        self.refresh()
        data = bytes(self.memory[address : address + length])
        return data + bytes(length - len(data))

    @property
    def locked(self) -> bool:
        """Whether EEPROM writes are kept only until the next power cycle."""
        return self.get(self.series.lock_register) != 0

    @property
    def torque_on(self) -> bool:
        return self.get("torque_enable") == 1

    @property
    def status(self) -> int:
        """The status bits (register 65, and every status packet's error byte)."""
        bits = 0
        if not self.get("min_voltage_limit") <= round(self.supply_v * 10) <= self.get(
                "max_voltage_limit"):
            bits |= StatusError.VOLTAGE
        if self.angle_fault:
            bits |= StatusError.ANGLE
        if self._overheated():
            bits |= StatusError.OVERHEAT
        if self.overloaded:
            bits |= StatusError.OVERLOAD
        return bits

    def return_delay_s(self) -> float:
        return self.get("return_delay_time") * 2e-6

    # -- writes -----------------------------------------------------------------------------------

    def write(self, address: int, data: bytes, now: float) -> None:
        """Apply a WRITE (or an ACTION's held REG_WRITE) of ``data`` at ``address``."""
        self.step(now)
        was_on = self.torque_on
        end = min(address + len(data), MEMORY_SIZE)
        written = [at for at in range(address, end) if self._writable(at)]
        for at in written:
            self.memory[at] = data[at - address]
        if not self.locked:  # the lock as it reads after this write
            stored = bytearray(self.stored)
            for at in written:
                if at < EEPROM_END:
                    stored[at] = self.memory[at]
            self.stored = bytes(stored)
        if self.torque_on and not was_on:
            goal = self._register("goal_position").address
            self._torque_switched_on(keep_goal=goal in written)
        self.stale = True

    def _writable(self, address: int) -> bool:
        # An address no register names is kept, as a real servo's spare byte would be.
        return address not in _read_only(self.series)

    def _torque_switched_on(self, keep_goal: bool) -> None:
        """Torque Enable went to 1: hold where the shaft is, unless the same write gave a goal
        (emulator choice, see the module docstring)."""
        if self._unloading():
            self.set("torque_enable", 0)  # the protection holds the torque off
            return
        self.overloaded = False
        self._over_since = None
        self.motor.reset_reference()
        if not keep_goal:
            self.set("goal_position", self.present_steps())

    def power_cycle(self, now: float) -> None:
        """Power off and on: RAM back to its defaults, EEPROM back to what was stored, torque
        off, held REG_WRITE and latched overload forgotten."""
        self.step(now)
        defaults = DEFAULTS[self.series.name]
        self.memory[:] = bytes(MEMORY_SIZE)
        self.memory[:EEPROM_END] = self.stored
        for name, value in defaults.items():
            if not self._register(name).eeprom:
                self.set(name, value)
        self.registered = None
        self.overloaded = False
        self._over_since = None
        self.motor.reset_reference()
        self.set("goal_position", self.present_steps())
        self.stale = True

    # -- physics ----------------------------------------------------------------------------------

    def _homing_offset(self) -> int:
        return self.get("homing_offset") if "homing_offset" in self.series.registers else 0

    def present_steps(self) -> int:
        """Present Position: the shaft's steps minus the homing offset, wrapped into the range
        on STS/SMS (single-turn)."""
        steps = round(self.motor.position / self.model.rad_per_step) - self._homing_offset()
        if self.series.name is SeriesName.STS_SMS:
            return steps % (self.model.position_max + 1)
        return max(0, min(self.model.position_max, steps))

    def _goal_rad(self) -> float:
        goal = self.get("goal_position")
        low, high = self.get("min_position_limit"), self.get("max_position_limit")
        if high > low:
            goal = max(low, min(high, goal))
        return (goal + self._homing_offset()) * self.model.rad_per_step

    def _overheated(self) -> bool:
        return round(self.temperature_c) > self.get("max_temperature_limit")

    def _unloading(self) -> bool:
        """Whether a persisting protection in Unloading Condition holds the torque off."""
        return bool(self.get("unloading_condition") & self.status & ~StatusError.OVERLOAD)

    def _torque_limit_nm(self) -> float:
        # SCS has no RAM Torque Limit register in the control table: its EEPROM maximum.
        name = "torque_limit" if "torque_limit" in self.series.registers else "max_torque_limit"
        limit = self.physics.stall_torque_nm * min(self.get(name), 1000) / 1000.0
        if self.overloaded:  # overload protection without unloading: Protective Torque
            limit = min(limit, self.physics.stall_torque_nm
                        * self.get("protective_torque") / 100.0)
        return limit

    def step(self, now: float) -> None:
        """Advance the shaft and the protections to ``now`` (earlier times are ignored)."""
        dt = now - self.last_step
        if dt <= 0.0:
            return
        self.last_step = now
        self.stale = True
        motor = self.motor
        if self._unloading() and self.torque_on:
            self._enter(StatusError(self.status & self.get("unloading_condition")), now, True)
        if not self.torque_on:
            motor.coast(dt)
            if self.blocked:
                motor.velocity = 0.0
            self._over_since = None
            return
        limit = self._torque_limit_nm()
        if motor.params.torque_limit != limit:
            motor.params = dataclasses.replace(self.params, torque_limit=limit)
        speed = self.get("goal_velocity")
        speed_rad_s = abs(speed) * self.model.speed_unit_rad_s if speed else 0.0
        unit = self.model.acceleration_unit_rad_s2
        accel = self.get("acceleration") * unit if unit is not None else 0.0
        held = motor.position
        motor.step_position(dt, self._goal_rad(), speed_rad_s, accel)
        if self.blocked:  # the loop pushes against the obstacle: torque builds, nothing moves
            motor.position, motor.velocity = held, 0.0
        self._check_overload(now - dt, now)

    def _check_overload(self, start: float, now: float) -> None:
        """Overload protection: the torque above the threshold for Protection Time."""
        if self.overloaded:
            return
        if "overload_torque" in self.series.registers:
            percent = self.get("overload_torque")
        else:
            percent = _SCS_OVERLOAD_PERCENT
        if abs(self.motor.torque) <= self.physics.stall_torque_nm * percent / 100.0:
            self._over_since = None
            return
        if self._over_since is None:
            self._over_since = start
        due = self._over_since + self.get("protection_time") * 0.010
        if now >= due:
            self.overloaded = True
            unload = bool(self.get("unloading_condition") & StatusError.OVERLOAD)
            self._enter(StatusError.OVERLOAD, due, unload)

    def _enter(self, error: StatusError, at: float, torque_off: bool) -> None:
        if torque_off:
            self.set("torque_enable", 0)
        self.events.append(ProtectionEvent(self.id, error, at, torque_off))
        self.notify()

    def set_temperature(self, celsius: float, now: float) -> None:
        """The temperature sensor reads ``celsius`` from ``now`` on (see *Overheat*)."""
        self.step(now)
        was = self._overheated()
        self.temperature_c = float(celsius)
        if self._overheated() and not was:
            unload = bool(self.get("unloading_condition") & StatusError.OVERHEAT)
            self._enter(StatusError.OVERHEAT, now, unload and self.torque_on)
        self.stale = True

    def set_supply(self, volts: float, now: float) -> None:
        """The supply reads ``volts`` from ``now`` on (see *Voltage*)."""
        self.step(now)
        was = self.status & StatusError.VOLTAGE
        self.supply_v = float(volts)
        if self.status & StatusError.VOLTAGE and not was:
            unload = bool(self.get("unloading_condition") & StatusError.VOLTAGE)
            self._enter(StatusError.VOLTAGE, now, unload and self.torque_on)
        self.stale = True

    def set_angle_fault(self, fault: bool) -> None:
        """The position sensor reports a fault (the angle bit) while ``fault``."""
        self.angle_fault = bool(fault)
        self.stale = True

    def refresh(self) -> None:
        """Rewrite the present registers from the motor if a step or a write made them stale."""
        if not self.stale:
            return
        motor, physics, model = self.motor, self.physics, self.model
        load = round(1000.0 * motor.torque / physics.stall_torque_nm)
        velocity = round(motor.velocity / model.speed_unit_rad_s)
        values = {
            "present_position": self.present_steps(),
            "present_velocity": velocity,
            "present_load": load,
            "present_voltage": round(self.supply_v * 10.0),
            "present_temperature": round(self.temperature_c),
            "status": self.status,
            "moving": int(velocity != 0),
        }
        if model.current_unit_a is not None:
            amps = abs(motor.torque) / physics.stall_torque_nm * physics.stall_current_a
            values["present_current"] = round(amps / model.current_unit_a)
        for name in _PRESENT:
            if name in values and name in self.series.registers:
                self.set(name, values[name])
        self.stale = False
