"""Binary frames (protocol version 2) in the transport-free layer: exact byte vectors through
``framing.MessageDecoder`` and ``protocol.Decoder`` (docs/protocol.md, "Binary frames")."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from jtc_hw.api.framing import Attachment, MessageDecoder, RequestError, encode_frame
from jtc_hw.api.protocol import Decoder, column_names, parse_request, parse_trajectory
from jtc_hw.api.requests import SendGoal, SendTrajectory
from jtc_hw.controller.messages import PointColumns

ROOT = Path(__file__).resolve().parents[2]
NAMES = ["j1", "j2"]
GOAL = {"id": 2, "op": "send_goal", "trajectory": {"joint_names": NAMES}}
VALUES = np.array([[1.0, 0.5, -0.5], [2.0, 1.0, 0.0]])
COLUMNS = column_names(NAMES, ["positions"])


def frame(values: np.ndarray = VALUES, columns: list[str] = COLUMNS, **header: object) -> bytes:
    """A frame, its header fields replaced by ``header``'s."""
    data = encode_frame(GOAL, values, columns)
    line, raw = data.split(b"\n", 1)
    obj = json.loads(line)
    obj["attachment"].update(header)
    return json.dumps(obj).encode() + b"\n" + raw


def doc_example() -> bytes:
    """The worked example of docs/protocol.md, rebuilt from its text blocks."""
    text = (ROOT / "docs" / "protocol.md").read_text()
    section = text.split("\n## Binary frames\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```text\n(.*?)```", section, re.DOTALL)
    line = next(b for b in blocks if b.startswith('{"id":2')).strip()
    hexdump = next(b for b in blocks if b.startswith("00 "))
    raw = bytes.fromhex(" ".join(row[:23] for row in hexdump.splitlines()))
    return line.encode() + b"\n" + raw


def test_the_documented_example_is_what_the_decoder_reads_and_the_encoder_writes() -> None:
    data = doc_example()
    assert data == encode_frame(GOAL, VALUES, COLUMNS)
    assert data.endswith(struct.pack("<6d", 1.0, 0.5, -0.5, 2.0, 1.0, 0.0) + b"\n")
    (goal,) = Decoder().feed(data)
    assert isinstance(goal, SendGoal) and goal.id == 2
    points = goal.trajectory.points
    assert isinstance(points, PointColumns)
    assert points.times_ns.tolist() == [1_000_000_000, 2_000_000_000]
    assert [p.positions for p in points] == [(0.5, -0.5), (1.0, 0.0)]
    assert points.values("velocities") is None


def test_a_frame_split_anywhere_decodes_the_same_and_the_stream_goes_on() -> None:
    data = frame() + b'{"id": 3, "op": "hello"}\n'
    whole = Decoder().feed(data)
    assert [type(r).__name__ for r in whole] == ["SendGoal", "Hello"]
    for cut in range(1, len(data)):
        decoder = Decoder()
        assert decoder.feed(data[:cut]) + decoder.feed(data[cut:]) == whole, cut


def test_raw_bytes_holding_newlines_are_not_lines() -> None:
    values = np.frombuffer(b"\n" * 48, dtype="<f8").reshape(2, 3)  # tiny but finite numbers
    decoder = MessageDecoder()
    (message,) = decoder.feed(encode_frame(GOAL, values, COLUMNS))
    assert isinstance(message["attachment"], Attachment)
    assert message["attachment"].data == b"\n" * 48


def test_every_field_and_the_order_of_the_columns() -> None:
    fields = ["positions", "velocities", "accelerations", "effort"]
    values = np.arange(2 * 9, dtype=float).reshape(2, 9) / 10
    (goal,) = Decoder().feed(frame(values, column_names(NAMES, fields)))
    assert isinstance(goal, SendGoal)
    point = goal.trajectory.points[1]
    assert point.time_from_start_ns == 900_000_000
    assert (point.positions, point.velocities) == ((1.0, 1.1), (1.2, 1.3))
    assert (point.accelerations, point.effort) == ((1.4, 1.5), (1.6, 1.7))
    swapped = column_names(NAMES, ["velocities", "positions"])
    (error,) = Decoder().feed(frame(values[:, :5], swapped))
    assert isinstance(error, RequestError) and error.code == "bad_request"
    assert "columns[3]" in error.message and "'accelerations.<joint>'" in error.message


def test_send_trajectory_carries_one_too_and_other_ops_refuse_it() -> None:
    data = frame().replace(b'"send_goal"', b'"send_trajectory"')
    (request,) = Decoder().feed(data)
    assert isinstance(request, SendTrajectory) and len(request.trajectory.points) == 2
    (error,) = Decoder().feed(encode_frame({"id": 4, "op": "get_status"}, VALUES, COLUMNS))
    assert isinstance(error, RequestError) and "unknown field 'attachment'" in error.message


