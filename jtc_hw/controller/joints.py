"""Joint state and command vectors: float64 arrays in the configured joint order, SI units."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


_FLOAT64 = np.dtype(np.float64)


def _array(values: Sequence[float] | F64 | None) -> F64 | None:
    if values is None or (type(values) is np.ndarray and values.dtype is _FLOAT64):
        return values  # what ``asarray`` would return, without its call (every cycle)
    return np.asarray(values, dtype=np.float64)


def all_finite(values: F64) -> bool:
    """Whether every value is finite. A finite sum of squares says so in one call (the check of
    every cycle); one that is not (a NaN, an infinity, or finite values whose squares overflow)
    is checked value by value. The sum is a dot product: numpy's reductions (``sum``, ``all``)
    pay about 0.6 us of set-up each, a dot product of a few values a third of that."""
    flat = values if values.ndim == 1 else values.ravel()
    return math.isfinite(flat.dot(flat)) or bool(np.isfinite(values).all())


@dataclass(frozen=True, eq=False, init=False)
class JointState:
    """Measured state of the controller's joints.

    Args:
        positions: rad (or m), one per joint, in the configured joint order. Required.
        velocities: rad/s, when the ``velocity`` state interface is configured.
        accelerations: rad/s^2, when the ``acceleration`` state interface is configured.
    """

    positions: F64
    velocities: F64 | None
    accelerations: F64 | None

    def __init__(
        self,
        positions: Sequence[float] | F64,
        velocities: Sequence[float] | F64 | None = None,
        accelerations: Sequence[float] | F64 | None = None,
    ) -> None:
        object.__setattr__(self, "positions", np.asarray(positions, dtype=np.float64)
                           if positions is None else _array(positions))
        object.__setattr__(self, "velocities", _array(velocities))
        object.__setattr__(self, "accelerations", _array(accelerations))


@dataclass(frozen=True, eq=False, init=False)
class JointCommand:
    """Commands for the configured command interfaces.

    A field is ``None`` when its interface is not configured. A ``NaN`` entry means "no value":
    the hardware must not write that joint's interface this cycle (and, read back at
    activation, that the interface holds no command yet).
    """

    positions: F64 | None
    velocities: F64 | None
    accelerations: F64 | None
    effort: F64 | None

    def __init__(
        self,
        positions: Sequence[float] | F64 | None = None,
        velocities: Sequence[float] | F64 | None = None,
        accelerations: Sequence[float] | F64 | None = None,
        effort: Sequence[float] | F64 | None = None,
    ) -> None:
        object.__setattr__(self, "positions", _array(positions))
        object.__setattr__(self, "velocities", _array(velocities))
        object.__setattr__(self, "accelerations", _array(accelerations))
        object.__setattr__(self, "effort", _array(effort))
