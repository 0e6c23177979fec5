"""Per-joint PID, vectorised: ``u = k_p e + k_i sum(e dt) + k_d e_dot`` (feed-forward added by
the controller). The integral contribution ``k_i sum(e dt)`` is clamped to ``+-i_clamp`` as
control_toolbox does, so ``i_clamp = 0`` disables it (``jtc-hw check`` warns about that)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


class Pid:
    """PID state for all joints at once."""

    def __init__(self, p: F64, i: F64, d: F64, i_clamp: F64) -> None:
        self.p = np.asarray(p, dtype=np.float64)
        self.i = np.asarray(i, dtype=np.float64)
        self.d = np.asarray(d, dtype=np.float64)
        self.i_clamp = np.asarray(i_clamp, dtype=np.float64)
        self.i_term = np.zeros_like(self.p)

    def set_gains(self, p: F64, i: F64, d: F64, i_clamp: F64) -> None:
        """New gains from the next ``compute``; the integral is kept (control_toolbox's
        ``set_gains``, which upstream calls when its parameters change)."""
        self.p = np.asarray(p, dtype=np.float64)
        self.i = np.asarray(i, dtype=np.float64)
        self.d = np.asarray(d, dtype=np.float64)
        self.i_clamp = np.asarray(i_clamp, dtype=np.float64)

    def reset(self) -> None:
        """Forget the integral (activation, and entering a hold after cancel or abort)."""
        self.i_term[:] = 0.0

    def compute(self, error: F64, error_dot: F64, dt_s: float) -> F64:
        """One step; ``dt_s`` is the time since the previous step, in seconds.

        Raises:
            ValueError: never for valid arrays; shapes must match the joint count.
        """
        if dt_s > 0.0:
            self.i_term += self.i * error * dt_s
            np.clip(self.i_term, -self.i_clamp, self.i_clamp, out=self.i_term)
        out: F64 = self.p * error + self.i_term + self.d * error_dot
        return out
