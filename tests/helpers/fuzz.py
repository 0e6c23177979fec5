"""Random and mutated request lines covering every operation of ``docs/protocol.md``.

Shared by the in-process fuzz test (``tests/daemon/test_fuzz_protocol.py``, the real ``Server``
on the stand-in backend) and ``bench/fuzz_protocol.py`` (100,000 lines against a real daemon).
Each line is one complete, non-blank message ending with ``\\n``, so the protocol owes it
exactly one reply; the fuzz checks that each gets one, in order, and that none is ``internal``.

A line is built from a plausible request of a random op and then, at random, left as it is,
given wrong or extreme values (types, surrogate escapes, times at and beyond int64, positions
near the float64 range, unknown or missing fields), mutated byte by byte, or replaced by a
known troublemaker (``NaN`` tokens, duplicate keys, deep nesting, huge integers, non-objects,
over-long lines). Speed factors out of range (above ``max_scaling_factor``, 1e308, negative,
NaN and infinity tokens, huge integers, strings) and parameter changes of every family of the
schema (top level, ``constraints``, per joint constraints and gains, ``limits``,
``speed_scaling``) with huge, NaN, negative and ill-typed values are among them (issue 21).
"""

from __future__ import annotations

import json
import random
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from jtc_hw.api.protocol import OPS
from jtc_hw.config.controller import (
    CONSTRAINT_PARAMETERS,
    GAIN_PARAMETERS,
    JOINT_CONSTRAINT_PARAMETERS,
    LIMITS_PARAMETERS,
    PARAMETERS,
    SPEED_SCALING_PARAMETERS,
)

MAX_NS = 2**63 - 1

# Values at the edges of every type a field may hold (or wrongly be given).
EDGE_INTS = [0, 1, -1, 7, 2**31 - 1, 2**31, 2**53 + 1, MAX_NS - 1, MAX_NS, MAX_NS + 1, -MAX_NS,
             -(2**63) - 1, 10**30]
EDGE_FLOATS = [0.0, -0.0, 1e-9, 5e-324, 0.5, -0.5, 1.0, 3.0, 1e6, -1e6, 1e6 + 1, 1e9, 1e12,
               9223372036.854776, 9223372036.0, 1e18, 1e300, 1e308, -1e308, 1.7976931348623157e308]
EDGE_STRINGS = ["", " ", "j1", "joint1", "mirror", "arm", "\ud800", "x\udc00y", "\ud83d\ude00",
                "é", "\u0000", "\n", "\\", '"', "a" * 300, "\u202e", "NaN", "null"]
# Speed factors outside [0, max_scaling_factor] or not numbers.
BAD_FACTORS = [1e308, -1e308, 1.7976931348623157e308, -1, -0.5, -5e-324, 1.5, 10.0, 10.000001,
               1e6, 10**30, 2**63, 2**64, -(2**64), 10**400, "1", "nan", "inf", "", None, [],
               {}, True, [1.0]]
# Parameter values out of every range, or of the wrong type.
BAD_PARAMETER_VALUES = [1e308, -1e308, 5e-324, -5e-324, -1, -1e-9, 0, 10**30, 2**64, -(2**64),
                        10**400, "x", "", "nan", "1.0", [], ["j1"], ["j1", "j1"], {},
                        {"a": 1}, None, True, False]
