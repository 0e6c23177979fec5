"""``/controller_manager/list_controllers``: what ``ros2 control list_controllers`` and
rqt_joint_trajectory_controller ask first (controller_manager.py).

The hashes are golden values rosidl generated (cited below), not computed by the code under
test; the end-to-end part asks the daemon with the independent client of
``tests/helpers/ros2_peer.py``. Every wait is on an event with a bound.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import JOINTS, WAIT_S, connect
from helpers.ros2_peer import Ros2Peer

from jtc_hw.daemon.transports.ros2 import controller_manager as cm
from jtc_hw.daemon.transports.ros2.messages import Messages
from jtc_hw.daemon.transports.ros2.types import (
    DISTROS,
    LIST_CONTROLLERS,
    TYPE_HASH_NOT_SUPPORTED,
    ros_types,
)

from .test_node_books import robot
from .test_node_e2e import _router, ros2_daemon

pytestmark = pytest.mark.usefixtures("daemon_log_on_failure")

STATE = "controller_manager_msgs/msg/ControllerState"
# controller_manager_msgs (ros2_control's jazzy layout: is_async, update_rate,
# exported_state_interfaces) as rosidl generated it: github.com/dhruvigoradia/ros2-warehouse-robot,
# build/controller_manager_msgs/rosidl_generator_c/controller_manager_msgs/srv/detail/
# list_controllers__description.c (the service, its halves, and the EXPECTED_HASH of the
# ControllerState and ChainConnection it references). No Humble value is needed: Humble has no
# hashes. No kilted/rolling-generated file was found; their .msg texts equal jazzy's.
LIST_CONTROLLERS_HASHES = {
    LIST_CONTROLLERS: "4f8e36bb1fa5afdeba45c2d56ae6a2097b1493a253f961dd6290c085033bd189",
    LIST_CONTROLLERS + "_Request":
        "fb985bc3dcc9b07c7d3af4b46787afa5a09ac79da6465ea42b5696f9355c1f70",
    LIST_CONTROLLERS + "_Response":
        "445459f6b387bda67942d8bea4dfee82dedf12388317e68d5bc4513993799b86",
    LIST_CONTROLLERS + "_Event":
        "33f64fb8f4d3a7415113d5b6a9fa74f91c732c5f4d491b0077cfe8f7ca15cb2b",
    STATE: "9a8780ab9814b6032978a07c6c7033cf1a7894ac8d948a6fb72afea07b04cc83",
    "controller_manager_msgs/msg/ChainConnection":
        "2daecd1da4b171f48b291c79747657a651eb1ab8821b68e38b1c88c736bba91c",
}


@pytest.mark.parametrize("distro", ["jazzy", "kilted", "rolling"])
def test_list_controllers_hashes_are_rosidls(distro: str) -> None:
    types = ros_types(distro)
    for name, digest in LIST_CONTROLLERS_HASHES.items():
        assert types.type_hash(name) == "RIHS01_" + digest, name
    dds = "controller_manager_msgs::srv::dds_::ListControllers_"
    assert types.dds_name(LIST_CONTROLLERS) == dds


def test_humble_controller_state_is_humbles() -> None:
    types = ros_types("humble")
    assert types.type_hash(LIST_CONTROLLERS) == TYPE_HASH_NOT_SUPPORTED
    fields = [name for name, _ in types.typestore.fielddefs[STATE][1]]
    assert "update_rate" not in fields and "is_async" not in fields
    assert fields[-2:] == ["reference_interfaces", "chain_connections"]


CONFIG = {"command_interfaces": ["position", "velocity"], "state_interfaces": ["position"],
          "update_rate": 500.0}


def test_the_controller_and_the_broadcaster_as_upstream_lists_them() -> None:
    active = {"controller": {"active": True, "fault": None}}
    jtc, jsb = cm.controllers("arm", ["a", "b"], CONFIG, active, broadcaster=True)
    assert (jtc.name, jtc.state, jtc.type, jtc.update_rate) == ("arm", "active", cm.JTC_TYPE, 500)
    assert jtc.claimed_interfaces == jtc.required_command_interfaces == (
        "a/position", "a/velocity", "b/position", "b/velocity")
    assert jtc.required_state_interfaces == ("a/position", "b/position")
    assert (jsb.name, jsb.type, jsb.state) == ("joint_state_broadcaster", cm.BROADCASTER_TYPE,
                                               "active")
    assert jsb.claimed_interfaces == () and jsb.required_state_interfaces == ("a/position",
                                                                              "b/position")
    for status in ({"controller": {"active": True, "fault": "encoder lost"}},
                   {"controller": {"active": False}}, {}):
        (entry,) = cm.controllers("arm", ["a"], CONFIG, status, broadcaster=False)
        assert entry.state == "inactive" and entry.claimed_interfaces == ()
        assert entry.required_command_interfaces == ("a/position", "a/velocity")
    # a speed scaling interface configured: upstream's JTC requires it after the joints'
    scaled = {**CONFIG, "speed_scaling": {"state_interface": "speed_scaling/factor",
                                          "command_interface": "speed_scaling/target"}}
    jtc, jsb = cm.controllers("arm", ["a"], scaled, active, broadcaster=True)
    assert jtc.required_command_interfaces == ("a/position", "a/velocity",
                                               "speed_scaling/target")
    assert jtc.required_state_interfaces == ("a/position", "speed_scaling/factor")
    assert jsb.required_state_interfaces == ("a/position",)


@pytest.mark.parametrize("distro", DISTROS)
def test_response_round_trips_in_each_distro(distro: str) -> None:
    types = ros_types(distro)
    entries = cm.controllers("arm", ["a"], CONFIG, {"controller": {"active": True}}, True)
    data = cm.list_controllers_response(Messages(types, ["a"]), entries)
    msg = types.typestore.deserialize_cdr(data, f"{LIST_CONTROLLERS}_Response")
    jtc, jsb = msg.controller
    assert (jtc.name, jtc.state, jtc.type) == ("arm", "active", cm.JTC_TYPE)
    assert list(jtc.claimed_interfaces) == ["a/position", "a/velocity"]
    assert list(jsb.required_state_interfaces) == ["a/position"]
    assert not jtc.is_chainable and list(jtc.chain_connections) == []
    if distro != "humble":
        assert jtc.update_rate == 500 and not jtc.is_async


def test_the_setting_is_on_by_default(tmp_path: Path) -> None:
    assert robot(tmp_path).daemon.ros2.controller_manager
    assert not robot(tmp_path, controller_manager=False).daemon.ros2.controller_manager


# -- end to end ---------------------------------------------------------------------------------

C = "/joint_trajectory_controller"
SERVICE = "/controller_manager/list_controllers"


@pytest.fixture(scope="module")
def graph(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Ros2Peer, Any]]:
    router, endpoint = _router()
    try:
        daemon = ros2_daemon(tmp_path_factory.mktemp("ros2cm"), endpoint)
        with daemon.serving():
            peer = Ros2Peer(endpoint)
            client = connect(daemon)
            try:
                peer.wait_until(lambda: SERVICE in peer.services(), WAIT_S,
                                "the controller manager's service")
                yield peer, client
            finally:
                client.close()
                peer.close()
    finally:
        router.close()


def _list(peer: Ros2Peer) -> dict[str, Any]:
    reply = peer.call(SERVICE, cm.LIST_CONTROLLERS, {}, WAIT_S)
    return {c.name: c for c in reply.controller}


def test_list_controllers_shows_an_active_trajectory_controller(
        graph: tuple[Ros2Peer, Any]) -> None:
    peer, client = graph
    assert "/controller_manager" in peer.nodes()
    assert peer.services()[SERVICE] == [cm.LIST_CONTROLLERS]
    (server,) = peer.servers(SERVICE)
    assert server["node_name"] == "controller_manager"
    # its token: a service server's, with rclcpp's services QoS (reliable, volatile, keep last 10)
    qos = {t.split("/")[9]: t.rsplit("/", 1)[1] for t in peer.tokens()
           if len(t.split("/")) > 9 and t.split("/")[8] == "controller_manager"}
    assert qos == {"%controller_manager%list_controllers": "::,10:,:,:,,"}
    # active once the loop reports it (get_status refreshes at 2 Hz): ask until then
    deadline = time.monotonic() + WAIT_S
    while (listed := _list(peer))[C[1:]].state != "active":
        assert time.monotonic() < deadline, "the controller never listed as active"
        client.get_status()  # a round trip to the daemon between the calls, not a sleep
    config = client.get_config()["controller"]
    jtc = listed[C[1:]]
    assert jtc.type == "joint_trajectory_controller/JointTrajectoryController"
    command = [f"{j}/{i}" for j in JOINTS for i in config["command_interfaces"]]
    state = [f"{j}/{i}" for j in JOINTS for i in config["state_interfaces"]]
    assert list(jtc.claimed_interfaces) == list(jtc.required_command_interfaces) == command
    assert list(jtc.required_state_interfaces) == state
    assert jtc.update_rate == round(config["update_rate"])
    jsb = listed["joint_state_broadcaster"]
    assert jsb.type == "joint_state_broadcaster/JointStateBroadcaster" and jsb.state == "active"
    assert list(jsb.required_state_interfaces) == state


def test_without_the_setting_no_controller_manager(tmp_path: Path) -> None:
    router, endpoint = _router()
    try:
        daemon = ros2_daemon(tmp_path, endpoint, controller_manager=False,
                             joint_state_broadcaster=False)
        with daemon.serving(), Ros2Peer(endpoint) as peer:
            peer.wait_until(lambda: f"{C}/query_state" in peer.services(), WAIT_S,
                            "the controller's services")
            assert "/controller_manager" not in peer.nodes()
            assert SERVICE not in peer.services()
    finally:
        router.close()


def test_humble_lists_in_humbles_layout(tmp_path: Path) -> None:
    """``distro: humble``: the service's key says ``TypeHashNotSupported`` and the answer is
    Humble's ControllerState (no ``update_rate``), read by a Humble peer."""
    router, endpoint = _router()
    try:
        daemon = ros2_daemon(tmp_path, endpoint, distro="humble")
        with daemon.serving(), Ros2Peer(endpoint, distro="humble") as peer:
            peer.wait_until(lambda: SERVICE in peer.services(), WAIT_S, "list_controllers")
            (token,) = [t for t in peer.tokens() if "%list_controllers" in t]
            assert "/TypeHashNotSupported/" in token
            listed = _list(peer)
            assert listed[C[1:]].type == cm.JTC_TYPE
            assert not hasattr(listed[C[1:]], "update_rate")
            assert "joint_state_broadcaster" in listed
    finally:
        router.close()
