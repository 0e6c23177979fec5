"""One exception tree for the whole project.

Every message names the joint, point, key or motor concerned and says what to check.
"""

from __future__ import annotations

from typing import Any


class JtcHwError(Exception):
    """Base of every error raised by jtc_hw."""


class ConfigurationError(JtcHwError, ValueError):
    """A configuration value is missing, mistyped, out of range or a forbidden combination.

    Attributes:
        path: dotted key path of the offending parameter (e.g. ``constraints.joint1.goal``).
        value: the offending value, if any.
    """

    def __init__(self, message: str, path: str = "", value: Any = None) -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path
        self.value = value


class GoalRejected(JtcHwError, ValueError):
    """A goal or trajectory was refused; nothing about the running motion changed.

    Attributes:
        reason: human-readable reason naming the joint / point / value.
        error_code: the FollowJointTrajectory result code that fits the reason
            (``-1`` INVALID_GOAL, ``-2`` INVALID_JOINTS, ``-3`` OLD_HEADER_TIMESTAMP).
    """

    def __init__(self, reason: str, error_code: int = -1) -> None:
        super().__init__(reason)
        self.reason = reason
        self.error_code = error_code


class ControllerStateError(JtcHwError, RuntimeError):
    """A controller method was called in a lifecycle state that does not allow it."""


class StalePlan(JtcHwError):
    """A planned command no longer fits: the reference changed, or its time has passed.

    Raised by ``JointTrajectoryController.commit``; plan again against the current reference.
    """


class ProtocolError(JtcHwError):
    """A message on a wire (socket, serial, CAN) could not be decoded."""


class HardwareError(JtcHwError):
    """The hardware could not do what was asked."""


class CommunicationError(HardwareError):
    """A device did not answer, or answered garbage."""


class MotorFault(HardwareError):
    """A motor reported a fault (overload, overheating, ...)."""


def add_note(exc: BaseException, note: str) -> None:
    """``exc.add_note(note)``: Python 3.11's, or the same ``__notes__`` list on 3.10 (which
    stores it for the log and for code that reads it, but does not print it in tracebacks).
    """
    adder = getattr(exc, "add_note", None)
    if adder is not None:
        adder(note)
        return
    notes = getattr(exc, "__notes__", None)
    exc.__notes__ = [*(notes or ()), note]  # type: ignore[attr-defined]  # 3.11's attribute
