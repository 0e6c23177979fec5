"""Real-time set-up of the control loop's process: CPU affinity, locked memory, SCHED_FIFO.

Theory of operation: :func:`apply_realtime` is called once, from the thread that will run the
control loop, before the loop starts (threads started afterwards inherit the scheduling policy
and affinity; the memory lock covers the whole process). It validates every value first, so a
configuration error changes nothing, then applies, in this order:

1. CPU affinity (``sched_setaffinity``), so the later steps already run on the chosen CPUs;
2. ``mlockall(MCL_CURRENT | MCL_FUTURE)``, so page faults cannot stall a cycle (pages mapped
   later are locked as they are mapped);
3. ``SCHED_FIFO`` at the given priority (``sched_setscheduler``), last, so the set-up work above
   does not itself run at real-time priority.

Lacking privileges is an expected deployment state (a developer's laptop, a container, a unit
without ``CAP_SYS_NICE``): it is never an error, the loop just runs with normal scheduling. Each
step returns one human-readable line saying what was applied, or why not and what to change;
the caller logs them. Only values that are wrong everywhere (a priority outside 1..99, a CPU this
machine does not have) raise :class:`~jtc_hw.errors.ConfigurationError`.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import platform
import resource
from collections.abc import Sequence
from typing import Any

from ..errors import ConfigurationError

__all__ = ["CAP_SYS_NICE", "apply_realtime", "has_capability", "set_process_name"]

_PATH = "daemon.realtime"

# Linux capability numbers (linux/capability.h).
_CAP_IPC_LOCK = 14
CAP_SYS_NICE = 23


def apply_realtime(priority: int, lock_memory: bool, cpu_affinity: Sequence[int]) -> list[str]:
    """Applies CPU affinity, memory locking and SCHED_FIFO (module docstring: to what, when);
    returns one line per step, saying what was applied or why it was not and how to allow it.

    Args:
        priority: SCHED_FIFO priority, 1 (lowest) to 99 (highest); 0 keeps normal
            scheduling. Stay below the kernel's threaded interrupt handlers (50 by default)
            unless the bus driver's IRQ thread is raised above the loop too.
        lock_memory: whether to lock all current and future pages in RAM.
        cpu_affinity: CPUs to run on; empty leaves the affinity unchanged.

    Raises:
        ConfigurationError: ``priority`` is not an integer in 1..99 (path
            ``daemon.realtime.priority``), or ``cpu_affinity`` names a CPU that this machine
            does not have or this process may never use (path ``daemon.realtime.cpu_affinity``).
    """
    _check_priority(priority)
    cpus = _check_cpus(cpu_affinity)
    return [
        _apply_affinity(cpus),
        _apply_memory_lock() if lock_memory else "memory locking disabled (lock_memory: false)",
        _apply_fifo(priority)
        if priority
        else "normal scheduling (daemon.realtime.priority: 0; 1..99 asks for SCHED_FIFO)",
    ]


def _check_priority(priority: int) -> None:
    if isinstance(priority, bool) or not isinstance(priority, int):
        raise ConfigurationError(
            f"SCHED_FIFO priority must be an integer 1..99, got {priority!r}",
            f"{_PATH}.priority",
            priority,
        )
    if priority == 0:
        return  # 0: leave the scheduling policy alone
    low, high = 1, 99
    if hasattr(os, "sched_get_priority_min"):
        low = os.sched_get_priority_min(os.SCHED_FIFO)
        high = os.sched_get_priority_max(os.SCHED_FIFO)
    if not low <= priority <= high:
        raise ConfigurationError(
            f"SCHED_FIFO priority must be {low}..{high} (higher runs first), got {priority}",
            f"{_PATH}.priority",
            priority,
        )


def _check_cpus(cpu_affinity: Sequence[int]) -> frozenset[int]:
    path = f"{_PATH}.cpu_affinity"
    if isinstance(cpu_affinity, str | bytes):
        raise ConfigurationError("must be a list of CPU numbers", path, cpu_affinity)
    present = _present_cpus()
    for cpu in cpu_affinity:
        if isinstance(cpu, bool) or not isinstance(cpu, int):
            raise ConfigurationError(
                f"CPU numbers must be integers, got {cpu!r}", path, list(cpu_affinity)
            )
        if cpu not in present:
            raise ConfigurationError(
                f"CPU {cpu} is not present on this machine (present: {_cpu_list(present)}); "
                "check `nproc` / /sys/devices/system/cpu/present",
                path,
                list(cpu_affinity),
            )
    return frozenset(cpu_affinity)


def _present_cpus() -> frozenset[int]:
    try:
        with open("/sys/devices/system/cpu/present", encoding="utf-8") as f:
            return _parse_cpu_list(f.read())
    except (OSError, ValueError):
        return frozenset(range(os.cpu_count() or 1))


def _parse_cpu_list(text: str) -> frozenset[int]:
    """The kernel's CPU list format, e.g. ``0-3,6``."""
    cpus: set[int] = set()
    for part in text.strip().split(","):
        if not part:
            continue
        first, _, last = part.partition("-")
        cpus.update(range(int(first), int(last or first) + 1))
    return frozenset(cpus)


