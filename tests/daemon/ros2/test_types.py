"""Golden tests of the ROS 2 types: DDS names and RIHS01 hashes against values rosidl generated.

Every expected hash below comes from a file we did not write (cited per test); none is computed
by the code under test or by rosbags.
"""

from __future__ import annotations

import pytest

from jtc_hw.daemon.transports.ros2 import types
from jtc_hw.daemon.transports.ros2.types import (
    CANCEL_GOAL,
    CONTROLLER_STATE,
    DISTROS,
    FJT_FEEDBACK_MESSAGE,
    FJT_GET_RESULT,
    FJT_SEND_GOAL,
    FOLLOW_JOINT_TRAJECTORY,
    GET_PARAMETERS,
    JOINT_STATE,
    SPEED_SCALING_FACTOR,
    TYPE_HASH_NOT_SUPPORTED,
    RosTypes,
    ros_types,
)

FJT = FOLLOW_JOINT_TRAJECTORY

# rmw_zenoh docs/design.md at 99a6a2bd10b949052f4f12c5854825dc005e95a5 (key expression examples).
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
# `ros2 topic info /joint_states --verbose` of a joint_state_broadcaster (a public transcript in
# the code index; the same value is in rosbags' and several rmw_zenoh clients' tables).
JOINT_STATE_HASH = "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
# The same transcript's `ros2 topic info -v` of a joint_trajectory_controller's joint_trajectory.
JOINT_TRAJECTORY_HASH = "RIHS01_179b33eba59d676f6d967ac71fe35e7ca2f64b2f3928f4a018cec115e213796e"
# control_msgs 4.x/5.x FollowJointTrajectory (no index fields), as rosidl generated it:
# github.com/saahu27/aprs, aprs_ws/build/control_msgs/rosidl_generator_c/control_msgs/action/
# detail/follow_joint_trajectory__description.c (and __struct.h beside it).
FJT_HASHES = {
    FJT: "738ebcb7a2d7cfa42f9f1001cc99ce3a4383d1cfe508015d9be8485e4b1c66f6",
    FJT + "_Goal": "8a9060704b269608f5a340934cc26e66869dd14bdac29e2e7fd9ec8b9882d205",
    FJT + "_Result": "8002e99ed2c14c6faa522f2a93c26d744c5982f254f9e98ff9c6f19789bdb220",
    FJT + "_Feedback": "3fd0aaecf71725121ae1ff7f01098a5e0da581e672be18a6b2c286cb43d96b49",
    FJT_SEND_GOAL: "b13789dddc325a7a962825c45e28c77d37237ec129dd0c34dc5994562938c57f",
    FJT_SEND_GOAL + "_Request": "179c93691f1f6d1d115881ff88c3917b7cc6eac2ba4bf56766cc7c4389e19ef1",
    FJT_SEND_GOAL + "_Response":
        "e6a48ba740ae254500129a877f0b071be8663a115da1a539b74599cc97921fbf",
    FJT_SEND_GOAL + "_Event": "906dd566308db02673c73c654f69bdd84738589629c1bc2841ddb49059ed1c6f",
    FJT_GET_RESULT: "e3ceb38e3e1867c8dc0f46014df26e90eb93422f27e9e97f936e07f94be4bc8b",
    FJT_GET_RESULT + "_Request":
        "ecf7ea8463d3beec7084bca75216d0b01b87b6e1e4e09679bb26093041efcbe9",
    FJT_GET_RESULT + "_Response":
        "08eefbaa146ce02ba45898d5e99160afd6c4c54a30d159aee0f2ca6035b1580f",
    FJT_GET_RESULT + "_Event": "43161a489e52daaa5bbc2fa74f73f1804d099574fcf8f819170807d75472662a",
    FJT_FEEDBACK_MESSAGE: "80398fcb9674a79081a9906e2ccf0c804dd7cb15e22e362e606ee87186beab71",
}
# rosidl-generated headers of released rcl_interfaces (…/srv/detail/cancel_goal__struct.h,
# …/srv/detail/get_parameters__struct.h, ``TYPE_HASH`` initialisers; code index).
CANCEL_GOAL_HASH = "RIHS01_573d8b0a534451d7bc2ac8c5ffde8ac14b8593b7001175d0cd6516dcbeb8689a"
GET_PARAMETERS_HASH = "RIHS01_bf9803d5c74cf989a5de3e0c2e99444599a627c7ff75f97b8c05b01003675cbc"


@pytest.mark.parametrize("distro", ["jazzy", "kilted", "rolling"])
def test_message_hashes_match_the_quoted_ones(distro: str) -> None:
    t = ros_types(distro)
    assert t.type_hash("std_msgs/msg/String") == STRING_HASH
    assert t.type_hash(JOINT_STATE) == JOINT_STATE_HASH
    assert t.type_hash(types.JOINT_TRAJECTORY) == JOINT_TRAJECTORY_HASH


