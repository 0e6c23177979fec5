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
not receive its own frames; python-can's virtual bus does not echo either). Two threads per
client: one reads the socket and sends on the virtual bus, one receives from the virtual bus
and writes the socket. A client disconnecting (or the server stopping) ends both and shuts its
virtual bus down.

python-can's client reads the handshake replies with one ``recv`` each and compares them
exactly, so no bus frame may be written to a client before it has read the ``< ok >`` of
``rawmode``: frames are forwarded only after the client's first ``< send >`` or
:data:`FORWARD_AFTER_S` after that ``< ok >``, whichever is first.
"""

from __future__ import annotations

import logging
import re
import socket
import threading
import time
from collections.abc import Mapping

import can

__all__ = ["FORWARD_AFTER_S", "SocketcandServer", "format_frame", "parse_send"]

_log = logging.getLogger(__name__)

FORWARD_AFTER_S = 0.05
"""Forward bus frames to a silent client this long after its rawmode ``< ok >``."""

_POLL_S = 0.1  # how often blocked threads look at their stop flag
_MAX_ELEMENT = 512
_SEND = re.compile(
    r"<\s*send\s+([0-9A-Fa-f]{1,8})\s+([0-9A-Fa-f]{1,2})((?:\s+[0-9A-Fa-f]{1,2})*)\s*>"
)


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
    match = _SEND.fullmatch(element.strip())
    if match is None:
        return None
    ident_text, length_text, data_text = match.groups()
    data = bytes(int(b, 16) for b in data_text.split())
    length = int(length_text, 16)
    if length != len(data) or length > 8:
        return None
    return can.Message(arbitration_id=int(ident_text, 16), is_extended_id=len(ident_text) > 3,
                       data=data)


class _Client:
    def __init__(self, server: SocketcandServer, conn: socket.socket, peer: str) -> None:
        self.server = server
        self.conn = conn
        self.peer = peer
        self.bus: can.BusABC | None = None
        self.stop = threading.Event()
        self.forward = threading.Event()
        self.send_lock = threading.Lock()
        self.reader = threading.Thread(target=self._read_tcp, name=f"socketcand-{peer}",
                                       daemon=True)
        self.writer: threading.Thread | None = None

    def write(self, text: str) -> None:
        with self.send_lock:
            self.conn.sendall(text.encode("ascii"))

    def _read_tcp(self) -> None:
        buffer = ""
        try:
            self.write("< hi >")
            self.conn.settimeout(_POLL_S)
            while not self.stop.is_set():
                try:
                    chunk = self.conn.recv(4096)
                except TimeoutError:
                    continue
                if not chunk:
                    break
                buffer += chunk.decode("ascii", errors="replace")
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
                    self._element(element)
        except OSError as exc:
            _log.debug("socketcand client %s: %s", self.peer, exc)
        finally:
            self.close()

    def _element(self, element: str) -> None:
        words = element.strip("<> ").split()
        if not words:
            return
        if words[0] == "send":
            msg = parse_send(element)
            if msg is None or self.bus is None:
                self.write("< error bad send >")
                return
            self.forward.set()
            self.bus.send(msg)
            self.server.frames_from_clients += 1
        elif words[0] == "open" and len(words) == 2 and self.bus is None:
            virtual = self.server.virtual_channel(words[1])
            if virtual is None:
                self.write(f"< error no such channel {words[1]} >")
                return
            self.bus = can.Bus(interface="virtual", channel=virtual)
            self.write("< ok >")
        elif words[0] == "rawmode" and self.bus is not None:
            self.write("< ok >")
            self.writer = threading.Thread(target=self._write_tcp, name=f"socketcand-w-{self.peer}",
                                           daemon=True)
            self.writer.start()
        elif words[0] == "echo":
            self.write("< echo >")
        else:
            self.write(f"< error unsupported {words[0]} >")

    def _write_tcp(self) -> None:
        assert self.bus is not None
        self.forward.wait(FORWARD_AFTER_S)
        try:
            while not self.stop.is_set():
                msg = self.bus.recv(timeout=_POLL_S)
                if msg is not None:
                    self.write(format_frame(msg))
                    self.server.frames_to_clients += 1
        except (OSError, can.CanError) as exc:
            _log.debug("socketcand client %s: %s", self.peer, exc)
        finally:
            self.stop.set()

    def close(self) -> None:
        self.stop.set()
        writer = self.writer
        if writer is not None and writer is not threading.current_thread():
            writer.join(2.0)
        try:
            self.conn.close()
        except OSError:
            pass
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None
        self.server._forget(self)

    def join(self, timeout_s: float) -> None:
        self.reader.join(timeout_s)


class SocketcandServer:
    """socketcand on ``host:port`` serving the given channels (see the module docstring).

    Args:
        host: listening address (loopback by default; nothing here authenticates).
        port: TCP port, 0 for any free one (read :attr:`port` after :meth:`start`).
        channels: client channel name -> python-can virtual channel name; ``None``: any
            name a client opens is served as the virtual channel of that name.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        channels: Mapping[str, str] | None = None,
    ) -> None:
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
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(self, conn, f"{addr[0]}:{addr[1]}")
            with self._lock:
                if self._stop.is_set():
                    conn.close()
                    break
                self._clients.append(client)
                self.connections += 1
            client.reader.start()

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
