"""Simulated joints (kind ``mirror``): commands become state, like ros2_control's GenericSystem.

Theory of operation
-------------------
The mirror never reads a clock. Every timed call (``activate``, ``read``, ``write``,
``deactivate``) first advances the simulation from the previous call's ``now_ns`` to its own,
with the commands in force during that interval, solved exactly (no integration error, so one
step of ``2 T`` equals two steps of ``T``). Then ``write`` swaps in new commands.

Each joint is driven by one interface at a time, its *mode*: the first interface, in the order
position, velocity, acceleration, effort, that has a finite value for it in the latest write
that gave it any. ``NaN`` (or any non-finite value) means "not written": the joint keeps its mode
and set point, as a real drive keeps its registers.

* **position**: the joint tracks the (limit-clamped) target: reached at the next read when
  ``lag_s`` is 0, else a first-order lag ``dp/dt = (target - p) / lag_s``; either way at most
  ``velocity_limit`` fast (the lag saturates into a constant-speed ramp, solved piecewise).
  The velocity state is the actual rate of change over the interval, the acceleration state
  that of the velocity.
* **velocity**: ``p += v dt`` with the command clamped to ``velocity_limit``.
* **acceleration**: constant acceleration, integrated twice; the velocity saturates at
  ``velocity_limit``.
* **effort**: a unit inertia with viscous ``damping``: ``dv/dt = effort - damping v``
  (``velocity_limit`` does not apply: a torque-driven joint has no velocity loop).

One scalar interface, ``speed_scaling_factor``, is both a state and a command interface (a
controller's ``speed_scaling.state_interface`` / ``command_interface``,
``<component>/speed_scaling_factor``): as GenericSystem mirrors, a value written is the state
from the next read; before any write the state is the ``speed_scaling_factor`` parameter (a
robot whose speed slider or safety controller has slowed it: with only the state interface
configured, nothing writes it). While frozen, it keeps its value too.

``position_limits`` clamp the position; a joint driven into a limit stops there (velocity and
acceleration 0). Before the first command, while inactive, and after a deactivation, a joint is
held by a position servo (its target: its last position command, or where it stood).

Positions start at ``initial_positions`` when the instance is built and persist across
``cleanup``/``configure`` (a simulated arm does not teleport); held commands do not survive
``configure`` or a ``torque_off`` deactivation.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from ..config.schema import ParamKind, ParamSpec, param_table
from ..controller.config import COMMAND_INTERFACE_TYPES
from ..controller.joints import F64, JointCommand, JointState
from ..controller.messages import NS_PER_S
from ..errors import CommunicationError, ConfigurationError, HardwareError
from .interface import DeviceWatchdog, HardwareInterface
from .lifecycle import SafeAction

__all__ = ["MirrorHardware"]

_POSITION, _VELOCITY, _ACCELERATION, _EFFORT = 0, 1, 2, 3


class MirrorHardware(HardwareInterface):
    """Simulated joints for tests and the embedded default (see the module docstring).

    Test knobs, usable in any state: :meth:`set_frozen` (feedback stops changing, to provoke
    tolerance aborts), :meth:`inject_fault` / :meth:`clear_fault` (reads raise
    ``CommunicationError``) and :meth:`displace` (the joints moved from outside).

    Raises:
        ConfigurationError: invalid parameters (see :attr:`PARAMS`), or an initial position
            outside its joint's position limits.
    """

    kind: ClassVar[str] = "mirror"

    PARAMS: ClassVar[Mapping[str, ParamSpec]] = param_table(
        ParamSpec("lag_s", ParamKind.FLOAT, 0.0,
                  "first-order time constant of position tracking, s (0: ideal, the target "
                  "is reached at the next read)", minimum=0.0),
        ParamSpec("position_limits", ParamKind.RANGE, (-math.inf, math.inf),
                  "per joint [min, max] position, rad (omitted or null: unlimited)",
                  per_joint=True, nullable=True),
        ParamSpec("velocity_limit", ParamKind.FLOAT, 0.0,
                  "per joint maximum speed, rad/s (0: none)", minimum=0.0, per_joint=True),
        ParamSpec("initial_positions", ParamKind.FLOAT, 0.0,
                  "per joint position when the simulation starts, rad", per_joint=True),
        ParamSpec("damping", ParamKind.FLOAT, 0.0,
                  "viscous damping of effort-driven joints (unit inertia), N*m*s/rad",
                  minimum=0.0),
        ParamSpec("speed_scaling_factor", ParamKind.FLOAT, 1.0,
                  "the scalar interface speed_scaling_factor's state until a value is written "
                  "to it (module docstring)", minimum=0.0),
    )

    SCALAR_STATE_INTERFACES: ClassVar[tuple[str, ...]] = ("speed_scaling_factor",)
    SCALAR_COMMAND_INTERFACES: ClassVar[tuple[str, ...]] = ("speed_scaling_factor",)

    def __init__(
        self,
        name: str,
        joints: Sequence[str],
        command_interfaces: Sequence[str],
        state_interfaces: Sequence[str],
        params: Mapping[str, Any],
    ) -> None:
        super().__init__(name, joints, command_interfaces, state_interfaces, params)
        n = len(self.joints)
        p = self.params
        self._lag_s: float = p["lag_s"]
        self._damping: float = p["damping"]
        self._lower = np.array([lim[0] for lim in p["position_limits"]], dtype=np.float64)
        self._upper = np.array([lim[1] for lim in p["position_limits"]], dtype=np.float64)
        vmax = np.array(p["velocity_limit"], dtype=np.float64)
        self._vmax = np.where(vmax > 0.0, vmax, np.inf)
        self._p = np.array(p["initial_positions"], dtype=np.float64)
        outside = (self._p < self._lower) | (self._p > self._upper)
        if outside.any():
            i = int(np.flatnonzero(outside)[0])
            raise ConfigurationError(
                f"initial position {self._p[i]:g} of joint {self.joints[i]!r} is outside its "
                f"position_limits [{self._lower[i]:g}, {self._upper[i]:g}]",
                "params.initial_positions",
                float(self._p[i]),
            )
        self._v = np.zeros(n)
        self._a = np.zeros(n)
        self._mode = np.full(n, _POSITION, dtype=np.int8)
        self._same_mode: int | None = _POSITION
        """The mode of every joint when they share one (the usual case), else None; kept
        with ``_mode`` by :meth:`_modes_changed`."""
        self._target = self._p.copy()
        # Last finite value written per interface: set points of the mode, and what
        # activate() reports as held.
        self._held = np.full((4, n), np.nan)
        self._commanded = tuple(i in self.command_interfaces for i in COMMAND_INTERFACE_TYPES)
        # Per-cycle shortcuts, decided once: a position-only command, no speed limit, no
        # position limit (the usual simulated arm) skip work whose result is known.
        self._position_only = self._commanded == (True, False, False, False)
        self._speed_limited = bool(np.isfinite(self._vmax).any())
        self._bounded = bool(np.isfinite(self._lower).any() or np.isfinite(self._upper).any())
        self._t_ns: int | None = None
        # dt (s) of the last step without a speed limit, and its arrays (``_position_step``).
        self._dt = math.nan
        self._dts = self._decay = np.zeros(n)
        self._frozen = False
        self._fault: str | None = None
        # speed_scaling_factor: as the last read left it, written (for the next read), set
        # (for the next write).
        self._scalar_read = math.nan
        self._scalar_written: float = p["speed_scaling_factor"]
        self._scalar_set = math.nan

    # -- test knobs ---------------------------------------------------------------------------

    @property
    def frozen(self) -> bool:
        """Whether the feedback is frozen (see :meth:`set_frozen`)."""
        return self._frozen

    def device_watchdog(self) -> DeviceWatchdog:
        """Simulated joints live in the loop process: nothing moves once it is gone."""
        return DeviceWatchdog(0.0, "simulated joints: nothing moves without the loop process")

    def set_frozen(self, frozen: bool) -> None:
        """Freeze (or unfreeze) the joints: every read returns the same state.

        While frozen the joints do not move (commands are still accepted and stored); after
        unfreezing they continue from where they were, without a jump.
        """
        self._frozen = bool(frozen)

    def inject_fault(self, message: str) -> None:
        """Make every read raise ``CommunicationError(message)`` until :meth:`clear_fault`
        or :meth:`recover` (the fault latches, as a device's does).

        The joints keep following their commands meanwhile: the next good read shows where
        they got to.
        """
        self._fault = str(message)

    def clear_fault(self) -> None:
        """Undo :meth:`inject_fault`."""
        self._fault = None

    def displace(self, positions: Sequence[float] | NDArray[np.float64]) -> None:
        """Move the joints from outside (a push, a slip, a hand while the torque is off) to
        ``positions``, clamped to the position limits, at the time of the last call.

        The velocity and acceleration states and the commands in force are unchanged: the
        next read shows the new positions, each joint following its command from there (an
        ideal position-driven one is back on its target at the next read after time passed).
        Frozen joints stay where they were put.

        Raises:
            ValueError: ``positions`` is not one value per joint.
        """
        p = np.array(positions, dtype=np.float64)
        if p.shape != self._p.shape:
            raise ValueError(f"{self._owner()}: {p.size} positions for {len(self.joints)} joints")
        self._p = np.clip(p, self._lower, self._upper)

    # -- primitives ---------------------------------------------------------------------------

    def _recover(self) -> None:
        self._fault = None

    def _configure(self) -> None:
        self._held.fill(np.nan)
        self._hold_here(np.ones(len(self.joints), dtype=bool))
        self._t_ns = None

    def _activate(self, now_ns: int) -> JointCommand:
        self._advance(now_ns)
        fields = [
            self._held[k].copy() if on else None for k, on in enumerate(self._commanded)
        ]
        return JointCommand(*fields)

    def _read(self, now_ns: int) -> JointState:
        if self._fault is not None:
            raise CommunicationError(self._fault)
        self._advance(now_ns)
        if not self._frozen or math.isnan(self._scalar_read):
            self._scalar_read = self._scalar_written
        return JointState(
            self._p.copy(),
            self._v.copy() if self._velocity_state else None,
            self._a.copy() if self._acceleration_state else None,
        )

    def _write(self, now_ns: int, command: JointCommand) -> None:
        self._advance(now_ns)
        if not math.isnan(self._scalar_set):
            self._scalar_written = self._scalar_set
        values = command.positions
        # Every joint given a finite position (the usual cycle): what the loop below does. A
        # finite sum of squares says every value is finite (one that overflows takes the loop,
        # which gives the same; a dot product costs a third of a numpy reduction); ufuncs
        # called directly skip numpy's Python-level wrappers (~1 us).
        if (self._position_only and values is not None
                and math.isfinite(values.dot(values))):
            self._held[_POSITION] = values
            self._mode.fill(_POSITION)
            self._same_mode = _POSITION
            np.minimum(np.maximum(values, self._lower), self._upper, out=self._target)
            return
        claimed = np.zeros(len(self.joints), dtype=bool)
        fields = (command.positions, command.velocities, command.accelerations, command.effort)
        for mode, (on, values) in enumerate(zip(self._commanded, fields, strict=True)):
            if not on or values is None:
                continue
            given = np.isfinite(values)
            self._held[mode][given] = values[given]
            take = given & ~claimed
            self._mode[take] = mode
            self._modes_changed()
            if mode == _POSITION:
                self._target[take] = np.clip(values[take], self._lower[take], self._upper[take])
            claimed |= given

    def _deactivate(self, now_ns: int, action: SafeAction) -> None:
        self._advance(now_ns)
        if action is SafeAction.TORQUE_OFF:
            # A drive switched off holds no set point: the next activation starts from the
            # measured state, not from a command issued before someone moved the arm by hand.
            self._held.fill(np.nan)
            self._hold_here(np.ones(len(self.joints), dtype=bool))
        else:
            self._hold_here(self._mode != _POSITION)

    def _scalar_state(self, name: str) -> float:
        return self._scalar_read

    def _set_scalar_command(self, name: str, value: float) -> None:
        self._scalar_set = value

    def _details(self) -> Mapping[str, Any]:
        return {"frozen": self._frozen, "injected_fault": self._fault,
                "speed_scaling_factor": {  # None: not read / not written yet
                    "state": None if math.isnan(self._scalar_read) else self._scalar_read,
                    "command": None if math.isnan(self._scalar_set) else self._scalar_set}}

    # -- physics ------------------------------------------------------------------------------

    def _hold_here(self, which: NDArray[np.bool_]) -> None:
        self._mode[which] = _POSITION
        self._modes_changed()
        self._target[which] = self._p[which]

    def _modes_changed(self) -> None:
        mode = self._mode
        first = int(mode[0])
        self._same_mode = first if (mode == first).all() else None

    def _advance(self, now_ns: int) -> None:
        if self._t_ns is None:
            self._t_ns = now_ns
            return
        dt_ns = now_ns - self._t_ns
        if dt_ns < 0:
            raise HardwareError(
                f"{self._owner()}: time went backwards ({now_ns} ns after {self._t_ns} ns); "
                "pass the loop's monotonic time"
            )
        self._t_ns = now_ns
        if dt_ns == 0 or self._frozen:
            return
        dt = dt_ns / NS_PER_S
        same = self._same_mode
        if same is not None:
            # Every joint driven the same way (the usual case): one step on whole arrays.
            p, v, a = _STEPS[same](self, _ALL, dt)
        else:
            mode = self._mode
            p, v, a = self._p.copy(), self._v.copy(), self._a.copy()
            for m, step in enumerate(_STEPS):
                index = np.flatnonzero(mode == m)
                if index.size:
                    p[index], v[index], a[index] = step(self, index, dt)
        if not self._bounded:
            self._p, self._v, self._a = p, v, a
            return
        over = (p < self._lower) | (p > self._upper)
        if np.count_nonzero(over):  # a third of what ``any()`` costs on a few values
            p = np.clip(p, self._lower, self._upper)
            v[over] = 0.0
            a[over] = 0.0
        self._p, self._v, self._a = p, v, a

    def _position_step(self, i: NDArray[np.intp] | slice, dt: float) -> tuple[F64, F64, F64]:
        if i is _ALL:  # every joint (the usual cycle): the arrays themselves, no views
            p0, v0, target = self._p, self._v, self._target
        else:
            p0, v0, target = self._p[i], self._v[i], self._target[i]
        if not self._speed_limited:
            # What the general case below gives without a speed limit, in fewer operations;
            # with dt and the lag's decay over it as arrays (one per period length, kept): the
            # same values, and an operation between two arrays costs 60 % of one with a float.
            if dt != self._dt:
                n = len(self.joints)
                self._dt = dt
                self._dts = np.full(n, dt)
                self._decay = np.full(n, math.exp(-dt / self._lag_s) if self._lag_s else 0.0)
            dts, decay = self._dts, self._decay
            if i is not _ALL:
                dts, decay = dts[i], decay[i]
            if self._lag_s == 0.0:
                p = target.copy()
            else:
                p = target - (target - p0) * decay
            v = (p - p0) / dts
            return p, v, (v - v0) / dts
        vmax = self._vmax[i]
        error = target - p0
        if self._lag_s == 0.0:
            reach = vmax * dt
            p = np.where(np.abs(error) <= reach, target, p0 + np.clip(error, -reach, reach))
        else:
            tau = self._lag_s
            direction = np.sign(error)
            # Saturated while the lag would ask for more than vmax: |error| > vmax * tau.
            excess = np.maximum(np.abs(error) - vmax * tau, 0.0)
            limited = np.isfinite(vmax)
            t_ramp = np.divide(excess, vmax, out=np.zeros_like(excess), where=limited)
            t1 = np.minimum(dt, t_ramp)
            ramp = np.where(t1 > 0.0, direction * np.where(limited, vmax, 0.0) * t1, 0.0)
            remaining = error - ramp
            p = target - remaining * np.exp(-(dt - t1) / tau)
        v = (p - p0) / dt
        return p, v, (v - v0) / dt

    def _velocity_step(self, i: NDArray[np.intp] | slice, dt: float) -> tuple[F64, F64, F64]:
        vmax = self._vmax[i]
        v = np.clip(self._held[_VELOCITY][i], -vmax, vmax)
        return self._p[i] + v * dt, v, (v - self._v[i]) / dt

    def _acceleration_step(self, i: NDArray[np.intp] | slice, dt: float) -> tuple[F64, F64, F64]:
        vmax = self._vmax[i]
        acc = self._held[_ACCELERATION][i]
        p0 = self._p[i]
        v0 = np.clip(self._v[i], -vmax, vmax)
        p = p0 + v0 * dt + 0.5 * acc * dt * dt
        v = v0 + acc * dt
        a = acc.copy()
        sat = np.flatnonzero(np.abs(v) > vmax)  # only where vmax is finite and acc != 0
        if sat.size:
            limit = np.sign(acc[sat]) * vmax[sat]
            t_sat = (limit - v0[sat]) / acc[sat]  # when the speed limit is reached
            p[sat] = (
                p0[sat] + v0[sat] * t_sat + 0.5 * acc[sat] * t_sat * t_sat
                + limit * (dt - t_sat)
            )
            v[sat] = limit
            a[sat] = 0.0
        return p, v, a

    def _effort_step(self, i: NDArray[np.intp] | slice, dt: float) -> tuple[F64, F64, F64]:
        u = self._held[_EFFORT][i]
        p0, v0 = self._p[i], self._v[i]
        c = self._damping
        if c == 0.0:
            return p0 + v0 * dt + 0.5 * u * dt * dt, v0 + u * dt, u.copy()
        decay = math.exp(-c * dt)
        v_end = u / c
        v = v_end + (v0 - v_end) * decay
        p = p0 + v_end * dt + (v0 - v_end) * (1.0 - decay) / c
        return p, v, u - c * v


_ALL = slice(None)
_STEPS = (
    MirrorHardware._position_step,
    MirrorHardware._velocity_step,
    MirrorHardware._acceleration_step,
    MirrorHardware._effort_step,
)
"""The step of each mode, in the order of ``_POSITION`` ... ``_EFFORT``."""
