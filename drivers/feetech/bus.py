"""The Feetech bus: the one module that imports ``scservo_sdk``.

Theory of operation
-------------------
:class:`FeetechBus` wraps the SDK's ``PortHandler`` and packet handler (PyPI
``feetech-servo-sdk`` 1.0.0, the package LeRobot uses) for one bus of STS/SMS or SCS servos, and
exposes snake_case calls that either return good data or raise an error naming the servo and the
cause. The SDK's return codes never leave this module. One bus carries one series
(:class:`~jtc_hw.drivers.feetech.control_table.Series`): its byte order, and whether its servos
answer a Sync Read.

The SDK has traps, each handled here (the facts are in :mod:`.control_table`, "Notes for the SDK
wrapper"):

* **Byte order is process-global.** ``PacketHandler(end)`` (0: little-endian words, STS/SMS; 1:
  big-endian, SCS) stores ``end`` in a module global that every word helper of the SDK reads
  (``SCS_MAKEWORD``, ``SCS_LOBYTE``, its ``ping``'s model number, ``GroupSyncRead.getData``), so a
  second bus of the other series in the same process flips the first one's. The handler is
  still made with the series' end (``PacketHandler(series.sdk_protocol_end)``), as a reader of
  the SDK expects, but no word goes through those helpers: every value is packed and unpacked by
  our codec (:func:`.codec.encode_value` / :func:`.codec.unpack_word`) in the series' order, and
  :meth:`FeetechBus.ping` reads the model number itself.
* **Sign-magnitude registers** (STS/SMS: positions and speeds bit 15, present load bit 10, homing
  offset bit 11): the codec encodes and decodes them; the SDK hands out raw words.
* **The packet timeout, which LeRobot patches.** ``setPacketTimeout(n)`` allows the wire time of
  the ``n`` status bytes plus ``2 * LATENCY_TIMER + 2`` = 34 ms, counted from when ``writePort``
  returned, i.e. before the instruction has left the USB adapter, with no room for the request's
  own wire time nor for the servo's Return Delay Time (500 us from the factory); LeRobot replaces
  it with the wire time plus 3 bytes plus 50 ms (``patch_setPacketTimeout``, citing Feetech's
  issue IBY2S6, fixed in Feetech's own FTServo_Python, which is not on PyPI). Here
  :class:`_Port` computes every deadline from what the transaction really takes: the request's
  and the replies' wire time at the baud rate, each reply's return delay, plus ``timeout_ms``
  (an allowance for the adapter and the host, given per bus; the SDK's constant is not touched).
* **Wall-clock timeouts.** The SDK times packets with ``time.time()``; an NTP step would stretch
  or cut a timeout. :class:`_Port` uses ``time.monotonic_ns()``.
* **Busy polling.** The SDK opens the port with ``timeout=0`` and calls ``readPort`` in a loop
  until the deadline: a core at 100 % while waiting. :class:`_Port` blocks in ``select()`` until
  bytes arrive or the deadline passes.
* **The input is never cleared.** The SDK's ``clearPort`` calls ``ser.flush()``, which waits for
  the *output* to drain; the input keeps whatever a late reply left there, and the next
  transaction takes it for its own answer. :class:`_Port` clears the input before every request,
  and after a failed transaction the line is drained until quiet (bounded).
* **GroupSyncRead keeps stale data.** After a failed ``txRxPacket`` its ``getData`` still returns
  the previous read's bytes for the servos after the one that failed (``isAvailable`` ignores the
  result: the check is commented out) and 0 for that one: a timeout would become an old or a zero
  position. The sync read here is our own (the request from our codec, the replies through our
  decoder): it returns data only when every servo answered with a good checksum, and raises
  otherwise, naming the first servo that did not. SCS servos know no Sync Read (LeRobot:
  "not available with Feetech motors using Protocol 1"): :meth:`FeetechBus.group_read` reads them
  one at a time, with the same all-or-nothing rule.
* **The status byte.** Every status packet carries the servo's Status bits (voltage, angle
  sensor, overheat, overcurrent, overload); the SDK drops them in ``GroupSyncRead``. Here they are
  returned per servo (:attr:`GroupReadResult.errors`), so that the hardware sees an overload in
  the cycle's own read.
* **Stuck busy flag.** ``port.is_using`` stays set if anything raises inside a transaction, after
  which every call returns "port busy"; it is reset after every transaction.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Final

import scservo_sdk as _sdk  # type: ignore[import-untyped]

from ..sdk_port import BusStats as _BusStats
from ..sdk_port import DescriptorIO, SdkBusErrors, ServoCommunicationError
from .codec import Decoder, Instruction, encode_sync_read, encode_sync_write, unpack_word
from .control_table import Series

__all__ = [
    "SDK_BAUD_RATES",
    "BusStats",
    "FeetechBus",
    "GroupReadResult",
    "ServoCommunicationError",
]

_log = logging.getLogger(__name__)

#: The baud rates the SDK's ``PortHandler`` accepts (``getCFlagBaud``) that the servos have too.
SDK_BAUD_RATES: Final = (38_400, 57_600, 115_200, 128_000, 250_000, 500_000, 1_000_000)
MAX_ID: Final = 252  # the SDK's MAX_ID (0xFC)
_STATUS_OVERHEAD: Final = 6  # FF FF id len error ... checksum
#: Bytes allowed for a single-servo request in a deadline the SDK arms (``setPacketTimeout``
#: is told only the reply's length): the longest one sent here, a 2-byte write, is 9.
_SINGLE_REQUEST_BYTES: Final = 9

_COMM_SUCCESS: Final[int] = _sdk.COMM_SUCCESS
_COMM_CAUSES: Final[Mapping[int, str]] = {
    _sdk.COMM_PORT_BUSY: "port busy (another transaction in progress)",
    _sdk.COMM_TX_FAIL: "could not transmit the instruction packet",
    _sdk.COMM_RX_FAIL: "no status packet",
    _sdk.COMM_TX_ERROR: "malformed instruction packet",
    _sdk.COMM_RX_WAITING: "status packet incomplete",
    _sdk.COMM_RX_TIMEOUT: "timeout (no reply)",
    _sdk.COMM_RX_CORRUPT: "corrupt reply (checksum or framing error)",
    _sdk.COMM_NOT_AVAILABLE: "instruction not available",
}


def _check_id(servo_id: int) -> None:
    if not isinstance(servo_id, int) or isinstance(servo_id, bool) or not 0 <= servo_id <= MAX_ID:
        raise ValueError(f"servo id must be an integer in 0..{MAX_ID}, got {servo_id!r}")


@dataclass(frozen=True)
class GroupReadResult:
    """A successful group read (every servo answered with a good checksum).

    Attributes:
        data: servo id -> the ``size`` bytes read, for every servo asked.
        errors: servo id -> the status packet's Status bits, only where they are not 0.
    """

    data: Mapping[int, bytes]
    errors: Mapping[int, int]


class BusStats(_BusStats):
    """Counters of one bus (JSON-able with :meth:`as_dict`); the hardware counts retries.
    Feetech's status has called its corrupt replies ``checksum_errors``."""

    CORRUPT_KEY: ClassVar[str] = "checksum_errors"

    @property
    def checksum_errors(self) -> int:
        """Replies whose checksum did not match (``corrupt``, by Feetech's name)."""
        return self.corrupt


