"""The receive buffer under the serial drivers' incremental frame decoders.

A decoder (Dynamixel Protocol 2.0, Feetech) is fed chunks of bytes as they arrive and returns
the frames they complete; what is not yet a frame waits here, and what can never be one is
skipped and counted, so that a noisy bus shows up in the counters instead of as silence.
"""

from __future__ import annotations

__all__ = ["StreamBuffer"]


class StreamBuffer:
    """Bytes received and not yet decoded.

    Attributes:
        junk_bytes: bytes skipped while looking for a frame.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.junk_bytes = 0

    @property
    def pending(self) -> int:
        """Bytes held that do not yet form a complete frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Drop a partial frame (counted as junk), e.g. after a long silence on the bus."""
        self._skip(len(self._buf))

    def _skip(self, n: int) -> None:
        """Drop the first ``n`` bytes held, counting them as junk."""
        self.junk_bytes += n
        del self._buf[:n]