@pytest.mark.parametrize(
    ("header", "columns", "values", "says"),
    [
        ({"dtype": ">f8"}, COLUMNS, VALUES, 'attachment.dtype: a string (">f8") is not supported'),
        ({"dtype": "<f4"}, COLUMNS, VALUES, "the only dtype is \"<f8\""),
        ({"shape": [3, 3]}, COLUMNS, VALUES, "[3, 3] of <f8 is 72 bytes, the attachment has 48"),
        ({"shape": [2]}, COLUMNS, VALUES, "attachment.shape: expected [points, columns]"),
        ({"shape": [1, 6]}, COLUMNS, VALUES, "6 columns, but 'columns' names 3"),
        ({"extra": 1}, COLUMNS, VALUES, "unknown field 'extra'"),
        ({}, ["time_from_start", "positions.j2", "positions.j1"], VALUES,
         'columns[1]: expected "positions.j1" (joint_names[0] is "j1"), got "positions.j2"'),
        ({}, ["t", "positions.j1", "positions.j2"], VALUES, 'must be "time_from_start"'),
        ({}, ["time_from_start", "positions.j1", "velocities.j1"], VALUES,
         'columns[2]: expected "positions.j2"'),
        ({}, COLUMNS, np.array([[1.0, 0.5, -0.5], [2.0, np.nan, 0.0]]),
         'point 1, column "positions.j1": nan is not a finite number'),
        ({}, COLUMNS, np.array([[np.inf, 0.5, -0.5], [2.0, 1.0, 0.0]]),
         'point 0, column "time_from_start": inf is not a finite number'),
        ({}, COLUMNS, np.array([[1.0, 0.5, -0.5], [2.0, 1.0, -2e6]]),
         'point 1, column "positions.j2": -2000000.0 is out of range'),
        ({}, COLUMNS, np.array([[1e12, 0.5, -0.5], [2.0, 1.0, 0.0]]),
         "point 0, time_from_start: 1000000000000.0 s is out of range"),
    ],
)
def test_each_bad_header_or_number_is_one_bad_request_and_the_stream_goes_on(
    header: dict[str, object], columns: list[str], values: np.ndarray, says: str
) -> None:
    decoder = Decoder()
    error, hello = decoder.feed(frame(values, columns, **header) + b'{"op": "hello"}\n')
    assert isinstance(error, RequestError) and error.code == "bad_request", error
    assert says in error.message and error.request_id == 2
    assert not isinstance(hello, RequestError)


@pytest.mark.parametrize(
    ("data", "says"),
    [
        (frame(bytes=40), "40 bytes are not followed by"),  # announced 40: byte 41 is no \n
        (frame(bytes=56), "56 bytes are not followed by"),  # more: into the next line
        (frame(bytes="48"), "attachment.bytes must be an integer"),
        (frame(bytes=-1), "must not be negative"),
        (frame()[:-1] + b"x", "not followed by \\n (byte 0x78)"),
        (b'{"op": "send_goal", "attachment": 48\n', "names an attachment"),
        (b'{"op": "send_goal", "attachment": [48]}\n', "'attachment' must be an object"),
    ],
)
def test_a_frame_that_cannot_be_trusted_is_bad_frame_and_nothing_after_it_is_read(
    data: bytes, says: str
) -> None:
    decoder = Decoder()
    items = decoder.feed(data + b'{"op": "hello"}\n' + b"\0" * 16 + b'{"op": "stop"}\n')
    assert [getattr(i, "code", None) for i in items] == ["bad_frame"], items
    assert says in items[0].message
    assert "out of sync" in items[0].message
    assert decoder.feed(b'{"op": "stop"}\n') == [] and decoder.end() == []


def test_a_stream_that_ends_inside_the_raw_bytes_is_bad_frame() -> None:
    decoder = Decoder()
    assert decoder.feed(frame()[:-10]) == []
    (error,) = decoder.end()
    assert isinstance(error, RequestError) and error.code == "bad_frame"
    assert "ended after 39 of the attachment's 48 bytes" in error.message
    assert error.request_id == 2


def test_an_oversized_attachment_is_too_large_and_skipped_wherever_it_is_cut() -> None:
    values = np.zeros((100, 3))
    data = encode_frame(GOAL, values, COLUMNS) + b'{"id": 9, "op": "hello"}\n'
    for cut in (0, 200, 1000, len(data) - 30):
        decoder = Decoder(max_message_bytes=1024)
        items = decoder.feed(data[:cut]) + decoder.feed(data[cut:])
        assert [getattr(i, "code", type(i).__name__) for i in items] == ["too_large", "Hello"]
        assert "attachment of 2400 bytes" in items[0].message and items[0].request_id == 2


def test_points_and_an_attachment_together_are_refused() -> None:
    line, raw = frame().split(b"\n", 1)
    obj = json.loads(line)
    obj["trajectory"]["points"] = []
    (error,) = Decoder().feed(json.dumps(obj).encode() + b"\n" + raw)
    assert isinstance(error, RequestError) and "leave 'points' out" in error.message


