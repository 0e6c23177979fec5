"""A socketcand-protocol server on 127.0.0.1 bridging TCP clients to in-process virtual buses.

Theory of operation
-------------------
`socketcand <https://github.com/linux-can/socketcand>`_ exposes SocketCAN interfaces over TCP
with a line-less ASCII protocol of ``< ... >`` elements. This server speaks the subset that
python-can's ``socketcand`` interface (a client) uses, in raw mode:

==========================  =======================================================
server -> client            ``< hi >`` on connect
client -> server            ``< open CHANNEL >``; server answers ``< ok >`` (or ``< error ... >``)
client -> server            ``< rawmode >``; server answers ``< ok >``
client -> server            ``< send ID LEN B0 B1 ... >`` (id: 3 hex digits standard, 8
                            extended; len and bytes hex)
server -> client            ``< frame ID SECS.USECS HEXDATA >`` for every frame on the bus
server -> client            ``< error ID SECS.USECS HEXDATA >`` for error frames
==========================  =======================================================

Each client gets its own python-can ``virtual`` bus on the channel's virtual name, so frames a
client sends reach the emulators and every other client, never itself (a CAN controller does
not receive its own frames; python-can's virtual bus does not echo either). One thread per
client reads the socket, parses the ``< send >`` elements of each TCP segment and puts them on
its virtual bus, stamped with the segment's arrival time (when the frame reached "the
controller", not when this thread got to it). Frames in the other direction take no thread
of their own: the client's receive queue on the virtual channel is replaced by a sink that
formats the frame and writes it to the socket in the sending peer's thread (an emulator
releasing a reply at its due time writes it to TCP at once, instead of waking a writer thread,
a hop that costs tens of microseconds under the interpreter lock). A client disconnecting
(or the server stopping) ends its thread and shuts its virtual bus down.

One-thread mode (``timers=``): one thread accepts, waits with ``select`` on the listener and
every client socket (``select.select``: its timeout has microsecond resolution, ``epoll``'s
only milliseconds) until a client sends or the earliest due frame of the given timers (the
emulators, each with its own heap of due frames) is near, handles the clients' elements in
itself (the emulators in push mode answer in it) and releases the due frames (waking a little
early and spinning the rest, :class:`~jtc_hw.drivers.can.emulation.WakeEarly`). No thread of
the process then competes for the interpreter lock or waits on another.

python-can's client reads the handshake replies with one ``recv`` each and compares them
exactly, so no bus frame may be written to a client before it has read the ``< ok >`` of
``rawmode``: frames are held (in order) and forwarded only after the client's first
``< send >`` or :data:`FORWARD_AFTER_S` after that ``< ok >``, whichever is first.

The sink relies on python-can's ``virtual`` interface keeping, per channel, a list of
receive queues that ``send`` calls ``put(msg, block=True, timeout=...)`` on, and skipping
the sender's own ``queue``: true of python-can 4.x (checked when a client opens a channel,
with a clear error otherwise).
"""

from __future__ import annotations

import logging
import queue
import select
import socket
import struct
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any

import can

from jtc_hw.hardware.timing import reduce_timer_slack

from .emulation import Timer, WakeEarly, attach_sink

__all__ = [
    "FORWARD_AFTER_S", "SocketcandServer", "format_frame", "parse_send",
]

_log = logging.getLogger(__name__)

FORWARD_AFTER_S = 0.05
"""Forward bus frames to a silent client this long after its rawmode ``< ok >``."""

_POLL_S = 0.1  # how often blocked threads look at their stop flag
_MAX_ELEMENT = 512
# SO_TIMESTAMPNS (= SCM_TIMESTAMPNS), not exported by the socket module; Linux value (64-bit
# struct timespec ancillary data).
_SO_TIMESTAMPNS = 35 if sys.platform.startswith("linux") else None
_MAX_HELD = 10_000  # frames held for a client that has not started reading yet
_HEX = frozenset("0123456789abcdefABCDEF")


def format_frame(msg: can.Message) -> str:
    """A bus frame as the server's ``< frame ... >`` (or ``< error ... >``) element."""
    if msg.is_extended_id or msg.is_error_frame:
        ident = f"{msg.arbitration_id & 0x1FFFFFFF:08X}"
    else:
        ident = f"{msg.arbitration_id & 0x7FF:03X}"
    stamp = msg.timestamp if msg.timestamp else time.time()
    secs = int(stamp)
    usecs = int(round((stamp - secs) * 1e6))
    if usecs >= 1_000_000:
        secs, usecs = secs + 1, usecs - 1_000_000
    word = "error" if msg.is_error_frame else "frame"
    return f"< {word} {ident} {secs}.{usecs:06d} {bytes(msg.data).hex().upper()} >"