def test_a_service_hash_matches_the_design_doc() -> None:
    """AddTwoInts from its .srv text (example_interfaces/srv/AddTwoInts.srv): the service hash
    covers AddTwoInts_Event, hence ServiceEventInfo, whose ``char[16]`` rosidl hashes as
    ``uint8[16]``; rosbags' own hash of it would be wrong."""
    t = RosTypes("jazzy")
    t.register("example_interfaces/srv/AddTwoInts", "int64 a\nint64 b\n---\nint64 sum\n")
    assert t.type_hash("example_interfaces/srv/AddTwoInts") == ADD_TWO_INTS_HASH
    assert t.dds_name("example_interfaces/srv/AddTwoInts") == (
        "example_interfaces::srv::dds_::AddTwoInts_")


def test_an_action_of_the_ros_2_tutorials_matches_ros2_action_info() -> None:
    """turtlesim_msgs/action/RotateAbsolute from its .action text: the hashes
    ``ros2 action info -v`` prints in ROS 2's tutorial "Understanding actions"
    (ros2/ros2_documentation, Tutorials/Beginner-CLI-Tools/Understanding-ROS2-Actions)."""
    t = RosTypes("jazzy")
    t.register("turtlesim_msgs/action/RotateAbsolute",
               "float32 theta\n---\nfloat32 delta\n---\nfloat32 remaining\n")
    action = "turtlesim_msgs/action/RotateAbsolute"
    assert t.type_hash(action + "_SendGoal") == (
        "RIHS01_3d5d3cfcbb721f88038eaedcd4af95565360a82b36f1983e3a6c7448d2d18fbe")
    assert t.type_hash(action + "_GetResult") == (
        "RIHS01_f96fd02477be2a47122fca142e960d407b24850c6eac72047872ba764473c4ef")
    assert t.type_hash(action + "_FeedbackMessage") == (
        "RIHS01_bef10993e1ee82b35f99f7e390bac1e6cc64e2a3090536887832e122aa71f1b5")
    # The same page's status and cancel hashes.
    assert t.type_hash("action_msgs/msg/GoalStatusArray") == (
        "RIHS01_6c1684b00f177d37438febe6e709fc4e2b0d4248dca4854946f9ed8b30cda83e")
    assert t.type_hash(CANCEL_GOAL) == CANCEL_GOAL_HASH


def test_a_malformed_interface_text_is_refused() -> None:
    t = RosTypes("jazzy")
    with pytest.raises(ValueError, match="sections"):
        t.register("x_msgs/srv/Broken", "int64 a\n")
    with pytest.raises(ValueError, match="sections"):
        t.register("x_msgs/action/Broken", "int64 a\n---\nint64 b\n")
    for name in ("x_msgs/Broken", "x_msgs/idl/Broken", "x_msgs/msg/"):
        with pytest.raises(ValueError, match="not an interface name"):
            t.register(name, "int64 a\n")
    assert t.is_action(FJT) and not t.is_action(FJT_SEND_GOAL)


def test_rosbags_hashes_char_differently_which_is_why_we_do_not_use_it() -> None:
    t = ros_types("jazzy")
    info = "service_msgs/msg/ServiceEventInfo"
    assert t.typestore.hash_rihs01(info) != t.type_hash(info)


def test_the_follow_joint_trajectory_hashes_of_jazzy_match_rosidl() -> None:
    t = ros_types("jazzy")
    assert {name: t.type_hash(name) for name in FJT_HASHES} == {
        name: "RIHS01_" + digest for name, digest in FJT_HASHES.items()
    }


def test_the_action_services_hashes_match_rosidl() -> None:
    t = ros_types("jazzy")
    assert t.type_hash(CANCEL_GOAL) == CANCEL_GOAL_HASH
    assert t.type_hash(GET_PARAMETERS) == GET_PARAMETERS_HASH


@pytest.mark.parametrize("distro", ["kilted", "rolling"])
def test_control_msgs_6_3_feedback_changes_the_feedback_hashes_only(distro: str) -> None:
    """control_msgs >= 6.3 (master: Kilted and Rolling) adds ``index``/``multi_dof_index`` to
    the feedback: the feedback message and the action change, the goal services do not."""
    jazzy, later = ros_types("jazzy"), ros_types(distro)
    for same in (FJT + "_Goal", FJT + "_Result", FJT_SEND_GOAL, FJT_GET_RESULT):
        assert later.type_hash(same) == jazzy.type_hash(same)
    for changed in (FJT + "_Feedback", FJT_FEEDBACK_MESSAGE, FJT):
        assert later.type_hash(changed) != jazzy.type_hash(changed)
    fields = [name for name, _ in later.typestore.fielddefs[FJT + "_Feedback"][1]]
    assert "index" in fields and "multi_dof_index" in fields


