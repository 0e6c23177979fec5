"""Joint units <-> the servos' register counts, per joint, the same factors both ways.

Theory of operation
-------------------
For joint *i* with model resolution ``ticks_per_rev``, ``direction`` d (+1 / -1),
``gear_ratio`` g (motor turns per joint turn) and ``offset`` o (rad)::

    motor_rad   = ticks * 2*pi / ticks_per_rev          (tick 0 is 0 rad; mid-range 2048 is pi)
    joint       = d * motor_rad / g + o
    ticks       = round(d * (joint - o) * g * ticks_per_rev / (2*pi))
    joint_vel   = d * raw_velocity * velocity_unit / g   (velocity_unit = 0.229 rev/min in rad/s)
    raw_velocity= round(d * joint_vel * g / velocity_unit)
    joint_effort= d * raw_current * current_unit * torque_constant * g
    raw_current = round(d * joint_effort / (torque_constant * g * current_unit))

The same per-joint factors are used both ways, so ``ticks -> joint -> ticks`` is the identity.
They are computed once: the hot path is then one multiply (and one add for positions) per
direction for all joints at once. No I/O: the hardware (:mod:`.hardware`) reads and writes the
counts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .control_table import Model

__all__ = ["JointUnits"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class JointUnits:
    """The conversions of the joints of one bus (see the module docstring).

    Args:
        models: each joint's servo model.
        direction: each joint's direction, +1 or -1.
        gear_ratio: each joint's motor turns per joint turn.
        offset: each joint's position at motor angle 0, rad.

    Attributes:
        gear: the gear ratios, as an array.
        offset: the offsets, rad, as an array.
        pos_scale, vel_scale, effort_scale: joint units per register count (position, velocity,
            current).
        pos_inverse, vel_inverse, effort_inverse: register counts per joint unit (0 for the
            effort of a model without current sensing).
    """

    def __init__(
        self,
        models: Sequence[Model],
        direction: Sequence[float],
        gear_ratio: Sequence[float],
        offset: Sequence[float],
    ) -> None:
        d = np.array(direction, dtype=np.float64)
        g = np.array(gear_ratio, dtype=np.float64)
        self.gear: F64 = g
        self.offset: F64 = np.array(offset, dtype=np.float64)
        # Motor-side units of one count, per joint.
        rad_per_tick = np.array([2.0 * math.pi / m.ticks_per_rev for m in models])
        rad_s_per_count = np.array([m.velocity_unit_rad_s for m in models])
        nm_per_count = np.array([
            (m.current_unit_a or 0.0) * (m.torque_constant_nm_per_a or 0.0) for m in models
        ])
        self.pos_scale: F64 = d * rad_per_tick / g
        self.pos_inverse: F64 = d * g / rad_per_tick
        self.vel_scale: F64 = d * rad_s_per_count / g
        self.vel_inverse: F64 = d * g / rad_s_per_count
        self.effort_scale: F64 = d * nm_per_count * g
        sensing = nm_per_count > 0
        self.effort_inverse: F64 = np.where(
            sensing, d / (g * np.where(sensing, nm_per_count, 1.0)), 0.0)

    def ticks_to_joint(self, ticks: NDArray[Any]) -> F64:
        """Present Position ticks -> joint positions, rad."""
        result: F64 = np.asarray(ticks) * self.pos_scale + self.offset
        return result

    def joint_to_ticks_float(self, joint: NDArray[Any]) -> F64:
        """Joint positions, rad -> ticks, unrounded (infinite stays infinite)."""
        result: F64 = (np.asarray(joint, dtype=np.float64) - self.offset) * self.pos_inverse
        return result

    def joint_to_ticks(self, joint: NDArray[Any]) -> I64:
        """Joint positions, rad -> ticks, rounded to the nearest (the inverse of
        :meth:`ticks_to_joint` on whole ticks)."""
        result: I64 = np.rint(self.joint_to_ticks_float(joint)).astype(np.int64)
        return result

    def velocity_to_joint(self, raw: NDArray[Any]) -> F64:
        """Velocity register counts -> joint velocities, rad/s."""
        result: F64 = np.asarray(raw) * self.vel_scale
        return result

    def joint_to_velocity(self, joint_vel: NDArray[Any]) -> I64:
        """Joint velocities, rad/s -> velocity register counts (rounded)."""
        result: I64 = np.rint(np.asarray(joint_vel) * self.vel_inverse).astype(np.int64)
        return result

    def current_to_joint(self, raw: NDArray[Any]) -> F64:
        """Current register counts -> joint efforts, N*m (torque constant times gear ratio)."""
        result: F64 = np.asarray(raw) * self.effort_scale
        return result

    def joint_to_current(self, effort: NDArray[Any]) -> I64:
        """Joint efforts, N*m -> current register counts (rounded; 0 without current sensing)."""
        result: I64 = np.rint(np.asarray(effort) * self.effort_inverse).astype(np.int64)
        return result