def parse_send(element: str) -> can.Message | None:
    """A client's ``< send ID LEN DATA >`` element as a frame (``None``: not a send)."""
    text = element.strip()
    if len(text) < 2 or text[0] != "<" or text[-1] != ">":
        return None
    words = text[1:-1].split()
    if len(words) < 3 or words[0] != "send":
        return None
    ident_text, length_text, data_words = words[1], words[2], words[3:]
    if (
        not 1 <= len(ident_text) <= 8
        or not 1 <= len(length_text) <= 2
        or any(not 1 <= len(b) <= 2 for b in data_words)
        or not _HEX.issuperset("".join(words[1:]))
    ):
        return None
    data = bytes(int(b, 16) for b in data_words)
    length = int(length_text, 16)
    if length != len(data) or length > 8:
        return None
    return can.Message(arbitration_id=int(ident_text, 16), is_extended_id=len(ident_text) > 3,
                       data=data)


class _Sink:
    """Stands in for a client's receive queue on a python-can virtual channel: ``put``
    writes the frame to the client's socket in the caller's thread (see the module
    docstring)."""

    def __init__(self, client: _Client) -> None:
        self.client = client

    def put(self, msg: can.Message, block: bool = True, timeout: float | None = None) -> None:
        self.client.deliver(msg)

    def put_nowait(self, msg: can.Message) -> None:
        self.client.deliver(msg)

    def get(self, block: bool = True, timeout: float | None = None) -> can.Message:
        raise queue.Empty  # nobody receives from the client's own bus: frames go to TCP

    def get_nowait(self) -> can.Message:
        raise queue.Empty

    def empty(self) -> bool:
        return True

    def qsize(self) -> int:
        return 0


