"""The python-can bus layer shared by the CAN hardware kinds (``can-mit``, ``can-cia402``).

This is the only module of ``drivers/can`` that decides how a ``can.Bus`` is opened, drained,
checked and closed; the protocols' codecs (``mit.codec``, ``cia402.codec``) do no I/O.

Public API (used by ``mit.hardware`` and ``cia402.hardware``)
-------------------------------------------------------------
Configuration:

* :data:`BUS_FIELDS` -- the per-bus parameter schema (``interface``, ``channel``, ``bitrate``,
  ``host``, ``port``, ``receive_timeout``, ``setup_timeout``, ``options``), a ``param_table``.
* :func:`buses_param` -- a ``ParamSpec`` named ``buses`` for a kind's ``PARAMS``: a mapping
  ``{bus name: {interface, channel, bitrate, ...}}``; validated to ``{name: BusSettings}``.
* :func:`joint_bus_param` -- the per-joint ``bus`` ParamSpec (which bus a joint is on; may be
  omitted when there is one bus).
* :class:`BusSettings` -- one bus's validated settings (frozen dataclass).
* :meth:`BusSettings.device_names` / :func:`bus_keys` -- the canonical device-lock names of a
  bus and of what is unique on it (motor ids, the CANopen master), for ``devices()``.
* :func:`joint_buses` -- resolve the per-joint ``bus`` values against the buses (errors name
  ``params.bus.<joint>``).

Opening and closing:

* :func:`open_bus` ``(interface, channel, bitrate, **options) -> can.BusABC``: a bus, or
  ``ConfigurationError`` (unknown interface / bad option) / ``CommunicationError`` (the
  interface exists but the device cannot be opened, e.g. "no SocketCAN on this kernel"), both
  naming the interface and channel. For ``socketcand`` the TCP server is probed first so that a
  dead server fails at once (python-can retries for 10 s otherwise).
* :func:`open_settings` ``(settings) -> can.BusABC``: the same from a :class:`BusSettings`
  (socketcand: ``tcp_tune`` on by default).
* :func:`close_bus` ``(bus)``: flush and shut down, never raises.

Per cycle:

* :func:`drain_latest` ``(bus, latest, key=..., accept=...) -> DrainResult``: receive
  without blocking whatever arrived, keep only the newest frame per key (default: the
  arbitration id) in the dict ``latest``; error frames are not stored but reported.
* :func:`collect_until` ``(bus, latest, want, deadline, key=...) -> DrainResult``: like
  ``drain_latest`` but blocks (bounded by the monotonic ``deadline``) until every key in
  ``want`` got a frame.
* :func:`send` ``(bus, msg, health)``: transmit; a full transmit buffer
  (``can.CanOperationError``) flushes the stale queue, is counted in ``health`` and returns
  ``False`` (the caller treats the motor as not answered this cycle).
* :class:`BusHealth` -- counters and the bus state (``active`` / ``error-passive`` /
  ``bus-off``) as seen from ``bus.state`` (where the interface reports it) and from error
  frames (SocketCAN's ``CAN_ERR_BUSOFF`` / ``CAN_ERR_CRTL`` passive bits; python-can's
  ``socketcand`` client turns ``< error >`` into error frames). :meth:`BusHealth.check`
  raises ``CommunicationError`` on bus-off; the recovery action is closing and reopening
  the bus (:func:`reopen`) on the client's re-arm.
* :func:`full_queue` ``(health)``: the explanation of a full transmit queue (frames refused
  since the last one it took), or ``None``; drivers append it to a no-feedback fault.
* :func:`flush` ``(bus)``: discard every queued received frame and the transmit queue (where
  the interface can): used on stop/activate so stale frames are never replayed.

Timing:

* :func:`wire_bits` ``(msg, stuffing="exact"|"worst") -> int``: the bits a classic CAN data
  frame occupies on the wire, SOF through the 3-bit interframe space.
* :func:`wire_time_s` ``(frames, bitrate, stuffing="exact") -> float``.

Theory of operation
-------------------
One cycle on a bus is "send every command, then collect every reply". Buses are independent
wires: sending on all of them first and then collecting bus by bus lets them transmit
concurrently, so the cycle costs the slowest bus, not the sum, without a thread per bus in the
control-loop process (whose interpreter lock would delay the loop). Frames are received without
blocking (``recv(timeout=0)``) except while waiting, bounded, for replies the cycle expects.
"""

