"""The harness before the transport: two independent ROS 2 peers (tests/helpers/ros2_peer.py,
on zenoh-ros2-sdk) talk through the router fixture, and the peer's type hashes agree with the
values rmw_zenoh's design doc quotes and with rosbags'."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import ros2_peer
from helpers.ros2_peer import FJT, STORE, OfflineTypeError, Ros2Peer

pytestmark = pytest.mark.usefixtures("no_leaks")

WAIT_S = 10.0


@pytest.fixture
def two(router: str) -> Iterator[tuple[Ros2Peer, Ros2Peer]]:
    with Ros2Peer(router, node_name="talker") as a, Ros2Peer(router, node_name="listener") as b:
        yield a, b


# -- hashes (no network) ---------------------------------------------------------------------


def test_hashes_match_the_design_doc() -> None:
    # ros2/rmw_zenoh docs/design.md @ 99a6a2bd10b949052f4f12c5854825dc005e95a5, "Topic and
    # Service name mapping to Zenoh key expressions"
    assert ros2_peer.message_hash("std_msgs/msg/String") == (
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert ros2_peer.service_hash("example_interfaces/srv/AddTwoInts") == (
        "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a")


@pytest.mark.parametrize("typename", [
    "sensor_msgs/msg/JointState", "trajectory_msgs/msg/JointTrajectory",
    "action_msgs/msg/GoalStatusArray", "control_msgs/msg/JointTrajectoryControllerState",
    "control_msgs/msg/SpeedScalingFactor", f"{FJT}_FeedbackMessage"])
def test_message_hashes_agree_with_rosbags(typename: str) -> None:
    """Two implementations of REP-2016 (the sdk's, rosbags') on the same definitions."""
    assert ros2_peer.message_hash(typename) == STORE.hash_rihs01(typename)


def test_service_hash_agrees_with_the_sdks_own_for_a_plain_service() -> None:
    from zenoh_ros2_sdk import utils

    srv = "control_msgs/srv/QueryTrajectoryState"
    assert ros2_peer.service_hash(srv) == utils.compute_service_type_hash(
        srv, ros2_peer.msg_text(f"{srv}_Request"), ros2_peer.msg_text(f"{srv}_Response"),
        {**ros2_peer.JAZZY.dependencies(f"{srv}_Request"),
         **ros2_peer.JAZZY.dependencies(f"{srv}_Response")})


def test_the_distros_differ_where_upstream_does() -> None:
    """Humble writes no hash; Kilted/Rolling's FollowJointTrajectory feedback (control_msgs
    >= 6.3) has two more fields, so another hash; Humble's controller_state has no
    speed_scaling_factor and Humble has no SpeedScalingFactor."""
    humble, jazzy, rolling = (ros2_peer.types(d) for d in ("humble", "jazzy", "rolling"))
    assert humble.message_hash("sensor_msgs/msg/JointState") == "TypeHashNotSupported"
    assert humble.service_hash(f"{FJT}_SendGoal") == "TypeHashNotSupported"
    feedback = f"{FJT}_FeedbackMessage"
    assert rolling.message_hash(feedback) != jazzy.message_hash(feedback)
    assert rolling.make(f"{FJT}_Feedback").index == 0
    state = "control_msgs/msg/JointTrajectoryControllerState"
    assert hasattr(humble.make(state), "desired")
    assert not hasattr(humble.make(state), "speed_scaling_factor")
    assert jazzy.make(state).speed_scaling_factor == 0.0
    with pytest.raises(OfflineTypeError):
        humble.make("control_msgs/msg/SpeedScalingFactor")
    with pytest.raises(OfflineTypeError):
        humble.message_hash("control_msgs/msg/SpeedScalingFactor")
    with pytest.raises(ValueError):
        ros2_peer.types("iron")


# -- two peers through the router --------------------------------------------------------------


def test_discovery_of_the_other_peers_node_and_topic(two: tuple[Ros2Peer, Ros2Peer]) -> None:
    a, b = two
    a.publish("/chatter", "std_msgs/msg/String", {"data": "hi"})
    b.wait_until(lambda: "/talker" in b.nodes() and "/chatter" in b.topics(), WAIT_S)
    assert b.topics()["/chatter"] == ["std_msgs/msg/String"]
    (pub,) = b.publishers("/chatter")
    assert pub["node_name"] == "talker"
    assert pub["type_hash"] == ros2_peer.message_hash("std_msgs/msg/String")
    assert pub["qos"] == "::,10:,:,:,,"  # the design doc's default
    a.close_entities()
    b.wait_until(lambda: "/chatter" not in b.topics() and "/talker" not in b.nodes(), WAIT_S)


def test_joint_state_published_by_one_is_echoed_by_the_other(
        two: tuple[Ros2Peer, Ros2Peer]) -> None:
    a, b = two
    sub = b.subscribe("/joint_states", "sensor_msgs/msg/JointState")
    msg = {"header": {"stamp": {"sec": 3, "nanosec": 4}}, "name": ["shoulder", "elbow"],
           "position": [0.5, -1.25], "velocity": [0.0, 0.1], "effort": []}
    a.publish("/joint_states", "sensor_msgs/msg/JointState", msg, wait_for_subscriber=WAIT_S)
    (got,) = sub.take(1, WAIT_S)
    assert got.name == ["shoulder", "elbow"]
    np.testing.assert_array_equal(got.position, [0.5, -1.25])
    assert (got.header.stamp.sec, got.header.stamp.nanosec) == (3, 4)


def test_a_service_served_by_one_is_called_by_the_other(two: tuple[Ros2Peer, Ros2Peer]) -> None:
    a, b = two
    srv = "example_interfaces/srv/AddTwoInts"
    a.serve("/add_two_ints", srv, lambda req: ros2_peer.make(f"{srv}_Response", sum=req.a + req.b))
    b.wait_until(lambda: bool(b.servers("/add_two_ints")), WAIT_S)
    assert b.call("/add_two_ints", srv, {"a": 2, "b": 40}, WAIT_S).sum == 42
    assert b.services()["/add_two_ints"] == [srv]


def test_raw_bytes_for_the_bad_input_tests(two: tuple[Ros2Peer, Ros2Peer]) -> None:
    """A payload sent as bytes goes as it is: good CDR decodes on the other side; bad CDR in
    a request gets the sdk server's error reply, raised as Ros2CallError."""
    a, b = two
    sub = b.subscribe("/joint_states", "sensor_msgs/msg/JointState")
    good = ros2_peer.JAZZY.make("sensor_msgs/msg/JointState", name=["raw"])
    a.publish("/joint_states", "sensor_msgs/msg/JointState",
              bytes(STORE.serialize_cdr(good, "sensor_msgs/msg/JointState")),
              wait_for_subscriber=WAIT_S)
    assert sub.take(1, WAIT_S)[0].name == ["raw"]
    srv = "example_interfaces/srv/AddTwoInts"
    a.serve("/add", srv, lambda req: ros2_peer.make(f"{srv}_Response", sum=req.a + req.b))
    b.wait_until(lambda: bool(b.servers("/add")), WAIT_S)
    # The server's token can be seen before its queryable is routed to us (a query then ends
    # with no reply at all): ask until one is answered, then the route is there.
    deadline = time.monotonic() + WAIT_S
    while True:
        call = b.request("/add", srv, {"a": 1, "b": 1})
        assert call.done.wait(WAIT_S), "the query never ended"
        if call.replies or call.errors:
            break
        assert time.monotonic() < deadline, "/add: never routed"
    with pytest.raises(ros2_peer.Ros2CallError):
        b.request("/add", srv, b"\x00\x01").first(WAIT_S, "/add")
    raw = b.request("/add", srv, {"a": 1, "b": 2}, decode=False).first(WAIT_S, "/add")
    assert STORE.deserialize_cdr(raw, "example_interfaces/srv/msg/AddTwoInts_Response").sum == 3


