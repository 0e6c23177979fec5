"""Shared memory for the plans the API process hands to the loop: sealed ``memfd`` regions,
and the API process's pool of them.

Theory of operation
-------------------
A plan of tens of megabytes copied through the socket takes the loop a dozen cycles to read
(docs/decisions.md 17). Instead, :func:`~.pipe.prepare` writes the plan's arrays into a region
of shared memory and the pipe carries only its head and the region's descriptor; the loop maps
the region and reads the arrays in place (:class:`~.pipe.Inbox`), in the cycle the record
arrives.

Two costs decide the rest, measured here for 24 MB (a 20,000-point plan):

- **Giving memory to a region costs more than copying into it**: 5.7 ms to allocate the pages
  of a new ``memfd``, 1.7 ms to copy the plan into pages it already has. So the API process
  keeps its regions (:class:`SharedPool`) and reuses one once the loop says it has unmapped it
  (``Released``), and drops the idle ones after :data:`IDLE_S` (the memory goes back to the
  system, as after any large plan).
- **Freeing a region's pages costs 4 ms** (24 MB), paid by whoever drops the last reference to
  it. The pool keeps its descriptor until the loop has released the region, so that is always
  the API process (in a worker thread), never the loop: the loop's unmapping only removes its
  page-table entries (:class:`~.pipe.Inbox` does that a chunk at a time, in spare time).

A region is sealed against shrinking and growing (``F_SEAL_SHRINK | F_SEAL_GROW``), and the
loop maps only regions so sealed: a page cut off under its mapping would kill it with SIGBUS.
Nothing else writes a region while the loop may read it: the pool hands it out again only
after ``Released``.
"""

from __future__ import annotations

import fcntl
import mmap
import os
import threading
import time
from dataclasses import dataclass, field

__all__ = [
    "IDLE_S",
    "SEALS",
    "SHARED_AVAILABLE",
    "Region",
    "SharedPool",
    "layout",
    "new_memfd",
]

SHARED_AVAILABLE = hasattr(os, "memfd_create") and hasattr(fcntl, "F_ADD_SEALS")
"""Linux: ``memfd_create`` and file seals. Elsewhere plans go through the socket."""

SEALS = (fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL) if SHARED_AVAILABLE else 0
"""What every region is sealed with, and what the loop checks before it maps one."""

ALIGN = 64
"""Each array starts on a cache line."""

REGION_ROUND = 1 << 20
"""A new region's size is rounded up to this, so that plans of about the same size share one."""

REUSE_SLACK = 2
"""A free region is reused for a plan at least ``1 / REUSE_SLACK`` of its size."""

IDLE_S = 5.0
"""A free region unused this long is dropped (its memory returned to the system)."""


