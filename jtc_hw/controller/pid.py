"""Per-joint PID, vectorised, with control_toolbox's ``Pid::compute_command`` semantics.

One call with error ``e``, error derivative ``e_dot`` (the velocity error, not a difference
quotient) and step ``dt``, per joint::

    dt == 0                     -> the previous output, nothing changes
    e or e_dot not finite       -> NaN (for that joint), nothing changes
    u_unsat = k_p e + I + k_d e_dot       # I: the integral of the *previous* calls
    u       = clamp(u_unsat, u_min, u_max)
    if |e| > error_deadband:  I += dt k_i e
    I       = clamp(I, i_min, i_max)

So the integral contribution lags one call (the first call after a reset has none), as
upstream's (jtc_upstream_behaviour.md section 12). ``i_clamp`` gives ``i_min = -i_clamp``,
``i_max = +i_clamp``; the output clamp and the deadband are off unless given, and feed-forward
is added by the controller, outside the clamp (docs/behaviour.md, "The PID law").
"""

from __future__ import annotations

import numpy as np

from .interpolation import F64


class Pid:
    """PID state for all joints at once.

    Args:
        p, i, d: gains per joint.
        i_clamp: symmetric bound of the integral term per joint (>= 0).
        u_min, u_max: bounds of the PID output (without feed-forward); default unbounded.
        error_deadband: integration stops while ``|e| <= error_deadband``; default 0, so only
            an exact zero error stops it.
    """

    def __init__(
        self,
        p: F64,
        i: F64,
        d: F64,
        i_clamp: F64,
        *,
        u_min: F64 | float = -np.inf,
        u_max: F64 | float = np.inf,
        error_deadband: F64 | float = 0.0,
    ) -> None:
        self.set_gains(p, i, d, i_clamp)
        self.u_min = np.broadcast_to(np.asarray(u_min, dtype=np.float64), self.p.shape)
        self.u_max = np.broadcast_to(np.asarray(u_max, dtype=np.float64), self.p.shape)
        self.error_deadband = np.broadcast_to(
            np.asarray(error_deadband, dtype=np.float64), self.p.shape
        )
        self.i_term = np.zeros_like(self.p)
        self.output = np.zeros_like(self.p)
        self._clamps_output = bool(np.isfinite(self.u_min).any() or np.isfinite(self.u_max).any())
        self._deadband = bool((self.error_deadband != 0.0).any())

    def set_gains(self, p: F64, i: F64, d: F64, i_clamp: F64) -> None:
        """New gains from the next ``compute``; the integral is kept (control_toolbox's
        ``set_gains``, which upstream calls when its parameters change)."""
        self.p, self.i, self.d, self.i_clamp = (
            np.asarray(gains, dtype=np.float64) for gains in (p, i, d, i_clamp))

    def reset(self) -> None:
        """Forget the integral and the previous output (activation, and entering a hold after
        cancel or abort)."""
        self.i_term[:] = 0.0
        self.output[:] = 0.0

    def compute(self, error: F64, error_dot: F64, dt_s: float) -> F64:
        """One step; ``dt_s`` is the time since the previous step, in seconds; the arrays
        have one value per joint, as has the output (a new array; NaN where ``error`` or
        ``error_dot`` is not finite)."""
        if dt_s == 0.0:
            # control_toolbox: no time has passed, so nothing is integrated and the command
            # is the previous one.
            out: F64 = self.output.copy()
            return out
        u: F64 = self.p * error + self.i_term + self.d * error_dot
        if np.isfinite(u).all():
            # Every input finite (a non-finite e or e_dot makes u non-finite, whatever the
            # gains): the common case, without per-joint masks.
            if self._clamps_output:
                np.clip(u, self.u_min, self.u_max, out=u)
            if self._deadband:
                outside = np.abs(error) > self.error_deadband
                self.i_term += np.where(outside, dt_s * self.i * error, 0.0)
            else:
                # |e| > 0: a zero error would add zero anyway.
                self.i_term += dt_s * self.i * error
            np.clip(self.i_term, -self.i_clamp, self.i_clamp, out=self.i_term)
            self.output[:] = u
            return u
        finite = np.isfinite(error) & np.isfinite(error_dot)
        # A non-finite input gives NaN for that joint and leaves its state alone; the other
        # joints are computed as usual (each joint has its own PID upstream).
        e = np.where(finite, error, 0.0)
        e_dot = np.where(finite, error_dot, 0.0)
        u = self.p * e + self.i_term + self.d * e_dot
        np.clip(u, self.u_min, self.u_max, out=u)
        integrate = finite & (np.abs(e) > self.error_deadband)
        self.i_term += np.where(integrate, dt_s * self.i * e, 0.0)
        np.clip(self.i_term, -self.i_clamp, self.i_clamp, out=self.i_term)
        self.output[finite] = u[finite]
        u[~finite] = np.nan
        return u