def test_controller_state_fields_per_distro() -> None:
    humble = [n for n, _ in ros_types("humble").typestore.fielddefs[CONTROLLER_STATE][1]]
    jazzy = [n for n, _ in ros_types("jazzy").typestore.fielddefs[CONTROLLER_STATE][1]]
    assert "desired" in humble and "actual" in humble
    assert "speed_scaling_factor" not in humble
    assert "desired" not in jazzy and jazzy[-1] == "speed_scaling_factor"


def test_humble_has_no_hashes_and_no_speed_scaling() -> None:
    humble = ros_types("humble")
    assert humble.type_hash(JOINT_STATE) == TYPE_HASH_NOT_SUPPORTED == "TypeHashNotSupported"
    assert humble.type_hash(FJT_SEND_GOAL) == TYPE_HASH_NOT_SUPPORTED
    with pytest.raises(KeyError):
        humble.type_hash(SPEED_SCALING_FACTOR)
    assert FJT_SEND_GOAL + "_Event" not in humble.typestore.fielddefs


def test_dds_names_as_rmw_zenoh_writes_them() -> None:
    t = ros_types("jazzy")
    assert t.dds_name(JOINT_STATE) == "sensor_msgs::msg::dds_::JointState_"
    assert t.dds_name(CANCEL_GOAL) == "action_msgs::srv::dds_::CancelGoal_"
    # Quoted in public rmw_zenoh traces: "...::action::dds_::Fibonacci_GetResult_".
    assert t.dds_name(FJT_SEND_GOAL) == (
        "control_msgs::action::dds_::FollowJointTrajectory_SendGoal_")
    assert t.dds_name(FJT_GET_RESULT) == (
        "control_msgs::action::dds_::FollowJointTrajectory_GetResult_")
    assert t.dds_name(FJT_FEEDBACK_MESSAGE) == (
        "control_msgs::action::dds_::FollowJointTrajectory_FeedbackMessage_")
    assert t.is_service(FJT_SEND_GOAL) and t.is_service(CANCEL_GOAL)
    assert not t.is_service(JOINT_STATE) and not t.is_service(FJT_FEEDBACK_MESSAGE)


@pytest.mark.parametrize("distro", DISTROS)
def test_every_type_the_transport_uses_round_trips_through_the_store(distro: str) -> None:
    t = ros_types(distro)
    names = [types.JOINT_STATE, types.JOINT_TRAJECTORY, types.CONTROLLER_STATE,
             types.GOAL_STATUS_ARRAY, FJT_FEEDBACK_MESSAGE]
    services = [FJT_SEND_GOAL, FJT_GET_RESULT, CANCEL_GOAL, types.QUERY_TRAJECTORY_STATE,
                GET_PARAMETERS, types.SET_PARAMETERS, types.LIST_PARAMETERS]
    names += [t.request_type(s) for s in services] + [t.response_type(s) for s in services]
    if distro != "humble":
        names.append(SPEED_SCALING_FACTOR)
    for name in names:
        msg = t.typestore.types[name]
        raw = t.typestore.serialize_cdr(_default(t, name), name)
        assert type(t.typestore.deserialize_cdr(raw, name)) is msg
        assert t.type_hash(name).startswith("RIHS01_" if t.hashed else "TypeHash")


def test_unknown_names_and_distros_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown ROS 2 distro"):
        RosTypes("iron")
    t = ros_types("jazzy")
    assert not t.is_service("junk") and not t.is_service("a/srv/Nothing")
    for bad in ("sensor_msgs/JointState", "nope/msg/Nothing", ""):
        with pytest.raises(KeyError):
            t.type_hash(bad)
        with pytest.raises(KeyError):
            t.dds_name(bad)


def _default(t: RosTypes, name: str) -> object:
    """A message of type ``name`` with every field at its zero value."""
    import numpy as np
    from rosbags.interfaces import Nodetype

    fields = {}
    for field, (node, rest) in t.typestore.fielddefs[name][1]:
        if node == Nodetype.NAME:
            fields[field] = _default(t, rest)
        elif node == Nodetype.ARRAY:
            (sub, base), size = rest
            dtype = {"uint8": np.uint8, "char": np.uint8}.get(base[0], np.float64)
            fields[field] = np.zeros(size, dtype=dtype) if sub == Nodetype.BASE else [
                _default(t, base) for _ in range(size)]
        elif node == Nodetype.SEQUENCE:
            (sub, base), _ = rest
            fields[field] = np.zeros(0, dtype=np.float64) if (
                sub == Nodetype.BASE and base[0] not in ("string", "bool")) else []
        else:
            fields[field] = {"string": "", "bool": False}.get(
                rest[0], 0.0 if rest[0].startswith("float") else 0)
    return t.typestore.types[name](**fields)
