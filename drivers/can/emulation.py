"""What the CAN emulators and the socketcand server share: pacing, push delivery, control.

- :class:`WakeEarly`: when a paced emulator thread wakes before a frame's due time.
- :class:`PushSink` and :func:`attach_sink`: frames other peers send on a python-can virtual
  channel are handed to an emulator at once, in the sender's thread, instead of queued.
- :class:`Timer`: frames due at set times, released by a one-thread socketcand server.
- :class:`ControlSocket`: fault commands to an emulator process, one line each, on a unix
  socket (what a test or an operator in another process uses to brown a motor out).
- :func:`clocks_now`: the monotonic and the wall clock read together, to place a frame's
  receive stamp (wall clock) on the monotonic clock.

The MIT-mode emulator, the CiA 402 emulator and the socketcand server all import this module
and none imports another's, so there is no import circle among them.
"""

from __future__ import annotations

import contextlib
import os
import queue
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import can

__all__ = ["ControlSocket", "PushSink", "Timer", "WakeEarly", "attach_sink", "clocks_now"]


_CLOCK_PAIR_TRIES = 3
_CLOCK_PAIR_WINDOW_S = 1e-3


def clocks_now() -> tuple[float, float]:
    """``(monotonic, wall)`` read as one instant.

    The wall reading is taken between two monotonic readings and kept when they are less than
    a millisecond apart (up to three tries; else the last): a thread preempted between the two
    reads (100 ms beside busy processes) would otherwise shift every receive stamp placed on
    the monotonic clock by as much, and the emulated motor would move for the wrong time.
    """
    for _ in range(_CLOCK_PAIR_TRIES):
        before = time.monotonic()
        wall = time.time()
        after = time.monotonic()
        if after - before < _CLOCK_PAIR_WINDOW_S:
            break
    return (before + after) / 2.0, wall


class WakeEarly:
    """When a paced emulator thread should wake before a frame's due time, learnt.

    Timed waits of a thread in a process with other Python threads wake late (30-130 us on
    the development machine: timer, scheduler, a virtual CPU leaving idle, the interpreter
    lock), which would add to every cycle a driver measures against the emulator. The
    thread wakes :attr:`early_s` before the due time and spins the rest. ``early_s`` follows
    a high quantile of the observed lateness of the timed waits (faster up than down) plus
    a small margin, bounded by :attr:`MAX_EARLY_S`, so the spin is usually a few tens of
    microseconds and the frame leaves at its modelled time (a wake later than that releases
    it late by the difference). Emulators only: the driver never spins.
    """

    MARGIN_S = 10e-6
    MAX_EARLY_S = 200e-6

    def __init__(self) -> None:
        self.lateness_s = 50e-6

    @property
    def early_s(self) -> float:
        """How long before a due time to end the timed wait."""
        return min(self.lateness_s + self.MARGIN_S, self.MAX_EARLY_S)

    def observe(self, planned: float, woke: float) -> None:
        """A timed wait meant to end at ``planned`` (monotonic) ended at ``woke``."""
        late = woke - planned
        if late < 0.0:
            return  # ended by an event, not by its timeout: says nothing
        # Up a quarter of the way, down a 32nd: tracks a high quantile of the lateness, not
        # its rare outliers (a release that late is late; one that early spins longer).
        step = 4.0 if late > self.lateness_s else 32.0
        self.lateness_s = min(self.lateness_s + (late - self.lateness_s) / step,
                              self.MAX_EARLY_S)

    @staticmethod
    def spin_until(due: float) -> None:
        """Spin to ``due`` (callers only do so within :attr:`early_s` of it)."""
        while time.monotonic() < due:
            pass


class PushSink:
    """Stands in for an emulator bus's receive queue in push mode: frames other peers send
    are handed to ``handle`` at once, in their thread (MIT motors and CiA 402 drives alike).

    Args:
        handle: called with each frame sent on the channel by another peer.
    """

    def __init__(self, handle: Callable[[can.Message], object]) -> None:
        self.handle = handle

    def put(self, msg: can.Message, block: bool = True, timeout: float | None = None) -> None:
        self.handle(msg)

    def put_nowait(self, msg: can.Message) -> None:
        self.handle(msg)

    def get(self, block: bool = True, timeout: float | None = None) -> can.Message:
        raise queue.Empty

    def get_nowait(self) -> can.Message:
        raise queue.Empty

    def empty(self) -> bool:
        return True

    def qsize(self) -> int:
        return 0


class Timer(Protocol):
    """Frames due at set times, released by a one-thread :class:`SocketcandServer`."""

    def next_due(self) -> float | None:
        """The monotonic time the next frame is due (``None``: nothing pending)."""

    def release_due(self, now: float) -> None:
        """Send every frame due at or before ``now``."""


def attach_sink(bus: can.BusABC, sink: Any) -> None:
    """Replace a python-can virtual bus's receive queue by ``sink`` (an object with
    ``put(msg, block, timeout)``), in the channel's list of receivers too, so that frames
    other peers send reach the sink in their thread and the bus's own frames still skip it.
    Nothing may ``recv`` from that bus afterwards.

    Raises:
        AttributeError, ValueError: python-can's virtual bus is not laid out as expected.
    """
    from can.interfaces import virtual

    with virtual.channels_lock:
        receivers = bus.channel  # type: ignore[attr-defined]
        index = receivers.index(bus.queue)  # type: ignore[attr-defined]
        receivers[index] = sink
        bus.queue = sink  # type: ignore[attr-defined]


class ControlSocket:
    """A unix stream socket taking one-line commands, each answered with one line.

    One thread accepts connections and serves them one at a time (commands are rare: a test
    or an operator injecting a fault). Each line is given to ``handle``, whose return value
    is the answer (``"ok"``, or ``"error: ..."``); a ``ValueError`` or ``KeyError`` it
    raises is answered ``error: <text>``.

    Raises:
        OSError: the socket cannot be bound at ``path`` (an existing file is replaced).
    """

    def __init__(self, path: str, handle: Callable[[str], str]) -> None:
        self.path = path
        self._handle = handle
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.bind(path)
        self._sock.listen(4)
        self._sock.settimeout(0.2)  # how often the thread looks at its stop flag
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="emulator-control",
                                        daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # closed
            with conn, conn.makefile("rw", encoding="utf-8", newline="\n") as stream:
                conn.settimeout(None)
                for line in stream:
                    if not line.strip():
                        continue
                    try:
                        answer = self._handle(line.strip())
                    except (ValueError, KeyError) as exc:
                        answer = f"error: {exc}"
                    stream.write(answer.replace("\n", " ") + "\n")
                    stream.flush()

    def close(self) -> None:
        """Stop serving and remove the socket file."""
        self._stop.set()
        self._sock.close()
        self._thread.join(2.0)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)
