"""Real-time set-up (jtc_hw.daemon.realtime), each real attempt in a child process.

The test runner must never become real-time, locked or pinned itself, so every call that may
change the process runs in ``sys.executable -c``; the child reports, as JSON, the lines returned
and the scheduling state the kernel then shows. The refused paths are real refusals: as root the
child drops to ``nobody`` (which also drops every capability) with zero RLIMIT_RTPRIO /
RLIMIT_MEMLOCK before calling.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest

from jtc_hw.daemon.realtime import _parse_cpu_list, apply_realtime
from jtc_hw.errors import ConfigurationError

ROOT = Path(__file__).resolve().parents[2]
NOBODY = 65534

CHILD = """
import json, os, resource, sys
from jtc_hw.daemon.realtime import apply_realtime  # before the prelude: nobody cannot read it
{prelude}
try:
    lines = apply_realtime({args})
    error = None
except Exception as exc:
    lines, error = None, [type(exc).__name__, str(exc), getattr(exc, "path", None)]
vmlck = [l.split()[1] for l in open("/proc/self/status") if l.startswith("VmLck:")][0]
print(json.dumps({{
    "lines": lines,
    "error": error,
    "policy": os.sched_getscheduler(0),
    "priority": os.sched_getparam(0).sched_priority,
    "affinity": sorted(os.sched_getaffinity(0)),
    "vmlck_kb": int(vmlck),
}}))
"""

DROP_PRIVILEGES = f"""
resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
os.setgroups([])
os.setgid({NOBODY})
os.setuid({NOBODY})
"""


def run_child(args: str, prelude: str = "") -> dict[str, Any]:
    code = CHILD.format(prelude=textwrap.dedent(prelude), args=args)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    result: dict[str, Any] = json.loads(proc.stdout)
    return result


def fifo_permitted() -> bool:
    """Whether a child of this process may actually use SCHED_FIFO (root, CAP_SYS_NICE, ...)."""
    probe = "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))"
    return subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0


def mlock_permitted() -> bool:
    probe = (
        "import ctypes, sys; libc = ctypes.CDLL(None, use_errno=True); sys.exit(libc.mlockall(3))"
    )
    return subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0


def refusal_prelude() -> str:
    """Code making the child unprivileged, or skip when it cannot be made so for real."""
    if os.geteuid() == 0:
        return DROP_PRIVILEGES
    if fifo_permitted():
        pytest.skip("not root (cannot drop to nobody) and SCHED_FIFO is permitted here")
    return "resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))"


# -- permitted paths ------------------------------------------------------------------------------


def test_fifo_applied_when_permitted() -> None:
    if not fifo_permitted():
        pytest.skip("SCHED_FIFO is not permitted for this user/cgroup; refusal tested below")
    out = run_child("20, False, []")
    assert out["error"] is None
    assert out["lines"][2] == "SCHED_FIFO priority 20 applied"
    assert out["policy"] == os.SCHED_FIFO
    assert out["priority"] == 20


def test_memory_locked_when_permitted() -> None:
    if not mlock_permitted():
        pytest.skip("mlockall is not permitted here; refusal tested below")
    out = run_child("1, True, []", prelude="resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))")
    assert out["lines"][1].startswith("memory locked (mlockall MCL_CURRENT|MCL_FUTURE)")
    assert out["vmlck_kb"] > 0


def test_affinity_applied() -> None:
    cpu = min(os.sched_getaffinity(0))
    out = run_child(f"1, False, [{cpu}]")
    assert out["lines"][0] == f"CPU affinity set to CPUs {cpu}"
    assert out["affinity"] == [cpu]


def test_empty_affinity_left_unchanged() -> None:
    out = run_child("1, False, []")
    assert out["lines"][0].startswith("CPU affinity left unchanged (CPUs ")
    assert out["affinity"] == sorted(os.sched_getaffinity(0))
    assert out["lines"][1] == "memory locking disabled (lock_memory: false)"


# -- refused paths (real EPERM / ENOMEM) ----------------------------------------------------------


def test_fifo_refused_is_a_line_not_an_error() -> None:
    out = run_child("80, False, []", prelude=refusal_prelude())
    assert out["error"] is None
    assert out["lines"][2] == (
        "SCHED_FIFO priority 80 not permitted (EPERM): run as root, give the service "
        "CAP_SYS_NICE, or set LimitRTPRIO=80; continuing with normal scheduling"
    )
    assert out["policy"] == os.SCHED_OTHER


def test_memory_lock_refused_with_zero_limit_is_eperm() -> None:
    prelude = refusal_prelude() + "\nresource.setrlimit(resource.RLIMIT_MEMLOCK, (0, 0))"
    out = run_child("1, True, []", prelude=prelude)
    assert out["error"] is None
    assert out["lines"][1] == (
        "memory locking not permitted (EPERM): run as root, give the service CAP_IPC_LOCK, "
        "or set LimitMEMLOCK=infinity; continuing without it"
    )
    assert out["vmlck_kb"] == 0


def test_memory_lock_refused_with_small_limit_is_enomem() -> None:
    prelude = refusal_prelude() + "\nresource.setrlimit(resource.RLIMIT_MEMLOCK, (65536, 65536))"
    out = run_child("1, True, []", prelude=prelude)
    assert out["error"] is None
    assert out["lines"][1].startswith(
        "memory locking refused (ENOMEM): RLIMIT_MEMLOCK=65536 bytes is smaller than the process"
    )
    assert "LimitMEMLOCK=infinity" in out["lines"][1]
    assert out["vmlck_kb"] == 0


def test_everything_refused_still_returns_three_lines() -> None:
    cpu = min(os.sched_getaffinity(0))
    prelude = refusal_prelude() + "\nresource.setrlimit(resource.RLIMIT_MEMLOCK, (0, 0))"
    out = run_child(f"99, True, [{cpu}]", prelude=prelude)
    assert out["error"] is None
    first, memory, fifo = out["lines"]
    assert first == f"CPU affinity set to CPUs {cpu}"  # own affinity needs no privilege
    assert "EPERM" in memory and "EPERM" in fifo


# -- invalid values: raised before anything is applied (safe in-process) --------------------------


@pytest.mark.parametrize("priority", [100, -1, 1000, True, 50.0, "80"])
def test_priority_out_of_range_raises(priority: Any) -> None:
    before = (os.sched_getscheduler(0), os.sched_getaffinity(0))
    with pytest.raises(ConfigurationError) as info:
        apply_realtime(priority, True, [0])
    assert info.value.path == "daemon.realtime.priority"
    assert info.value.value == priority
    assert str(info.value).startswith("daemon.realtime.priority: ")
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == before


@pytest.mark.parametrize("cpus", [[4096], [0, 4096], [-1], [True], [0.0], "0"])
def test_cpu_not_present_raises(cpus: Any) -> None:
    before = (os.sched_getscheduler(0), os.sched_getaffinity(0))
    with pytest.raises(ConfigurationError) as info:
        apply_realtime(50, True, cpus)
    assert info.value.path == "daemon.realtime.cpu_affinity"
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == before


def test_missing_cpu_message_names_the_present_ones() -> None:
    with pytest.raises(ConfigurationError, match=r"CPU 4096 is not present on this machine"):
        apply_realtime(50, False, [4096])


def test_errors_are_raised_in_the_child_too() -> None:
    out = run_child("100, False, []")
    assert out["error"][0] == "ConfigurationError"
    assert out["error"][2] == "daemon.realtime.priority"
    assert out["policy"] == os.SCHED_OTHER


@pytest.mark.parametrize(
    ("text", "cpus"),
    [("0", {0}), ("0-3", {0, 1, 2, 3}), ("0-1,4,6-7\n", {0, 1, 4, 6, 7}), ("", set())],
)
def test_kernel_cpu_list_format(text: str, cpus: set[int]) -> None:
    assert _parse_cpu_list(text) == cpus


def test_priority_zero_keeps_normal_scheduling() -> None:
    out = run_child("0, False, []")
    assert out["policy"] == os.SCHED_OTHER
    assert any("normal scheduling" in line for line in out["lines"])


def test_reduce_timer_slack_in_a_child() -> None:
    code = (
        "from jtc_hw.hardware.timing import reduce_timer_slack; "
        "line = reduce_timer_slack(1); "
        "print(line); print(open('/proc/self/timerslack_ns').read().strip())"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    line, slack = done.stdout.splitlines()
    if "not Linux" in line:
        pytest.skip("no /proc/self/timerslack_ns on this system")
    assert line == "timer slack set to 1 ns (sleeps end on time)"
    assert slack == "1"


def test_huge_pages_are_turned_off_for_the_process() -> None:
    code = (
        "from jtc_hw.daemon.realtime import disable_huge_pages\n"
        "print(disable_huge_pages())\n"
        "print(open('/proc/self/status').read())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    line, status = out.stdout.split("\n", 1)
    if "THP_enabled:" not in status:
        pytest.skip("this kernel does not report THP_enabled in /proc/<pid>/status")
    assert line.startswith("transparent huge pages off")
    assert "THP_enabled:\t0" in status


def test_release_freed_memory_returns_a_freed_heap_to_the_system() -> None:
    code = (
        "import ctypes\n"
        "from jtc_hw.daemon.realtime import release_freed_memory\n"
        "libc = ctypes.CDLL(None)\n"
        "libc.malloc.restype = ctypes.c_void_p\n"
        "libc.free.argtypes = [ctypes.c_void_p]\n"
        "libc.mallopt(-1, 1 << 30)\n"  # M_TRIM_THRESHOLD: free() alone keeps the memory
        "libc.mallopt(-3, 1 << 30)\n"  # M_MMAP_THRESHOLD: blocks come from the heap
        "def rss():\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith('VmRSS:'):\n"
        "            return int(line.split()[1])\n"
        "blocks = [libc.malloc(1 << 20) for _ in range(64)]\n"
        "for b in blocks:\n"
        "    ctypes.memset(b, 1, 1 << 20)\n"
        "full = rss()\n"
        "for b in blocks:\n"
        "    libc.free(b)\n"
        "kept = rss()\n"
        "print(release_freed_memory(), full, kept, rss())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    released, full, kept, after = out.stdout.split()
    assert int(kept) > int(full) - 8 * 1024  # freed but kept by the allocator (kB)
    assert released == "True"
    assert int(after) < int(kept) - 48 * 1024  # most of the 64 MB went back


def test_locked_memory_large_buffers_are_locked_as_touched_and_given_back() -> None:
    """With lock_memory, a plan's own mapping is neither faulted in whole when it is made (one
    read of the inbox would pay for 90 MB) nor kept for good: MADV_DONTNEED refuses locked
    pages, so each chunk is unlocked first."""
    if not mlock_permitted():
        pytest.skip("mlockall is not permitted here")
    code = textwrap.dedent(
        """
        import json
        from jtc_hw.daemon.channel import pipe
        from jtc_hw.daemon.realtime import apply_realtime

        def kib(key):
            for line in open("/proc/self/status"):
                if line.startswith(key):
                    return int(line.split()[1])

        lines = apply_realtime(0, True, [])
        before = kib("VmRSS:")
        mapping = pipe._receive_buffer(64 << 20)  # 64 MB: a mapping of its own
        made = kib("VmRSS:")
        mapping[: 8 << 20] = b"x" * (8 << 20)  # what the reads would have touched
        touched, locked = kib("VmRSS:"), kib("VmLck:")
        mapped = pipe._Mapped(mapping)
        assert mapped.unused()
        while not mapped.give_back(2 << 20):
            pass
        print(json.dumps({"line": lines[1], "before": before, "made": made, "touched": touched,
                          "locked": locked, "after": kib("VmRSS:")}))
        """
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    if "MCL_ONFAULT" not in out["line"]:
        pytest.skip(f"this kernel has no MCL_ONFAULT: {out['line']}")
    assert out["made"] - out["before"] < 4 * 1024  # kB: not faulted in when made
    assert out["touched"] - out["made"] >= 8 * 1024 - 64  # the touched part is resident...
    assert out["locked"] >= 8 * 1024  # ... and locked
    assert out["after"] < out["touched"] - 7 * 1024  # and given back, though it was locked
