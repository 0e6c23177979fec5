"""The live view (``daemon.foxglove``) end to end, seen by a plain Foxglove WebSocket client.

The daemon runs as a subprocess on simulated (mirror) joints with the live view on an
ephemeral port; the client is the ``websockets`` package speaking ``foxglove.websocket.v1``
by hand (JSON ops, binary message-data frames decoded per the protocol spec: opcode 0x01,
uint32 subscription id, uint64 timestamp, payload, little-endian), so the test checks the
wire, not the SDK's own client. Values are compared with the daemon's socket state stream.
"""

from __future__ import annotations

import json
import re
import struct
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import JOINTS, WAIT_S, DaemonProcess, connect, traj

pytest.importorskip("foxglove")
websockets_client = pytest.importorskip("websockets.sync.client")

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

# foxglove.websocket.v1 is the protocol's spec; the official SDK's server (0.30 here, as the
# ROS foxglove_bridge 3) negotiates it under its new name foxglove.sdk.v1, which Foxglove states
# is the identical protocol. A client offers both, as current viewers do.
SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
CONTROLLER = "joint_trajectory_controller"
TOPICS = {
    "/joint_states": "sensor_msgs/msg/JointState",
    f"/{CONTROLLER}/controller_state": "control_msgs/msg/JointTrajectoryControllerState",
    f"/{CONTROLLER}/joint_trajectory": "trajectory_msgs/msg/JointTrajectory",
    f"/{CONTROLLER}/goal_events": "jtc_hw/msg/GoalEvent",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[DaemonProcess, int]]:
    """A daemon with the live view on a free port, and that port (from its log)."""
    d = DaemonProcess(tmp_path_factory.mktemp("fox"), foxglove={"port": 0})
    d.start()
    try:
        d.wait_ready()
        line = d.wait_log("live view (Foxglove WebSocket) on ws://127.0.0.1:")
        match = re.search(r"ws://127\.0\.0\.1:(\d+)", line)
        assert match is not None, line
        yield d, int(match.group(1))
    finally:
        code = d.shutdown()
    assert code == 0, f"the daemon exited with {code}:\n{d.log()}"


