"""Speed scaling (upstream section 13): the trajectory time, advancing by the elapsed clock
time times a factor that ramps toward its target within the acceleration limits, and the
reference's samples as the joints move on the clock.

A mixin of :class:`~.controller.JointTrajectoryController`, which sets the state declared
here in its ``__init__`` and calls these methods from ``update`` directly (no indirection).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigurationError
from .config import MAX_SCALING_CEILING, ControllerConfig
from .messages import NS_PER_S
from .trajectory import Trajectory, TrajectorySample


class SpeedScaling:
    """The speed scaling methods of the controller (module docstring)."""

    config: ControllerConfig
    joint_names: tuple[str, ...]
    _n: int
    _lookahead_ns: int
    _ref: Trajectory
    _stop_ref: Trajectory | None
    _tau_ns: int  # the trajectory time, advanced to clock time _wall_ns
    _wall_ns: int
    _scale: float
    _scale_target: float
    _scale_rate: float
    _ramp_target: float
    _resume_scale: float

    def set_speed_scaling(self, factor: float) -> None:
        """Set the speed scaling factor's target: the trajectory time advances by the elapsed
        time times the factor (1: as planned, 0.5: half speed, 0: paused; above 1, where
        ``speed_scaling.max_scaling_factor`` allows it: faster).

        The factor ramps toward the target from the next ``update`` within the acceleration
        limits (:meth:`_ramp`; docs/behaviour.md, "Speed scaling"); velocity and acceleration
        commands and feed-forwards scale with it. It holds across goals; ``activate`` resets it
        to ``speed_scaling.initial_scaling_factor``.

        Example::

            ctrl.set_speed_scaling(0.0)   # pause smoothly
            ctrl.resume_speed_scaling()   # back to the factor before the pause

        Raises:
            ConfigurationError: ``factor`` is not a number in ``[0, max_scaling_factor]``
                (upstream's ``[0, 1]`` by default); the message names the range.
        """
        most = self.config.speed_scaling.max_scaling_factor
        if (
            isinstance(factor, bool)
            or not isinstance(factor, (int, float))
            or not 0.0 <= factor <= most  # False for NaN
        ):
            wider = (
                f"; speed_scaling.max_scaling_factor allows up to {MAX_SCALING_CEILING:g}"
                if most < MAX_SCALING_CEILING
                else ""
            )
            raise ConfigurationError(
                f"the speed scaling factor must be a number in [0, {most:g}] (1: full speed, "
                f"0: pause{wider}), got {factor!r}",
                "factor",
                factor,
            )
        self._scale_target = float(factor)
        if factor > 0.0:
            self._resume_scale = float(factor)

    def resume_speed_scaling(self) -> float:
        """Ramp back to the last non-zero factor set (the one before a pause; initially
        ``initial_scaling_factor``, or 1 if that is 0); returns that target."""
        self._scale_target = self._resume_scale
        return self._resume_scale

    @property
    def speed_scaling_factor(self) -> float:
        """The speed scaling factor in force (it ramps toward :attr:`speed_scaling_target`)."""
        return self._scale

    @property
    def speed_scaling_target(self) -> float:
        """The factor the speed scaling ramps toward (``set_speed_scaling``)."""
        return self._scale_target

    @property
    def trajectory_time_ns(self) -> int:
        """The trajectory time of the last cycle: where the reference is sampled. It equals the
        clock while the factor has been 1 throughout; below 1 it falls behind the clock."""
        return self._tau_ns

    def _traj_time(self, wall_ns: int) -> int:
        """The trajectory time at clock time ``wall_ns``, at the factor in force."""
        elapsed = wall_ns - self._wall_ns
        if elapsed == 0:
            return self._tau_ns
        scale = 1.0 if self._following_stop else self._scale
        return self._tau_ns + (elapsed if scale == 1.0 else round(elapsed * scale))

    @property
    def _following_stop(self) -> bool:
        """Whether the reference is a decelerating stop: it runs on the clock, not slowed by
        the speed scaling factor, so that the joints decelerate at the configured rate from
        the velocity they were measured at, whatever the factor (0 included)."""
        ref = self._stop_ref
        return ref is not None and ref is self._ref

    def _advance(self, now_ns: int) -> int:
        """Move the trajectory time (and the ramping factor) to clock time ``now_ns``."""
        elapsed = now_ns - self._wall_ns
        if elapsed == 0:
            return self._tau_ns
        self._tau_ns = self._traj_time(now_ns)
        self._wall_ns = now_ns
        rate = self._scale_rate
        if rate != 0.0 and elapsed > 0:
            target = self._ramp_target
            scale = self._scale + rate * (elapsed / NS_PER_S)
            # The rate was chosen to land on the target; rounding must not overshoot it.
            if (rate > 0.0 and scale >= target - 1e-12) or (rate < 0.0 and scale <= target + 1e-12):
                scale = target
            self._scale = max(scale, 0.0)
        return self._tau_ns

    def _set_ramp_bounds(self, config: ControllerConfig) -> None:
        """What bounds the factor's ramp: per joint with one, its acceleration limit; a ramp
        time for the joints without (``speed_scaling.ramp_time``, 0: no bound)."""
        limited = [
            i
            for i, j in enumerate(self.joint_names)
            if j in config.limits and config.limits[j].acceleration is not None
        ]
        self._acc_index: NDArray[np.intp] | None = (
            np.array(limited, dtype=np.intp) if limited else None
        )
        self._acc_limit = np.array(
            [config.limits[self.joint_names[i]].acceleration for i in limited], dtype=np.float64
        )
        ramp_time = config.speed_scaling.ramp_time
        self._default_ramp_rate = (
            1.0 / ramp_time if ramp_time > 0.0 and len(limited) < self._n else math.inf
        )

    def _ramp(
        self, ahead: TrajectorySample | None, here: TrajectorySample | None = None
    ) -> None:
        """Choose the factor's rate of change for the coming period (``_scale_rate``): the
        fastest toward the target with ``|ds/dt| <= (A - |a| s^2) / |v|`` for every moving joint
        with an acceleration limit ``A``, at the look-ahead sample ``ahead`` (docs/behaviour.md,
        "Speed scaling"); the ramp time bounds the others. With ``here`` (the sample at the
        cycle's own trajectory time) the larger speed and acceleration of the two count: the
        period's velocity step is taken between them, and a trajectory slowing down (or paused,
        its time standing still) is faster at ``here`` than at ``ahead``.
        """
        scale, target = self._scale, self._scale_target
        if scale == target:
            self._scale_rate = 0.0
            return
        direction = 1.0 if target > scale else -1.0
        self._ramp_target = target
        bound = self._default_ramp_rate
        index = self._acc_index
        if index is not None and ahead is not None:
            speed = np.abs(ahead.velocities[index])
            acc = np.abs(ahead.accelerations[index])
            if here is not None:
                speed = np.maximum(speed, np.abs(here.velocities[index]))
                acc = np.maximum(acc, np.abs(here.accelerations[index]))
            moving = speed > 1e-9
            if moving.any():
                room = self._acc_limit - acc * (scale * scale)
                bound = min(bound, float((np.maximum(room, 0.0)[moving] / speed[moving]).min()))
        period_s = self._lookahead_ns / NS_PER_S
        self._scale_rate = direction * min(bound, abs(target - scale) / period_s)

    def _scaled(self, sample: TrajectorySample) -> TrajectorySample:
        """``sample`` (a reference sample in trajectory time) as the joints move on the clock:
        velocities times the factor, accelerations ``a s^2 + v ds/dt``; positions and effort
        as they are."""
        scale, rate = self._scale, self._scale_rate
        if (scale == 1.0 and rate == 0.0) or self._following_stop:
            return sample
        v = sample.velocities
        return TrajectorySample(
            sample.positions, v * scale, sample.accelerations * (scale * scale) + v * rate,
            sample.effort,
        )