class _Port(DescriptorIO, _sdk.PortHandler):  # type: ignore[misc]
    """``PortHandler`` with monotonic time, a blocking bounded read (``DescriptorIO``), an
    input that is cleared before each request, and deadlines from the transaction's real
    duration."""

    def __init__(self, port_name: str, allowance_ms: float, return_delay_ms: float) -> None:
        super().__init__(port_name)
        self.init_io()
        self.allowance_ms = allowance_ms
        self.return_delay_ms = return_delay_ms

    # The SDK's names are kept on this subclass only: they are what it calls.
    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802 - SDK override
        # The SDK arms this after a single-servo request, with the reply's byte count: the
        # request's and the reply's wire time, the servo's return delay, our allowance.
        self.arm(self.tx_time_per_byte * (packet_length + _SINGLE_REQUEST_BYTES)
                 + self.return_delay_ms)

    def arm(self, expected_ms: float) -> None:
        """The deadline of a transaction expected to take ``expected_ms`` on the wire."""
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = expected_ms + self.allowance_ms

    def clearPort(self) -> None:  # noqa: N802 - SDK override
        # The SDK's flushes the output only; a late reply left in the input would be taken
        # for the next request's answer.
        self.drop_input()
        self.ser.reset_input_buffer()


class FeetechBus(SdkBusErrors):
    """One bus of Feetech servos of one series on a serial port.

    Args:
        port: serial device (``/dev/ttyACM0``, a ``/dev/serial/by-id/...`` link, a pty).
        baud_rate: bit/s, one of :data:`SDK_BAUD_RATES` (the servos' factory rate: 1000000).
        series: the servos' register family (byte order, Sync Read).
        timeout_ms: allowance beyond a transaction's wire time and return delays before a reply
            counts as missing (the USB adapter's latency, the host's scheduling).
        return_delay_us: the servos' Return Delay Time, us (it delays each reply).

    Raises:
        ValueError: ``timeout_ms`` is not positive, or a baud rate the SDK cannot set.
    """

    VENDOR: ClassVar[str] = "Feetech"
    """Named in its communication errors (``SdkBusErrors``)."""

    def __init__(
        self,
        port: str,
        baud_rate: int,
        series: Series,
        *,
        timeout_ms: float = 20.0,
        return_delay_us: float = 0.0,
    ) -> None:
        if not timeout_ms > 0:
            raise ValueError(f"timeout_ms must be > 0, got {timeout_ms!r}")
        if baud_rate not in SDK_BAUD_RATES:
            raise ValueError(f"baud rate {baud_rate} is not one the servos and the SDK share; "
                             f"use one of {', '.join(map(str, SDK_BAUD_RATES))}")
        self.port = port
        self.baud_rate = baud_rate
        self.series = series
        self.timeout_ms = float(timeout_ms)
        self.stats = BusStats()
        self._port = _Port(port, self.timeout_ms, return_delay_us / 1000.0)
        # Made with the series' end (the SDK's global), but no word passes the SDK's helpers.
        self._handler = _sdk.PacketHandler(series.sdk_protocol_end)
        self._open = False
        self._byte_ms = 10_000.0 / baud_rate  # one byte on the wire (8N1), ms
        self._sync_reads: dict[tuple[int, int, tuple[int, ...]], bytes] = {}

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        return self._open

    def __repr__(self) -> str:
        state = "open" if self._open else "closed"
        return f"<FeetechBus {self.port} {self.baud_rate} bit/s {self.series.name.value} {state}>"

    # -- port -----------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the port at the configured baud rate.

        Raises:
            ServoCommunicationError: the port cannot be opened (the message says what to check).
        """
        if self._open:
            return
        self._port.baudrate = self.baud_rate
        try:
            ok = self._port.openPort()
        except Exception as exc:  # serial.SerialException, OSError
            raise ServoCommunicationError(
                f"Feetech bus {self.port}: cannot open the port: {exc}; check that the adapter "
                "is plugged in, the path is right and you may access it (group dialout)",
                None, "cannot open port",
            ) from exc
        if not ok:
            raise ServoCommunicationError(
                f"Feetech bus {self.port}: cannot set {self.baud_rate} bit/s", None,
                "cannot set baud rate")
        self._open = True

    def close(self) -> None:
        """Close the port (idempotent)."""
        if not self._open:
            return
        self._open = False
        try:
            self._port.closePort()
        except Exception as exc:  # noqa: BLE001 - closing must not fail the caller
            _log.warning("Feetech bus %s: closing the port failed: %s", self.port, exc)

    # -- single-servo transactions --------------------------------------------------------------

    def ping(self, servo_id: int) -> int:
        """Ping a servo, then read its model number (address 3) in the series' byte order.

        Returns:
            The model number.

        Raises:
            ValueError: bad id.
            ServoCommunicationError: no reply, corrupt reply, or the port failed.
        """
        _check_id(servo_id)
        packet = [0xFF, 0xFF, servo_id, 2, int(Instruction.PING), 0]
        self._transact(servo_id, "ping", lambda: self._handler.txRxPacket(self._port, packet))
        return unpack_word(self.read_bytes(servo_id, 3, 2), self.series.byte_order)

    def read_bytes(self, servo_id: int, address: int, size: int) -> bytes:
        """Read ``size`` bytes from ``address`` of one servo.

        Raises:
            ValueError: bad id or size.
            ServoCommunicationError: no reply, corrupt reply, or the port failed.
        """
        return self._read_one(servo_id, address, size)[0]

    def _read_one(self, servo_id: int, address: int, size: int) -> tuple[bytes, int]:
        """One READ: the data and the Status bits of the reply."""
        _check_id(servo_id)
        if not 0 < size <= 0xFF:
            raise ValueError(f"size must be 1..255, got {size}")
        what = f"read of {size} bytes at address {address}"
        data, error = self._transact(
            servo_id, what, lambda: self._handler.readTxRx(self._port, servo_id, address, size))
        if len(data) != size:
            raise self._comm_error(servo_id, "corrupt reply (wrong length)", what)
        return bytes(data), int(error)

    def write_bytes(self, servo_id: int, address: int, data: bytes) -> int:
        """WRITE ``data`` (a register's bytes from :func:`.codec.encode_value`) at ``address``.

        Returns:
            The reply's Status bits (a Feetech servo has no bit to refuse a write with: they
            report its state).

        Raises:
            ValueError: bad id or no data.
            ServoCommunicationError: no reply, corrupt reply, or the port failed.
        """
        _check_id(servo_id)
        if not data:
            raise ValueError("a write needs at least one byte")
        what = f"write of {bytes(data).hex()} at address {address}"
        _, error = self._transact(
            servo_id, what,
            lambda: (None, *self._handler.writeTxRx(self._port, servo_id, address, len(data),
                                                    list(data))))
        return int(error)

    # -- group transactions ---------------------------------------------------------------------

    def group_read(self, ids: Sequence[int], address: int, size: int) -> GroupReadResult:
        """``size`` bytes at ``address`` of every servo of ``ids``: one Sync Read on STS/SMS,
        one READ per servo on SCS (which has no Sync Read).

        All or nothing: either every servo answered with a good packet, or this raises (no
        partial, stale or zero-filled data is ever returned).

        Raises:
            ValueError: no ids or a bad id.
            ServoCommunicationError: a servo did not answer or its reply was corrupt; names the
                first servo (in request order) that failed.
        """
        if not self.series.sync_read:
            data: dict[int, bytes] = {}
            errors: dict[int, int] = {}
            for servo_id in ids:
                data[servo_id], error = self._read_one(servo_id, address, size)
                if error:
                    errors[servo_id] = error
            if not data:
                raise ValueError("a group read needs at least one servo id")
            return GroupReadResult(data, errors)
        return self._sync_read(tuple(ids), address, size)

    def _sync_read(self, ids: tuple[int, ...], address: int, size: int) -> GroupReadResult:
        key = (address, size, ids)
        request = self._sync_reads.get(key)
        if request is None:
            for servo_id in ids:
                _check_id(servo_id)
            request = encode_sync_read(address, size, ids)  # ValueError: no ids, duplicates
            if len(self._sync_reads) >= 16:
                self._sync_reads.clear()  # bounded, whatever a caller asks for
            self._sync_reads[key] = request
        what = f"sync read of {size} bytes at address {address}"
        port = self._port
        self.stats.transactions += 1
        if not self._open:
            raise self._comm_error(None, "the port is not open", what)
        try:
            port.clearPort()
            if port.writePort(request) != len(request):
                raise self._comm_error(None, _COMM_CAUSES[_sdk.COMM_TX_FAIL], what)
            reply = _STATUS_OVERHEAD + size
            port.arm(self._byte_ms * (len(request) + reply * len(ids))
                     + port.return_delay_ms * len(ids))
            return self._sync_read_rx(ids, size, what)
        except ServoCommunicationError:
            self._recover_port()
            raise
        except Exception as exc:
            self._recover_port()
            raise self._comm_error(None, f"{type(exc).__name__}: {exc}", what) from exc
        finally:
            port.is_using = False

    def _sync_read_rx(self, ids: tuple[int, ...], size: int, what: str) -> GroupReadResult:
        """Collect one status packet per servo of ``ids``, in order, until the deadline.

        Raises:
            ServoCommunicationError: naming the first servo without a good reply.
        """
        port = self._port
        decoder = Decoder(status=True)
        data: dict[int, bytes] = {}
        errors: dict[int, int] = {}
        index = 0
        while True:
            chunk = port.readPort(4096)  # whatever has arrived; blocks up to the deadline
            if not chunk:
                cause = _COMM_CAUSES[_sdk.COMM_RX_CORRUPT if decoder.pending
                                     else _sdk.COMM_RX_TIMEOUT]
                raise self._comm_error(ids[index], cause, what)
            for packet in decoder.feed(chunk):
                servo_id = ids[index]
                if not packet.checksum_ok:
                    raise self._comm_error(servo_id, _COMM_CAUSES[_sdk.COMM_RX_CORRUPT], what)
                if packet.id != servo_id:
                    continue  # as the SDK's readRx: not the reply waited for
                if len(packet.params) != size:
                    raise self._comm_error(servo_id, "corrupt reply (wrong length)", what)
                data[servo_id] = packet.params
                if packet.code:
                    errors[servo_id] = packet.code
                index += 1
                if index == len(ids):
                    return GroupReadResult(data, errors)

    def sync_write(self, address: int, data: Mapping[int, bytes]) -> None:
        """One Sync Write of the same number of bytes to each servo: ``{id: bytes}`` (the
        register's bytes from :func:`.codec.encode_value`). No replies: the servos' state shows
        in the next read.

        Raises:
            ValueError: a bad id, chunks of different lengths.
            ServoCommunicationError: the port failed.
        """
        if not data:
            return
        size = len(next(iter(data.values())))
        packet = encode_sync_write(address, size, data)  # ValueError: ids, lengths
        what = f"sync write of {size} bytes at address {address}"
        self.stats.transactions += 1
        if not self._open:
            raise self._comm_error(None, "the port is not open", what)
        try:
            written = self._port.writePort(packet)
        except Exception as exc:
            raise self._comm_error(None, f"{type(exc).__name__}: {exc}", what) from exc
        if written != len(packet):
            raise self._comm_error(None, _COMM_CAUSES[_sdk.COMM_TX_FAIL], what)

    # -- helpers --------------------------------------------------------------------------------

    def _transact(self, servo_id: int, what: str, call: Any) -> tuple[Any, int]:
        """Run one SDK transaction; ``(its value, the reply's Status bits)``.

        Raises:
            ServoCommunicationError: the SDK's result was not a success.
        """
        if not self._open:
            raise ServoCommunicationError(
                f"Feetech bus {self.port}: {what} on servo {servo_id}: the port is not open",
                servo_id, "port not open")
        self.stats.transactions += 1
        try:
            value, result, error = call()
        except Exception as exc:
            self._recover_port()
            raise self._comm_error(servo_id, f"{type(exc).__name__}: {exc}", what) from exc
        finally:
            self._port.is_using = False
        if result != _COMM_SUCCESS:
            self._recover_port()
            raise self._comm_error(servo_id, _COMM_CAUSES.get(result, f"error {result}"), what)
        return value, int(error)