from __future__ import annotations

import errno
import functools
import ipaddress
import logging
import os
import socket
import time
from collections.abc import Callable, Iterable, Mapping, MutableMapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Final

import can

from jtc_hw.errors import CommunicationError, ConfigurationError
from jtc_hw.hardware import (
    DeviceName,
    ParamKind,
    ParamSpec,
    one_line,
    param_table,
    validate_params,
)

__all__ = [
    "BUS_FIELDS",
    "CAN_ERR_BUSOFF",
    "CAN_ERR_CRTL",
    "CAN_ERR_CRTL_RX_PASSIVE",
    "CAN_ERR_CRTL_TX_PASSIVE",
    "BusHealth",
    "BusSettings",
    "DrainResult",
    "THIS_HOST",
    "bus_keys",
    "canonical_hosts",
    "buses_param",
    "close_bus",
    "collect_until",
    "drain_latest",
    "flush",
    "full_queue",
    "joint_bus_param",
    "joint_buses",
    "open_bus",
    "open_settings",
    "reopen",
    "send",
    "wire_bits",
    "wire_time_s",
]

_log = logging.getLogger(__name__)

# SocketCAN error-frame classes (linux/can/error.h), carried in the arbitration id.
CAN_ERR_CRTL: Final = 0x00000004
"""Controller problem; details in data[1]."""
CAN_ERR_BUSOFF: Final = 0x00000040
"""The controller went bus-off."""
CAN_ERR_CRTL_RX_PASSIVE: Final = 0x10
CAN_ERR_CRTL_TX_PASSIVE: Final = 0x20


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------

BUS_FIELDS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("interface", ParamKind.STRING, "socketcan",
              "python-can interface: socketcan, slcan, pcan, kvaser, virtual, socketcand, ..."),
    ParamSpec("channel", ParamKind.STRING, "can0",
              "python-can channel (can0, vcan0, /dev/ttyACM0, PCAN_USBBUS1, a virtual name)"),
    ParamSpec("bitrate", ParamKind.INT, 1_000_000,
              "bit rate in bit/s (passed to interfaces that set it; used for wire-time figures)",
              minimum=10_000, maximum=1_000_000),
    ParamSpec("host", ParamKind.STRING, "127.0.0.1", "socketcand only: server host"),
    ParamSpec("port", ParamKind.INT, 29536, "socketcand only: server TCP port",
              minimum=1, maximum=65535),
    ParamSpec("receive_timeout", ParamKind.FLOAT, 0.0005,
              "s a read waits, at most, for the replies to the last write (0: take what has "
              "arrived, never wait)", minimum=0.0, maximum=1.0),
    ParamSpec("setup_timeout", ParamKind.FLOAT, 0.2,
              "s to wait for a device's answer while configuring / activating / recovering",
              minimum=0.001, maximum=10.0),
    ParamSpec("options", ParamKind.SECTION, MappingProxyType({}),
              "extra keyword arguments passed to can.Bus (e.g. {tcp_tune: true})"),
)
"""Schema of one bus's settings (the values of the ``buses`` mapping)."""


@dataclass(frozen=True)
class BusSettings:
    """One bus's validated settings (see :data:`BUS_FIELDS`)."""

    name: str
    interface: str
    channel: str
    bitrate: int
    host: str = "127.0.0.1"
    port: int = 29536
    receive_timeout: float = 0.0005
    setup_timeout: float = 0.2
    options: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))

    def describe(self) -> str:
        """A short human description: ``bus 'can0' (socketcan can0 @ 1000 kbit/s)``."""
        where = self.channel
        if self.interface == "socketcand":
            where = f"{self.channel} at {self.host}:{self.port}"
        return f"bus {self.name!r} ({self.interface} {where} @ {self.bitrate // 1000} kbit/s)"

    def device_names(self, things: Mapping[str, str]) -> tuple[DeviceName, ...]:
        """The device locks of ``things`` on this bus (``HardwareInterface.devices``).

        ``things`` maps what must be unique on the bus to its label, e.g. ``{"mit:3": "motor
        3"}``; each becomes ``<bus key>:<thing>``, where the bus key is canonical
        (:func:`bus_keys`), and is labelled ``<describe()> <label>``. A socketcand host that
        resolves to several addresses gives one name per address.

        Raises:
            HardwareError: the bus cannot be named (see :func:`bus_keys`).
        """
        where = self.describe()
        return tuple(
            DeviceName(f"{bus}:{thing}", f"{where} {label}")
            for bus in bus_keys(self) for thing, label in things.items()
        )


