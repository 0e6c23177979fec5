"""MIT-mode CAN motors (kind ``can-mit``): CubeMars AK, Damiao DM, mini-cheetah drivers.

Theory of operation
-------------------
Every motor runs its own PD law ``t = kp (p_des - p) + kd (v_des - v) + t_ff`` and answers
each frame it receives with one state reply (position, velocity, torque; Damiao adds a state
code and temperatures). So one cycle on a bus is "send one frame per motor, collect one reply
per motor" and a motor is heard from only when it is spoken to.

* ``write`` encodes the held set-points (updated from the command's finite entries) and sends
  one frame per motor, on every bus, before anything is collected: buses transmit
  concurrently, so several buses cost the slowest one, not the sum.
* ``read`` collects the replies to the last ``write``, waiting for them at most the bus's
  ``receive_timeout`` (0: never waits) counted from when the wire could have carried every
  set-point and its reply (worst-case stuffing), or from the read if that is later: a loop
  catching up after a late cycle reads right after it wrote, while the replies are still on
  the wire, and must not count them missed. When nothing was written since the previous read
  (inactive, or two reads in a row) it first sends each motor its held frame (the set-point
  in motor mode, ``exit motor mode`` otherwise) to get an answer -- MIT has no read-only
  request. Replies are drained without blocking and only the newest per motor is kept; a
  motor whose newest feedback is older than its ``feedback_timeout`` is a communication
  fault.
* Every Damiao reply says whether the motor is enabled (state nibble ``1``) or disabled
  (``0``, as after a power-up). A motor the driver enabled that answers disabled has reset --
  a supply dip shorter than ``feedback_timeout`` restarts its firmware, which comes back out
  of motor mode, limp -- and is a fault ("motor 3 ... reset: answers disabled ..."), cleared
  by the re-arm, which enables it again. An AK reply carries no mode: an AK reset shorter
  than ``feedback_timeout`` cannot be seen (docs/can.md, "Motor reset").
* Bus-off (``bus.state`` where the interface reports it, or a SocketCAN bus-off error frame)
  is a fault; error-passive is counted and logged. A full transmit buffer flushes the stale
  queue (the motor then misses one cycle, which its ``feedback_timeout`` tolerates); a queue
  that stays full starves the motors, and their no-feedback fault names the full queue as
  the cause. A send error saying the interface is down or gone is a bus loss. Stale
  received frames are flushed on configure, activate and deactivate, and the transmit queue
  on deactivate, so nothing queued before a stop is replayed.

Command interfaces, per joint (the MIT PD is how position commands reach the motor):

* ``position`` (optionally + ``velocity``): ``p_des`` = command, ``v_des`` = velocity command
  (0 without it), the configured ``kp``/``kd``, ``t_ff`` = effort command if ``effort`` is also
  an interface, else 0.
* ``velocity`` alone: ``kp = 0``, ``kd`` = configured kd, ``v_des`` = command.
* ``effort`` alone: ``t_ff`` = command, ``kp = 0``, ``kd = effort_kd`` (0: pure torque).

Units. Per joint, with ``s = direction`` (+1/-1), ``g = gear_ratio`` (external gearing
between the motor's output shaft and the joint) and ``o = offset``::

    joint_position = s * motor_position / g + o      motor_position = s * g * (joint_position - o)
    joint_velocity = s * motor_velocity / g          motor_velocity = s * g * joint_velocity
    joint_effort   = s * g * motor_torque            motor_torque   = s * joint_effort / g

``kp``/``kd`` are sent as given: motor-side units (N*m/rad, N*m*s/rad of the motor's output).
Position commands are clamped to ``position_limits`` (joint units), then every value to the
model's MIT ranges by the codec.

Lifecycle: ``configure`` opens the buses and pings every motor (MIT has no read-only request:
a motor this instance left holding, e.g. across a re-arm, gets its held set-point and keeps
holding; any other motor, e.g. after the daemon restarted, gets ``exit motor mode``, the
conservative choice for a motor in an unknown state). ``activate`` arms the device-side
timeout (below), sends "enter motor mode" to every motor and checks each reply (a Damiao
reply must say "enabled"; an AK reply, which has no state, proves the motor is powered and
heard it), then seeds the set-point from the measured position (no jump) -- except for
motors that were holding without a fault, which keep their set-point (entering motor mode
again does not change it) -- and sends the set-points. ``deactivate`` holds (set-point = last
commanded position, v = t_ff = 0, the configured gains; effort-driven joints hold where they
are) or exits motor mode (torque off). ``recover`` (re-arm) resets the bus health after the
reopen of ``configure`` and clears Damiao errors (``FB``); motors that faulted -- every motor
of a bus that failed as a whole (send / receive failure, bus-off, every reply missing) --
are re-seeded by the ``activate`` that follows, which proves every motor enabled or fails
naming the first that is not (one line).

Device-side timeout (the ``watchdog_s`` parameter). A Damiao motor has a CAN timeout
(register 9, units of 50 us): ``activate`` writes ``watchdog_s`` into it (RAM, checked by the
echo) before enabling, so an enabled motor that hears nothing for that long -- the daemon or
its loop died, the bus was cut -- disables itself (torque off, state ``0xD``). A ``hold``
deactivate writes 0 (off) after the hold set-point, because the daemon stops commanding then
and "hold" must outlast it; if that cannot be confirmed the deactivate fails, saying the motor
will go limp. ``activate`` clears a ``0xD`` left by an expired timeout (it is the timeout's
own latch, not a drive fault). AK motors have no timeout settable over CAN (the firmware's is
set from its setup tool and off by default): they keep their last command if the daemon dies;
:meth:`MitHardware.device_watchdog` lists their joints as unprotected.

Every error message is one line naming the motor (or bus) and what to check: text from
python-can (whose socketcand client puts a whole traceback into its errors) is cut to its
first line.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import can
import numpy as np
from numpy.typing import NDArray

from jtc_hw.errors import CommunicationError, ConfigurationError, HardwareError, MotorFault
from jtc_hw.hardware import (
    JOINT_MAPPING_PARAMS,
    WATCHDOG_PARAM,
    DeviceName,
    DeviceWatchdog,
    HardwareInterface,
    JointCommand,
    JointState,
    ParamKind,
    ParamSpec,
    SafeAction,
    health_params,
    miss_rate_param,
    one_line,
    param_table,
)

from ..bus import (
    BusHealth,
    BusSettings,
    buses_param,
    close_bus,
    collect_until,
    drain_latest,
    flush,
    full_queue,
    joint_bus_param,
    joint_buses,
    open_settings,
    send,
    wire_bits,
)
from .codec import (
    CLEAR_ERROR,
    DAMIAO_STATES,
    DAMIAO_TIMEOUT_RID,
    ENTER_MOTOR_MODE,
    EXIT_MOTOR_MODE,
    MODEL_PRESETS,
    REGISTER_ID,
    REGISTER_WRITE,
    SET_ZERO,
    CommandEncoder,
    MitLimits,
    RegisterFrame,
    decode_register_frame,
    decode_reply,
    encode_register_frame,
    reply_motor_id,
    timeout_register_value,
)

__all__ = ["MitHardware"]

# A logger name is public (log filters name it): the one from before drivers/can/ was split.
_log = logging.getLogger("jtc_hw.drivers.can.mit")
F64 = NDArray[np.float64]
NS_PER_S = 1_000_000_000
DISABLED = 0  # Damiao state code of a motor out of motor mode (as after a power-up)
ENABLED = 1  # Damiao state code of an enabled motor
COMMUNICATION_LOST = 0xD  # Damiao state code of an expired CAN timeout
# The health readings each reply format carries (unknown while the reply is stale).
_REPLY_READINGS = {
    "damiao": ["mode", "torque_enabled", "temperature_c", "drive_temperature_c",
               "rotor_temperature_c", "state"],
    "ak": [],
}



@dataclass
class _Link:
    """One bus and the motors on it."""

    settings: BusSettings
    joints: list[int]  # indices into the component's joints
    ids: list[int]
    health: BusHealth
    reply_ids: frozenset[int]
    reply_format: str
    bus: can.BusABC | None = None
    latest: dict[int, can.Message] = field(default_factory=dict)
    pending: set[int] = field(default_factory=set)
    index_of: dict[int, int] = field(default_factory=dict)  # motor id -> joint index
    on_reply: Any = None  # (motor id, frame) -> None: decodes a reply as it is received
    sent_at: float = 0.0  # monotonic time the last exchange's first frame was queued
    exchange_s: float = 0.0  # wire time of a set-point and its reply, worst-case stuffing

    def key(self, msg: can.Message) -> int | None:
        if msg.arbitration_id not in self.reply_ids or msg.is_extended_id:
            return None
        motor = reply_motor_id(msg.data, self.reply_format)
        return motor if motor in self.index_of else None


class MitHardware(HardwareInterface):
    """MIT-mode CAN motors on one or more python-can buses (see the module docstring).

    Raises:
        ConfigurationError: invalid parameters (unknown model or bus, duplicate motor id on a
            bus, an id the model's reply cannot carry, a zero direction, a ``watchdog_s``
            beyond the Damiao timeout register's range).
    """

    kind: ClassVar[str] = "can-mit"
    COMMAND_INTERFACES: ClassVar[tuple[str, ...]] = ("position", "velocity", "effort")
    STATE_INTERFACES: ClassVar[tuple[str, ...]] = ("position", "velocity")

    PARAMS: ClassVar[Mapping[str, ParamSpec]] = param_table(
        buses_param(),
        joint_bus_param(),
        ParamSpec("ids", ParamKind.INT, None, "per joint: the motor's CAN id",
                  per_joint=True, required=True, minimum=1, maximum=0x7FF),
        ParamSpec("model", ParamKind.STRING, "AK80-9",
                  "per joint: motor model, which sets the MIT ranges and reply format",
                  per_joint=True, choices=tuple(MODEL_PRESETS)),
        ParamSpec("p_max", ParamKind.FLOAT, 0.0,
                  "per joint: MIT position range override, rad (0: the model's)",
                  per_joint=True, minimum=0.0),
        ParamSpec("v_max", ParamKind.FLOAT, 0.0,
                  "per joint: MIT velocity range override, rad/s (0: the model's)",
                  per_joint=True, minimum=0.0),
        ParamSpec("t_max", ParamKind.FLOAT, 0.0,
                  "per joint: MIT torque range override, N*m (0: the model's)",
                  per_joint=True, minimum=0.0),
        ParamSpec("master_id", ParamKind.INT, 0,
                  "per joint: arbitration id the motor's replies use (AK: 0; Damiao: its "
                  "MST_ID)", per_joint=True, minimum=0, maximum=0x7FF),
        ParamSpec("kp", ParamKind.FLOAT, 20.0,
                  "per joint: MIT kp for position commands and holding, N*m/rad (motor side)",
                  per_joint=True, minimum=0.0),
        ParamSpec("kd", ParamKind.FLOAT, 0.5,
                  "per joint: MIT kd for position / velocity commands and holding, N*m*s/rad",
                  per_joint=True, minimum=0.0),
        ParamSpec("effort_kd", ParamKind.FLOAT, 0.0,
                  "per joint: MIT kd (damping) with effort commands, N*m*s/rad",
                  per_joint=True, minimum=0.0),
        *JOINT_MAPPING_PARAMS,
        ParamSpec("position_limits", ParamKind.RANGE, (-math.inf, math.inf),
                  "per joint [min, max] commanded position, rad (null: unlimited)",
                  per_joint=True, nullable=True),
        ParamSpec("feedback_timeout", ParamKind.FLOAT, 0.02,
                  "per joint: s after which a motor's newest feedback counts as lost",
                  per_joint=True, minimum=0.0005, maximum=10.0),
        ParamSpec("max_temperature_c", ParamKind.FLOAT, 80.0,
                  "per joint: drive temperature (Damiao replies) above which it is a fault, "
                  "degC", per_joint=True, minimum=0.0, maximum=200.0),
        # Applies to the models with a CAN timeout (Damiao); AK motors have none over CAN.
        WATCHDOG_PARAM,
        # Only Damiao replies carry temperatures (a warning before max_temperature_c's fault);
        # no MIT reply carries the supply voltage.
        *health_params(65.0, None),
        # On a sound bus every set-point is answered within its wire time: a rate of missed
        # replies that a `feedback_timeout` still tolerates is worth a warning before it is not.
        miss_rate_param(0.01),
    )

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
        self._ids: tuple[int, ...] = p["ids"]
        buses: Mapping[str, BusSettings] = p["buses"]
        self._bus_of = joint_buses(self.joints, p["bus"], buses)
        self._limits: list[MitLimits] = []
        for i, joint in enumerate(self.joints):
            base = MODEL_PRESETS[p["model"][i]]
            self._limits.append(MitLimits(
                p["p_max"][i] or base.p_max, p["v_max"][i] or base.v_max,
                p["t_max"][i] or base.t_max, base.kp_max, base.kd_max, base.reply,
            ))
            if base.reply == "damiao" and self._ids[i] > 0x0F:
                raise ConfigurationError(
                    f"joint {joint!r}: {p['model'][i]} replies carry ids 1..15, got "
                    f"{self._ids[i]}", f"params.ids.{joint}", self._ids[i])
        self._encoders = [CommandEncoder(limits) for limits in self._limits]
        self._links: dict[str, _Link] = {}
        for bus_name, settings in buses.items():
            members = [i for i in range(n) if self._bus_of[i] == bus_name]
            if not members:
                continue
            formats = {self._limits[i].reply for i in members}
            if len(formats) > 1:
                raise ConfigurationError(
                    f"bus {bus_name!r} mixes reply formats {sorted(formats)}; put AK and "
                    "Damiao motors on separate buses", "params.model", sorted(formats))
            ids = [self._ids[i] for i in members]
            for motor_id in ids:
                if ids.count(motor_id) > 1:
                    dupes = [self.joints[i] for i in members if self._ids[i] == motor_id]
                    raise ConfigurationError(
                        f"motor id {motor_id} is used by {', '.join(dupes)} on bus {bus_name!r}",
                        "params.ids", motor_id)
            link = _Link(settings, members, ids, BusHealth(settings),
                         frozenset(p["master_id"][i] for i in members), formats.pop())
            link.index_of = {self._ids[i]: i for i in members}
            link.on_reply = functools.partial(self._take_reply, link.index_of)
            link.exchange_s = 2 * wire_bits(
                can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)),
                "worst") / settings.bitrate
            self._links[bus_name] = link
        self._sign = np.array(p["direction"], dtype=np.float64)
        self._gear = np.array(p["gear_ratio"], dtype=np.float64)
        self._offset = np.array(p["offset"], dtype=np.float64)
        self._lower = np.array([lim[0] for lim in p["position_limits"]], dtype=np.float64)
        self._upper = np.array([lim[1] for lim in p["position_limits"]], dtype=np.float64)
        self._kp = np.array(p["kp"], dtype=np.float64)
        self._kd = np.array(p["kd"], dtype=np.float64)
        self._effort_kd = np.array(p["effort_kd"], dtype=np.float64)
        self._timeout_ns = np.array([round(t * NS_PER_S) for t in p["feedback_timeout"]],
                                    dtype=np.int64)
        self._damiao = any(lim.reply == "damiao" for lim in self._limits)
        # Motors with a device-side timeout: Damiao's CAN timeout register.
        self._has_timeout = np.array([lim.reply == "damiao" for lim in self._limits],
                                     dtype=bool)
        self._watchdog_s: float = p["watchdog_s"]
        try:
            self._timeout_counts = timeout_register_value(self._watchdog_s)
        except ValueError as exc:
            raise ConfigurationError(f"{self._owner()}: watchdog_s: {exc}", "params.watchdog_s",
                                     self._watchdog_s) from exc
        self._armed = np.zeros(n, dtype=bool)
        self._max_temp = np.array(p["max_temperature_c"], dtype=np.float64)
        ci = self.command_interfaces
        self._cmd_position = "position" in ci
        self._cmd_velocity = "velocity" in ci
        self._cmd_effort = "effort" in ci
        # Motor-side state and held set-points (persist across cleanup/configure: a motor
        # left holding keeps holding, and configure's ping must not change that).
        self._p = np.full(n, np.nan)
        self._v = np.zeros(n)
        self._t = np.zeros(n)
        self._rx_ns = np.zeros(n, dtype=np.int64)
        self._temperature: list[int | None] = [None] * n
        self._state_code: list[int | None] = [None] * n
        self._rotor_temperature: list[int | None] = [None] * n
        self._missed = [0] * n
        self._held_p = np.zeros(n)
        self._held_v = np.zeros(n)
        self._held_t = np.zeros(n)
        self._held_kp = np.zeros(n)
        self._held_kd = np.zeros(n)
        self._motor_mode = np.zeros(n, dtype=bool)
        self._written = False
        self._faults: dict[str, str] = {}

    # -- public extras ------------------------------------------------------------------------

    def set_zero(self, joints: Sequence[str] | None = None) -> None:
        """Make the current position each motor's zero (the ``FE`` command; Damiao/AK store
        it). Only while INACTIVE: the motor's notion of position jumps.

        Raises:
            HardwareError: not INACTIVE, or a motor did not answer.
        """
        if self.state.value != "inactive":
            raise HardwareError(f"{self._owner()}: set_zero() needs the component configured "
                                f"and inactive, it is {self.state.value}")
        which = set(self.joints if joints is None else joints)
        self._exchange(lambda i: SET_ZERO if self.joints[i] in which else None, setup=True)

    def device_watchdog(self) -> DeviceWatchdog:
        """What stops the motors if the daemon cannot command them (no I/O).

        Damiao motors: their CAN timeout, armed on activate at ``watchdog_s``. AK motors have
        none settable over CAN: their joints are listed as unprotected.
        """
        unprotected = tuple(j for i, j in enumerate(self.joints) if not self._has_timeout[i])
        if len(unprotected) == len(self.joints):
            return DeviceWatchdog(
                None, "no device-side watchdog: motors keep their last command if the daemon "
                "dies (AK firmware's CAN timeout is set only from its setup tool)", unprotected)
        mechanism = (f"Damiao CAN timeout (register 9) {self._watchdog_s * 1e3:g} ms: motors "
                     "disable themselves (torque off) when no frame comes")
        if unprotected:
            mechanism += "; AK motors have none and keep their last command"
        return DeviceWatchdog(self._watchdog_s, mechanism, unprotected)

    def devices(self) -> tuple[DeviceName, ...]:
        """One lock per motor id on each bus (``BusSettings.device_names``): a motor listens
        to the frames of its id, so two daemons may share a bus with different ids, never one
        id. Nothing else on the bus is exclusive: replies carry the motor id (AK) or come to a
        master id that only filters (Damiao), and each driver keeps only its own motors'.

        Raises:
            CommunicationError: a bus cannot be named (unknown interface, unresolved host).
        """
        return tuple(
            name
            for link in self._links.values()
            for name in link.settings.device_names(
                {f"mit:{motor_id}": f"motor {motor_id}" for motor_id in link.ids})
        )

    # -- primitives ---------------------------------------------------------------------------

    def _configure(self) -> None:
        opened: list[_Link] = []
        try:
            for link in self._links.values():
                link.bus = open_settings(link.settings)
                opened.append(link)
                link.health.state = "active"
                self._flush(link)
                link.latest.clear()
                link.pending.clear()
            self._exchange(self._ping_frame, setup=True)
        except BaseException:
            for link in opened:
                close_bus(link.bus)
                link.bus = None
            raise

    def _ping_frame(self, i: int) -> bytes:
        if self._motor_mode[i]:
            return self._setpoint(i)
        return EXIT_MOTOR_MODE

    def _recover(self) -> None:
        for link in self._links.values():
            link.health.state = "active"
        damiao = [i for i in range(len(self.joints)) if self._limits[i].reply == "damiao"]
        if damiao:
            self._exchange(lambda i: CLEAR_ERROR if i in damiao else None, setup=True)
        # A motor that faulted -- or whose bus failed as a whole: it may have been power
        # cycled -- is re-seeded from where it is by the activation that follows (which
        # sends every motor "enter motor mode" and checks its reply); the others keep
        # holding their set-point undisturbed.
        for i, joint in enumerate(self.joints):
            if joint in self._faults:
                self._motor_mode[i] = False
        self._faults.clear()

    def _activate(self, now_ns: int) -> JointCommand:
        for link in self._links.values():
            self._flush(link)
        # Motors already holding (a re-arm after a hold) keep their set-point: re-seeding from
        # the measured position would let a loaded joint sag by its PD error. A Damiao reply
        # says whether it is really enabled.
        holding = self._motor_mode & np.array(
            [code is None or code == ENABLED for code in self._state_code], dtype=bool)
        entering = ~holding
        try:
            # The timeout first: from the moment a motor is enabled, it stops by itself if
            # the daemon goes away.
            self._write_timeouts(self._has_timeout, self._timeout_counts)
            lost = [i for i, code in enumerate(self._state_code) if code == COMMUNICATION_LOST]
            if lost:
                # An expired timeout (the daemon, its loop or the bus went away): the
                # timeout's own latch, not a drive fault; it blocks "enter motor mode".
                self._exchange(lambda i: CLEAR_ERROR if i in lost else None, setup=True)
            # Every motor, holding or not: only its reply proves it is powered and enabled
            # (entering again keeps the set-point of a motor in motor mode).
            self._exchange(lambda i: ENTER_MOTOR_MODE, setup=True)
            self._check_enabled()
            self._check_faults(time.monotonic_ns())
            self._motor_mode[:] = True
            # Seed the others: hold where the motor is.
            self._held_p[entering] = self._p[entering]
            self._held_v[:] = 0.0
            self._held_t[:] = 0.0
            if self._cmd_position:
                self._held_kp[:], self._held_kd[:] = self._kp, self._kd
            elif self._cmd_velocity:
                self._held_kp[:], self._held_kd[:] = 0.0, self._kd
            else:
                self._held_kp[:], self._held_kd[:] = 0.0, self._effort_kd
            self._exchange(self._setpoint, setup=True)
            self._check_faults(time.monotonic_ns())
        except BaseException:
            self._undo_activation(entering)
            raise
        held = self.nan_command()
        if held.positions is not None:
            held.positions[:] = self._sign * self._held_p / self._gear + self._offset
        return held

    def _undo_activation(self, entering: NDArray[np.bool_]) -> None:
        """After a failed activation, best effort: the motors it enabled switch off again
        (not left in motor mode with no set-point, free or worse); the ones that were holding
        keep holding, their timeout off again (nobody commands them until the next re-arm)."""
        self._motor_mode[entering] = False
        try:
            self._send_all(lambda i: EXIT_MOTOR_MODE if entering[i] else None)
            self._collect(setup=True)
        except Exception as exc:  # noqa: BLE001 - the original error matters more
            _log.warning("%s: switching motors off after a failed activation: %s",
                         self._owner(), one_line(exc))
        try:
            self._write_timeouts(self._has_timeout & ~entering & self._armed, 0)
        except Exception as exc:  # noqa: BLE001 - the original error matters more
            _log.warning("%s: switching the CAN timeout off after a failed activation: %s",
                         self._owner(), one_line(exc))

    def _check_enabled(self) -> None:
        """After "enter motor mode": a Damiao reply must say "enabled" (an AK reply has no
        state: that it came proves the motor is powered and heard the command).

        Raises:
            MotorFault: a motor is not enabled; one line naming it and what to check.
        """
        for i, joint in enumerate(self.joints):
            code = self._state_code[i]
            if self._limits[i].reply != "damiao" or code == ENABLED:
                continue
            where = self._where(i)
            if code is not None and code >= 8:
                message = (f"{self._owner()}: {where} did not enable: it reports "
                           f"{DAMIAO_STATES.get(code, f'error code {code:#x}')}; check supply, "
                           "load and cooling, then re-arm (clears the error)")
            else:
                message = (f"{self._owner()}: {where} did not enable (it reports "
                           f"{DAMIAO_STATES.get(code or 0, 'disabled')}); check that it is in "
                           "MIT mode (register 10 = 1) and powered, then re-arm")
            self._faults[joint] = message
            raise MotorFault(message)

    def _read(self, now_ns: int) -> JointState:
        if not self._written:
            self._send_all(self._ping_frame)
        self._written = False
        self._collect(setup=False)
        self._check_faults(time.monotonic_ns())
        return JointState(
            self._joint_positions(),
            self._sign * self._v / self._gear if self._velocity_state else None,
        )

    def _write(self, now_ns: int, command: JointCommand) -> None:
        sign, gear, offset = self._sign, self._gear, self._offset
        if self._cmd_position and command.positions is not None:
            given = np.isfinite(command.positions)
            target = np.clip(command.positions, self._lower, self._upper)
            self._held_p[given] = (sign * gear * (target - offset))[given]
        elif not self._cmd_position:
            self._held_p[:] = self._p  # kp = 0: the position set-point is unused
        if self._cmd_velocity and command.velocities is not None:
            given = np.isfinite(command.velocities)
            self._held_v[given] = (sign * gear * command.velocities)[given]
        if self._cmd_effort and command.effort is not None:
            given = np.isfinite(command.effort)
            self._held_t[given] = (sign * command.effort / gear)[given]
        self._send_all(self._setpoint)
        self._written = True

    def _deactivate(self, now_ns: int, action: SafeAction) -> None:
        for link in self._links.values():
            if link.bus is not None:
                self._flush(link)
        if action is SafeAction.TORQUE_OFF:
            self._motor_mode[:] = False
            frame = self._ping_frame
        else:
            if not self._cmd_position:
                self._held_p[:] = np.where(np.isfinite(self._p), self._p, self._held_p)
            self._held_v[:] = 0.0
            self._held_t[:] = 0.0
            self._held_kp[:], self._held_kd[:] = self._kp, self._kd
            frame = self._setpoint
        self._written = False
        self._send_all(frame)
        self._collect(setup=False)
        if action is SafeAction.HOLD and self._armed.any():
            # The daemon stops commanding now: with the timeout on, the motors would let go
            # after watchdog_s; "hold" must outlast the daemon's stop or fault state.
            self._write_timeouts(self._armed.copy(), 0, what="keep holding: it disables "
                                 "itself (limp) when the timeout expires")

    def _cleanup(self) -> None:
        for link in self._links.values():
            close_bus(link.bus)
            link.bus = None
            link.latest.clear()
            link.pending.clear()

    def _details(self) -> Mapping[str, Any]:
        now = time.monotonic_ns()
        motors = {}
        for i, joint in enumerate(self.joints):
            age = (now - int(self._rx_ns[i])) / NS_PER_S if self._rx_ns[i] else None
            motors[joint] = {
                "id": self._ids[i],
                "bus": self._bus_of[i],
                "motor_mode": bool(self._motor_mode[i]),
                "timeout_s": self._watchdog_s if self._armed[i] else None,
                "feedback_age_s": age,
                "missed_replies": self._missed[i],
                "temperature_c": self._temperature[i],
                "state_code": self._state_code[i],
                "fault": self._faults.get(joint),
            }
        return {
            "buses": {name: link.health.as_dict() for name, link in self._links.items()},
            "motors": motors,
        }

    def _health(self) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
        """From the replies the cycle collects anyway (no extra frame): Damiao's state code and
        drive / rotor temperatures; AK replies carry neither. The warning temperature is the
        hotter of the two.

        Every reading comes from the motor's newest reply; ``age_s`` is that reply's age. A
        reply older than ``feedback_timeout`` (``stale``: true), or none yet, shows every
        reading as unknown (``None``, listed in ``unknown``) rather than the last one heard:
        after a bus loss the motor may have lost power. ``torque_enabled`` is the Damiao
        reply's state ("enabled"); an AK reply does not say, so it is always unknown there
        (``commanded_mode`` says what the driver asked for).
        """
        now = time.monotonic_ns()
        motors: list[dict[str, Any]] = []
        for i, joint in enumerate(self.joints):
            heard = int(self._rx_ns[i])
            age = (now - heard) / NS_PER_S if heard else None
            fresh = bool(heard) and now - heard <= int(self._timeout_ns[i])
            code = self._state_code[i] if fresh else None
            drive_t = self._temperature[i] if fresh else None
            rotor_t = self._rotor_temperature[i] if fresh else None
            temps = [t for t in (drive_t, rotor_t) if t is not None]
            errors = ([DAMIAO_STATES.get(code, f"error code {code:#x}")]
                      if code is not None and code >= 8 else [])
            motors.append({
                "motor": self._ids[i],
                "joint": joint,
                "model": self.params["model"][i],
                "mode": None if code is None else ("mit" if code == ENABLED else "off"),
                "commanded_mode": "mit" if self._motor_mode[i] else "off",
                "torque_enabled": None if code is None else code == ENABLED,
                "temperature_c": max(temps) if temps else None,
                "drive_temperature_c": drive_t,
                "rotor_temperature_c": rotor_t,
                "state": None if code is None else DAMIAO_STATES.get(code, f"{code:#x}"),
                "age_s": None if age is None else round(age, 3),
                "stale": not fresh,
                "unknown": [] if fresh else _REPLY_READINGS[self._limits[i].reply],
                "errors": errors,
                "last_fault": self._faults.get(joint),
            })
        healths = [link.health for link in self._links.values()]
        bus = {
            "transactions": sum(h.tx_frames for h in healths),
            "timeouts": sum(self._missed),
            # The CAN controller checks CRCs itself; what reaches us is its error frames.
            "crc_errors": sum(h.error_frames for h in healths),
            "retries": None,  # MIT never resends: the next cycle's frame supersedes
        }
        return motors, bus

    # -- helpers ------------------------------------------------------------------------------

    def _where(self, i: int) -> str:
        return f"motor {self._ids[i]} (joint {self.joints[i]!r}) on bus {self._bus_of[i]!r}"

    def _joint_positions(self) -> F64:
        result: F64 = self._sign * self._p / self._gear + self._offset
        return result

    def _setpoint(self, i: int) -> bytes:
        return self._encoders[i](self._held_p.item(i), self._held_v.item(i),
                                 self._held_kp.item(i), self._held_kd.item(i),
                                 self._held_t.item(i))

    def _bus_fault(self, link: _Link, message: str) -> CommunicationError:
        """A failure of a bus as a whole: every motor on it is in an unknown state (it may
        have lost power, or missed commands); each is marked faulted, so that the re-arm
        re-seeds it. Returns the error to raise."""
        for i in link.joints:
            self._faults[self.joints[i]] = message
        return CommunicationError(message)

    def _flush(self, link: _Link) -> None:
        """Drop the stale frames of ``link`` (its bus is open).

        Raises:
            CommunicationError: the interface failed (the bus is marked faulted).
        """
        assert link.bus is not None
        try:
            link.health.stale_flushed += flush(link.bus)
        except (can.CanError, OSError) as exc:
            raise self._bus_fault(link, f"{self._owner()}: receiving on "
                                  f"{link.settings.describe()} failed: {one_line(exc)}; check "
                                  "the interface and its connection") from exc

    def _send_all(self, frame_of: Any) -> None:
        """Send one frame per motor on every bus (all buses before any collecting).

        The buses take turns, one frame each (bus A's first, bus B's first, A's second...):
        every bus gets its first frame, and so starts transmitting, as early as possible,
        instead of waiting for the frames of the buses before it to be handed over.
        """
        for link in self._links.values():
            if link.bus is None:
                raise CommunicationError(f"{self._owner()}: {link.settings.describe()} is "
                                         "not open; configure first")
        rounds = max(len(link.ids) for link in self._links.values()) if self._links else 0
        links = list(self._links.values())
        for k in range(rounds):
            for link in links:
                if k >= len(link.ids):
                    continue
                if k == 0:
                    link.sent_at = time.monotonic()
                bus = link.bus
                assert bus is not None  # checked above
                motor_id, i = link.ids[k], link.joints[k]
                data = frame_of(i)
                if data is None:
                    continue
                link.latest.pop(motor_id, None)
                msg = can.Message(arbitration_id=motor_id, is_extended_id=False, data=data)
                try:
                    ok = send(bus, msg, link.health)
                except (can.CanError, OSError) as exc:
                    # The interface (or the connection to it) failed: the whole bus is gone.
                    raise self._bus_fault(
                        link, f"{self._owner()}: sending to motor {motor_id} (joint "
                        f"{self.joints[i]!r}) on {link.settings.describe()} failed: "
                        f"{one_line(exc)}; check the interface and its connection"
                    ) from exc
                if ok:
                    link.pending.add(motor_id)

    def _collect(self, setup: bool) -> None:
        """Collect the replies pending on every bus; decode the newest per motor."""
        for link in self._links.values():
            bus = link.bus
            assert bus is not None
            timeout = link.settings.setup_timeout if setup else link.settings.receive_timeout
            # The replies cannot all be in before the wire has carried every frame sent and
            # its reply: receive_timeout (the bound for stragglers) counts from then, or from
            # now, whichever is later -- so a cycle that follows a late one closely (the
            # loop catching up) does not count replies still on the wire as missed.
            on_wire = link.sent_at + len(link.pending) * link.exchange_s
            deadline = max(time.monotonic(), on_wire) + timeout
            try:
                # Each reply is decoded as it is received (on_reply), while the others are
                # still on the wire: after the last one only its own decoding is left.
                if link.pending:
                    result = collect_until(bus, link.latest, link.pending, deadline, link.key,
                                           link.on_reply)
                else:
                    result = drain_latest(bus, link.latest, link.key, on_stored=link.on_reply)
            except (can.CanError, OSError) as exc:
                raise self._bus_fault(
                    link, f"{self._owner()}: receiving on {link.settings.describe()} failed: "
                    f"{one_line(exc)}; check the interface and its connection"
                ) from exc
            stamp = time.monotonic_ns()
            link.health.rx_frames += result.stored
            for error in result.errors:
                link.health.note_error_frame(error)
            for motor_id in link.pending:
                self._missed[link.index_of[motor_id]] += 1
            link.pending.clear()
            for motor_id in link.latest:
                self._rx_ns[link.index_of[motor_id]] = stamp
            link.latest.clear()
            try:
                link.health.check(bus, self._owner())
            except CommunicationError as exc:
                raise self._bus_fault(link, str(exc)) from exc

    def _take_reply(self, index_of: Mapping[int, int], motor_id: int,
                    msg: can.Message) -> None:
        """Decode the reply ``msg`` of ``motor_id`` (its key: a reply of the link's format)
        into the motor's state; a newer reply in the same collection overwrites it."""
        i = index_of[motor_id]
        reply = decode_reply(msg.data, self._limits[i])
        self._p[i], self._v[i], self._t[i] = reply.position, reply.velocity, reply.torque
        self._temperature[i] = reply.temperature
        self._state_code[i] = reply.error_code
        self._rotor_temperature[i] = reply.rotor_temperature

    def _exchange(self, frame_of: Any, setup: bool) -> None:
        """Send, collect, and require an answer from every motor that was sent a frame."""
        before = self._rx_ns.copy()
        self._written = False
        self._send_all(frame_of)
        self._collect(setup)
        silent = [i for i in range(len(self.joints))
                  if frame_of(i) is not None and self._rx_ns[i] == before[i]]
        if silent:
            raise self._silent(silent, "; check its power, CAN id, bitrate, wiring and "
                               "termination")

    def _silent(self, silent: Sequence[int], hint: str) -> CommunicationError:
        """The error for motors that did not answer (marked faulted)."""
        message = (f"{self._owner()}: no answer from "
                   + ", ".join(f"motor {self._ids[i]} (joint {self.joints[i]!r}) on "
                               f"{self._links[self._bus_of[i]].settings.describe()}"
                               for i in silent) + hint)
        for i in silent:
            self._faults[self.joints[i]] = message
        return CommunicationError(message)

    def _write_timeouts(
        self, which: NDArray[np.bool_], counts: int,
        what: str = "stop by itself if the daemon goes away",
    ) -> None:
        """Write the Damiao CAN timeout register of the motors in ``which`` and wait for
        every echo (register requests go to ``0x7FF``; the echo comes on the reply id).

        Raises:
            CommunicationError: a motor did not confirm the value (named, with ``what`` the
                motor cannot then do), or the bus failed.
        """
        if not which.any():
            return
        for link in self._links.values():
            if link.bus is None:
                raise CommunicationError(f"{self._owner()}: {link.settings.describe()} is "
                                         "not open; configure first")
        confirmed: set[int] = set()
        for link in self._links.values():
            bus = link.bus
            assert bus is not None
            want = {link.ids[k] for k, i in enumerate(link.joints) if which[i]}
            if not want:
                continue

            def echo(msg: can.Message, link: _Link = link) -> int | None:
                if msg.arbitration_id not in link.reply_ids or len(msg.data) != 8:
                    return None
                try:
                    frame = decode_register_frame(msg.data)
                except ValueError:
                    return None  # a state reply
                if (frame.command, frame.rid, frame.value) != (
                        REGISTER_WRITE, DAMIAO_TIMEOUT_RID, counts):
                    return None
                return frame.motor_id if frame.motor_id in link.index_of else None

            try:
                for motor_id in sorted(want):
                    data = encode_register_frame(
                        RegisterFrame(motor_id, REGISTER_WRITE, DAMIAO_TIMEOUT_RID, counts))
                    send(bus, can.Message(arbitration_id=REGISTER_ID, is_extended_id=False,
                                          data=data), link.health)
                latest: dict[int, can.Message] = {}
                pending = set(want)
                collect_until(bus, latest, pending, time.monotonic()
                              + link.settings.setup_timeout, echo)
            except (can.CanError, OSError) as exc:
                raise self._bus_fault(
                    link, f"{self._owner()}: setting the CAN timeout on "
                    f"{link.settings.describe()} failed: {one_line(exc)}; check the interface "
                    "and its connection") from exc
            confirmed.update(link.index_of[m] for m in latest)
        for i in confirmed:
            self._armed[i] = counts > 0  # unconfirmed: unknown, left as it was
        missing = [int(i) for i in np.flatnonzero(which) if i not in confirmed]
        if missing:
            value = f"{counts * 50e-3:g} ms" if counts else "0 (off)"
            raise self._silent(missing, f" to setting its CAN timeout (register 9) to {value}: "
                               f"it cannot {what}; check its power and wiring")

    def _check_faults(self, now_ns: int) -> None:
        stale = (self._rx_ns == 0) | (now_ns - self._rx_ns > self._timeout_ns)
        if not (self._damiao or stale.any()):
            return  # the usual cycle: one vector comparison
        first: HardwareError | None = None
        # Every motor's fault is recorded (the re-arm re-seeds each); the first is raised.
        for i, joint in enumerate(self.joints):
            code = self._state_code[i]
            where = self._where(i)
            error: HardwareError | None = None
            if code is not None and code >= 8:
                error = MotorFault(
                    f"{self._owner()}: {where} reports "
                    f"{DAMIAO_STATES.get(code, f'error code {code:#x}')}; check supply, "
                    "load and cooling, then re-arm (clears the error)")
            elif (temp := self._temperature[i]) is not None and temp > self._max_temp[i]:
                error = MotorFault(
                    f"{self._owner()}: {where} is at {temp} degC, above max_temperature_c "
                    f"{self._max_temp[i]:g}; let it cool, then re-arm")
            elif code == DISABLED and self._motor_mode[i] and not stale[i]:
                # Enabled by us, disabled by itself without an error: the firmware restarted
                # (a supply dip, a power cycle) and came back out of motor mode, limp.
                error = MotorFault(
                    f"{self._owner()}: {where} reset: answers disabled (out of motor mode) "
                    "while it should be enabled, so it holds no torque; it lost power or "
                    "restarted: check its supply and connectors, then re-arm")
            elif stale[i]:
                age = now_ns - int(self._rx_ns[i])
                why = full_queue(self._links[self._bus_of[i]].health)
                error = CommunicationError(
                    f"{self._owner()}: no feedback from {where} for {age / 1e6:.0f} ms "
                    f"(feedback_timeout {self._timeout_ns[i] / 1e6:g} ms); "
                    + (why or "check its power, CAN id and wiring"))
            if error is not None:
                self._faults[joint] = str(error)
                first = first or error
        if first is not None:
            raise first
