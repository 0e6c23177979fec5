"""What the ROS 2 transport runs between Zenoh's threads and the event loop: the outbox, and
the guard every Zenoh callback runs under.

Theory of operation
-------------------
Zenoh's Python API is synchronous: a ``put`` or a ``reply`` may wait on the network. The event
loop never calls it: everything for Zenoh goes into one bounded :class:`Outbox` that a thread of
ours runs in order (as ``zenoh_iface``'s, docs/decisions.md 21), where the periodic messages are
also encoded. Droppable sends (states, feedback) are refused beyond ``size`` waiting and counted;
replies and results only beyond ``hard_cap`` (logged). In the other direction Zenoh calls back in
its own threads: :func:`guard` wraps each callback so that nothing raises into them (a failure
is logged, counted, and a query dropped unanswered).
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["Outbox", "guard", "quietly"]

log = logging.getLogger("jtc_hw.ros2")


class Outbox:
    """Sends for Zenoh, run in order by one thread: droppable ones beyond ``size`` waiting,
    the others beyond ``hard_cap``."""

    def __init__(self, size: int, hard_cap: int) -> None:
        self._items: collections.deque[Callable[[], None]] = collections.deque()
        self._cond = threading.Condition()
        self._size, self._hard_cap = size, hard_cap
        self._closed = False
        self.dropped = self.lost = self.errors = 0
        self._thread = threading.Thread(target=self._run, name="jtc_hw-ros2-out", daemon=True)
        self._thread.start()

    def offer(self, action: Callable[[], None]) -> bool:
        """Queue a droppable send; False (counted in ``dropped``) beyond ``size`` waiting or
        once closed. Never blocks."""
        return self._add(action, self._size)

    def put(self, action: Callable[[], None]) -> bool:
        """Queue a send that must not be dropped; False (counted in ``lost``, logged) only
        beyond ``hard_cap`` waiting or once closed. Never blocks."""
        return self._add(action, self._hard_cap)

    def _add(self, action: Callable[[], None], limit: int) -> bool:
        with self._cond:
            if self._closed or len(self._items) >= limit:
                if limit == self._size:
                    self.dropped += 1
                else:
                    self.lost += 1
                    if self.lost <= 3 or self.lost % 1000 == 0:
                        log.error("ros2: %d sends waiting; a reply or result was lost",
                                  len(self._items))
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
            self._items.clear()
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
                    log.exception("ros2: cannot send; skipped")


def guard(callback: Callable[[Any], None] | None, counters: Any,
           query: bool = False) -> Callable[[Any], None]:
    """``callback`` that never raises into Zenoh's thread (a failure is logged, counted, and
    a query dropped)."""
    assert callback is not None

    def guarded(item: Any) -> None:
        try:
            callback(item)
        except Exception:
            counters["callback_errors"] += 1
            if counters["callback_errors"] <= 3:
                log.exception("ros2: cannot take a sample or request")
            if query:
                quietly(item.drop)

    return guarded


def quietly(fn: Callable[[], Any]) -> None:
    try:
        fn()
    except Exception:
        log.debug("ros2: ignored while closing", exc_info=True)