THIS_HOST: Final = "this-host"
"""The socketcand lock key's host for every address of this machine (see :func:`bus_keys`)."""


def bus_keys(settings: BusSettings) -> tuple[str, ...]:
    """The canonical names of the bus ``settings`` reaches, for device locks.

    Two configurations that reach one bus get the same key, whatever they spell:

    * ``socketcan``: the kernel's interface index (``can:socketcan:#3``), which an
      alternative name (``ip link property add ... altname``) or a rename does not change.
      An interface that does not exist is an error now (it could not be opened anyway, and
      the lock must not be keyed on a name that may later name another interface).
    * ``socketcand``: ``can:socketcand:<host>:<port>:<channel>``, the port a number and the
      host resolved (``getaddrinfo``), one key per address. Every address of this machine
      (loopback ``127.0.0.0/8`` and ``::1``, and any address a socket can bind to here) is
      :data:`THIS_HOST`: ``localhost``, ``127.0.0.1``, ``::1`` and the machine's own name
      reach one listener when socketcand listens on all addresses, its usual setup. A
      server that listens on one loopback address only, next to another server on another
      with the same port, is thereby taken for the same device: a refusal to start, never
      two daemons on one bus. A remote server is its address: ``robot.lan`` and
      ``10.0.0.5`` meet there; daemons on different machines do not see each other's locks
      at all.
    * any other interface: ``can:<interface>:<channel>``, the channel as given, except a
      path (slcan's ``/dev/ttyACM0``), which is resolved as a serial port is.

    Raises:
        CommunicationError: the host does not resolve, or the SocketCAN interface does not
            exist (names the bus and what to check).
    """
    if settings.interface == "socketcan":
        try:
            index = socket.if_nametoindex(settings.channel)
        except OSError:
            raise CommunicationError(
                f"{settings.describe()}: no network interface {settings.channel!r} (see "
                f"'ip link show'); bring it up before starting the daemon"
            ) from None
        return (f"can:socketcan:#{index}",)
    if settings.interface == "socketcand":
        return tuple(
            f"can:socketcand:{host}:{settings.port}:{settings.channel}"
            for host in canonical_hosts(settings.host, settings.port, settings.describe())
        )
    channel = settings.channel
    if channel.startswith("/"):
        channel = os.path.realpath(channel)
    return (f"can:{settings.interface}:{channel}",)


def canonical_hosts(host: str, port: int, what: str) -> tuple[str, ...]:
    """``host``'s addresses as lock keys: :data:`THIS_HOST` for this machine's, else the
    address (IPv4-mapped IPv6 as IPv4); sorted, without repeats.

    Raises:
        CommunicationError: ``host`` does not resolve (``what`` names the bus).
    """
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        reason = exc.strerror if isinstance(exc, socket.gaierror) else "not a host name"
        raise CommunicationError(
            f"{what}: host {host!r} does not resolve ({reason}); check the bus's host"
        ) from None
    keys = set()
    for family, _, _, _, sockaddr in infos:
        try:
            address = ipaddress.ip_address(str(sockaddr[0]).split("%")[0])
        except ValueError:
            continue
        if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
            address = address.ipv4_mapped
        if address.is_loopback or _assigned_here(family, sockaddr):
            keys.add(THIS_HOST)
        else:
            keys.add(str(address))
    return tuple(sorted(keys))


