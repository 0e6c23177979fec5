"""Golden tests of rmw_zenoh's wire format: keys, tokens, QoS text and attachments.

The expected strings are quoted verbatim from rmw_zenoh's docs/design.md at commit
99a6a2bd10b949052f4f12c5854825dc005e95a5 ("Topic and Service name mapping to Zenoh key
expressions", "Graph Cache"); the attachment bytes follow its "Publishers" section and are
checked against zenoh-ext's own serializer (eclipse-zenoh's ``zenoh.ext.z_serialize``), which
rmw_zenoh's ``attachment_helpers.cpp`` uses.
"""

from __future__ import annotations

import dataclasses

import pytest

from jtc_hw.daemon.transports.ros2 import wire
from jtc_hw.daemon.transports.ros2.types import FJT_SEND_GOAL, ros_types
from jtc_hw.daemon.transports.ros2.wire import (
    ATTACHMENT_SIZE,
    QOS_ACTION_STATUS,
    QOS_DEFAULT,
    QOS_PARAMETERS,
    QOS_SENSOR_DATA,
    QOS_SERVICES,
    QOS_SYSTEM_DEFAULT,
    Durability,
    EntityKind,
    History,
    Qos,
    Reliability,
    decode_attachment,
    encode_attachment,
    entity_token,
    node_token,
    parse_qos,
    parse_token,
    qos_text,
    topic_key,
)

STRING = "std_msgs::msg::dds_::String_"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD = "example_interfaces::srv::dds_::AddTwoInts_"
ADD_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


def test_data_keys_of_the_design_doc() -> None:
    assert topic_key(0, "/chatter", STRING, STRING_HASH) == (
        "0/chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert topic_key(0, "/robot1/chatter", STRING, STRING_HASH) == (
        "0/robot1/chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert topic_key(2, "/add_two_ints", ADD, ADD_HASH) == (
        "2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/"
        "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a")


DOC_TOKENS = [
    "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener",
    "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
    "std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,",
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    "std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,",
    "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/"
    "%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/"
    "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a/::,10:,:,:,,",
    "@ros2_lv/2/e1dc8d1b45ae8717fce78689cc655685/0/10/SC/%/%/add_two_ints_client/"
    "%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/"
    "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a/::,10:,:,:,,",
]


def test_tokens_of_the_design_doc_are_built_verbatim() -> None:
    assert node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener") == DOC_TOKENS[0]
    assert entity_token(EntityKind.SUBSCRIPTION, 2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 10,
                        "/", "listener", "/chatter", STRING, STRING_HASH,
                        QOS_DEFAULT) == DOC_TOKENS[1]
    assert entity_token(EntityKind.PUBLISHER, 2, "8b20917502ee955ac4476e0266340d5c", 0, 10,
                        "/", "talker", "/chatter", STRING, STRING_HASH,
                        Qos(depth=7)) == DOC_TOKENS[2]
    assert entity_token(EntityKind.SERVICE, 2, "f9980ee0495eaafb3e38f0d19e2eae12", 0, 10, "/",
                        "add_two_ints_server", "/add_two_ints", ADD, ADD_HASH,
                        QOS_SERVICES) == DOC_TOKENS[3]
    assert entity_token(EntityKind.CLIENT, 2, "e1dc8d1b45ae8717fce78689cc655685", 0, 10, "/",
                        "add_two_ints_client", "/add_two_ints", ADD, ADD_HASH,
                        QOS_SERVICES) == DOC_TOKENS[4]


@pytest.mark.parametrize("token", DOC_TOKENS)
def test_tokens_of_the_design_doc_parse_and_rebuild(token: str) -> None:
    entity = parse_token(token)
    assert entity.token == token
    assert entity.domain_id == 2 and entity.namespace == "/" and entity.enclave == "/"
    if entity.kind is not EntityKind.NODE:
        assert entity.name in ("/chatter", "/add_two_ints")
        assert entity.qos is not None and entity.qos.reliability is Reliability.RELIABLE


def test_namespaced_node_and_action_service_token() -> None:
    t = ros_types("jazzy")
    names = wire.action_names("/arm_controller/follow_joint_trajectory")
    assert names.send_goal == "/arm_controller/follow_joint_trajectory/_action/send_goal"
    assert names.status == "/arm_controller/follow_joint_trajectory/_action/status"
    token = entity_token(EntityKind.SERVICE, 0, "1f", 3, 7, "/robot1", "arm_controller",
                         "/robot1" + names.send_goal, t.dds_name(FJT_SEND_GOAL),
                         t.type_hash(FJT_SEND_GOAL), QOS_SERVICES)
    assert token == (
        "@ros2_lv/0/1f/3/7/SS/%/%robot1/arm_controller/"
        "%robot1%arm_controller%follow_joint_trajectory%_action%send_goal/"
        "control_msgs::action::dds_::FollowJointTrajectory_SendGoal_/"
        "RIHS01_b13789dddc325a7a962825c45e28c77d37237ec129dd0c34dc5994562938c57f/::,10:,:,:,,")
    assert topic_key(0, "/robot1" + names.send_goal, "T_", "H") == (
        "0/robot1/arm_controller/follow_joint_trajectory/_action/send_goal/T_/H")
    humble = ros_types("humble")
    assert topic_key(0, names.get_result, humble.dds_name(FJT_SEND_GOAL), humble.type_hash(
        FJT_SEND_GOAL)).endswith("FollowJointTrajectory_SendGoal_/TypeHashNotSupported")


