"""CDR for the ROS 2 transport: a ``JointTrajectory`` or a ``FollowJointTrajectory`` goal straight
to the planner's columns, without a Python object per number (no I/O).

Theory of operation
-------------------
A sample's payload is XCDR1 (plain CDR), little-endian, behind a 4-byte encapsulation header,
as rmw_zenoh (through Fast-CDR) and rosbags' ``serialize_cdr`` write it. Every primitive is
aligned to its own size *relative to the body* (the byte after the header), sequences and
strings are a ``uint32`` count then the elements, a string's count includes its NUL, and an
empty sequence has no padding after its count (eProsima/Fast-CDR src/cpp/Cdr.cpp,
``serialize_array``: zero elements return before aligning; rosbags writes the same)::

    0      2      4 (body offset 0)
    | 00 01 | opt | header.stamp.sec i32 | .nanosec u32 | frame_id: len u32, bytes.., NUL |
    | joint_names: count u32 | len u32, bytes.., NUL | ... |
    | points: count u32 | point 0 | point 1 | ...
    point: | n u32 | pad to 8 | n x f64 | (positions; pad and values only when n > 0)
           | velocities | accelerations | effort (the same shape) | tfs.sec i32 | tfs.nanosec u32 |

A point's layout depends only on its four lengths and on where it starts modulo 8 (0 or 4).
When every point has the lengths of the first (the normal case) the point offsets repeat with
a period of one or two points, so each field of every point is read by one strided
``numpy.ndarray`` view over the buffer (two when the period is two), after a vectorised check
that every length read through the same strides is the one assumed: if so, by induction on
the points, every assumed offset is the true one. Otherwise (points without some field, mixed
layouts) one Python step per point reads the four counts and notes where the values are, and
each field is then gathered by one index array (``present`` says which points carry it); a
field whose present rows are not all of one length (a goal the controller refuses) falls back
to ``TrajectoryPoint`` objects, for the controller to name the problem in its own words.
Measured (bench/cdr_decode.py, a 6-joint goal with positions, velocities, accelerations):
2,000 points 0.12 ms strided, 1.9 ms walked (one point lacking velocities), against 7.4 ms
for rosbags' ``deserialize_cdr`` and 9.3 ms for the socket's JSON parse of the same goal.

No encoders: what the transport publishes often is left to rosbags' ``serialize_cdr``, which
takes 7 us for a 6-joint ``JointState`` and 22-26 us for a Jazzy
``JointTrajectoryControllerState`` (message objects built included), under the 30 us budget.

``FollowJointTrajectory_SendGoal`` request (control_msgs >= 4, the same on Humble, Jazzy,
Kilted and Rolling: control_msgs/action/FollowJointTrajectory.action)::

    goal_id: uint8[16] | trajectory | multi_dof_trajectory | path_tolerance: JointTolerance[]
    | component_path_tolerance: JointComponentTolerance[] | goal_tolerance: JointTolerance[]
    | component_goal_tolerance: JointComponentTolerance[] | goal_time_tolerance: Duration

Decisions (docs: this docstring; the transport relies on them):

- ``header.stamp`` (ROS time, nanoseconds since the epoch) of 0 means "start now", as upstream
  (jtc_upstream_behaviour.md 4.1): ``WireTrajectory.start_time_ns`` None. A non-zero stamp is
  converted to the daemon clock with ``clock_offset_ns`` (daemon clock minus ROS time, which
  the caller measures when the sample arrives); without an offset it is refused, and so is a
  stamp whose daemon time falls outside ``0..MAX_NS`` or a negative ``sec`` (rclcpp cannot
  hold a negative time point). ``frame_id`` is read and ignored, as upstream does.
- ``multi_dof_trajectory`` and the component tolerances are read (to find the fields after
  them) and ignored: upstream's JTC (joint_trajectory_controller.cpp,
  ``goal_received_callback``) validates ``goal->trajectory`` only, and never looks at them.
- Encapsulation: only ``00 01`` (CDR little-endian) is accepted; big-endian ``00 00``,
  parameter lists and XCDR2 are refused (no ROS 2 peer on a little-endian host sends them).
  The two option bytes are ignored.
- Trailing bytes after the message are allowed and ignored: CDR lets a writer pad its stream
  (the options' low bits count such padding), and the decoder reads what the type says.
- Values are not checked: NaN, infinities and huge numbers pass through to the controller,
  whose validation refuses them with upstream's messages.

Every malformed buffer raises :class:`CdrError` naming the field and the offset. Counts are
checked against the bytes left *before* anything is allocated, so a length of ten million in a
100-byte buffer costs nothing.
"""

