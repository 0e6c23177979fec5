"""jtc_hw.daemon.transports.ros2.cdr against rosbags' CDR serializer (a source we did not write).

Every buffer decoded here is rosbags' ``serialize_cdr`` of a message built with rosbags' classes,
and every field of the result is compared bit for bit (NaN and -0.0 included). control_msgs is
not in rosbags' store: its types are declared below from the .msg text of
ros-controls/control_msgs (control_msgs/action/FollowJointTrajectory.action,
msg/JointTolerance.msg, msg/JointComponentTolerance.msg; the goal is the same from 4.x on).
"""

from __future__ import annotations

import random
import struct
import tracemalloc
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from jtc_hw.api.protocol import parse_request
from jtc_hw.controller.messages import FIELDS, PointColumns
from jtc_hw.daemon.transports.ros2 import cdr
from jtc_hw.daemon.transports.ros2.cdr import (
    CdrError,
    decode_joint_trajectory,
    decode_joint_trajectory_message,
    decode_send_goal_request,
)

STORE = get_typestore(Stores.ROS2_JAZZY)
_CONTROL_MSGS = {
    "control_msgs/msg/JointTolerance":
        "string name\nfloat64 position\nfloat64 velocity\nfloat64 acceleration\n",
    "control_msgs/msg/JointComponentTolerance":
        "uint16 X_AXIS=1\nuint16 Y_AXIS=2\nuint16 Z_AXIS=3\nuint16 TRANSLATION=4\n"
        "uint16 ROTATION=5\nstring joint_name\nuint16 component\nfloat64 position\n"
        "float64 velocity\nfloat64 acceleration\n",
    "control_msgs/action/FollowJointTrajectory_Goal":
        "trajectory_msgs/JointTrajectory trajectory\n"
        "trajectory_msgs/MultiDOFJointTrajectory multi_dof_trajectory\n"
        "control_msgs/JointTolerance[] path_tolerance\n"
        "control_msgs/JointComponentTolerance[] component_path_tolerance\n"
        "control_msgs/JointTolerance[] goal_tolerance\n"
        "control_msgs/JointComponentTolerance[] component_goal_tolerance\n"
        "builtin_interfaces/Duration goal_time_tolerance\n",
    "control_msgs/action/FollowJointTrajectory_SendGoal_Request":
        "unique_identifier_msgs/UUID goal_id\n"
        "control_msgs/action/FollowJointTrajectory_Goal goal\n",
}
for _name, _text in _CONTROL_MSGS.items():
    STORE.register(get_types_from_msg(_text, _name))

T = STORE.types
Time = T["builtin_interfaces/msg/Time"]
Duration = T["builtin_interfaces/msg/Duration"]
Header = T["std_msgs/msg/Header"]
JT = T["trajectory_msgs/msg/JointTrajectory"]
JTP = T["trajectory_msgs/msg/JointTrajectoryPoint"]
MDT = T["trajectory_msgs/msg/MultiDOFJointTrajectory"]
MDTP = T["trajectory_msgs/msg/MultiDOFJointTrajectoryPoint"]
Transform = T["geometry_msgs/msg/Transform"]
Twist = T["geometry_msgs/msg/Twist"]
Vector3 = T["geometry_msgs/msg/Vector3"]
Quaternion = T["geometry_msgs/msg/Quaternion"]
UUID = T["unique_identifier_msgs/msg/UUID"]
Tol = T["control_msgs/msg/JointTolerance"]
CTol = T["control_msgs/msg/JointComponentTolerance"]
Goal = T["control_msgs/action/FollowJointTrajectory_Goal"]
SendGoalRequest = T["control_msgs/action/FollowJointTrajectory_SendGoal_Request"]

EMPTY = np.array([], dtype=np.float64)
Spec = tuple[tuple[int, int], list[list[float] | None]]
"""A point: (time_from_start sec, nanosec), then positions, velocities, accelerations, effort
(None: absent, an empty sequence on the wire)."""


def serialize(msg: Any) -> bytes:
    return bytes(STORE.serialize_cdr(msg, msg.__msgtype__))


def trajectory_msg(names: list[str], points: list[Spec], stamp: tuple[int, int] = (0, 0),
                   frame_id: str = "") -> Any:
    return JT(
        header=Header(stamp=Time(*stamp), frame_id=frame_id),
        joint_names=names,
        points=[
            JTP(*(EMPTY if f is None else np.array(f, dtype=np.float64) for f in fields),
                time_from_start=Duration(*tfs))
            for tfs, fields in points],
    )