# Raw JSON text that Python's json reads but the protocol refuses, or that stresses the parser.
TROUBLE = [
    b'{"op": "set_speed_scaling", "id": 1, "factor": NaN}',
    b'{"op": "set_speed_scaling", "id": 1, "factor": Infinity}',
    b'{"op": "set_speed_scaling", "id": 1, "factor": -Infinity}',
    b'{"op": "set_speed_scaling", "id": 1, "factor": 1e400}',
    b'{"op": "set_speed_scaling", "id": 1, "factor": ' + b"9" * 400 + b"}",
    b'{"op": "set_parameters", "id": 1, "parameters": {"gains.joint1.p": NaN}}',
    b'{"op": "set_parameters", "id": 1, "parameters": {"constraints.goal_time": Infinity}}',
    b'{"op": "set_parameters", "id": 1, "parameters": {"speed_scaling.ramp_time": 1e400}}',
    b'{"op": "set_parameters", "id": 1, "parameters": {"state_publish_rate": -Infinity}}',
    b'{"op": "hello", "id": NaN}',
    b'{"op": "query_state", "in": Infinity}',
    b'{"op": "query_state", "in": -Infinity}',
    b'{"op": "hello", "op": "get_status"}',
    b'{"op": "cancel_goal", "goal_id": ' + b"9" * 5000 + b"}",
    b'{"op": "query_state", "in": 1e400}',
    b"[" * 5000 + b"]" * 5000,
    b'{"a":' * 3000 + b"1" + b"}" * 3000,
    b'"just a string"',
    b"[1, 2, 3]",
    b"42",
    b"null",
    b"{",
    b"}",
    b'{"op": "hello"',
    b'{"op": "\\ud800"}',
    b'{"\\udfff": 1, "op": "hello"}',
    b'{"op": "hello", "id": "\\ud800\\ud800"}',
    b'{"op": "sim", "component": "mirror", "fault": "\\udc00"}',
    b'{"op": "hello", "id": "\\ud83d\\ude00"}',
    b"\xff\xfe{}",
    b'{"op": "hello", "id": "\xc3\x28"}',
    b'{"op": "stop", "id": 1}\r',
]


@dataclass(frozen=True)
class Line:
    """One message to send.

    Attributes:
        data: the bytes, ending with exactly one newline (a binary frame: its line, raw bytes
            and newline; one that ``closes`` may end anywhere).
        op: the op it was made from.
        request_id: the id the reply must echo, when the line is certain to carry it to the
            server readably (an unmutated object with an integer id, not over-long).
        closes: a binary frame that cannot be trusted: its one reply is ``bad_frame`` and the
            daemon then closes the connection. The sender ends its writing after it (a frame
            cut short or announcing more bytes than follow is told by the end of the stream),
            and the next line goes on a new connection (:func:`segments`).
        binary: a binary frame (protocol version 2).
    """

    data: bytes
    op: str
    request_id: int | None
    closes: bool = False
    binary: bool = False


def segments(lines: Sequence[Line]) -> list[list[Line]]:
    """``lines`` cut after each one that ``closes``: what goes on one connection."""
    out: list[list[Line]] = [[]]
    for line in lines:
        out[-1].append(line)
        if line.closes:
            out.append([])
    return [segment for segment in out if segment]


