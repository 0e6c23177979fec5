"""Newline-delimited JSON framing of the socket API, no I/O: bytes to messages and back.

Every message is one JSON object on one line, UTF-8, ending with ``\\n`` (a ``\\r`` before it is
ignored, blank lines are skipped). :class:`MessageDecoder` turns whatever the socket gave into
complete JSON objects, with the refusals the protocol adds to Python's ``json`` (``NaN`` tokens,
duplicate keys, lone surrogate escapes, over-long lines reported once and skipped, a last line
without its newline never decoded); :func:`encode` writes one message.

Binary frames (protocol version 2, docs/protocol.md "Binary frames")::

    {"id":1,"op":"send_goal",...,"attachment":{"bytes":N,"dtype":"<f8",...}}\\n
    <N raw bytes>\\n

A line whose object has an ``attachment`` is followed by exactly ``N`` raw bytes and one
``\\n``; the decoder reads them without looking for newlines in them and hands the message on
with an :class:`Attachment` in place of the header's object (:mod:`.protocol` reads its
numbers). A frame that cannot be trusted -- an attachment header without a usable ``bytes``,
a header line that is not JSON but names an attachment, raw bytes not followed by ``\\n``, or
the stream ending inside them -- is ``bad_frame``: the stream is out of sync, the decoder
reads nothing more and the transport closes the connection. An attachment longer than the
line limit is ``too_large`` and its bytes are skipped; the connection goes on.
The error codes and :class:`RequestError` live here because both directions use them; what a
request means is :mod:`jtc_hw.api.protocol`.
"""

from __future__ import annotations

import contextlib
import gc
import json
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from enum import Enum
from types import ModuleType
from typing import Any

import numpy as np

from ..errors import ProtocolError

_orjson: ModuleType | None
try:
    import orjson as _orjson
except ImportError:  # optional: the standard library decodes everything, only slower
    _orjson = None

__all__ = [
    "ATTACHMENT_FIELDS", "BAD_FRAME", "BAD_JSON", "BAD_REQUEST", "BUSY",
    "DEFAULT_MAX_MESSAGE_BYTES", "ERROR_CODES", "GOAL_REJECTED", "HARDWARE", "IDLE", "INTERNAL",
    "NOT_ACTIVE", "NOT_FOUND", "PROTOCOL_VERSION", "PROTOCOL_VERSIONS", "TOO_LARGE",
    "UNAUTHORIZED", "UNKNOWN_OP", "Attachment", "MessageDecoder", "RequestError", "RequestId",
    "encode", "encode_frame", "error_reply", "reply",
]

PROTOCOL_VERSION = 2
"""Version of this wire format; ``hello`` reports it and may ask for it. Version 2 added binary
frames (module docstring); a version 1 client (NDJSON only) is served unchanged."""
PROTOCOL_VERSIONS = (1, 2)
"""The versions a client may ask for in ``hello``."""

DEFAULT_MAX_MESSAGE_BYTES = 4 << 20
"""Default limit on one request line (bytes, without the newline): 4 MiB, as the robot file's
``daemon.max_message_bytes`` default."""

# Machine error codes (``error.code`` of a failed reply).
BAD_JSON = "bad_json"
BAD_FRAME = "bad_frame"
TOO_LARGE = "too_large"
BAD_REQUEST = "bad_request"
UNKNOWN_OP = "unknown_op"
GOAL_REJECTED = "goal_rejected"
NOT_ACTIVE = "not_active"
NOT_FOUND = "not_found"
BUSY = "busy"
UNAUTHORIZED = "unauthorized"
IDLE = "idle"
HARDWARE = "hardware"
INTERNAL = "internal"
ERROR_CODES = (
    BAD_JSON,
    BAD_FRAME,
    TOO_LARGE,
    BAD_REQUEST,
    UNKNOWN_OP,
    GOAL_REJECTED,
    NOT_ACTIVE,
    NOT_FOUND,
    BUSY,
    UNAUTHORIZED,
    IDLE,
    HARDWARE,
    INTERNAL,
)

RequestId = int | str | None
"""A client-chosen request id, echoed in the reply (``None``: the request had none)."""


