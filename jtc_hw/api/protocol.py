"""The daemon's socket API wire format (version 2): what a request means, no I/O.

Theory of operation
-------------------
The complete specification, with an example per operation and event, is ``docs/protocol.md``.
This module only turns bytes into values, in the manner of h11: the server and the client own
the sockets. The line framing, its refusals and the error codes are :mod:`jtc_hw.api.framing`;
this module parses each message into the typed requests of :mod:`.requests`.
``Decoder.feed(data)`` takes whatever the socket gave (half a message, several messages) and
returns the requests completed by it, in order; a message that cannot be used comes back as a
``RequestError`` *value* in the same list, carrying the machine code, a message naming the
offending JSON path, and the request ``id`` when it could be read.

Beyond what the framing refuses, a request is refused for a number too large for a float64
where a number is expected, and for an unknown field (a misspelt ``time_from_start`` must not
silently become 0).

A ``send_goal`` or ``send_trajectory`` may carry its points as a binary attachment (version 2,
docs/protocol.md "Binary frames"): the framing hands over the raw bytes, and
:func:`attachment_columns` reads them with ``numpy.frombuffer`` into the same
``PointColumns`` the JSON points become, checking the header (dtype, shape against the byte
count, the columns against the joint names) and the numbers (finite, in range) as whole arrays.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from itertools import chain, compress, repeat
from operator import is_not, methodcaller
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..config.schema import join
from ..config.values import did_you_mean
from ..controller.limits_check import TIME_SCALING_MODES
from ..controller.messages import (
    NS_PER_S,
    PointColumns,
    TrajectoryPoint,
    seconds_to_ns,
)
from ..controller.tolerances import JointTolerance
from .framing import (
    ATTACHMENT_FIELDS,
    BAD_REQUEST,
    DEFAULT_MAX_MESSAGE_BYTES,
    UNKNOWN_OP,
    Attachment,
    MessageDecoder,
    RequestError,
    RequestId,
    _describe,
    gc_paused,
)
from .requests import (
    MAX_NS,
    Auth,
    CancelGoal,
    GetConfig,
    GetParameters,
    GetStatus,
    Hello,
    QueryState,
    Rearm,
    Request,
    SendGoal,
    SendTrajectory,
    SetParameters,
    SetSpeedScaling,
    Sim,
    Stop,
    SubscribeState,
    UnsubscribeState,
    WireTrajectory,
    check_end,
)

__all__ = [
    "ATTACHMENT_DTYPE", "BINARY_FIELDS", "Decoder", "MAX_JOINT_VALUE", "OPS",
    "attachment_columns", "column_names", "parse_request", "parse_trajectory",
]


MAX_JOINT_VALUE = 1e6
"""Largest magnitude of a trajectory point's value (positions in rad or m, their derivatives,
effort in N·m or N). No joint travels a thousand kilometres or a million radians; beyond this a
value is a client's bug, and values near the float64 range overflow the polynomial fit."""

_MAX_SECONDS = MAX_NS / NS_PER_S

_OP_FIELDS: dict[str, tuple[str, ...]] = {
    "hello": ("protocol_version",),
    "auth": ("token",),
    "send_goal": (
        "trajectory", "path_tolerance", "goal_tolerance", "goal_time_tolerance", "time_scaling",
        "attachment",
    ),
    "cancel_goal": ("goal_id",),
    "send_trajectory": ("trajectory", "time_scaling", "attachment"),
    "stop": (),
    "query_state": ("time_ns", "in"),
    "subscribe_state": ("commands",),
    "unsubscribe_state": (),
    "get_config": (),
    "get_status": (),
    "sim": ("component", "freeze", "fault"),
    "rearm": (),
    "get_parameters": ("names",),
    "set_parameters": ("parameters",),
    "set_speed_scaling": ("factor", "resume"),
}
OPS: tuple[str, ...] = tuple(_OP_FIELDS)
"""Every operation name, in documentation order."""

