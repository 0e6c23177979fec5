"""The Dynamixel bus: the one module that imports ``dynamixel_sdk``.

Theory of operation
-------------------
:class:`DynamixelBus` wraps the ROBOTIS SDK's ``PortHandler`` / ``Protocol2PacketHandler`` for a
Protocol 2.0 bus and exposes snake_case calls that either return good data or raise an error that
names the servo and the cause. The SDK's return codes never leave this module.

The SDK has traps, each handled here:

* **Busy polling.** ``PortHandler`` opens the port with ``timeout=0`` and the packet handler
  calls ``readPort`` in a loop until the packet timeout: one core at 100 % while waiting for a
  reply. :class:`_Port` overrides ``readPort`` to block in ``select()`` until bytes arrive or the
  packet deadline passes, so waiting costs no CPU and a reply is picked up as soon as it lands.
* **Wall-clock timeouts.** ``getCurrentTime`` uses ``time.time()``; an NTP step would stretch or
  cut a timeout. :class:`_Port` uses ``time.monotonic_ns()``.
* **Latency timer.** The SDK's packet timeout is ``wire time + 2 * LATENCY_TIMER + 2 ms`` with
  the module constant ``LATENCY_TIMER = 16`` (ms, the FTDI default): one silent servo stalls a
  read for ~34 ms. Here the allowance beyond the wire time is ``timeout_ms`` (given per bus, the
  SDK constant is not touched), and :meth:`DynamixelBus.open` warns when a USB serial adapter's
  own latency timer (``/sys/bus/usb-serial/devices/<tty>/latency_timer``) is above 1 ms, saying
  how to lower it.
* **getData after a failure.** ``GroupSyncRead.getData`` returns 0 for every servo after a failed
  read: a timeout would become position 0. The sync read here is written against the port
  handler directly (the request, then one status packet per servo), returns bytes only when
  every servo answered, and raises otherwise, naming the first servo that did not answer.
* **Per-byte parsing.** The SDK's ``readRx`` parses each status packet in Python byte by byte
  (header search, CRC); for the six replies of a cycle that is ~100 us at 4 Mbit/s, a fifth of
  the wire time. The sync read here sends a request our codec encoded once and kept (the
  cycle's request is the same every time; the SDK's ``syncReadTx`` rebuilt it in Python: 7.2
  against 3.6 us of CPU a request), doing what ``syncReadTx`` does after building it (flush the
  input, write, arm the port's packet timeout with the SDK's formula), and takes the replies
  from the port handler's ``readPort`` through our own codec
  (:class:`~jtc_hw.drivers.dynamixel.packets.Decoder`), with the SDK's
  rules: packets that are not status packets or come from another servo are skipped, a bad CRC
  is a corrupt reply of the servo waited for, and at the deadline the servo waited for is
  reported as not answering (or as corrupt if part of a packet had arrived).
* **Lost hardware-error bits.** ``GroupSyncRead`` drops the status packets' error byte; here it is
  returned per servo (:attr:`SyncReadResult.errors`) so that the caller sees the alert bit.
* **Fast sync read.** ``GroupSyncRead.fastSyncRead`` indexes past the end of the reply
  (``IndexError``) when a servo is missing. The fast variant here parses the combined reply with
  length and id checks and names the missing servo.
* **Stuck busy flag.** ``port.is_using`` stays set if anything raises inside a transaction, after
  which every call returns "port busy"; it is reset after every transaction.
* **Late replies.** A reply arriving after its timeout would be taken as the answer to the next
  request; after a failed transaction the input is drained (bounded by ``timeout_ms``).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Final

import dynamixel_sdk as _sdk  # type: ignore[import-untyped]

from jtc_hw.errors import HardwareError

from ..sdk_port import BusStats, DescriptorIO, SdkBusErrors, ServoCommunicationError
from .packets import Decoder, crc16, encode_sync_read, encode_sync_write

__all__ = [
    "BROADCAST_ID",
    "ERROR_ALERT",
    "MAX_ID",
    "BusStats",
    "DynamixelBus",
    "ServoCommunicationError",
    "ServoStatusError",
    "SyncReadResult",
    "latency_timer_ms",
    "usb_serial_tty",
]

_log = logging.getLogger(__name__)

BROADCAST_ID: Final = 0xFE
MAX_ID: Final = 252
ERROR_ALERT: Final = 0x80
"""Bit of a status packet's error byte: the servo has a latched hardware error."""

