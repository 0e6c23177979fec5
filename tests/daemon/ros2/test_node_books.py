"""The ROS 2 transport's pure parts: the action server's books (actions.py) and daemon.ros2.

No Zenoh session: these run without a router.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from jtc_hw.daemon.robot import load_robot
from jtc_hw.daemon.transports.ros2 import actions as a
from jtc_hw.daemon.transports.ros2.actions import GoalBook
from jtc_hw.errors import ConfigurationError

from conftest import make_robot_config

S = 10**9


def uuid(n: int) -> bytes:
    return bytes([n]) * 16


# -- the books ----------------------------------------------------------------------------------


def test_accept_releases_events_held_before() -> None:
    book = GoalBook()
    book.hold(7, "feedback")
    book.hold(7, "result")
    book.hold(8, "another transport's")
    goal, held = book.accept(uuid(1), 7, 5 * S)
    assert held == ["feedback", "result"]
    assert goal.status == a.EXECUTING and book.by_id(7) is goal and book.known(uuid(1))
    assert book.accept(uuid(2), 9, 6 * S)[1] == []
    with pytest.raises(ValueError):
        book.accept(uuid(1), 10, 7 * S)


def test_holding_is_bounded_and_keeps_the_last_event() -> None:
    book = GoalBook()
    for goal_id in range(a.EARLY_GOALS + 5):
        book.hold(goal_id, "x")
    assert book.accept(uuid(1), 0, 0)[1] == []  # the oldest held goals were forgotten
    for i in range(a.EARLY_EVENTS + 10):
        book.hold(1000, i)
    book.hold(1000, "result")
    held = book.accept(uuid(2), 1000, 0)[1]
    assert len(held) == a.EARLY_EVENTS and held[-1] == "result"


def test_one_result_and_waiting_requests() -> None:
    book = GoalBook()
    goal, _ = book.accept(uuid(1), 1, 0)
    assert book.want_result(uuid(1), "q1") and book.want_result(uuid(1), "q2")
    assert not book.want_result(uuid(9), "unknown")
    assert book.waiting == 2
    done = book.finish(1, a.SUCCEEDED, 0, "Goal successfully reached!", 3 * S)
    assert done is goal and goal.terminal and goal.ended_ns == 3 * S
    assert book.answered(goal) == ["q1", "q2"] and book.waiting == 0
    assert book.finish(1, a.ABORTED, -4, "second", 4 * S) is None  # one result per goal
    assert goal.status == a.SUCCEEDED
    assert not book.want_result(uuid(1), "late")  # has its result: answered at once
    assert book.finish(99, a.SUCCEEDED, 0, "", 0) is None  # not ours


def test_waiting_requests_are_bounded() -> None:
    book = GoalBook()
    book.accept(uuid(1), 1, 0)
    for i in range(a.MAX_WAITING):
        assert book.want_result(uuid(1), i)
    assert not book.want_result(uuid(1), "one too many")


def test_results_kept_for_the_result_timeout_and_bounded() -> None:
    book = GoalBook()
    book.accept(uuid(1), 1, 0)
    book.finish(1, a.ABORTED, -4, "Aborted due to path tolerance violation", 10 * S)
    assert book.expire(10 * S + a.RESULT_TIMEOUT_NS - 1) == 0 and book.known(uuid(1))
    assert book.expire(10 * S + a.RESULT_TIMEOUT_NS) == 1 and not book.known(uuid(1))
    assert book.by_id(1) is None
    for n in range(a.MAX_KEPT + 3):
        book.accept(bytes(8) + n.to_bytes(8, "little"), 100 + n, n)
        book.finish(100 + n, a.SUCCEEDED, 0, "", n)
    assert book.kept == a.MAX_KEPT
    assert not book.known(bytes(8) + (0).to_bytes(8, "little"))
    assert len(book.status_list()) == a.MAX_STATUS


def test_cancel_rules_as_rcl_action() -> None:
    book = GoalBook()
    g1, _ = book.accept(uuid(1), 1, 1 * S)
    g2, _ = book.accept(uuid(2), 2, 2 * S)
    g3, _ = book.accept(uuid(3), 3, 3 * S)
    book.finish(3, a.SUCCEEDED, 0, "", 4 * S)
    # zero UUID, zero stamp: every goal that can be canceled
    assert book.cancel_targets(a.ZERO_UUID, 0) == (a.ERROR_REJECTED, [g1, g2])
    # zero UUID, a stamp: those accepted at or before it
    assert book.cancel_targets(a.ZERO_UUID, 1 * S) == (a.ERROR_REJECTED, [g1])
    # one UUID
    assert book.cancel_targets(uuid(2), 0) == (a.ERROR_REJECTED, [g2])
    assert book.cancel_targets(uuid(9), 0) == (a.ERROR_UNKNOWN_GOAL_ID, [])
    assert book.cancel_targets(uuid(3), 0) == (a.ERROR_GOAL_TERMINATED, [])
    # a UUID and a stamp: that goal and those accepted at or before the stamp
    assert book.cancel_targets(uuid(2), 1 * S) == (a.ERROR_REJECTED, [g1, g2])
    book.canceling(g2)
    assert g2.status == a.CANCELING
    book.finish(2, a.CANCELED, 0, "", 5 * S)
    assert [g.status for g in book.status_list()] == [a.EXECUTING, a.CANCELED, a.SUCCEEDED]


def test_status_codes_of_our_goal_statuses() -> None:
    from jtc_hw.controller.goals import GoalStatus

    assert [a.status_code(s) for s in (GoalStatus.SUCCEEDED, GoalStatus.CANCELED,
                                       GoalStatus.ABORTED)] == [4, 5, 6]


# -- daemon.ros2 --------------------------------------------------------------------------------


def robot(tmp_path: Path, **ros2: Any) -> Any:
    hardware = [{"name": "m", "kind": "mirror", "joints": ["j1"]}]
    return load_robot(make_robot_config(tmp_path / "d.sock", ["j1"], hardware, ros2=ros2))


def test_ros2_section_defaults_are_rmw_zenohs(tmp_path: Path) -> None:
    settings = robot(tmp_path).daemon.ros2
    assert settings.domain_id == 0 and settings.namespace == "" and settings.distro == "jazzy"
    assert settings.controller_name is None and settings.joint_state_broadcaster
    assert settings.node_name("joint_trajectory_controller") == "joint_trajectory_controller"
    z = settings.zenoh
    assert z.mode == "client" and z.connect == ("tcp/127.0.0.1:7447",) and z.listen == ()
    named = robot(tmp_path, controller_name="arm_controller", namespace="robot1/",
                  distro="humble", domain_id=7).daemon.ros2
    assert named.node_name("x") == "arm_controller" and named.namespace == "/robot1"
    assert named.distro == "humble" and named.domain_id == 7


@pytest.mark.parametrize(("ros2", "path", "words"), [
    ({"distro": "iron"}, "daemon.ros2.distro", "jazzy"),
    ({"domain_id": 300}, "daemon.ros2.domain_id", "232"),
    ({"namespace": "/9lives"}, "daemon.ros2.namespace", "not a ROS name"),
    ({"controller_name": "arm-controller"}, "daemon.ros2.controller_name", "not a ROS node"),
    ({"zenoh": {"listen": ["tcp/0.0.0.0:7447"]}}, "daemon.ros2.zenoh.listen",
     "neither TLS nor authentication"),
    ({"zenoh": {"connect": [], "listen": []}}, "daemon.ros2.zenoh", "reach nobody"),
    ({"zenoh": {"connect": ["127.0.0.1:7447"]}}, "daemon.ros2.zenoh", "<protocol>/<address>"),
    ({"zenoh": {"mode": "router"}}, "daemon.ros2.zenoh.mode", "client"),
    ({"zenoh": {"config": "missing.json5"}}, "daemon.ros2.zenoh.config", "not a file"),
    ({"colour": "blue"}, "daemon.ros2", "colour"),
])
def test_ros2_section_errors_name_the_key(tmp_path: Path, ros2: dict[str, Any], path: str,
                                          words: str) -> None:
    with pytest.raises(ConfigurationError) as info:
        robot(tmp_path, **ros2)
    assert info.value.path.startswith(path) and words in str(info.value), str(info.value)


def test_ros2_listen_beyond_loopback_with_authentication(tmp_path: Path) -> None:
    pytest.importorskip("zenoh")
    config = tmp_path / "z.json5"
    config.write_text(json.dumps({"transport": {"auth": {"usrpwd": {
        "user": "robot", "password": "a long enough password"}}}}))
    z = robot(tmp_path, zenoh={"listen": ["tcp/0.0.0.0:7447"], "config": str(config)})
    assert z.daemon.ros2.zenoh.listen == ("tcp/0.0.0.0:7447",)


# -- messages -----------------------------------------------------------------------------------


@pytest.mark.parametrize("distro", ["humble", "jazzy", "rolling"])
def test_messages_round_trip_through_rosbags(distro: str) -> None:
    """What the transport writes reads back with rosbags' deserializer (the distro's types),
    the hand-written send_goal response byte for byte as rosbags writes it."""
    import numpy as np

    from jtc_hw.controller.goals import GoalFeedback
    from jtc_hw.controller.trajectory import TrajectorySample
    from jtc_hw.daemon.transports.ros2.messages import Messages, make
    from jtc_hw.daemon.transports.ros2.types import ros_types

    types = ros_types(distro)
    store = types.typestore
    m = Messages(types, ["a", "b"])
    name = "control_msgs/action/FollowJointTrajectory_SendGoal_Response"
    for accepted, stamp in ((True, 1_700_000_000_123_456_789), (False, 0)):
        ours = m.send_goal_response(accepted, stamp)
        theirs = bytes(store.serialize_cdr(make(store, name, accepted=accepted, stamp={
            "sec": stamp // S, "nanosec": stamp % S}), name))
        assert ours == theirs
    snapshot = {
        "actual": {"positions": [0.1, 0.2], "velocities": None, "time_from_start": 1.5},
        "desired": {"positions": [0.1, 0.3], "velocities": [0.0, 1.0], "accelerations": None,
                    "effort": None, "time_from_start": 1.5},
        "error": {"positions": [0.0, 0.1], "velocities": [None, None], "accelerations": None},
        "output": {"positions": [0.1, 0.3]},
        "speed_scaling": {"factor": 0.5, "target": 0.5},
    }
    js = store.deserialize_cdr(m.joint_state(snapshot, 5 * S + 7), "sensor_msgs/msg/JointState")
    assert list(js.name) == ["a", "b"] and js.position.tolist() == [0.1, 0.2]
    assert np.isnan(js.velocity).all() and (js.header.stamp.sec, js.header.stamp.nanosec) == (5, 7)
    cs = store.deserialize_cdr(m.controller_state(snapshot, S),
                               "control_msgs/msg/JointTrajectoryControllerState")
    reference = cs.desired if distro == "humble" else cs.reference
    assert reference.positions.tolist() == [0.1, 0.3]
    assert (reference.time_from_start.sec, reference.time_from_start.nanosec) == (1, 500_000_000)
    if distro != "humble":
        assert cs.speed_scaling_factor == 0.5 and cs.feedback.positions.tolist() == [0.1, 0.2]
    sample = TrajectorySample(np.array([1.0, 2.0]), np.zeros(2), np.zeros(2), np.zeros(2))
    feedback = GoalFeedback(3, 0, 0.25, sample, np.array([0.9, 2.1]), None, np.zeros((3, 2)))
    fb = store.deserialize_cdr(m.feedback(uuid(4), feedback, S),
                               "control_msgs/action/FollowJointTrajectory_FeedbackMessage")
    assert bytes(fb.goal_id.uuid) == uuid(4) and fb.feedback.actual.positions.tolist() == [0.9, 2.1]
    book = GoalBook()
    book.accept(uuid(1), 1, 2 * S)
    arr = store.deserialize_cdr(m.status_array(book.status_list()),
                                "action_msgs/msg/GoalStatusArray")
    assert [(bytes(s.goal_info.goal_id.uuid), s.status) for s in arr.status_list] == [
        (uuid(1), a.EXECUTING)]
    cancel = "action_msgs/srv/CancelGoal_Request"
    request = bytes(store.serialize_cdr(make(store, cancel, goal_info={
        "goal_id": {"uuid": np.frombuffer(uuid(2), np.uint8).copy()},
        "stamp": {"sec": 3, "nanosec": 4}}), cancel))
    assert m.cancel_request(request) == (uuid(2), 3 * S + 4)


def test_small_requests_refuse_bad_bytes() -> None:
    from jtc_hw.daemon.transports.ros2.cdr import CdrError
    from jtc_hw.daemon.transports.ros2.messages import Messages
    from jtc_hw.daemon.transports.ros2.types import ros_types

    m = Messages(ros_types("jazzy"), ["a"])
    for bad in (b"", b"\x00\x01\x00\x00", b"\x00\x01\x00\x00\x01", b"\x00" * 10_000):
        for decode in (m.cancel_request, m.get_result_request, m.query_state_request,
                       m.speed_scaling):
            with pytest.raises(CdrError):
                decode(bad)


# -- the outbox and the callback guard -----------------------------------------------------------


def test_outbox_drops_droppable_first_and_runs_in_order() -> None:
    import threading

    from jtc_hw.daemon.transports.ros2.outbox import Outbox

    gate, blocked = threading.Event(), threading.Event()
    ran: list[int] = []
    outbox = Outbox(size=2, hard_cap=3, label="ros2")

    def block() -> None:
        blocked.set()
        gate.wait(10.0)

    try:
        assert outbox.put(block)
        assert blocked.wait(10.0)  # the thread is busy: the others queue up
        assert outbox.offer(lambda: ran.append(1)) and outbox.offer(lambda: ran.append(2))
        assert not outbox.offer(lambda: ran.append(3))  # beyond size: a state, dropped
        assert outbox.put(lambda: ran.append(4))  # a result still goes
        assert not outbox.put(lambda: ran.append(5))  # beyond the hard cap: lost
    finally:
        gate.set()
        outbox.close(5.0)
    assert ran == [1, 2, 4] and (outbox.dropped, outbox.lost) == (1, 1)
    assert not outbox.put(lambda: None)  # closed


def test_guard_never_raises_into_zenoh() -> None:
    import collections

    from jtc_hw.daemon.transports.ros2.outbox import guard

    class Query:
        dropped = False

        def drop(self) -> None:
            self.dropped = True

    counters: collections.Counter[str] = collections.Counter()
    query = Query()
    guard(lambda item: 1 / 0, counters, query=True)(query)
    assert counters["callback_errors"] == 1 and query.dropped


# -- parameters (params.py) -----------------------------------------------------------------------


def test_parameter_values_both_ways() -> None:
    from types import SimpleNamespace

    from jtc_hw.daemon.transports.ros2 import params as p

    for value, kind in ((True, p.BOOL), (3, p.INTEGER), (0.5, p.DOUBLE), ("spline", p.STRING),
                        ([True, False], p.BOOL_ARRAY), ([1, 2], p.INTEGER_ARRAY),
                        ([1, 2.5], p.DOUBLE_ARRAY), (["a", "b"], p.STRING_ARRAY),
                        (None, p.NOT_SET)):
        fields = p.to_parameter_value(value)
        assert fields["type"] == kind
        msg = SimpleNamespace(**{"bool_value": False, "integer_value": 0, "double_value": 0.0,
                                 "string_value": "", "bool_array_value": [],
                                 "integer_array_value": [], "double_array_value": [],
                                 "string_array_value": [], **fields})
        back = p.from_parameter_value(msg)
        assert back == (list(value) if isinstance(value, list) else value)
    with pytest.raises(ValueError):
        p.from_parameter_value(SimpleNamespace(type=p.BYTE_ARRAY))


def test_list_parameters_as_rclcpp() -> None:
    from jtc_hw.daemon.transports.ros2.params import list_names

    names = ["cmd_timeout", "constraints.goal_time", "constraints.j1.goal", "gains.j1.p"]
    assert list_names(names, [], 0) == (names, ["constraints", "constraints.j1", "gains.j1"])
    assert list_names(names, [], 1) == (["cmd_timeout"], [])
    assert list_names(names, ["constraints"], 1) == (["constraints.goal_time"], ["constraints"])
    assert list_names(names, ["constraints", "gains"], 0)[0] == names[1:]
    assert list_names(names, ["cmd_timeout"], 0) == (["cmd_timeout"], [])


# -- jtc-hw check and status --------------------------------------------------------------------


def test_check_and_status_say_the_ros2_section(tmp_path: Path) -> None:
    from jtc_hw.cli.run import _ros2_line
    from jtc_hw.cli.status import status_lines

    daemon = robot(tmp_path, controller_name="arm_controller", namespace="robot1").daemon
    assert _ros2_line(daemon, "joint_trajectory_controller") == (
        "  ros2            node /robot1/arm_controller, /joint_states in domain 0, jazzy "
        "(client; connect tcp/127.0.0.1:7447)")
    off = load_robot(make_robot_config(tmp_path / "d.sock", ["j1"], [
        {"name": "m", "kind": "mirror", "joints": ["j1"]}])).daemon
    assert _ros2_line(off, "x") == "  ros2            off (daemon.ros2)"
    lines = status_lines({"ros2": {"node": "/arm_controller", "domain_id": 0,
                                   "goals_accepted": 3, "goals_rejected": 1, "goals_running": 1,
                                   "joint_trajectory_dropped": 2, "published": 40,
                                   "dropped": 0}})
    assert ("ros2          node /arm_controller in domain 0: goals accepted 3, rejected 1, "
            "running 1; samples dropped 2; published 40, dropped 0") in lines
    assert not any(x.startswith("ros2") for x in status_lines({}))


def test_without_rosbags_the_transport_says_what_to_install(monkeypatch: pytest.MonkeyPatch
                                                           ) -> None:
    """The daemon imports the transport (registry) without rosbags; starting it says the
    extra to install, as a ConfigurationError naming daemon.ros2 (exit 2, one line)."""
    import asyncio
    import builtins
    from types import SimpleNamespace

    from jtc_hw.daemon.ros2_config import Ros2Settings
    from jtc_hw.daemon.transports.ros2.node import Ros2Interface

    real_import = builtins.__import__

    def no_rosbags(name: str, *args: Any, **kwargs: Any) -> Any:
        if name.startswith("rosbags") or (name == "types" and len(args) > 3 and args[3] > 0):
            raise ImportError("no rosbags here", name="rosbags")
        return real_import(name, *args, **kwargs)

    requests = SimpleNamespace(backend=SimpleNamespace(joint_names=("a",)),
                               max_message_bytes=1 << 20, status_sections={})
    transport = Ros2Interface(Ros2Settings(), "c", requests)  # type: ignore[arg-type]
    monkeypatch.setattr(builtins, "__import__", no_rosbags)
    with pytest.raises(ConfigurationError) as info:
        asyncio.run(transport.start())
    assert info.value.path == "daemon.ros2" and "jtc_hw[ros2]" in str(info.value)
