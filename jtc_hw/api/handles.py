"""What a client holds while the daemon works: an accepted goal, and a state subscription.

Both are fed by the :class:`~jtc_hw.api.client.Client`'s reader thread and waited on by the
caller with explicit timeouts (``threading`` conditions; nothing polls).
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable, Iterator
from typing import Any, Protocol

__all__ = ["FeedbackCallback", "GoalHandle", "StateSubscription"]

log = logging.getLogger("jtc_hw.client")


FeedbackCallback = Callable[[dict[str, Any]], None]


class ClientLike(Protocol):
    """What a handle asks of the :class:`~jtc_hw.api.client.Client` feeding it (which builds
    on this module, so it is not imported here)."""

    def cancel(self, goal_id: int, timeout_s: float | None = None) -> dict[str, Any]: ...

    def _unsubscribe(self, subscription: StateSubscription, timeout_s: float | None) -> None: ...


class GoalHandle:
    """An accepted goal: its feedback and its one result.

    Attributes:
        goal_id: the daemon's id of the goal.
        feedback_dropped: feedback messages discarded here because nobody consumed them
            (the buffer keeps the newest ``feedback_maxlen``).
        time_scale: with ``time_scaling`` ``fit`` in effect, the factor the goal was slowed
            down by to fit the joint limits (1.0: not at all); None otherwise.
        duration_s: with ``fit`` in effect, the goal's duration after slowing; else None.
    """

    def __init__(
        self,
        client: ClientLike,
        goal_id: int,
        on_feedback: FeedbackCallback | None = None,
        feedback_maxlen: int = 1000,
    ) -> None:
        self.goal_id = goal_id
        self.feedback_dropped = 0
        self.time_scale: float | None = None
        self.duration_s: float | None = None
        self._client = client
        self._on_feedback = on_feedback
        self._cond = threading.Condition()
        self._feedback: collections.deque[dict[str, Any]] = collections.deque(
            maxlen=feedback_maxlen)
        self._result: dict[str, Any] | None = None
        self._lost: Exception | None = None

    def __repr__(self) -> str:
        state = self._result["status"] if self._result else "running"
        return f"GoalHandle(goal_id={self.goal_id}, {state})"

    # -- called by the reader thread --

    def _add_feedback(self, message: dict[str, Any]) -> None:
        if self._on_feedback is not None:
            try:
                self._on_feedback(message)
            except Exception:  # a broken callback must not kill the reader thread
                log.exception("goal %d: the feedback callback failed", self.goal_id)
        with self._cond:
            if len(self._feedback) == self._feedback.maxlen:  # the append drops the oldest
                self.feedback_dropped += 1
            self._feedback.append(message)
            self._cond.notify_all()

    def _set_result(self, message: dict[str, Any]) -> None:
        with self._cond:
            self._result = message
            self._cond.notify_all()

    def _connection_lost(self, error: Exception) -> None:
        with self._cond:
            if self._result is None:
                self._lost = error
            self._cond.notify_all()

    # -- public --

    @property
    def done(self) -> bool:
        """Whether the result has arrived."""
        with self._cond:
            return self._result is not None

    @property
    def result(self) -> dict[str, Any] | None:
        """The ``result`` event (``status``, ``error_code``, ``error_string``: upstream's text,
        ``details``: which joint broke which tolerance, ``time_ns``), or ``None`` while the goal
        runs."""
        with self._cond:
            return self._result

    def wait(self, timeout_s: float) -> dict[str, Any]:
        """Block until the goal's result arrives; return the ``result`` event (a failed goal is a
        result too: ``status`` ``aborted``).

        Raises:
            TimeoutError: no result within ``timeout_s`` (the goal keeps running).
            ClientConnectionError: the connection was lost before the result arrived.
        """
        with self._cond:
            self._cond.wait_for(
                lambda: self._result is not None or self._lost is not None, timeout_s
            )
            if self._result is not None:
                return self._result
            if self._lost is not None:
                raise self._lost
        raise TimeoutError(f"goal {self.goal_id}: no result within {timeout_s} s")

    def feedback(self, timeout_s: float) -> Iterator[dict[str, Any]]:
        """Iterate over the goal's ``feedback`` events, ending when its result has arrived.

        Feedback already received (up to ``feedback_maxlen``) comes first.

        Args:
            timeout_s: the longest wait for the next feedback or the result.

        Raises:
            TimeoutError: nothing arrived for ``timeout_s``.
            ClientConnectionError: the connection was lost before the result arrived.
        """
        while True:
            with self._cond:
                self._cond.wait_for(
                    lambda: (
                        bool(self._feedback) or self._result is not None or self._lost is not None
                    ),
                    timeout_s,
                )
                if self._feedback:
                    item = self._feedback.popleft()
                elif self._result is not None:
                    return
                elif self._lost is not None:
                    raise self._lost
                else:
                    raise TimeoutError(
                        f"goal {self.goal_id}: no feedback or result within {timeout_s} s"
                    )
            yield item

    def cancel(self, timeout_s: float | None = None) -> dict[str, Any]:
        """Ask the daemon to cancel this goal; its result (``canceled``) follows. Raises as
        :meth:`Client.cancel` does (``not_found`` when the goal is no longer executing)."""
        return self._client.cancel(self.goal_id, timeout_s=timeout_s)


class StateSubscription:
    """``state`` events of the daemon; ``close`` (or leaving the ``with`` block) unsubscribes.

    Iterating waits up to the subscription's ``timeout_s`` for each message.

    Attributes:
        dropped_locally: messages discarded here because nobody consumed them (the buffer
            keeps the newest ``maxlen``); each message's ``dropped`` counts the daemon's side.
    """

    def __init__(self, client: ClientLike, timeout_s: float, maxlen: int,
                 commands: bool = False) -> None:
        self.timeout_s = timeout_s
        self.commands = commands
        """Whether ``command`` and ``record`` events come too (``subscribe_state(commands=
        True)``)."""
        self.dropped_locally = 0
        self._client = client
        self._cond = threading.Condition()
        self._queue: collections.deque[dict[str, Any]] = collections.deque(maxlen=maxlen)
        self._closed = False
        self._lost: Exception | None = None

    def _add(self, message: dict[str, Any]) -> None:
        with self._cond:
            if len(self._queue) == self._queue.maxlen:  # the append drops the oldest
                self.dropped_locally += 1
            self._queue.append(message)
            self._cond.notify_all()

    def _connection_lost(self, error: Exception) -> None:
        with self._cond:
            self._lost = error
            self._cond.notify_all()

    def get(self, timeout_s: float | None = None) -> dict[str, Any]:
        """The next ``state`` event.

        Raises:
            TimeoutError: none within ``timeout_s`` (default: the subscription's).
            ClientConnectionError: the connection was lost.
            StopIteration: the subscription is closed.
        """
        timeout = self.timeout_s if timeout_s is None else timeout_s
        with self._cond:
            self._cond.wait_for(
                lambda: bool(self._queue) or self._closed or self._lost is not None, timeout
            )
            if self._queue:
                return self._queue.popleft()
            if self._closed:
                raise StopIteration
            if self._lost is not None:
                raise self._lost
        raise TimeoutError(f"no state message within {timeout} s")

    def __iter__(self) -> Iterator[dict[str, Any]]:
        return self

    def __next__(self) -> dict[str, Any]:
        return self.get()

    def close(self, timeout_s: float | None = None) -> None:
        """Stop receiving; unsubscribes when it is the client's last subscription. Idempotent.

        Raises:
            TimeoutError: the daemon did not confirm within the timeout.
        """
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        self._client._unsubscribe(self, timeout_s)

    def __enter__(self) -> StateSubscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
