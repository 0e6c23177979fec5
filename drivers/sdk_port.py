"""Fast, bounded I/O under the vendors' serial SDKs (Dynamixel's and Feetech's ``PortHandler``).

Both SDKs (Feetech's derives from ROBOTIS') read a reply a few bytes at a time through
``readPort``, spin on ``getTimeSinceStart`` against a wall-clock deadline, and write through
pyserial, whose ``write`` adds a timeout object and a ``select`` per call. Each bus wrapper
(``drivers/dynamixel/bus.py``, ``drivers/feetech/bus.py``, the only modules importing their
SDK) mixes :class:`DescriptorIO` in before the SDK's ``PortHandler``: the time is the monotonic
clock; a read takes whatever has arrived in one system call and serves the SDK from a buffer,
blocking in ``select`` until bytes or the SDK's deadline, never spinning; a write goes straight
to the descriptor. The deadline (``packet_timeout``) stays each wrapper's own business.
"""

from __future__ import annotations

import os
import select
import time
from typing import Any

__all__ = ["DescriptorIO"]


class DescriptorIO:
    """The ``PortHandler`` methods both SDKs call, on the serial port's descriptor (a mixin:
    ``class _Port(DescriptorIO, sdk.PortHandler)``; call :meth:`init_io` in ``__init__``)."""

    fd: int
    packet_timeout: float
    ser: Any

    def init_io(self) -> None:
        """No descriptor yet (``setupPort`` sets it), nothing buffered."""
        self.fd = -1
        self._rx = bytearray()

    # The SDK's names: they are what it calls.
    def getCurrentTime(self) -> float:  # noqa: N802 - SDK override
        return time.monotonic_ns() / 1e6

    def setupPort(self, cflag_baud: int) -> bool:  # noqa: N802 - SDK override
        ok = bool(super().setupPort(cflag_baud))  # type: ignore[misc]
        self.fd = self.ser.fileno()
        return ok

    def readPort(self, length: int) -> bytes:  # noqa: N802 - SDK override
        # Whatever has arrived is taken in one system call and served from a buffer: the SDK
        # asks for a header first, then the rest, then the next servo's reply; reading only
        # what it asks for doubles the select/read calls per reply. An empty buffer blocks
        # until bytes or the deadline.
        if length <= 0:
            return b""
        rx = self._rx
        if not rx:
            remaining_s = (self.packet_timeout - self.getTimeSinceStart()) / 1000.0
            ready, _, _ = select.select([self.fd], [], [], max(0.0, remaining_s))
            if not ready:
                return b""
            try:
                rx += os.read(self.fd, 4096)
            except BlockingIOError:
                return b""
        data = bytes(rx[:length])
        del rx[:length]
        return data

    def writePort(self, packet: list[int] | bytes) -> int:  # noqa: N802 - SDK override
        # Straight to the descriptor: pyserial's write adds a timeout object and a select per
        # call, which is measurable at 4 Mbit/s.
        data = memoryview(bytes(packet))
        written = 0
        while written < len(data):
            try:
                written += os.write(self.fd, data[written:])
            except BlockingIOError:
                # The adapter's buffer is full; a port that stays full this long is gone (the
                # SDK then reports a transmit failure).
                _, ready, _ = select.select([], [self.fd], [], 0.1)
                if not ready:
                    break
        return written

    def drop_input(self) -> None:
        """Forget what the buffer holds (before a request: a late reply is no answer to it)."""
        self._rx.clear()

    def drain(self, quiet_s: float) -> int:
        """Discard input until the line has been quiet for ``quiet_s``; bytes discarded."""
        discarded = len(self._rx)
        self._rx.clear()
        deadline = time.monotonic() + 10 * quiet_s  # bounded even if a servo keeps talking
        while time.monotonic() < deadline:
            ready, _, _ = select.select([self.fd], [], [], quiet_s)
            if not ready:
                break
            try:
                discarded += len(os.read(self.fd, 4096))
            except BlockingIOError:
                break
        return discarded
