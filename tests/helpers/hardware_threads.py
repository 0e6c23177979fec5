"""Emulators living in the test process, scheduled as the hardware they stand for.

A test that injects faults by calling an emulator runs it in its own process, beside the
test's thread and a busy host. Normally scheduled, the emulator then answers late whenever
the host is busy, and the driver counts a real motor's or servo's reply as missed (issue 22:
the suite failed at a load average of 5-10). Real devices answer in microseconds whatever the
host does, so their emulators' threads run at the SCHED_FIFO priority ``jtc-hw emulate`` takes
for its whole process; the test's own thread keeps normal scheduling (a daemon's loop takes
its own: conftest's ``TEST_LOOP_REALTIME``).
"""

from __future__ import annotations

import gc
import threading
from collections.abc import Callable

from jtc_hw.drivers.emulation_cli import DEFAULT_PRIORITY, realtime_priority

__all__ = ["start_as_hardware"]


def start_as_hardware(*starts: Callable[[], None]) -> str | None:
    """Call each of ``starts`` (an emulator's or a socketcand server's ``start``) in a helper
    thread running at SCHED_FIFO :data:`DEFAULT_PRIORITY`, as ``jtc-hw emulate can`` runs its
    whole process: the threads they start inherit that policy, so the emulated motors answer
    as soon as a frame wakes them however busy the host is (motors do not slow down when the
    host does), while the test's own thread keeps normal scheduling (the daemon's loop
    takes its own, conftest's ``TEST_LOOP_REALTIME``).

    Returns:
        ``None``, or the line saying why the priority was refused (no CAP_SYS_NICE): the
        emulators then run normally scheduled.

    Raises:
        BaseException: whatever a start raised.
    """
    # The test process's garbage collector holds the GIL, so an emulator thread cannot answer
    # during a collection: a full one over the session's objects took 0.4-1 s on a busy
    # machine, twice the daemon tests' reply timeout (CI, issue 22: a module's shared daemon
    # faulted between two tests and the tests after it failed). Collect now, while nothing is
    # served, and freeze the survivors so that later collections walk only newer objects.
    gc.collect()
    gc.freeze()
    outcome: list[str | None] = []
    failure: list[BaseException] = []

    def run() -> None:
        try:
            outcome.append(realtime_priority(DEFAULT_PRIORITY))
            for start in starts:
                start()
        except BaseException as exc:  # handed to the caller
            failure.append(exc)

    helper = threading.Thread(target=run, name="start-as-hardware")
    helper.start()
    helper.join()
    if failure:
        raise failure[0]
    return outcome[0] if outcome else None