def _assigned_here(family: int, sockaddr: tuple[Any, ...]) -> bool:
    """Whether ``sockaddr`` is an address of this machine: a socket binds to it (port 0)."""
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.bind((sockaddr[0], 0, *sockaddr[2:]))
    except OSError:
        return False
    return True


def _coerce_buses(value: Any, path: str) -> Mapping[str, BusSettings]:
    if not isinstance(value, Mapping) or not value:
        raise ConfigurationError(
            "expected a non-empty mapping {bus name: {interface, channel, bitrate, ...}}",
            path, value,
        )
    result: dict[str, BusSettings] = {}
    for name, raw in value.items():
        if not isinstance(name, str) or not name:
            raise ConfigurationError("bus names must be non-empty strings", path, name)
        checked = validate_params(BUS_FIELDS, raw, f"{path}.{name}", owner=f"bus {name!r}")
        result[name] = BusSettings(
            name=name,
            interface=checked["interface"],
            channel=checked["channel"],
            bitrate=checked["bitrate"],
            host=checked["host"],
            port=checked["port"],
            receive_timeout=checked["receive_timeout"],
            setup_timeout=checked["setup_timeout"],
            options=MappingProxyType(dict(checked["options"])),
        )
    return MappingProxyType(result)


def buses_param() -> ParamSpec:
    """The ``buses`` parameter: ``{bus name: {interface, channel, bitrate, ...}}`` (required).

    Validated to a read-only ``{name: BusSettings}`` mapping, in the order given.
    """
    return ParamSpec("buses", ParamKind.SECTION, None,
                     "the CAN buses: {name: {interface, channel, bitrate, host, port, "
                     "receive_timeout, setup_timeout, options}}",
                     required=True, coerce=_coerce_buses)


def joint_bus_param() -> ParamSpec:
    """The per-joint ``bus`` parameter (a bus name; may be omitted with a single bus)."""
    return ParamSpec("bus", ParamKind.STRING, "",
                     "per joint: the name of the bus (key of buses) the motor is on; may be "
                     "omitted when there is one bus", per_joint=True)


def joint_buses(
    joints: Iterable[str], given: Iterable[str], buses: Mapping[str, BusSettings]
) -> tuple[str, ...]:
    """Resolve each joint's bus name (empty: the only bus).

    Raises:
        ConfigurationError: a joint names an unknown bus, or omits it while there are several.
    """
    names = list(buses)
    result = []
    for joint, bus in zip(joints, given, strict=True):
        if not bus:
            if len(names) != 1:
                raise ConfigurationError(
                    f"joint {joint!r} does not say which bus it is on; there are several "
                    f"({', '.join(names)})", f"params.bus.{joint}", bus,
                )
            bus = names[0]
        if bus not in buses:
            raise ConfigurationError(
                f"joint {joint!r} is on bus {bus!r}, which is not one of params.buses "
                f"({', '.join(names)})", f"params.bus.{joint}", bus,
            )
        result.append(bus)
    return tuple(result)


# --------------------------------------------------------------------------------------------
# Opening and closing
# --------------------------------------------------------------------------------------------


def _probe_tcp(host: str, port: int, what: str) -> None:
    try:
        with socket.create_connection((host, port), timeout=2.0):
            pass
    except OSError as exc:
        raise CommunicationError(
            f"{what}: cannot connect to the socketcand server at {host}:{port} ({exc}); "
            "check that socketcand (or `jtc-hw emulate can`) runs there"
        ) from exc


