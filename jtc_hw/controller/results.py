"""What one control cycle returns: :class:`UpdateResult`, with the cycle's
:class:`ControllerState` (upstream's ``controller_state``).
"""

from __future__ import annotations

from typing import NamedTuple

from .goals import Event
from .joints import F64, JointCommand, JointState
from .trajectory import TrajectorySample


class ControllerState(NamedTuple):
    """The ``controller_state`` of one cycle (jtc_upstream_behaviour.md section 16).

    Attributes:
        time_ns: the cycle's time.
        reference: the desired state at ``time_ns`` (upstream's ``reference``).
        reference_time_from_start: seconds from the start of the trajectory being followed
            (the command's start time, or when the current hold began) to ``time_ns``.
        feedback: the measured state; velocities only with a velocity state interface,
            accelerations only with an acceleration state interface (else ``None``).
        feedback_time_from_start: seconds of the daemon's clock since that start (with speed
            scaling, ``reference_time_from_start`` is about this times the factor).
        error: ``(3, n)`` desired minus measured position / velocity / acceleration.
        output: what the command interfaces hold, read back with upstream's rule: refreshed
            only in a cycle whose command is finite on every configured command interface of
            every command joint, else the previous value is kept; ``None`` for an interface
            that is not configured, ``NaN`` for joints that are not command joints.
        speed_scaling_factor: the speed scaling factor in force this cycle (upstream's
            ``speed_scaling_factor``).
        speed_scaling_target: the factor it ramps toward (``set_speed_scaling``).
    """

    time_ns: int
    reference: TrajectorySample
    reference_time_from_start: float
    feedback: JointState
    feedback_time_from_start: float
    error: F64
    output: JointCommand
    speed_scaling_factor: float = 1.0
    speed_scaling_target: float = 1.0


class UpdateResult(NamedTuple):
    """What one cycle produced.

    Attributes:
        command: values to write; ``NaN`` entries mean "write nothing".
        events: goal results, feedback and stop notices, in the order they happened
            (including those caused by ``send_goal`` / ``cancel_goal`` since the last cycle).
        desired: the reference at ``now``.
        error: ``(3, n)`` desired minus measured position / velocity / acceleration.
        state: the cycle's controller state (``controller_state`` topic).
    """

    command: JointCommand
    events: tuple[Event, ...]
    desired: TrajectorySample
    error: F64
    state: ControllerState