def test_the_action_client_against_an_action_server_made_of_sdk_parts(
        two: tuple[Ros2Peer, Ros2Peer]) -> None:
    """The action client's wire names and types, against a minimal server built here from the
    sdk's service servers and publishers (a stand-in for the transport): accept, feedback,
    status, exactly one result, cancel."""
    a, b = two
    action = "/arm_controller/follow_joint_trajectory"
    goals: list[Any] = []

    def send_goal(req: Any) -> Any:
        goals.append(req)
        feedback = {"goal_id": {"uuid": req.goal_id.uuid},
                    "feedback": {"joint_names": list(req.goal.trajectory.joint_names)}}
        a.publish(f"{action}/_action/feedback", f"{FJT}_FeedbackMessage", feedback)
        a.publish(f"{action}/_action/status", "action_msgs/msg/GoalStatusArray", {"status_list": [
            {"goal_info": {"goal_id": {"uuid": req.goal_id.uuid}}, "status": 4}]},
            qos=ros2_peer.STATUS_QOS)
        return ros2_peer.make(f"{FJT}_SendGoal_Response", accepted=True)

    a.serve(f"{action}/_action/send_goal", f"{FJT}_SendGoal", send_goal)
    a.serve(f"{action}/_action/get_result", f"{FJT}_GetResult", lambda req: ros2_peer.make(
        f"{FJT}_GetResult_Response", status=4, result={"error_string": "done"}))
    a.serve(f"{action}/_action/cancel_goal", "action_msgs/srv/CancelGoal",
            lambda req: ros2_peer.make("action_msgs/srv/CancelGoal_Response", return_code=3))
    # what `ros2 action list` needs: the feedback topic, from a publisher; and the status
    a.publish(f"{action}/_action/feedback", f"{FJT}_FeedbackMessage", {})
    a.publish(f"{action}/_action/status", "action_msgs/msg/GoalStatusArray", {},
              qos=ros2_peer.STATUS_QOS)
    assert not b.action_ready(f"{action}_not")
    b.wait_for_action(action, WAIT_S)
    assert b.actions()[action] == [FJT]
    b._action_topics(action, FJT)  # subscribed before the goal, as send_goal does
    a.wait_for_subscriber(f"{action}/_action/feedback", f"{FJT}_FeedbackMessage", WAIT_S)

    handle = b.send_goal(action, {"trajectory": {"joint_names": ["shoulder"], "points": [
        {"positions": [1.0], "time_from_start": {"sec": 1}}]}}, timeout=WAIT_S)
    assert handle.accepted
    assert bytes(goals[0].goal_id.uuid) == handle.goal_id
    assert handle.wait_feedback(1, WAIT_S)[0].joint_names == ["shoulder"]
    handle.wait_status(4, WAIT_S)
    status, result = handle.result(WAIT_S)
    assert (status, result.error_string) == (4, "done")
    assert handle.result_call is not None and len(handle.result_call.replies) == 1
    assert handle.cancel(WAIT_S).return_code == 3


