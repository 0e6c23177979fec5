"""What the emulators' command lines (``jtc-hw emulate dynamixel``, ``jtc-hw emulate can``)
share: the ``--ids`` syntax and the real-time priority they serve at.

One syntax for every bus: ``"1-6"``, ``"1,3,5"``, ``"1-3,7"``; each number in Python's
integer-literal syntax (decimal, or ``0x1F`` as CAN ids are often written). A family's own
id range (Dynamixel 0..252) is checked by passing it as ``valid``.

An emulator process asks for SCHED_FIFO :data:`DEFAULT_PRIORITY` (:func:`realtime_priority`,
or :func:`apply_priority` for a command line's ``--priority``): it is scheduled as the hardware
it stands for, not as one more program on a busy host.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys

__all__ = ["DEFAULT_PRIORITY", "apply_priority", "parse_ids", "realtime_priority"]

DEFAULT_PRIORITY = 1
"""SCHED_FIFO priority an emulator process asks for unless told otherwise: the lowest, so a
control loop at any real-time priority still preempts it, while busy normally scheduled
programs (a compiler, a second test suite) no longer do."""


def parse_ids(text: str, valid: range | None = None) -> list[int]:
    """``"1-6"``, ``"1,3,5"``, ``"1-3,7"`` -> the ids, in the order given.

    Raises:
        ValueError: not of that form, no id, an id given twice, or one outside ``valid``.
    """
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            low, high = (int(x, 0) for x in part.split("-", 1))
            if high < low:
                raise ValueError(f"empty id range {part!r}")
            ids.extend(range(low, high + 1))
        elif part:
            ids.append(int(part, 0))
    outside = valid is not None and any(i not in valid for i in ids)
    if not ids or len(set(ids)) != len(ids) or outside:
        within = f" in {valid.start}..{valid.stop - 1}" if valid is not None else ""
        raise ValueError(f"expected distinct ids{within} like 1-6 or 1,2,3, got {text!r}")
    return ids


def realtime_priority(priority: int, whole_process: bool = False) -> str | None:
    """Run the calling thread, and the threads it starts afterwards, at SCHED_FIFO
    ``priority`` (0: leave normal scheduling); with ``whole_process``, every thread the
    process already has too (an emulator's command line: numpy's BLAS threads start at
    import, before ``main`` can set anything).

    Motors answer within microseconds whatever the host does; an emulator process scheduled
    like any other program answers late whenever the host is busy (measured: 0.3-0.6 % of
    the replies of a 500 Hz loop over six motors later than their read's deadline with the
    machine otherwise idle, 4-7 % beside two busy processes; docs/benchmarks.md), which the
    driver would count as missed replies of real motors. At a real-time priority the
    emulator's threads preempt normally scheduled work as soon as a frame or a due reply
    wakes them. Call it before starting any thread.

    Returns:
        ``None`` when applied (or ``priority`` is 0), else one line saying why not (no
        privilege: CAP_SYS_NICE or an RLIMIT_RTPRIO of at least ``priority``).

    Raises:
        ValueError: ``priority`` is not in 0..99.
    """
    if not 0 <= priority <= 99:
        raise ValueError(f"a SCHED_FIFO priority is 1..99 (0: normal scheduling), got "
                         f"{priority}")
    if priority == 0:
        return None
    threads = [0]  # the calling thread
    if whole_process:
        with contextlib.suppress(OSError, ValueError):  # no /proc: the calling thread only
            threads = [int(tid) for tid in os.listdir("/proc/self/task")]
    try:
        for tid in threads:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:  # EPERM; AttributeError: not Linux
        return (f"normal scheduling (SCHED_FIFO {priority} refused: {exc}); on a busy host "
                "its replies may come late: run it as root, with CAP_SYS_NICE, or with "
                "`ulimit -r` >= the priority")
    return None


def apply_priority(parser: argparse.ArgumentParser, priority: int | None) -> None:
    """An emulator command line's ``--priority``: check it (``parser.error``, exit 2, when out
    of 0..99), then run the whole process at it (``None``: :data:`DEFAULT_PRIORITY` where
    permitted, silently normal otherwise; a priority asked for and refused is said on stderr).
    Call it before any thread starts: they inherit the policy.
    """
    if priority is not None and not 0 <= priority <= 99:
        parser.error(f"--priority must be 0..99, got {priority}")
    refused = realtime_priority(DEFAULT_PRIORITY if priority is None else priority,
                                whole_process=True)
    if refused is not None and priority is not None:  # asked for: say it was not given
        print(f"{parser.prog}: {refused}", file=sys.stderr)
