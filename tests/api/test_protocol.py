"""The wire format: byte-level decoder and parser vectors, encoder guarantees (no I/O)."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jtc_hw import ErrorCode, GoalFeedback, GoalResult, GoalStatus, JointTolerance, TrajectorySample
from jtc_hw.api.events import feedback_event, result_event, tolerances_to_json, trajectory_to_json
from jtc_hw.api.framing import (
    BAD_JSON,
    BAD_REQUEST,
    ERROR_CODES,
    TOO_LARGE,
    UNKNOWN_OP,
    MessageDecoder,
    RequestError,
    encode,
    error_reply,
    reply,
)
from jtc_hw.api.protocol import OPS, Decoder, parse_request, parse_trajectory
from jtc_hw.api.requests import (
    Auth,
    CancelGoal,
    GetConfig,
    GetStatus,
    Hello,
    QueryState,
    Rearm,
    SendGoal,
    SendTrajectory,
    Sim,
    Stop,
    SubscribeState,
    UnsubscribeState,
)
from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.errors import ProtocolError

S = 1_000_000_000


def line(obj: Any) -> bytes:
    return json.dumps(obj).encode() + b"\n"


def one(data: bytes, max_bytes: int = 1 << 20) -> Any:
    items = Decoder(max_bytes).feed(data)
    assert len(items) == 1, items
    return items[0]


def error(data: bytes, code: str, *fragments: str, max_bytes: int = 1 << 20) -> RequestError:
    item = one(data, max_bytes)
    assert isinstance(item, RequestError), item
    assert item.code == code, item
    for fragment in fragments:
        assert fragment in item.message, (fragment, item.message)
    return item


def goal(**trajectory: Any) -> dict[str, Any]:
    traj = {
        "joint_names": ["j1", "j2"],
        "points": [{"time_from_start": 1.0, "positions": [0.1, 0.2]}],
    }
    traj.update(trajectory)
    return {"id": 7, "op": "send_goal", "trajectory": traj}


# -- framing ------------------------------------------------------------------------------------


def test_one_request_per_line() -> None:
    assert one(b'{"op": "hello", "id": 1}\n') == Hello(id=1)


def test_split_reads_byte_by_byte() -> None:
    decoder = Decoder()
    stream = b'{"id": "a", "op": "get_status"}\n{"op": "get_config", "id": 2}\n'
    out: list[Any] = []
    first_done_at = None
    for i in range(len(stream)):
        out += decoder.feed(stream[i : i + 1])
        if out and first_done_at is None:
            first_done_at = i
    assert out == [GetStatus(id="a"), GetConfig(id=2)]
    assert first_done_at == stream.index(b"\n")  # completed exactly at its newline


def test_coalesced_reads() -> None:
    data = b'{"op":"hello"}\n{"op":"subscribe_state","id":3}\n{"op":"unsubscribe_state"}\n{"op'
    decoder = Decoder()
    assert decoder.feed(data) == [Hello(), SubscribeState(id=3), UnsubscribeState()]
    assert decoder.feed(b'": "hello", "id": 4}\n') == [Hello(id=4)]


def test_crlf_and_blank_lines() -> None:
    assert Decoder().feed(b'\n  \r\n{"op":"hello"}\r\n\n') == [Hello()]


def test_last_line_without_newline_at_end_of_input_is_never_parsed() -> None:
    decoder = Decoder()
    assert decoder.feed(b'{"op": "hello", "id": 1}\n{"op": "hello", "id": 9}') == [Hello(id=1)]
    (refused,) = decoder.end()
    assert isinstance(refused, RequestError) and refused.code == BAD_JSON
    assert refused.request_id is None  # not even the id is read from a cut-off message
    assert refused.message == (
        "line 2: the connection ended before this message's newline; it was not executed "
        "(end every message with \\n)"
    )
    assert decoder.end() == []
    blank = Decoder()
    assert blank.feed(b'{"op": "hello"}\n \r') == [Hello()]
    assert blank.end() == []  # only blanks after the last newline: nothing was cut off
    long = Decoder(10)
    assert [i.code for i in long.feed(b"x" * 20) if isinstance(i, RequestError)] == [TOO_LARGE]
    assert long.end() == []  # the over-long line was reported already


def test_oversize_line_then_valid_line_same_chunk() -> None:
    big = b'{"op": "hello", "pad": "' + b"x" * 200 + b'"}\n'
    items = Decoder(100).feed(big + b'{"op": "hello", "id": 2}\n')
    assert len(items) == 2
    assert isinstance(items[0], RequestError) and items[0].code == TOO_LARGE
    assert "line 1" in items[0].message and "100 bytes" in items[0].message
    assert items[1] == Hello(id=2)


def test_oversize_reported_once_as_soon_as_limit_passes_and_discarded_across_reads() -> None:
    decoder = Decoder(64)
    first = decoder.feed(b"[" + b"1," * 40)  # 81 bytes, no newline yet
    assert len(first) == 1 and isinstance(first[0], RequestError)
    assert first[0].code == TOO_LARGE and first[0].request_id is None
    assert decoder.feed(b"2," * 1000) == []  # still the same message: silently discarded
    assert decoder.feed(b'3]\n{"op": "hello", "id": 5}\n{"op": "hel') == [Hello(id=5)]
    assert decoder.feed(b'lo"}\n') == [Hello()]
    bad = decoder.feed(b"{]\n")
    assert isinstance(bad[0], RequestError) and "line 4" in bad[0].message


def test_line_of_exactly_the_limit_is_accepted() -> None:
    body = b'{"op":"hello","id":"' + b"a" * 20 + b'"}'
    assert isinstance(one(body + b"\n", len(body)), Hello)
    error(body + b"\n", TOO_LARGE, max_bytes=len(body) - 1)
    with pytest.raises(ValueError):
        Decoder(0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(min_value=1, max_value=40), min_size=1, max_size=30))
def test_any_chunking_gives_the_same_items(cuts: list[int]) -> None:
    stream = (
        b'{"op":"hello","id":1}\n'
        + b'{"op":"x'
        + b"y" * 200
        + b'"}\n'
        + b"{oops}\n"
        + line(goal())
        + b'{"op": "query_state", "in": 0.5}\n'
    )
    whole = Decoder(150).feed(stream)
    decoder, pos, parts = Decoder(150), 0, []
    for cut in cuts:
        parts += decoder.feed(stream[pos : pos + cut])
        pos += cut
    parts += decoder.feed(stream[pos:])

    def key(item: Any) -> Any:
        return (item.code, item.message) if isinstance(item, RequestError) else item

    assert [key(i) for i in parts] == [key(i) for i in whole]
    assert [getattr(i, "code", None) for i in whole] == [None, TOO_LARGE, BAD_JSON, None, None]


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=300))
def test_garbage_never_raises(data: bytes) -> None:
    decoder = Decoder(128)
    for item in decoder.feed(data) + decoder.feed(b"\n") + decoder.end():
        if isinstance(item, RequestError):
            assert item.code in ERROR_CODES and item.message


# -- JSON-level errors --------------------------------------------------------------------------


def test_malformed_json_names_line_and_column() -> None:
    decoder = Decoder()
    items = decoder.feed(b'{"op": "hello"}\n{"op" "hello"}\n')
    assert items[0] == Hello()
    assert isinstance(items[1], RequestError) and items[1].code == BAD_JSON
    assert items[1].message.startswith("line 2, column 7: malformed JSON")


@pytest.mark.parametrize("token", [b"NaN", b"Infinity", b"-Infinity"])
def test_nan_and_infinity_tokens_refused(token: bytes) -> None:
    data = (
        b'{"op": "send_goal", "trajectory": {"joint_names": ["j1"], "points": ['
        b'{"time_from_start": 1, "positions": [' + token + b"]}]}}\n"
    )
    error(data, BAD_JSON, token.decode().lstrip("-"), "not JSON")


def test_number_overflowing_float64_refused_with_its_path() -> None:
    data = line(goal()).replace(b"0.2", b"1e400")
    err = error(data, BAD_REQUEST, "trajectory.points[0].positions[1]", "float64")
    assert err.request_id == 7


def test_invalid_utf8() -> None:
    error(b'{"op": "hello", "id": "\xff"}\n', BAD_JSON, "UTF-8", "byte 24")


def test_duplicate_keys_refused() -> None:
    error(b'{"op": "hello", "op": "get_status"}\n', BAD_JSON, "duplicate key 'op'")


def test_deep_nesting_refused() -> None:
    error(b"[" * 100_000 + b"]" * 100_000 + b"\n", BAD_JSON, "nested too deeply")


def test_huge_integer_literal_refused() -> None:
    error(b'{"op": "cancel_goal", "goal_id": ' + b"9" * 5000 + b"}\n", BAD_JSON, "line 1")


@pytest.mark.parametrize(
    ("data", "what"),
    [
        (b"[1, 2]\n", "an array"),
        (b'"hello"\n', "a string"),
        (b"3\n", "a number"),
        (b"null\n", "null"),
    ],
)
def test_non_object_json(data: bytes, what: str) -> None:
    error(data, BAD_REQUEST, "must be a JSON object", what)


# -- request-level errors -----------------------------------------------------------------------


def test_unknown_op_suggests_and_lists() -> None:
    err = error(b'{"op": "send_gaol", "id": 3}\n', UNKNOWN_OP, "did you mean 'send_goal'?")
    assert err.request_id == 3
    for op in OPS:
        assert op in err.message
    no_guess = error(b'{"op": "zzz"}\n', UNKNOWN_OP)
    assert "did you mean" not in no_guess.message


def test_missing_or_mistyped_op() -> None:
    error(b'{"id": 1}\n', BAD_REQUEST, "missing required field 'op'", "hello")
    error(b'{"op": 5}\n', BAD_REQUEST, "op: expected a string, got a number (5)")


def test_id_is_echoed_or_refused() -> None:
    assert error(line({"id": "abc", "op": "cancel_goal"}), BAD_REQUEST).request_id == "abc"
    err = error(line({"id": [1], "op": "hello"}), BAD_REQUEST, "id: expected an integer or")
    assert err.request_id is None
    assert error(line({"id": True, "op": "hello"}), BAD_REQUEST).request_id is None


def test_missing_fields() -> None:
    error(line({"op": "send_goal"}), BAD_REQUEST, "send_goal: missing required field 'trajectory'")
    error(line({"op": "cancel_goal"}), BAD_REQUEST, "missing required field 'goal_id'")
    error(line({"op": "sim", "component": "m"}), BAD_REQUEST, "missing required field 'freeze'")
    error(line({"op": "sim", "component": "m", "fault": " "}), BAD_REQUEST, "fault: must not be")
    error(line({"op": "sim", "component": "m", "fault": 3}), BAD_REQUEST, "expected a string")
    error(line({"op": "rearm", "now": True}), BAD_REQUEST, "unknown field 'now'")
    error(line({"op": "auth"}), BAD_REQUEST, "missing required field 'token'")
    msg = goal(points=[{"positions": [1, 2]}])
    error(line(msg), BAD_REQUEST, "trajectory.points[0]: missing required field 'time_from_start'")
    error(
        line(goal(joint_names=None) | {"trajectory": {"points": []}}),
        BAD_REQUEST,
        "trajectory: missing required field 'joint_names'",
    )


def test_wrong_type_names_the_deep_path() -> None:
    points = [{"time_from_start": i, "positions": [0, 0]} for i in range(4)]
    points[3]["positions"] = [0.0, "a"]
    error(
        line(goal(points=points)),
        BAD_REQUEST,
        'trajectory.points[3].positions[1]: expected a number, got a string ("a")',
    )
    error(
        line(goal(points=[{"time_from_start": True}])),
        BAD_REQUEST,
        "trajectory.points[0].time_from_start: expected a number, got a boolean (true)",
    )
    error(
        line(goal(joint_names=["j1", 2])),
        BAD_REQUEST,
        "trajectory.joint_names[1]: expected a string",
    )
    error(line(goal(points={"a": 1})), BAD_REQUEST, "trajectory.points: expected an array")
    error(
        line(goal(points=[{"time_from_start": 1, "velocities": 3}])),
        BAD_REQUEST,
        "trajectory.points[0].velocities: expected an array of numbers",
    )
    msg = goal() | {"path_tolerance": [{"name": "j1", "position": "x"}]}
    error(line(msg), BAD_REQUEST, "path_tolerance[0].position: expected a number")
    msg = goal() | {"goal_tolerance": {"name": "j1"}}
    error(line(msg), BAD_REQUEST, "goal_tolerance: expected an array of")
    error(
        line({"op": "sim", "component": "m", "freeze": 1}),
        BAD_REQUEST,
        "freeze: expected true or false",
    )
    error(
        line({"op": "cancel_goal", "goal_id": 1.0}),
        BAD_REQUEST,
        "goal_id: expected an integer",
        "without a fraction",
    )


def test_unknown_fields_refused_with_suggestion() -> None:
    msg = goal(points=[{"time_from_start": 1, "positon": [1, 2]}])
    error(
        line(msg),
        BAD_REQUEST,
        "trajectory.points[0]: unknown field 'positon'",
        "did you mean 'positions'?",
    )
    error(line({"op": "hello", "verbose": True}), BAD_REQUEST, "hello: unknown field 'verbose'")
    error(line(goal(start_at=5)), BAD_REQUEST, "trajectory: unknown field 'start_at'")


def test_start_fields() -> None:
    error(
        line(goal(start_time_ns=1.5e9)),
        BAD_REQUEST,
        "trajectory.start_time_ns: expected an integer",
    )
    error(line(goal(start_time_ns=-1)), BAD_REQUEST, "trajectory.start_time_ns: -1 is out of range")
    error(line(goal(start_time_ns=5, start_in=1.0)), BAD_REQUEST, "mutually exclusive")
    error(line(goal(start_in=1e300)), BAD_REQUEST, "trajectory.start_in", "out of range")


def test_times_must_fit_int64_nanoseconds() -> None:
    """2**63 - 1 ns is the end of the daemon clock; nothing may be due after it."""
    end = 2**63 - 1
    refused = error(
        line(goal(start_time_ns=end)),
        BAD_REQUEST,
        "trajectory.points[0].time_from_start: the point would be due at "
        f"{end + S} ns (start {end} ns + {S} ns), after the end of the daemon clock's range",
    )
    assert refused.request_id == 7
    last = {"time_from_start": 2.0, "positions": [0.0, 0.0]}
    error(
        line(goal(start_time_ns=end - S, points=[last, {"time_from_start": 0.5}])),
        BAD_REQUEST,
        "trajectory.points[0].time_from_start",  # the latest point, wherever it is
    )
    fits = one(line(goal(start_time_ns=end - S)))
    assert fits.trajectory.to_joint_trajectory(now_ns=5).start_time_ns == end - S
    error(
        line(goal(points=[{"time_from_start": 9223372036.854776}])),
        BAD_REQUEST,
        "trajectory.points[0].time_from_start: 9223372036.854776 s is 9223372036854775808 ns, "
        "beyond the protocol's int64 nanoseconds",
    )
    # Relative to now: start 0 ("now") and start_in are resolved against the daemon clock.
    near_end = one(line(goal(points=[{"time_from_start": 9223372030.0}])))
    assert near_end.trajectory.to_joint_trajectory(now_ns=S).points[0]
    with pytest.raises(RequestError, match=r"points\[0\].time_from_start: the point would be"):
        near_end.trajectory.to_joint_trajectory(now_ns=10**10)
    later = one(line(goal(start_in=9223372000.0)))
    with pytest.raises(RequestError, match="after the end of the daemon clock's range"):
        later.trajectory.to_joint_trajectory(now_ns=36 * S)  # starts in range, ends out
    error(
        line(goal() | {"goal_time_tolerance": 1e300}),
        BAD_REQUEST,
        "goal_time_tolerance: 1e+300 s is out of range",
    )


@pytest.mark.parametrize("field", ["positions", "velocities", "accelerations", "effort"])
def test_absurd_joint_values_are_refused_naming_point_and_joint(field: str) -> None:
    points = [
        {"time_from_start": 1.0, "positions": [0.0, 0.0]},
        {"time_from_start": 2.0, "positions": [0.0, 0.0], field: [1e6, -1e308]},
    ]
    error(
        line(goal(points=points)),
        BAD_REQUEST,
        f"trajectory.points[1].{field}[1] (joint 'j2'): -1e+308 is out of range; a joint value "
        "must be at most 1e+06 in magnitude",
    )
    points[1][field] = [1e6, -1e6]  # the bound itself is accepted
    assert isinstance(one(line(goal(points=points))), SendGoal)
    points[1][field] = [1e6, 0.0, 2e6]  # more values than joints: named by index only
    error(line(goal(points=points)), BAD_REQUEST, f"points[1].{field}[2]: 2000000.0 is out")


@pytest.mark.parametrize(
    ("text", "path"),
    [
        (b'{"id": 4, "op": "hello", "x": "\\ud800"}', "x"),  # an unknown field, still refused
        (b'{"id": 4, "op": "send_goal", "trajectory": {"joint_names": ["j1", "j\\udc00"], '
         b'"points": []}}', "trajectory.joint_names[1]"),
        (b'{"id": 4, "op": "sim", "component": "mirror", "fault": "x\\ud800y"}', "fault"),
        (b'{"id": 4, "op": "hello", "\\udfff": 1}', "the key"),
        (b'{"id": 4, "op": "send_goal", "trajectory": {"\\ud800": 1}}', "trajectory: the key"),
        (b'{"id": 4, "op": "\\ud800"}', "op"),
    ],
)
def test_lone_surrogates_are_refused_with_an_encodable_reply(text: bytes, path: str) -> None:
    refused = error(text + b"\n", BAD_REQUEST, f"line 1: {path} ", "lone UTF-16 surrogate",
                    "not executed")
    assert refused.request_id == 4
    data = encode(refused.reply())  # the reply can be sent: the text is quoted escaped
    assert data.isascii() and json.loads(data)["error"]["code"] == BAD_REQUEST


def test_a_lone_surrogate_in_the_id_gives_a_reply_without_id() -> None:
    refused = error(b'{"id": "a\\ud800", "op": "hello"}\n', BAD_REQUEST, 'id "a\\ud800"')
    assert refused.request_id is None
    assert json.loads(encode(refused.reply()))["id"] is None


def test_surrogate_pairs_are_characters() -> None:
    assert one(b'{"id": "\\ud83d\\ude00", "op": "hello"}\n') == Hello(id="\U0001f600")
    escaped_backslash = one(b'{"id": "\\\\ud800", "op": "hello"}\n')  # the text \ud800
    assert escaped_backslash == Hello(id="\\ud800")


def test_query_state_needs_exactly_one_time() -> None:
    error(line({"op": "query_state"}), BAD_REQUEST, "exactly one of 'time_ns'")
    error(line({"op": "query_state", "in": 1, "time_ns": 5}), BAD_REQUEST, "both were given")
    assert one(line({"op": "query_state", "time_ns": 5})) == QueryState(time_ns=5)
    q = one(line({"op": "query_state", "in": 0.25}))
    assert q == QueryState(in_s=0.25) and q.resolve(10 * S) == 10 * S + S // 4
    with pytest.raises(RequestError, match="outside the daemon clock"):
        QueryState(in_s=-20.0).resolve(10 * S)


# -- parsed requests ----------------------------------------------------------------------------


def test_send_goal_parses_into_controller_types() -> None:
    msg = goal(
        points=[
            {"time_from_start": 0.5, "positions": [1, 2], "velocities": [0, 0]},
            {
                "time_from_start": 1.25,
                "positions": [3, 4],
                "accelerations": [0.1, 0.2],
                "effort": [1, 1],
            },
        ],
    ) | {
        "path_tolerance": [{"name": "j1", "position": 0.1}],
        "goal_tolerance": [{"name": "j2", "velocity": -1, "acceleration": 2}],
        "goal_time_tolerance": 0.5,
    }
    req = one(line(msg))
    assert isinstance(req, SendGoal) and req.id == 7
    assert req.path_tolerance == (JointTolerance("j1", 0.1, 0.0, 0.0),)
    assert req.goal_tolerance == (JointTolerance("j2", 0.0, -1.0, 2.0),)
    assert req.goal_time_tolerance == 0.5
    traj = req.trajectory.to_joint_trajectory(now_ns=123)
    assert traj.start_time_ns == 0  # no start given: "when the controller receives it"
    assert traj.joint_names == ("j1", "j2")
    assert traj.points[0] == TrajectoryPoint(0.5, [1.0, 2.0], [0.0, 0.0])
    assert traj.points[1].time_from_start_ns == 1_250_000_000
    assert traj.points[1].accelerations == (0.1, 0.2) and traj.points[1].velocities is None


def test_start_time_resolution() -> None:
    absolute = one(line(goal(start_time_ns=42 * S)))
    assert absolute.trajectory.to_joint_trajectory(now_ns=S).start_time_ns == 42 * S
    relative = one(line(goal(start_in=0.5)))
    assert relative.trajectory.start_in == 0.5
    assert relative.trajectory.to_joint_trajectory(now_ns=10 * S).start_time_ns == 10 * S + S // 2
    with pytest.raises(RequestError, match="outside the daemon clock"):
        one(line(goal(start_in=-100.0))).trajectory.to_joint_trajectory(now_ns=S)


@pytest.mark.parametrize(
    ("obj", "expected"),
    [
        ({"op": "hello", "protocol_version": 1}, Hello(protocol_version=1)),
        ({"op": "auth", "token": "s3cret"}, Auth(token="s3cret")),
        ({"op": "cancel_goal", "goal_id": 4}, CancelGoal(goal_id=4)),
        ({"op": "subscribe_state"}, SubscribeState()),
        ({"op": "unsubscribe_state"}, UnsubscribeState()),
        ({"op": "get_config"}, GetConfig()),
        ({"op": "get_status"}, GetStatus()),
        ({"op": "sim", "component": "arm", "freeze": True}, Sim(component="arm", freeze=True)),
        (
            {"op": "sim", "component": "arm", "fault": "servo 3 silent"},
            Sim(component="arm", freeze=None, fault="servo 3 silent"),
        ),
        (
            {"op": "sim", "component": "arm", "freeze": False, "fault": "x"},
            Sim(component="arm", freeze=False, fault="x"),
        ),
        ({"op": "rearm"}, Rearm()),
        ({"op": "stop", "id": 3}, Stop(id=3)),
    ],
)
def test_every_simple_op(obj: dict[str, Any], expected: Any) -> None:
    assert parse_request(obj) == expected


def test_send_trajectory_may_be_empty() -> None:
    req = one(line({"op": "send_trajectory", "trajectory": {"joint_names": [], "points": []}}))
    assert isinstance(req, SendTrajectory) and req.trajectory.points == ()


def test_auth_repr_hides_the_token() -> None:
    assert "s3cret" not in repr(Auth(token="s3cret"))


def test_parse_request_raises_and_errors_are_protocol_errors() -> None:
    with pytest.raises(RequestError) as info:
        parse_request({"op": "nope", "id": 1})
    assert isinstance(info.value, ProtocolError) and info.value.reply() == error_reply(
        1, UNKNOWN_OP, info.value.message
    )


def test_message_decoder_returns_objects() -> None:
    decoder = MessageDecoder()
    items = decoder.feed(b'{"event": "state", "x": [1, null]}\n[1]\n')
    assert items[0] == {"event": "state", "x": [1, None]}
    assert isinstance(items[1], RequestError) and items[1].code == BAD_REQUEST


# -- encoding -----------------------------------------------------------------------------------


def test_encode_never_emits_non_finite_numbers() -> None:
    data = encode(
        {
            "a": math.nan,
            "b": [math.inf, -math.inf, 1.5],
            "c": np.array([np.nan, 2.0]),
            "d": np.float64("inf"),
            "e": np.array([[1.0, np.nan]]),
            "f": (np.int64(3), np.bool_(True)),
        }
    )
    assert data.endswith(b"}\n") and data.count(b"\n") == 1
    for token in (b"NaN", b"Infinity"):
        assert token not in data
    assert json.loads(data) == {
        "a": None,
        "b": [None, None, 1.5],
        "c": [None, 2.0],
        "d": None,
        "e": [[1.0, None]],
        "f": [3, True],
    }


def test_encode_writes_a_lone_surrogate_as_the_replacement_character() -> None:
    assert encode({"m": "motor \ud800 silent", "ok": "\U0001f600"}) == (
        '{"m":"motor \ufffd silent","ok":"\U0001f600"}\n'.encode()
    )


def test_encode_enums_unicode_and_refuses_unknown_types() -> None:
    assert encode({"s": GoalStatus.ABORTED, "c": ErrorCode.INVALID_JOINTS, "t": "é\n"}) == (
        '{"s":"aborted","c":-2,"t":"é\\n"}\n'.encode()
    )
    with pytest.raises(TypeError, match="cannot encode a object"):
        encode({"x": object()})


def test_replies_and_events() -> None:
    assert reply(3, goal_id=4) == {"id": 3, "ok": True, "goal_id": 4}
    assert error_reply("a", "goal_rejected", "why", -2) == {
        "id": "a",
        "ok": False,
        "error": {"code": "goal_rejected", "message": "why", "error_code": -2},
    }
    assert "error_code" not in error_reply(None, "busy", "full")["error"]
    result = GoalResult(5, GoalStatus.SUCCEEDED, ErrorCode.SUCCESSFUL, "done", 77)
    assert json.loads(encode(result_event(result))) == {
        "event": "result",
        "goal_id": 5,
        "status": "succeeded",
        "error_code": 0,
        "error_string": "done",
        "details": "",
        "time_ns": 77,
    }
    z = np.zeros(2)
    fb = GoalFeedback(5, 80, 0.5, TrajectorySample(z + 1, z, z, z), z, None, np.zeros((3, 2)))
    event = json.loads(encode(feedback_event(fb, ("j1", "j2"))))
    assert event["desired"]["positions"] == [1.0, 1.0]
    assert event["actual"] == {"positions": [0.0, 0.0], "velocities": None}
    assert set(event["error"]) == {"positions", "velocities", "accelerations"}
    assert event["joint_names"] == ["j1", "j2"] and event["time_from_start"] == 0.5


def test_trajectory_round_trip_through_the_wire_form() -> None:
    traj = JointTrajectory(
        ["a", "b"],
        [TrajectoryPoint(0.1, [1, 2], [0, 0]), TrajectoryPoint(2.000000001, [3, 4])],
        start_time_ns=5 * S,
    )
    wire = json.loads(encode(trajectory_to_json(traj)))
    back = parse_trajectory(wire).to_joint_trajectory(now_ns=0)
    assert back == traj
    assert trajectory_to_json(JointTrajectory(["a"], []), start_in=1.0)["start_in"] == 1.0
    with pytest.raises(ValueError):
        trajectory_to_json(traj, start_in=1.0)
    assert tolerances_to_json([JointTolerance("a", 0.1)]) == [
        {"name": "a", "position": 0.1, "velocity": 0.0, "acceleration": 0.0}
    ]


def test_error_codes_are_the_documented_set() -> None:
    assert set(ERROR_CODES) == {
        "bad_json",
        "bad_frame",  # protocol version 2: a binary frame that cannot be trusted
        "too_large",
        "bad_request",
        "unknown_op",
        "goal_rejected",
        "not_active",
        "not_found",
        "busy",
        "unauthorized",
        "idle",
        "hardware",
        "internal",
    }