def bits(values: Any) -> bytes:
    return np.asarray(values, dtype=np.float64).tobytes()


def assert_points_equal(points: Any, specs: list[Spec]) -> None:
    """Every point's time and fields, bit for bit."""
    assert len(points) == len(specs)
    for point, (tfs, fields) in zip(points, specs):
        assert point.time_from_start_ns == tfs[0] * 1_000_000_000 + tfs[1]
        for name, want in zip(FIELDS, fields):
            got = getattr(point, name)
            if not want:
                assert not got, name
            else:
                assert bits(got) == bits(want), name


def six_joint_points(m: int, fields: int = 2) -> list[Spec]:
    rng = np.random.default_rng(m)
    return [((i // 10, (i % 10) * 100_000_000),
             [rng.standard_normal(6).tolist() if f < fields else None for f in range(4)])
            for i in range(m)]


NAMES6 = [f"joint_{i}" for i in range(6)]


# -- golden round trips ------------------------------------------------------------------------


def test_a_joint_trajectory_decodes_to_columns_bit_for_bit() -> None:
    specs = six_joint_points(50)
    specs[3][1][0][2] = float("nan")
    specs[4][1][1][0] = -0.0
    specs[5][1][0][1] = float("-inf")
    wire = decode_joint_trajectory_message(serialize(trajectory_msg(NAMES6, specs, frame_id="w")))
    assert wire.joint_names == tuple(NAMES6)
    assert wire.start_time_ns is None and wire.start_in is None
    assert isinstance(wire.points, PointColumns)
    assert wire.points.values("accelerations") is None
    assert_points_equal(wire.points, specs)


def test_decode_at_an_offset_returns_the_end() -> None:
    buf = serialize(trajectory_msg(NAMES6, six_joint_points(3)))
    wire, end = decode_joint_trajectory(buf + b"\x00\x00\x00", 4)
    assert end == len(buf)
    assert wire.joint_names == tuple(NAMES6)


@pytest.mark.parametrize("k", [1, 2, 3, 6, 7])
@pytest.mark.parametrize("present", [(1, 0, 0, 0), (1, 1, 0, 0), (1, 1, 1, 0), (1, 1, 1, 1),
                                     (0, 1, 0, 1), (1, 0, 1, 0)])
@pytest.mark.parametrize("frame_id", ["", "abc", "base_link"])
def test_regular_layouts_take_the_strided_path(
    monkeypatch: pytest.MonkeyPatch, k: int, present: tuple[int, ...], frame_id: str
) -> None:
    """Point sizes of 0 and 4 modulo 8, starting at either residue (the frame_id shifts it):
    every one is read by strided views, never point by point."""
    def no_walk(*_: Any) -> None:
        raise AssertionError("walked point by point")

    monkeypatch.setattr(cdr, "_walk_points", no_walk)
    rng = np.random.default_rng(k)
    specs: list[Spec] = [
        ((i, 7), [rng.standard_normal(k).tolist() if p else None for p in present])
        for i in range(9)]
    buf = serialize(trajectory_msg([f"j{i}" for i in range(k)], specs, frame_id=frame_id))
    assert_points_equal(decode_joint_trajectory_message(buf).points, specs)


def test_points_without_some_fields_walk_and_say_which_are_present() -> None:
    specs = six_joint_points(7, fields=3)
    specs[2][1][1] = None  # no velocities at point 2
    specs[5][1][2] = None
    specs[6][1][3] = [1.0] * 6  # effort at the last point only
    wire = decode_joint_trajectory_message(serialize(trajectory_msg(NAMES6, specs)))
    assert isinstance(wire.points, PointColumns)
    velocities = wire.points.values("velocities")
    assert velocities is not None
    assert velocities[1].tolist() == [True, True, False, True, True, True, True]
    assert_points_equal(wire.points, specs)


def test_a_field_of_mixed_lengths_becomes_points_for_the_controller_to_refuse() -> None:
    specs = six_joint_points(4)
    specs[1][1][0] = [1.0, 2.0]  # two positions among six-joint points
    wire = decode_joint_trajectory_message(serialize(trajectory_msg(NAMES6, specs)))
    assert not isinstance(wire.points, PointColumns)
    assert_points_equal(wire.points, specs)


def test_no_points_is_an_empty_trajectory() -> None:
    wire = decode_joint_trajectory_message(serialize(trajectory_msg(NAMES6, [])))
    assert wire.points == () and wire.joint_names == tuple(NAMES6)


def goal_request(specs: list[Spec], names: list[str] = NAMES6, **goal: Any) -> Any:
    fields: dict[str, Any] = {
        "trajectory": trajectory_msg(names, specs),
        "multi_dof_trajectory": MDT(header=Header(stamp=Time(0, 0), frame_id=""),
                                    joint_names=[], points=[]),
        "path_tolerance": [], "component_path_tolerance": [], "goal_tolerance": [],
        "component_goal_tolerance": [], "goal_time_tolerance": Duration(0, 0),
    }
    fields.update(goal)
    uuid = np.arange(16, dtype=np.uint8) + 0xF0
    return SendGoalRequest(goal_id=UUID(uuid=uuid), goal=Goal(**fields))


def multi_dof(points: int) -> Any:
    v = Vector3(1.0, 2.0, 3.0)
    return MDT(
        header=Header(stamp=Time(5, 6), frame_id="odom"), joint_names=["base"],
        points=[MDTP(transforms=[Transform(v, Quaternion(0.0, 0.0, 0.0, 1.0))] * (i % 3),
                     velocities=[Twist(v, v)] * (i % 2), accelerations=[],
                     time_from_start=Duration(i, 0))
                for i in range(points)])


def test_a_follow_joint_trajectory_goal_decodes_with_its_tolerances() -> None:
    specs = six_joint_points(20)
    request = goal_request(
        specs,
        multi_dof_trajectory=multi_dof(5),
        path_tolerance=[Tol("joint_1", 0.1, 0.2, 0.3), Tol("joint_é", -1.0, 0.0, float("nan"))],
        component_path_tolerance=[CTol("base", 4, 0.1, 0.2, 0.3)],
        goal_tolerance=[Tol("joint_5", 0.01, 0.0, 0.0)],
        component_goal_tolerance=[CTol("base", 5, 1.0, 2.0, 3.0), CTol("x", 1, 0, 0, 0)],
        goal_time_tolerance=Duration(1, 500_000_000),
    )
    uuid, goal = decode_send_goal_request(serialize(request))
    assert uuid == bytes(range(0xF0, 0x100))
    assert goal.trajectory.joint_names == tuple(NAMES6)
    assert_points_equal(goal.trajectory.points, specs)
    assert [(t.name, t.position, t.velocity) for t in goal.path_tolerance] == [
        ("joint_1", 0.1, 0.2), ("joint_é", -1.0, 0.0)]
    assert goal.path_tolerance[0].acceleration == 0.3
    assert np.isnan(goal.path_tolerance[1].acceleration)
    assert [(t.name, t.position) for t in goal.goal_tolerance] == [("joint_5", 0.01)]
    assert goal.goal_time_tolerance == 1.5
    assert goal.time_scaling is None


def test_a_goal_with_nothing_but_a_trajectory() -> None:
    uuid, goal = decode_send_goal_request(serialize(goal_request(six_joint_points(2))))
    assert len(uuid) == 16
    assert goal.path_tolerance == () and goal.goal_tolerance == ()
    assert goal.goal_time_tolerance == 0.0


# -- the header stamp --------------------------------------------------------------------------


def test_a_non_zero_stamp_is_placed_on_the_daemon_clock_with_the_offset() -> None:
    buf = serialize(trajectory_msg(NAMES6, six_joint_points(2), stamp=(1_700_000_000, 5)))
    offset = -1_699_999_000 * 1_000_000_000
    wire = decode_joint_trajectory_message(buf, clock_offset_ns=offset)
    assert wire.start_time_ns == 1_700_000_000 * 1_000_000_000 + 5 + offset
    with pytest.raises(CdrError, match="non-zero stamp"):
        decode_joint_trajectory_message(buf)
    with pytest.raises(CdrError, match="outside"):  # before the daemon clock's start
        decode_joint_trajectory_message(buf, clock_offset_ns=-2_000_000_000 * 1_000_000_000)


def test_a_stamp_of_zero_starts_now_whatever_the_offset() -> None:
    buf = serialize(trajectory_msg(NAMES6, six_joint_points(2)))
    assert decode_joint_trajectory_message(buf, clock_offset_ns=123).start_time_ns is None


def test_a_negative_stamp_is_refused() -> None:
    buf = serialize(trajectory_msg(NAMES6, six_joint_points(2), stamp=(-1, 0)))
    with pytest.raises(CdrError, match="negative"):
        decode_joint_trajectory_message(buf, clock_offset_ns=0)


# -- hypothesis --------------------------------------------------------------------------------

_values = st.floats(allow_nan=True, allow_infinity=True, width=64)


@st.composite
def trajectories(draw: st.DrawFn) -> tuple[list[str], list[Spec], str]:
    k = draw(st.integers(0, 7))
    m = draw(st.integers(0, 12))
    regular = draw(st.booleans())
    layout = draw(st.lists(st.booleans(), min_size=4, max_size=4))
    specs: list[Spec] = []
    for _ in range(m):
        tfs = (draw(st.integers(-(2**31), 2**31 - 1)), draw(st.integers(0, 2**32 - 1)))
        fields: list[list[float] | None] = []
        for f in range(4):
            present = layout[f] if regular else draw(st.booleans())
            n = k if regular or draw(st.integers(0, 4)) else draw(st.integers(1, 8))
            fields.append(draw(st.lists(_values, min_size=n, max_size=n)) if present else None)
        specs.append((tfs, fields))
    names = draw(st.lists(st.text(max_size=6).filter(lambda s: "\x00" not in s),
                          min_size=k, max_size=k))
    frame = draw(st.text(max_size=9).filter(lambda s: "\x00" not in s))
    return names, specs, frame


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(trajectories())
def test_any_trajectory_round_trips(case: tuple[list[str], list[Spec], str]) -> None:
    names, specs, frame = case
    buf = serialize(trajectory_msg(names, specs, frame_id=frame))
    wire = decode_joint_trajectory_message(buf)
    assert wire.joint_names == tuple(names)
    assert_points_equal(wire.points, specs)
    _, end = decode_joint_trajectory(buf)
    assert end == len(buf)


# -- bad input ---------------------------------------------------------------------------------


def valid_goal() -> bytes:
    return serialize(goal_request(
        six_joint_points(6, fields=3), multi_dof_trajectory=multi_dof(3),
        path_tolerance=[Tol("joint_1", 0.1, 0.2, 0.3)],
        component_goal_tolerance=[CTol("base", 5, 1.0, 2.0, 3.0)],
        goal_time_tolerance=Duration(2, 0)))


def test_every_truncation_of_a_goal_is_a_cdr_error() -> None:
    buf = valid_goal()
    for n in range(len(buf)):
        with pytest.raises(CdrError):
            decode_send_goal_request(buf[:n])


def test_every_truncation_of_a_trajectory_is_a_cdr_error() -> None:
    specs = six_joint_points(5)
    specs[2][1][1] = None  # and of the walked kind
    for buf in (serialize(trajectory_msg(NAMES6, six_joint_points(5))),
                serialize(trajectory_msg(NAMES6, specs))):
        for n in range(len(buf)):
            with pytest.raises(CdrError):
                decode_joint_trajectory_message(buf[:n])


def patched(buf: bytes, at: int, value: int) -> bytes:
    return buf[:at] + struct.pack("<I", value) + buf[at + 4 :]


# Body offsets of the counts in a trajectory with stamp 0, frame_id "" (4 + 1 bytes, padded):
# joint_names count at 12 (absolute 16) in an empty-names message, points count after it.
def _empty_trajectory() -> bytes:
    return serialize(trajectory_msg([], []))


@pytest.mark.parametrize("where", ["joint_names", "points", "positions", "frame_id"])
def test_a_ten_million_length_in_a_small_buffer_allocates_nothing(where: str) -> None:
    if where == "positions":
        buf = serialize(trajectory_msg([], [((0, 0), [None, None, None, None])]))
        at = 4 + 24  # stamp 8, frame_id 8, names count 4, points count 4: positions at 24
    else:
        buf = _empty_trajectory()
        at = {"frame_id": 4 + 8, "joint_names": 4 + 16, "points": 4 + 20}[where]
    buf = patched(buf, at, 10_000_000) + bytes(100 - len(buf))
    assert len(buf) == 100
    tracemalloc.start()
    try:
        with pytest.raises(CdrError, match="10000000|truncated"):
            decode_joint_trajectory_message(buf)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 200_000


@pytest.mark.parametrize(("at", "field"), [
    (60, "multi_dof_trajectory.points"), (64, "goal.path_tolerance"),
    (68, "component_path_tolerance"), (72, "goal.goal_tolerance"),
    (76, "component_goal_tolerance")])
def test_a_huge_count_in_a_goal_is_refused_before_reading(at: int, field: str) -> None:
    buf = serialize(goal_request([], names=[]))
    # uuid 16, trajectory: stamp 8, frame 8, names 4, points 4 -> multi-dof at body 40:
    # stamp 8, frame 8, names 4, points 4 -> the four tolerance counts from body 64.
    assert struct.unpack_from("<I", buf, 4 + at) == (0,)
    with pytest.raises(CdrError, match=f"{field}: 10000000 elements"):
        decode_send_goal_request(patched(buf, 4 + at, 10_000_000))


def test_a_string_without_its_nul_is_refused() -> None:
    buf = bytearray(serialize(trajectory_msg(["ab"], [])))
    # names: count at body 16, length at 20 (3), bytes at 24: "ab\0"
    assert bytes(buf[4 + 24 : 4 + 27]) == b"ab\x00"
    buf[4 + 26] = ord("c")
    with pytest.raises(CdrError, match="does not end with NUL"):
        decode_joint_trajectory_message(bytes(buf))


def test_a_string_of_length_zero_is_refused() -> None:
    buf = patched(serialize(trajectory_msg(["ab"], [])), 4 + 20, 0)
    with pytest.raises(CdrError, match="length 0"):
        decode_joint_trajectory_message(buf)


def test_a_name_that_is_not_utf8_is_refused() -> None:
    buf = bytearray(serialize(trajectory_msg(["ab"], [])))
    buf[4 + 24] = 0xFF
    with pytest.raises(CdrError, match="not UTF-8"):
        decode_joint_trajectory_message(bytes(buf))


@pytest.mark.parametrize("header", [b"\x00\x00\x00\x00", b"\x00\x03\x00\x00", b"\x01\x01\x00\x00",
                                    b"\x00"])
def test_an_encapsulation_other_than_cdr_little_endian_is_refused(header: bytes) -> None:
    buf = serialize(trajectory_msg(NAMES6, six_joint_points(2)))
    with pytest.raises(CdrError, match="encapsulation header"):
        decode_joint_trajectory_message(header + buf[4:] if len(header) == 4 else header)


def test_the_option_bytes_and_trailing_bytes_are_ignored() -> None:
    specs = six_joint_points(3)
    buf = serialize(trajectory_msg(NAMES6, specs))
    wire = decode_joint_trajectory_message(buf[:2] + b"\x00\x03" + buf[4:] + b"\xff" * 13)
    assert_points_equal(wire.points, specs)


def test_an_offset_outside_the_body_is_refused() -> None:
    with pytest.raises(CdrError, match="offset"):
        decode_joint_trajectory(_empty_trajectory(), 2)


def test_random_truncations_and_byte_flips_raise_only_cdr_errors() -> None:
    """Mutations of a valid goal and of a valid trajectory: each decodes or raises CdrError,
    never another exception."""
    rng = random.Random(25)
    goal = valid_goal()
    specs = six_joint_points(8, fields=2)
    specs[3][1][1] = None
    trajectory = serialize(trajectory_msg(NAMES6, specs))
    outcomes = {"ok": 0, "error": 0}
    for i in range(3000):
        base = goal if i % 2 else trajectory
        buf = bytearray(base)
        for _ in range(rng.randint(1, 4)):
            at = rng.randrange(len(buf))
            buf[at] = rng.choice((rng.randrange(256), buf[at] ^ (1 << rng.randrange(8)), 0xFF))
        if rng.random() < 0.3:
            del buf[rng.randrange(len(buf)) :]
        try:
            if base is goal:
                decode_send_goal_request(bytes(buf))
            else:
                decode_joint_trajectory_message(memoryview(bytes(buf)))
            outcomes["ok"] += 1
        except CdrError:
            outcomes["error"] += 1
    assert outcomes["ok"] and outcomes["error"]


def test_a_goal_decodes_to_the_request_the_socket_makes_of_the_same_goal() -> None:
    """The same goal as the socket's JSON (``parse_request``) and as CDR: equal requests."""
    specs = six_joint_points(30, fields=3)
    specs[4][1][1] = None
    line = {"op": "send_goal",
            "trajectory": {"joint_names": NAMES6, "points": [
                {"time_from_start": tfs[0] + tfs[1] / 1e9,
                 **{name: values for name, values in zip(FIELDS, fields) if values}}
                for tfs, fields in specs]},
            "path_tolerance": [{"name": "joint_1", "position": 0.5, "velocity": 0.25,
                                "acceleration": 0.0}],
            "goal_time_tolerance": 0.75}
    request = goal_request(specs, path_tolerance=[Tol("joint_1", 0.5, 0.25, 0.0)],
                           goal_time_tolerance=Duration(0, 750_000_000))
    _, goal = decode_send_goal_request(serialize(request))
    assert goal == parse_request(line)
