"""Motor physics shared by the emulators: a rigid joint driven by a torque, and the servo loops
that real drives close around it.

Theory of operation
-------------------
A :class:`Motor` is one joint, on the output side of its gearbox, in SI units: position (rad),
velocity (rad/s), the torque that acts on it (N*m). Its dynamics are::

    inertia * dv/dt = torque - damping * v - friction * sign(v)

integrated with semi-implicit Euler in sub-steps of at most :attr:`MotorParams.max_step_s` so that
the stiff servo loops below stay stable whatever interval the emulator advances by. A torque is
clamped to ``torque_limit``; the velocity to ``velocity_limit`` (the motor's no-load speed).

Drives close loops around the joint; each ``step_*`` method advances the joint by ``dt_s`` in one
operating mode:

- :meth:`Motor.step_torque`: current / torque mode (the command is the torque).
- :meth:`Motor.step_velocity`: velocity mode, an acceleration-limited velocity reference
  tracked by a proportional-integral loop.
- :meth:`Motor.step_position`: position mode, a reference that moves toward the goal within a
  velocity / acceleration profile (``0`` or ``inf``: no limit, the reference jumps), tracked by a
  critically damped PD loop of bandwidth ``servo_bandwidth_hz`` (Dynamixel's profile, CiA 402's
  cyclic synchronous position).
- :meth:`Motor.step_pd`: the MIT mini-cheetah law ``kp*(p_des-p) + kd*(v_des-v) + t_ff``.

Everything here is pure computation; time is a parameter (no clock is read).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Motor", "MotorParams"]


@dataclass(frozen=True)
class MotorParams:
    """Physical parameters of one joint (output side of the gearbox).

    Attributes:
        inertia: reflected inertia, kg*m^2 (> 0).
        damping: viscous friction, N*m*s/rad.
        friction: Coulomb friction, N*m.
        torque_limit: the largest torque the drive applies, N*m.
        velocity_limit: no-load speed, rad/s.
        servo_bandwidth_hz: bandwidth of the drive's position / velocity loops, Hz.
        max_step_s: the longest integration sub-step, s.
    """

    inertia: float = 0.005
    damping: float = 0.05
    friction: float = 0.0
    torque_limit: float = 4.0
    velocity_limit: float = 8.0
    servo_bandwidth_hz: float = 40.0
    max_step_s: float = 0.0002

    def __post_init__(self) -> None:
        if not self.inertia > 0.0:
            raise ValueError(f"inertia must be > 0, got {self.inertia!r}")
        for name in ("damping", "friction", "torque_limit", "velocity_limit"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not self.servo_bandwidth_hz > 0.0 or not self.max_step_s > 0.0:
            raise ValueError("servo_bandwidth_hz and max_step_s must be > 0")


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


class Motor:
    """One simulated joint (see the module docstring).

    Args:
        params: physical parameters.
        position: initial position, rad.

    Attributes:
        position: rad.
        velocity: rad/s.
        torque: torque applied during the last sub-step (after clamping), N*m.
        reference: the position mode's profiled reference, rad (follows the position otherwise).
    """

    def __init__(self, params: MotorParams | None = None, position: float = 0.0) -> None:
        self.params = params or MotorParams()
        self.position = float(position)
        self.velocity = 0.0
        self.torque = 0.0
        self.reference = float(position)
        self._reference_velocity = 0.0
        self._integral = 0.0
        w = 2.0 * math.pi * self.params.servo_bandwidth_hz
        self._kp = self.params.inertia * w * w
        self._kd = 2.0 * self.params.inertia * w
        self._ki_velocity = self._kp
        self._kp_velocity = self._kd

    def reset_reference(self) -> None:
        """Make the position mode's reference start from here, at rest (e.g. on torque on)."""
        self.reference = self.position
        self._reference_velocity = 0.0
        self._integral = 0.0

    # -- integration ------------------------------------------------------------------------

    def _substeps(self, dt_s: float) -> tuple[int, float]:
        if dt_s <= 0.0:
            return 0, 0.0
        n = max(1, math.ceil(dt_s / self.params.max_step_s))
        return n, dt_s / n

    def _integrate(self, h: float, torque: float) -> None:
        p = self.params
        torque = _clamp(torque, p.torque_limit)
        self.torque = torque
        net = torque - p.damping * self.velocity
        if p.friction > 0.0:
            if self.velocity != 0.0:
                net -= math.copysign(p.friction, self.velocity)
            elif abs(net) <= p.friction:
                net = 0.0  # static friction holds the joint
            else:
                net -= math.copysign(p.friction, net)
        v = self.velocity + h * net / p.inertia
        if p.friction > 0.0 and self.velocity != 0.0 and v * self.velocity < 0.0:
            v = 0.0  # friction stops the joint, it does not reverse it
        self.velocity = _clamp(v, p.velocity_limit)
        self.position += h * self.velocity

    # -- operating modes --------------------------------------------------------------------

    def coast(self, dt_s: float) -> None:
        """Torque off: the joint coasts (friction and damping slow it down)."""
        self.step_torque(dt_s, 0.0)

    def step_torque(self, dt_s: float, torque: float) -> None:
        """Current / torque mode: apply ``torque`` (N*m, clamped) for ``dt_s`` seconds."""
        n, h = self._substeps(dt_s)
        for _ in range(n):
            self._integrate(h, torque)
        self.reference = self.position

    def step_pd(
        self, dt_s: float, p_des: float, v_des: float, kp: float, kd: float, t_ff: float
    ) -> None:
        """MIT mode: ``torque = kp*(p_des - p) + kd*(v_des - v) + t_ff`` for ``dt_s`` seconds."""
        n, h = self._substeps(dt_s)
        for _ in range(n):
            self._integrate(h, kp * (p_des - self.position) + kd * (v_des - self.velocity) + t_ff)
        self.reference = self.position

    def step_velocity(self, dt_s: float, target: float, max_acceleration: float = 0.0) -> None:
        """Velocity mode: track ``target`` (rad/s), ramped at ``max_acceleration`` (0: no ramp)."""
        n, h = self._substeps(dt_s)
        target = _clamp(target, self.params.velocity_limit)
        for _ in range(n):
            ref = self._reference_velocity
            if max_acceleration > 0.0 and math.isfinite(max_acceleration):
                step = max_acceleration * h
                ref += _clamp(target - ref, step)
            else:
                ref = target
            self._reference_velocity = ref
            error = ref - self.velocity
            self._integral = _clamp(
                self._integral + error * h, self.params.torque_limit / max(self._ki_velocity, 1e-9)
            )
            self._integrate(h, self._kp_velocity * error + self._ki_velocity * self._integral)
        self.reference = self.position

    def step_position(
        self,
        dt_s: float,
        goal: float,
        profile_velocity: float = 0.0,
        profile_acceleration: float = 0.0,
        velocity_feedforward: float = 0.0,
    ) -> None:
        """Position mode: move the reference toward ``goal`` within the profile, and track it.

        Args:
            dt_s: interval, s.
            goal: goal position, rad.
            profile_velocity: the profile's speed limit, rad/s (0 or inf: none).
            profile_acceleration: the profile's acceleration limit, rad/s^2 (0 or inf: none).
            velocity_feedforward: velocity added to the reference's (CiA 402's velocity
                offset), rad/s; used only when the profile has no speed limit.
        """
        n, h = self._substeps(dt_s)
        vmax = profile_velocity if 0.0 < profile_velocity < math.inf else math.inf
        amax = profile_acceleration if 0.0 < profile_acceleration < math.inf else math.inf
        unlimited = math.isinf(vmax) and math.isinf(amax)
        if unlimited and n:
            # No profile: the reference moves to the goal evenly over the interval, as a drive
            # interpolating between cyclic set-points does.
            ramp_v = (goal - self.reference) / dt_s
        for _ in range(n):
            ref, ref_v = self.reference, self._reference_velocity
            if unlimited:
                ref_v = velocity_feedforward or ramp_v
                ref += ramp_v * h
            else:
                distance = goal - ref
                # Fastest speed from which the profile can still stop at the goal.
                stop_v = math.sqrt(2.0 * amax * abs(distance)) if math.isfinite(amax) else math.inf
                want = math.copysign(min(vmax, stop_v, abs(distance) / h), distance)
                if math.isfinite(amax):
                    want = ref_v + _clamp(want - ref_v, amax * h)
                ref_v = want
                ref += ref_v * h
            self.reference, self._reference_velocity = ref, ref_v
            torque = self._kp * (ref - self.position) + self._kd * (ref_v - self.velocity)
            self._integrate(h, torque)
