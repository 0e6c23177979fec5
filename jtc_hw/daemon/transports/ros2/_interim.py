"""INTERIM stand-ins for types.py / wire.py / cdr.py (helpers A and B), removed when they land.

Only what node.py needs, with the same names; slow and approximate where theirs is exact.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from typing import Any

from ....api.requests import SendGoal, WireTrajectory
from ....controller.messages import TrajectoryPoint
from ....controller.tolerances import JointTolerance

DISTROS = ("humble", "jazzy", "kilted", "rolling")

_DEFS = {
    "control_msgs/msg/JointTolerance": "string name\nfloat64 position\nfloat64 velocity\n"
                                       "float64 acceleration\n",
    "control_msgs/msg/JointComponentTolerance": "string joint_name\nuint16 component\n"
                                                "float64 position\nfloat64 velocity\n"
                                                "float64 acceleration\n",
    "control_msgs/msg/SpeedScalingFactor": "float64 factor\n",
    "control_msgs/msg/JointTrajectoryControllerState": (
        "std_msgs/Header header\nstring[] joint_names\n"
        "trajectory_msgs/JointTrajectoryPoint reference\n"
        "trajectory_msgs/JointTrajectoryPoint feedback\n"
        "trajectory_msgs/JointTrajectoryPoint error\n"
        "trajectory_msgs/JointTrajectoryPoint output\n"
        "string[] multi_dof_joint_names\n"
        "trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_reference\n"
        "trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_feedback\n"
        "trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_error\n"
        "trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_output\n"
        "float64 speed_scaling_factor\n"),
    "control_msgs/action/FollowJointTrajectory_Goal": (
        "trajectory_msgs/JointTrajectory trajectory\n"
        "trajectory_msgs/MultiDOFJointTrajectory multi_dof_trajectory\n"
        "control_msgs/JointTolerance[] path_tolerance\n"
        "control_msgs/JointComponentTolerance[] component_path_tolerance\n"
        "control_msgs/JointTolerance[] goal_tolerance\n"
        "control_msgs/JointComponentTolerance[] component_goal_tolerance\n"
        "builtin_interfaces/Duration goal_time_tolerance\n"),
    "control_msgs/action/FollowJointTrajectory_Result": "int32 error_code\nstring error_string\n",
    "control_msgs/action/FollowJointTrajectory_Feedback": (
        "std_msgs/Header header\nstring[] joint_names\n"
        "trajectory_msgs/JointTrajectoryPoint desired\n"
        "trajectory_msgs/JointTrajectoryPoint actual\n"
        "trajectory_msgs/JointTrajectoryPoint error\n"
        "string[] multi_dof_joint_names\n"
        "trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_desired\n"
        "trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_actual\n"
        "trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_error\n"),
    "control_msgs/action/FollowJointTrajectory_SendGoal_Request": (
        "unique_identifier_msgs/UUID goal_id\n"
        "control_msgs/action/FollowJointTrajectory_Goal goal\n"),
    "control_msgs/action/FollowJointTrajectory_SendGoal_Response": (
        "bool accepted\nbuiltin_interfaces/Time stamp\n"),
    "control_msgs/action/FollowJointTrajectory_GetResult_Request": (
        "unique_identifier_msgs/UUID goal_id\n"),
    "control_msgs/action/FollowJointTrajectory_GetResult_Response": (
        "int8 status\ncontrol_msgs/action/FollowJointTrajectory_Result result\n"),
    "control_msgs/action/FollowJointTrajectory_FeedbackMessage": (
        "unique_identifier_msgs/UUID goal_id\n"
        "control_msgs/action/FollowJointTrajectory_Feedback feedback\n"),
    "action_msgs/srv/CancelGoal_Request": "action_msgs/GoalInfo goal_info\n",
    "action_msgs/srv/CancelGoal_Response": "int8 return_code\n"
                                           "action_msgs/GoalInfo[] goals_canceling\n",
    "control_msgs/srv/QueryTrajectoryState_Request": "builtin_interfaces/Time time\n",
    "control_msgs/srv/QueryTrajectoryState_Response": (
        "bool success\nstring message\nstring[] name\nfloat64[] position\n"
        "float64[] velocity\nfloat64[] acceleration\n"),
}


class RosTypes:
    """Stand-in: Jazzy's rosbags store plus control_msgs; hashes from rosbags."""

    def __init__(self, distro: str) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.distro = distro
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        types: dict[str, Any] = {}
        for name, text in _DEFS.items():
            types.update(get_types_from_msg(text, name))
        self.typestore.register(types)

    def dds_name(self, ros_type: str) -> str:
        pkg, kind, name = ros_type.split("/")
        return f"{pkg}::{kind}::dds_::{name}_"

    def type_hash(self, ros_type: str) -> str:
        if self.distro == "humble":
            return "TypeHashNotSupported"
        try:
            return str(self.typestore.hash_rihs01(ros_type))
        except Exception:
            import hashlib
            return "RIHS01_" + hashlib.sha256(ros_type.encode()).hexdigest()