def _cpu_list(cpus: frozenset[int] | set[int]) -> str:
    return ",".join(str(c) for c in sorted(cpus))


def _apply_affinity(cpus: frozenset[int]) -> str:
    if not hasattr(os, "sched_setaffinity"):
        return "CPU affinity not supported on this platform; left unchanged"
    current = os.sched_getaffinity(0)
    if not cpus:
        return f"CPU affinity left unchanged (CPUs {_cpu_list(current)})"
    try:
        os.sched_setaffinity(0, cpus)
    except PermissionError:
        return (
            f"CPU affinity {_cpu_list(set(cpus))} not permitted (EPERM); "
            f"continuing on CPUs {_cpu_list(current)}"
        )
    except OSError as exc:
        if exc.errno == errno.EINVAL:
            # Present, but outside this process's cpuset (container, systemd AllowedCPUs=,
            # isolcpus without a matching cpuset): wrong for this deployment, so refuse loudly.
            raise ConfigurationError(
                f"CPUs {_cpu_list(set(cpus))} are not usable by this process (its cpuset "
                f"allows {_cpu_list(current)}); check the container's or unit's CPU set",
                f"{_PATH}.cpu_affinity",
                sorted(cpus),
            ) from exc
        return f"CPU affinity {_cpu_list(set(cpus))} failed ({exc}); left unchanged"
    return f"CPU affinity set to CPUs {_cpu_list(set(cpus))}"


def libc_function(name: str) -> Any:
    """The C library's function ``name`` (``errno`` kept for ``ctypes.get_errno``), or None
    where there is none. The interpreter is linked against libc: its own symbol table has
    it, and ``find_library`` would spawn ldconfig to find the same library."""
    try:
        return getattr(ctypes.CDLL(None, use_errno=True), name)
    except (OSError, AttributeError):
        return None


def _mcl_flags() -> tuple[int, int, int]:
    """``(MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT)`` (the last: Linux 4.4+): most architectures
    use 1, 2, 4; a few use their own values."""
    if platform.machine().lower().startswith(("ppc", "powerpc", "sparc", "alpha")):
        return 0x2000, 0x4000, 0x8000
    return 1, 2, 4


def _apply_memory_lock() -> str:
    mlockall = libc_function("mlockall")
    if mlockall is None:
        return "memory locking not supported on this platform (no mlockall in libc); skipped"
    mlockall.argtypes = [ctypes.c_int]
    mlockall.restype = ctypes.c_int
    current, future, on_fault = _mcl_flags()
    if mlockall(current | future) == 0:
        # What is mapped now is faulted in and locked. Later mappings are locked as they are
        # touched (MCL_ONFAULT), not all at once when made: a large plan's receive buffer
        # (90 MB for 75,000 points) would otherwise be faulted in by the one read that
        # allocates it, tens of milliseconds in one cycle. Pages stay locked once touched.
        onfault = mlockall(current | future | on_fault) == 0
        how = (
            "; later mappings locked as they are touched (MCL_ONFAULT)"
            if onfault
            else "; later mappings are faulted in whole when made (no MCL_ONFAULT: Linux < 4.4)"
        )
        soft, _hard = resource.getrlimit(resource.RLIMIT_MEMLOCK)
        if soft != resource.RLIM_INFINITY and not has_capability(_CAP_IPC_LOCK):
            return (
                f"memory locked (mlockall MCL_CURRENT|MCL_FUTURE){how}; note RLIMIT_MEMLOCK is "
                f"{soft} bytes without CAP_IPC_LOCK, so allocations beyond it will fail: "
                "set LimitMEMLOCK=infinity"
            )
        return f"memory locked (mlockall MCL_CURRENT|MCL_FUTURE){how}"
    err = ctypes.get_errno()
    how = "run as root, give the service CAP_IPC_LOCK, or set LimitMEMLOCK=infinity"
    if err == errno.EPERM:
        return f"memory locking not permitted (EPERM): {how}; continuing without it"
    if err == errno.ENOMEM:
        soft, _hard = resource.getrlimit(resource.RLIMIT_MEMLOCK)
        return (
            f"memory locking refused (ENOMEM): RLIMIT_MEMLOCK={_limit(soft)} bytes is smaller "
            f"than the process: {how}; continuing without it"
        )
    return f"memory locking failed ({errno.errorcode.get(err, err)}): {os.strerror(err)}; skipped"


def _apply_fifo(priority: int) -> str:
    if not hasattr(os, "sched_setscheduler"):
        return "SCHED_FIFO not supported on this platform; continuing with normal scheduling"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        hint = ""
        if os.geteuid() == 0 and has_capability(CAP_SYS_NICE):
            # Privileged, yet refused: real-time bandwidth is not granted to our cgroup.
            hint = (
                " (privileged, so the real-time CPU budget is likely zero for this cgroup: "
                "check /proc/sys/kernel/sched_rt_runtime_us and cpu.rt_runtime_us)"
            )
        return (
            f"SCHED_FIFO priority {priority} not permitted (EPERM): run as root, give the "
            f"service CAP_SYS_NICE, or set LimitRTPRIO={priority}{hint}; "
            "continuing with normal scheduling"
        )
    except OSError as exc:
        return f"SCHED_FIFO priority {priority} failed ({exc}); continuing with normal scheduling"
    return f"SCHED_FIFO priority {priority} applied"