class _Client:
    def __init__(self, server: SocketcandServer, conn: socket.socket, peer: str) -> None:
        self.server = server
        self.conn = conn
        self.peer = peer
        self.bus: can.BusABC | None = None
        self.stop = threading.Event()
        self.send_lock = threading.Lock()
        # Frames for the client before it may get them (see the module docstring), in order;
        # None once forwarding.
        self.held: list[bytes] | None = []
        self.forward_at: float | None = None  # monotonic time to start forwarding anyway
        self.buffer = ""  # received text not yet making a whole element
        self.reader = threading.Thread(target=self._read_tcp, name=f"socketcand-{peer}",
                                       daemon=True)

    def write(self, text: str) -> None:
        with self.send_lock:
            self.conn.sendall(text.encode("ascii"))

    def deliver(self, msg: can.Message) -> None:
        """A bus frame for this client: written to the socket now (in the caller's thread),
        or held until forwarding starts."""
        data = format_frame(msg).encode("ascii")
        with self.send_lock:
            if self.stop.is_set():
                return
            if self.held is not None:
                if len(self.held) < _MAX_HELD:
                    self.held.append(data)
                return
            try:
                self.conn.sendall(data)
            except OSError as exc:  # gone, or not reading for the socket's timeout
                _log.debug("socketcand client %s: %s", self.peer, exc)
                self.stop.set()
                return
        self.server.frames_to_clients += 1

    def _start_forwarding(self) -> None:
        with self.send_lock:
            held, self.held = self.held, None
            if held:
                self.conn.sendall(b"".join(held))
        if held:
            self.server.frames_to_clients += len(held)

    def _read_tcp(self) -> None:
        try:
            self.write("< hi >")
            self.conn.settimeout(_POLL_S)
            while not self.stop.is_set():
                if self.forward_at is not None and self.held is not None:
                    wait = self.forward_at - time.monotonic()
                    if wait <= 0.0:
                        self._start_forwarding()
                    self.conn.settimeout(min(max(wait, 0.001), _POLL_S))
                try:
                    if not self.receive():
                        break
                except TimeoutError:
                    continue
        except OSError as exc:
            _log.debug("socketcand client %s: %s", self.peer, exc)
        finally:
            self.close()

    def receive(self) -> bool:
        """Read one TCP segment and act on its elements; ``False``: the client is gone.

        Raises:
            OSError: the socket failed (``TimeoutError``: nothing came in its timeout).
        """
        chunk, ancillary, _, _ = self.conn.recvmsg(65536, _ANCILLARY_SPACE)
        if not chunk:
            return False
        # Every frame of this segment reached "the controller" when the kernel received the
        # segment (SO_TIMESTAMPNS), not when this thread woke up for it: the wire starts then.
        arrived = _kernel_stamp(ancillary)
        buffer = self.buffer + chunk.decode("ascii", errors="replace")
        while True:
            start = buffer.find("<")
            end = buffer.find(">", start + 1) if start >= 0 else -1
            if start < 0:
                buffer = ""
                break
            if end < 0:
                buffer = buffer[start:] if len(buffer) - start < _MAX_ELEMENT else ""
                break
            element, buffer = buffer[start:end + 1], buffer[end + 1:]
            self._element(element, arrived)
        self.buffer = buffer
        return True

    def _element(self, element: str, arrived: float) -> None:
        if element.startswith("< send "):
            msg = parse_send(element)
            if msg is None or self.bus is None:
                self.write("< error bad send >")
                return
            if self.held is not None and self.forward_at is not None:
                self._start_forwarding()
            msg.timestamp = arrived
            self.bus.send(msg)
            self.server.frames_from_clients += 1
            return
        words = element.strip("<> ").split()
        if not words:
            return
        if words[0] == "send":
            self._element("< " + " ".join(words) + " >", arrived)
        elif words[0] == "open" and len(words) == 2 and self.bus is None:
            virtual = self.server.virtual_channel(words[1])
            if virtual is None:
                self.write(f"< error no such channel {words[1]} >")
                return
            bus = can.Bus(interface="virtual", channel=virtual, preserve_timestamps=True)
            try:
                attach_sink(bus, _Sink(self))
            except (AttributeError, ValueError):
                bus.shutdown()
                self.write("< error server cannot attach to the virtual bus >")
                raise
            self.bus = bus
            self.write("< ok >")
        elif words[0] == "rawmode" and self.bus is not None:
            self.write("< ok >")
            self.forward_at = time.monotonic() + FORWARD_AFTER_S
        elif words[0] == "echo":
            self.write("< echo >")
        else:
            self.write(f"< error unsupported {words[0]} >")

    def close(self) -> None:
        self.stop.set()
        with self.send_lock:  # no sender is writing to the socket while it closes
            try:
                self.conn.close()
            except OSError:
                pass
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None
        self.server._forget(self)

    def join(self, timeout_s: float) -> None:
        if self.reader.is_alive():  # one-thread servers start no reader
            self.reader.join(timeout_s)


_ANCILLARY_SPACE = socket.CMSG_SPACE(16)