_COMM_SUCCESS: Final[int] = _sdk.COMM_SUCCESS
_COMM_CAUSES: Final[Mapping[int, str]] = {
    _sdk.COMM_PORT_BUSY: "port busy (another transaction in progress)",
    _sdk.COMM_TX_FAIL: "could not transmit the instruction packet",
    _sdk.COMM_RX_FAIL: "no status packet",
    _sdk.COMM_TX_ERROR: "malformed instruction packet",
    _sdk.COMM_RX_WAITING: "status packet incomplete",
    _sdk.COMM_RX_TIMEOUT: "timeout (no reply)",
    _sdk.COMM_RX_CORRUPT: "corrupt reply (CRC or framing error)",
    _sdk.COMM_NOT_AVAILABLE: "instruction not available",
}
_STATUS_CAUSES: Final[Mapping[int, str]] = {
    1: "result fail (the servo could not process the instruction)",
    2: "instruction error",
    3: "the servo received a packet with a bad CRC",
    4: "data range error (value out of range)",
    5: "data length error",
    6: "data limit error (value beyond a limit register)",
    7: "access error (read-only / EEPROM with torque on / no such address)",
}

_FAST_SYNC_READ_OVERHEAD: Final = 4  # per servo in the combined reply: error, id, CRC16
_FAST_STATUS_PREFIX: Final = 8  # header (4), id, length (2), instruction
_SYNC_READ_CACHE: Final = 16  # Sync Read requests kept encoded (present block, health blocks)


def _check_id(servo_id: int) -> None:
    if not isinstance(servo_id, int) or isinstance(servo_id, bool) or not 0 <= servo_id <= MAX_ID:
        raise ValueError(f"servo id must be an integer in 0..{MAX_ID}, got {servo_id!r}")


class ServoStatusError(HardwareError):
    """A servo answered with an error in its status packet (other than the alert bit).

    Attributes:
        servo_id: the servo concerned.
        error: the status packet's error byte.
    """

    def __init__(self, message: str, servo_id: int, error: int) -> None:
        super().__init__(message)
        self.servo_id = servo_id
        self.error = error


@dataclass(frozen=True)
class SyncReadResult:
    """A successful sync read.

    Attributes:
        data: servo id -> the ``size`` bytes read, for every servo asked.
        errors: servo id -> the status packet's error byte, only where it is not 0 (the
            :data:`ERROR_ALERT` bit means a latched hardware error; the data is still valid).
    """

    data: Mapping[int, bytes]
    errors: Mapping[int, int]


def usb_serial_tty(port: str) -> str:
    """The kernel's tty name of ``port`` (symlinks such as ``/dev/serial/by-id/...`` resolved)."""
    return os.path.basename(os.path.realpath(port))


def latency_timer_ms(port: str, sysfs_root: Path = Path("/sys")) -> int | None:
    """The USB serial adapter's latency timer of ``port``, in ms (``None``: not a USB serial
    adapter, or not Linux).

    Args:
        port: the device path (symlinks are resolved).
        sysfs_root: where sysfs is mounted (injectable for tests).
    """
    path = sysfs_root / "bus" / "usb-serial" / "devices" / usb_serial_tty(port) / "latency_timer"
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


class _Port(DescriptorIO, _sdk.PortHandler):  # type: ignore[misc]
    """``PortHandler`` with monotonic time, a blocking bounded read (``DescriptorIO``) and our
    timeout allowance."""

    def __init__(self, port_name: str, allowance_ms: float) -> None:
        super().__init__(port_name)
        self.init_io()
        self.allowance_ms = allowance_ms
        # When the last broadcast instruction (the group instructions of every cycle) was
        # handed to the adapter, time.monotonic(): every servo's Bus Watchdog counts from it;
        # and the longest interval between two of them since DynamixelBus.take_silence_s().
        self.last_broadcast_s = -float("inf")
        self.longest_gap_s = 0.0

    # The SDK's names are kept on this subclass only: they are what it calls.
    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802 - SDK override
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.allowance_ms

    def clearPort(self) -> None:  # noqa: N802 - SDK override
        self.drop_input()
        super().clearPort()

    def writePort(self, packet: list[int] | bytes) -> int:  # noqa: N802 - SDK override
        written = super().writePort(packet)
        if written and len(packet) > 4 and packet[4] == BROADCAST_ID:  # id, after the header
            now = time.monotonic()
            self.longest_gap_s = max(self.longest_gap_s, now - self.last_broadcast_s)
            self.last_broadcast_s = now
        return written


