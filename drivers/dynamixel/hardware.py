"""Dynamixel X-series servos on one Protocol 2.0 bus (hardware kind ``dynamixel``).

Theory of operation
-------------------
One :class:`DynamixelHardware` owns one serial bus (:class:`~jtc_hw.drivers.dynamixel.bus.
DynamixelBus`, the only module that imports the SDK) and one servo per joint. Each cycle costs
exactly one transaction per direction:

* ``read``: one Sync Read of the contiguous block Present Current / Velocity / Position
  (addresses 126..135, 10 bytes per servo), decoded for all servos at once with numpy;
* ``write``: one Sync Write of the goal register of the operating mode.

**Operating mode** follows from the controller's command interface (exactly one):
``position`` -> Position Control (or Extended Position with ``extended_position: true``),
``velocity`` -> Velocity Control, ``effort`` -> Current Control.

**Units.** Joint units <-> register counts per joint, the same factors both ways
(:class:`~jtc_hw.drivers.dynamixel.units.JointUnits`: direction, gear ratio, offset).
Commands are clamped to the servo's limits (position limits, Velocity Limit, Current Limit read
back at configure) before they are sent: a Sync Write has no reply, so a value the servo would
refuse must never be sent.

**Bus Watchdog** (register 98; see docs/dynamixel.md). ``activate`` arms it on every servo, in
every operating mode, once the torque is on: ``ceil(watchdog_s / 20 ms)`` (1..127, so
``watchdog_s`` is at most 2.54 s). A daemon that stops commanding (killed, hung) then leaves
servos that brake to a stop by themselves. A clean ``deactivate`` disarms it (writes 0) after
the safe action; a servo found tripped is left tripped. A trip seen while active (the register
reads -1 when checked after a bus silence longer than half the watchdog time, before a cycle's
read or write; or a goal write answered with the Data Range Error) is a
:class:`~jtc_hw.errors.MotorFault` "bus watchdog expired ...; rearm to resume" and takes the
normal fault path; activation refuses such a servo until ``recover`` clears it (writes 0, then
at once a goal that keeps the servo still: the e-Manual does not say whether a cleared servo
resumes its old goal). A trip found at ``configure`` that this instance
never armed is a previous daemon's: ``activate`` clears it the same way, with a warning, so a
daemon started after a crash can run. Servos with firmware older than v38 have no Bus Watchdog
and are refused at ``configure`` (the message says how to update the firmware).

**Truthful activation.** After the torque is on and the watchdog armed, one Sync Read of
Torque Enable .. Present Position proves each servo enabled and obeying (no hardware error,
torque 1, watchdog armed, the goal the one just written); otherwise activation is undone and
fails with one line naming the servo and what to check. A rearm that succeeds is holding.

**Faults.** A failed read (the cycle's Sync Read, a register read, a ping at configuration) is
retried up to ``max_retries`` times at once (a read, so a retry repeats nothing); then a
:class:`~jtc_hw.errors.CommunicationError` names the servo (id and joint) and the cause. A status
packet with the alert bit makes the driver read that servo's Hardware Error Status and raise
:class:`~jtc_hw.errors.MotorFault` naming the cause (overload, overheating, ...). A failed read
never changes the last known positions. The loop then aborts the goal and applies the
``safe_action``. ``recover`` (the client's explicit ``rearm``) reboots every servo with a latched
error, waits (bounded by ``reboot_timeout_s``) for it to answer, re-applies its setup; ``activate``
then seeds the goal from the measured position, so re-arming never jumps.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar, Final, TypeVar

import numpy as np
from numpy.typing import NDArray

from jtc_hw.controller.config import STATE_INTERFACE_TYPES
from jtc_hw.errors import (
    CommunicationError,
    ConfigurationError,
    HardwareError,
    MotorFault,
    add_note,
)
from jtc_hw.hardware import (
    DeviceName,
    DeviceWatchdog,
    HardwareInterface,
    JointCommand,
    JointState,
    ParamSpec,
    SafeAction,
)

from .bus import (
    ERROR_ALERT,
    DynamixelBus,
    ServoCommunicationError,
    ServoStatusError,
    SyncReadResult,
)
from .control_table import (
    BUS_WATCHDOG_FIRMWARE,
    BUS_WATCHDOG_MAX,
    BUS_WATCHDOG_UNIT_S,
    PRESENT_BLOCK_ADDRESS,
    PRESENT_BLOCK_SIZE,
    Model,
    OperatingMode,
    UnknownModelError,
    hardware_error_text,
    model_by_name,
    model_by_number,
)
from .health import ServoHealth
from .params import GAINS, PARAMS
from .units import JointUnits

__all__ = ["DynamixelHardware"]

_log = logging.getLogger(__name__)
_T = TypeVar("_T")

F64 = NDArray[np.float64]

_POSITION_MODE_TICKS: Final = (0, 4095)
_EXTENDED_TICKS: Final = (-1_048_575, 1_048_575)
_PRESENT_DTYPE: Final = np.dtype([("current", "<i2"), ("velocity", "<i4"), ("position", "<i4")])
_BUS_WATCHDOG: Final = 98
#: Activation reads back Torque Enable (64) .. Present Position (132..135) in one Sync Read.
_ENABLED_BLOCK: Final = (64, 136)
#: Position modes: after activation the servo's goal must be this close to where it is, ticks
#: (a tick or two of motion between reading the position and switching the torque on; a goal
#: the servo refused would be wherever the last session left it).
_GOAL_SEED_TOLERANCE_TICKS: Final = 20
_DATA_RANGE_ERROR: Final = 4  # status packet error number: Data Range Error
_POSITION_FAMILY: Final = (
    OperatingMode.POSITION, OperatingMode.EXTENDED_POSITION, OperatingMode.CURRENT_BASED_POSITION
)


class DynamixelHardware(HardwareInterface):
    """Dynamixel X-series servos, one per joint, on one serial bus (see the module docstring).

    Raises:
        ConfigurationError: invalid parameters (see :attr:`PARAMS`): duplicate ids, an unknown
            model or one without the needed operating mode, a direction other than +-1,
            position limits outside the servo's range, or an unsupported interface combination.
    """

    kind: ClassVar[str] = "dynamixel"
    COMMAND_INTERFACES: ClassVar[tuple[str, ...]] = ("position", "velocity", "effort")
    STATE_INTERFACES: ClassVar[tuple[str, ...]] = tuple(
        i for i in ("position", "velocity", "effort") if i in STATE_INTERFACE_TYPES
    )

    PARAMS: ClassVar[Mapping[str, ParamSpec]] = PARAMS

    def __init__(
        self,
        name: str,
        joints: Sequence[str],
        command_interfaces: Sequence[str],
        state_interfaces: Sequence[str],
        params: Mapping[str, Any],
    ) -> None:
        super().__init__(name, joints, command_interfaces, state_interfaces, params)
        p = self.params
        n = len(self.joints)
        if len(self.command_interfaces) != 1:
            raise ConfigurationError(
                f"{self._owner()}: a servo takes exactly one command interface (position, "
                f"velocity or effort: its operating mode), got "
                f"[{', '.join(self.command_interfaces)}]",
                "command_interfaces",
                self.command_interfaces,
            )
        self._interface: str = self.command_interfaces[0]
        self.ids: tuple[int, ...] = tuple(p["ids"])
        seen: dict[int, str] = {}
        for joint, servo_id in zip(self.joints, self.ids, strict=True):
            if servo_id in seen:
                raise ConfigurationError(
                    f"servo id {servo_id} is given to both {seen[servo_id]!r} and {joint!r}; "
                    "each joint needs its own servo",
                    "params.ids",
                    servo_id,
                )
            seen[servo_id] = joint
        models: list[Model] = []
        for joint, model_name in zip(self.joints, p["model"], strict=True):
            try:
                models.append(model_by_name(model_name))
            except UnknownModelError as exc:
                raise ConfigurationError(f"joint {joint!r}: {exc}", "params.model",
                                         model_name) from None
        self.models: tuple[Model, ...] = tuple(models)
        if self._interface == "position":
            self.mode = (OperatingMode.EXTENDED_POSITION if p["extended_position"]
                         else OperatingMode.POSITION)
        elif self._interface == "velocity":
            self.mode = OperatingMode.VELOCITY
        else:
            self.mode = OperatingMode.CURRENT
        for joint, model in zip(self.joints, self.models, strict=True):
            if self.mode not in model.operating_modes or (
                self.mode is OperatingMode.CURRENT and model.current_unit_a is None
            ):
                raise ConfigurationError(
                    f"joint {joint!r}: {model.name} has no {self.mode.name.lower()} mode, "
                    f"needed by the {self._interface!r} command interface",
                    "command_interfaces", self._interface,
                )

        # Bus Watchdog value armed on activate: the configured time rounded up to 20 ms steps.
        watchdog_units = max(1, math.ceil(p["watchdog_s"] / BUS_WATCHDOG_UNIT_S - 1e-9))
        if watchdog_units > BUS_WATCHDOG_MAX:
            raise ConfigurationError(
                f"watchdog_s {p['watchdog_s']:g} s does not fit the servos' Bus Watchdog "
                f"(1..{BUS_WATCHDOG_MAX} x 20 ms: at most "
                f"{BUS_WATCHDOG_MAX * BUS_WATCHDOG_UNIT_S:g} s); lower params.watchdog_s",
                "params.watchdog_s",
                p["watchdog_s"],
            )
        self._watchdog_units: int = watchdog_units
        self.watchdog_timeout_s: float = watchdog_units * BUS_WATCHDOG_UNIT_S
        """The Bus Watchdog time armed on activate, s (``watchdog_s`` rounded up to 20 ms)."""

        self.units = JointUnits(self.models, p["direction"], p["gear_ratio"], p["offset"])
        """Joint units <-> register counts (public: tests and tools use it)."""
        units = self.units
        limits = p["position_limits"]
        self._joint_lower = np.array([lim[0] for lim in limits], dtype=np.float64)
        self._joint_upper = np.array([lim[1] for lim in limits], dtype=np.float64)
        # Tick limits from the joint limits (inf where not given).
        a = units.joint_to_ticks_float(self._joint_lower)
        b = units.joint_to_ticks_float(self._joint_upper)
        self._limit_ticks_lo = np.where(np.isnan(a), -np.inf, np.minimum(a, b))
        self._limit_ticks_hi = np.where(np.isnan(b), np.inf, np.maximum(a, b))
        if self.mode is OperatingMode.POSITION:
            low, high = _POSITION_MODE_TICKS
            for i, joint in enumerate(self.joints):
                lo, hi = self._limit_ticks_lo[i], self._limit_ticks_hi[i]
                if (np.isfinite(lo) and lo < low - 0.5) or (np.isfinite(hi) and hi > high + 0.5):
                    raise ConfigurationError(
                        f"joint {joint!r}: position_limits [{self._joint_lower[i]:g}, "
                        f"{self._joint_upper[i]:g}] rad map to servo ticks [{lo:.0f}, {hi:.0f}], "
                        f"outside Position mode's {low}..{high}; adjust offset (tick 2048 is "
                        "the middle) or set extended_position: true",
                        "params.position_limits", limits[i],
                    )
        self._n = n
        self._bus: DynamixelBus | None = None
        # Effective command clamps in register units, set at configure.
        self._cmd_lo = np.full(n, -np.inf)
        self._cmd_hi = np.full(n, np.inf)
        self._positions: F64 | None = None  # last good read, joint units
        self._present_ticks: NDArray[Any] = np.zeros(n, dtype=np.int32)
        self._velocities: F64 = np.zeros(n)
        self._efforts: F64 = np.zeros(n)
        self._latched: dict[int, int] = {}  # servo id -> hardware error flags
        # Bus Watchdog: armed while active; servos this instance saw trip (activation refuses
        # them until recover(), as a latched error); servos found tripped at configure that this
        # instance never armed (a previous daemon's): activate clears those, with a warning.
        self._armed = False
        # Servos whose watchdog the last deactivation could not disarm (a broken bus): while
        # any is, nothing is sent while faulted (_monitor).
        self._left_armed: set[int] = set()
        self._tripped: set[int] = set()
        self._leftover_trips: set[int] = set()
        self._last_fault_by_servo: dict[int, str] = {}
        self._retries = 0
        # Health: read in turn, one block per slot (see _read_health), kept per servo.
        self._servo_health = ServoHealth(self.ids, self.joints, self.models,
                                         p["health_period_s"], p["voltage_range"])
        self._joint_of = dict(zip(self.ids, self.joints, strict=True))
        self._index_of = {servo_id: i for i, servo_id in enumerate(self.ids)}
        # What write() sends: the command field, its register, and the conversion to counts.
        self._command_field = {"position": "positions", "velocity": "velocities",
                               "effort": "effort"}[self._interface]
        self._goal_name = {"position": "goal_position", "velocity": "goal_velocity",
                           "effort": "goal_current"}[self._interface]
        if self._interface == "position":
            self._goal_offset, self._goal_inverse = units.offset, units.pos_inverse
        elif self._interface == "velocity":
            self._goal_offset, self._goal_inverse = np.zeros(n), units.vel_inverse
        else:
            self._goal_offset, self._goal_inverse = np.zeros(n), units.effort_inverse

    # -- labels ---------------------------------------------------------------------------------

    def _servo(self, servo_id: int | None) -> str:
        if servo_id is None:
            return f"{self._owner()} (bus {self.params['port']})"
        joint = self._joint_of.get(servo_id, "?")
        return f"{self._owner()}: servo {servo_id} (joint {joint!r})"

    def _require_bus(self) -> DynamixelBus:
        if self._bus is None or not self._bus.is_open:
            raise CommunicationError(f"{self._owner()}: the bus is not open")
        return self._bus

    def _comm_error(self, exc: ServoCommunicationError, what: str,
                    attempts: int = 1) -> CommunicationError:
        tries = f" after {attempts} attempts" if attempts > 1 else ""
        message = (
            f"{self._servo(exc.servo_id)}: {what} failed{tries}: {exc.cause}; check the "
            f"servo's power and cable, its id and baud rate ({self.params['baud_rate']} bit/s)"
        )
        if exc.servo_id is not None:
            self._last_fault_by_servo[exc.servo_id] = exc.cause
        return CommunicationError(message)

    def _motor_fault(self, servo_id: int, flags: int) -> MotorFault:
        cause = hardware_error_text(flags)
        self._latched[servo_id] = flags
        self._last_fault_by_servo[servo_id] = cause
        return MotorFault(
            f"{self._servo(servo_id)}: hardware error: {cause} (the servo switched its torque "
            "off); remove the cause (load, temperature, supply), then re-arm (jtc-hw rearm) to "
            "reboot it"
        )

    def _watchdog_fault(self, servo_id: int) -> MotorFault:
        self._tripped.add(servo_id)
        self._last_fault_by_servo[servo_id] = "bus watchdog expired"
        return MotorFault(
            f"{self._servo(servo_id)}: bus watchdog expired (no command for "
            f"{self.watchdog_timeout_s * 1000:.0f} ms); rearm to resume"
        )

    # -- the hardware contract's descriptions ---------------------------------------------------

    def device_watchdog(self) -> DeviceWatchdog:
        """The servos' Bus Watchdog (every servo has one: older firmware is refused at
        configure)."""
        ms = self.watchdog_timeout_s * 1000
        return DeviceWatchdog(
            self.watchdog_timeout_s,
            f"Dynamixel Bus Watchdog {ms:.0f} ms (register 98, firmware v{BUS_WATCHDOG_FIRMWARE}"
            "+): with no instruction packet for that long each servo brakes to a stop and holds; "
            "goals are refused until a rearm",
        )

    def devices(self) -> tuple[DeviceName, ...]:
        """The serial port, resolved (``/dev/serial/by-id/...`` and ``/dev/ttyUSB0`` are one
        device). The whole port, not per servo id: the bus is half duplex with one master,
        so a second daemon's packets would collide with this one's whatever ids they name."""
        port = self.params["port"]
        real = os.path.realpath(port)
        return (DeviceName(real, real if real == port else f"{port} ({real})"),)

    # -- lifecycle primitives -------------------------------------------------------------------

    def _configure(self) -> None:
        p = self.params
        bus = DynamixelBus(
            p["port"], p["baud_rate"], timeout_ms=p["timeout_ms"],
            latency_timer_warn=p["latency_timer_warn"],
        )
        bus.open()
        self._bus = bus
        try:
            for i, servo_id in enumerate(self.ids):
                self._check_model(i, servo_id)
                self._check_firmware(servo_id)
            self._latched = {}
            self._leftover_trips = set()
            for i, servo_id in enumerate(self.ids):
                flags = self._read_register(servo_id, "hardware_error_status")
                if flags:
                    self._latched[servo_id] = flags
                    self._last_fault_by_servo[servo_id] = hardware_error_text(flags)
                if (self._read_register(servo_id, "bus_watchdog") < 0
                        and servo_id not in self._tripped):
                    self._leftover_trips.add(servo_id)
                self._setup_servo(i)
        except BaseException:
            bus.close()
            self._bus = None
            raise

    def _check_model(self, i: int, servo_id: int) -> None:
        bus = self._require_bus()
        number = self._retried("ping at configure", bus.ping, servo_id)
        expected = self.models[i]
        if number != expected.model_number:
            found = model_by_number(number)
            found_name = found.name if found else "an unknown model"
            raise ConfigurationError(
                f"{self._servo(servo_id)} is {found_name} (model number {number}) but the "
                f"configuration says {expected.name} (model number {expected.model_number}); "
                "fix params.model or the servo's id",
                "params.model",
                expected.name,
            )

    def _check_firmware(self, servo_id: int) -> None:
        """Refuse a servo without a Bus Watchdog: it would keep its last command (turning, in
        velocity mode) if the daemon stopped. Updating the firmware is free and quick; running
        some joints unprotected is not a choice this driver makes silently."""
        firmware = self._read_register(servo_id, "firmware_version")
        self._servo_health.firmware[servo_id] = firmware
        if firmware < BUS_WATCHDOG_FIRMWARE:
            raise HardwareError(
                f"{self._servo(servo_id)}: firmware v{firmware} has no Bus Watchdog (needs "
                f"v{BUS_WATCHDOG_FIRMWARE} or later), so it would keep moving if the daemon "
                "stopped; update its firmware with the Firmware Update of DYNAMIXEL Wizard 2.0"
            )

    def _read_register(self, servo_id: int, name: str) -> int:
        bus = self._require_bus()
        reg = self.models[self._index_of[servo_id]].register(name)
        raw = self._retried(f"reading {name}", bus.read_bytes, servo_id, reg.address, reg.size)
        value: int = reg.decode(raw)
        return value

    def _write_register(self, servo_id: int, name: str, value: int) -> None:
        bus = self._require_bus()
        reg = self.models[self._index_of[servo_id]].register(name)
        try:
            bus.write(servo_id, reg.address, reg.size, int(value))
        except ServoCommunicationError as exc:
            raise self._comm_error(exc, f"writing {name} = {value}") from exc
        except ServoStatusError as exc:
            if (name.startswith("goal_") and exc.error & ~ERROR_ALERT == _DATA_RANGE_ERROR
                    and self._read_register(servo_id, "bus_watchdog") < 0):
                # A tripped Bus Watchdog makes the goals read-only (Data Range Error).
                raise self._watchdog_fault(servo_id) from exc
            raise HardwareError(f"{self._servo(servo_id)}: writing {name} = {value}: {exc}") \
                from exc

    def _setup_servo(self, i: int) -> None:
        """Operating mode, return delay and limits (EEPROM, only if they differ: writing them
        needs the torque off), then gains and profile (RAM); read back the command clamps."""
        p = self.params
        servo_id = self.ids[i]
        model = self.models[i]
        eeprom: dict[str, int] = {
            "operating_mode": int(self.mode),
            "return_delay_time": p["return_delay_time_us"] // 2,
        }
        if self.mode is OperatingMode.POSITION:
            lo, hi = self._limit_ticks_lo[i], self._limit_ticks_hi[i]
            if np.isfinite(lo):
                eeprom["min_position_limit"] = max(_POSITION_MODE_TICKS[0], round(lo))
            if np.isfinite(hi):
                eeprom["max_position_limit"] = min(_POSITION_MODE_TICKS[1], round(hi))
        changes = {
            name: value for name, value in eeprom.items()
            if self._read_register(servo_id, name) != value
        }
        if changes:
            if self._read_register(servo_id, "torque_enable"):
                self._write_register(servo_id, "torque_enable", 0)
            for name, value in changes.items():
                self._write_register(servo_id, name, value)
        for gain in GAINS:
            value = p[gain][i]
            if value is not None:
                self._write_register(servo_id, gain, value)
        for name, per_joint, unit in (
            ("profile_velocity", p["profile_velocity"][i], model.velocity_unit_rad_s),
            ("profile_acceleration", p["profile_acceleration"][i],
             model.profile_acceleration_unit_rad_s2),
        ):
            counts = max(1, round(per_joint * self.units.gear[i] / unit)) if per_joint > 0 else 0
            if self._read_register(servo_id, name) != counts:
                self._write_register(servo_id, name, counts)
        # Clamps in register units of the goal register.
        if self.mode is OperatingMode.POSITION:
            lo = self._read_register(servo_id, "min_position_limit")
            hi = self._read_register(servo_id, "max_position_limit")
            self._cmd_lo[i] = max(lo, self._limit_ticks_lo[i])
            self._cmd_hi[i] = min(hi, self._limit_ticks_hi[i])
        elif self.mode is OperatingMode.EXTENDED_POSITION:
            self._cmd_lo[i] = max(_EXTENDED_TICKS[0], self._limit_ticks_lo[i])
            self._cmd_hi[i] = min(_EXTENDED_TICKS[1], self._limit_ticks_hi[i])
        elif self.mode is OperatingMode.VELOCITY:
            limit = self._read_register(servo_id, "velocity_limit")
            self._cmd_lo[i], self._cmd_hi[i] = -limit, limit
        else:
            limit = self._read_register(servo_id, "current_limit")
            self._cmd_lo[i], self._cmd_hi[i] = -limit, limit

    def _activate(self, now_ns: int) -> JointCommand:
        for servo_id, flags in self._latched.items():
            raise self._motor_fault(servo_id, flags)
        for servo_id in self.ids:
            if servo_id in self._tripped:
                raise self._watchdog_fault(servo_id)  # seen while active: only a rearm clears it
        for i, servo_id in enumerate(self.ids):
            if servo_id in self._leftover_trips:
                # Tripped before this instance armed it: a previous daemon stopped commanding
                # the servo, which then stopped by itself. Starting again is the clearing.
                self._clear_trip(i)
                self._leftover_trips.discard(servo_id)
                _log.warning(
                    "%s: its Bus Watchdog had expired before this activation (the previous "
                    "session stopped commanding it, so it stopped); cleared", self._servo(servo_id)
                )
        state = self._read(now_ns)  # also raises MotorFault on an alert bit
        n = self._n
        held_positions = np.full(n, np.nan)
        held_velocities = np.full(n, np.nan)
        held_effort = np.full(n, np.nan)
        for servo_id in self.ids:
            if self._read_register(servo_id, "operating_mode") != int(self.mode):
                # deactivate(HOLD) may have left a current-mode servo holding in position mode.
                self._write_register(servo_id, "torque_enable", 0)
                self._write_register(servo_id, "operating_mode", int(self.mode))
        goals: dict[int, int]
        if self._interface == "position":
            ticks = self._present_ticks
            goals = {servo_id: int(ticks[i]) for i, servo_id in enumerate(self.ids)}
            # The held command is exactly where the servo is (whole ticks): no jump.
            held_positions = state.positions.copy()
        elif self._interface == "velocity":
            goals = dict.fromkeys(self.ids, 0)
            held_velocities = np.zeros(n)
        else:
            goals = dict.fromkeys(self.ids, 0)
            held_effort = np.zeros(n)
        self._sync_write_goal(self._goal_name, goals)
        try:
            for servo_id in self.ids:
                self._write_register(servo_id, "torque_enable", 1)
            # Armed in every operating mode once the torque is on: from now on, a daemon that
            # stops commanding (killed, hung) leaves servos that stop by themselves.
            for servo_id in self.ids:
                self._write_register(servo_id, "bus_watchdog", self._watchdog_units)
            self._verify_enabled(goals)
            self._require_bus().take_silence_s()  # silences before now were not armed ones
            self._armed = True
        except HardwareError as exc:
            # Leave nothing enabled half way: the safe action, and the watchdogs disarmed.
            try:
                self._deactivate(now_ns, self.safe_action)
            except HardwareError as rollback:
                add_note(exc, f"undoing the activation failed too: {rollback}")
            raise
        return JointCommand(
            held_positions if self._interface == "position" else None,
            held_velocities if self._interface == "velocity" else None,
            None,
            held_effort if self._interface == "effort" else None,
        )

    def _verify_enabled(self, goals: Mapping[int, int]) -> None:
        """Prove that every servo is enabled and obeys, from what it reports (one Sync Read of
        Torque Enable .. Present Position): no hardware error, Torque Enable 1, Bus Watchdog
        armed with our value, and its goal the one just written (position modes: where the
        servo is), not one it refused. A truthful activation, so that a rearm that reports
        holding is holding.

        Raises:
            MotorFault: a servo reports a hardware error (latched: a rearm reboots it).
            HardwareError: one line naming the servo and what to check.
            CommunicationError: a servo did not answer.
        """
        bus = self._require_bus()
        start, end = _ENABLED_BLOCK
        try:
            result = bus.sync_read(self.ids, start, end - start)
        except ServoCommunicationError as exc:
            raise self._comm_error(exc, "reading back the enabled state") from exc
        for i, servo_id in enumerate(self.ids):
            block = result.data[servo_id]
            model = self.models[i]

            def value(name: str, block: bytes = block, model: Model = model) -> int:
                reg = model.register(name)
                return reg.decode(block[reg.address - start : reg.end - start])

            flags = value("hardware_error_status")
            if flags:
                raise self._motor_fault(servo_id, flags)
            who = self._servo(servo_id)
            torque = value("torque_enable")
            if torque != 1:
                raise HardwareError(
                    f"{who}: Torque Enable reads {torque} right after it was switched on; "
                    "check the servo's supply voltage and cable, and that no other program "
                    "uses the bus"
                )
            armed = value("bus_watchdog")
            if armed != self._watchdog_units:
                raise HardwareError(
                    f"{who}: Bus Watchdog reads {armed}, not the {self._watchdog_units} "
                    f"({self.watchdog_timeout_s * 1000:.0f} ms) just armed; check that no other "
                    "program uses the bus"
                )
            goal = value(self._goal_name)
            label = self._goal_name.replace("_", " ").title()
            if self.mode in _POSITION_FAMILY:
                present = value("present_position")
                if abs(goal - present) > _GOAL_SEED_TOLERANCE_TICKS:
                    raise HardwareError(
                        f"{who}: {label} reads {goal} but the servo is at {present} ticks: it "
                        "refused the goal just written and would move; check that no other "
                        "program uses the bus"
                    )
            elif goal != goals[servo_id]:
                raise HardwareError(
                    f"{who}: {label} reads {goal}, not the {goals[servo_id]} just written: it "
                    "refused the goal; check that no other program uses the bus"
                )

    def _watchdog_values(self) -> dict[int, int]:
        """Every servo's Bus Watchdog register (one Sync Read of one byte; -1: tripped).

        Raises:
            CommunicationError: a servo did not answer.
        """
        bus = self._require_bus()
        try:
            result = bus.sync_read(self.ids, _BUS_WATCHDOG, 1)
        except ServoCommunicationError as exc:
            raise self._comm_error(exc, "reading the Bus Watchdog") from exc
        return {i: int.from_bytes(result.data[i], "little", signed=True) for i in self.ids}

    def _check_watchdogs(self) -> None:
        """Raise the watchdog fault of the first tripped servo, if any.

        Raises:
            MotorFault: a servo's Bus Watchdog expired.
            CommunicationError: a servo did not answer.
        """
        for servo_id, value in self._watchdog_values().items():
            if value < 0:
                raise self._watchdog_fault(servo_id)

    def _clear_trip(self, i: int) -> None:
        """Clear servo ``i``'s tripped Bus Watchdog (write 0), then at once give it a goal that
        keeps it where it is: the e-Manual does not say whether a cleared servo resumes the
        goal it held before the trip (a velocity, say), so it is never left with that one.

        Raises:
            HardwareError: a write was refused; CommunicationError: no answer.
        """
        servo_id = self.ids[i]
        mode = self._read_register(servo_id, "operating_mode")
        present = self._read_register(servo_id, "present_position")
        if mode == OperatingMode.POSITION:
            low = self._read_register(servo_id, "min_position_limit")
            high = self._read_register(servo_id, "max_position_limit")
            present = min(max(present, low), high)
        self._write_register(servo_id, "bus_watchdog", 0)
        if mode in _POSITION_FAMILY:
            self._write_register(servo_id, "goal_position", present)
        elif mode == OperatingMode.VELOCITY:
            self._write_register(servo_id, "goal_velocity", 0)
        elif mode == OperatingMode.CURRENT and self.models[i].has_register("goal_current"):
            self._write_register(servo_id, "goal_current", 0)
        elif mode == OperatingMode.PWM:
            self._write_register(servo_id, "goal_pwm", 0)
        self._tripped.discard(servo_id)
        self._leftover_trips.discard(servo_id)
        self._last_fault_by_servo.pop(servo_id, None)

    def _sync_read_present(self) -> SyncReadResult:
        bus = self._require_bus()
        return self._retried("reading the present state", bus.sync_read, self.ids,
                             PRESENT_BLOCK_ADDRESS, PRESENT_BLOCK_SIZE,
                             fast=self.params["fast_sync_read"])

    def _retried(self, what: str, read: Callable[..., _T], *args: Any, **kwargs: Any) -> _T:
        """``read(*args, **kwargs)`` retried up to ``max_retries`` times after a missed or
        corrupt reply, each retry counted; the last attempt's error names the servo and
        ``what``."""
        retries = self.params["max_retries"]
        for _ in range(retries):
            try:
                return read(*args, **kwargs)
            except ServoCommunicationError:
                self._retries += 1
        try:
            return read(*args, **kwargs)
        except ServoCommunicationError as exc:
            raise self._comm_error(exc, what, retries + 1) from exc

    def _check_silence(self) -> None:
        """Before a cycle's transaction: after a bus silence longer than half the watchdog time
        since the previous call (a stalled loop, wherever in its cycle it stalled), check
        whether the servos stopped on their watchdog; the Sync Writes they then refuse would
        otherwise go unnoticed.

        Raises:
            MotorFault: a servo's Bus Watchdog expired.
            CommunicationError: a servo did not answer.
        """
        if self._armed and self._require_bus().take_silence_s() > 0.5 * self.watchdog_timeout_s:
            self._check_watchdogs()

    def _read(self, now_ns: int) -> JointState:
        self._check_silence()
        result = self._sync_read_present()
        for servo_id, error in result.errors.items():
            if error & ERROR_ALERT:
                flags = self._read_register(servo_id, "hardware_error_status")
                raise self._motor_fault(servo_id, flags or 0)
        return self._state_from(result)

    def _state_from(self, result: SyncReadResult) -> JointState:
        """The joints' state from a Sync Read of the present block (every servo answered)."""
        data = result.data
        raw = np.frombuffer(b"".join([data[i] for i in self.ids]), dtype=_PRESENT_DTYPE)
        # Only now, with every servo's data good, does the state change.
        ticks = raw["position"]
        units = self.units
        positions: F64 = ticks * units.pos_scale + units.offset
        self._present_ticks = ticks
        self._positions = positions
        self._velocities = raw["velocity"] * units.vel_scale
        self._efforts = raw["current"] * units.effort_scale
        # Effort is no state interface of the JTC: it is reported in status() details only.
        velocities = self._velocities.copy() if self._velocity_state else None
        return JointState(positions.copy(), velocities)

    def _write(self, now_ns: int, command: JointCommand) -> None:
        values = getattr(command, self._command_field)
        if values is None:
            return
        # NaN stays NaN through the clamps (np.maximum / np.minimum propagate it).
        raw = np.minimum(
            np.maximum((values - self._goal_offset) * self._goal_inverse, self._cmd_lo),
            self._cmd_hi,
        )
        counts = np.rint(raw)
        missing = np.isnan(counts)
        if missing.any():
            keep = ~missing
            ids = [i for i, k in zip(self.ids, keep.tolist(), strict=True) if k]
            goals = dict(zip(ids, counts[keep].astype(np.int64).tolist(), strict=True))
        else:
            goals = dict(zip(self.ids, counts.astype(np.int64).tolist(), strict=True))
        if goals:
            self._check_silence()
            self._sync_write_goal(self._goal_name, goals)
        self._read_health(now_ns)

    def _monitor(self, now_ns: int) -> JointState | None:
        """While faulted (INACTIVE): the health block due, then the present state, as a cycle
        reads them; alert bits are reported by the health block's hardware error status, not
        raised. Nothing at all while a servo's Bus Watchdog may still be armed
        (``_left_armed``): every instruction packet on the bus would feed it, keeping that
        servo on its last goal instead of stopping by itself.

        Raises:
            CommunicationError: a servo did not answer the present state's Sync Read.
        """
        if self._bus is None or self._left_armed:
            return None
        self._read_health(now_ns)
        return self._state_from(self._sync_read_present())

    def _read_health(self, now_ns: int) -> None:
        """Every health slot, one Sync Read of the next health block of every servo (after the
        cycle's write; see :mod:`.health`)."""
        block = self._servo_health.due(now_ns)
        if block is not None:
            self._servo_health.read(self._require_bus(), block)

    def _sync_write_goal(self, name: str, values: Mapping[int, int]) -> None:
        bus = self._require_bus()
        reg = self.models[0].register(name)
        try:
            bus.sync_write(reg.address, reg.size, values)
        except ServoCommunicationError as exc:
            raise self._comm_error(exc, f"writing {name}") from exc

    def _deactivate(self, now_ns: int, action: SafeAction) -> None:
        errors: list[Exception] = []
        # Which servos have tripped: they stopped by themselves and refuse goals, so the hold
        # leaves them alone, and they stay tripped (a rearm clears them, see _clear_trip).
        values: dict[int, int] | None
        try:
            values = self._watchdog_values()
        except HardwareError as exc:
            values = None  # the writes below report the broken bus
            _log.warning("%s: %s; the Bus Watchdogs stay armed (a servo not commanded stops "
                         "by itself)", self._owner(), exc)
        tripped = ({i for i, value in values.items() if value < 0} if values is not None
                   else set(self._tripped))
        if self._armed:
            self._tripped |= tripped
        skip = tripped | set(self._latched)
        if action is SafeAction.TORQUE_OFF:
            for servo_id in self.ids:
                try:
                    self._write_register(servo_id, "torque_enable", 0)
                except HardwareError as exc:
                    errors.append(exc)
        elif self._interface == "velocity":
            try:
                self._sync_write_goal("goal_velocity", {
                    servo_id: 0 for servo_id in self.ids if servo_id not in skip})
            except HardwareError as exc:
                errors.append(exc)
        elif self._interface == "effort":
            # Zero current would let the joints fall: hold in position mode until the next
            # activation switches back (a few ms with the torque off).
            for servo_id in self.ids:
                try:
                    if servo_id in skip:
                        continue
                    present = self._read_register(servo_id, "present_position")
                    self._write_register(servo_id, "torque_enable", 0)
                    self._write_register(servo_id, "operating_mode", int(OperatingMode.POSITION))
                    lo = self._read_register(servo_id, "min_position_limit")
                    hi = self._read_register(servo_id, "max_position_limit")
                    self._write_register(servo_id, "goal_position", min(max(present, lo), hi))
                    self._write_register(servo_id, "torque_enable", 1)
                except HardwareError as exc:
                    errors.append(exc)
        elif self._positions is not None:
            # Position mode already holds its last goal; pin it to where the joint is.
            try:
                ticks = self._present_ticks
                self._sync_write_goal("goal_position", {
                    servo_id: int(np.clip(ticks[i], self._cmd_lo[i], self._cmd_hi[i]))
                    for i, servo_id in enumerate(self.ids) if servo_id not in skip
                })
            except HardwareError as exc:
                errors.append(exc)
        # Disarmed after the safe action, not before: had the safe action failed or the
        # process died in between, a servo still armed stops by itself, while one disarmed
        # first would keep its last (moving) command. A tripped servo is not cleared here:
        # clearing is the rearm's, together with a goal that keeps it still. Unread states
        # (a broken bus) are not guessed at: disarming might clear a trip; left armed, a servo
        # still holding stops and holds by itself, which is the same.
        left_armed: set[int] = set()
        for servo_id in self.ids:
            if servo_id in tripped:
                continue
            if values is None:
                left_armed.add(servo_id)
                continue
            try:
                self._write_register(servo_id, "bus_watchdog", 0)
            except HardwareError as exc:
                errors.append(exc)
                left_armed.add(servo_id)
        self._left_armed = left_armed
        self._armed = False
        if errors:
            first = errors[0]
            for other in errors[1:]:
                add_note(first, f"also: {other}")
            raise first

    def _recover(self) -> None:
        bus = self._require_bus()
        deadline_s = self.params["reboot_timeout_s"]
        for i, servo_id in enumerate(self.ids):
            flags = self._latched.get(servo_id)
            if not flags:
                continue
            try:
                bus.reboot(servo_id)
            except ServoCommunicationError as exc:
                raise self._comm_error(exc, "reboot") from exc
            self._wait_for(servo_id, deadline_s)
            remaining = self._read_register(servo_id, "hardware_error_status")
            if remaining:
                raise self._motor_fault(servo_id, remaining)
            del self._latched[servo_id]
            self._last_fault_by_servo.pop(servo_id, None)
            self._setup_servo(i)  # the reboot reset the RAM area, Bus Watchdog included
            _log.info("%s: rebooted, hardware error %s cleared", self._servo(servo_id),
                      hardware_error_text(flags))
        # Tripped watchdogs: cleared (with a goal that keeps the servo still) so that goals are
        # accepted again; activate() then arms them anew.
        values = self._watchdog_values()
        for i, servo_id in enumerate(self.ids):
            if values[servo_id] < 0:
                self._clear_trip(i)
                _log.info("%s: bus watchdog error cleared", self._servo(servo_id))
        self._tripped.clear()
        self._leftover_trips.clear()

    def _wait_for(self, servo_id: int, timeout_s: float) -> None:
        """Ping until the rebooted servo answers, at most ``timeout_s`` (each ping is itself
        bounded by the bus timeout, so this never spins)."""
        bus = self._require_bus()
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                bus.ping(servo_id)
                return
            except ServoCommunicationError as exc:
                if time.monotonic() >= deadline:
                    raise CommunicationError(
                        f"{self._servo(servo_id)}: did not answer within {timeout_s:g} s after "
                        f"its reboot ({exc.cause}); check its power and cable"
                    ) from exc

    def _cleanup(self) -> None:
        if self._bus is not None:
            self._bus.close()
            self._bus = None

    def _details(self) -> Mapping[str, Any]:
        bus = self._bus
        return {
            "port": self.params["port"],
            "baud_rate": self.params["baud_rate"],
            "operating_mode": self.mode.name.lower(),
            "bus": bus.stats.as_dict() if bus is not None else None,
            "latency_timer_ms": bus.latency_timer if bus is not None else None,
            "retries": self._retries,
            "watchdog_ms": round(self.watchdog_timeout_s * 1000),
            "watchdog_armed": self._armed,
            "servos": {
                str(servo_id): {
                    "joint": joint,
                    "model": model.name,
                    "hardware_error": (hardware_error_text(self._latched[servo_id])
                                       if servo_id in self._latched else None),
                    "last_fault": self._last_fault_by_servo.get(servo_id),
                    "watchdog_expired": (servo_id in self._tripped
                                         or servo_id in self._leftover_trips),
                    "effort": (float(self._efforts[i]) if self._positions is not None
                               and model.current_unit_a else None),
                }
                for i, (servo_id, joint, model) in enumerate(
                    zip(self.ids, self.joints, self.models, strict=True))
            },
        }

    def _health(self) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
        """The servos' health as last read (stale blocks unknown: see :mod:`.health`)."""
        motors = self._servo_health.report(
            self.mode.name.lower(), self._latched, self._tripped | self._leftover_trips,
            self._last_fault_by_servo)
        stats = self._bus.stats if self._bus is not None else None
        bus = None if stats is None else {
            "transactions": stats.transactions,
            "timeouts": stats.timeouts,
            "crc_errors": stats.corrupt,
            "retries": self._retries,
            "health_read_errors": self._servo_health.read_errors,
        }
        return motors, bus

    # -- test / tool accessors ------------------------------------------------------------------

    @property
    def last_positions(self) -> F64 | None:
        """The joint positions of the last good read (``None`` before the first)."""
        return None if self._positions is None else self._positions.copy()

    @property
    def last_efforts(self) -> F64:
        """The joint efforts of the last good read, N*m (present current * torque constant *
        gear ratio)."""
        efforts: F64 = self._efforts.copy()
        return efforts

    @property
    def bus(self) -> DynamixelBus | None:
        """The bus while configured (``None`` otherwise)."""
        return self._bus
