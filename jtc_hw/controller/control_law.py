"""The control law and the command it writes: forwarded interfaces from the reference one
period ahead, PID on the error measured now (jtc_upstream_behaviour.md section 12), and the
read-back of what the command interfaces hold (``output``, section 16).

A mixin of :class:`~.controller.JointTrajectoryController`, which sets the state declared here.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .joints import F64, JointCommand, all_finite
from .messages import NS_PER_S
from .pid import Pid
from .speed_scaling import SpeedScaling
from .trajectory import TrajectorySample

_POSITION_ONLY = (True, False, False, False)
"""``_cmd_fields`` of a position-only controller."""


class ControlLaw(SpeedScaling):
    """The command methods of the controller (module docstring)."""

    _commanding: bool
    _use_pid: bool
    _pid: Pid
    _ff: F64
    _cmd_pos: bool
    _cmd_vel: bool
    _cmd_acc: bool
    _cmd_eff: bool
    _cmd_fields: tuple[bool, bool, bool, bool]
    _cmd_mask: NDArray[np.bool_] | None
    _last_command_positions: F64
    _last_command_velocities: F64 | None
    _last_command_accelerations: F64 | None
    _output: JointCommand
    _nan: F64

    @property
    def deactivation_command(self) -> JointCommand:
        """What upstream's ``on_deactivate`` writes: 0 to every velocity, acceleration and
        effort command interface, and the position command unchanged (``NaN``: write nothing,
        the device keeps its position target).

        A velocity-commanded joint would otherwise keep turning at its last command until the
        driver's own safe action (or watchdog) stops it. Joints outside a ``command_joints``
        subset get ``NaN`` everywhere: the controller never commands them.
        """
        zeros = np.zeros(self._n)
        if self._cmd_mask is not None:
            zeros[~self._cmd_mask] = np.nan  # joints outside command_joints: write nothing
        return JointCommand(
            self._nan if self._cmd_pos else None,
            zeros if self._cmd_vel else None,
            zeros if self._cmd_acc else None,
            zeros if self._cmd_eff else None,
        )

    def _control(
        self, tau_ns: int, period_ns: int, desired: TrajectorySample, error: F64
    ) -> JointCommand:
        if not self._commanding:
            if self._scale != self._scale_target:
                self._ramp(None)
            return self._nan_command()
        # Upstream (jtc_upstream_behaviour.md section 12): forwarded commands and the
        # closed-loop feed-forward (velocity, and effort for effort-only) come from the sample
        # one period ahead; the PID acts on the error at ``now`` (``desired``). Beyond
        # upstream, speed scaling applies to every interface: the sample's velocity and
        # acceleration are those of the slowed time (``_scaled``), with the factor's rate for
        # the coming period chosen first (``_ramp``).
        ahead = self._ref.sample(tau_ns + self._lookahead_ns)
        if self._scale != self._scale_target or self._scale_rate != 0.0:
            self._ramp(ahead, self._ref.sample(tau_ns))
        ahead = self._scaled(ahead)
        pid_out: F64 | None = None
        if self._use_pid:
            pid_out = self._ff * ahead.velocities + self._pid.compute(
                error[0], error[1], period_ns / NS_PER_S
            )
        position = ahead.positions if self._cmd_pos else None
        velocity = (ahead.velocities if pid_out is None else pid_out) if self._cmd_vel else None
        acceleration = ahead.accelerations if self._cmd_acc else None
        effort = None
        if self._cmd_eff:
            assert pid_out is not None
            effort = pid_out + ahead.effort
        # Upstream's last_commanded_state is the look-ahead sample in every joint (also the
        # ones that are only monitored): open-loop holds start from it.
        self._last_command_positions = ahead.positions
        self._last_command_velocities = ahead.velocities
        self._last_command_accelerations = ahead.accelerations
        mask = self._cmd_mask
        if mask is not None:
            # Commands go to command joints only; NaN ("write nothing") for monitored joints.
            position, velocity, acceleration, effort = (
                None if f is None else np.where(mask, f, np.nan)
                for f in (position, velocity, acceleration, effort)
            )
        command = JointCommand(position, velocity, acceleration, effort)
        self._refresh_output(command)
        return command

    def _nan_command(self) -> JointCommand:
        nan = self._nan
        return JointCommand(*(nan if on else None for on in self._cmd_fields))

    def _refresh_output(self, command: JointCommand) -> None:
        """Upstream's read-back rule for the state's ``output`` (section 16): take ``command``
        only if every configured interface holds a finite value for every command joint.
        Joints that are not command joints read NaN."""
        mask = self._cmd_mask
        fields = (command.positions, command.velocities, command.accelerations, command.effort)
        if (mask is None and self._cmd_fields == _POSITION_ONLY and fields[1] is None
                and fields[2] is None and fields[3] is None):
            # Position commanded on every joint (the usual arm): what the loop below decides,
            # without it.
            values = fields[0]
            if values is not None and values.shape == (self._n,) and all_finite(values):
                self._output = command
            return
        exact = True  # ``command`` has exactly the configured fields, NaN off command joints
        for on, values in zip(self._cmd_fields, fields, strict=True):
            if not on:
                exact = exact and values is None
                continue
            if values is None or values.shape != (self._n,):
                return
            if not all_finite(values if mask is None else values[mask]):
                return
            if mask is not None and not np.isnan(values[~mask]).all():
                exact = False
        if exact:
            self._output = command
            return
        self._output = JointCommand(
            *(
                None if not on or f is None else f if mask is None else np.where(mask, f, np.nan)
                for on, f in zip(self._cmd_fields, fields, strict=True)
            )
        )