def has_capability(bit: int) -> bool:
    """Whether ``bit`` is in this process's effective capability set (Linux ``/proc``)."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        with open("/proc/self/status", encoding="utf-8") as f:
            for line in f:
                if line.startswith("CapEff:"):
                    return bool(int(line.split()[1], 16) >> bit & 1)
    return False


def _limit(value: int) -> str:
    return "infinity" if value == resource.RLIM_INFINITY else str(value)


_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MALLOC_KEEP_BYTES = 1 << 30


def keep_freed_memory() -> str:
    """Make glibc's allocator keep freed memory instead of returning it to the kernel; a log
    line saying what was done.

    A new plan brings megabytes of arrays; by default glibc maps each large block separately
    and unmaps it when freed. Unmapping changes the page tables of the whole process, which
    stalls its other thread (the control loop) for up to milliseconds on a virtual machine
    (measured: deadlines skipped after each committed 2,000-point goal). Served from the heap
    and kept there, the memory of one plan is reused by the next: no unmapping and, after the
    first plans, no page faults. The cost is that the loop process keeps its peak size."""
    mallopt = libc_function("mallopt")
    if mallopt is None:
        return "allocator left unchanged (no glibc mallopt)"
    ok = mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(_MALLOC_KEEP_BYTES)) == 1
    ok = mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(_MALLOC_KEEP_BYTES)) == 1 and ok
    if not ok:
        return "allocator left unchanged (mallopt refused)"
    return "allocator keeps freed memory for reuse (no unmapping in the loop process)"


_RETURN_ABOVE_BYTES = 128 * 1024


def return_freed_memory_promptly() -> str:
    """Make glibc return freed memory above 128 KiB at the top of any arena to the kernel; a
    log line saying what was done.

    The API process with Zenoh on (docs/decisions.md 29): a 100 MB query is copied by Zenoh's
    threads into a per-thread arena; once freed, glibc's dynamic trim threshold (raised by the
    large blocks it saw) keeps the top of that arena, and ``malloc_trim`` does not shrink a
    non-main arena's top either, so about one large query in four left up to 60 MB resident.
    A fixed trim threshold (which also fixes the mmap threshold at its 128 KiB default: large
    blocks are mapped and unmapped) brought the process back to its size after each query.
    Not for the loop process, which keeps its memory on purpose (:func:`keep_freed_memory`)."""
    mallopt = libc_function("mallopt")
    if mallopt is None:
        return "allocator left unchanged (no glibc mallopt)"
    if mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(_RETURN_ABOVE_BYTES)) != 1:
        return "allocator left unchanged (mallopt refused)"
    return "allocator returns freed memory above 128 KiB (large Zenoh queries leave no trace)"


_PR_SET_NAME = 15


def set_process_name(name: str) -> None:
    """Name the calling thread (the process's main thread: the process) as ``ps``, ``top`` and
    ``/proc/<pid>/comm`` show it (Linux, at most 15 bytes; a no-op elsewhere or on failure).

    The loop process is a ``multiprocessing`` child whose command line is the interpreter's;
    its name is how an operator (or a test) tells it from the API process.
    """
    if not os.path.exists("/proc/self/comm"):
        return
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)


_PR_SET_THP_DISABLE = 41


def disable_huge_pages() -> str:
    """Turn transparent huge pages off for this process (``prctl(PR_SET_THP_DISABLE)``); a log
    line saying what was done.

    numpy asks for huge pages for every array of 4 MB or more (``madvise(MADV_HUGEPAGE)``).
    The first touch of each 2 MB page then zeroes it, and may first compact memory to find
    one: measured, receiving a 75,000-point plan (90 MB) had single reads of 5-7 ms where
    4 kB pages cost at most 0.8 ms. The loop process touches little memory; it does not need
    the fewer TLB misses."""
    prctl = libc_function("prctl")
    if prctl is None:
        return "transparent huge pages left as they are (no prctl)"
    if prctl(_PR_SET_THP_DISABLE, 1, 0, 0, 0) != 0:
        return f"transparent huge pages left as they are (prctl: errno {ctypes.get_errno()})"
    return "transparent huge pages off (no 2 MB page faults in the loop process)"


def release_freed_memory() -> bool:
    """Give the memory the allocator keeps free back to the system (glibc ``malloc_trim(0)``);
    whether memory was returned (False also without glibc).

    For the API process after a large goal: fitting a 75,000-point goal leaves tens of MB of
    freed temporaries in the heap, which glibc keeps (its RSS stayed at 110 MB, 45 before).
    Not for the loop process, which keeps freed memory on purpose (:func:`keep_freed_memory`).
    It walks the heap (milliseconds for a large one): call it outside any time-critical path."""
    trim = libc_function("malloc_trim")
    if trim is None:
        return False
    return bool(trim(ctypes.c_size_t(0)))
