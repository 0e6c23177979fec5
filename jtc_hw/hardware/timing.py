"""Timing for code that paces a bus: drivers, their emulators and the control loop.

It lives with the hardware contract, not in the daemon, because emulators and drivers pace
themselves too and must not import the daemon (the layering contract in ``pyproject.toml``).
"""

from __future__ import annotations

import ctypes
import errno
import os

__all__ = ["reduce_timer_slack"]

_PR_SET_TIMERSLACK = 29


def reduce_timer_slack(slack_ns: int = 1) -> str:
    """Shrink this thread's timer slack so sleeps end on time (Linux; a no-op elsewhere);
    returns a log line saying what was done.

    Linux lets a normally scheduled thread's timers fire up to its slack late (50 us by
    default) to batch wake-ups; for a control loop that is pure lateness. SCHED_FIFO threads
    have no slack, so this matters when real-time scheduling is off or refused.
    """
    if not os.path.exists("/proc/self/timerslack_ns"):
        return "timer slack left unchanged (not Linux)"
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(slack_ns), 0, 0, 0) != 0:
        err = ctypes.get_errno()
        return f"timer slack left unchanged ({errno.errorcode.get(err, err)})"
    return f"timer slack set to {slack_ns} ns (sleeps end on time)"