def test_a_json_attachment_without_raw_bytes_is_refused_by_the_parser() -> None:
    header = {"bytes": 0, "dtype": "<f8", "shape": [0, 1], "columns": ["time_from_start"]}
    with pytest.raises(RequestError, match="only valid on a binary frame"):
        parse_request({**GOAL, "attachment": header})  # e.g. a Zenoh body with no payload
    trajectory = parse_trajectory({"joint_names": NAMES}, attachment=Attachment(b"", header))
    assert len(trajectory.points) == 0  # no points: as "points": []


def test_a_header_with_a_lone_surrogate_is_refused_and_its_bytes_skipped() -> None:
    data = frame(columns=["time_from_start", "positions.j1", "positions.\\ud800"])
    data = data.replace(b"\\\\ud800", b"\\ud800")  # the JSON escape itself, not its text
    assert b'"positions.\\ud800"' in data
    error, hello = Decoder().feed(data + b'{"op": "hello"}\n')
    assert isinstance(error, RequestError) and error.code == "bad_request", error
    assert "lone UTF-16 surrogate" in error.message and error.request_id == 2
    assert not isinstance(hello, RequestError)
    # Not a frame at all, the word only in a string: refused as before, never executed.
    (plain,) = Decoder().feed(b'{"op": "sim", "component": "attachment", "fault": "\\udc00"}\n')
    assert isinstance(plain, RequestError) and "lone UTF-16 surrogate" in plain.message


@pytest.mark.parametrize("seed", range(20))
def test_a_frame_decodes_to_the_trajectory_its_json_form_does(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 300))
    fields = [f for f in ("positions", "velocities", "accelerations", "effort")
              if rng.random() < 0.6] or ["positions"]
    times = np.cumsum(rng.uniform(1e-4, 0.5, m))
    blocks = [rng.uniform(-1e6, 1e6, (m, len(NAMES))) for _ in fields]
    values = np.column_stack([times, *blocks])
    request = {"id": seed, "op": "send_trajectory",
               "trajectory": {"joint_names": NAMES, "start_in": 0.25}}
    (binary,) = Decoder().feed(encode_frame(request, values, column_names(NAMES, fields)))
    points = [{"time_from_start": float(t),
               **{f: block[i].tolist() for f, block in zip(fields, blocks, strict=True)}}
              for i, t in enumerate(times)]
    as_json = dict(request, trajectory={**request["trajectory"], "points": points})
    (text,) = Decoder().feed(json.dumps(as_json).encode() + b"\n")
    assert isinstance(binary, SendTrajectory) and binary == text


def test_a_decoder_without_frames_reads_an_attachment_field_as_any_other() -> None:
    """The client's decoder of the daemon's messages: the daemon sends no frames."""
    message = b'{"event": "x", "attachment": {"bytes": 5}}\n{"id": 1, "ok": true}\n'
    assert MessageDecoder(frames=False).feed(message) == [
        {"event": "x", "attachment": {"bytes": 5}}, {"id": 1, "ok": True}]
    (error,) = MessageDecoder(frames=False).feed(b'{"attachment": \n')
    assert isinstance(error, RequestError) and error.code == "bad_json"


def test_decode_cost_counts_json_and_a_frame_s_raw_bytes_at_their_price() -> None:
    """What the server decides the worker thread by: the JSON text a feed decodes, a frame's
    raw bytes at 1/RAW_BYTES_PER_JSON_BYTE; however the stream is cut, never less than the
    JSON the feed completes."""
    from jtc_hw.api.framing import RAW_BYTES_PER_JSON_BYTE

    values = np.arange(3 * 20_000, dtype=np.float64).reshape(20_000, 3)
    big = frame(values)  # 480 kB of raw bytes, some of them newlines
    line_bytes = big.index(b"\n")
    raw = len(big) - line_bytes - 1
    json_line = json.dumps({"id": 3, "op": "get_status", "pad": "x" * 100_000}).encode() + b"\n"
    decoder = MessageDecoder()
    whole = decoder.decode_cost(big)
    assert whole == line_bytes + raw // RAW_BYTES_PER_JSON_BYTE
    assert whole < 64 * 1024 < decoder.decode_cost(json_line)
    # Cut anywhere: each piece costs what it completes; the frame never counts as JSON.
    for cut in (1, line_bytes, line_bytes + 1, line_bytes + 100, len(big) - 1):
        decoder = MessageDecoder()
        first, rest = big[:cut], big[cut:] + json_line
        costs = [decoder.decode_cost(first)]
        decoder.feed(first)
        costs.append(decoder.decode_cost(rest))
        items = decoder.feed(rest)
        assert [type(i) for i in items] == [dict, dict], (cut, items)
        assert sum(costs) <= whole + len(json_line), (cut, costs)
        assert costs[1] >= len(json_line) - 1, (cut, costs)
    # A header it cannot read (not JSON) counts everything after it: the worker decides.
    bad = b'{"attachment": \n' + b"x" * 100_000
    assert MessageDecoder().decode_cost(bad) >= 100_000