_TRAJECTORY_FIELDS = ("joint_names", "points", "start_time_ns", "start_in")
_POINT_FIELDS = ("time_from_start", "positions", "velocities", "accelerations", "effort")
_POINT_FIELD_SET = frozenset(_POINT_FIELDS)
_TOLERANCE_FIELDS = ("name", "position", "velocity", "acceleration")


def _time_scaling(f: _Fields) -> str | None:
    """The optional ``time_scaling`` field: one of ``TIME_SCALING_MODES``.

    Raises:
        RequestError: not a string, or not one of them.
    """
    if not f.has("time_scaling"):
        return None
    mode = f.string("time_scaling", f.obj["time_scaling"])
    if mode not in TIME_SCALING_MODES:
        raise f.error(
            f"'{mode}' is not one of {', '.join(repr(m) for m in TIME_SCALING_MODES)} ('fit': "
            "slow a goal beyond the joint limits down until it fits, 'reject': refuse it)"
            f"{did_you_mean(mode, TIME_SCALING_MODES)}",
            "time_scaling",
        )
    return mode


class _Fields:
    """Typed access to one JSON object's fields, errors naming the JSON path."""

    def __init__(
        self, obj: Any, path: str, where: str, known: Sequence[str], request_id: RequestId
    ) -> None:
        self.path = path
        self.where = where  # how to name the object itself: its path, or the op at top level
        self.rid = request_id
        if not isinstance(obj, dict):
            raise self.error(f"expected an object, got {_describe(obj)}", where)
        for key in obj:
            if key not in known:
                listing = ", ".join(known) if known else "none"
                raise self.error(f"unknown field '{key}'{did_you_mean(key, known)} (fields "
                                 f"here: {listing})", where)
        self.obj: dict[str, Any] = obj

    def error(self, problem: str, where: str | None = None) -> RequestError:
        return RequestError(BAD_REQUEST, f"{where or self.where}: {problem}", self.rid)

    def has(self, key: str) -> bool:
        return key in self.obj

    def required(self, key: str, what: str) -> Any:
        if key not in self.obj:
            raise self.error(f"missing required field '{key}' ({what})")
        return self.obj[key]

    def number(self, key: str, value: Any) -> float:
        return _number(value, join(self.path, key), self.rid)

    def integer(self, key: str, value: Any, low: int, high: int) -> int:
        return _integer(value, join(self.path, key), self.rid, low, high)

    def string(self, key: str, value: Any) -> str:
        if not isinstance(value, str):
            raise self.error(f"expected a string, got {_describe(value)}", join(self.path, key))
        return value

    def boolean(self, key: str, value: Any) -> bool:
        if not isinstance(value, bool):
            raise self.error(
                f"expected true or false, got {_describe(value)}", join(self.path, key)
            )
        return value

    def array(self, key: str, value: Any) -> list[Any]:
        if not isinstance(value, list):
            raise self.error(f"expected an array, got {_describe(value)}", join(self.path, key))
        return value


def _number(value: Any, path: str, rid: RequestId) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RequestError(BAD_REQUEST, f"{path}: expected a number, got {_describe(value)}", rid)
    try:
        result = float(value)
    except OverflowError:
        result = math.inf
    if not math.isfinite(result):
        raise RequestError(
            BAD_REQUEST, f"{path}: {_describe(value)} is out of the range of a float64", rid
        )
    return result


