"""Raw clients of the socket server for tests: a JSON-lines peer on a real socket, a watch on
the server's log, and the asyncio runner the server tests share."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Coroutine, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


def run(coro: Coroutine[Any, Any, T], timeout_s: float = 15.0) -> T:
    return asyncio.run(asyncio.wait_for(coro, timeout_s))


def goal_msg(positions: Sequence[float] = (0.5, -0.5), t: float = 1.0, **extra: Any) -> Any:
    traj = {
        "joint_names": ["j1", "j2"],
        "points": [{"time_from_start": t, "positions": list(positions)}],
    }
    traj.update(extra)
    return traj


class Peer:
    """A raw client on a real socket: JSON lines out, JSON lines in."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer
        self.inbox: list[dict[str, Any]] = []  # events received while waiting for replies
        self._ids = 0

    @classmethod
    async def unix(cls, path: Path, limit: int = 1 << 24) -> Peer:
        """``limit``: the stream stops reading from the socket at twice this many unread
        bytes (a client that does not read)."""
        reader, writer = await asyncio.open_unix_connection(str(path), limit=limit)
        return cls(reader, writer)

    @classmethod
    async def tcp(cls, address: tuple[str, int]) -> Peer:
        reader, writer = await asyncio.open_connection(*address, limit=1 << 24)
        return cls(reader, writer)

    async def send(self, message: Any) -> None:
        data = message if isinstance(message, bytes) else json.dumps(message).encode() + b"\n"
        self.writer.write(data)
        await self.writer.drain()

    async def recv(self, timeout_s: float = 5.0) -> dict[str, Any]:
        line = await asyncio.wait_for(self.reader.readline(), timeout_s)
        assert line, "the server closed the connection"
        assert line.endswith(b"\n")
        message: dict[str, Any] = json.loads(line)
        return message

    async def request(self, op: str, **fields: Any) -> dict[str, Any]:
        self._ids += 1
        await self.send({"id": self._ids, "op": op, **fields})
        return await self.reply(self._ids)

    async def reply(self, request_id: Any) -> dict[str, Any]:
        while True:
            message = await self.recv()
            if "event" in message:
                self.inbox.append(message)
            else:
                assert message["id"] == request_id, message
                return message

    async def event(self, name: str, timeout_s: float = 5.0) -> dict[str, Any]:
        for i, message in enumerate(self.inbox):
            if message["event"] == name:
                return self.inbox.pop(i)
        while True:
            message = await self.recv(timeout_s)
            if message.get("event") == name:
                return message
            self.inbox.append(message)

    async def eof(self, timeout_s: float = 5.0) -> bytes:
        """Everything until the server closes the connection."""
        return await asyncio.wait_for(self.reader.read(), timeout_s)

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(OSError):
            await self.writer.wait_closed()


class LogWatch(logging.Handler):
    """Collects the socket server's records (``jtc_hw.daemon.transports.server``); tests await
    a record containing a fragment."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.messages: list[str] = []
        self._waiting: list[tuple[str, asyncio.Future[str]]] = []

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        self.messages.append(message)
        for fragment, future in self._waiting:
            if fragment in message and not future.done():
                future.set_result(message)

    async def wait_for(self, fragment: str, timeout_s: float = 5.0) -> str:
        for message in self.messages:
            if fragment in message:
                return message
        future: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        self._waiting.append((fragment, future))
        try:
            return await asyncio.wait_for(future, timeout_s)
        finally:
            self._waiting.remove((fragment, future))

    def count(self, fragment: str) -> int:
        return sum(fragment in m for m in self.messages)

    async def wait_count(self, fragment: str, n: int, timeout_s: float = 5.0) -> None:
        """Until ``n`` records contain ``fragment``."""
        while self.count(fragment) < n:
            future: asyncio.Future[str] = asyncio.get_running_loop().create_future()
            self._waiting.append((fragment, future))
            try:
                await asyncio.wait_for(future, timeout_s)
            finally:
                self._waiting.remove((fragment, future))


@contextlib.contextmanager
def watch_server_log() -> Iterator[LogWatch]:
    """Collect the server's log records (at DEBUG) while the block runs."""
    watch = LogWatch()
    logger = logging.getLogger("jtc_hw.server")
    old_level = logger.level
    logger.addHandler(watch)
    logger.setLevel(logging.DEBUG)
    yield watch
    logger.removeHandler(watch)
    logger.setLevel(old_level)