def test_humble_peers_meet_on_no_hash_and_never_meet_jazzys(router: str) -> None:
    state = "control_msgs/msg/JointTrajectoryControllerState"
    with Ros2Peer(router, node_name="h", distro="humble") as h, \
            Ros2Peer(router, node_name="j") as j, \
            Ros2Peer(router, node_name="h2", distro="humble") as h2:
        from_humble, from_jazzy = h2.subscribe("/c/controller_state", state), \
            j.subscribe("/c/controller_state", state)
        h.publish("/c/controller_state", state, {"joint_names": ["a"]}, wait_for_subscriber=WAIT_S)
        assert from_humble.take(1, WAIT_S)[0].joint_names == ["a"]
        (pub,) = j.publishers("/c/controller_state")
        assert pub["type_hash"] == "TypeHashNotSupported"
        # the same topic, another key: the Jazzy subscription can never match
        assert from_humble._sub.keyexpr.endswith("/TypeHashNotSupported")
        assert from_jazzy._sub.keyexpr.split("/")[-1].startswith("RIHS01_")


def test_a_second_process_echoes_what_this_one_publishes(router: str) -> None:
    """``python -m helpers.ros2_peer echo``: the peer as a process of its own (the issue's
    "a second process using the independent client sees /joint_states")."""
    tests = Path(__file__).resolve().parents[2]
    cmd = [sys.executable, "-m", "helpers.ros2_peer", "--endpoint", router, "--timeout",
           str(WAIT_S), "echo", "/joint_states", "sensor_msgs/msg/JointState"]
    with subprocess.Popen(cmd, cwd=tests, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True) as proc, Ros2Peer(router) as a:
        try:
            a.publish("/joint_states", "sensor_msgs/msg/JointState",
                      {"name": ["joint1"], "position": [0.25]}, wait_for_subscriber=WAIT_S * 3)
            out, err = proc.communicate(timeout=WAIT_S * 3)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 0, err
    msg = json.loads(out.splitlines()[0])
    assert (msg["name"], msg["position"]) == (["joint1"], [0.25])


def test_a_second_process_sends_a_goal(router: str) -> None:
    """``python -m helpers.ros2_peer send_goal``: accepted, the feedback, the result, one JSON
    line each, exit 0 on SUCCEEDED. The stand-in server publishes the feedback while it
    accepts the goal, once the client's feedback subscription has matched."""
    action = "/arm_controller/follow_joint_trajectory"
    tests = Path(__file__).resolve().parents[2]
    with Ros2Peer(router) as a:
        def send_goal(req: Any) -> Any:
            # The feedback goes out before the acceptance (the client subscribes first), so it
            # is delivered a whole get_result round trip before the result: a sample and a
            # reply travel apart, and one sent just before the result could come after it.
            a.publish(f"{action}/_action/feedback", f"{FJT}_FeedbackMessage",
                      {"goal_id": {"uuid": req.goal_id.uuid}, "feedback": {"joint_names": ["j"]}},
                      wait_for_subscriber=WAIT_S)
            return ros2_peer.make(f"{FJT}_SendGoal_Response", accepted=True)

        a.serve(f"{action}/_action/send_goal", f"{FJT}_SendGoal", send_goal)
        a.serve(f"{action}/_action/get_result", f"{FJT}_GetResult",
                lambda req: ros2_peer.make(f"{FJT}_GetResult_Response", status=4,
                                           result={"error_string": "fine"}))
        goal = json.dumps({"trajectory": {"joint_names": ["j"], "points": [
            {"positions": [0.5], "time_from_start": {"sec": 1}}]}})
        proc = subprocess.run(
            [sys.executable, "-m", "helpers.ros2_peer", "--endpoint", router, "--timeout",
             str(WAIT_S), "send_goal", action, goal], cwd=tests, capture_output=True, text=True,
            timeout=WAIT_S * 3)
    assert proc.returncode == 0, proc.stderr
    lines = [json.loads(line) for line in proc.stdout.splitlines()]
    assert lines[0] == {"accepted": True}
    assert lines[1]["feedback"]["joint_names"] == ["j"]
    assert lines[-1]["status"] == 4 and lines[-1]["result"]["error_string"] == "fine"


