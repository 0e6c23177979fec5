"""A call to the daemon in flight and how it ends, for every client transport: the pending
request, the exception a failed reply stands for, and the connection error with its codes.
"""

from __future__ import annotations

import threading
from typing import Any

from ..errors import GoalRejected, ProtocolError
from .framing import GOAL_REJECTED, RequestError
from .handles import FeedbackCallback, GoalHandle


class ClientConnectionError(ProtocolError):
    """The connection to the daemon could not be made, or was lost.

    Attributes:
        code: the machine code of the error the daemon sent before closing (``busy``,
            ``unauthorized``), or of the client's own refusal (``untrusted``,
            ``not_expected``, ``permission``), if any.
    """

    def __init__(self, message: str, code: str | None = None) -> None:
        super().__init__(message)
        self.code = code


UNTRUSTED = "untrusted"
"""``ClientConnectionError.code`` of a socket that failed the owner check."""
NOT_EXPECTED = "not_expected"
"""``ClientConnectionError.code`` of a socket served by another process than ``expect_pid``."""
PERMISSION = "permission"
"""``ClientConnectionError.code`` of a unix socket this user may not connect to (its mode, or
a directory on its way, keeps them out: ``EACCES``)."""


class Pending:
    """A request waiting for its reply."""

    __slots__ = ("op", "done", "reply", "error", "on_feedback", "feedback_maxlen", "goal")

    def __init__(self, op: str, on_feedback: FeedbackCallback | None, feedback_maxlen: int):
        self.op = op
        self.done = threading.Event()
        self.reply: dict[str, Any] | None = None
        self.error: Exception | None = None
        self.on_feedback = on_feedback
        self.feedback_maxlen = feedback_maxlen
        self.goal: GoalHandle | None = None


def reply_error(message: dict[str, Any]) -> Exception:
    """The exception a failed reply stands for (``GoalRejected`` or ``RequestError``)."""
    error = message.get("error")
    if not isinstance(error, dict):
        return ProtocolError(f"the daemon sent a failed reply without an error: {message!r:.200}")
    code = str(error.get("code", "internal"))
    text = str(error.get("message", ""))
    error_code = error.get("error_code")
    if code == GOAL_REJECTED:
        return GoalRejected(text, int(error_code) if isinstance(error_code, int) else -1)
    return RequestError(
        code, text, message.get("id"), error_code if isinstance(error_code, int) else None
    )
