"""What the ROS 2 transport runs between Zenoh's threads and the event loop: the outbox, and
the guard every Zenoh callback runs under.

Theory of operation
-------------------
Zenoh's Python API is synchronous: a ``put`` or a ``reply`` may wait on the network. The event
loop never calls it: everything for Zenoh goes into one bounded :class:`Outbox` that a thread of
ours runs in order (``zenoh_iface``'s too: ``..zenoh_outbox``, docs/decisions.md 21), where the
periodic messages are also encoded. Droppable sends (states, feedback) are refused beyond
``size`` waiting and counted; replies and results only beyond ``hard_cap`` (logged). In the
other direction Zenoh calls back in its own threads: :func:`guard` wraps each callback so that
nothing raises into them (a failure is logged, counted, and a query dropped unanswered).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from ..zenoh_outbox import Outbox

__all__ = ["Outbox", "guard", "quietly"]

log = logging.getLogger("jtc_hw.ros2")


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