class Fuzzer:
    """Lines of random requests for a daemon with ``joint_names`` and ``components``.

    Args:
        seed: the random seed (a failure names it, so it can be replayed).
        joint_names: the controller's joints (most trajectories use them).
        components: names for ``sim`` (simulated components, and others).
        max_message_bytes: the daemon's line limit; a few lines are made longer than it.
        binary: the share of lines that are binary frames (:meth:`frame`).
    """

    def __init__(
        self,
        seed: int,
        joint_names: Sequence[str],
        components: Sequence[str] = ("mirror",),
        max_message_bytes: int = 65536,
        binary: float = 0.0,
    ) -> None:
        self.binary = binary
        self.random = random.Random(seed)
        self.joints = list(joint_names)
        self.components = list(components)
        self.max_message_bytes = max_message_bytes
        self.ids = 0

    # -- values -------------------------------------------------------------------------------

    def any_value(self, depth: int = 0) -> Any:
        r = self.random
        kind = r.randrange(8 if depth < 3 else 5)
        if kind == 0:
            return r.choice(EDGE_INTS)
        if kind == 1:
            return r.choice(EDGE_FLOATS)
        if kind == 2:
            return r.choice(EDGE_STRINGS)
        if kind == 3:
            return r.choice([True, False, None])
        if kind == 4:
            return r.uniform(-10, 10)
        if kind == 5:
            return [self.any_value(depth + 1) for _ in range(r.randrange(4))]
        if kind == 6:
            return {r.choice(EDGE_STRINGS + ["op", "id", "x"]): self.any_value(depth + 1)
                    for _ in range(r.randrange(3))}
        return r.randrange(-5, 100)

    def number(self) -> Any:
        r = self.random
        roll = r.random()
        if roll < 0.7:
            return round(r.uniform(-1.5, 1.5), 4)
        if roll < 0.9:
            return r.choice(EDGE_FLOATS + [-x for x in EDGE_FLOATS] + EDGE_INTS)
        return self.any_value()

    def seconds(self) -> Any:
        r = self.random
        roll = r.random()
        if roll < 0.75:
            return round(r.uniform(0.05, 2.0), 3)
        if roll < 0.95:
            return r.choice(EDGE_FLOATS + [-1.0, -1e-9] + EDGE_INTS)
        return self.any_value()

    def names(self) -> Any:
        r = self.random
        roll = r.random()
        if roll < 0.75:
            return list(self.joints)
        if roll < 0.85:
            names = list(self.joints)
            r.shuffle(names)
            return names[: r.randrange(len(names) + 1)]
        if roll < 0.95:
            return [r.choice(EDGE_STRINGS + self.joints) for _ in range(r.randrange(4))]
        return self.any_value()

    def vector(self, n: int) -> Any:
        r = self.random
        if r.random() < 0.9:
            return [self.number() for _ in range(n if r.random() < 0.9 else r.randrange(n + 2))]
        return self.any_value()

    # -- structures ---------------------------------------------------------------------------

    def trajectory(self) -> Any:
        r = self.random
        if r.random() < 0.03:
            return self.any_value()
        names = self.names()
        n = len(names) if isinstance(names, list) else len(self.joints)
        points = []
        clock = 0.0
        for _ in range(r.choice([0, 1, 1, 2, 3, 5])):
            clock += r.uniform(0.05, 1.0)
            t = round(clock, 4) if r.random() < 0.9 else self.seconds()
            point: dict[str, Any] = {"time_from_start": t}
            for field in ("positions", "velocities", "accelerations", "effort"):
                if r.random() < (0.9 if field == "positions" else 0.3):
                    point[field] = self.vector(n)
            if r.random() < 0.03:
                point[r.choice(["time_form_start", "position", "x"])] = self.any_value()
            if r.random() < 0.03:
                point.pop("time_from_start")
            points.append(point)
        traj: dict[str, Any] = {"joint_names": names, "points": points}
        roll = r.random()
        if roll < 0.1:
            traj["start_time_ns"] = r.choice(EDGE_INTS + [r.randrange(0, 10**12)])
        elif roll < 0.25:
            traj["start_in"] = self.seconds() if r.random() < 0.5 else r.uniform(-1, 1)
        elif roll < 0.27:
            traj["start_time_ns"], traj["start_in"] = 0, 0.0
        return traj

    def tolerances(self) -> Any:
        r = self.random
        if r.random() < 0.05:
            return self.any_value()
        out = []
        for _ in range(r.randrange(3)):
            item: dict[str, Any] = {"name": r.choice(self.joints + EDGE_STRINGS)}
            for key in ("position", "velocity", "acceleration"):
                if r.random() < 0.5:
                    item[key] = r.choice([0.0, -1.0, 0.05, 1.0]) if r.random() < 0.7 else (
                        self.number()
                    )
            out.append(item)
        return out

    def request(self, op: str) -> dict[str, Any]:
        """A plausible request of ``op`` (sometimes with an odd value)."""
        r = self.random
        fields: dict[str, Any] = {}
        if op == "hello":
            if r.random() < 0.5:
                fields["protocol_version"] = r.choice([1, 1, 0, 2, -1, 2**40, "1", None])
        elif op == "auth":
            fields["token"] = r.choice(["0123456789abcdef", "", "\ud800"] + EDGE_STRINGS[:3])
        elif op == "send_goal":
            fields["trajectory"] = self.trajectory()
            if r.random() < 0.3:
                fields["path_tolerance"] = self.tolerances()
            if r.random() < 0.3:
                fields["goal_tolerance"] = self.tolerances()
            if r.random() < 0.2:
                fields["goal_time_tolerance"] = self.seconds()
        elif op == "cancel_goal":
            fields["goal_id"] = r.choice([r.randrange(1, 50), 0, -1, MAX_NS, MAX_NS + 1, "1"])
        elif op == "send_trajectory":
            traj = self.trajectory()
            if r.random() < 0.2:
                traj = {"joint_names": [], "points": []}
            fields["trajectory"] = traj
        elif op == "query_state":
            roll = r.random()
            if roll < 0.45:
                fields["in"] = self.seconds() if r.random() < 0.5 else r.uniform(-1, 1)
            elif roll < 0.9:
                fields["time_ns"] = r.choice(EDGE_INTS + [r.randrange(0, 10**13)])
            elif roll < 0.95:
                fields["in"], fields["time_ns"] = 0.0, 0
        elif op == "sim":
            fields["component"] = r.choice(self.components + EDGE_STRINGS[:8])
            roll = r.random()
            if roll < 0.6:
                fields["freeze"] = r.random() < 0.2  # mostly releasing: keep goals possible
            elif roll < 0.7:
                fields["fault"] = r.choice(["test fault", "", " ", "\u00e9t\u00e9", "x" * 200])
            elif roll < 0.8:
                fields["fault"], fields["freeze"] = "test fault", False
        elif op == "get_parameters":
            if r.random() < 0.6:
                fields["names"] = r.choice([
                    [self.parameter_name()],
                    [self.parameter_name() for _ in range(r.randrange(4))],
                    self.any_value(),
                ])
        elif op == "set_parameters":
            roll = r.random()
            if roll < 0.9:
                fields["parameters"] = {
                    self.parameter_name(): self.parameter_value() for _ in range(r.randrange(4))
                }
            elif roll < 0.95:
                fields["parameters"] = self.any_value()
        elif op == "set_speed_scaling":
            roll = r.random()
            if roll < 0.5:  # mostly near full speed: keep goals finishing
                fields["factor"] = r.choice([1.0, 1.0, 0.8, 1.0, 0.0, 0.5])
            elif roll < 0.6:
                fields["factor"] = r.choice(BAD_FACTORS)
            elif roll < 0.8:
                fields["resume"] = r.choice([True, True, False, "true", 1])
            elif roll < 0.9:
                fields["factor"], fields["resume"] = 1.0, True
            else:
                fields["factor"] = self.number()
        return {"op": op, **fields}

    def parameter_name(self) -> Any:
        r = self.random
        joint = r.choice(self.joints + EDGE_STRINGS[:6])
        if r.random() < 0.5:  # any parameter of any family of the schema
            return r.choice([
                *PARAMETERS,
                *(f"constraints.{name}" for name in CONSTRAINT_PARAMETERS),
                *(f"constraints.{joint}.{name}" for name in JOINT_CONSTRAINT_PARAMETERS),
                *(f"gains.{joint}.{name}" for name in GAIN_PARAMETERS),
                *(f"limits.{name}" for name in LIMITS_PARAMETERS),
                *(f"speed_scaling.{name}" for name in SPEED_SCALING_PARAMETERS),
            ])
        return r.choice([
            "cmd_timeout", "constraints.goal_time", "constraints.stopped_velocity_tolerance",
            f"constraints.{joint}.goal", f"constraints.{joint}.trajectory",
            f"gains.{joint}.p", f"gains.{joint}.i_clamp", "allow_partial_joints_goal",
            "state_publish_rate", "joints", "update_rate", "interpolation_method",
            "gains", f"gains.{joint}", "constraints.", f"limits.{joint}.velocity",
            "speed_scaling.max_scaling_factor", r.choice(EDGE_STRINGS),
        ])

    def parameter_value(self) -> Any:
        r = self.random
        roll = r.random()
        if roll < 0.6:  # mostly loose tolerances and small values: goals keep succeeding
            return r.choice([0.0, 0.5, 1.0, 2.0, 10.0, True, False])
        if roll < 0.8:
            return r.choice(BAD_PARAMETER_VALUES)
        return self.any_value()

    def mutate(self, obj: dict[str, Any]) -> dict[str, Any]:
        """Wrong structure: a field dropped, added, or given an arbitrary value."""
        r = self.random
        obj = dict(obj)
        roll = r.random()
        keys = [k for k in obj if k not in ("id",)]
        if roll < 0.3 and keys:
            obj.pop(r.choice(keys))
        elif roll < 0.5:
            obj[r.choice(["x", "ops", "trajectory", "goal_id", "in", "token", "freeze",
                          "names", "parameters"])] = (
                self.any_value()
            )
        elif keys:
            obj[r.choice(keys)] = self.any_value()
        return obj

    def mutate_bytes(self, data: bytes) -> bytes:
        r = self.random
        out = bytearray(data)
        for _ in range(r.randrange(1, 4)):
            if not out:
                break
            roll = r.random()
            i = r.randrange(len(out))
            if roll < 0.4:
                out[i] = r.randrange(256)
            elif roll < 0.6:
                del out[i : i + r.randrange(1, 8)]
            elif roll < 0.8:
                out[i:i] = r.choice([b"\\ud800", b"\\udfff", b"\xff", b",", b'"', b"{", b"]",
                                     b"NaN", b"-", b"e999", b"\\"])
            else:
                del out[i:]
        return bytes(out)

    # -- lines --------------------------------------------------------------------------------

    def line(self) -> Line:
        r = self.random
        if self.binary and r.random() < self.binary:
            return self.frame()
        op = r.choice(OPS)
        self.ids += 1
        rid = self.ids
        obj: dict[str, Any] = {"id": rid, **self.request(op)}
        roll = r.random()
        known_id: int | None = rid
        if roll < 0.55:
            pass
        elif roll < 0.75:
            obj = self.mutate(obj)
        elif roll < 0.8:
            obj["id"] = r.choice(EDGE_STRINGS + [True, 1.5, None, [1], MAX_NS + 1])
            known_id = None
        elif roll < 0.82:
            obj = {"id": rid, "op": r.choice(EDGE_STRINGS + ["helo", "stop_", "Stop"])}
        else:
            known_id = None
        text = json.dumps(obj, ensure_ascii=r.random() < 0.5)
        raw = r.random() < 0.5  # a lone surrogate as raw bytes (not UTF-8), else escaped
        data = text.encode("utf-8", "surrogatepass" if raw else "backslashreplace")
        if raw and any("\ud800" <= c <= "\udfff" for c in text):
            known_id = None  # not UTF-8: the id cannot be read
        if roll >= 0.82:
            if roll < 0.96:
                data = self.mutate_bytes(data)
            elif roll < 0.995:
                data = r.choice(TROUBLE)
            else:
                data = data + b" " * (self.max_message_bytes + 10)
        data = data.replace(b"\n", b" ")
        if not data.strip():
            data = b"x"
        return Line(data + b"\n", op, known_id)

    # -- binary frames (docs/protocol.md, "Binary frames") -------------------------------------

    def frame(self) -> Line:
        """A binary frame: mostly a plausible goal or trajectory, else one of the doc's wrong
        kinds: a shape that does not match the bytes, NaN or infinity, a dtype other than
        ``<f8``, columns that do not match the joints, header fields of the wrong type, an
        attachment on another op, an oversized attachment (``bad_request`` / ``too_large``,
        the stream goes on), and frames that cannot be trusted (``closes``): lengths that lie,
        a length that is no integer, raw bytes without their newline, frames cut short."""
        r = self.random
        self.ids += 1
        rid = self.ids
        op = r.choice(["send_goal", "send_goal", "send_trajectory"])
        names = list(self.joints)
        fields = [f for f in ("positions", "velocities", "accelerations", "effort")
                  if r.random() < (0.95 if f == "positions" else 0.3)]
        m = r.choice([1, 2, 3, 5, 10, 20, 40, 120]) if r.random() < 0.98 else 600
        clock = np.cumsum(np.round(np.array([r.uniform(0.02, 0.3) for _ in range(m)]), 4))
        values = np.column_stack([clock] + [
            np.round(np.array([[r.uniform(-1.0, 1.0) for _ in names] for _ in range(m)]), 4)
            for _ in fields]) if fields else clock[:, None]
        columns = ["time_from_start", *(f"{f}.{j}" for f in fields for j in names)]
        request: dict[str, Any] = {"id": rid, "op": op, "trajectory": {"joint_names": names}}
        if op == "send_goal" and r.random() < 0.2:
            request["goal_time_tolerance"] = r.choice([0.0, 0.5, 1.0])
        if r.random() < 0.1:
            request["trajectory"]["start_in"] = r.choice([0.0, 0.1, -0.1])
        header: dict[str, Any] = {}
        raw = values.astype("<f8").tobytes()
        roll = r.random()
        closes = False
        cut: int | None = None
        if roll < 0.45:
            pass  # plausible: ok, or goal_rejected
        elif roll < 0.52:  # a shape that does not match the bytes or the columns
            header["shape"] = r.choice([[m + 1, len(columns)], [m, len(columns) + 1],
                                        [len(columns), m], [m * len(columns)], [-1, 3],
                                        [m, 0], "2x3", None, [m, True], [2**40, 2**40]])
        elif roll < 0.6:  # NaN or an infinity somewhere
            bad = values.copy()
            bad[r.randrange(m), r.randrange(bad.shape[1])] = r.choice([np.nan, np.inf, -np.inf])
            raw = bad.astype("<f8").tobytes()
        elif roll < 0.66:  # values out of range (times beyond int64 ns, huge positions)
            bad = values.copy()
            bad[r.randrange(m), r.randrange(bad.shape[1])] = r.choice(
                [1e300, -1e300, 1.7976931348623157e308, 9223372037.0, 2e6, 5e-324])
            raw = bad.astype("<f8").tobytes()
        elif roll < 0.72:  # a dtype that is not little-endian float64
            header["dtype"] = r.choice([">f8", "<f4", "float64", "<i8", "f8", "", 8, None,
                                        ["<f8"]])
        elif roll < 0.78:  # columns that do not match the joints
            shuffled = list(columns)
            choice = r.randrange(5)
            if choice == 0 and len(shuffled) > 2:
                r.shuffle(shuffled)
            elif choice == 1:
                shuffled[r.randrange(len(shuffled))] = r.choice(EDGE_STRINGS)
            elif choice == 2:
                shuffled = [c.replace("positions", "position") for c in shuffled]
            elif choice == 3:
                shuffled = shuffled[::-1]
            else:
                shuffled = "time_from_start"  # type: ignore[assignment]
            header["columns"] = shuffled
        elif roll < 0.8:  # header fields missing or unknown
            header[r.choice(["extra", "byte_order", "Shape"])] = self.any_value()
        elif roll < 0.82:  # an attachment where none belongs, or points as well
            if r.random() < 0.5:
                request = {"id": rid, "op": r.choice(["hello", "stop", "get_status"])}
            else:
                request["trajectory"]["points"] = []
        elif roll < 0.835:  # longer than the daemon's limit: skipped, too_large
            raw = bytes(self.max_message_bytes + 8)
            header["shape"] = [len(raw) // 8 // len(columns), len(columns)]
        else:  # cannot be trusted: bad_frame, and the connection closes
            closes = True
            kind = r.randrange(5)
            if kind == 0:  # announces fewer bytes than follow (the byte there is no newline)
                shorter = [n for n in range(len(raw)) if raw[n : n + 1] != b"\n"]
                header["bytes"] = r.choice(shorter) if shorter else len(raw) + 7
            elif kind == 1:  # announces more than follow before the stream ends
                header["bytes"] = len(raw) + r.choice([1, 8, 1000])
            elif kind == 2:  # a length that is no integer
                header["bytes"] = r.choice([str(len(raw)), -1, float(len(raw)), None, [1],
                                            True])
            elif kind == 3:  # the raw bytes' newline missing
                cut = -1
            else:  # the stream ends inside the raw bytes
                cut = r.randrange(len(raw) + 1) - len(raw) - 1
        attachment = {"bytes": len(raw), "dtype": "<f8", "shape": list(values.shape),
                      "columns": columns, **header}
        line = json.dumps({**request, "attachment": attachment}).encode()
        data = line + b"\n" + raw + b"\n"
        if cut is not None:
            data = data[:cut] + (r.choice([b"x", b"\r", b" "]) if cut == -1 else b"")
        return Line(data, op, None if closes else rid, closes=closes, binary=True)