from __future__ import annotations

import struct
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from ....api.requests import MAX_NS, SendGoal, WireTrajectory
from ....controller.messages import FIELDS, NS_PER_S, PointColumns, TrajectoryPoint
from ....controller.tolerances import JointTolerance

__all__ = [
    "CdrError", "ENCAPSULATION", "decode_joint_trajectory", "decode_joint_trajectory_message",
    "decode_follow_joint_trajectory_goal", "decode_send_goal_request",
]

ENCAPSULATION: Final = b"\x00\x01"
"""The representation identifier accepted: CDR, little-endian."""
_BODY: Final = 4
"""Offset of the body: alignment is relative to it."""
_UUID_BYTES: Final = 16
_MIN_POINT: Final = 4 * 4 + 8
"""Smallest JointTrajectoryPoint: four empty sequences and a Duration."""
_MIN_STRING: Final = 5
_MIN_TOLERANCE: Final = _MIN_STRING + 24
_MIN_COMPONENT_TOLERANCE: Final = _MIN_STRING + 2 + 24
_MIN_MULTI_DOF_POINT: Final = 3 * 4 + 8
_TRANSFORM: Final = 7 * 8
_TWIST: Final = 6 * 8

_U16 = struct.Struct("<H").unpack_from
_U32 = struct.Struct("<I").unpack_from
_TIME = struct.Struct("<iI").unpack_from


class CdrError(ValueError):
    """A buffer that is not the CDR of the message expected: the message names the field and
    the byte offset (in the whole buffer, header included)."""


class _Reader:
    """A cursor over one CDR buffer; every read checks the bytes left first."""

    __slots__ = ("buf", "pos", "end")

    def __init__(self, buf: bytes | memoryview, pos: int) -> None:
        self.buf = buf
        self.pos = pos
        self.end = len(buf)

    def align(self, n: int) -> None:
        self.pos += -(self.pos - _BODY) % n

    def need(self, n: int, what: str) -> None:
        if n > self.end - self.pos:
            raise CdrError(
                f"{what}: needs {n} bytes at offset {self.pos}, the buffer has "
                f"{max(self.end - self.pos, 0)} left (truncated)")

    def u16(self, what: str) -> int:
        self.align(2)
        self.need(2, what)
        (v,) = _U16(self.buf, self.pos)
        self.pos += 2
        return int(v)

    def u32(self, what: str) -> int:
        self.align(4)
        self.need(4, what)
        (v,) = _U32(self.buf, self.pos)
        self.pos += 4
        return int(v)

    def count(self, what: str, min_size: int) -> int:
        """A sequence's count, refused when its elements could not fit in the bytes left."""
        n = self.u32(f"{what} (count)")
        left = self.end - self.pos
        if n * min_size > left:
            raise CdrError(
                f"{what}: {n} elements of at least {min_size} bytes each at offset "
                f"{self.pos - 4}, the buffer has {left} bytes left")
        return n

    def time(self, what: str) -> tuple[int, int]:
        """``builtin_interfaces`` Time or Duration: (sec int32, nanosec uint32)."""
        self.align(4)
        self.need(8, what)
        sec, nsec = _TIME(self.buf, self.pos)
        self.pos += 8
        return int(sec), int(nsec)

    def string(self, what: str) -> str:
        at = self.pos
        n = self.u32(f"{what} (length)")
        if n == 0:
            raise CdrError(f"{what}: string length 0 at offset {at}: a CDR string holds its NUL")
        self.need(n, what)
        raw = bytes(self.buf[self.pos : self.pos + n])
        if raw[-1] != 0:
            raise CdrError(f"{what}: string at offset {at} does not end with NUL")
        self.pos += n
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError as e:
            raise CdrError(f"{what}: string at offset {at} is not UTF-8 ({e.reason})") from None

    def strings(self, what: str) -> tuple[str, ...]:
        n = self.count(what, _MIN_STRING)
        return tuple(self.string(f"{what}[{i}]") for i in range(n))

    def skip_f64(self, n: int, size: int, what: str) -> None:
        """Skip ``n`` elements of ``size`` bytes made of float64s (8-aligned when n > 0)."""
        if n:
            self.align(8)
            self.need(n * size, what)
            self.pos += n * size


