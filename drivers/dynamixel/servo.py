"""One emulated Dynamixel X-series servo: its control table, its motor and its Bus Watchdog.

Theory of operation
-------------------
:class:`EmulatedServo` is what :class:`~jtc_hw.drivers.dynamixel.emulator.DynamixelEmulator`
keeps per servo id. The emulator owns the pty, the packet dispatch, the timing and the lock;
a servo owns what one device remembers and how its shaft moves. No I/O and no lock here: the
emulator calls a servo under its own lock.

Each servo keeps its control table as a ``bytearray`` built from the model's defaults. Writes
must cover whole registers; read-only registers and EEPROM registers while torque is on are
refused with the access error; values out of a register's range give the data range error and
values beyond a limit register (Goal Position outside the position limits in position mode,
Goal Current/Velocity/PWM beyond their limits) the data limit error. Writes are all-or-nothing.

Physics: each servo drives one :class:`~jtc_hw.drivers.motor_model.Motor` (stall torque and
no-load speed from the model), advanced once per packet to its arrival time, and every few
milliseconds while the bus is idle. The present registers are rewritten from the motor (one
``struct.pack_into`` of the block 120..146) only when something reads the table after a step or
a write, so a Sync Read of the present block is a slice of the table.

Operating modes: position, extended position (profile velocity
and acceleration from their registers; 0 means no limit), current-based position (torque limited
by Goal Current), velocity, current (Goal Current * current unit * torque constant), PWM (a
crude voltage model); torque off coasts. Present registers (position, velocity, current or load,
PWM, moving, moving status, trajectories, realtime tick, voltage, temperature) follow the motor.

Register <-> shaft mapping (the e-Manual's "Present Position = actual position + Homing Offset",
with Drive Mode bit 0 reversing the direction)::

    present_position = direction * shaft_ticks + homing_offset
    shaft_ticks      = direction * (goal_position - homing_offset)
    present_velocity = direction * shaft_velocity;  present_current likewise

where ``direction`` is -1 with Drive Mode bit 0 set, else +1. The time-based profile (Drive Mode
bit 2) and "torque on by goal update" (bit 3) are not emulated: profiles are always velocity
based. Enabling torque copies Present Position into Goal Position so that nothing jumps
(emulator choice).

Bus Watchdog (address 98, 1 byte, firmware v38 and later), as the e-Manual describes it:

- 0 disables it and clears its error; 1..127 arms it, in 20 ms units; -1 is its error state,
  set by the servo (a host cannot write -1: data range error).
- With Torque Enable 1, when the time since the last instruction packet the servo received is
  larger than the set time, the servo stops: Profile Acceleration and Profile Velocity are
  applied as 0, so in every operating mode the shaft brakes as hard as the motor can and then
  holds still. Bus Watchdog then reads -1 and Goal PWM / Current / Velocity / Position become
  read-only: a write gets the data range error until 0 is written to Bus Watchdog.
- Counted packets: good-CRC instruction packets addressed to the servo's id or to the
  broadcast id (so every Sync Write / Sync Read feeds the watchdog of every servo on the bus);
  not packets for other ids, and nothing while the servo reboots. Expiry is measured on the
  emulator's own clock (``time.monotonic``) and takes effect at its exact moment, however late
  the emulator notices it.
- Emulator choices where the e-Manual is silent: the goal registers keep their values; while
  tripped only 0 may be written to Bus Watchdog; after the clear the servo keeps holding still
  until a goal is written (clearing alone never restarts a motion); REBOOT resets it to 0.
- Below firmware v38 the register does not exist: it reads 0 and a write gets the access error.

Each trip is recorded as a :class:`WatchdogTrip` (last instruction, expiry, speed then, when and
where the shaft came to rest) in :attr:`EmulatedServo.trips`; the emulator reads them out
(:meth:`~jtc_hw.drivers.dynamixel.emulator.DynamixelEmulator.watchdog_trips`).
"""

from __future__ import annotations

import dataclasses
import math
import struct
import time
from collections.abc import Callable, Mapping

from ..motor_model import Motor, MotorParams
from ..pty_emulator import BusServo
from .control_table import (
    BAUD_RATES,
    BUS_WATCHDOG_FIRMWARE,
    BUS_WATCHDOG_UNIT_S,
    HardwareError,
    Model,
    OperatingMode,
    Register,
)
from .packets import ALERT_BIT, ErrorNumber

__all__ = ["EmulatedServo", "WatchdogTrip"]