def open_bus(interface: str, channel: str, bitrate: int, **options: Any) -> can.BusABC:
    """Open a python-can bus.

    Args:
        interface: python-can interface name.
        channel: its channel.
        bitrate: bit/s; passed on except to interfaces that take none (socketcan: set with
            ``ip link``; socketcand: set on the server).
        **options: further ``can.Bus`` keyword arguments (``host``/``port`` for socketcand).

    Returns:
        The open bus.

    Raises:
        ConfigurationError: python-can has no such interface, or rejects an option.
        CommunicationError: the interface exists but the device cannot be opened (no
            SocketCAN on this kernel, no such network device, driver library missing, server
            down); the message names the interface and channel.
    """
    what = f"CAN interface {interface!r} channel {channel!r}"
    if interface not in can.interfaces.VALID_INTERFACES:
        raise ConfigurationError(
            f"python-can has no interface {interface!r}; known: "
            f"{', '.join(sorted(can.interfaces.VALID_INTERFACES))}", "interface", interface,
        )
    kwargs = dict(options)
    if interface not in ("socketcan", "socketcand"):
        kwargs["bitrate"] = bitrate
    if interface == "socketcand":
        _probe_tcp(str(kwargs.get("host", "127.0.0.1")), int(kwargs.get("port", 29536)), what)
    try:
        return can.Bus(interface=interface, channel=channel, **kwargs)
    except TypeError as exc:
        raise ConfigurationError(f"{what}: bad option: {exc}", "options", options) from exc
    except OSError as exc:
        hint = ""
        if interface == "socketcan" and exc.errno == 97:
            hint = ": no SocketCAN on this kernel (AF_CAN unsupported); load the can/vcan " \
                   "modules or use another interface"
        elif interface == "socketcan" and exc.errno == 19:
            hint = f": no network device {channel!r}; check `ip link show {channel}`"
        raise CommunicationError(f"{what}: cannot open the bus ({one_line(exc)}){hint}") from exc
    except (can.CanError, ImportError, TimeoutError, ValueError) as exc:
        # (python-can's socketcand client puts a whole traceback in some of its errors.)
        raise CommunicationError(f"{what}: cannot open the bus: {one_line(exc)}") from exc


def open_settings(settings: BusSettings) -> can.BusABC:
    """:func:`open_bus` from validated settings (``host``/``port`` and, unless the options say
    otherwise, ``tcp_tune=True`` only for socketcand).

    Raises:
        ConfigurationError: see :func:`open_bus`.
        CommunicationError: see :func:`open_bus`; the message names the bus.
    """
    options = dict(settings.options)
    if settings.interface == "socketcand":
        options.setdefault("host", settings.host)
        options.setdefault("port", settings.port)
        # TCP_NODELAY: without it each small frame after the first waits for Nagle's algorithm
        # and the server's delayed ACK (tens of ms). Set `options: {tcp_tune: false}` to opt out.
        options.setdefault("tcp_tune", True)
    try:
        return open_bus(settings.interface, settings.channel, settings.bitrate, **options)
    except CommunicationError as exc:
        raise CommunicationError(f"{settings.describe()}: {exc}") from exc


def close_bus(bus: can.BusABC | None) -> None:
    """Flush the transmit queue and shut the bus down; never raises (a closing path)."""
    if bus is None:
        return
    try:
        flush(bus)
    except Exception:  # noqa: BLE001 - closing anyway
        pass
    try:
        bus.shutdown()
    except Exception as exc:  # noqa: BLE001 - closing anyway
        _log.debug("closing %s: %s", bus, exc)


def reopen(bus: can.BusABC | None, settings: BusSettings) -> can.BusABC:
    """The bus-off recovery action: close the bus and open it again.

    Raises:
        ConfigurationError, CommunicationError: see :func:`open_settings`.
    """
    close_bus(bus)
    return open_settings(settings)


# --------------------------------------------------------------------------------------------
# Health
# --------------------------------------------------------------------------------------------


