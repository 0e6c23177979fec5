"""Fast, bounded I/O under the vendors' serial SDKs (Dynamixel's and Feetech's ``PortHandler``).

Both SDKs (Feetech's derives from ROBOTIS') read a reply a few bytes at a time through
``readPort``, spin on ``getTimeSinceStart`` against a wall-clock deadline, and write through
pyserial, whose ``write`` adds a timeout object and a ``select`` per call. Each bus wrapper
(``drivers/dynamixel/bus.py``, ``drivers/feetech/bus.py``, the only modules importing their
SDK) mixes :class:`DescriptorIO` in before the SDK's ``PortHandler``: the time is the monotonic
clock; a read takes whatever has arrived in one system call and serves the SDK from a buffer,
blocking in ``select`` until bytes or the SDK's deadline, never spinning; a write goes straight
to the descriptor. The deadline (``packet_timeout``) stays each wrapper's own business.

What the two wrappers also share after a failed transaction: :class:`SdkBusErrors` counts it in
the bus's :class:`BusStats`, names it in one :class:`ServoCommunicationError` message (vendor,
servo, port, bit rate, what to check) and drains late replies so that none is taken for the
next request's.
"""

from __future__ import annotations

import os
import select
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

from jtc_hw.errors import CommunicationError

__all__ = ["BusStats", "DescriptorIO", "SdkBusErrors", "ServoCommunicationError"]


class ServoCommunicationError(CommunicationError):
    """A servo did not answer, or answered garbage.

    Attributes:
        servo_id: the servo concerned (``None``: the bus itself, e.g. the port).
        cause: short cause (``"timeout (no reply)"``, ``"corrupt reply ..."``).
    """

    def __init__(self, message: str, servo_id: int | None, cause: str) -> None:
        super().__init__(message)
        self.servo_id = servo_id
        self.cause = cause


@dataclass
class BusStats:
    """Counters of one bus (JSON-able with :meth:`as_dict`; ``CORRUPT_KEY`` names the corrupt
    replies there, as each family's status has always called them)."""

    CORRUPT_KEY: ClassVar[str] = "corrupt"

    transactions: int = 0
    timeouts: int = 0
    corrupt: int = 0
    other_errors: int = 0
    last_error: str | None = None
    by_servo: dict[int, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """The counters as a JSON-able mapping."""
        return {
            "transactions": self.transactions,
            "timeouts": self.timeouts,
            self.CORRUPT_KEY: self.corrupt,
            "other_errors": self.other_errors,
            "last_error": self.last_error,
            "errors_by_servo": {str(k): v for k, v in sorted(self.by_servo.items())},
        }


class SdkBusErrors:
    """A bus wrapper's failed transactions (a mixin: the wrapper has these attributes)."""

    VENDOR: ClassVar[str]
    port: str
    baud_rate: int
    timeout_ms: float
    stats: BusStats
    _port: Any  # the wrapper's DescriptorIO PortHandler
    _open: bool

    def _comm_error(self, servo_id: int | None, cause: str, what: str) -> ServoCommunicationError:
        """Count the failure and describe it (raised by the caller)."""
        if cause.startswith("timeout"):
            self.stats.timeouts += 1
        elif cause.startswith("corrupt"):
            self.stats.corrupt += 1
        else:
            self.stats.other_errors += 1
        if servo_id is not None:
            self.stats.by_servo[servo_id] = self.stats.by_servo.get(servo_id, 0) + 1
            who = f"servo {servo_id}"
        else:
            who = "the bus"
        message = (
            f"{self.VENDOR} {who} on {self.port} ({self.baud_rate} bit/s): {what}: {cause}; "
            "check its power, cable and id, and that every servo uses this baud rate"
        )
        self.stats.last_error = message
        return ServoCommunicationError(message, servo_id, cause)

    def _recover_port(self) -> None:
        """After a failure: drop late replies so that they are not taken for the next one."""
        self._port.is_using = False
        if self._open:
            try:
                self._port.drain(min(self.timeout_ms, 20.0) / 1000.0)
            except OSError:
                pass


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