_TWO_PI = 2.0 * math.pi
_POSITION_MODES = (
    OperatingMode.POSITION,
    OperatingMode.EXTENDED_POSITION,
    OperatingMode.CURRENT_BASED_POSITION,
)
#: The present registers that follow the motor, written together once per physics step.
_PRESENT_NAMES = (
    "realtime_tick",
    "moving",
    "moving_status",
    "present_pwm",
    "present_current",
    "present_load",
    "present_velocity",
    "present_position",
    "velocity_trajectory",
    "position_trajectory",
    "present_input_voltage",
    "present_temperature",
)
#: While a tripped servo brakes, physics runs in slices this long so that the moment it comes
#: to rest is recorded to within one slice (the motor model's own sub-step), s.
_BRAKE_SLICE_S = 0.0005
_STRUCT_CODES = {(1, False): "B", (1, True): "b", (2, False): "H", (2, True): "h",
                 (4, False): "I", (4, True): "i"}


@dataclasses.dataclass(frozen=True)
class WatchdogTrip:
    """One expiry of a servo's Bus Watchdog, as the emulator recorded it.

    Times are ``time.monotonic()`` of the emulator's process (Linux: ``CLOCK_MONOTONIC``, the
    same clock in every process of the machine, so a benchmark can subtract the moment it
    killed the host from ``stopped_s``).

    Attributes:
        servo_id: the servo.
        timeout_s: the armed time (Bus Watchdog value * 20 ms).
        last_instruction_s: the last instruction packet the servo received (addressed to it, or
            broadcast) before the expiry.
        expired_s: ``last_instruction_s + timeout_s``: when the servo started to stop.
        speed_at_expiry_rad_s: how fast the shaft turned then, rad/s (absolute value).
        position_at_expiry_rad: shaft position then, rad.
        stopped_s: when the shaft came to rest (Present Velocity reads 0), or ``None`` while it
            is still braking.
        stopped_position_rad: shaft position at rest, rad (``None`` while braking).
    """

    servo_id: int
    timeout_s: float
    last_instruction_s: float
    expired_s: float
    speed_at_expiry_rad_s: float
    position_at_expiry_rad: float
    stopped_s: float | None = None
    stopped_position_rad: float | None = None


@dataclasses.dataclass(frozen=True)
class _Layout:
    """A model's registers in the form the hot paths want (no Register method calls).

    Attributes:
        fields: name -> (address, end, signed, lowest, highest encodable value).
        present_names: the registers of :data:`_PRESENT_NAMES` the model has, by address.
        present_struct: packs ``present_names`` (gaps padded) starting at ``present_start``.
        present_bounds: (lowest, highest) encodable value of each of ``present_names``.
        registers: every register, by address.
        coverage: (address, end) of a write -> the registers it covers, or the error number of
            a write that splits a register; filled on first use (hosts repeat their writes).
    """

    fields: Mapping[str, tuple[int, int, bool, int, int]]
    present_names: tuple[str, ...]
    present_start: int
    present_struct: struct.Struct
    present_bounds: tuple[tuple[int, int], ...]
    registers: tuple[Register, ...]
    coverage: dict[tuple[int, int], tuple[Register, ...] | int]

    def covered(self, address: int, end: int) -> tuple[Register, ...] | int:
        """The registers a write of ``address .. end`` covers, or ``ErrorNumber.DATA_LENGTH``
        if it covers part of one."""
        key = (address, end)
        found = self.coverage.get(key)
        if found is None:
            regs: list[Register] = []
            found = tuple(regs)
            for reg in self.registers:
                if reg.end <= address or reg.address >= end:
                    continue
                if reg.address < address or reg.end > end:
                    found = int(ErrorNumber.DATA_LENGTH)
                    break
                regs.append(reg)
            else:
                found = tuple(regs)
            self.coverage[key] = found
        return found


def _bounds(reg: Register) -> tuple[int, int]:
    """The values ``reg``'s size and signedness can hold (what :meth:`EmulatedServo.set`
    clamps to)."""
    if reg.signed:
        return -(1 << (8 * reg.size - 1)), (1 << (8 * reg.size - 1)) - 1
    return 0, (1 << (8 * reg.size)) - 1


_LAYOUTS: dict[str, _Layout] = {}