# -- offline ------------------------------------------------------------------------------------


def test_the_sdk_never_reaches_for_the_network(router: str,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The sdk's downloader (git clones of message packages) is replaced: building entities,
    publishing, echoing and asking for a type the store lacks open no connection beyond
    loopback and start no process."""
    attempts: list[str] = []
    real_connect = socket.socket.connect

    def connect(self: socket.socket, address: Any) -> Any:
        if not (isinstance(address, str) or str(address[0]) in ("127.0.0.1", "::1", "localhost")):
            attempts.append(f"connect {address}")
            raise OSError("no network in this test")
        return real_connect(self, address)

    def popen(*args: Any, **_kwargs: Any) -> Any:
        attempts.append(f"popen {args}")
        raise OSError("no processes in this test")

    monkeypatch.setattr(socket.socket, "connect", connect)
    monkeypatch.setattr(subprocess, "Popen", popen)
    with Ros2Peer(router) as a, Ros2Peer(router) as b:
        sub = b.subscribe("/joint_states", "sensor_msgs/msg/JointState")
        a.publish("/joint_states", "sensor_msgs/msg/JointState", {"name": ["j"]},
                  wait_for_subscriber=WAIT_S)
        assert sub.take(1, WAIT_S)[0].name == ["j"]
        with pytest.raises((OfflineTypeError, KeyError)):
            a.publish("/odd", "odd_msgs/msg/Unknown", {})
        with pytest.raises(OfflineTypeError):  # the sdk's own path to a definition
            a.session.register_message_type(None, "odd_msgs/msg/Unknown")
    assert attempts == []


def test_action_hashes_match_rosidls() -> None:
    """An action's services hash as rosidl hashes them: nav2_msgs/action/Wait, against the
    type description rosidl_generator_type_description wrote for it in a colcon install
    (thomasankara/hive_ws2, install/nav2_msgs/share/nav2_msgs/action/Wait.json at
    a983b6c8e23eae4b246b0cc093a2077cdaa8acec; its fields are the definitions below). The
    ServiceEventInfo line checks ``char[16] client_gid`` hashed as ``uint8[16]``."""
    ros2_peer.register_action(
        "nav2_msgs/action/Wait", "builtin_interfaces/Duration time\n",
        "builtin_interfaces/Duration total_elapsed_time\nuint16 error_code\nstring error_msg\n",
        "builtin_interfaces/Duration time_left\n")
    hashes = {
        "nav2_msgs/action/Wait_SendGoal":
            "aa768b9f4248c70a9c68fcf3a52f10300d4b0d21cad3cf39f01f4f3d248c2490",
        "nav2_msgs/action/Wait_GetResult":
            "6fa1323df11147db06a24a126119f542104f535108774b930b8047cfa34df466",
    }
    for srv, digest in hashes.items():
        assert ros2_peer.service_hash(srv) == f"RIHS01_{digest}", srv
    messages = {
        "nav2_msgs/action/Wait_FeedbackMessage":
            "cb143310afa60cc18ef814ac127a730d4ee190828ce9b9a943fa8f0cb1a09f7c",
        "nav2_msgs/action/Wait_SendGoal_Request":
            "2153054419debd2560f3b9514eeda1b14b31f029ff03383a519568b5f67ba18a",
        "nav2_msgs/action/Wait_GetResult_Response":
            "c89ac345ba5364c16099f24b1166e1ca1dd13a0b0f7c7df283cf36f8948759cb",
        "service_msgs/msg/ServiceEventInfo":
            "41bcbbe07a75c9b52bc96bfd5c24d7f0fc0a08c0cb7921b3373c5732345a6f45",
    }
    for msg, digest in messages.items():
        assert ros2_peer.message_hash(msg) == f"RIHS01_{digest}", msg