@dataclass
class BusHealth:
    """Counters and the last known state of one bus (JSON-able with :meth:`as_dict`)."""

    settings: BusSettings
    state: str = "active"
    tx_frames: int = 0
    rx_frames: int = 0
    error_frames: int = 0
    tx_overflows: int = 0
    bus_offs: int = 0
    error_passives: int = 0
    stale_flushed: int = 0
    unsent: int = 0
    """Frames refused by a full transmit queue since the last one it took (0: not full)."""

    def note_error_frame(self, msg: can.Message) -> None:
        """Update the state from a SocketCAN-style error frame."""
        self.error_frames += 1
        err = msg.arbitration_id
        if err & CAN_ERR_BUSOFF:
            if self.state != "bus-off":
                self.bus_offs += 1
            self.state = "bus-off"
        elif err & CAN_ERR_CRTL and len(msg.data) > 1 and msg.data[1] & (
            CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE
        ):
            if self.state != "error-passive":
                self.error_passives += 1
            self.state = "error-passive"

    def check(self, bus: can.BusABC, owner: str) -> None:
        """Look at ``bus.state`` (where supported) and the error frames seen.

        Error-passive is logged and counted (frames still flow); bus-off is a fault.

        Raises:
            CommunicationError: the bus is bus-off; names the bus and what to check.
        """
        try:
            reported = bus.state
        except (NotImplementedError, can.CanError, OSError):
            reported = can.BusState.ACTIVE
        if reported is can.BusState.ERROR and self.state != "bus-off":
            self.bus_offs += 1
            self.state = "bus-off"
        elif reported is can.BusState.PASSIVE and self.state == "active":
            self.error_passives += 1
            self.state = "error-passive"
        if self.state == "bus-off":
            raise CommunicationError(
                f"{owner}: {self.settings.describe()} is bus-off (the controller stopped "
                "transmitting after too many errors); check termination (120 ohm at both "
                "ends), wiring and that every node uses "
                f"{self.settings.bitrate} bit/s; re-arm to reopen the bus"
            )

    def as_dict(self) -> dict[str, Any]:
        """JSON-able summary."""
        return {
            "interface": self.settings.interface,
            "channel": self.settings.channel,
            "bitrate": self.settings.bitrate,
            "state": self.state,
            "tx_frames": self.tx_frames,
            "rx_frames": self.rx_frames,
            "error_frames": self.error_frames,
            "tx_overflows": self.tx_overflows,
            "bus_offs": self.bus_offs,
            "error_passives": self.error_passives,
            "stale_flushed": self.stale_flushed,
            "unsent": self.unsent,
        }


# --------------------------------------------------------------------------------------------
# Per cycle
# --------------------------------------------------------------------------------------------


@dataclass
class DrainResult:
    """What one drain saw: frames stored, frames ignored, error frames (newest last)."""

    stored: int = 0
    ignored: int = 0
    errors: list[can.Message] = field(default_factory=list)


def _arbitration_id(msg: can.Message) -> int:
    return int(msg.arbitration_id)


OnStored = Callable[[int, can.Message], object]
"""Called with ``(key, frame)`` for each frame stored, as it is received (``None``: not)."""


def _take(
    msg: can.Message,
    latest: MutableMapping[int, can.Message],
    key: Callable[[can.Message], int | None],
    result: DrainResult,
    on_stored: OnStored | None = None,
) -> int | None:
    if msg.is_error_frame:
        result.errors.append(msg)
        return None
    k = key(msg)
    if k is None:
        result.ignored += 1
        return None
    latest[k] = msg
    result.stored += 1
    if on_stored is not None:
        on_stored(k, msg)
    return k


def drain_latest(
    bus: can.BusABC,
    latest: MutableMapping[int, can.Message],
    key: Callable[[can.Message], int | None] = _arbitration_id,
    limit: int = 10_000,
    on_stored: OnStored | None = None,
) -> DrainResult:
    """Receive, without blocking, every frame already queued; keep the newest per key.

    Args:
        bus: the bus.
        latest: updated in place: ``key(frame) -> frame``, newer frames replacing older ones.
        key: the key of a frame (default: its arbitration id); ``None`` ignores the frame
            (e.g. not a reply of ours).
        limit: at most this many frames (a babbling node cannot hold the loop forever).
        on_stored: called with each stored frame and its key as it is received, so that a
            caller can decode while later frames are still on the wire.

    Returns:
        Counts and the error frames seen.

    Raises:
        can.CanError: the interface failed (the hardware wraps it).
    """
    result = DrainResult()
    for _ in range(limit):
        msg = bus.recv(timeout=0.0)
        if msg is None:
            break
        _take(msg, latest, key, result, on_stored)
    return result


