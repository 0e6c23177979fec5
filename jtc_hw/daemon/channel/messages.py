"""The typed records the API process and the loop process exchange (see :mod:`.pipe`).

Theory of operation
-------------------
One record per message, a class per kind, matched by its class at the other end (``match``
on the class, as h11 matches its events), never by a string tag or a tuple's length::

    API process                                       loop process
    ---------------------------------------------------------------------------------
    Commit(plan_id, Plan)           -- records -->    swapped in at its next cycle, or
    Request(request_id, op)                           answered Stale; op is one of Cancel,
                                                      Stop, Sim, SetParameters,
                                                      SetSpeedScaling, Rearm, Shutdown
                                    <-- pickles --    Ready, Log, Fault, Exit
                                                      Reference (every change, in order)
                                                      Committed | Stale (per Commit)
                                                      Reply | Failed (per Request)
                                                      Events, State, Status

``State`` and ``Status`` are droppable (the outbox keeps the newest of each class while the
API process lags); every other record is delivered in order. With a cycle ring, the States do
not cross the pipe at all: the API process reads them from the ring (decisions 49). A
request's failure crosses as :class:`Failed`, which keeps the exception's class from the one
tree (``jtc_hw.errors``): the API process raises that class again, no name table in between.

What is written in a cycle (``State``, ``Events``) is a ``NamedTuple``: measured, pickling a
15-field state costs ~2 us more as a ``NamedTuple`` than as a plain tuple, ~6 us more as a
frozen dataclass (docs/benchmarks.md); everything else is a frozen dataclass with
slots. Both keep the positional order of their fields, which ``match`` uses.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, ClassVar, NamedTuple

import numpy as np

from ...controller.config import ControllerConfig
from ...controller.goals import Event
from ...controller.joints import JointCommand
from ...controller.planner import Plan
from ...controller.trajectory import Trajectory
from ...errors import (
    ConfigurationError,
    ControllerStateError,
    GoalRejected,
    HardwareError,
    JtcHwError,
)

__all__ = [
    "Cancel",
    "Commit",
    "Committed",
    "Events",
    "Exit",
    "Failed",
    "Fault",
    "Log",
    "LoopMessage",
    "LoopOp",
    "Ready",
    "Rearm",
    "Reference",
    "Released",
    "Reply",
    "Request",
    "SetParameters",
    "SetSpeedScaling",
    "Shutdown",
    "Sim",
    "Stale",
    "State",
    "Status",
    "Stop",
]


# -- API process -> loop process ---------------------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)
class Commit:
    """Swap in ``plan`` (made against the loop's reference) at the next cycle; answered by
    :class:`Committed` or :class:`Stale` with the same ``plan_id``. Sent in bulk: the
    plan's arrays travel out of band (``pipe.PlanWriter``)."""

    plan_id: int
    plan: Plan


@dataclasses.dataclass(frozen=True, slots=True)
class Cancel:
    """Cancel goal ``goal_id`` if it is executing; the reply says whether it was."""

    name: ClassVar[str] = "cancel"
    goal_id: int


@dataclasses.dataclass(frozen=True, slots=True)
class Stop:
    """End any motion and hold (``GoalRejected`` if the controller is not active)."""

    name: ClassVar[str] = "stop"


@dataclasses.dataclass(frozen=True, slots=True)
class Sim:
    """Freeze or release a simulated component's feedback (``None``: unchanged), or inject
    a latched read fault (``None``: none)."""

    name: ClassVar[str] = "sim"
    component: str
    freeze: bool | None = None
    fault: str | None = None


@dataclasses.dataclass(frozen=True, slots=True)
class SetParameters:
    """Switch the controller to ``config``, which the API process checked."""

    name: ClassVar[str] = "set_parameters"
    config: ControllerConfig


@dataclasses.dataclass(frozen=True, slots=True)
class SetSpeedScaling:
    """Ramp the speed scaling factor to ``factor`` (``None``: resume); the reply is
    ``{"factor": ..., "target": ...}``."""

    name: ClassVar[str] = "set_speed_scaling"
    factor: float | None


@dataclasses.dataclass(frozen=True, slots=True)
class Rearm:
    """Leave a hardware fault; the reply says whether there was one to leave."""

    name: ClassVar[str] = "rearm"


@dataclasses.dataclass(frozen=True, slots=True)
class Shutdown:
    """Finish: the active goal's result, hold, safe action. The reply is ``True`` (the loop
    ends at once) or the longest it keeps cycling for a decelerating stop, seconds."""

    name: ClassVar[str] = "shutdown"
    reason: str | None = None


LoopOp = Cancel | Stop | Sim | SetParameters | SetSpeedScaling | Rearm | Shutdown
"""What a :class:`Request` asks of the loop (``name``: how errors and logs call it)."""


@dataclasses.dataclass(frozen=True, slots=True)
class Request:
    """``op``, answered by :class:`Reply` or :class:`Failed` with the same ``request_id``."""

    request_id: int
    op: LoopOp


# -- loop process -> API process ---------------------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)
class Ready:
    """The hardware is active and the controller holds; the loop cycles from now on."""

    pid: int
    t0_ns: int
    """The activation time: trajectory time equals the clock there."""
    period_ns: int
    hardware: Mapping[str, Any]


@dataclasses.dataclass(frozen=True, slots=True)
class Reference:
    """The controller's reference changed to version ``version``: the plan ``plan_id`` the
    API process made, or (``plan_id`` None) ``trajectory`` itself (a hold, a few bytes)."""

    version: int
    trajectory: Trajectory | None
    plan_id: int | None


@dataclasses.dataclass(frozen=True, slots=True)
class Committed:
    """The plan ``plan_id`` is in force; ``goal_id`` is its goal (None: a topic trajectory)."""

    plan_id: int
    goal_id: int | None


@dataclasses.dataclass(frozen=True, slots=True)
class Stale:
    """The plan ``plan_id`` was refused: ``reason`` (``not active...``: do not plan again)."""

    plan_id: int
    reason: str


@dataclasses.dataclass(frozen=True, slots=True)
class Reply:
    """The request ``request_id`` was done; ``value`` is what its op returns."""

    request_id: int
    value: Any


_ANSWERED_BY_KIND = (ConfigurationError, ControllerStateError, GoalRejected, HardwareError)
"""The error classes the API process answers each in its own way; any other error of the
loop reaches it as a ``HardwareError`` (it came from the loop's devices)."""


@dataclasses.dataclass(frozen=True, slots=True)
class Failed:
    """The request ``request_id`` raised ``kind(text)``, from the one exception tree."""

    request_id: int
    kind: type[JtcHwError]
    text: str

    @classmethod
    def of(cls, request_id: int, exc: JtcHwError) -> Failed:
        """The record of ``exc``, raised while serving ``request_id``."""
        return cls(request_id, type(exc), str(exc))

    def exception(self) -> JtcHwError:
        """The error to raise in the API process, with the loop's text: of the loop's class if
        the API process answers it (``_ANSWERED_BY_KIND``), else a ``HardwareError``."""
        kind = self.kind if issubclass(self.kind, _ANSWERED_BY_KIND) else HardwareError
        return kind(self.text)


@dataclasses.dataclass(frozen=True, slots=True)
class Log:
    """A line for the API process's log (its level, ``logging``'s numbers)."""

    level: int
    text: str


@dataclasses.dataclass(frozen=True, slots=True)
class Fault:
    """A hardware fault stopped the controller: ``reason``. Logged as an error line
    ``hardware fault: <reason>``, recorded, and the flight recorder triggered."""

    reason: str

    @property
    def text(self) -> str:
        """The log line."""
        return f"hardware fault: {self.reason}"


@dataclasses.dataclass(frozen=True, slots=True)
class Released:
    """The loop unmapped these regions of shared memory (their pool's tokens): the API process
    may reuse or free them (``channel.shared``)."""

    tokens: tuple[int, ...]


@dataclasses.dataclass(frozen=True, slots=True)
class Exit:
    """The loop process ends with exit status ``code`` (its last message)."""

    code: int


@dataclasses.dataclass(frozen=True, slots=True)
class Status:
    """The loop's statistics, hardware and controller status (``ControlLoop.status``)."""

    status: dict[str, Any]


class Events(NamedTuple):
    """A cycle's goal events (feedback, results, a topic trajectory's stop), in order."""

    events: tuple[Event, ...]


class State(NamedTuple):
    """The controller's state after one cycle, at ``state_publish_rate``.

    Arrays are per joint in the controller's joint order; ``desired`` stacks position,
    velocity, acceleration and effort ``(4, n)``, ``error`` position, velocity and
    acceleration ``(3, n)``.
    """

    time_ns: int
    desired: Any
    positions: Any
    velocities: Any
    error: Any
    command: JointCommand
    holding: bool
    active_goal: int | None
    reference_time_from_start: float
    feedback_time_from_start: float
    accelerations: Any
    output: JointCommand
    speed_scaling_factor: float
    speed_scaling_target: float
    trajectory_time_ns: int
    """Where trajectory time stands at ``time_ns`` (the API process plans in it)."""

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled with its float64 arrays packed into one buffer: pickling each array costs
        about 4.6 us and a State holds six or more (the loop pickles one per state publish);
        the other process gets the same record, each array its own (writable) values."""
        arrays = [self.desired, self.positions, self.velocities, self.error,
                  self.accelerations]
        for command in (self.command, self.output):
            if not isinstance(command, JointCommand):
                return (State, tuple(self))
            arrays += (command.positions, command.velocities, command.accelerations,
                       command.effort)
        present = []
        for array in arrays:
            if array is None:
                continue
            if type(array) is not np.ndarray or array.dtype != np.float64:
                return (State, tuple(self))
            present.append(array.ravel())
        shapes = tuple(None if array is None else array.shape for array in arrays)
        scalars = (self.time_ns, self.holding, self.active_goal, self.reference_time_from_start,
                   self.feedback_time_from_start, self.speed_scaling_factor,
                   self.speed_scaling_target, self.trajectory_time_ns)
        return (_unpack_state, (scalars, shapes, np.concatenate(present).tobytes()))


def _unpack_state(scalars: tuple[Any, ...], shapes: tuple[tuple[int, ...] | None, ...],
                  data: bytes) -> State:
    """The :class:`State` that ``State.__reduce__`` packed."""
    flat = np.frombuffer(data, dtype=np.float64).copy()
    arrays: list[Any] = []
    at = 0
    for shape in shapes:
        if shape is None:
            arrays.append(None)
            continue
        size = math.prod(shape)
        arrays.append(flat[at:at + size].reshape(shape))
        at += size
    (time_ns, holding, active_goal, reference_tfs, feedback_tfs, factor, target,
     trajectory_time_ns) = scalars
    return State(time_ns, arrays[0], arrays[1], arrays[2], arrays[3],
                 JointCommand(*arrays[5:9]), holding, active_goal, reference_tfs, feedback_tfs,
                 arrays[4], JointCommand(*arrays[9:13]), factor, target, trajectory_time_ns)


LoopMessage = (
    Ready | Reference | Committed | Stale | Reply | Failed | Log | Fault | Exit | Status
    | Events | State | Released
)
"""Every record the loop process sends."""