def _body_reader(buf: bytes | memoryview) -> _Reader:
    """A reader after the encapsulation header, checked.

    Raises:
        CdrError: shorter than the header, or a representation other than CDR little-endian.
    """
    if len(buf) < _BODY:
        raise CdrError(f"encapsulation header: needs 4 bytes, the buffer has {len(buf)}")
    rep = bytes(buf[:2])
    if rep != ENCAPSULATION:
        kind = {b"\x00\x00": "CDR big-endian", b"\x00\x02": "PL_CDR big-endian",
                b"\x00\x03": "PL_CDR little-endian"}.get(rep, "an unknown representation")
        raise CdrError(
            f"encapsulation header: {rep.hex(' ')} ({kind}) is not supported; expected "
            f"{ENCAPSULATION.hex(' ')} (CDR little-endian)")
    return _Reader(buf, _BODY)


# -- points ------------------------------------------------------------------------------------


def _layout(lengths: tuple[int, ...], residue: int) -> tuple[int, list[int], list[int], int]:
    """A point's size and its length, values and Duration offsets (from the point's start) for
    these four lengths, when the point starts at ``residue`` (0 or 4) modulo 8 in the body."""
    o = 0
    len_at: list[int] = []
    data_at: list[int] = []
    for n in lengths:
        len_at.append(o)
        o += 4
        if n:
            o += -(residue + o) % 8
        data_at.append(o)
        o += 8 * n
    return o + 8, len_at, data_at, o


def _view(buf: Any, dtype: str, shape: tuple[int, ...], offset: int,
          strides: tuple[int, ...]) -> NDArray[Any]:
    view: NDArray[Any] = np.ndarray(shape, dtype=dtype, buffer=buf, offset=offset,
                                    strides=strides)
    return view


