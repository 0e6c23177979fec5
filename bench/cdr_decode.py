#!/usr/bin/env python3
"""What decoding a large ``FollowJointTrajectory`` goal costs: ours against rosbags' decoder.

A 6-joint goal of N points (positions, velocities and accelerations at every point, as a
planner sends them) is serialized once with rosbags' ``serialize_cdr`` as the action's
``SendGoal`` request, then decoded, best of ``--repeat`` runs each, by:

- ours: ``jtc_hw.daemon.transports.ros2.cdr.decode_send_goal_request``, to a ``SendGoal``
  whose points are ``PointColumns`` (strided numpy views, no Python object per number);
- rosbags: ``Typestore.deserialize_cdr``, to rosbags' message objects (one numpy array per
  field of each point);
- socket: the same goal as the socket's JSON line, ``json.loads`` then ``parse_request``
  (for scale: what the goal costs over the socket today).

control_msgs is not in rosbags' store: its goal is declared here from the .msg text of
ros-controls/control_msgs (action/FollowJointTrajectory.action, msg/JointTolerance.msg,
msg/JointComponentTolerance.msg).

Usage:  python bench/cdr_decode.py [--points 2000 20000] [--repeat 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jtc_hw.api.protocol import parse_request  # noqa: E402
from jtc_hw.daemon.transports.ros2.cdr import decode_send_goal_request  # noqa: E402

JOINTS = 6
REQUEST = "control_msgs/action/FollowJointTrajectory_SendGoal_Request"
_DEFINITIONS = {
    "control_msgs/msg/JointTolerance":
        "string name\nfloat64 position\nfloat64 velocity\nfloat64 acceleration\n",
    "control_msgs/msg/JointComponentTolerance":
        "string joint_name\nuint16 component\nfloat64 position\nfloat64 velocity\n"
        "float64 acceleration\n",
    "control_msgs/action/FollowJointTrajectory_Goal":
        "trajectory_msgs/JointTrajectory trajectory\n"
        "trajectory_msgs/MultiDOFJointTrajectory multi_dof_trajectory\n"
        "control_msgs/JointTolerance[] path_tolerance\n"
        "control_msgs/JointComponentTolerance[] component_path_tolerance\n"
        "control_msgs/JointTolerance[] goal_tolerance\n"
        "control_msgs/JointComponentTolerance[] component_goal_tolerance\n"
        "builtin_interfaces/Duration goal_time_tolerance\n",
    REQUEST: "unique_identifier_msgs/UUID goal_id\n"
             "control_msgs/action/FollowJointTrajectory_Goal goal\n",
}


def store() -> Any:
    ts = get_typestore(Stores.ROS2_JAZZY)
    for name, text in _DEFINITIONS.items():
        ts.register(get_types_from_msg(text, name))
    return ts


def goal(ts: Any, points: int) -> tuple[bytes, str]:
    """The goal's CDR (rosbags') and the same goal as the socket's JSON line."""
    t = ts.types
    names = [f"joint_{j}" for j in range(JOINTS)]
    s = np.linspace(0.0, 1.0, points)[:, None] * np.linspace(0.5, 1.5, JOINTS)
    times = np.arange(1, points + 1) * 0.01
    empty = np.array([], dtype=np.float64)
    pts = [t["trajectory_msgs/msg/JointTrajectoryPoint"](
        positions=s[i], velocities=s[i] * 0.1, accelerations=s[i] * 0.01, effort=empty,
        time_from_start=t["builtin_interfaces/msg/Duration"](int(times[i]),
                                                            round(times[i] % 1 * 1e9)))
        for i in range(points)]
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](0, 0), frame_id="")
    request = t[REQUEST](
        goal_id=t["unique_identifier_msgs/msg/UUID"](uuid=np.arange(16, dtype=np.uint8)),
        goal=t["control_msgs/action/FollowJointTrajectory_Goal"](
            trajectory=t["trajectory_msgs/msg/JointTrajectory"](
                header=header, joint_names=names, points=pts),
            multi_dof_trajectory=t["trajectory_msgs/msg/MultiDOFJointTrajectory"](
                header=header, joint_names=[], points=[]),
            path_tolerance=[], component_path_tolerance=[], goal_tolerance=[],
            component_goal_tolerance=[],
            goal_time_tolerance=t["builtin_interfaces/msg/Duration"](0, 0)))
    line = json.dumps({"op": "send_goal", "trajectory": {"joint_names": names, "points": [
        {"time_from_start": float(times[i]), "positions": s[i].tolist(),
         "velocities": (s[i] * 0.1).tolist(), "accelerations": (s[i] * 0.01).tolist()}
        for i in range(points)]}})
    return bytes(ts.serialize_cdr(request, REQUEST)), line


def best_ms(fn: Callable[[], object], repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def measure(ts: Any, points: int, repeat: int) -> dict[str, Any]:
    buf, line = goal(ts, points)
    _, ours = decode_send_goal_request(buf)
    assert len(ours.trajectory.points) == points
    return {
        "bench": "cdr_decode",
        "points": points,
        "joints": JOINTS,
        "bytes": len(buf),
        "ours_ms": best_ms(lambda: decode_send_goal_request(buf), repeat),
        "rosbags_ms": best_ms(lambda: ts.deserialize_cdr(buf, REQUEST), repeat),
        "socket_json_ms": best_ms(lambda: parse_request(json.loads(line)), repeat),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, nargs="+", default=[2000, 20000],
                        help="points per goal")
    parser.add_argument("--repeat", type=int, default=5, help="runs per decoder (best kept)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args()
    ts = store()
    rows = [measure(ts, n, args.repeat) for n in args.points]
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    print(f"{'points':>7} {'bytes':>9} {'ours ms':>9} {'rosbags ms':>11} {'socket JSON ms':>15}")
    for r in rows:
        print(f"{r['points']:>7} {r['bytes']:>9} {r['ours_ms']:>9.3f} {r['rosbags_ms']:>11.2f} "
              f"{r['socket_json_ms']:>15.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
