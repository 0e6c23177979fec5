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
    _scale_jump: bool  # the rate's target is reached in one step: nothing bounds the ramp
    _resume_scale: float
    _scale_request: float  # what set_speed_scaling asked: the command interface's value
    _commanding: bool

    def set_speed_scaling(self, factor: float) -> None:
        """Set the speed scaling factor's target: the trajectory time advances by the elapsed
        time times the factor (1: as planned, 0.5: half speed, 0: paused; above 1, where
        ``speed_scaling.max_scaling_factor`` allows it: faster).

        As upstream, the next ``update`` is the first at the new factor: it reports it, its
        trajectory time advances by the period times it, and its velocity commands are scaled
        by it. With a ramp (beyond upstream: acceleration limits, ``speed_scaling.ramp_time``;
        :meth:`_ramp`, docs/behaviour.md, "Speed scaling") that update takes the ramp's first
        step, and the factor reaches the target in the steps that follow; with neither (or
        ``ramp_time: 0`` and no limited joint moving) it is the target at once. Velocity and
        acceleration commands and feed-forwards scale with it. It holds across goals;
        ``activate`` resets it to ``speed_scaling.initial_scaling_factor``.

        Example::

            ctrl.set_speed_scaling(0.0)   # pause smoothly
            ctrl.resume_speed_scaling()   # back to the factor before the pause

        With ``speed_scaling.state_interface`` the hardware's factor is the target, read each
        cycle (:meth:`set_speed_scaling_state`): this only asks for ``factor`` through
        ``speed_scaling.command_interface`` (:attr:`speed_scaling_request`), and the factor
        changes when the hardware's does.

        Raises:
            ConfigurationError: ``factor`` is not a number in ``[0, max_scaling_factor]``
                (upstream's ``[0, 1]`` by default); the message names the range. Or the factor
                is read from a state interface and there is no command interface to ask the
                hardware for another.
        """
        self._check_requestable()
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
        self._request(float(factor))
        if factor > 0.0:
            self._resume_scale = float(factor)

    def resume_speed_scaling(self) -> float:
        """Ramp back to the last non-zero factor set (the one before a pause; initially
        ``initial_scaling_factor``, or 1 if that is 0); returns that target. Raises as
        :meth:`set_speed_scaling` does without a command interface to ask the hardware."""
        self._check_requestable()
        self._request(self._resume_scale)
        return self._resume_scale

    def set_speed_scaling_state(self, factor: float) -> None:
        """The factor the hardware's ``speed_scaling.state_interface`` reads this cycle (a
        speed slider, a safety controller's reduced mode): the target from the next
        ``update`` on, as from :meth:`set_speed_scaling` (upstream reads it first thing in
        ``update``; the ramp applies as to any target). The loop calls it each cycle between
        ``read`` and ``update``. A value that is not a finite number >= 0 (a device that did
        not report it) is ignored: the target stays; above ``max_scaling_factor`` it is that
        bound (docs/behaviour.md, "Speed scaling")."""
        if not 0.0 <= factor < math.inf:  # False for NaN
            return
        factor = min(float(factor), self.config.speed_scaling.max_scaling_factor)
        if factor != self._scale_target:
            self._scale_target = factor
            self._plan_ramp()

    @property
    def speed_scaling_request(self) -> float:
        """The factor asked for (:meth:`set_speed_scaling`, :meth:`resume_speed_scaling`;
        ``initial_scaling_factor`` at activation): what the loop writes to
        ``speed_scaling.command_interface`` each cycle (upstream's ``scaling_factor_cmd``).
        Without a state interface it is also the target."""
        return self._scale_request

    def _check_requestable(self) -> None:
        scaling = self.config.speed_scaling
        if scaling.state_interface and not scaling.command_interface:
            raise ConfigurationError(
                f"the speed scaling factor is read from the hardware's "
                f"{scaling.state_interface!r} each cycle and no "
                "speed_scaling.command_interface is configured to ask it for another; change "
                "it on the robot (its speed slider), or configure a command interface",
                "speed_scaling.state_interface",
                scaling.state_interface,
            )

    def _request(self, factor: float) -> None:
        self._scale_request = factor
        if not self.config.speed_scaling.state_interface:
            self._scale_target = factor
            self._plan_ramp()

    @property
    def speed_scaling_factor(self) -> float:
        """The speed scaling factor in force (it ramps toward :attr:`speed_scaling_target`)."""
        return self._scale

    @property
    def speed_scaling_target(self) -> float:
        """The factor the speed scaling ramps toward (``set_speed_scaling``, or the hardware's
        with a state interface: :meth:`set_speed_scaling_state`)."""
        return self._scale_target

    @property
    def trajectory_time_ns(self) -> int:
        """The trajectory time of the last cycle: where the reference is sampled. It equals the
        clock while the factor has been 1 throughout; below 1 it falls behind the clock."""
        return self._tau_ns

    def _traj_time(self, wall_ns: int) -> int:
        """The trajectory time an ``update`` at clock time ``wall_ns`` will reach: the elapsed
        time times the factor that update will have (:meth:`_next_scale`)."""
        elapsed = wall_ns - self._wall_ns
        if elapsed == 0:
            return self._tau_ns
        scale = 1.0 if self._following_stop else self._next_scale(elapsed)
        return self._tau_ns + (elapsed if scale == 1.0 else round(elapsed * scale))

    def _next_scale(self, elapsed_ns: int) -> float:
        """The factor of an ``update`` ``elapsed_ns`` after the last one: the factor in force
        moved by the ramp's rate over the elapsed time (upstream: the factor set before an
        update is the one it advances by), landing on the ramp's target, not past it; the
        target itself when nothing bounds the ramp (``_scale_jump``: upstream's step)."""
        rate = self._scale_rate
        if rate == 0.0 or elapsed_ns < 0:
            return self._scale
        target = self._ramp_target
        if self._scale_jump:
            return target
        if elapsed_ns == 0:
            return self._scale
        scale = self._scale + rate * (elapsed_ns / NS_PER_S)
        # The rate was chosen to land on the target; rounding must not overshoot it.
        if (rate > 0.0 and scale >= target - 1e-12) or (rate < 0.0 and scale <= target + 1e-12):
            return target
        return max(scale, 0.0)

    @property
    def _following_stop(self) -> bool:
        """Whether the reference is a decelerating stop: it runs on the clock, not slowed by
        the speed scaling factor, so that the joints decelerate at the configured rate from
        the velocity they were measured at, whatever the factor (0 included)."""
        ref = self._stop_ref
        return ref is not None and ref is self._ref

    def _advance(self, now_ns: int) -> int:
        """Move the factor, then the trajectory time, to clock time ``now_ns``: the factor
        first, so that the period just ended advances at the factor this update reports
        (upstream section 7 step 6: ``traj_time += period * scaling``, the scaling read at the
        start of the update)."""
        elapsed = now_ns - self._wall_ns
        if self._scale_rate != 0.0:
            self._scale = self._next_scale(elapsed)
            if self._scale_jump and elapsed >= 0:
                self._scale_rate = 0.0  # a step, not a ramp: no ds/dt in the accelerations
                self._scale_jump = False
        if elapsed == 0:
            return self._tau_ns
        scale = 1.0 if self._following_stop else self._scale
        self._tau_ns += elapsed if scale == 1.0 else round(elapsed * scale)
        self._wall_ns = now_ns
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

        The period's trajectory time advances at the factor its step reaches (upstream: the
        factor read at an update is the one its period advances by), so the reference's own
        ``|a| s^2`` counts at that factor: for a rising factor ``s`` is ``s + |ds/dt| T`` at the
        period's end (:func:`_rate_bound`); a falling one only lowers it.
        """
        scale, target = self._scale, self._scale_target
        self._scale_jump = False
        if scale == target:
            self._scale_rate = 0.0
            return
        direction = 1.0 if target > scale else -1.0
        self._ramp_target = target
        bound = self._default_ramp_rate
        period_s = self._lookahead_ns / NS_PER_S
        index = self._acc_index
        if index is not None and ahead is not None:
            speed = np.abs(ahead.velocities[index])
            acc = np.abs(ahead.accelerations[index])
            if here is not None:
                speed = np.maximum(speed, np.abs(here.velocities[index]))
                acc = np.maximum(acc, np.abs(here.accelerations[index]))
            moving = speed > 1e-9
            if moving.any():
                rising = period_s if direction > 0.0 else 0.0
                bound = min(bound, _rate_bound(
                    self._acc_limit[moving], speed[moving], acc[moving], scale, rising))
        self._scale_rate = direction * min(bound, abs(target - scale) / period_s)
        self._scale_jump = bound == math.inf

    def _plan_ramp(self) -> None:
        """Choose the factor's rate for the period under way, now that its target changed
        between two updates, so that the next ``update`` already takes its step (upstream: a
        factor set between two updates is in force from the next one). The rate is bounded as
        the last ``update`` would have bounded it: at its trajectory time and one look-ahead
        period later (or where a reference installed since begins)."""
        if self._scale == self._scale_target or not self._commanding:
            self._ramp(None)
            return
        # A reference installed since that update (a command committed, a stop) starts later.
        tau = max(self._tau_ns, self._ref.state_before_ns)
        self._ramp(self._ref.sample(tau + self._lookahead_ns), self._ref.sample(tau))

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


def _rate_bound(limit: NDArray[np.float64], speed: NDArray[np.float64],
                acc: NDArray[np.float64], scale: float, rising_s: float) -> float:
    """The largest rate ``r`` with ``|a| (s + r T)^2 + |v| r <= A`` for every joint given (all
    moving; ``T = rising_s``, 0 for a falling factor, where the factor the period ends at is
    below ``s``): the positive root of that quadratic in ``r``, written ``2 c / (b + sqrt(b^2
    + 4 |a| T^2 c))`` with ``c = A - |a| s^2`` and ``b = |v| + 2 |a| s T`` (no cancellation;
    ``c / |v|`` at ``T = 0``). 0 for a joint whose reference alone already uses its whole limit
    at ``s``."""
    room = np.maximum(limit - acc * (scale * scale), 0.0)
    if rising_s == 0.0:
        return float((room / speed).min())
    b = speed + acc * (2.0 * scale * rising_s)
    root = np.sqrt(b * b + acc * (4.0 * rising_s * rising_s) * room)
    return float((2.0 * room / (b + root)).min())