def collect_until(
    bus: can.BusABC,
    latest: MutableMapping[int, can.Message],
    want: set[int],
    deadline: float,
    key: Callable[[can.Message], int | None] = _arbitration_id,
    on_stored: OnStored | None = None,
) -> DrainResult:
    """Receive until every key in ``want`` got a frame, or ``time.monotonic()`` passes
    ``deadline``; keep the newest per key. ``want`` is consumed (what is left did not come).
    ``on_stored``: as for :func:`drain_latest`.

    Raises:
        can.CanError: the interface failed.
    """
    # Callers remove the keys they wait for from `latest` before sending the requests, so a
    # key present after the drain is an answer to this cycle's request.
    result = drain_latest(bus, latest, key, on_stored=on_stored)
    want.difference_update([k for k in want if k in latest])
    while want:
        remaining = deadline - time.monotonic()
        if remaining <= 0.0:
            break
        msg = bus.recv(timeout=remaining)
        if msg is None:
            break
        k = _take(msg, latest, key, result, on_stored)
        if k is not None:
            want.discard(k)
    return result


_GONE_ERRNOS: Final = frozenset({
    errno.ENETDOWN, errno.ENODEV, errno.ENXIO, errno.EBADF, errno.EPIPE, errno.ECONNRESET,
})
"""Send errors that mean the interface is gone, not full (SocketCAN: ``ip link set can0
down``, an unplugged USB adapter); python-can raises them as ``CanOperationError`` too."""


def send(bus: can.BusABC, msg: can.Message, health: BusHealth | None = None) -> bool:
    """Transmit one frame without waiting for room in the queue.

    A full transmit buffer (``can.CanOperationError``; SocketCAN: ``ENOBUFS`` from the
    interface's queue) means frames are queued faster than the wire carries them (or nobody
    acknowledges them): the queued, now stale, frames are flushed so they are never sent
    late, it is counted in ``health.tx_overflows`` (and ``health.unsent``, until a frame is
    queued again), and ``False`` is returned.

    Returns:
        ``True`` when the frame was queued.

    Raises:
        can.CanError: another interface failure, among them an interface that is down or
            gone (``ENETDOWN``, ``ENODEV``, ...: a bus loss, not a full queue); the hardware
            wraps it.
    """
    try:
        bus.send(msg, timeout=0.0)
    except can.CanOperationError as exc:
        if exc.error_code in _GONE_ERRNOS:
            raise
        count = 1
        if health is not None:
            health.tx_overflows += 1
            health.unsent += 1
            count = health.tx_overflows
        if count == 1 or count % 1000 == 0:  # a jammed bus must not flood the log
            _log.warning("transmit buffer full on %s (%s; %d times): flushing stale frames",
                         bus.channel_info, exc, count)
        _flush_tx(bus)
        return False
    if health is not None:
        health.tx_frames += 1
        health.unsent = 0
    return True


def full_queue(health: BusHealth) -> str | None:
    """Why frames do not get out, when the transmit queue refuses them (``None``: it does
    not): the end of a no-feedback fault's message, so that a jammed queue is named as the
    cause instead of the motors."""
    if not health.unsent:
        return None
    return (f"the transmit queue of {health.settings.describe()} is full ({health.unsent} "
            f"frames refused in a row, {health.tx_overflows} in all): the bus carries fewer "
            "frames than are sent; check that the other nodes acknowledge (power, bitrate, "
            "termination), the bus load, and the interface's queue (txqueuelen, qdisc)")


def _flush_tx(bus: can.BusABC) -> None:
    try:
        bus.flush_tx_buffer()
    except (NotImplementedError, can.CanError, OSError):
        pass  # the interface queues nothing of its own (virtual, socketcand)


def flush(bus: can.BusABC, limit: int = 100_000) -> int:
    """Discard the transmit queue (where the interface has one) and every received frame
    waiting; returns how many received frames were dropped.

    Raises:
        can.CanError: receiving failed.
    """
    _flush_tx(bus)
    dropped = 0
    for _ in range(limit):
        if bus.recv(timeout=0.0) is None:
            break
        dropped += 1
    return dropped


# --------------------------------------------------------------------------------------------
# Wire time
# --------------------------------------------------------------------------------------------

_CRC15_POLY: Final = 0x4599
_TAIL_BITS: Final = 1 + 1 + 1 + 7 + 3
"""CRC delimiter, ACK slot, ACK delimiter, end of frame, interframe space (not stuffed)."""


