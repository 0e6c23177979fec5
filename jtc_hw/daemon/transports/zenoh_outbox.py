"""The one thread that talks to Zenoh for a transport: a bounded, ordered outbox.

Theory of operation
-------------------
Zenoh's Python API is synchronous: a ``put`` or a ``reply`` may wait on the network. The event
loop never calls it (docs/decisions.md 21): a transport on Zenoh (``zenoh_iface``, ``ros2``)
queues every send as an action in one :class:`Outbox`, which a thread of its own runs in order.
Droppable sends (states, feedback) are refused beyond ``size`` waiting and counted in
``dropped``; replies and results only beyond ``hard_cap`` (counted in ``lost``, logged). An
action that raises is logged (the first three) and counted in ``errors``; the next one runs.
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable

__all__ = ["Outbox"]

log = logging.getLogger("jtc_hw.transports")


class Outbox:
    """Sends for Zenoh, run in order by one thread named ``jtc_hw-<label>-out``.

    Args:
        size: waiting actions beyond which :meth:`offer` refuses.
        hard_cap: waiting actions beyond which even :meth:`put` refuses.
        label: the transport (``zenoh``, ``ros2``), in the thread's name and the log lines.
    """

    def __init__(self, size: int, hard_cap: int, label: str) -> None:
        self._items: collections.deque[Callable[[], None]] = collections.deque()
        self._cond = threading.Condition()
        self._size, self._hard_cap, self._label = size, hard_cap, label
        self._closed = False
        self.dropped = self.lost = self.errors = 0
        self._thread = threading.Thread(target=self._run, name=f"jtc_hw-{label}-out",
                                        daemon=True)
        self._thread.start()

    def offer(self, action: Callable[[], None]) -> bool:
        """Queue a droppable send; False (counted in ``dropped``) beyond ``size`` waiting or
        once closed. Never blocks."""
        with self._cond:
            if self._closed or len(self._items) >= self._size:
                self.dropped += 1
                return False
            self._items.append(action)
            self._cond.notify()
        return True

    def put(self, action: Callable[[], None]) -> bool:
        """Queue a send that must not be dropped; False (counted in ``lost``, logged) only
        beyond ``hard_cap`` waiting or once closed. Never blocks."""
        with self._cond:
            if self._closed or len(self._items) >= self._hard_cap:
                self.lost += 1
                if self.lost <= 3 or self.lost % 1000 == 0:
                    log.error("%s: %d sends waiting; a reply or result was lost (%d so far)",
                              self._label, len(self._items), self.lost)
                return False
            self._items.append(action)
            self._cond.notify()
        return True

    def close(self, timeout_s: float) -> None:
        """Run what is waiting (for up to ``timeout_s``), drop the rest, end the thread."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout_s)
        with self._cond:
            self._items.clear()  # not sent in time: the session closes now
            self._cond.notify()
        self._thread.join()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._items and not self._closed:
                    self._cond.wait()
                if not self._items:
                    return
                action = self._items.popleft()
            try:
                action()
            except Exception:
                self.errors += 1
                if self.errors <= 3:
                    log.exception("%s: cannot send; skipped", self._label)