class _Protocol2(_sdk.Protocol2PacketHandler):  # type: ignore[misc]
    """The SDK's Protocol 2.0 packet handler with two per-packet helpers made cheap.

    ``updateCRC`` rebuilds its 256-entry table on every call and ``addStuffing`` copies every
    packet through a 1 KiB scratch list even when nothing needs stuffing; both run for every
    instruction sent (twice per cycle). The results are the same: the CRC is our codec's
    (same polynomial, table built once) and a packet without ``FF FF FD`` in its body is left
    as it is, while one that needs stuffing still goes through the SDK's own code.
    """

    # The SDK's names are kept on this subclass only: they are what it calls.
    def updateCRC(self, crc_accum: int, data_blk_ptr: Any, data_blk_size: int) -> int:  # noqa: N802
        return crc16(bytes(data_blk_ptr[:data_blk_size]), crc_accum)

    def addStuffing(self, packet: list[int]) -> list[int]:  # noqa: N802 - SDK override
        # Stuffing applies to the instruction onward (index 7) up to the CRC; the SDK also
        # rewrites LEN, unchanged when nothing is stuffed.
        length = packet[5] | packet[6] << 8
        if b"\xff\xff\xfd" not in bytes(packet[5 : 7 + length - 2]):
            return packet
        result: list[int] = super().addStuffing(packet)
        return result