def _layout(model: Model) -> _Layout:
    """The :class:`_Layout` of ``model`` (built once per model name)."""
    cached = _LAYOUTS.get(model.name)
    if cached is not None:
        return cached
    fields = {
        name: (reg.address, reg.end, reg.signed, *_bounds(reg))
        for name, reg in model.registers.items()
    }
    present = sorted(
        (model.registers[n] for n in _PRESENT_NAMES if n in model.registers),
        key=lambda r: r.address,
    )
    start = present[0].address
    fmt, at = "<", start
    for reg in present:
        fmt += "x" * (reg.address - at) + _STRUCT_CODES[reg.size, reg.signed]
        at = reg.end
    layout = _Layout(
        fields=fields,
        present_names=tuple(r.name for r in present),
        present_start=start,
        present_struct=struct.Struct(fmt),
        present_bounds=tuple(_bounds(r) for r in present),
        registers=tuple(sorted(model.registers.values(), key=lambda r: r.address)),
        coverage={},
    )
    _LAYOUTS[model.name] = layout
    return layout


class EmulatedServo(BusServo):
    """One emulated servo: its control table, motor and injected faults."""

    def __init__(
        self,
        model: Model,
        servo_id: int,
        position: float,
        baud_value: int,
        notify: Callable[[], None] = lambda: None,
    ) -> None:
        super().__init__()  # the reply faults: drop, delay_s, corrupt, silent
        self.model = model
        self.table = model.defaults()
        self._layout = _layout(model)
        self._fields = self._layout.fields
        # Decoded register values: every physics step reads a dozen of them, and the table
        # changes only through set(), apply_write(), reboot() and sync_present(), which keep
        # this in step.
        self._values: dict[str, int] = {}
        # The present registers are rewritten lazily: after a physics step or a write they are
        # stale until something reads the table (see refresh()).
        self.stale = True
        self.epoch = time.monotonic()
        self.set("id", servo_id)
        self.set("baud_rate", baud_value)
        self.params = MotorParams(
            inertia=0.002 * max(model.stall_torque_nm, 0.1),
            damping=0.02 * model.stall_torque_nm / max(model.no_load_speed_rad_s, 1e-6),
            torque_limit=model.stall_torque_nm,
            velocity_limit=model.no_load_speed_rad_s,
            servo_bandwidth_hz=20.0,
            max_step_s=0.0005,
        )
        self.motor = Motor(self.params, position)
        self.last_step = self.epoch
        self.last_instruction = self.epoch
        self.registered: tuple[int, bytes] | None = None
        self.rebooting_until = 0.0
        # Bus Watchdog: after a trip the servo holds still until, the register cleared, a goal
        # is written (see step()); every trip is recorded, and ``notify`` (the emulator's
        # condition, called under its lock) wakes whoever waits for one.
        self.halted = False
        self.hold_rad: float | None = None  # where a tripped servo came to rest
        self.trips: list[WatchdogTrip] = []
        self.notify = notify
        # faults
        self.torque_on_fault = 0  # hardware error bits latched by the next torque on
        # Health: what the temperature and supply sensors read (set_temperature /
        # set_input_voltage); None: the model's nominal voltage.
        self.temperature_c = 35.0
        self.voltage_v: float | None = None
        self.sync_present()

    # -- table access -------------------------------------------------------------------------

    @property
    def id(self) -> int:
        return self.table[7]

    def get(self, name: str) -> int:
        value = self._values.get(name)
        if value is None:
            address, end, signed, _, _ = self._fields[name]
            value = int.from_bytes(self.table[address:end], "little", signed=signed)
            self._values[name] = value
        return value

    def set(self, name: str, value: int) -> None:
        """Store ``value`` (clamped to what the register's bytes hold); unknown names ignored."""
        f = self._fields.get(name)
        if f is not None:
            address, end, signed, lo, hi = f
            value = max(lo, min(hi, int(value)))
            self.table[address:end] = value.to_bytes(end - address, "little", signed=signed)
            self._values[name] = value
            self.stale = True

    def value(self, name: str) -> int:
        """The value of register ``name`` now (present registers rewritten from the motor).

        Raises:
            KeyError: the model has no such register (``UnknownRegisterError``).
        """
        self.sync_present()
        self.model.register(name)
        return self.get(name)

    @property
    def direction(self) -> int:
        return -1 if self.get("drive_mode") & 0x01 else 1

    @property
    def torque_on(self) -> bool:
        return self.table[64] == 1

    @property
    def error_byte(self) -> int:
        return ALERT_BIT if self.get("hardware_error_status") else 0

    def baud(self) -> int:
        return BAUD_RATES.get(self.get("baud_rate"), 57600)

    def return_delay_s(self) -> float:
        return self.get("return_delay_time") * 2e-6

    # -- physics ------------------------------------------------------------------------------

    def present_ticks(self) -> int:
        m = self.model
        return self.direction * m.rad_to_ticks(self.motor.position) + self.get("homing_offset")

    def goal_shaft_rad(self) -> float:
        raw = self.direction * (self.get("goal_position") - self.get("homing_offset"))
        return self.model.ticks_to_rad(raw)

    @property
    def has_watchdog(self) -> bool:
        return self.get("firmware_version") >= BUS_WATCHDOG_FIRMWARE

    def watchdog_timeout_s(self) -> float | None:
        """The armed Bus Watchdog time, s (``None``: off, tripped, or no watchdog)."""
        value = self.get("bus_watchdog")
        return value * BUS_WATCHDOG_UNIT_S if value > 0 else None

    def heard(self, now: float) -> None:
        """An instruction packet for this servo (its id or broadcast) arrived at ``now``."""
        self.last_instruction = now

    def step(self, now: float) -> None:
        """Advance to ``now``; trips the Bus Watchdog at the exact moment it expires."""
        if now <= self.last_step:
            return
        timeout = self.watchdog_timeout_s()
        # The e-Manual: with torque on, an interval *larger* than the set time stops the servo.
        if timeout is not None and self.torque_on and now - self.last_instruction > timeout:
            expiry = max(self.last_instruction + timeout, self.last_step)
            self._advance(expiry)
            self.trip_watchdog(expiry, timeout)
        self._advance(now)

    def _advance(self, now: float) -> None:
        dt = now - self.last_step
        if dt <= 0.0:
            return
        start, self.last_step = self.last_step, now
        self.stale = True
        m, motor = self.model, self.motor
        if not self.torque_on or self.get("hardware_error_status"):
            motor.coast(dt)
            return
        if self.halted:
            self._brake(start, now)
            return
        mode = self.get("operating_mode")
        d = self.direction
        if mode in _POSITION_MODES:
            limit = m.stall_torque_nm
            if mode == OperatingMode.CURRENT_BASED_POSITION and m.current_unit_a is not None:
                kt = m.torque_constant_nm_per_a or 0.0
                limit = min(limit, abs(self.get("goal_current")) * m.current_unit_a * kt)
            if motor.params.torque_limit != limit:
                motor.params = dataclasses.replace(self.params, torque_limit=limit)
            motor.step_position(
                dt,
                self.goal_shaft_rad(),
                m.velocity_to_rad_s(self.get("profile_velocity")),
                self.get("profile_acceleration") * m.profile_acceleration_unit_rad_s2,
            )
            if motor.params is not self.params:
                motor.params = self.params
        elif mode == OperatingMode.VELOCITY:
            motor.step_velocity(
                dt,
                d * m.velocity_to_rad_s(self.get("goal_velocity")),
                self.get("profile_acceleration") * m.profile_acceleration_unit_rad_s2,
            )
        elif mode == OperatingMode.CURRENT and m.current_unit_a is not None:
            kt = m.torque_constant_nm_per_a or 0.0
            motor.step_torque(dt, d * self.get("goal_current") * m.current_unit_a * kt)
        elif mode == OperatingMode.PWM:
            duty = self.get("goal_pwm") / 885.0
            back_emf = motor.velocity / max(m.no_load_speed_rad_s, 1e-6)
            motor.step_torque(dt, m.stall_torque_nm * (d * duty - back_emf))
        else:
            motor.coast(dt)

    def _at_rest(self) -> bool:
        """Present Velocity reads 0 (below half a count)."""
        return abs(self.motor.velocity) < 0.5 * self.model.velocity_unit_rad_s

    def _brake(self, start: float, end: float) -> None:
        """After a trip, in every operating mode: stop with Profile Velocity and Profile
        Acceleration applied as 0 (the e-Manual), i.e. as hard as the motor's torque allows,
        then hold that position.

        Until the shaft is at rest the physics runs in short slices, so that the recorded
        ``stopped_s`` is exact to a slice however rarely the emulator is stepped.
        """
        motor, params = self.motor, self.params
        if motor.params is not params:
            motor.params = params
        t = start
        while self.hold_rad is None and t < end:
            h = min(_BRAKE_SLICE_S, end - t)
            # The torque that would stop the shaft within this slice, within the motor's limit.
            brake = motor.velocity * params.inertia / h
            motor.step_torque(h, -max(-params.torque_limit, min(params.torque_limit, brake)))
            t += h
            if self._at_rest():
                self._stopped(t)
        if t < end and self.hold_rad is not None:
            motor.step_position(end - t, self.hold_rad)

    def _stopped(self, at: float) -> None:
        self.hold_rad = self.motor.position
        self.motor.reset_reference()
        self.trips[-1] = dataclasses.replace(
            self.trips[-1], stopped_s=at, stopped_position_rad=self.motor.position
        )
        self.notify()

    def trip_watchdog(self, at: float, timeout_s: float) -> None:
        """The Bus Watchdog expired at ``at``: Bus Watchdog = -1, goals read-only, stop.

        The goal registers keep their values (the e-Manual makes them read-only; it does not
        say they change). Where the e-Manual is silent the emulator takes the safe side: the
        servo holds still until, the register cleared with 0, a goal is written (clearing alone
        never restarts a motion).
        """
        self.set("bus_watchdog", -1)
        self.halted = True
        self.hold_rad = None
        self.trips.append(WatchdogTrip(
            servo_id=self.id,
            timeout_s=timeout_s,
            last_instruction_s=self.last_instruction,
            expired_s=at,
            speed_at_expiry_rad_s=abs(self.motor.velocity),
            position_at_expiry_rad=self.motor.position,
        ))
        if self._at_rest():
            self._stopped(at)
        else:
            self.notify()

    def refresh(self) -> None:
        """Bring the present registers up to date if a step or a write made them stale."""
        if self.stale:
            self.sync_present()

    def sync_present(self) -> None:
        """Copy the motor's state into the present registers (one ``pack_into`` of the block)."""
        m, motor, d = self.model, self.motor, self.direction
        now = self.last_step
        present_ticks = self.present_ticks()
        velocity = m.rad_s_to_velocity(motor.velocity)
        values = {
            "present_position": present_ticks,
            "present_velocity": d * velocity,
            "present_pwm": d * round(885.0 * motor.torque / m.stall_torque_nm),
        }
        if m.current_unit_a is not None and m.torque_constant_nm_per_a:
            amps = motor.torque / m.torque_constant_nm_per_a
            values["present_current"] = d * m.a_to_current(amps)
        else:
            values["present_load"] = d * round(1000.0 * motor.torque / m.stall_torque_nm)
        moving = abs(velocity) > self.get("moving_threshold")
        values["moving"] = int(moving)
        in_position = abs(self.get("goal_position") - present_ticks) <= 20
        profiling = abs(motor.reference - motor.position) > 1e-3 or moving
        values["moving_status"] = (0x01 if in_position else 0) | (0x02 if profiling else 0)
        values["position_trajectory"] = (
            d * m.rad_to_ticks(motor.reference) + self.get("homing_offset")
        )
        values["velocity_trajectory"] = d * velocity
        values["realtime_tick"] = int((now - self.epoch) * 1000.0) % 32768
        volts = m.nominal_voltage_v if self.voltage_v is None else self.voltage_v
        values["present_input_voltage"] = round(volts * 10.0)
        values["present_temperature"] = round(self.temperature_c)
        layout = self._layout
        packed = [
            # Clamped like set(); a register the motor does not drive keeps its value.
            max(lo, min(hi, int(values[name]))) if name in values else self.get(name)
            for name, (lo, hi) in zip(layout.present_names, layout.present_bounds, strict=True)
        ]
        layout.present_struct.pack_into(self.table, layout.present_start, *packed)
        self._values.update(zip(layout.present_names, packed, strict=True))
        self.stale = False

    # -- writes -------------------------------------------------------------------------------

    def check_write(self, address: int, data: bytes) -> int:
        """The error number a write of ``data`` at ``address`` gets (0: accepted)."""
        m = self.model
        end = address + len(data)
        if not data:
            return ErrorNumber.DATA_LENGTH
        regs = self._layout.covered(address, end)
        if isinstance(regs, int):
            return regs
        covered = [
            (reg, int.from_bytes(data[reg.address - address : reg.end - address], "little",
                                 signed=reg.signed))
            for reg in regs
        ]
        if not covered or end > len(self.table):
            return ErrorNumber.ACCESS
        pending = {reg.name: value for reg, value in covered}
        for reg, value in covered:
            if not reg.writable or (reg.eeprom and self.torque_on):
                return ErrorNumber.ACCESS
            if reg.name == "bus_watchdog" and not self.has_watchdog:
                return ErrorNumber.ACCESS  # not defined before firmware v38
            if not reg.minimum <= value <= reg.maximum:
                return ErrorNumber.DATA_RANGE
        if "operating_mode" in pending:
            try:
                if OperatingMode(pending["operating_mode"]) not in m.operating_modes:
                    return ErrorNumber.DATA_RANGE
            except ValueError:
                return ErrorNumber.DATA_RANGE
        if self.get("bus_watchdog") < 0:
            # After a trip the goals are read-only (the e-Manual: Data Range Error) until 0 is
            # written to Bus Watchdog; the emulator refuses any other value meanwhile, so that
            # the reset rule is one rule: clear with 0, then arm again.
            if any(name.startswith("goal_") for name in pending):
                return ErrorNumber.DATA_RANGE
            if pending.get("bus_watchdog", 0) != 0:
                return ErrorNumber.DATA_RANGE
        if pending.get("torque_enable") == 1 and self.get("hardware_error_status"):
            return ErrorNumber.RESULT_FAIL

        def limit(name: str) -> int:
            return pending[name] if name in pending else self.get(name)

        mode = limit("operating_mode")
        if "goal_position" in pending and mode == OperatingMode.POSITION:
            if (
                not limit("min_position_limit")
                <= pending["goal_position"]
                <= limit("max_position_limit")
            ):
                return ErrorNumber.DATA_LIMIT
        for goal, lim in (
            ("goal_current", "current_limit"),
            ("goal_velocity", "velocity_limit"),
            ("goal_pwm", "pwm_limit"),
        ):
            if goal in pending and abs(pending[goal]) > limit(lim):
                return ErrorNumber.DATA_LIMIT
        return 0

    def apply_write(self, address: int, data: bytes) -> None:
        """Store an accepted write and apply its side effects."""
        was_on = self.torque_on
        end = address + len(data)
        self.table[address:end] = data
        regs = self._layout.covered(address, end)
        if isinstance(regs, int):  # not through check_write: forget every decoded value
            self._values.clear()
        else:
            for reg in regs:
                self._values.pop(reg.name, None)
        self.stale = True  # goals, offsets and the drive mode feed the present registers
        if self.torque_on and not was_on:
            self.motor.reset_reference()
            self.set("goal_position", self.present_ticks())
            if self.torque_on_fault:
                # An injected fault found on energising the motor: latched, torque off again.
                self.set("hardware_error_status", self.torque_on_fault)
                self.set("torque_enable", 0)
                self.torque_on_fault = 0
        if (
            self.halted
            and not isinstance(regs, int)
            and self.get("bus_watchdog") >= 0
            and any(reg.name.startswith("goal_") for reg in regs)
        ):
            self.halted = False  # a new goal after the clear: the servo obeys again
            self.hold_rad = None
            self.motor.reset_reference()

    def write(self, address: int, data: bytes) -> int:
        error = self.check_write(address, data)
        if not error:
            self.apply_write(address, data)
        return error

    def reboot(self, now: float, reboot_time_s: float) -> None:
        """Reset the RAM area and the latched errors; silent for ``reboot_time_s``."""
        defaults = self.model.defaults()
        self.table[64:] = defaults[64:]
        self._values.clear()
        self.registered = None
        self.halted = False
        self.hold_rad = None
        self.motor.reset_reference()
        self.epoch = now
        self.rebooting_until = now + reboot_time_s
        self.sync_present()

    def clear_multi_turn(self) -> None:
        """CLEAR (multi-turn): the shaft's position wraps into one turn, where it stands."""
        self.motor.position = math.remainder(self.motor.position, _TWO_PI) % _TWO_PI
        self.motor.reset_reference()
        self.sync_present()

    def detect(self, bits: HardwareError) -> None:
        """Set ``bits`` in Hardware Error Status; torque off if Shutdown holds one of them."""
        self.set("hardware_error_status", self.get("hardware_error_status") | int(bits))
        if self.get("shutdown") & int(bits):
            self.set("torque_enable", 0)

    def set_firmware(self, version: int) -> None:
        """Report Firmware Version ``version``; below :data:`BUS_WATCHDOG_FIRMWARE` the Bus
        Watchdog register does not exist (reads 0).

        Raises:
            ValueError: ``version`` outside 0..255.
        """
        if not 0 <= version <= 255:
            raise ValueError(f"firmware version must be in 0..255, got {version}")
        self.set("firmware_version", version)
        if not self.has_watchdog:
            self.set("bus_watchdog", 0)