def topic_key(domain_id: int, fq_name: str, dds_type: str, type_hash: str) -> str:
    return f"{domain_id}/{fq_name.strip('/')}/{dds_type}/{type_hash}"


def mangle(name: str) -> str:
    return name.replace("/", "%") if name else "%"


@dataclass(frozen=True)
class Qos:
    reliability: int = 1
    durability: int = 2
    history: int = 1
    depth: int = 10


def qos_text(qos: Qos) -> str:
    rel = "" if qos.reliability == 1 else str(qos.reliability)
    dur = "" if qos.durability == 2 else str(qos.durability)
    return f"{rel}:{dur}:,{qos.depth}:,:,:,,"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node_name: str,
               enclave: str = "") -> str:
    return (f"@ros2_lv/{domain_id}/{zid}/{node_id}/{node_id}/NN/{mangle(enclave)}/"
            f"{mangle(namespace)}/{node_name}")


def entity_token(kind: str, domain_id: int, zid: str, node_id: int, entity_id: int,
                 namespace: str, node_name: str, name: str, dds_type: str, type_hash: str,
                 qos: Qos, enclave: str = "") -> str:
    return (f"@ros2_lv/{domain_id}/{zid}/{node_id}/{entity_id}/{kind}/{mangle(enclave)}/"
            f"{mangle(namespace)}/{node_name}/{mangle(name)}/{dds_type}/{type_hash}/"
            f"{qos_text(qos)}")


def encode_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    return struct.pack("<qqB", sequence_number, source_timestamp_ns, len(gid)) + gid


@dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes


def decode_attachment(data: bytes) -> Attachment:
    if len(data) < 17:
        raise ValueError("short attachment")
    seq, ts, n = struct.unpack_from("<qqB", data)
    gid = bytes(data[17:17 + n])
    if len(gid) != n:
        raise ValueError("short gid")
    return Attachment(seq, ts, gid)


def new_gid() -> bytes:
    return os.urandom(16)


class CdrError(ValueError):
    pass


_TYPES: RosTypes | None = None


def _store() -> Any:
    global _TYPES
    if _TYPES is None:
        _TYPES = RosTypes("jazzy")
    return _TYPES.typestore


def _seconds(d: Any) -> float:
    return float(d.sec) + float(d.nanosec) * 1e-9


def _wire(msg: Any) -> WireTrajectory:
    points = []
    for p in msg.points:
        def vals(a: Any) -> tuple[float, ...] | None:
            return tuple(float(x) for x in a) if len(a) else None
        points.append(TrajectoryPoint(
            positions=vals(p.positions), velocities=vals(p.velocities),
            accelerations=vals(p.accelerations), effort=vals(p.effort),
            time_from_start_ns=int(p.time_from_start.sec) * 10**9
            + int(p.time_from_start.nanosec)))
    return WireTrajectory(tuple(msg.joint_names), tuple(points))


def decode_joint_trajectory_message(buf: bytes | memoryview) -> WireTrajectory:
    try:
        msg = _store().deserialize_cdr(bytes(buf), "trajectory_msgs/msg/JointTrajectory")
        return _wire(msg)
    except Exception as exc:
        raise CdrError(f"bad JointTrajectory: {exc}") from None


def decode_send_goal_request(buf: bytes | memoryview) -> tuple[bytes, SendGoal]:
    try:
        msg = _store().deserialize_cdr(
            bytes(buf), "control_msgs/action/FollowJointTrajectory_SendGoal_Request")
        goal = msg.goal
        if goal.multi_dof_trajectory.points.__len__():
            raise CdrError("multi_dof_trajectory is not supported")
        tol = tuple(JointTolerance(t.name, t.position, t.velocity, t.acceleration)
                    for t in goal.path_tolerance)
        gtol = tuple(JointTolerance(t.name, t.position, t.velocity, t.acceleration)
                     for t in goal.goal_tolerance)
        return bytes(msg.goal_id.uuid), SendGoal(
            trajectory=_wire(goal.trajectory), path_tolerance=tol, goal_tolerance=gtol,
            goal_time_tolerance=_seconds(goal.goal_time_tolerance))
    except CdrError:
        raise
    except Exception as exc:
        raise CdrError(f"bad SendGoal request: {exc}") from None