def layout(sizes: list[int]) -> tuple[list[int], int]:
    """Where each of arrays of ``sizes`` bytes starts in a region, and the bytes they span."""
    offsets, at = [], 0
    for size in sizes:
        offsets.append(at)
        at += -(-size // ALIGN) * ALIGN
    return offsets, max(at, 1)


def new_memfd(size: int) -> int:
    """A sealed ``memfd`` of ``size`` bytes (reads as zeros; no memory given to it yet).

    Raises:
        OSError: the system refused (out of descriptors or memory).
    """
    fd = os.memfd_create("jtc-hw-plan", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    try:
        os.ftruncate(fd, size)
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, SEALS)
    except BaseException:
        os.close(fd)
        raise
    return fd


@dataclass(eq=False)
class Region:
    """A region of the pool: its descriptor, the API process's mapping of it, its token."""

    token: int
    fd: int
    mapping: mmap.mmap
    size: int
    busy: bool = True
    freed_at: float = field(default=0.0)

    def write(self, at: int, data: memoryview) -> None:
        """Copy ``data`` into the region at offset ``at``."""
        self.mapping[at : at + data.nbytes] = data

    def close(self) -> None:
        """Unmap and close (frees the memory once the loop has none of it mapped)."""
        self.mapping.close()
        os.close(self.fd)


class SharedPool:
    """The API process's regions: :meth:`acquire` one for a plan (a free one big enough, else a
    new one), :meth:`released` when the loop has unmapped it, :meth:`trim` the idle ones.

    Thread-safe: plans are prepared in worker threads, ``Released`` arrives in the event loop.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._regions: dict[int, Region] = {}
        self._next_token = 1
        self.closed = False
        self.made = 0
        """Regions made (each paid its pages' allocation)."""
        self.reused = 0
        """Plans written into a region made for an earlier one."""
        self.dropped = 0
        """Regions dropped after :data:`IDLE_S` unused."""

    def acquire(self, nbytes: int) -> Region:
        """A region of at least ``nbytes``, marked busy until :meth:`released`.

        Raises:
            OSError: a new region could not be made (out of memory or descriptors).
        """
        with self._lock:
            fits = [
                r for r in self._regions.values()
                if not r.busy and nbytes <= r.size <= REUSE_SLACK * max(nbytes, REGION_ROUND)
            ]
            if fits:
                region = min(fits, key=lambda r: r.size)
                region.busy = True
                self.reused += 1
                return region
            token = self._next_token
            self._next_token += 1
            self.made += 1
        size = -(-max(nbytes, 1) // REGION_ROUND) * REGION_ROUND
        fd = new_memfd(size)
        try:
            mapping = mmap.mmap(fd, size, flags=mmap.MAP_SHARED,
                                prot=mmap.PROT_READ | mmap.PROT_WRITE)
        except BaseException:
            os.close(fd)
            raise
        region = Region(token, fd, mapping, size)
        with self._lock:
            if self.closed:
                region.close()
                raise OSError("the pool of shared memory is closed (the loop is gone)")
            self._regions[token] = region
        return region

    def released(self, tokens: tuple[int, ...], now: float | None = None) -> None:
        """The loop unmapped these regions: free for reuse (unknown tokens are ignored)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            for token in tokens:
                region = self._regions.get(token)
                if region is not None:
                    region.busy = False
                    region.freed_at = now

    def unsent(self, region: Region) -> None:
        """``region`` was acquired but its plan never reached the loop: free for reuse."""
        self.released((region.token,))

    def trim(self, idle_s: float = IDLE_S, now: float | None = None) -> int:
        """Drop the free regions unused for ``idle_s``; the bytes dropped. Costs the freeing of
        their pages (4 ms for 24 MB): call it from a worker thread."""
        now = time.monotonic() if now is None else now
        with self._lock:
            idle = [r for r in self._regions.values()
                    if not r.busy and now - r.freed_at >= idle_s]
            for region in idle:
                del self._regions[region.token]
            self.dropped += len(idle)
        for region in idle:
            region.close()
        return sum(r.size for r in idle)

    @property
    def free_bytes(self) -> int:
        """Bytes of the regions waiting for reuse."""
        with self._lock:
            return sum(r.size for r in self._regions.values() if not r.busy)

    @property
    def busy_bytes(self) -> int:
        """Bytes of the regions the loop may still read."""
        with self._lock:
            return sum(r.size for r in self._regions.values() if r.busy)

    def status(self) -> dict[str, int]:
        """For ``get_status``: the regions, their bytes in the loop's hands and waiting for
        reuse, and the counters."""
        with self._lock:
            regions = list(self._regions.values())
            return {
                "regions": len(regions),
                "busy_bytes": sum(r.size for r in regions if r.busy),
                "free_bytes": sum(r.size for r in regions if not r.busy),
                "made": self.made,
                "reused": self.reused,
                "dropped": self.dropped,
            }

    def close(self) -> None:
        """Drop every region (the loop is gone: nothing reads them any more)."""
        with self._lock:
            regions = list(self._regions.values())
            self._regions.clear()
            self.closed = True
        for region in regions:
            region.close()