def _regular_points(
    r: _Reader, m: int, what: str
) -> tuple[NDArray[np.int64], dict[str, NDArray[np.float64]]] | None:
    """The points by strided views when every one has the first one's lengths, else None
    (the reader is then left where it was). On success the reader is after the last point."""
    start = r.pos
    buf = r.buf
    # The first point's lengths, walking it once (bounds checked by the reader).
    lengths = []
    for name in FIELDS:
        n = r.count(f"{what}[0].{name}", 8)
        lengths.append(n)
        r.skip_f64(n, 8, f"{what}[0].{name}")
    r.pos = start
    lens = tuple(lengths)
    # Runs of points sharing one layout: (first point, step, count, offset, stride, residue).
    r0 = (start - _BODY) % 8
    s0 = _layout(lens, r0)[0]
    if s0 % 8 == 0:
        runs = [(0, 1, m, start, s0, r0)]
        end = start + m * s0
    else:
        r1 = r0 ^ 4
        s1 = _layout(lens, r1)[0]
        if s1 % 8 == 0:
            runs = [(0, 1, 1, start, s0, r0), (1, 1, m - 1, start + s0, s1, r1)]
            end = start + s0 + (m - 1) * s1
        else:
            pair = s0 + s1
            runs = [(0, 2, (m + 1) // 2, start, pair, r0),
                    (1, 2, m // 2, start + s0, pair, r1)]
            end = start + (m // 2) * pair + (m % 2) * s0
    if end > r.end:
        return None  # the per-point walk names the truncation
    runs = [run for run in runs if run[2] > 0]
    layouts = {res: _layout(lens, res) for res in {run[5] for run in runs}}
    for _, _, count, offset, stride, res in runs:
        _, len_at, _, _ = layouts[res]
        for i in range(4):
            got = _view(buf, "<u4", (count,), offset + len_at[i], (stride,))
            if not (got == lens[i]).all():
                return None
    times = np.empty(m, dtype=np.int64)
    values = {name: np.empty((m, n)) for name, n in zip(FIELDS, lens, strict=True) if n}
    for first_i, step, count, offset, stride, res in runs:
        _, _, data_at, dur_at = layouts[res]
        sec = _view(buf, "<i4", (count,), offset + dur_at, (stride,)).astype(np.int64)
        nsec = _view(buf, "<u4", (count,), offset + dur_at + 4, (stride,)).astype(np.int64)
        times[first_i::step] = sec * NS_PER_S + nsec
        for i, name in enumerate(FIELDS):
            if lens[i]:
                values[name][first_i::step] = _view(
                    buf, "<f8", (count, lens[i]), offset + data_at[i], (stride, 8))
    r.pos = end
    return times, values


def _walk_points(
    r: _Reader, m: int, what: str
) -> PointColumns | tuple[TrajectoryPoint, ...]:
    """The points one Python step per point: any mix of lengths.

    The loop only reads the four counts and notes where each point's values and Duration are;
    the values are then gathered by index arrays, one per field (every float64 body is
    8-aligned relative to the body, so one float64 view of the body holds them all).
    """
    buf, pos, end = r.buf, r.pos, r.end
    u32 = _U32
    counts = [0] * (4 * m)
    at = [0] * (4 * m)
    durations = [0] * m
    i = 0
    for p in range(m):
        for _ in range(4):  # a count is always 4-aligned here: after a count or float64s
            if pos + 4 > end:
                r.pos = pos
                r.need(4, f"{what}[{p}].{FIELDS[i % 4]} (count)")
            (n,) = u32(buf, pos)
            pos += 4
            if n:
                pos += (pos - _BODY) % 8  # 0 or 4 to the float64s' alignment
                if n > (end - pos) // 8:
                    r.pos = pos
                    r.need(8 * n, f"{what}[{p}].{FIELDS[i % 4]}")
                counts[i] = n
                at[i] = pos
                pos += 8 * n
            i += 1
        if pos + 8 > end:
            r.pos = pos
            r.need(8, f"{what}[{p}].time_from_start")
        durations[p] = pos
        pos += 8
    r.pos = pos
    body = memoryview(buf)[_BODY:]
    words = np.frombuffer(body[: len(body) // 4 * 4], dtype="<u4")
    where = (np.array(durations, dtype=np.int64) - _BODY) // 4
    sec = words[where].view("<i4").astype(np.int64)
    times = sec * NS_PER_S + words[where + 1].astype(np.int64)
    floats = np.frombuffer(body[: len(body) // 8 * 8], dtype="<f8")
    n_all = np.array(counts, dtype=np.int64).reshape(m, 4)
    at_all = (np.array(at, dtype=np.int64).reshape(m, 4) - _BODY) // 8
    arrays: dict[str, NDArray[np.float64]] = {}
    present: dict[str, NDArray[np.bool_]] = {}
    for f, name in enumerate(FIELDS):
        n = n_all[:, f]
        mask = n > 0
        if not mask.any():
            continue
        lengths = np.unique(n[mask])
        if lengths.shape[0] != 1:
            return _points_as_objects(times, n_all, at_all, floats)
        k = int(lengths[0])
        full = np.zeros((m, k))
        full[mask] = floats[at_all[mask, f][:, None] + np.arange(k)]
        arrays[name] = full
        present[name] = mask
    return PointColumns(times, present=present, **arrays)


def _points_as_objects(
    times: NDArray[np.int64], counts: NDArray[np.int64], at: NDArray[np.int64],
    floats: NDArray[np.float64],
) -> tuple[TrajectoryPoint, ...]:
    """Points whose present rows differ in length: objects, for the controller to refuse (or,
    for effort, to accept, as upstream does not check its size)."""
    return tuple(
        TrajectoryPoint(
            None, *(tuple(floats[a : a + n].tolist()) if n else None
                    for n, a in zip(ns, starts, strict=True)),
            time_from_start_ns=t)
        for t, ns, starts in zip(times.tolist(), counts.tolist(), at.tolist(), strict=True))


def _points(r: _Reader, what: str) -> PointColumns | tuple[TrajectoryPoint, ...]:
    m = r.count(what, _MIN_POINT)
    if m == 0:
        return ()
    fast = _regular_points(r, m, what)
    if fast is not None:
        times, values = fast
        return PointColumns(
            times, values.get("positions"), values.get("velocities"),
            values.get("accelerations"), values.get("effort"))
    return _walk_points(r, m, what)


# -- messages ----------------------------------------------------------------------------------


def _start_time(sec: int, nsec: int, clock_offset_ns: int | None, what: str) -> int | None:
    """``header.stamp`` as ``WireTrajectory.start_time_ns`` (the module docstring's rule)."""
    if sec == 0 and nsec == 0:
        return None
    if sec < 0:
        raise CdrError(f"{what}: sec {sec} is negative; a ROS time cannot be before the epoch")
    stamp = sec * NS_PER_S + nsec
    if clock_offset_ns is None:
        raise CdrError(
            f"{what}: a non-zero stamp ({stamp} ns, ROS time) needs the offset between ROS "
            "time and the daemon clock, which this decoder was not given")
    start = stamp + clock_offset_ns
    if not 0 < start <= MAX_NS:
        raise CdrError(
            f"{what}: {stamp} ns (ROS time) is {start} ns on the daemon clock, outside "
            f"1..{MAX_NS}")
    return start


def _trajectory(r: _Reader, clock_offset_ns: int | None, what: str) -> WireTrajectory:
    sec, nsec = r.time(f"{what}.header.stamp")
    start = _start_time(sec, nsec, clock_offset_ns, f"{what}.header.stamp")
    r.string(f"{what}.header.frame_id")
    names = r.strings(f"{what}.joint_names")
    points = _points(r, f"{what}.points")
    return WireTrajectory(names, points, start_time_ns=start)


def decode_joint_trajectory(
    buf: bytes | memoryview, offset: int = _BODY, *, clock_offset_ns: int | None = None
) -> tuple[WireTrajectory, int]:
    """A ``trajectory_msgs/msg/JointTrajectory`` in a CDR buffer at ``offset`` (default: the
    body of a whole sample), and the offset after it.

    ``buf`` must include the encapsulation header: alignment is relative to byte 4. The
    header stamp becomes ``start_time_ns`` as the module docstring says (``clock_offset_ns``:
    daemon clock minus ROS time, in nanoseconds).

    Raises:
        CdrError: the buffer is truncated or malformed (the message names the field and the
            offset), or the stamp cannot be placed on the daemon clock.
    """
    if offset < _BODY or offset > len(buf):
        raise CdrError(f"offset {offset} is outside the body (4..{len(buf)})")
    r = _Reader(buf, offset)
    trajectory = _trajectory(r, clock_offset_ns, "trajectory")
    return trajectory, r.pos


def decode_joint_trajectory_message(
    buf: bytes | memoryview, *, clock_offset_ns: int | None = None
) -> WireTrajectory:
    """A whole ``trajectory_msgs/msg/JointTrajectory`` sample (encapsulation header first):
    the topic interface's message, for a ``SendTrajectory`` request.

    Raises:
        CdrError: as :func:`decode_joint_trajectory`, or a bad encapsulation header.
    """
    r = _body_reader(buf)
    return _trajectory(r, clock_offset_ns, "trajectory")


def _tolerances(r: _Reader, what: str) -> tuple[JointTolerance, ...]:
    n = r.count(what, _MIN_TOLERANCE)
    out = []
    for i in range(n):
        name = r.string(f"{what}[{i}].name")
        r.align(8)
        r.need(24, f"{what}[{i}]")
        p, v, a = np.frombuffer(r.buf, dtype="<f8", count=3, offset=r.pos).tolist()
        r.pos += 24
        out.append(JointTolerance(name, p, v, a))
    return tuple(out)


def _skip_component_tolerances(r: _Reader, what: str) -> None:
    n = r.count(what, _MIN_COMPONENT_TOLERANCE)
    for i in range(n):
        r.string(f"{what}[{i}].joint_name")
        r.u16(f"{what}[{i}].component")
        r.skip_f64(1, 24, f"{what}[{i}]")


def _skip_multi_dof(r: _Reader, what: str) -> None:
    r.time(f"{what}.header.stamp")
    r.string(f"{what}.header.frame_id")
    r.strings(f"{what}.joint_names")
    m = r.count(f"{what}.points", _MIN_MULTI_DOF_POINT)
    for p in range(m):
        for name, size in (("transforms", _TRANSFORM), ("velocities", _TWIST),
                           ("accelerations", _TWIST)):
            where = f"{what}.points[{p}].{name}"
            r.skip_f64(r.count(where, size), size, where)
        r.time(f"{what}.points[{p}].time_from_start")


def decode_follow_joint_trajectory_goal(
    buf: bytes | memoryview, *, clock_offset_ns: int | None = None
) -> tuple[bytes, SendGoal]:
    """A whole ``control_msgs/action/FollowJointTrajectory_SendGoal`` request sample: the
    goal's UUID (16 bytes) and the ``SendGoal`` request it asks for.

    ``multi_dof_trajectory`` and the component tolerances are checked for structure and
    ignored (upstream ignores them); ``goal_time_tolerance`` becomes seconds.

    Raises:
        CdrError: a bad encapsulation header, a truncated or malformed buffer (the message
            names the field and the offset), or a stamp that cannot be placed on the daemon
            clock.
    """
    r = _body_reader(buf)
    r.need(_UUID_BYTES, "goal_id")
    uuid = bytes(buf[r.pos : r.pos + _UUID_BYTES])
    r.pos += _UUID_BYTES
    trajectory = _trajectory(r, clock_offset_ns, "goal.trajectory")
    _skip_multi_dof(r, "goal.multi_dof_trajectory")
    path = _tolerances(r, "goal.path_tolerance")
    _skip_component_tolerances(r, "goal.component_path_tolerance")
    goal = _tolerances(r, "goal.goal_tolerance")
    _skip_component_tolerances(r, "goal.component_goal_tolerance")
    sec, nsec = r.time("goal.goal_time_tolerance")
    goal_time = (sec * NS_PER_S + nsec) / NS_PER_S
    return uuid, SendGoal(
        trajectory=trajectory, path_tolerance=path, goal_tolerance=goal,
        goal_time_tolerance=goal_time)


decode_send_goal_request = decode_follow_joint_trajectory_goal
"""The name the transport calls: :func:`decode_follow_joint_trajectory_goal`."""