class RequestError(ProtocolError):
    """A request that cannot be served, as a value (``Decoder.feed``) or raised (the client).

    ``str(error)`` is the human message.

    Attributes:
        code: one of ``ERROR_CODES``.
        message: precise human text (names the JSON path, the value, what would be accepted).
        request_id: the request's ``id`` when it could be read, else ``None``.
        error_code: for ``goal_rejected``, the ``FollowJointTrajectory`` result code.
    """

    def __init__(
        self,
        code: str,
        message: str,
        request_id: RequestId = None,
        error_code: int | None = None,
    ) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.request_id = request_id
        self.error_code = error_code

    def reply(self) -> dict[str, Any]:
        """The error reply for this error."""
        return error_reply(self.request_id, self.code, self.message, self.error_code)

    def __repr__(self) -> str:
        return f"RequestError({self.code!r}, {self.message!r}, request_id={self.request_id!r})"


def _describe(value: Any) -> str:
    """A JSON-flavoured description of a received value, for error messages."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"a boolean ({'true' if value else 'false'})"
    if isinstance(value, (int, float)):
        text = repr(value)
        return f"a number ({text if len(text) <= 24 else text[:21] + '...'})"
    if isinstance(value, str):
        text = json.dumps(value, ensure_ascii=False)
        return f"a string ({text if len(text) <= 40 else text[:37] + '...'})"
    if isinstance(value, list):
        return f"an array of {len(value)} element(s)"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__  # pragma: no cover - json.loads produces nothing else


# -- decoding ---------------------------------------------------------------------------------


class _Refused(ValueError):
    """Raised from inside ``json.loads`` hooks."""


def _refuse_constant(name: str) -> Any:
    raise _Refused(f"'{name}' is not JSON (non-finite numbers are refused); send a finite number")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise _Refused(f"duplicate key '{key}' in an object")
            seen.add(key)
    return obj


# A JSON ``\uD800``..``\uDFFF`` escape: the only way a surrogate code point reaches a decoded
# string (raw UTF-8 cannot carry one; Python's codec refuses it). A pair is joined into one
# character by ``json``; a lone one stays in the ``str`` and can never be written back as UTF-8.
_SURROGATE_ESCAPE = re.compile(rb"\\u[dD][89abcdefABCDEF]")


FAST_DECODE_BYTES = 16 << 10
"""Lines from this size on are decoded by ``orjson`` when it is installed (see
:func:`_fast_loads`); shorter ones cost the standard library little."""

# Digits as "0", and what can stand right before an integer literal as "y" (JSON puts it after
# a "-", ":", ",", "[" or whitespace). See _fast_loads.
_INTEGER_STARTS = bytes.maketrans(b"0123456789-:,[ \t\r\n", b"0000000000yyyyyyyy")
_LONG_INTEGER = b"y" + b"0" * 19  # an integer beyond int64 has at least 19 digits
_UNUSABLE = object()


def _fast_loads(line: bytes) -> Any:
    """``line`` decoded by ``orjson``, or ``_UNUSABLE`` where its result could differ from
    :func:`json.loads` with the protocol's refusals; then the standard library decodes it.

    A 2,000-point goal (617 kB) takes 6.5 ms with the standard library, 2.4 ms here (1.1 ms of
    it ``orjson`` itself, the rest the two checks below). ``orjson`` refuses on its own what the
    protocol refuses: ``NaN``/``Infinity`` tokens, numbers that overflow a float64, lone
    surrogates (escaped or not), invalid UTF-8 (the fallback then words the error as before).
    It differs in two ways, both checked here:

    - duplicate keys: it keeps the last. The text has one ``:`` per key plus those inside
      strings; re-encoded, the value has one per key it kept plus the same ones inside strings
      (a ``\\u003a`` escape would add one: such a line is left to the standard library). Equal
      counts: no key was dropped.
    - integer literals beyond 64 bits become floats (the standard library keeps them ints,
      which the protocol then names exactly). Such a literal is a run of 19 or more digits
      at the start or after a ``-``, ``:``, ``,``, ``[`` or whitespace: none may occur (a
      float's integer part, a negative exponent or a string holding such a run are taken for
      one too, and go to the standard library; a fraction's digits follow a ``.``).
    """
    assert _orjson is not None
    if b"\\" in line and b"\\u003" in line:
        return _UNUSABLE
    starts = line.translate(_INTEGER_STARTS)
    if _LONG_INTEGER in starts or starts.startswith(_LONG_INTEGER[1:]):
        return _UNUSABLE
    try:
        obj = _orjson.loads(line)
        again = _orjson.dumps(obj)
    except (_orjson.JSONDecodeError, _orjson.JSONEncodeError):
        return _UNUSABLE
    if again.count(b":") != line.count(b":"):
        return _UNUSABLE
    return obj


@contextlib.contextmanager
def gc_paused(enabled: bool = True) -> Iterator[None]:
    """The cyclic garbage collector off for the block (if ``enabled``), back as it was after.

    Decoding a long line makes tens of thousands of lists and dicts (a 75,000-point goal:
    150,000), none of them garbage and none in a cycle; meanwhile the collector runs every
    700 allocations over a young generation that keeps growing, and some of its runs go
    through everything: measured 180 ms instead of 45 ms for that goal with ``orjson``
    (230-360 instead of 80-115 ms with ``json``). They are examined a few times afterwards
    instead of hundreds of times during.
    """
    if not enabled or not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


def _loads_line(line: bytes, lineno: int) -> Any:
    """Decode one message's JSON (``orjson`` for long lines when it is installed and gives
    what the standard library would: :func:`_fast_loads`).

    Raises:
        RequestError: ``bad_json``, with the connection line and the column; ``bad_request``
            for a string holding a lone surrogate (names its JSON path, the text escaped).
    """
    if _orjson is not None and len(line) >= FAST_DECODE_BYTES:
        fast = _fast_loads(line)
        if fast is not _UNUSABLE:
            return fast
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RequestError(
            BAD_JSON, f"line {lineno}: not valid UTF-8 at byte {exc.start + 1}"
        ) from None
    try:
        obj = json.loads(text, parse_constant=_refuse_constant, object_pairs_hook=_unique_keys)
    except json.JSONDecodeError as exc:
        raise RequestError(
            BAD_JSON, f"line {lineno}, column {exc.colno}: malformed JSON: {exc.msg}"
        ) from None
    except _Refused as exc:
        raise RequestError(BAD_JSON, f"line {lineno}: {exc}") from None
    except RecursionError:
        raise RequestError(BAD_JSON, f"line {lineno}: JSON nested too deeply") from None
    except ValueError as exc:  # e.g. an integer literal with more than 4300 digits
        raise RequestError(BAD_JSON, f"line {lineno}: {exc}") from None
    if _SURROGATE_ESCAPE.search(line) is not None:
        _refuse_unencodable(obj, lineno)
    return obj


def _unencodable(text: str) -> bool:
    if text.isascii():
        return False
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return True
    return False


def _escaped(text: str, limit: int = 40) -> str:
    """``text`` as a JSON string literal with every non-ASCII character escaped (so that a
    message quoting it can always be encoded), shortened to about ``limit`` characters."""
    quoted = json.dumps(text)
    return quoted if len(quoted) <= limit else quoted[: limit - 4] + '..."'


def _refuse_unencodable(obj: Any, lineno: int) -> None:
    """Raise for the first string (key or value) of ``obj`` that is not valid Unicode.

    Iterative: ``obj`` may be nested as deeply as ``json`` allows.

    Raises:
        RequestError: ``bad_request`` naming the JSON path, with the request ``id`` when it is
            itself usable.
    """
    rid: RequestId = None
    if isinstance(obj, dict):
        candidate = obj.get("id")
        if (isinstance(candidate, int) and not isinstance(candidate, bool)) or (
            isinstance(candidate, str) and not _unencodable(candidate)
        ):
            rid = candidate
    stack: list[tuple[str, Any]] = [("", obj)]
    while stack:
        path, value = stack.pop()
        bad: str | None
        if isinstance(value, str):
            bad, where = value, path or "the message"
        elif isinstance(value, dict):
            bad = next((key for key in value if _unencodable(key)), None)
            where = f"{path}: the key" if path else "the key"
            if bad is None:
                items = list(value.items())
                stack.extend(
                    (f"{path}.{key}" if path else key, item) for key, item in reversed(items)
                )
                continue
        elif isinstance(value, list):
            stack.extend((f"{path}[{i}]", item) for i, item in reversed(list(enumerate(value))))
            continue
        else:
            continue
        if bad is not None and _unencodable(bad):
            raise RequestError(
                BAD_REQUEST,
                f"line {lineno}: {where} {_escaped(bad)} holds a lone UTF-16 surrogate "
                "(a \\uD800-\\uDFFF escape without its pair), which is not a character; "
                "send valid Unicode text. The request was not executed",
                rid,
            )


ATTACHMENT_FIELDS = ("bytes", "dtype", "shape", "columns")
"""The fields of a request's ``attachment`` object (docs/protocol.md, "Binary frames")."""


@dataclass(frozen=True)
class Attachment:
    """A binary frame's raw bytes and the header that describes them, as received.

    Only ``bytes`` (the length) is checked here: it says where the next message starts. The
    other fields are the header's values as they came (:mod:`.protocol` checks them, and the
    numbers).

    Attributes:
        data: the raw bytes (``header["bytes"]`` of them).
        header: the request's ``attachment`` object.
    """

    data: bytes
    header: dict[str, Any]

    def __repr__(self) -> str:
        return f"Attachment({len(self.data)} bytes, {self.header!r:.120})"


RAW_BYTES_PER_JSON_BYTE = 32
"""A binary frame's raw bytes cost about this many times less to decode than JSON text (a
2,000-point goal: 0.14 ms for its 208 kB frame, 24 ms for its 617 kB line)."""


def _announced_length(line: bytes) -> int | None:
    """The attachment length a (short) header line announces, or ``None`` (not readable)."""
    if len(line) > 1 << 16:
        return None
    try:
        obj = json.loads(line)
    except ValueError:
        return None
    if not isinstance(obj, dict) or "attachment" not in obj:
        return None
    length = _frame_length(obj)
    return None if isinstance(length, str) else length


def _frame_length(obj: dict[str, Any]) -> int | str:
    """The raw byte count a message's ``attachment`` announces, or why it cannot be trusted."""
    header = obj["attachment"]
    if not isinstance(header, dict):
        return f"'attachment' must be an object, got {_describe(header)}"
    length = header.get("bytes")
    if isinstance(length, bool) or not isinstance(length, int):
        return f"attachment.bytes must be an integer, got {_describe(length)}"
    if length < 0:
        return f"attachment.bytes must not be negative, got {length}"
    return length


class _Lines:
    """A byte stream as lines, or as a given number of raw bytes (a binary frame's).

    ``add`` buffers data; ``line`` and ``take`` consume it. Lines are limited to ``max_bytes``
    (without the newline); an over-long one is reported once as ``None`` and skipped up to its
    newline. ``skip`` discards a number of bytes, buffered or still to come.
    """

    def __init__(self, max_bytes: int) -> None:
        if max_bytes < 1:
            raise ValueError(f"max_message_bytes must be >= 1, got {max_bytes}")
        self.max_bytes = max_bytes
        self._buf = bytearray()
        self._pos = 0  # start of what is not consumed yet
        self._scanned = 0  # bytes from _pos known to hold no newline
        self._discarding = False
        self._skipping = 0  # raw bytes still to discard
        self.lineno = 0  # lines completed so far

    def add(self, data: bytes) -> None:
        if self._skipping:
            n = min(self._skipping, len(data))
            self._skipping -= n
            data = data[n:]
        if self._discarding and data:
            nl = data.find(b"\n")
            if nl < 0:
                return
            self._discarding = False
            self.lineno += 1
            data = data[nl + 1 :]
        self._buf += data

    def line(self) -> tuple[int, bytes | None] | None:
        """The next complete line as ``(line number, content)`` (``None`` content: it was
        too long), or ``None`` if it has not all arrived."""
        buf, pos = self._buf, self._pos
        nl = buf.find(b"\n", pos + self._scanned)
        if nl < 0:
            if len(buf) - pos > self.max_bytes:
                self._drop()
                self._discarding = True
                return (self.lineno + 1, None)
            self._scanned = len(buf) - pos
            return None
        self._scanned = 0
        self._pos = nl + 1
        self.lineno += 1
        if nl > pos and buf[nl - 1] == 0x0D:  # "\r\n"
            nl -= 1
        if nl - pos > self.max_bytes:
            return (self.lineno, None)
        return (self.lineno, bytes(buf[pos:nl]))

    def take(self, n: int) -> bytes | None:
        """The next ``n`` raw bytes, or ``None`` if they have not all arrived."""
        if len(self._buf) - self._pos < n:
            return None
        data = bytes(self._buf[self._pos : self._pos + n])
        self._pos += n
        self._scanned = 0
        return data

    def skip(self, n: int) -> None:
        """Discard the next ``n`` raw bytes (those not buffered yet as they arrive)."""
        held = len(self._buf) - self._pos
        if held >= n:
            self._pos += n
        else:
            self._drop()
            self._skipping = n - held
        self._scanned = 0

    def compact(self) -> None:
        """Forget what was consumed (after each ``feed``)."""
        if self._pos:
            del self._buf[: self._pos]
            self._pos = 0

    def _drop(self) -> None:
        self._buf.clear()
        self._pos = self._scanned = 0

    def unconsumed(self, limit: int) -> bytes:
        """The bytes received and not consumed, if at most ``limit``; else nothing."""
        if len(self._buf) - self._pos > limit:
            return b""
        return bytes(self._buf[self._pos :])

    @property
    def held(self) -> int:
        """Bytes received and not consumed."""
        return len(self._buf) - self._pos

    def end(self) -> int | None:
        """Forget the input after the last newline; the line number of that unterminated
        rest if it held anything but blanks (an over-long line was reported already)."""
        rest = bytes(self._buf[self._pos :])
        self._drop()
        discarding, self._discarding = self._discarding, False
        if discarding or not rest.strip():
            return None
        self.lineno += 1
        return self.lineno


class MessageDecoder:
    """Messages from a byte stream: NDJSON lines, and binary frames (module docstring).

    Args:
        max_message_bytes: longest accepted line, without its newline, and longest accepted
            attachment.
        frames: read binary frames (a daemon's requests); ``False``: NDJSON only, an
            ``attachment`` being a field like any other (a client reading the daemon's
            messages: the daemon sends no frames).
    """

    def __init__(
        self, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES, frames: bool = True
    ) -> None:
        self._lines = _Lines(max_message_bytes)
        self._frames = frames
        self._frame: tuple[int, dict[str, Any], int] | None = None  # awaiting its raw bytes
        self._skipped = False  # the awaited frame's bytes are skipped (too_large)
        self._refusal: RequestError | None = None  # the awaited frame's reply, if refused
        self.broken = False
        """A ``bad_frame`` was returned: the stream is out of sync, nothing more is read."""

    def feed(self, data: bytes) -> list[dict[str, Any] | RequestError]:
        """Messages completed by ``data``, in order; unusable ones as ``RequestError`` values
        (it never raises).

        Blank lines are skipped. An over-long line yields one ``too_large`` error, as soon as
        the limit is passed, and its remaining bytes are discarded up to the next newline. A
        message with an attachment comes out once its raw bytes and their newline are in,
        with an :class:`Attachment` as its ``attachment``. After a ``bad_frame``, nothing.
        """
        if self.broken:
            return []
        lines = self._lines
        lines.add(data)
        out: list[dict[str, Any] | RequestError] = []
        while not self.broken:
            if self._frame is not None:
                item = self._frame_bytes()
                if item is None:
                    break
                out.append(item)
                continue
            got = lines.line()
            if got is None:
                break
            item = self._decode(*got)
            if item is not None:
                out.append(item)
        lines.compact()
        return out

    def decode_cost(self, data: bytes) -> int:
        """About what :meth:`feed` of ``data`` costs, in bytes of JSON decoded: the lines it
        completes (with what is held of an unfinished one), and a binary frame's raw bytes at
        :data:`RAW_BYTES_PER_JSON_BYTE` to one (they are sliced, then read with
        ``numpy.frombuffer``). A caller decides by it whether to feed in a worker thread; it
        errs high: a header line it cannot read (over 64 KiB, not JSON) counts everything
        after it as JSON."""
        held = self._lines.held
        at, cost = 0, 0
        if self._frame is not None:  # its raw bytes are arriving
            due = (1 if self._skipped else self._frame[2] + 1) - held
            if due > len(data):
                return 0
            cost, at, held = due // RAW_BYTES_PER_JSON_BYTE, due, 0
        while True:
            newline = data.find(b"\n", at)
            if newline < 0:
                return cost
            cost += held + newline - at
            line = data[at:newline]
            if held:
                line = self._lines.unconsumed(1 << 16) + line
            at = newline + 1
            if not self._frames or b'"attachment"' not in line:
                held = 0
                continue
            length = _announced_length(line)
            if length is None:
                return cost + len(data) - at
            due = min(length + 1, len(data) - at)
            cost += due // RAW_BYTES_PER_JSON_BYTE
            at += due
            held = 0

    def end(self) -> list[dict[str, Any] | RequestError]:
        """Call at end of input. A last message without its newline is never decoded: it may
        be cut off (the peer died mid-write), and a truncated request must not be executed.
        Returns nothing, or one error for the unterminated rest: ``bad_json`` for a line,
        ``bad_frame`` for a binary frame's bytes (it never raises).
        """
        if self.broken:
            return []
        if self._frame is not None:
            lineno, obj, length = self._frame
            held = self._lines.held
            self._frame = None
            self._lines.end()
            return [self._bad_frame(
                f"line {lineno}: the connection ended after {held} of the attachment's "
                f"{length} bytes and its newline; the request was not executed",
                _readable_id(obj))]
        rest = self._lines.end()
        if rest is None:
            return []
        return [
            RequestError(
                BAD_JSON,
                f"line {rest}: the connection ended before this message's newline; it was "
                "not executed (end every message with \\n)",
            )
        ]

    def _bad_frame(self, message: str, rid: RequestId = None) -> RequestError:
        self.broken = True
        return RequestError(
            BAD_FRAME,
            f"{message}; the stream is out of sync, closing the connection "
            "(docs/protocol.md, \"Binary frames\")",
            rid,
        )

    def _frame_bytes(self) -> dict[str, Any] | RequestError | None:
        """The awaited frame's message once its raw bytes and newline are in, else None."""
        assert self._frame is not None
        lineno, obj, length = self._frame
        raw = self._lines.take(1 if self._skipped else length + 1)
        if raw is None:
            return None
        refusal = self._refusal
        self._frame, self._skipped, self._refusal = None, False, None
        if raw[-1:] != b"\n":
            return self._bad_frame(
                f"line {lineno}: the attachment's {length} bytes are not followed by \\n "
                f"(byte {raw[-1]:#04x}): its length is wrong",
                _readable_id(obj),
            )
        if refusal is not None:
            return refusal
        return {**obj, "attachment": Attachment(raw[:-1], obj["attachment"])}

    def _decode(self, lineno: int, line: bytes | None) -> dict[str, Any] | RequestError | None:
        """One line's message, or the error; ``None`` for a blank line. A line whose object
        has an attachment starts a frame (``None`` until its bytes are in)."""
        if line is None:
            return RequestError(
                TOO_LARGE,
                f"line {lineno}: message longer than the limit of "
                f"{self._lines.max_bytes} bytes; it was discarded up to its newline",
            )
        if not line.strip():
            return None
        refusal: RequestError | None = None
        try:
            with gc_paused(len(line) >= FAST_DECODE_BYTES):
                obj = _loads_line(line, lineno)
        except RequestError as exc:
            if not self._frames or b'"attachment"' not in line:
                return exc
            if exc.code != BAD_REQUEST:
                return self._bad_frame(f"{exc.message}; the line names an attachment, whose "
                                       "length cannot be read")
            # JSON, but a string in it is not Unicode (a lone surrogate escape): the length
            # can be read, the frame is skipped whole and refused.
            obj, refusal = json.loads(line.decode("utf-8")), exc
        if not isinstance(obj, dict):
            return refusal or RequestError(
                BAD_REQUEST,
                f"line {lineno}: a message must be a JSON object, got {_describe(obj)}",
            )
        if not self._frames or "attachment" not in obj:
            return obj if refusal is None else refusal
        length = _frame_length(obj)
        if isinstance(length, str):
            return self._bad_frame(f"line {lineno}: {length}", _readable_id(obj))
        self._frame = (lineno, obj, length)
        self._refusal = refusal
        if length > self._lines.max_bytes:
            self._lines.skip(length)
            self._skipped = True
            self._refusal = refusal or RequestError(
                TOO_LARGE,
                f"line {lineno}: attachment of {length} bytes, longer than the limit of "
                f"{self._lines.max_bytes} bytes; it was skipped and the request not executed",
                _readable_id(obj),
            )
        return self._frame_bytes()


def _readable_id(obj: dict[str, Any]) -> RequestId:
    rid = obj.get("id")
    if isinstance(rid, str) or (isinstance(rid, int) and not isinstance(rid, bool)):
        return rid
    return None


# -- encoding ---------------------------------------------------------------------------------


_FLOAT_ONLY = frozenset({float})


def _jsonable(obj: Any) -> Any:
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    if isinstance(obj, Enum):
        return _jsonable(obj.value)
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        if obj and _FLOAT_ONLY.issuperset(map(type, obj)) and math.isfinite(sum(obj)):
            # Finite floats only (a sum of floats is finite only if each is): as they are. A
            # trajectory's value arrays, 12,000 per 2,000-point goal, skip a call per value.
            return list(obj)
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    raise TypeError(f"cannot encode a {type(obj).__name__} as JSON: {obj!r:.60}")


def encode(obj: Any) -> bytes:
    """One message: compact JSON, UTF-8, ending with a newline.

    Accepts dicts, lists, tuples, strings, numbers, booleans, ``None``, enums (their value),
    numpy arrays and scalars. A non-finite float (``NaN``, ``inf``) is written as ``null``: it
    means "no value" (e.g. a joint without a velocity reading), and JSON has no such numbers.
    A lone surrogate in a string (not Unicode, cannot be UTF-8) is written as U+FFFD.

    Raises:
        TypeError: ``obj`` contains something else.
    """
    text = json.dumps(_jsonable(obj), allow_nan=False, ensure_ascii=False, separators=(",", ":"))
    try:
        return text.encode("utf-8") + b"\n"
    except UnicodeEncodeError:
        # A lone surrogate in a string that did not come off the wire (requests holding one
        # are refused), e.g. a driver's error text: U+FFFD, so the message is still sent.
        fixed = text.encode("utf-16", "surrogatepass").decode("utf-16", "replace")
        return fixed.encode("utf-8") + b"\n"


def encode_frame(obj: dict[str, Any], values: Any, columns: Sequence[str]) -> bytes:
    """One message with a binary attachment (docs/protocol.md, "Binary frames"): ``obj`` with
    an ``attachment`` header as its line, then ``values`` as little-endian float64 bytes (row
    by row) and a newline.

    Args:
        obj: the request without its attachment.
        values: an ``(m, c)`` array of numbers, one row per point.
        columns: the ``c`` column names.

    Raises:
        ValueError: ``values`` is not two-dimensional with one column per name.
    """
    array = np.ascontiguousarray(values, dtype="<f8")
    if array.ndim != 2 or array.shape[1] != len(columns):
        raise ValueError(f"values must have shape (points, {len(columns)}), got {array.shape}")
    data = array.tobytes()
    header = {"bytes": len(data), "dtype": "<f8", "shape": list(array.shape),
              "columns": list(columns)}
    return b"".join((encode({**obj, "attachment": header}), data, b"\n"))


def reply(request_id: RequestId, **fields: Any) -> dict[str, Any]:
    """A successful reply."""
    return {"id": request_id, "ok": True, **fields}


def error_reply(
    request_id: RequestId, code: str, message: str, error_code: int | None = None
) -> dict[str, Any]:
    """A failed reply; ``error_code`` (goal rejections) goes into the ``error`` object."""
    error: dict[str, Any] = {"code": code, "message": message}
    if error_code is not None:
        error["error_code"] = int(error_code)
    return {"id": request_id, "ok": False, "error": error}
