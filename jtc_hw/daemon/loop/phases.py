"""Where the loop's period goes, phase by phase: a measuring aid that is off unless asked for.

Theory of operation
-------------------
``bench/loop_jitter.py --breakdown`` starts the daemon with :data:`PHASES_ENV` naming a file.
The loop process reads the variable once, when it starts (:meth:`PhaseRecorder.from_env`);
without it nothing here is imported into the cycle's path: no wrapper, no branch, so the
production loop pays nothing. With it, :meth:`PhaseRecorder.instrument` replaces, on the loop's
own objects, the bound methods each phase runs (``hardware.read``, ``ctrl.update``, the stats'
``record``, the outbox's ``serve``, ...) by timing wrappers: a wrapped call adds its duration
(``time.perf_counter_ns`` before and after) to its phase's slot of the current cycle. The
ticker's ``wait`` closes a cycle: on entry it adds the whole period's work (from the previous
``wait``'s return to now: everything the process did between two wake-ups) and writes the
cycle's row into a ring of rows in the memory-mapped file, then publishes the count.

The file (``int64`` throughout)::

    header  [MAGIC, VERSION, columns, capacity, count, 0, 0, 0]
    rows    capacity x columns, row ``k % capacity`` holds cycle ``k``'s nanoseconds per
            column of :data:`COLUMNS`

A reader (the bench, another process) copies the rows between two counts it read
(:func:`read_rows`) and summarises them (:func:`summarise`). Nested phases (``read`` inside
``cycle``) each hold their own inclusive time; :func:`summarise` adds each parent's remainder
(``cycle: rest``, ``period: rest``), where the wrappers' own overhead lands as well
(measured: about 0.25 us a call, 3-4 us a period).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from ..channel.pipe import Inbox
    from .clock import Ticker

__all__ = ["COLUMNS", "PHASES_ENV", "PhaseRecorder", "read_rows", "summarise"]

PHASES_ENV = "JTC_HW_LOOP_PHASES"
"""The environment variable naming the file the loop process writes its phases into."""

MAGIC = 0x4A5443504853  # "JTCPHS"
VERSION = 1
HEADER_SLOTS = 8
_H_MAGIC, _H_VERSION, _H_COLUMNS, _H_CAPACITY, _H_COUNT = range(5)
DEFAULT_CAPACITY = 1 << 16
"""Cycles the file holds (65 s at 1 kHz; 8 MiB with the columns below)."""

COLUMNS = (
    "period",  # the whole work between two wake-ups
    "cycle",  # ControlLoop.cycle: the next seven, and the rest (reference, events, State built)
    "requests",  # its inbox drain at the cycle's start
    "read",
    "update",
    "write",
    "ring",  # the cycle ring's row (the flight recorder's feed)
    "state",  # publishing the State (its slot in the cycle ring, or pickled into the outbox)
    "stats",  # LoopStats.record
    "status",  # building and publishing the Status (2 Hz)
    "outbox",  # serve_outbox: writing the outbox to the API process
    "inbox read",  # Inbox.pump
    "inbox handle",  # handling what the read completed
    "free/gc",  # Inbox.release, the generation-0 collection
)
PARENT = {"requests": "cycle", "read": "cycle", "update": "cycle", "write": "cycle",
          "ring": "cycle", "state": "cycle", "cycle": "period", "stats": "period",
          "status": "period", "outbox": "period", "inbox read": "period",
          "inbox handle": "period", "free/gc": "period"}
"""Each nested phase's parent; a parent's remainder is shown as ``<parent>: rest``."""
_COL = {name: i for i, name in enumerate(COLUMNS)}


class Loop(Protocol):
    """What :meth:`PhaseRecorder.instrument` wraps: ``cycle.ControlLoop`` (which imports this
    module, hence a protocol and not the class)."""

    hardware: object  # read, write
    ctrl: object  # update
    ring: object | None  # write, write_state
    stats: object  # record
    cycle: Callable[..., None]
    handle_inbox: Callable[..., bool]
    publish: Callable[[Any], None]
    status: Callable[[], dict[str, Any]]
    serve_outbox: Callable[[int], None]
    collect_garbage: Callable[[int], int]


class PhaseRecorder:
    """Accumulates each cycle's phase durations and writes one row per cycle into a ring in a
    memory-mapped file (module docstring).

    Args:
        path: the file (created, or overwritten).
        capacity: rows in the ring.
        clock: nanoseconds of a monotonic clock (``time.perf_counter_ns``; a test's fake).
    """

    def __init__(self, path: str | os.PathLike[str], capacity: int = DEFAULT_CAPACITY,
                 clock: Callable[[], int] = time.perf_counter_ns) -> None:
        width = len(COLUMNS)
        self._map = np.memmap(path, dtype=np.int64, mode="w+",
                              shape=(HEADER_SLOTS + capacity * width,))
        self._map[:] = 0  # every page touched now, not in a cycle
        header = self._map[:HEADER_SLOTS]
        header[_H_VERSION], header[_H_COLUMNS], header[_H_CAPACITY] = VERSION, width, capacity
        header[_H_MAGIC] = MAGIC
        self._header = header
        self._rows = self._map[HEADER_SLOTS:].reshape(capacity, width)
        self.capacity = capacity
        self._clock = clock
        self._acc = [0] * width
        self._zeros = [0] * width
        self._count = 0
        self._woke: int | None = None
        self._in_cycle = False

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> PhaseRecorder | None:
        """A recorder writing into the file :data:`PHASES_ENV` names, or None if unset.

        Raises:
            OSError: the file cannot be created.
        """
        path = (os.environ if environ is None else environ).get(PHASES_ENV)
        return cls(path) if path else None

    @property
    def count(self) -> int:
        """Cycles written."""
        return self._count

    def close(self) -> None:
        """Write the file out and release the mapping."""
        self._map.flush()
        self._header = self._rows = self._map = None  # type: ignore[assignment]

    # -- wrapping -----------------------------------------------------------------------------

    def wrap(self, obj: object, name: str, column: str) -> None:
        """Replace the bound method ``obj.<name>`` by one adding its duration to ``column``.

        Raises:
            KeyError: ``column`` is not one of :data:`COLUMNS`.
        """
        fn = getattr(obj, name)
        col, acc, clock = _COL[column], self._acc, self._clock

        def timed(*args: Any, **kwargs: Any) -> Any:
            t = clock()
            result = fn(*args, **kwargs)
            acc[col] += clock() - t
            return result

        setattr(obj, name, timed)

    def wrap_ticker(self, ticker: Ticker) -> None:
        """Make ``ticker.wait`` close each cycle (and start the next)."""
        wait, clock = ticker.wait, self._clock

        def timed_wait() -> Any:
            now = clock()
            if self._woke is not None:
                self._acc[0] += now - self._woke
                self._close_cycle()
            tick = wait()
            self._woke = clock()
            return tick

        ticker.wait = timed_wait  # type: ignore[method-assign]

    def _close_cycle(self) -> None:
        count = self._count
        self._rows[count % self.capacity] = self._acc
        self._count = count + 1
        self._header[_H_COUNT] = count + 1
        self._acc[:] = self._zeros

    def instrument(self, loop: Loop, ticker: Ticker, inbox: Inbox) -> None:
        """Wrap every phase of ``loop``'s period (called once, before it cycles)."""
        cycle, handle = loop.cycle, loop.handle_inbox
        acc, clock = self._acc, self._clock
        c_cycle, c_requests, c_handle = _COL["cycle"], _COL["requests"], _COL["inbox handle"]
        c_state, c_status = _COL["state"], _COL["status"]

        def timed_cycle(*args: Any) -> None:
            t = clock()
            self._in_cycle = True
            cycle(*args)
            self._in_cycle = False
            acc[c_cycle] += clock() - t

        def timed_handle(*args: Any) -> bool:
            t = clock()
            result = handle(*args)
            acc[c_requests if self._in_cycle else c_handle] += clock() - t
            return result

        publish = loop.publish

        def timed_publish(message: Any) -> None:
            t = clock()
            publish(message)
            acc[c_state if self._in_cycle else c_status] += clock() - t

        loop.cycle = timed_cycle  # type: ignore[method-assign]
        loop.handle_inbox = timed_handle  # type: ignore[method-assign]
        loop.publish = timed_publish  # type: ignore[method-assign]
        self.wrap(loop.hardware, "read", "read")
        self.wrap(loop.ctrl, "update", "update")
        self.wrap(loop.hardware, "write", "write")
        if loop.ring is not None:
            self.wrap(loop.ring, "write", "ring")
            self.wrap(loop.ring, "write_state", "state")
        self.wrap(loop.stats, "record", "stats")
        self.wrap(loop, "status", "status")
        self.wrap(loop, "serve_outbox", "outbox")
        self.wrap(inbox, "pump", "inbox read")
        self.wrap(inbox, "release", "free/gc")
        self.wrap(loop, "collect_garbage", "free/gc")
        self.wrap_ticker(ticker)


# -- reading ----------------------------------------------------------------------------------


def read_rows(path: str | os.PathLike[str], since: int = 0) -> tuple[NDArray[np.int64], int]:
    """The rows of the cycles from ``since`` on that the file still holds, as a copy, and the
    count to read from next.

    Raises:
        OSError: the file cannot be read.
        ValueError: it is not a phase file.
    """
    data = np.fromfile(Path(path), dtype=np.int64)
    if data.size < HEADER_SLOTS or data[_H_MAGIC] != MAGIC or data[_H_VERSION] != VERSION:
        raise ValueError(f"{path} is not a loop phase file")
    width, capacity, count = (int(data[i]) for i in (_H_COLUMNS, _H_CAPACITY, _H_COUNT))
    if width != len(COLUMNS):
        raise ValueError(f"{path} has {width} columns, this reader knows {len(COLUMNS)}")
    rows = data[HEADER_SLOTS:].reshape(capacity, width)
    # The writer may be writing the row after ``count``: leave one out.
    start = max(since, count - capacity + 1)
    if count <= start:
        return rows[:0].copy(), count
    index = np.arange(start, count) % capacity
    return rows[index], count


def summarise(rows: NDArray[np.int64]) -> dict[str, dict[str, float]]:
    """Per phase (and each parent's ``rest``): ``runs`` (cycles where it took any time),
    ``p50``, ``p99`` and ``max`` over every cycle (0 where it did not run), and ``mean``,
    microseconds. Percentiles are nearest-rank."""
    columns = {name: rows[:, i] for i, name in enumerate(COLUMNS)}
    for parent in ("cycle", "period"):
        children = [c for c, p in PARENT.items() if p == parent]
        columns[f"{parent}: rest"] = columns[parent] - sum(columns[c] for c in children)
    n = rows.shape[0]
    out = {}
    for name, values in columns.items():
        if n == 0:
            out[name] = {"runs": 0, "p50": math.nan, "p99": math.nan, "max": math.nan,
                         "mean": math.nan}
            continue
        ranks = (max(0, -(-50 * n // 100) - 1), max(0, -(-99 * n // 100) - 1), n - 1)
        picked = np.partition(values, ranks)
        out[name] = {
            "runs": int(np.count_nonzero(values)),
            "p50": picked[ranks[0]] / 1e3,
            "p99": picked[ranks[1]] / 1e3,
            "max": picked[ranks[2]] / 1e3,
            "mean": float(values.mean()) / 1e3,
        }
    return out