def _integer(value: Any, path: str, rid: RequestId, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        hint = " (write it without a fraction or exponent)" if isinstance(value, float) else ""
        raise RequestError(
            BAD_REQUEST, f"{path}: expected an integer, got {_describe(value)}{hint}", rid
        )
    if not low <= value <= high:
        raise RequestError(
            BAD_REQUEST, f"{path}: {value} is out of range; expected {low}..{high}", rid
        )
    return value


def _seconds(value: Any, path: str, rid: RequestId) -> float:
    seconds = _number(value, path, rid)
    if abs(seconds) > _MAX_SECONDS:
        raise RequestError(
            BAD_REQUEST,
            f"{path}: {seconds!r} s is out of range; expected at most {_MAX_SECONDS:.6g} s "
            "in magnitude",
            rid,
        )
    return seconds


def _ns(seconds: float, path: str, rid: RequestId) -> int:
    """``seconds`` in integer nanoseconds, which must fit an int64.

    Raises:
        RequestError: ``bad_request`` naming ``path``.
    """
    ns = seconds_to_ns(seconds)
    if not -MAX_NS <= ns <= MAX_NS:
        raise RequestError(
            BAD_REQUEST,
            f"{path}: {seconds!r} s is {ns} ns, beyond the protocol's int64 nanoseconds "
            f"(at most {MAX_NS} ns in magnitude, about 292 years)",
            rid,
        )
    return ns


def _vector(
    value: Any, path: str, rid: RequestId, joint_names: Sequence[str] = ()
) -> tuple[float, ...]:
    if not isinstance(value, list):
        raise RequestError(
            BAD_REQUEST, f"{path}: expected an array of numbers, got {_describe(value)}", rid
        )
    out = tuple(_number(v, f"{path}[{i}]", rid) for i, v in enumerate(value))
    for i, v in enumerate(out):
        if abs(v) > MAX_JOINT_VALUE:
            joint = f" (joint '{joint_names[i]}')" if i < len(joint_names) else ""
            raise RequestError(
                BAD_REQUEST,
                f"{path}[{i}]{joint}: {v!r} is out of range; a joint value must be at most "
                f"{MAX_JOINT_VALUE:g} in magnitude (SI units: rad or m, per s, per s^2; N m or N)",
                rid,
            )
    return out


def parse_trajectory(
    obj: Any,
    path: str = "trajectory",
    request_id: RequestId = None,
    attachment: Attachment | None = None,
) -> WireTrajectory:
    """Check a trajectory object's shape and types (content is the controller's business).

    With an ``attachment`` (a binary frame's), the points are its columns and the object has
    no ``points``.

    Raises:
        RequestError: ``bad_request`` naming the JSON path of the first problem.
    """
    f = _Fields(obj, path, path, _TRAJECTORY_FIELDS, request_id)
    names_raw = f.array("joint_names", f.required("joint_names", "array of joint names"))
    names = tuple(f.string(f"joint_names[{i}]", n) for i, n in enumerate(names_raw))
    points: Sequence[TrajectoryPoint] | None
    if attachment is not None:
        if f.has("points"):
            raise f.error("the points are in the attachment: leave 'points' out", "points")
        points = attachment_columns(attachment, names, request_id)
    else:
        points_raw = f.array("points", f.required("points", "array of points; empty means stop"))
        points = _point_columns(points_raw)
        if points is None:  # irregular, or a problem to name: point by point
            with gc_paused(len(points_raw) >= _MANY_POINTS):  # an object or more per point
                points = tuple(
                    _parse_point(p, f"{path}.points[{i}]", request_id, names)
                    for i, p in enumerate(points_raw)
                )
    start_time_ns: int | None = None
    start_in: float | None = None
    if f.has("start_time_ns") and f.has("start_in"):
        raise f.error(
            "'start_time_ns' (absolute daemon clock) and 'start_in' (seconds from now) are "
            "mutually exclusive; give at most one"
        )
    if f.has("start_time_ns"):
        start_time_ns = f.integer("start_time_ns", f.obj["start_time_ns"], 0, MAX_NS)
        try:
            check_end(points, start_time_ns, join(path, "points"))
        except RequestError as exc:
            exc.request_id = request_id
            raise
    if f.has("start_in"):
        start_in = _seconds(f.obj["start_in"], join(path, "start_in"), request_id)
    return WireTrajectory(names, points, start_time_ns, start_in)


ATTACHMENT_DTYPE = "<f8"
"""The one ``dtype`` an attachment may have: little-endian IEEE 754 float64."""
BINARY_FIELDS = _POINT_FIELDS[1:]
"""The per-joint fields an attachment may carry, in the order its columns must have them."""


def column_names(joint_names: Sequence[str], fields: Sequence[str]) -> list[str]:
    """An attachment's columns: ``time_from_start``, then ``<field>.<joint>`` for each field
    given (in :data:`BINARY_FIELDS` order) and each joint (in ``joint_names`` order)."""
    return ["time_from_start", *(f"{f}.{j}" for f in fields for j in joint_names)]


def _attachment_error(problem: str, rid: RequestId) -> RequestError:
    return RequestError(BAD_REQUEST, f"attachment{problem}; the request was not executed", rid)


def _attachment_fields(
    columns: list[str], names: Sequence[str], rid: RequestId
) -> list[str]:
    """The fields ``columns`` carry, checked against :func:`column_names`.

    Raises:
        RequestError: ``bad_request`` naming the first column that is not the expected one.
    """
    fields: list[str] = []
    i, k = 1, len(names)
    while i < len(columns):
        field = columns[i].split(".", 1)[0]
        later = BINARY_FIELDS[BINARY_FIELDS.index(fields[-1]) + 1 :] if fields else BINARY_FIELDS
        if field not in later or not k:
            choices = ", ".join(f"'{f}.<joint>'" for f in later) if k else "none (no joints)"
            raise _attachment_error(
                f".columns[{i}]: {json.dumps(columns[i])} is not a column here; expected one "
                f"of {choices} (time_from_start, then positions, velocities, accelerations, "
                "effort as present, one column per joint in joint_names order)", rid)
        want = column_names(names, [field])[1:]
        for j, (got, expected) in enumerate(zip(columns[i : i + k], want, strict=False)):
            if got != expected:
                raise _attachment_error(
                    f".columns[{i + j}]: expected {json.dumps(expected)} (joint_names[{j}] "
                    f"is {json.dumps(names[j])}), got {json.dumps(got)}", rid)
        if len(columns) < i + k:
            raise _attachment_error(
                f".columns: '{field}' has {len(columns) - i} column(s), expected one per "
                f"joint ({k})", rid)
        fields.append(field)
        i += k
    return fields


def _attachment_shape(header: dict[str, Any], size: int, rid: RequestId) -> tuple[int, int]:
    """The header's ``(points, columns)``, checked against its dtype, columns and ``size``."""
    for key in header:
        if key not in ATTACHMENT_FIELDS:
            raise _attachment_error(
                f": unknown field '{key}'{did_you_mean(key, ATTACHMENT_FIELDS)} (fields here: "
                f"{', '.join(ATTACHMENT_FIELDS)})", rid)
    for key in ATTACHMENT_FIELDS[1:]:
        if key not in header:
            raise _attachment_error(f": missing required field '{key}'", rid)
    dtype = header["dtype"]
    if dtype != ATTACHMENT_DTYPE:
        raise _attachment_error(
            f".dtype: {_describe(dtype)} is not supported; the only dtype is "
            f'"{ATTACHMENT_DTYPE}" (little-endian float64)', rid)
    shape, columns = header["shape"], header["columns"]
    if not (isinstance(shape, list) and len(shape) == 2 and all(
            type(n) is int and n >= 0 for n in shape)):
        raise _attachment_error(
            f".shape: expected [points, columns], two integers >= 0, got {_describe(shape)}"
            f"{' ' + json.dumps(shape) if isinstance(shape, list) else ''}", rid)
    if not isinstance(columns, list) or not all(isinstance(c, str) for c in columns):
        raise _attachment_error(
            f".columns: expected an array of strings, got {_describe(columns)}", rid)
    m, c = shape
    if c != len(columns):
        raise _attachment_error(
            f".shape: {c} columns, but 'columns' names {len(columns)}", rid)
    if not columns or columns[0] != "time_from_start":
        raise _attachment_error(".columns[0]: the first column must be \"time_from_start\"", rid)
    if m * c * 8 != size:
        raise _attachment_error(
            f".shape: [{m}, {c}] of {ATTACHMENT_DTYPE} is {m * c * 8} bytes, the attachment "
            f"has {size} (attachment.bytes)", rid)
    return m, c


def attachment_columns(
    attachment: Attachment, names: Sequence[str], rid: RequestId = None
) -> PointColumns:
    """A binary frame's points (docs/protocol.md, "Binary frames"), read with
    ``numpy.frombuffer``: no Python object per number.

    Raises:
        RequestError: ``bad_request``, one per problem: a field of the header unknown or
            missing, a dtype other than ``"<f8"``, a shape that does not match the bytes or
            the columns, columns that do not match ``names``, a number that is not finite or
            out of range (naming the point and the column).
    """
    m, c = _attachment_shape(attachment.header, len(attachment.data), rid)
    columns: list[str] = attachment.header["columns"]
    fields = _attachment_fields(columns, names, rid)
    values = np.frombuffer(attachment.data, dtype=ATTACHMENT_DTYPE).reshape(m, c)
    bad = ~np.isfinite(values)
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise _attachment_error(
            f": point {row}, column {json.dumps(columns[col])}: {float(values[row, col])!r} "
            "is not a finite number (NaN and infinities are refused)", rid)
    times = values[:, 0]
    ns_float = np.rint(times * NS_PER_S)  # as seconds_to_ns: rounded half to even
    over = (np.abs(times) > _MAX_SECONDS) | (np.abs(ns_float) >= 2.0**63)
    if over.any():
        row = int(over.argmax())
        raise _attachment_error(
            f": point {row}, time_from_start: {float(times[row])!r} s is out of range; expected at "
            f"most {_MAX_SECONDS:.6g} s in magnitude", rid)
    joints = values[:, 1:]
    over = np.abs(joints) > MAX_JOINT_VALUE
    if over.any():
        row, col = (int(i) for i in np.argwhere(over)[0])
        raise _attachment_error(
            f": point {row}, column {json.dumps(columns[col + 1])}: "
            f"{float(joints[row, col])!r} is out of range; a joint value must be at most "
            f"{MAX_JOINT_VALUE:g} in magnitude", rid)
    ns = ns_float.astype(np.int64)
    k = len(names)
    arrays: dict[str, NDArray[np.float64]] = {
        f: values[:, 1 + j * k : 1 + (j + 1) * k] for j, f in enumerate(fields)}
    return PointColumns(ns, present=None, **arrays)


_MISSING = object()
_MANY_POINTS = 1000
_NUMBERS = frozenset({float, int})
_DICT_ONLY = frozenset({dict})
_LIST_ONLY = frozenset({list})


def _point_columns(points: list[Any]) -> PointColumns | None:
    """The points as arrays, when every one is well-formed and regular: objects with known
    fields, a number of seconds that fits int64 nanoseconds, and arrays of finite numbers
    within ``MAX_JOINT_VALUE``, of one length per field.

    Whole-array checks instead of one Python call per value: a 2,000-point goal took 13 ms
    point by point. None means "walk the points": they may be valid yet irregular (arrays of
    different lengths, for the controller to refuse with its own message), or hold a problem
    that ``_parse_point`` names with its JSON path. Either way the result is the same as the
    point-by-point parse's (``tests/api/test_protocol_columns.py``).
    """
    m = len(points)
    if not m or not _DICT_ONLY.issuperset(map(type, points)):
        return None
    keys = set(chain.from_iterable(points))
    if not _POINT_FIELD_SET.issuperset(keys):
        return None
    seconds = list(map(methodcaller("get", "time_from_start", _MISSING), points))
    kinds = set(map(type, seconds))
    if not _NUMBERS.issuperset(kinds):  # missing, bool, or not a number
        return None
    try:
        times = np.array(seconds, dtype=np.float64)
    except OverflowError:
        return None
    if not (np.abs(times) <= _MAX_SECONDS).all():
        return None
    # As seconds_to_ns: integers exactly, floats rounded (half to even) to the nanosecond.
    # Beyond int64 (MAX_NS) the point-by-point parse names the point; 2**63 - 1024 is the
    # largest float below 2**63, and -2**63 itself is out of the protocol's range too.
    times_ns = np.rint(times * NS_PER_S)
    if not (np.abs(times_ns) < 2.0**63).all():
        return None
    ns = times_ns.astype(np.int64)
    if int in kinds:
        at = [i for i, s in enumerate(seconds) if type(s) is int]
        ns[at] = np.array([seconds[i] for i in at], dtype=np.int64) * NS_PER_S
    arrays: dict[str, NDArray[np.float64]] = {}
    present: dict[str, NDArray[np.bool_]] = {}
    for name in _POINT_FIELDS[1:]:
        if name not in keys:  # no point carries it
            continue
        column = list(map(methodcaller("get", name, _MISSING), points))
        mask = np.fromiter(map(is_not, column, repeat(_MISSING)), dtype=np.bool_, count=m)
        given = column if mask.all() else list(compress(column, mask.tolist()))
        if not _LIST_ONLY.issuperset(map(type, given)):  # null, or not an array
            return None
        lengths = set(map(len, given))
        if len(lengths) != 1:  # mixed lengths: for the controller to refuse, or a problem
            return None
        (k,) = lengths
        if not k:  # empty arrays (absent fields)
            return None
        if not _NUMBERS.issuperset(map(type, chain.from_iterable(given))):
            return None
        try:
            flat = np.fromiter(chain.from_iterable(given), dtype=np.float64, count=len(given) * k)
        except (ValueError, OverflowError):  # an integer beyond float64
            return None
        values = flat.reshape(len(given), k)
        if not (np.abs(values) <= MAX_JOINT_VALUE).all():
            return None  # out of range, or not finite (1e999): named point by point
        if len(given) == m:
            arrays[name] = values
        else:
            full = np.zeros((m, values.shape[1]))
            full[mask] = values
            arrays[name] = full
        present[name] = mask
    return PointColumns(ns, present=present, **arrays)


def _parse_point(
    obj: Any, path: str, rid: RequestId, joint_names: Sequence[str]
) -> TrajectoryPoint:
    f = _Fields(obj, path, path, _POINT_FIELDS, rid)
    where = join(path, "time_from_start")
    t = _seconds(f.required("time_from_start", "seconds after the trajectory's start"), where, rid)
    t_ns = _ns(t, where, rid)
    values = {
        name: _vector(f.obj[name], join(path, name), rid, joint_names) if f.has(name) else None
        for name in _POINT_FIELDS[1:]
    }
    return TrajectoryPoint(
        time_from_start_ns=t_ns,
        positions=values["positions"],
        velocities=values["velocities"],
        accelerations=values["accelerations"],
        effort=values["effort"],
    )


def _parse_tolerances(value: Any, path: str, rid: RequestId) -> tuple[JointTolerance, ...]:
    if not isinstance(value, list):
        raise RequestError(
            BAD_REQUEST,
            f'{path}: expected an array of {{"name", "position", "velocity", '
            f'"acceleration"}} objects, got {_describe(value)}',
            rid,
        )
    out = []
    for i, item in enumerate(value):
        where = f"{path}[{i}]"
        f = _Fields(item, where, where, _TOLERANCE_FIELDS, rid)
        name = f.string("name", f.required("name", "the joint's name"))
        numbers = {k: f.number(k, f.obj[k]) if f.has(k) else 0.0 for k in _TOLERANCE_FIELDS[1:]}
        out.append(JointTolerance(name, **numbers))
    return tuple(out)


def _attachment(f: _Fields) -> Attachment | None:
    """The request's binary attachment, if it has one.

    Raises:
        RequestError: ``attachment`` is there but is no binary frame's (a JSON object where
            the transport carries no raw bytes).
    """
    if not f.has("attachment"):
        return None
    value = f.obj["attachment"]
    if not isinstance(value, Attachment):
        raise f.error(
            "an attachment header is only valid on a binary frame, followed by its raw bytes "
            "(docs/protocol.md, \"Binary frames\")", "attachment")
    return value


def _request_id(obj: dict[str, Any]) -> RequestId:
    rid = obj.get("id")
    if rid is None or isinstance(rid, str) or (isinstance(rid, int) and not isinstance(rid, bool)):
        return rid
    raise RequestError(
        BAD_REQUEST, f"id: expected an integer or a string, got {_describe(rid)}", None
    )


def parse_request(obj: Any) -> Request:
    """Turn one decoded JSON value into a typed request.

    Raises:
        RequestError: ``bad_request`` (not an object, missing or mistyped field, unknown
            field) or ``unknown_op``; carries the request ``id`` when it was readable.
    """
    if not isinstance(obj, dict):
        raise RequestError(
            BAD_REQUEST, f"a request must be a JSON object, got {_describe(obj)}", None
        )
    rid = _request_id(obj)
    if "op" not in obj:
        raise RequestError(
            BAD_REQUEST, f"missing required field 'op' (one of: {', '.join(OPS)})", rid
        )
    op = obj["op"]
    if not isinstance(op, str):
        raise RequestError(BAD_REQUEST, f"op: expected a string, got {_describe(op)}", rid)
    if op not in _OP_FIELDS:
        raise RequestError(
            UNKNOWN_OP, f"unknown op '{op}'{did_you_mean(op, OPS)} (ops: {', '.join(OPS)})", rid
        )
    f = _Fields(obj, "", op, ("id", "op", *_OP_FIELDS[op]), rid)
    o = f.obj
    if op == "hello":
        version = None
        if f.has("protocol_version"):
            version = f.integer("protocol_version", o["protocol_version"], 0, 2**31 - 1)
        return Hello(rid, version)
    if op == "auth":
        return Auth(rid, f.string("token", f.required("token", "the daemon's TCP token")))
    if op == "send_goal":
        traj = parse_trajectory(
            f.required("trajectory", "the trajectory to execute"), "trajectory", rid,
            _attachment(f),
        )
        path_tol = _parse_tolerances(o.get("path_tolerance", []), "path_tolerance", rid)
        goal_tol = _parse_tolerances(o.get("goal_tolerance", []), "goal_tolerance", rid)
        gtt = _seconds(o.get("goal_time_tolerance", 0.0), "goal_time_tolerance", rid)
        _ns(gtt, "goal_time_tolerance", rid)
        return SendGoal(rid, traj, path_tol, goal_tol, gtt, _time_scaling(f))
    if op == "subscribe_state":
        return SubscribeState(rid, f.has("commands") and f.boolean("commands", o["commands"]))
    if op == "cancel_goal":
        goal_id = f.integer("goal_id", f.required("goal_id", "the goal to cancel"), 0, MAX_NS)
        return CancelGoal(rid, goal_id)
    if op == "send_trajectory":
        traj = parse_trajectory(
            f.required("trajectory", "the trajectory; no points means stop"), "trajectory", rid,
            _attachment(f),
        )
        return SendTrajectory(rid, traj, _time_scaling(f))
    if op == "query_state":
        if f.has("time_ns") == f.has("in"):
            raise f.error(
                "give exactly one of 'time_ns' (absolute daemon clock, ns) or 'in' "
                f"(seconds from now){'; both were given' if f.has('in') else ''}"
            )
        if f.has("time_ns"):
            return QueryState(rid, time_ns=f.integer("time_ns", o["time_ns"], 0, MAX_NS))
        return QueryState(rid, in_s=_seconds(o["in"], "in", rid))
    if op == "sim":
        component = f.string("component", f.required("component", "the simulated component"))
        fault = f.string("fault", o["fault"]) if f.has("fault") else None
        if fault is not None and not fault.strip():
            raise f.error("must not be empty (it is the fault's message)", "fault")
        freeze: bool | None = None
        if fault is None or f.has("freeze"):
            freeze = f.boolean("freeze", f.required("freeze", "true to freeze its feedback"))
        return Sim(rid, component, freeze, fault)
    if op == "get_parameters":
        if not f.has("names"):
            return GetParameters(rid)
        names = tuple(
            f.string(f"names[{i}]", name) for i, name in enumerate(f.array("names", o["names"]))
        )
        if not names:
            raise f.error("give at least one name, or leave 'names' out for all", "names")
        return GetParameters(rid, names)
    if op == "set_parameters":
        changes = f.required("parameters", "new values by name, e.g. {\"gains.j1.p\": 10.0}")
        if not isinstance(changes, dict) or not changes:
            raise f.error(
                f"expected a non-empty object of new values by name, got {_describe(changes)}",
                "parameters",
            )
        return SetParameters(rid, dict(changes))
    if op == "set_speed_scaling":
        resume = f.has("resume") and f.boolean("resume", o["resume"])
        if f.has("factor") == resume:
            raise f.error(
                "give exactly one of 'factor' (a number in [0, 1]: 1 full speed, 0.5 half, "
                f"0 pause) or 'resume': true{'; both were given' if resume else ''}"
            )
        if resume:
            return SetSpeedScaling(rid, None, True)
        factor = f.number("factor", o["factor"])
        if factor < 0.0:
            raise f.error(
                f"must be in [0, 1] (1: full speed, 0: pause; up to "
                f"speed_scaling.max_scaling_factor where the daemon's configuration raises it), "
                f"got {factor!r}",
                "factor",
            )
        return SetSpeedScaling(rid, factor)
    simple: dict[str, type[Request]] = {
        "stop": Stop,
        "unsubscribe_state": UnsubscribeState,
        "get_config": GetConfig,
        "get_status": GetStatus,
        "rearm": Rearm,
    }
    return simple[op](rid)


class Decoder:
    """Requests from a client's byte stream (the server side of the protocol).

    Example::

        decoder = Decoder()
        for item in decoder.feed(data):
            if isinstance(item, RequestError):
                send(encode(item.reply()))
            else:
                handle(item)

    Args:
        max_message_bytes: longest accepted request line, without its newline.
    """

    def __init__(self, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> None:
        self._messages = MessageDecoder(max_message_bytes)

    def feed(self, data: bytes) -> list[Request | RequestError]:
        """Requests completed by ``data``, in order; unusable ones as ``RequestError`` values
        (it never raises)."""
        return [self._parse(item) for item in self._messages.feed(data)]

    def decode_cost(self, data: bytes) -> int:
        """What :meth:`feed` of ``data`` costs, about, in bytes of JSON decoded
        (``MessageDecoder.decode_cost``)."""
        return self._messages.decode_cost(data)

    def end(self) -> list[Request | RequestError]:
        """Call at end of input. A last request without its newline is never parsed nor
        executed (it may be cut off): it comes back as one ``bad_json`` error (it never raises).
        """
        return [self._parse(item) for item in self._messages.end()]

    @staticmethod
    def _parse(item: dict[str, Any] | RequestError) -> Request | RequestError:
        if isinstance(item, RequestError):
            return item
        try:
            return parse_request(item)
        except RequestError as exc:
            return exc
