"""The trajectory command messages: points, ``JointTrajectory`` and its prepared form.

A ``JointTrajectory`` is what a client sends (``trajectory_msgs/JointTrajectory``): joint names,
points with ``time_from_start``, and a start time (the header stamp; 0 means "start now").
``PreparedTrajectory`` is one validated by :mod:`.validation`, in the controller's joint order;
:mod:`.trajectory` splices it into the reference.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, overload

import numpy as np
from numpy.typing import NDArray

from .interpolation import F64

NS_PER_S = 1_000_000_000


def seconds_to_ns(seconds: float) -> int:
    """Convert seconds to integer nanoseconds, rounding to the nearest nanosecond.

    Raises:
        ValueError: ``seconds`` is not a finite number.
    """
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)):
        raise ValueError(f"expected a number of seconds, got {seconds!r}")
    if not math.isfinite(seconds):
        raise ValueError(f"expected a finite number of seconds, got {seconds!r}")
    if isinstance(seconds, int):
        return seconds * NS_PER_S
    return round(seconds * NS_PER_S)


Values = Sequence[float] | NDArray[np.floating[Any]]
"""A joint vector as accepted from users: a sequence of floats or a float numpy array."""


def _field(values: Values | None) -> tuple[float, ...] | None:
    if values is None:
        return None
    out = tuple(values)
    return out if out else None


@dataclass(frozen=True, init=False)
class TrajectoryPoint:
    """One waypoint (``trajectory_msgs/JointTrajectoryPoint``).

    Fields that are absent (``None`` or empty) are not used; which ones are present selects the
    interpolation (see ``Trajectory``). Values are in SI units in the order of the trajectory's
    ``joint_names``. Content is checked by the controller, not here.

    Args:
        time_from_start: seconds after the trajectory's start time (``time_from_start_ns`` gives
            it in integer nanoseconds instead).
    """

    time_from_start_ns: int
    positions: tuple[float, ...] | None
    velocities: tuple[float, ...] | None
    accelerations: tuple[float, ...] | None
    effort: tuple[float, ...] | None

    def __init__(
        self,
        time_from_start: float | None = None,
        positions: Values | None = None,
        velocities: Values | None = None,
        accelerations: Values | None = None,
        effort: Values | None = None,
        *,
        time_from_start_ns: int | None = None,
    ) -> None:
        if time_from_start_ns is None:
            time_from_start_ns = 0 if time_from_start is None else seconds_to_ns(time_from_start)
        object.__setattr__(self, "time_from_start_ns", int(time_from_start_ns))
        object.__setattr__(self, "positions", _field(positions))
        object.__setattr__(self, "velocities", _field(velocities))
        object.__setattr__(self, "accelerations", _field(accelerations))
        object.__setattr__(self, "effort", _field(effort))

    @property
    def time_from_start(self) -> float:
        """``time_from_start`` in seconds."""
        return self.time_from_start_ns / NS_PER_S


FIELDS = ("positions", "velocities", "accelerations", "effort")
"""The value fields of a point, in message order."""


class PointColumns(Sequence[TrajectoryPoint]):
    """A trajectory's points as arrays, one row per point (what a parser of many points builds).

    It is the sequence of ``TrajectoryPoint`` it stands for -- indexing builds a point on
    demand, equality is the points' -- so it can be a ``JointTrajectory``'s ``points``; the
    controller validates and fits the arrays as a whole, without a Python object per point.

    Args:
        times_ns: ``(m,)`` each point's ``time_from_start`` in integer nanoseconds.
        positions, velocities, accelerations, effort: ``(m, k)`` arrays in the order of the
            trajectory's ``joint_names``, or None where no point carries the field.
        present: for fields given, ``(m,)`` bools saying which points carry them (default:
            every point); the rows of the other points are not used.

    Raises:
        ValueError: the arrays' shapes do not agree.
    """

    __slots__ = ("times_ns", "_values", "_present")

    def __init__(
        self,
        times_ns: Sequence[int] | NDArray[np.integer[Any]],
        positions: NDArray[np.floating[Any]] | None = None,
        velocities: NDArray[np.floating[Any]] | None = None,
        accelerations: NDArray[np.floating[Any]] | None = None,
        effort: NDArray[np.floating[Any]] | None = None,
        present: dict[str, NDArray[np.bool_]] | None = None,
    ) -> None:
        times = np.array(times_ns, dtype=np.int64)
        if times.ndim != 1:
            raise ValueError(f"times_ns must be one-dimensional, got shape {times.shape}")
        m = times.shape[0]
        times.setflags(write=False)
        self.times_ns: NDArray[np.int64] = times
        self._values: dict[str, F64] = {}
        self._present: dict[str, NDArray[np.bool_]] = {}
        given = dict(zip(FIELDS, (positions, velocities, accelerations, effort), strict=True))
        for name, values in given.items():
            if values is None:
                continue
            array = np.array(values, dtype=np.float64)
            if array.ndim != 2 or array.shape[0] != m:
                raise ValueError(f"{name} must have shape ({m}, joints), got {array.shape}")
            mask = np.ones(m, dtype=bool)
            if present is not None and name in present:
                mask = np.array(present[name], dtype=bool)
                if mask.shape != (m,):
                    raise ValueError(f"present[{name!r}] must have shape ({m},)")
            array.setflags(write=False)
            mask.setflags(write=False)
            self._values[name] = array
            self._present[name] = mask
        unknown = set(present or ()) - set(self._values)
        if unknown:
            raise ValueError(f"present names fields without values: {sorted(unknown)}")

    def values(self, name: str) -> tuple[F64, NDArray[np.bool_]] | None:
        """A field's ``(m, k)`` values and ``(m,)`` presence, or None if no point carries it."""
        if name not in self._values:
            return None
        return self._values[name], self._present[name]

    def __len__(self) -> int:
        return int(self.times_ns.shape[0])

    def _point(self, i: int) -> TrajectoryPoint:
        row = [
            tuple(self._values[name][i].tolist())
            if name in self._values and self._present[name][i]
            else None
            for name in FIELDS
        ]
        return TrajectoryPoint(None, *row, time_from_start_ns=int(self.times_ns[i]))

    @overload
    def __getitem__(self, index: int) -> TrajectoryPoint: ...

    @overload
    def __getitem__(self, index: slice) -> tuple[TrajectoryPoint, ...]: ...

    def __getitem__(self, index: int | slice) -> TrajectoryPoint | tuple[TrajectoryPoint, ...]:
        if isinstance(index, slice):
            return tuple(self._point(i) for i in range(len(self))[index])
        m = len(self)
        if not -m <= index < m:
            raise IndexError(f"point index {index} out of range for {m} point(s)")
        return self._point(index % m)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, str):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other, strict=True))

    def __hash__(self) -> int:
        return hash(tuple(self))

    def __repr__(self) -> str:
        return f"PointColumns({len(self)} point(s), fields {', '.join(self._values) or 'none'})"