def test_qos_text_of_the_usual_profiles() -> None:
    """rmw_zenoh's qos_to_keyexpr leaves every field empty that equals its default (keep last
    42, reliable, volatile, infinite durations, automatic liveliness: its qos.cpp)."""
    assert qos_text(QOS_DEFAULT) == "::,10:,:,:,,"
    assert qos_text(QOS_SERVICES) == "::,10:,:,:,,"
    assert qos_text(QOS_SENSOR_DATA) == "2::,5:,:,:,,"
    assert qos_text(QOS_ACTION_STATUS) == ":1:,1:,:,:,,"
    assert qos_text(Qos(durability=Durability.TRANSIENT_LOCAL, depth=1)) == ":1:,1:,:,:,,"
    assert qos_text(QOS_PARAMETERS) == "::,1000:,:,:,,"
    # rclcpp::SystemDefaultsQoS(), adapted: everything rmw_zenoh's default.
    assert qos_text(QOS_SYSTEM_DEFAULT) == "::,:,:,:,,"
    # joint_trajectory_controller's ~/speed_scaling_input: SystemDefaultsQoS().transient_local()
    speed_scaling = dataclasses.replace(QOS_SYSTEM_DEFAULT, durability=Durability.TRANSIENT_LOCAL)
    assert qos_text(speed_scaling) == ":1:,:,:,:,,"
    assert qos_text(Qos(history=History.KEEP_ALL)) == "::2,10:,:,:,,"
    assert qos_text(Qos(deadline=(1, 500))) == "::,10:1,500:,:,,"


def test_qos_text_parses_back_to_the_adapted_profile() -> None:
    for qos in (QOS_DEFAULT, QOS_SENSOR_DATA, QOS_ACTION_STATUS, QOS_SYSTEM_DEFAULT,
                Qos(lifespan=(3, 0), lease=(0, 7))):
        assert parse_qos(qos_text(qos)) == qos.adapted()
    assert parse_qos("::,:,:,:,,").depth == 42
    for bad in ("", "::,10:,:,:", "::10:,:,:,,", "x::,10:,:,:,,", "9::,10:,:,:,,"):
        with pytest.raises(ValueError):
            parse_qos(bad)


def test_malformed_tokens_are_refused() -> None:
    good = DOC_TOKENS[1]
    for bad in (
        "", "@ros2_lv/2", good.replace("@ros2_lv", "@other"), good.replace("/MS/", "/XX/"),
        good.replace("/0/10/", "/0/x/"), good + "/extra", DOC_TOKENS[0] + "/%chatter",
        good.rsplit("/", 1)[0], good.replace("/%/%/", "//%/"),
    ):
        with pytest.raises(ValueError):
            parse_token(bad)


def test_bad_names_are_refused() -> None:
    with pytest.raises(ValueError):
        node_token(0, "ab", 0, "", "node")  # rcl's namespace is never empty
    with pytest.raises(ValueError):
        node_token(0, "ab", 0, "/", "no*de")
    with pytest.raises(ValueError):
        entity_token(EntityKind.NODE, 0, "ab", 0, 0, "/", "n", "/t", "T_", "H", QOS_DEFAULT)
    with pytest.raises(ValueError):
        topic_key(0, "/", "T_", "H")
    with pytest.raises(ValueError):
        topic_key(0, "/a//b", "T_", "H")
    with pytest.raises(ValueError):
        topic_key(-1, "/a", "T_", "H")


GID = bytes(range(0xA0, 0xB0))
# Design doc, "Publishers": int64 LE sequence number, int64 LE timestamp, one byte of GID
# length (16), the 16 GID bytes.
VECTOR = bytes.fromhex(
    "2a00000000000000"          # sequence number 42
    "00ca9a3b00000000"          # 1_000_000_000 ns
    "10"                        # GID length 16
    "a0a1a2a3a4a5a6a7a8a9aaabacadaeaf")


def test_attachment_bytes() -> None:
    assert len(VECTOR) == ATTACHMENT_SIZE == 33
    assert encode_attachment(42, 1_000_000_000, GID) == VECTOR
    decoded = decode_attachment(VECTOR)
    assert (decoded.sequence_number, decoded.source_timestamp_ns, decoded.gid) == (
        42, 1_000_000_000, GID)
    assert decode_attachment(memoryview(encode_attachment(-1, -5, GID))).sequence_number == -1


def test_attachment_is_zenoh_exts_serialization_of_the_tuple() -> None:
    zenoh = pytest.importorskip("zenoh")
    zext = pytest.importorskip("zenoh.ext")
    for seq, stamp in ((42, 1_000_000_000), (1, 1_765_000_000_123_456_789), (2**63 - 1, 0)):
        ours = encode_attachment(seq, stamp, GID)
        theirs = zext.z_serialize((zext.Int64(seq), zext.Int64(stamp), GID)).to_bytes()
        assert ours == theirs
        back = zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes], zenoh.ZBytes(ours))
        assert tuple(back) == (seq, stamp, GID)


def test_bad_attachments_are_refused() -> None:
    for bad in (b"", VECTOR[:-1], VECTOR + b"\0", VECTOR[:16] + b"\x0f" + VECTOR[17:]):
        with pytest.raises(ValueError):
            decode_attachment(bad)
    with pytest.raises(ValueError):
        encode_attachment(1, 2, b"short")
    with pytest.raises(ValueError):
        encode_attachment(2**63, 0, GID)


def test_new_gids_are_16_bytes_and_distinct() -> None:
    gids = {wire.new_gid() for _ in range(100)}
    assert len(gids) == 100 and all(len(g) == 16 for g in gids)


def test_graph_key() -> None:
    assert wire.graph_key(0) == "@ros2_lv/0/**"