class DynamixelBus(SdkBusErrors):
    """One Protocol 2.0 bus on a serial port.

    Args:
        port: serial device (``/dev/ttyUSB0``, a ``/dev/serial/by-id/...`` link, a pty).
        baud_rate: bit/s; one of the SDK's standard rates (57600 ... 4000000).
        timeout_ms: allowance beyond the wire time of the expected replies before a request
            counts as unanswered (covers the adapter's latency timer and return delays).
        sysfs_root: where sysfs is mounted (for the latency-timer check; injectable for tests).
        latency_timer_warn: log a warning at :meth:`open` when the adapter's latency timer is
            above 1 ms.

    Raises:
        ValueError: ``timeout_ms`` is not positive.
    """

    VENDOR: ClassVar[str] = "Dynamixel"
    """Named in its communication errors (``SdkBusErrors``)."""

    def __init__(
        self,
        port: str,
        baud_rate: int,
        *,
        timeout_ms: float = 4.0,
        sysfs_root: Path = Path("/sys"),
        latency_timer_warn: bool = True,
    ) -> None:
        if not timeout_ms > 0:
            raise ValueError(f"timeout_ms must be > 0, got {timeout_ms!r}")
        self.port = port
        self.baud_rate = baud_rate
        self.timeout_ms = float(timeout_ms)
        self.sysfs_root = sysfs_root
        self.latency_timer_warn = latency_timer_warn
        self.stats = BusStats()
        self._port = _Port(port, self.timeout_ms)
        self._handler = _Protocol2()
        self._open = False
        self._sync_reads: dict[tuple[int, int, bool, tuple[int, ...]],
                               tuple[bytes, list[int], str]] = {}
        self.latency_timer: int | None = None
        """The adapter's latency timer (ms) found at :meth:`open` (``None``: not a USB adapter)."""

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        return self._open

    @property
    def last_broadcast_s(self) -> float:
        """When the last broadcast instruction packet (a Sync Read / Sync Write, ...) went out,
        ``time.monotonic()`` (``-inf``: none yet).

        A broadcast packet reaches every servo, so this is the latest moment from which every
        servo's Bus Watchdog is known to count.
        """
        last: float = self._port.last_broadcast_s
        return last

    def take_silence_s(self) -> float:
        """The longest time without a broadcast instruction since the previous call (between
        two of them, or from the last one until now), s; resets it.

        A stall anywhere (between a cycle's read and its write as well) shows here at the
        next call, even once packets flow again.
        """
        port = self._port
        longest: float = max(port.longest_gap_s, time.monotonic() - port.last_broadcast_s)
        port.longest_gap_s = 0.0
        return longest

    def __repr__(self) -> str:
        state = "open" if self._open else "closed"
        return f"<DynamixelBus {self.port} {self.baud_rate} bit/s {state}>"

    def __enter__(self) -> DynamixelBus:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- port -----------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the port at the configured baud rate (checks the latency timer).

        Raises:
            ServoCommunicationError: the port cannot be opened or the baud rate is not
                supported (the message says what to check).
        """
        if self._open:
            return
        if self._port.getCFlagBaud(self.baud_rate) <= 0:
            raise ServoCommunicationError(
                f"Dynamixel bus {self.port}: baud rate {self.baud_rate} is not supported; use "
                "57600, 115200, 1000000, 2000000, 3000000 or 4000000",
                None,
                "unsupported baud rate",
            )
        self._port.baudrate = self.baud_rate
        try:
            ok = self._port.openPort()
        except Exception as exc:  # serial.SerialException, OSError
            raise ServoCommunicationError(
                f"Dynamixel bus {self.port}: cannot open the port: {exc}; check that the "
                "adapter is plugged in, the path is right and you may access it (group dialout)",
                None,
                "cannot open port",
            ) from exc
        if not ok:
            raise ServoCommunicationError(
                f"Dynamixel bus {self.port}: cannot set {self.baud_rate} bit/s",
                None,
                "cannot set baud rate",
            )
        self._open = True
        self.latency_timer = self.latency_timer_ms()
        if self.latency_timer_warn:
            self._check_latency_timer()

    def close(self) -> None:
        """Close the port (idempotent)."""
        if not self._open:
            return
        self._open = False
        try:
            self._port.closePort()
        except Exception as exc:  # noqa: BLE001 - closing must not fail the caller
            _log.warning("Dynamixel bus %s: closing the port failed: %s", self.port, exc)

    def latency_timer_ms(self) -> int | None:
        """The USB serial adapter's latency timer, ms (``None``: not a USB serial adapter)."""
        return latency_timer_ms(self.port, self.sysfs_root)

    def _check_latency_timer(self) -> None:
        value = self.latency_timer
        if value is not None and value > 1:
            tty = usb_serial_tty(self.port)
            _log.warning(
                "Dynamixel bus %s: the USB serial adapter's latency timer is %d ms, which "
                "delays every reply by up to that long; set it to 1 ms: "
                "echo 1 | sudo tee /sys/bus/usb-serial/devices/%s/latency_timer  (or "
                "permanently with a udev rule: ACTION==\"add\", SUBSYSTEM==\"usb-serial\", "
                "DRIVER==\"ftdi_sio\", ATTR{latency_timer}=\"1\")",
                self.port, value, tty,
            )

    # -- single-servo transactions --------------------------------------------------------------

    def ping(self, servo_id: int) -> int:
        """Ping a servo.

        Returns:
            Its model number.

        Raises:
            ValueError: bad id.
            ServoCommunicationError: no reply, corrupt reply, or the port failed.
        """
        _check_id(servo_id)
        model, result, _error = self._transact(
            servo_id, "ping", lambda: self._handler.ping(self._port, servo_id)
        )
        return int(model)

    def read(self, servo_id: int, address: int, size: int) -> int:
        """Read an unsigned little-endian register of 1, 2 or 4 bytes.

        Raises:
            ValueError: bad id or size.
            ServoCommunicationError: no reply, corrupt reply, or the port failed.
            ServoStatusError: the servo refused (the alert bit alone is not an error).
        """
        return int.from_bytes(self.read_bytes(servo_id, address, size), "little")

    def read_bytes(self, servo_id: int, address: int, size: int) -> bytes:
        """Read ``size`` bytes from ``address``.

        Raises:
            ValueError: bad id or size.
            ServoCommunicationError: no reply, corrupt reply, or the port failed.
            ServoStatusError: the servo refused (the alert bit alone is not an error).
        """
        _check_id(servo_id)
        if size <= 0:
            raise ValueError(f"size must be positive, got {size}")
        data, _result, error = self._transact(
            servo_id,
            f"read of {size} bytes at address {address}",
            lambda: self._handler.readTxRx(self._port, servo_id, address, size),
        )
        self._check_status(servo_id, error, f"read at address {address}")
        if len(data) != size:
            raise self._comm_error(servo_id, "corrupt reply (wrong length)",
                                   f"read at address {address}")
        return bytes(data)

    def write(self, servo_id: int, address: int, size: int, value: int) -> int:
        """Write a little-endian register of ``size`` bytes (negative values: two's complement).

        Returns:
            The status packet's error byte (0, or :data:`ERROR_ALERT` when the servo has a
            latched hardware error).

        Raises:
            ValueError: bad id, or a value that does not fit.
            ServoCommunicationError: no reply, corrupt reply, or the port failed.
            ServoStatusError: the servo refused the value (range, limit, access).
        """
        _check_id(servo_id)
        raw = _to_bytes(value, size)
        _, _result, error = self._transact(
            servo_id,
            f"write of {value} at address {address}",
            lambda: (None, *self._handler.writeTxRx(self._port, servo_id, address, size,
                                                    list(raw))),
        )
        self._check_status(servo_id, error, f"write of {value} at address {address}")
        return int(error)

    def reboot(self, servo_id: int) -> None:
        """Reboot a servo (clears its latched hardware error; it is silent for a while).

        Raises:
            ValueError: bad id.
            ServoCommunicationError: no acknowledgement.
        """
        _check_id(servo_id)
        self._transact(
            servo_id, "reboot",
            lambda: (None, *self._handler.reboot(self._port, servo_id)),
        )

    # -- group transactions ---------------------------------------------------------------------

    def sync_read(
        self, ids: Iterable[int], address: int, size: int, *, fast: bool = False
    ) -> SyncReadResult:
        """One Sync Read (or Fast Sync Read) of ``size`` bytes at ``address`` from ``ids``.

        All or nothing: either every servo answered with a good packet, or this raises (no
        partial or zero-filled data is ever returned).

        Raises:
            ValueError: no ids or a bad id.
            ServoCommunicationError: a servo did not answer or its reply was corrupt; names the
                first servo (in request order) that failed.
        """
        key = (address, size, fast, tuple(ids))
        request = self._sync_reads.get(key)
        if request is None:
            request = self._sync_read_request(*key)
        packet, id_list, what = request
        port = self._port
        self.stats.transactions += 1
        try:
            # The request was encoded once by our codec (it is the same every cycle); sending
            # it is what the SDK's syncReadTx does after building it: flush the input, write,
            # arm the packet timeout with the SDK's formula.
            port.clearPort()
            if port.writePort(packet) != len(packet):
                raise self._comm_error(None, _cause(_sdk.COMM_TX_FAIL), what)
            port.setPacketTimeout((11 + size) * len(id_list))
            if fast:
                return self._fast_sync_read_rx(id_list, size, what)
            return self._sync_read_rx(id_list, size, what)
        except ServoCommunicationError:
            self._recover_port()
            raise
        except Exception as exc:
            self._recover_port()
            raise self._comm_error(None, f"{type(exc).__name__}: {exc}", what) from exc
        finally:
            port.is_using = False

    def _sync_read_request(
        self, address: int, size: int, fast: bool, ids: tuple[int, ...]
    ) -> tuple[bytes, list[int], str]:
        """The Sync Read request packet for these arguments, its ids and its description,
        built once and kept (a cycle reads the same block of the same servos every time).

        Raises:
            ValueError: no ids or a bad id.
        """
        id_list = list(ids)
        if not id_list:
            raise ValueError("sync_read needs at least one servo id")
        for servo_id in id_list:
            _check_id(servo_id)
        packet = encode_sync_read(address, size, id_list, fast=fast)
        what = f"{'fast ' if fast else ''}sync read of {size} bytes at address {address}"
        if len(self._sync_reads) >= _SYNC_READ_CACHE:
            self._sync_reads.clear()  # bounded, whatever a caller asks for
        request = self._sync_reads[(address, size, fast, ids)] = (packet, id_list, what)
        return request

    def _sync_read_rx(self, ids: list[int], size: int, what: str) -> SyncReadResult:
        """Collect one status packet per servo of ``ids``, in order, until the port's deadline.

        Raises:
            ServoCommunicationError: naming the first servo without a good reply.
        """
        port = self._port
        decoder = Decoder()
        data: dict[int, bytes] = {}
        errors: dict[int, int] = {}
        index, count = 0, len(ids)
        while True:
            chunk = port.readPort(4096)  # whatever has arrived; blocks up to the deadline
            if not chunk:
                cause = _COMM_CAUSES[_sdk.COMM_RX_CORRUPT if decoder.pending
                                     else _sdk.COMM_RX_TIMEOUT]
                raise self._comm_error(ids[index], cause, what)
            for packet in decoder.feed(chunk):
                if not packet.crc_ok:
                    raise self._comm_error(ids[index], _COMM_CAUSES[_sdk.COMM_RX_CORRUPT], what)
                servo_id = ids[index]
                if not packet.is_status or packet.id != servo_id:
                    continue  # as the SDK's readRx: not the reply waited for
                params = packet.params  # error byte, then the data
                if len(params) < size + 1:
                    raise self._comm_error(servo_id, "short reply", what)
                data[servo_id] = params[1 : size + 1]
                if params[0]:
                    errors[servo_id] = params[0]
                index += 1
                if index == count:
                    return SyncReadResult(data, errors)

    def _fast_sync_read_rx(self, ids: list[int], size: int, what: str) -> SyncReadResult:
        packet, result = self._handler.rxPacket(self._port, True)
        stride = size + _FAST_SYNC_READ_OVERHEAD
        if result != _COMM_SUCCESS:
            # The servos append their pieces in request order, each after the previous one:
            # the first incomplete piece belongs to the servo that did not answer.
            complete = max(0, len(packet) - _FAST_STATUS_PREFIX) // stride
            blamed = ids[min(complete, len(ids) - 1)]
            raise self._comm_error(blamed, _cause(result), what)
        body = bytes(packet[_FAST_STATUS_PREFIX:-2])  # the pieces, without the final CRC
        data: dict[int, bytes] = {}
        errors: dict[int, int] = {}
        for index, servo_id in enumerate(ids):
            start = index * stride
            chunk = body[start:start + stride]
            if len(chunk) < stride - 2 or chunk[1] != servo_id:
                raise self._comm_error(servo_id, "missing from the fast sync read reply", what)
            data[servo_id] = chunk[2:2 + size]
            if chunk[0]:
                errors[servo_id] = chunk[0]
        return SyncReadResult(data, errors)

    def sync_write(self, address: int, size: int, values: Mapping[int, int]) -> None:
        """One Sync Write of ``size``-byte values (no replies: errors show in later reads).

        Raises:
            ValueError: a bad id or a value that does not fit.
            ServoCommunicationError: the port failed.
        """
        if not values:
            return
        if size not in (1, 2, 4):
            raise ValueError(f"register size must be 1, 2 or 4 bytes, got {size}")
        low, high = -(1 << (8 * size - 1)), (1 << (8 * size)) - 1
        items: list[tuple[int, bytes]] = []
        for servo_id, value in values.items():
            # Plain ints in range take the short way (this runs every cycle); anything else
            # gets the full checks and their messages.
            if type(servo_id) is not int or not 0 <= servo_id <= MAX_ID:
                _check_id(servo_id)
            if type(value) is int and low <= value <= high:
                items.append((servo_id, (value & high).to_bytes(size, "little")))
            else:
                items.append((servo_id, _to_bytes(value, size)))
        # The packet comes from our codec (the one the emulator parses, checked against the
        # e-Manual's vectors) and goes out through the SDK's port: the SDK's packet building
        # and its input flush (a system call; a broadcast write gets no reply to protect) cost
        # ~15 us a cycle, 3 % of the 4 Mbit/s wire time.
        packet = encode_sync_write(address, size, items)
        self.stats.transactions += 1
        if not self._open:
            raise self._comm_error(None, "the port is not open", _sync_write_what(address, size))
        try:
            written = self._port.writePort(packet)
        except Exception as exc:
            raise self._comm_error(None, f"{type(exc).__name__}: {exc}",
                                   _sync_write_what(address, size)) from exc
        if written != len(packet):
            raise self._comm_error(None, _cause(_sdk.COMM_TX_FAIL),
                                   _sync_write_what(address, size))

    # -- helpers --------------------------------------------------------------------------------

    def _transact(self, servo_id: int, what: str, call: Any) -> tuple[Any, int, int]:
        if not self._open:
            raise ServoCommunicationError(
                f"Dynamixel bus {self.port}: {what} on servo {servo_id}: the port is not open",
                servo_id, "port not open",
            )
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
            raise self._comm_error(servo_id, _cause(result), what)
        return value, result, int(error)

    def _check_status(self, servo_id: int, error: int, what: str) -> None:
        code = error & ~ERROR_ALERT
        if code:
            cause = _STATUS_CAUSES.get(code, f"status error {code}")
            self.stats.other_errors += 1
            message = f"Dynamixel servo {servo_id} on {self.port}: {what} refused: {cause}"
            self.stats.last_error = message
            raise ServoStatusError(message, servo_id, error)


def _sync_write_what(address: int, size: int) -> str:
    return f"sync write of {size} bytes at address {address}"


def _cause(result: int) -> str:
    return _COMM_CAUSES.get(result, f"communication error {result}")


def _to_bytes(value: int, size: int) -> bytes:
    if size not in (1, 2, 4):
        raise ValueError(f"register size must be 1, 2 or 4 bytes, got {size}")
    value = int(value)
    low, high = -(1 << (8 * size - 1)), (1 << (8 * size)) - 1
    if not low <= value <= high:
        raise ValueError(f"value {value} does not fit in {size} bytes")
    return (value & high).to_bytes(size, "little")