def _kernel_stamp(ancillary: list[tuple[int, int, bytes]]) -> float:
    """The kernel's receive time (wall clock) from ``SO_TIMESTAMPNS`` ancillary data, or now."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= 16:
            secs, nanos = struct.unpack("@qq", data[:16])
            return float(secs + nanos * 1e-9)
    return time.time()






class SocketcandServer:
    """socketcand on ``host:port`` serving the given channels (see the module docstring).

    Args:
        host: listening address (loopback by default; nothing here authenticates).
        port: TCP port, 0 for any free one (read :attr:`port` after :meth:`start`).
        channels: client channel name -> python-can virtual channel name; ``None``: any
            name a client opens is served as the virtual channel of that name.
        timers: one-thread mode: the emulators (in push mode, without threads of their own)
            whose due frames this server's single thread releases. One thread then accepts,
            reads every client (the frames reaching the emulators in it) and sends the
            emulators' answers at their due time: a process serving several buses keeps one
            busy thread, with nothing to hand over and no interpreter lock to contend for.
            ``None``: a thread per client, the emulators' own threads send their answers.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        channels: Mapping[str, str] | None = None,
        timers: Sequence[Timer] | None = None,
    ) -> None:
        self._timers = list(timers) if timers is not None else None
        self.error: BaseException | None = None
        self.host = host
        self._requested_port = port
        self.port = port
        self.channels = dict(channels) if channels is not None else None
        self._listener: socket.socket | None = None
        self._acceptor: threading.Thread | None = None
        self._stop = threading.Event()
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self.connections = 0
        self.frames_from_clients = 0
        self.frames_to_clients = 0

    def virtual_channel(self, channel: str) -> str | None:
        """The virtual channel serving ``channel`` (``None``: not served)."""
        if self.channels is None:
            return channel
        return self.channels.get(channel)

    def send_raw(self, data: bytes) -> int:
        """Write ``data`` as is to every connected client: fault injection, a peer sending
        what a client cannot decode (e.g. bytes that are not ASCII). Returns how many
        clients it was written to."""
        with self._lock:
            clients = list(self._clients)
        written = 0
        for client in clients:
            with client.send_lock:
                try:
                    client.conn.sendall(data)
                except OSError:
                    continue
            written += 1
        return written

    @property
    def clients(self) -> int:
        """Connected clients."""
        with self._lock:
            return len(self._clients)

    def start(self) -> None:
        """Listen and accept clients in a thread.

        Raises:
            OSError: the address cannot be bound.
        """
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((self.host, self._requested_port))
            listener.listen(16)
        except OSError:
            listener.close()
            raise
        listener.settimeout(_POLL_S)
        self._listener = listener
        self.port = listener.getsockname()[1]
        self._stop.clear()
        if self._timers is not None:
            self._acceptor = threading.Thread(target=self._serve, name="socketcand",
                                              daemon=True)
        else:
            self._acceptor = threading.Thread(target=self._accept, name="socketcand-accept",
                                              daemon=True)
        self._acceptor.start()

    def _accept(self) -> None:
        assert self._listener is not None
        while not self._stop.is_set():
            try:
                conn, addr = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            client = self._new_client(conn, addr)
            if client is None:
                break
            client.reader.start()

    def _new_client(self, conn: socket.socket, addr: Any) -> _Client | None:
        """Set up an accepted connection (``None``: the server is stopping)."""
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if _SO_TIMESTAMPNS is not None:
            try:
                conn.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            except OSError:
                pass  # no kernel receive stamps: frames are stamped when read
        client = _Client(self, conn, f"{addr[0]}:{addr[1]}")
        with self._lock:
            if self._stop.is_set():
                conn.close()
                return None
            self._clients.append(client)
            self.connections += 1
        return client

    def _serve(self) -> None:
        """One-thread mode: accept, read every client and release the timers' due frames
        in this thread (see the class docstring)."""

        assert self._listener is not None
        reduce_timer_slack()  # frames are due at exact times; the slack is per thread
        early = WakeEarly()
        timers = self._timers or []
        listener = self._listener
        readers: dict[int, _Client] = {}
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                due: float | None = None
                for timer in timers:
                    t = timer.next_due()
                    if t is not None and (due is None or t < due):
                        due = t
                if due is not None and due - now <= early.early_s:
                    # A frame is ready; hold it until its modelled time (see WakeEarly).
                    early.spin_until(due)
                    now = time.monotonic()
                    for timer in timers:
                        timer.release_due(now)
                    continue
                timeout = _POLL_S if due is None else min(_POLL_S, due - now - early.early_s)
                for client in readers.values():
                    if client.held is not None and client.forward_at is not None:
                        wait = client.forward_at - now
                        if wait <= 0.0:
                            client._start_forwarding()
                        timeout = min(timeout, max(wait, 0.0))
                ready, _, _ = select.select([listener, *[c.conn for c in readers.values()]],
                                            [], [], timeout)
                if not ready:
                    if due is not None:
                        early.observe(now + timeout, time.monotonic())
                    continue
                for sock in ready:
                    if sock is listener:
                        try:
                            conn, addr = listener.accept()
                        except OSError:
                            continue
                        conn.settimeout(_POLL_S)  # bounds a send to a client not reading
                        new = self._new_client(conn, addr)
                        if new is None:
                            return
                        readers[conn.fileno()] = new
                        new.write("< hi >")
                        continue
                    client = readers[sock.fileno()]
                    try:
                        alive = client.receive() and not client.stop.is_set()
                    except TimeoutError:
                        alive = True
                    except OSError as exc:
                        _log.debug("socketcand client %s: %s", client.peer, exc)
                        alive = False
                    if not alive:
                        del readers[sock.fileno()]
                        client.close()
        except Exception as exc:  # noqa: BLE001 - reported through .error
            _log.exception("socketcand server stopped")
            self.error = exc
        finally:
            for client in list(readers.values()):
                client.close()

    def _forget(self, client: _Client) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close the listener and every client; join the threads."""
        self._stop.set()
        if self._acceptor is not None:
            self._acceptor.join(timeout_s)
            self._acceptor = None
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        with self._lock:
            clients = list(self._clients)
        for client in clients:
            client.stop.set()
            try:
                client.conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        for client in clients:
            client.join(timeout_s)

    def __enter__(self) -> SocketcandServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