def _bits_of(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def _crc15(bits: Iterable[int]) -> int:
    crc = 0
    for bit in bits:
        feedback = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= _CRC15_POLY
    return crc


def _stuffed_fields(msg: can.Message) -> list[int]:
    """The bits from SOF through the CRC (the part subject to bit stuffing)."""
    dlc = len(msg.data) if msg.dlc is None else int(msg.dlc)
    data_len = 0 if msg.is_remote_frame else min(len(msg.data), 8)
    rtr = 1 if msg.is_remote_frame else 0
    if msg.is_extended_id:
        ident = int(msg.arbitration_id) & 0x1FFFFFFF
        head = (
            [0] + _bits_of(ident >> 18, 11) + [1, 1] + _bits_of(ident & 0x3FFFF, 18)
            + [rtr, 0, 0] + _bits_of(dlc, 4)
        )
    else:
        head = [0] + _bits_of(int(msg.arbitration_id) & 0x7FF, 11) + [rtr, 0, 0] + _bits_of(dlc, 4)
    for byte in bytes(msg.data[:data_len]):
        head += _bits_of(byte, 8)
    return head + _bits_of(_crc15(head), 15)


def _count_stuff_bits(bits: list[int]) -> int:
    stuffed = 0
    run_bit, run = -1, 0
    for bit in bits:
        if bit == run_bit:
            run += 1
        else:
            run_bit, run = bit, 1
        if run == 5:
            stuffed += 1
            # The stuff bit is the complement and starts the next run.
            run_bit, run = 1 - bit, 1
    return stuffed


@functools.lru_cache(maxsize=8192)
def _exact_bits(ident: int, extended: bool, remote: bool, dlc: int, data: bytes) -> int:
    msg = can.Message(arbitration_id=ident, is_extended_id=extended, is_remote_frame=remote,
                      dlc=dlc, data=data, check=False)
    bits = _stuffed_fields(msg)
    return len(bits) + _count_stuff_bits(bits) + _TAIL_BITS


def wire_bits(msg: can.Message, stuffing: str = "exact") -> int:
    """Bits a classic CAN data / remote frame occupies on the wire, SOF to interframe space.

    Args:
        msg: the frame (standard or extended id, 0..8 data bytes).
        stuffing: ``"exact"`` stuffs the frame's actual bits (SOF..CRC, CRC computed);
            ``"worst"`` adds the worst case ``(n - 1) // 4`` stuff bits for ``n`` stuffed
            bits; ``"none"`` adds none.

    Returns:
        Bits: the stuffed part plus CRC delimiter, ACK slot and delimiter, 7-bit EOF and
        3-bit interframe space.

    Raises:
        ValueError: unknown ``stuffing`` or a CAN FD frame.
    """
    if msg.is_fd:
        raise ValueError("wire_bits: CAN FD frames are not supported")
    if stuffing == "exact":
        # Cached per frame content: emulators pace every frame, and a bus repeats the same
        # frames (set-points held, SYNC, unchanged PDOs); the bit walk costs ~30 us.
        return _exact_bits(int(msg.arbitration_id), bool(msg.is_extended_id),
                           bool(msg.is_remote_frame),
                           len(msg.data) if msg.dlc is None else int(msg.dlc),
                           bytes(msg.data[:8]))
    bits = _stuffed_fields(msg)
    if stuffing == "exact":
        extra = _count_stuff_bits(bits)
    elif stuffing == "worst":
        extra = (len(bits) - 1) // 4
    elif stuffing == "none":
        extra = 0
    else:
        raise ValueError(f"stuffing must be 'exact', 'worst' or 'none', got {stuffing!r}")
    return len(bits) + extra + _TAIL_BITS


def wire_time_s(frames: Iterable[can.Message], bitrate: int, stuffing: str = "exact") -> float:
    """Seconds the frames occupy a bus at ``bitrate`` bit/s, back to back.

    Raises:
        ValueError: ``bitrate`` is not positive, or see :func:`wire_bits`.
    """
    if bitrate <= 0:
        raise ValueError(f"bitrate must be > 0, got {bitrate!r}")
    return sum(wire_bits(m, stuffing) for m in frames) / bitrate