@dataclass(frozen=True, init=False)
class JointTrajectory:
    """A trajectory command (``trajectory_msgs/JointTrajectory``).

    Args:
        joint_names: names of the joints the point values refer to, in that order.
        points: the waypoints (a ``PointColumns`` is kept as it is).
        start_time_ns: the header stamp, on the controller's clock, in nanoseconds; 0 means
            "start now" (when the controller receives it).
    """

    joint_names: tuple[str, ...]
    points: tuple[TrajectoryPoint, ...] | PointColumns
    start_time_ns: int

    def __init__(
        self,
        joint_names: Sequence[str],
        points: Sequence[TrajectoryPoint],
        start_time_ns: int = 0,
    ) -> None:
        object.__setattr__(self, "joint_names", tuple(joint_names))
        if not isinstance(points, PointColumns):
            points = tuple(points)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "start_time_ns", int(start_time_ns))


@dataclass(frozen=True)
class PreparedTrajectory:
    """A validated trajectory in the controller's joint indexing (built by ``validation``).

    Arrays of one row per point: ``times_ns`` (int64, strictly increasing), the four fields
    ``(m, k)`` with ``NaN`` rows where a point lacks the field, and ``has_*`` (bool) saying
    which fields each point carries.
    """

    joint_indices: NDArray[np.intp]
    start_time_ns: int
    times_ns: NDArray[np.int64]
    positions: F64
    velocities: F64
    accelerations: F64
    effort: F64
    has_positions: NDArray[np.bool_]
    has_velocities: NDArray[np.bool_]
    has_accelerations: NDArray[np.bool_]
    has_effort: NDArray[np.bool_]
