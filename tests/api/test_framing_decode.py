"""Long lines decoded by ``orjson`` give exactly what the standard library gives.

``framing._loads_line`` hands lines of ``FAST_DECODE_BYTES`` or more to ``orjson`` when it is
installed, and falls back to ``json`` wherever ``orjson``'s result could differ (duplicate
keys, integers beyond 64 bits) or it refuses the line (so the error is worded as before). Here
every line is decoded both ways -- the threshold lowered to 0, then ``orjson`` taken away --
and must give the same value (same types, same float bits, same key order) or the same error.
The texts are random JSON written with the liberties a client can take: whitespace, number
spellings, escapes, duplicate keys, big integers, non-finite tokens, lone surrogates.
"""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from jtc_hw.api import framing
from jtc_hw.api.framing import RequestError, encode

pytest.importorskip("orjson")

SPACES = st.sampled_from(["", "", "", " ", "\t", "\r ", "  "])  # no newline: a line


def _number(draw: st.DrawFn) -> str:
    kind = draw(st.sampled_from(
        ["int", "bigint", "float", "exp", "fraction", "special", "negzero", "int19"]
    ))
    if kind == "int":
        return str(draw(st.integers(-(2**63), 2**64)))
    if kind == "bigint":
        return str(draw(st.one_of(st.integers(2**64, 2**200), st.integers(-(2**200), -(2**63)))))
    if kind == "int19":
        return draw(st.sampled_from(["-", ""])) + "1" + "0" * draw(st.integers(17, 25))
    if kind == "float":
        return repr(draw(st.floats(allow_nan=False, allow_infinity=False)))
    if kind == "exp":
        mantissa = draw(st.floats(-10, 10, allow_nan=False))
        return f"{mantissa!r}{draw(st.sampled_from(['e', 'E']))}" + draw(
            st.sampled_from(["", "+", "-"])
        ) + str(draw(st.integers(0, 400)))
    if kind == "fraction":
        return "0." + "0" * draw(st.integers(0, 6)) + str(draw(st.integers(0, 10**25)))
    if kind == "negzero":
        return draw(st.sampled_from(["-0", "-0.0", "0e0", "-0E-0"]))
    return draw(st.sampled_from(["NaN", "Infinity", "-Infinity", "1e999", "-1e400"]))


def _string(draw: st.DrawFn) -> str:
    text = draw(st.text(max_size=6))
    out = []
    for ch in text:
        how = draw(st.integers(0, 9))
        if how == 0:
            out.append(f"\\u{ord(ch):04x}" if ord(ch) < 0x10000 else json.dumps(ch)[1:-1])
        else:
            out.append(json.dumps(ch, ensure_ascii=False)[1:-1])
    extra = draw(st.sampled_from(["", "", "", ":", "\\u003a", "\\u003A", "\\ud800", "\\udc00x",
                                  "\\ud83d\\ude00", "1234567890123456789012"]))
    return '"' + "".join(out) + extra + '"'


@st.composite
def json_strings(draw: st.DrawFn) -> str:
    return _string(draw)


@st.composite
def json_texts(draw: st.DrawFn, depth: int = 0) -> str:
    sp = draw(SPACES)
    kind = draw(st.sampled_from(["object", "object", "array", "number", "string", "literal"]
                                if depth < 4 else ["number", "string", "literal"]))
    if kind == "number":
        return sp + _number(draw) + sp
    if kind == "string":
        return sp + _string(draw) + sp
    if kind == "literal":
        return sp + draw(st.sampled_from(["true", "false", "null"])) + sp
    if kind == "array":
        items = draw(st.lists(json_texts(depth + 1), max_size=4))
        return sp + "[" + ",".join(items) + "]" + sp
    keys = draw(st.lists(json_strings(), max_size=4))
    if keys and draw(st.integers(0, 5)) == 0:
        keys.append(keys[0])  # a duplicate key
    values = [draw(json_texts(depth + 1)) for _ in keys]
    pairs = [f"{k}{draw(SPACES)}:{v}" for k, v in zip(keys, values, strict=True)]
    return sp + "{" + ",".join(pairs) + "}" + sp


def decode(line: bytes) -> tuple[str, Any]:
    try:
        return "ok", framing._loads_line(line, 3)
    except RequestError as exc:
        return "error", (exc.code, exc.message, exc.request_id)


def same(a: Any, b: Any) -> bool:
    """Equal values of equal types; floats bit for bit; dict keys in the same order."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return a == b and math.copysign(1, a) == math.copysign(1, b) or (a != a and b != b)
    if isinstance(a, dict):
        return list(a) == list(b) and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return bool(a == b)


def both_ways(line: bytes, monkeypatch: pytest.MonkeyPatch) -> tuple[Any, Any]:
    with monkeypatch.context() as m:
        m.setattr(framing, "FAST_DECODE_BYTES", 0)
        fast = decode(line)
    with monkeypatch.context() as m:
        m.setattr(framing, "_orjson", None)
        slow = decode(line)
    return fast, slow


@settings(max_examples=1500, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(text=json_texts())
def test_fast_decode_equals_the_standard_library(
    text: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    line = text.encode("utf-8", "surrogatepass")
    fast, slow = both_ways(line, monkeypatch)
    assert fast[0] == slow[0], (line, fast, slow)
    if fast[0] == "error":
        assert fast == slow
    else:
        assert same(fast[1], slow[1]), (line, fast, slow)
    used = framing._fast_loads(line) is not framing._UNUSABLE
    event(f"{fast[0]}, {'orjson' if used else 'fallback'}")


def test_a_large_goal_is_decoded_by_orjson_and_equal() -> None:
    points = [
        {"time_from_start": (i + 1) * 0.001, "positions": [math.sin(i / 7 + j) for j in range(6)],
         "velocities": [math.cos(i / 7 + j) / 7 for j in range(6)]}
        for i in range(2000)
    ]
    line = encode({"id": 1, "op": "send_goal", "trajectory": {"joint_names": list("abcdef"),
                                                             "points": points}})[:-1]
    assert len(line) >= framing.FAST_DECODE_BYTES
    assert framing._fast_loads(line) is not framing._UNUSABLE  # the fast path is taken
    assert same(framing._loads_line(line, 1), json.loads(line))


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        (b'{"a":1,"b":{"c":2,"c":3}}', "duplicate key"),
        (b'{"id":123456789012345678901234567890}', "integer beyond 64 bits"),
        (b'{"k":"\\u003a","a":1,"a":2}', "escaped colon"),
    ],
)
def test_what_orjson_would_decode_differently_goes_to_the_standard_library(
    text: bytes, reason: str
) -> None:
    assert framing._fast_loads(text) is framing._UNUSABLE, reason