class FoxgloveClient:
    """The client side of ``foxglove.websocket.v1``, enough to subscribe and decode."""

    def __init__(self, port: int, **options: Any) -> None:
        self.ws = websockets_client.connect(
            f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=WAIT_S,
            proxy=None, **options,
        )
        assert self.ws.subprotocol in SUBPROTOCOLS
        self.channels: dict[str, dict[str, Any]] = {}  # by topic
        self.server_info: dict[str, Any] | None = None
        self.subscriptions: dict[int, str] = {}  # subscription id -> topic

    def close(self) -> None:
        self.ws.close()

    def _json(self, op: dict[str, Any]) -> None:
        if op["op"] == "serverInfo":
            self.server_info = op
        elif op["op"] == "advertise":
            for channel in op["channels"]:
                self.channels[channel["topic"]] = channel

    def handshake(self) -> None:
        """Until the server info and an advertisement of every topic have arrived."""
        deadline = time.monotonic() + WAIT_S
        while self.server_info is None or not set(TOPICS) <= set(self.channels):
            remaining = deadline - time.monotonic()
            assert remaining > 0, (self.server_info, sorted(self.channels))
            frame = self.ws.recv(timeout=remaining)
            assert isinstance(frame, str), "binary data before any subscription"
            self._json(json.loads(frame))

    def subscribe(self, *topics: str) -> None:
        subs = []
        for topic in topics:
            sub_id = len(self.subscriptions) + 1
            self.subscriptions[sub_id] = topic
            subs.append({"id": sub_id, "channelId": self.channels[topic]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def message(self, timeout_s: float = WAIT_S) -> tuple[str, int, dict[str, Any]]:
        """The next message data frame: (topic, timestamp ns, decoded JSON payload)."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            assert remaining > 0, "no message data within the wait"
            frame = self.ws.recv(timeout=remaining)
            if isinstance(frame, str):
                self._json(json.loads(frame))
                continue
            assert frame[0] == 0x01, f"unexpected binary opcode {frame[0]:#x}"
            sub_id, stamp = struct.unpack_from("<IQ", frame, 1)
            assert sub_id in self.subscriptions, sub_id
            return self.subscriptions[sub_id], stamp, json.loads(frame[13:])

    def collect(self, until: Any, timeout_s: float = WAIT_S) -> list[tuple[str, int, Any]]:
        """Messages until ``until(topic, payload)`` is true for one (included)."""
        got = []
        deadline = time.monotonic() + timeout_s
        while True:
            topic, stamp, payload = self.message(deadline - time.monotonic())
            got.append((topic, stamp, payload))
            if until(topic, payload):
                return got


def stamp_ns(header: dict[str, Any]) -> int:
    stamp = header["stamp"]
    assert 0 <= stamp["nanosec"] < 1_000_000_000
    return int(stamp["sec"]) * 1_000_000_000 + int(stamp["nanosec"])


def test_a_plain_client_gets_server_info_advertisements_and_joint_states(
    live: tuple[DaemonProcess, int],
) -> None:
    d, port = live
    target = [0.2, -0.1, 0.3, 0.0, -0.2, 0.1]
    fox = FoxgloveClient(port)
    try:
        fox.handshake()
        assert fox.server_info is not None
        assert CONTROLLER in fox.server_info["name"]
        # Read-only: no client publishing, services or parameters offered.
        assert fox.server_info["capabilities"] == []
        for topic, schema_name in TOPICS.items():
            channel = fox.channels[topic]
            assert channel["encoding"] == "json", channel
            assert channel["schemaName"] == schema_name, channel
            assert channel["schemaEncoding"] == "jsonschema", channel
            assert json.loads(channel["schema"])["type"] == "object"
        fox.subscribe("/joint_states", f"/{CONTROLLER}/controller_state",
                      f"/{CONTROLLER}/joint_trajectory", f"/{CONTROLLER}/goal_events")
        with connect(d) as client, client.subscribe_state(maxlen=1000) as sub:
            # A message on the view before the goal: it is live, subscribed and decoding.
            fox.collect(lambda topic, _: topic == "/joint_states")
            before_send_ns = time.monotonic_ns()
            goal = client.send_goal(traj(target, 0.5), start_in=0.2)
            after_send_ns = time.monotonic_ns()
            got = fox.collect(
                lambda topic, m: topic.endswith("goal_events") and m["event"] == "result"
            )
            result = goal.wait(timeout_s=WAIT_S)
            # The state after the result: the reference holds at the target.
            got += fox.collect(
                lambda topic, m: topic.endswith("controller_state") and all(
                    abs(p - q) < 1e-9
                    for p, q in zip(m["reference"]["positions"], target, strict=True)
                )
            )
            # The socket's state stream of the same period, for comparison.
            states = []
            while True:
                state = sub.get(timeout_s=WAIT_S)
                states.append(state)
                if state["time_ns"] >= result["time_ns"]:
                    break
    finally:
        fox.close()

    assert result["status"] == "succeeded", result
    by_topic: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    for topic, stamp, payload in got:
        by_topic.setdefault(topic, []).append((stamp, payload))

    # /joint_states: the measured values of the state stream, with consistent stamps.
    joint_states = by_topic["/joint_states"]
    assert len(joint_states) >= 5, "a 0.5 s goal at state_publish_rate 50 Hz"
    # Positions that occur once in the state stream (while moving) identify their state.
    seen: dict[tuple[float, ...], list[int]] = {}
    for s in states:
        seen.setdefault(tuple(s["actual"]["positions"]), []).append(s["time_ns"])
    positions = {key: times[0] for key, times in seen.items() if len(times) == 1}
    matched = []
    for stamp, message in joint_states:
        assert message["name"] == JOINTS
        assert stamp == stamp_ns(message["header"]), "frame timestamp = header stamp"
        assert len(message["velocity"]) == len(JOINTS)
        key = tuple(message["position"])
        if key in positions:
            matched.append((stamp, positions[key]))
    assert len(matched) >= 3, "the view's joint states are the daemon's state stream's"
    # One mapping of the loop's clock to wall time: stamps keep the loop's spacing exactly.
    offsets = {wall - loop for wall, loop in matched}
    assert len(offsets) == 1, offsets
    offset = offsets.pop()
    assert abs(offset - (time.time_ns() - time.monotonic_ns())) < 5_000_000_000

    # controller_state: the reference reaches the target; the error is reference - feedback.
    controller = [m for _, m in by_topic[f"/{CONTROLLER}/controller_state"]]
    assert controller, "no controller state"
    last = controller[-1]
    assert last["joint_names"] == JOINTS
    assert last["reference"]["positions"] == pytest.approx(target, abs=1e-9)
    assert last["speed_scaling_factor"] == pytest.approx(1.0)
    for message in controller:
        ref, fb, err = (message[k]["positions"] for k in ("reference", "feedback", "error"))
        assert err == pytest.approx([r - f for r, f in zip(ref, fb, strict=True)], abs=1e-9)

    # The accepted command and the goal's result.
    (_, command), = by_topic[f"/{CONTROLLER}/joint_trajectory"]
    assert command["joint_names"] == JOINTS
    assert command["header"]["frame_id"] == f"goal {goal.goal_id}"
    # Stamped with its start as sent, on the loop's clock mapped like the states.
    start_ns = stamp_ns(command["header"]) - offset
    assert before_send_ns + 200_000_000 <= start_ns <= after_send_ns + 200_000_000
    assert command["points"][-1]["positions"] == pytest.approx(target)
    assert command["points"][-1]["time_from_start"] == {"sec": 0, "nanosec": 500_000_000}
    events = [m for _, m in by_topic[f"/{CONTROLLER}/goal_events"]]
    assert events[-1]["event"] == "result" and events[-1]["goal_id"] == goal.goal_id
    assert events[-1]["status"] == "succeeded" and events[-1]["error_code"] == 0
    feedback = [e for e in events if e["event"] == "feedback"]
    assert feedback and all(e["goal_id"] == goal.goal_id for e in feedback)


def test_diagnostics_carry_the_loop_controller_and_hardware(
    live: tuple[DaemonProcess, int],
) -> None:
    _, port = live
    fox = FoxgloveClient(port)
    try:
        fox.handshake()
        fox.subscribe("/diagnostics")
        topic, stamp, message = fox.message()
    finally:
        fox.close()
    assert topic == "/diagnostics"
    assert stamp == stamp_ns(message["header"])
    entries = {s["name"]: s for s in message["status"]}
    assert set(entries) == {"jtc_hw: loop", "jtc_hw: controller", "jtc_hw: hardware arm"}
    arm = entries["jtc_hw: hardware arm"]
    assert arm["level"] == 0 and arm["hardware_id"] == "mirror"
    values = {v["key"]: v["value"] for v in arm["values"]}
    assert values["state"] == "active" and int(values["counters.reads"]) > 0
    loop_keys = {v["key"] for v in entries["jtc_hw: loop"]["values"]}
    assert "api_stalls" in loop_keys


def test_a_viewer_that_stops_reading_loses_samples_and_the_daemon_nothing(
    live: tuple[DaemonProcess, int],
) -> None:
    """A viewer subscribed to everything stops reading: once its socket buffers and the SDK's
    queue for it (256 messages) are full, the oldest samples are dropped for it alone. The
    daemon's socket clients lose nothing meanwhile, and the viewer, reading again, gets the
    newest samples with a hole before them."""
    import socket

    d, port = live
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    stuck = FoxgloveClient(port, sock=sock, max_queue=1, max_size=None)
    try:
        stuck.handshake()
        stuck.subscribe(*TOPICS)
        with connect(d) as client, client.subscribe_state(maxlen=2000) as sub:
            here_state = sub.get(timeout_s=WAIT_S)
            here = here_state["actual"]["positions"]
            # Large commands fill the socket buffers between the server and the viewer (a
            # few MB) fast: each is about 1 MB of JSON (4,000 points holding where it is).
            points = [{"time_from_start": 0.002 * (i + 1), "positions": here}
                      for i in range(4000)]
            for _ in range(6):
                client.send_goal({"joint_names": JOINTS, "points": points})
            after_goals_ns = client.hello()["now_ns"]
            # Then 2 messages per state: 400 states are beyond the SDK's 256-message queue.
            # (The subscription holds every state since it began, the goals' time included.)
            states = [here_state]
            while len(states) < 400 or states[-1]["time_ns"] < after_goals_ns + 8 * 10**9:
                states.append(sub.get(timeout_s=WAIT_S))
            client.stop()
            status = client.get_status()
        # Reading again: what the buffers held, then the queue's newest messages after a hole.
        stamps: list[int] = []
        while len(stamps) < 1000:
            topic, stamp, _ = stuck.message()
            if topic != "/joint_states":
                continue
            stamps.append(stamp)
            if len(stamps) > 1 and stamps[-1] - stamps[-2] > 10 * 20_000_000:
                break
    finally:
        stuck.close()
    assert all(s["dropped"] == 0 for s in states), "a socket client lost states"
    # The API process kept up: the stream it served has no hole like the viewer's.
    stream_gap = max(b["time_ns"] - a["time_ns"] for a, b in zip(states, states[1:],
                                                                  strict=False))
    viewer_gap = stamps[-1] - stamps[-2]
    assert stream_gap * 2 < viewer_gap, (stream_gap, viewer_gap)
    assert status["alive"] is True and status["loop"]["api_stalls"] == 0
    assert stamps == sorted(stamps)
    assert stamps[-1] - stamps[-2] > 10 * 20_000_000, "no sample was dropped for the viewer"


def test_the_live_view_is_off_by_default_and_its_options_are_checked(tmp_path: Path) -> None:
    from helpers.daemon import robot_config

    from jtc_hw.daemon.robot import load_robot, security_warnings
    from jtc_hw.errors import ConfigurationError

    sock = tmp_path / "d.sock"
    assert load_robot(robot_config(sock)).daemon.foxglove is None
    view = load_robot(robot_config(sock, foxglove={})).daemon.foxglove
    assert view is not None
    assert (view.host, view.port, view.rate) == ("127.0.0.1", 8765, None)
    cases = {
        "daemon.foxglove.port: must be": {"port": 70000},
        "daemon.foxglove.host: 'robot.local' is not an IP address": {"host": "robot.local"},
        "daemon.foxglove.rate: must be >= 0.1": {"rate": 0.0},
        "daemon.foxglove.prot: unknown parameter 'prot'; did you mean 'port'?": {"prot": 1},
    }
    for expected, value in cases.items():
        with pytest.raises(ConfigurationError) as caught:
            load_robot(robot_config(sock, foxglove=value))
        assert expected in str(caught.value), (value, str(caught.value))
    open_view = load_robot(robot_config(sock, foxglove={"host": "0.0.0.0"}))
    (warning,) = security_warnings(open_view)
    assert "daemon.foxglove.host" in warning and "authentication" in warning
    assert security_warnings(load_robot(robot_config(sock, foxglove={}))) == []


def test_a_missing_sdk_names_the_extra_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    from jtc_hw.daemon.settings import FoxgloveSettings
    from jtc_hw.daemon.transports.liveview import LiveView
    from jtc_hw.errors import ConfigurationError

    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove -> ImportError
    view = LiveView(FoxgloveSettings(port=0), CONTROLLER, JOINTS, 50.0, dict)
    with pytest.raises(ConfigurationError) as caught:
        view.start()
    assert "pip install 'jtc_hw[foxglove]'" in str(caught.value)
    assert "daemon.foxglove" in str(caught.value)



def test_a_start_that_fails_on_a_taken_port_writes_no_flight_recorder_bag(
    tmp_path: Path,
) -> None:
    """Issue 22, point 9: the live view's port is taken, so the daemon cannot start (exit 2);
    the loop ran meanwhile, but nothing happened that a bag could explain: no bag, and no
    ``flight recorder`` line in the log."""
    import socket

    pytest.importorskip("rosbags")  # the recorder is on only with it
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        d = DaemonProcess(tmp_path / "d", foxglove={"port": taken.getsockname()[1]})
        d.start()
        assert d.wait_exit() == 2
    log = d.log()
    assert "cannot start:" in log and "Traceback" not in log, log
    assert "flight recorder" not in log, log
    flight = tmp_path / "d" / "state" / "jtc-hw" / "flight"  # XDG_STATE_HOME of DaemonProcess
    assert not flight.exists() or list(flight.iterdir()) == [], log
    assert d.leftovers() == {}
