"""Feetech STS/SMS and SCS serial servos on one bus (hardware kind ``feetech``).

Theory of operation
-------------------
One :class:`FeetechHardware` owns one serial bus (:class:`~jtc_hw.drivers.feetech.bus.
FeetechBus`, the only module that imports the SDK) and one servo per joint, all of one series
(LeRobot's SO-100/SO-101: six STS3215 at 1 Mbit/s). Each cycle costs one transaction per
direction (SCS: one read per servo, it has no Sync Read):

* ``read``: one group read of Present Position / Speed / Load (56..61, 6 bytes per servo),
  decoded for all servos at once; every reply also carries the servo's Status bits;
* ``write``: one Sync Write of Goal Position (42), in steps.

**Position control only**, the servo's own position loop (Operating Mode 0). jtc_hw's
interpolation is in charge of the motion: at configure Acceleration (41) is set to 0 (no ramp)
and Goal Speed (46) to 0 (the servo's maximum), so the servo follows each cycle's goal as fast
as it can. Multi-turn and step mode are out of scope.

**Units.** joint = direction * steps * 2 pi / steps_per_rev / gear_ratio + offset (4096 steps a
turn on STS; the SCS0009's 1024 over 300 degrees), the same factors both ways
(:class:`~jtc_hw.drivers.feetech.codec.JointScale`). Present Load (0.1 % of full load,
sign-magnitude) is reported per servo as ``load`` in ``details`` and :attr:`last_loads`: the
controller's state interfaces are position, velocity and acceleration, so effort is no state
interface here (as for Dynamixel). Commands are clamped to ``position_limits`` and to the
servo's own Min/Max Position Limit (read at configure) before they are sent: a Sync Write has
no reply.

**Nothing is stored in EEPROM.** What configure sets in the EEPROM area (Return Delay Time,
Operating Mode) is written with the EPROM lock closed (the lock, 55 on STS/SMS, 48 on SCS, is
closed first if it reads open): it takes effect at once and is forgotten at the next power
cycle, so the servo keeps its own stored settings (LeRobot's calibration among them).

**No bus watchdog.** These servos have none: a servo keeps its last Goal Position, torque on,
for as long as it has power. If the daemon dies, the arm holds where it was last commanded
(usually where it was, the commands being the interpolated trajectory); nothing on the bus can
make it limp or stop it otherwise. What this driver does on a clean stop or a fault is the
``safe_action``: ``hold`` (default) writes the present position as the goal, read fresh (a servo
whose read fails keeps its last goal, the last command); ``torque_off`` switches every servo's
torque off (the arm falls under gravity). ``jtc-hw check`` says so (:meth:`device_watchdog`).

**Faults.** A failed read (the cycle's group read, a register read, a ping) is retried up to
``max_retries`` times at once (a read, so a retry repeats nothing); then a
:class:`~jtc_hw.errors.CommunicationError` names the servo (id and joint) and the cause (no
reply, checksum error). A reply whose Status bits say overload, overheat, overcurrent or an
angle sensor fault raises :class:`~jtc_hw.errors.MotorFault` naming the servo and the cause
(the servo's protection has switched its torque off, or its position cannot be trusted); the
voltage bit is a health warning only (the servo keeps driving). A failed read never changes
the last known positions and returns nothing: no stale position becomes a command. The loop
then aborts the goal and applies the ``safe_action``. ``recover`` (``jtc-hw rearm``) checks that
every servo answers and that no protection persists (an overheated servo must cool first);
``activate`` then seeds the goal from the measured position and switches the torque on, which
clears a latched overload, and reads back that every servo is enabled, so re-arming never jumps.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar, Final, TypeVar

import numpy as np
from numpy.typing import NDArray

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

from .bus import FeetechBus, GroupReadResult, ServoCommunicationError
from .codec import StatusError, decode_value, encode_value, status_error_text
from .control_table import Model, SeriesName, UnknownModelError, model_by_name, model_by_number
from .health import ServoHealth
from .params import PARAMS

__all__ = ["FAULT_BITS", "FeetechHardware"]

_log = logging.getLogger(__name__)
_T = TypeVar("_T")
F64 = NDArray[np.float64]

#: Status bits that end a goal: the servo's protection unloads it (overheat, overcurrent,
#: overload: the factory Unloading Condition) or its position cannot be trusted (angle sensor).
FAULT_BITS: Final = (StatusError.OVERHEAT | StatusError.OVERCURRENT | StatusError.OVERLOAD
                     | StatusError.ANGLE)
#: Bits that persist until their cause is gone (a rearm cannot clear them); an overload is
#: latched by the servo until its torque is switched on again.
_PERSISTENT_BITS: Final = StatusError.OVERHEAT | StatusError.ANGLE
_PRESENT_ADDRESS: Final = 56  # Present Position, Speed, Load: 56..61
_PRESENT_SIZE: Final = 6
#: Sign bits of Present Position / Speed / Load per series (``None``: unsigned). SCS: the
#: direction bits of Feetech's SCSCL library (``ReadSpeed``, ``ReadLoad``); its positions have none.
_PRESENT_SIGNS: Final = {SeriesName.STS_SMS: (15, 15, 10), SeriesName.SCS: (None, 15, 10)}
#: After activation a servo's goal must be this close to where it stands, steps.
_GOAL_SEED_TOLERANCE_STEPS: Final = 20


def _sign_magnitude(raw: NDArray[Any], bit: int | None) -> NDArray[np.int64]:
    values = raw.astype(np.int64)
    if bit is None:
        return values
    magnitude = values & ((1 << bit) - 1)
    result: NDArray[np.int64] = np.where((values >> bit) & 1, -magnitude, magnitude)
    return result


class FeetechHardware(HardwareInterface):
    """Feetech servos, one per joint, on one serial bus (see the module docstring).

    Raises:
        ConfigurationError: invalid parameters (see :attr:`PARAMS`): duplicate ids, an unknown
            model, models of two series on one bus, or position limits outside the servo's
            range.
    """

    kind: ClassVar[str] = "feetech"
    COMMAND_INTERFACES: ClassVar[tuple[str, ...]] = ("position",)
    STATE_INTERFACES: ClassVar[tuple[str, ...]] = ("position", "velocity")
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
        self.ids: tuple[int, ...] = tuple(p["ids"])
        seen: dict[int, str] = {}
        for joint, servo_id in zip(self.joints, self.ids, strict=True):
            if servo_id in seen:
                raise ConfigurationError(
                    f"servo id {servo_id} is given to both {seen[servo_id]!r} and {joint!r}; "
                    "each joint needs its own servo", "params.ids", servo_id)
            seen[servo_id] = joint
        models: list[Model] = []
        for joint, model_name in zip(self.joints, p["model"], strict=True):
            try:
                models.append(model_by_name(model_name))
            except UnknownModelError as exc:
                raise ConfigurationError(f"joint {joint!r}: {exc}", "params.model",
                                         model_name) from None
        self.models: tuple[Model, ...] = tuple(models)
        self.series = models[0].series
        if any(m.series is not self.series for m in models):
            raise ConfigurationError(
                f"{self._owner()}: STS/SMS and SCS servos speak with different byte orders and "
                "cannot share one bus here; give each series its own hardware component",
                "params.model", p["model"])
        d = np.array(p["direction"], dtype=np.float64)
        g = np.array(p["gear_ratio"], dtype=np.float64)
        rad_per_step = np.array([m.rad_per_step for m in models])
        self._offset: F64 = np.array(p["offset"], dtype=np.float64)
        self._pos_scale: F64 = d * rad_per_step / g
        self._pos_inverse: F64 = d * g / rad_per_step
        self._vel_scale: F64 = d * np.array([m.speed_unit_rad_s for m in models]) / g
        self._direction = d
        # Step limits from the joint limits (inf where not given), checked against the range.
        limits = p["position_limits"]
        lower = np.array([lim[0] for lim in limits], dtype=np.float64)
        upper = np.array([lim[1] for lim in limits], dtype=np.float64)
        with np.errstate(invalid="ignore"):
            a = (lower - self._offset) * self._pos_inverse
            b = (upper - self._offset) * self._pos_inverse
        self._limit_lo = np.where(np.isnan(a), -np.inf, np.minimum(a, b))
        self._limit_hi = np.where(np.isnan(b), np.inf, np.maximum(a, b))
        for i, joint in enumerate(self.joints):
            lo, hi, top = self._limit_lo[i], self._limit_hi[i], models[i].position_max
            if (np.isfinite(lo) and lo < -0.5) or (np.isfinite(hi) and hi > top + 0.5):
                raise ConfigurationError(
                    f"joint {joint!r}: position_limits [{lower[i]:g}, {upper[i]:g}] rad map to "
                    f"servo steps [{lo:.0f}, {hi:.0f}], outside the servo's 0..{top}; adjust "
                    f"offset (step {(top + 1) // 2} is the middle) or direction",
                    "params.position_limits", limits[i])
        self._n = n
        self._bus: FeetechBus | None = None
        self._cmd_lo = np.zeros(n)
        self._cmd_hi = np.array([float(m.position_max) for m in models])
        self._positions: F64 | None = None  # last good read, joint units
        self._steps: NDArray[np.int64] = np.zeros(n, dtype=np.int64)
        self._velocities: F64 = np.zeros(n)
        self._loads: F64 = np.zeros(n)
        self._torque: dict[int, bool | None] = dict.fromkeys(self.ids)
        self._latched: dict[int, int] = {}  # servo id -> fault bits seen
        self._last_fault_by_servo: dict[int, str] = {}
        self._retries = 0
        self._servo_health = ServoHealth(self.ids, self.joints, self.models, p["health_period_s"])
        self._joint_of = dict(zip(self.ids, self.joints, strict=True))
        order = ">" if self.series.byte_order else "<"
        self._present_dtype = np.dtype([("position", f"{order}u2"), ("velocity", f"{order}u2"),
                                        ("load", f"{order}u2")])
        self._signs = _PRESENT_SIGNS[self.series.name]
        self._goal_reg = self.series.register("goal_position")

    # -- labels ---------------------------------------------------------------------------------

    def _servo(self, servo_id: int | None) -> str:
        if servo_id is None:
            return f"{self._owner()} (bus {self.params['port']})"
        return f"{self._owner()}: servo {servo_id} (joint {self._joint_of.get(servo_id, '?')!r})"

    def _require_bus(self) -> FeetechBus:
        if self._bus is None or not self._bus.is_open:
            raise CommunicationError(f"{self._owner()}: the bus is not open")
        return self._bus

    def _comm_error(self, exc: ServoCommunicationError, what: str,
                    attempts: int = 1) -> CommunicationError:
        tries = f" after {attempts} attempts" if attempts > 1 else ""
        if exc.servo_id is not None:
            self._last_fault_by_servo[exc.servo_id] = exc.cause
        return CommunicationError(
            f"{self._servo(exc.servo_id)}: {what} failed{tries}: {exc.cause}; check the "
            f"servo's power and cable, its id and baud rate ({self.params['baud_rate']} bit/s)")

    def _motor_fault(self, servo_id: int, bits: int) -> MotorFault:
        cause = status_error_text(bits & FAULT_BITS)
        self._latched[servo_id] = bits & FAULT_BITS
        self._last_fault_by_servo[servo_id] = cause
        return MotorFault(
            f"{self._servo(servo_id)}: {cause} (the servo's protection switches its torque off, "
            "or its position cannot be trusted); remove the cause (load, temperature, supply), "
            "then re-arm (jtc-hw rearm)")

    # -- the hardware contract's descriptions ---------------------------------------------------

    def device_watchdog(self) -> DeviceWatchdog:
        """None: Feetech servos have no bus watchdog (see the module docstring)."""
        return DeviceWatchdog(
            None,
            "Feetech servos have no bus watchdog: if the daemon dies they hold their last goal "
            "position, torque on, until their power is cut (safe_action applies only to a "
            "stop the daemon performs)")

    def devices(self) -> tuple[DeviceName, ...]:
        """The serial port, resolved: the bus is half duplex with one master, so a second
        daemon's packets would collide with this one's whatever ids they name."""
        port = self.params["port"]
        real = os.path.realpath(port)
        return (DeviceName(real, real if real == port else f"{port} ({real})"),)

    # -- lifecycle primitives -------------------------------------------------------------------

    def _configure(self) -> None:
        p = self.params
        # Until configure sets it, a servo answers after its own Return Delay Time (factory
        # 500 us), which timeout_ms covers for the single-servo reads made before.
        bus = FeetechBus(p["port"], p["baud_rate"], self.series, timeout_ms=p["timeout_ms"],
                         return_delay_us=p["return_delay_time_us"])
        bus.open()
        self._bus = bus
        try:
            for i, servo_id in enumerate(self.ids):
                self._check_model(i, servo_id)
            for i, servo_id in enumerate(self.ids):
                self._setup_servo(i, servo_id)
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
            raise ConfigurationError(
                f"{self._servo(servo_id)} is {found.name if found else 'an unknown model'} "
                f"(model number {number}) but the configuration says {expected.name} (model "
                f"number {expected.model_number}); fix params.model or the servo's id",
                "params.model", expected.name)
        major = self._read_register(servo_id, "firmware_major")
        minor = self._read_register(servo_id, "firmware_minor")
        self._servo_health.firmware[servo_id] = f"{major}.{minor}"

    def _read_register(self, servo_id: int, name: str) -> int:
        bus = self._require_bus()
        reg = self.series.register(name)
        raw = self._retried(f"reading {name}", bus.read_bytes, servo_id, reg.address, reg.size)
        return decode_value(reg, raw, self.series.byte_order)

    def _write_register(self, servo_id: int, name: str, value: int) -> int:
        bus = self._require_bus()
        reg = self.series.register(name)
        data = encode_value(reg, int(value), self.series.byte_order)
        try:
            return bus.write_bytes(servo_id, reg.address, data)
        except ServoCommunicationError as exc:
            raise self._comm_error(exc, f"writing {name} = {value}") from exc

    def _setup_servo(self, i: int, servo_id: int) -> None:
        """Return delay and operating mode (EEPROM, written with the lock closed so that
        nothing is stored), the profile at the servo's maximum (RAM), the command clamps."""
        eeprom = {"return_delay_time": self.params["return_delay_time_us"] // 2}
        if "operating_mode" in self.series.registers:
            eeprom["operating_mode"] = 0  # position servo mode
        changes = {name: value for name, value in eeprom.items()
                   if self._read_register(servo_id, name) != value}
        if changes:
            if self._read_register(servo_id, self.series.lock_register) == 0:
                self._write_register(servo_id, self.series.lock_register, 1)
            if "operating_mode" in changes and self._read_register(servo_id, "torque_enable"):
                self._write_register(servo_id, "torque_enable", 0)
            for name, value in changes.items():
                self._write_register(servo_id, name, value)
        for name in ("acceleration", "goal_velocity"):  # 0: no ramp, the servo's top speed
            if self._read_register(servo_id, name) != 0:
                self._write_register(servo_id, name, 0)
        low = self._read_register(servo_id, "min_position_limit")
        high = self._read_register(servo_id, "max_position_limit")
        top = self.models[i].position_max
        if not high > low:
            low, high = 0, top
        self._cmd_lo[i] = max(low, self._limit_lo[i], 0)
        self._cmd_hi[i] = min(high, self._limit_hi[i], top)

    def _activate(self, now_ns: int) -> JointCommand:
        for servo_id, bits in self._latched.items():
            raise self._motor_fault(servo_id, bits)  # only a rearm clears it
        # Held exactly where each servo stands (whole steps), not clamped into the limits: a
        # joint found outside them is moved back by a goal, never by the activation.
        state = self._state_from(self._read_present(allow=StatusError.OVERLOAD))
        goals = {servo_id: int(self._steps[i]) for i, servo_id in enumerate(self.ids)}
        self._sync_write_goal(goals)
        try:
            for servo_id in self.ids:
                self._write_register(servo_id, "torque_enable", 1)
                self._torque[servo_id] = True
            self._verify_enabled(goals)
        except HardwareError as exc:
            try:
                self._deactivate(now_ns, self.safe_action)
            except HardwareError as rollback:
                add_note(exc, f"undoing the activation failed too: {rollback}")
            raise
        return JointCommand(state.positions.copy(), None, None, None)

    def _verify_enabled(self, goals: Mapping[int, int]) -> None:
        """Prove that every servo is enabled and holds where it stands, from what it reports:
        Torque Enable 1, its goal the one just written, no fault in its Status.

        Raises:
            MotorFault: a servo reports a fault (its protection keeps the torque off).
            HardwareError: one line naming the servo and what to check.
            CommunicationError: a servo did not answer.
        """
        for servo_id in self.ids:
            torque = self._read_register(servo_id, "torque_enable")
            status = self._read_register(servo_id, "status")
            if status & FAULT_BITS:
                raise self._motor_fault(servo_id, status)
            if torque != 1:
                raise HardwareError(
                    f"{self._servo(servo_id)}: Torque Enable reads {torque} right after it was "
                    "switched on; check the servo's supply voltage and cable, and that no other "
                    "program uses the bus")
            goal = self._read_register(servo_id, "goal_position")
            if abs(goal - goals[servo_id]) > _GOAL_SEED_TOLERANCE_STEPS:
                raise HardwareError(
                    f"{self._servo(servo_id)}: Goal Position reads {goal}, not the "
                    f"{goals[servo_id]} just written; check that no other program uses the bus")

    def _retried(self, what: str, read: Callable[..., _T], *args: Any) -> _T:
        """``read(*args)`` retried up to ``max_retries`` times after a missed or corrupt reply,
        each retry counted; the last attempt's error names the servo and ``what``."""
        retries = self.params["max_retries"]
        for _ in range(retries):
            try:
                return read(*args)
            except ServoCommunicationError:
                self._retries += 1
        try:
            return read(*args)
        except ServoCommunicationError as exc:
            raise self._comm_error(exc, what, retries + 1) from exc

    def _read_present(self, allow: int = 0) -> GroupReadResult:
        """The cycle's group read (retried); a reply with a fault bit not in ``allow`` raises.

        Raises:
            CommunicationError: a servo did not answer (after the retries).
            MotorFault: a servo reports overload, overheat, overcurrent or an angle fault.
        """
        bus = self._require_bus()
        result = self._retried("reading the present state", bus.group_read, self.ids,
                               _PRESENT_ADDRESS, _PRESENT_SIZE)
        for servo_id, bits in result.errors.items():
            if bits & FAULT_BITS & ~allow:
                raise self._motor_fault(servo_id, bits)
        return result

    def _read(self, now_ns: int) -> JointState:
        return self._state_from(self._read_present())

    def _state_from(self, result: GroupReadResult) -> JointState:
        """The joints' state from a group read in which every servo answered."""
        data = result.data
        raw = np.frombuffer(b"".join([data[i] for i in self.ids]), dtype=self._present_dtype)
        pos_bit, vel_bit, load_bit = self._signs
        # Only now, with every servo's data good, does the state change.
        steps = _sign_magnitude(raw["position"], pos_bit)
        positions: F64 = steps * self._pos_scale + self._offset
        self._steps = steps
        self._positions = positions
        self._velocities = _sign_magnitude(raw["velocity"], vel_bit) * self._vel_scale
        self._loads = _sign_magnitude(raw["load"], load_bit) * self._direction / 1000.0
        velocities = self._velocities.copy() if self._velocity_state else None
        return JointState(positions.copy(), velocities)

    def _write(self, now_ns: int, command: JointCommand) -> None:
        values = command.positions
        if values is None:
            return
        raw = np.minimum(np.maximum((values - self._offset) * self._pos_inverse, self._cmd_lo),
                         self._cmd_hi)  # NaN stays NaN
        counts = np.rint(raw)
        keep = ~np.isnan(counts)
        goals = {servo_id: int(c) for servo_id, c, k in
                 zip(self.ids, counts.tolist(), keep.tolist(), strict=True) if k}
        if goals:
            self._sync_write_goal(goals)
        if self._servo_health.due(now_ns):
            self._servo_health.read(self._require_bus())

    def _sync_write_goal(self, goals: Mapping[int, int]) -> None:
        bus = self._require_bus()
        reg, order = self._goal_reg, self.series.byte_order
        try:
            bus.sync_write(reg.address, {i: encode_value(reg, v, order) for i, v in goals.items()})
        except ServoCommunicationError as exc:
            raise self._comm_error(exc, "writing goal_position") from exc

    def _monitor(self, now_ns: int) -> JointState | None:
        """While faulted (INACTIVE): the health block when due, then the present state (no
        watchdog to feed: reading commands nothing). Fault bits are reported, not raised.

        Raises:
            CommunicationError: a servo did not answer the present state's read.
        """
        if self._bus is None:
            return None
        if self._servo_health.due(now_ns):
            self._servo_health.read(self._require_bus())
        return self._state_from(self._read_present(allow=FAULT_BITS))

    def _deactivate(self, now_ns: int, action: SafeAction) -> None:
        if action is SafeAction.TORQUE_OFF:
            errors: list[HardwareError] = []
            for servo_id in self.ids:
                try:
                    self._write_register(servo_id, "torque_enable", 0)
                    self._torque[servo_id] = False
                except HardwareError as exc:
                    errors.append(exc)
            if errors:
                for other in errors[1:]:
                    add_note(errors[0], f"also: {other}")
                raise errors[0]
            return
        self._hold()

    def _hold(self) -> None:
        """Goal Position := the present position, read fresh: one group read, else servo by
        servo. A servo whose read fails keeps its last goal (the last command): its position is
        not known, and no stale one is sent in its place."""
        bus = self._require_bus()
        try:
            result = bus.group_read(self.ids, _PRESENT_ADDRESS, _PRESENT_SIZE)
            fresh = {i: result.data[i] for i in self.ids}
        except ServoCommunicationError:
            fresh = {}
            for servo_id in self.ids:
                try:
                    fresh[servo_id] = bus.read_bytes(servo_id, _PRESENT_ADDRESS, _PRESENT_SIZE)
                except ServoCommunicationError as exc:
                    _log.warning("%s: not read for the hold (%s): it keeps its last goal",
                                 self._servo(servo_id), exc.cause)
        goals: dict[int, int] = {}
        for servo_id, block in fresh.items():  # where each stands, as activation holds it
            raw = np.frombuffer(block, dtype=self._present_dtype)["position"]
            goals[servo_id] = int(_sign_magnitude(raw, self._signs[0])[0])
        if goals:
            self._sync_write_goal(goals)

    def _recover(self) -> None:
        """No reboot exists: check that every servo answers and that no protection persists;
        a latched overload clears when ``activate`` switches the torque on again."""
        for servo_id in self.ids:
            self._retried("ping at rearm", self._require_bus().ping, servo_id)
            status = self._read_register(servo_id, "status")
            if status & _PERSISTENT_BITS:
                temperature = self._read_register(servo_id, "present_temperature")
                raise MotorFault(
                    f"{self._servo(servo_id)}: still reports {status_error_text(status)} "
                    f"({temperature} degC); let it cool / check it before re-arming")
            self._latched.pop(servo_id, None)
            self._last_fault_by_servo.pop(servo_id, None)

    def _cleanup(self) -> None:
        if self._bus is not None:
            self._bus.close()
            self._bus = None

    def _details(self) -> Mapping[str, Any]:
        bus = self._bus
        known = self._positions is not None
        return {
            "port": self.params["port"],
            "baud_rate": self.params["baud_rate"],
            "series": self.series.name.value,
            "bus": bus.stats.as_dict() if bus is not None else None,
            "retries": self._retries,
            "watchdog": None,
            "servos": {
                str(servo_id): {
                    "joint": joint,
                    "model": model.name,
                    "fault": (status_error_text(self._latched[servo_id])
                              if servo_id in self._latched else None),
                    "last_fault": self._last_fault_by_servo.get(servo_id),
                    "load": float(self._loads[i]) if known else None,
                }
                for i, (servo_id, joint, model) in enumerate(
                    zip(self.ids, self.joints, self.models, strict=True))
            },
        }

    def _health(self) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
        """The servos' health as last read (stale readings unknown: see :mod:`.health`)."""
        unloading = StatusError.OVERHEAT | StatusError.OVERCURRENT | StatusError.OVERLOAD
        torque = {i: (False if self._latched.get(i, 0) & unloading else on)
                  for i, on in self._torque.items()}
        motors = self._servo_health.report(torque, self._latched, self._last_fault_by_servo)
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
    def last_loads(self) -> F64:
        """The servos' Present Load of the last good read, a signed fraction of full load in
        the joint's direction (the effort the servos report)."""
        loads: F64 = self._loads.copy()
        return loads

    @property
    def bus(self) -> FeetechBus | None:
        """The bus while configured (``None`` otherwise)."""
        return self._bus
