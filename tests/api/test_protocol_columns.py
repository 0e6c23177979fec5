"""Points parsed as arrays (``PointColumns``) give what the point-by-point parser gives.

``parse_trajectory`` reads a regular, well-formed ``points`` array as whole columns and walks
the points one by one otherwise; random point lists -- well-formed, irregular, or broken in a
way a client can break them -- must parse to an equal trajectory or fail with the same error.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from jtc_hw.api import protocol
from jtc_hw.api.framing import MessageDecoder, RequestError
from jtc_hw.controller.messages import PointColumns

FIELDS = ("positions", "velocities", "accelerations", "effort")

number = st.one_of(
    st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False),
    st.integers(-5, 5),
)


@st.composite
def point_lists(draw: st.DrawFn) -> list[Any]:
    k = draw(st.integers(1, 4))
    m = draw(st.integers(1, 8))
    fields = draw(st.sets(st.sampled_from(FIELDS), min_size=1))
    points: list[Any] = []
    for _ in range(m):
        point: dict[str, Any] = {"time_from_start": draw(st.one_of(
            st.floats(0, 100, allow_nan=False), st.integers(0, 100)
        ))}
        for name in fields:
            if draw(st.integers(0, 5)):  # mostly present
                point[name] = draw(st.lists(number, min_size=k, max_size=k))
        points.append(point)
    for _ in range(draw(st.integers(0, 2))):  # mistakes and irregularities
        i = draw(st.integers(0, m - 1))
        how = draw(st.sampled_from(
            ["length", "value", "null", "unknown", "time", "no_time", "not_object", "empty"]
        ))
        name = draw(st.sampled_from(FIELDS))
        if how == "not_object":
            points[i] = draw(st.sampled_from([None, 1, [1.0], "p"]))
            continue
        point = points[i] if isinstance(points[i], dict) else {}
        if how == "length":
            point[name] = [0.5] * draw(st.integers(0, 6))
        elif how == "value":
            row = list(point.get(name) or [0.0])
            row[0] = draw(st.sampled_from(
                [True, None, "1", 10**400, 1e308 * 10, [1.0], 2e6, -1.5e6, 1e6, -(10**6)]
            ))
            point[name] = row
        elif how == "null":
            point[name] = None
        elif how == "unknown":
            point[draw(st.sampled_from(["velocity", "time", "extra"]))] = [1.0]
        elif how == "time":
            point["time_from_start"] = draw(st.sampled_from(
                [True, "1.0", None, 1e300, -1e10, 9223372036.854775, 2**70, -0.0,
                 -9223372036.854775, 9223372036, 9223372037, 9223372036.8547759]
            ))
        elif how == "no_time":
            point.pop("time_from_start", None)
        else:
            point[name] = []
    return points


def parse(points: list[Any], start_time_ns: int | None = None) -> Any:
    obj: dict[str, Any] = {"joint_names": ["a", "b"], "points": points}
    if start_time_ns is not None:
        obj["start_time_ns"] = start_time_ns
    try:
        return ("ok", protocol.parse_trajectory(obj, "trajectory", 7))
    except RequestError as exc:
        return ("error", exc.code, exc.message, exc.request_id)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    points=point_lists(),
    start=st.one_of(st.none(), st.sampled_from([0, 2**63 - 10**11, 2**63 - 1])),
)
def test_columns_parse_as_the_points_do(points: list[Any], start: int | None) -> None:
    fast = parse(points, start)
    original = protocol._point_columns
    protocol._point_columns = lambda _points: None
    try:
        slow = parse(points, start)
    finally:
        protocol._point_columns = original
    assert fast[0] == slow[0], (fast, slow)
    if fast[0] == "error":
        assert fast == slow
        event("error")
        return
    assert fast[1] == slow[1]
    for a, b in zip(fast[1].points, slow[1].points, strict=True):
        assert a == b
        for name in FIELDS:
            got = getattr(a, name)
            assert got is None or all(type(x) is float for x in got)
    event("columns" if isinstance(fast[1].points, PointColumns) else "points")


def test_a_regular_request_parses_into_columns() -> None:
    t = np.arange(1, 2001) * 0.001
    points = [
        {"time_from_start": s, "positions": [s, -s], "velocities": [1.0, -1.0]}
        for s in t.tolist()
    ]
    points[5]["time_from_start"] = 1  # an integer number of seconds: exact
    trajectory = {"joint_names": ["a", "b"], "points": points}
    line = json.dumps({"op": "send_goal", "trajectory": trajectory})
    request = protocol.parse_request(MessageDecoder().feed(line.encode() + b"\n")[0])
    assert isinstance(request, protocol.SendGoal)
    columns = request.trajectory.points
    assert isinstance(columns, PointColumns) and len(columns) == 2000
    assert columns.times_ns[5] == 1_000_000_000 and columns.times_ns[6] == 7_000_000
    assert columns[0].positions == (0.001, -0.001)
