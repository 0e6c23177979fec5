"""End to end across processes: the daemon (``python -m jtc_hw run``) drives CiA 402 drives
emulated in this test process, over python-can's stock ``socketcand`` interface.

This process runs the socketcand server (``jtc_hw.drivers.can.socketcand``) bridging TCP to a
python-can virtual channel, and the emulated drives on that channel; the daemon subprocess
connects with ``interface: socketcand``. Waits are on messages, or on the emulated drives'
record, with deadlines; nothing sleeps.
"""

from __future__ import annotations

import os
import signal
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from helpers.daemon import WAIT_S, DaemonProcess, connect, loop_process, next_state, settle

from jtc_hw.api.client import Client
from jtc_hw.api.framing import RequestError
from jtc_hw.cli.status import format_hardware, hardware_report

from conftest import make_robot_config

socketcand = pytest.importorskip(
    "jtc_hw.drivers.can.socketcand", reason="the socketcand server (CAN-MIT) is not available"
)

from jtc_hw.drivers.can.cia402.codec import AbortConnection, State  # noqa: E402
from jtc_hw.drivers.can.cia402.emulator import Cia402DriveEmulator  # noqa: E402

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

JOINTS = ["shoulder", "elbow"]
NODES = [3, 7]
GOAL_TOL = 0.01
MS = 1_000_000


def robot_yaml(socket_path: Path, port: int) -> dict[str, Any]:
    """Two joints at 250 Hz on CiA 402 drives reached through socketcand."""
    hardware = [{
        "name": "arm",
        "kind": "can-cia402",
        "joints": JOINTS,
        "params": {
            "buses": {"can0": {"interface": "socketcand", "channel": "can0",
                               "host": "127.0.0.1", "port": port,
                               "receive_timeout": 0.002, "setup_timeout": 0.5}},
            "node_id": NODES,
            "feedback_timeout_s": 0.25,
            # Longer than the default 0.1 s: the drives are emulated in this busy test process.
            "watchdog_s": 0.3,
        },
    }]
    return make_robot_config(socket_path, JOINTS, hardware, update_rate=250, goal_time=1.0,
                             path_tolerance=0.1, goal_tolerance=GOAL_TOL)


class Drives:
    """The socketcand server and the emulated drives of one test."""

    def __init__(self) -> None:
        virtual = f"cia402-e2e-{uuid.uuid4().hex[:8]}"
        self.bus = can.Bus(interface="virtual", channel=virtual)
        self.drives = {n: Cia402DriveEmulator(self.bus, n, initial_position=0.1 * (i + 1))
                       for i, n in enumerate(NODES)}
        self.server = socketcand.SocketcandServer(port=0, channels={"can0": virtual})

    def start(self) -> None:
        for d in self.drives.values():
            d.start()
        self.server.start()

    def stop(self) -> None:
        try:
            self.server.stop()
        finally:
            for d in self.drives.values():
                d.stop()
            self.bus.shutdown()


@pytest.fixture
def drives() -> Iterator[Drives]:
    d = Drives()
    try:
        d.start()
        yield d
    finally:
        d.stop()


@pytest.fixture
def daemon(tmp_path: Path, drives: Drives) -> Iterator[DaemonProcess]:
    d = DaemonProcess(tmp_path / "d")
    d.config_path.write_text(
        yaml.safe_dump(robot_yaml(d.socket, drives.server.port), sort_keys=False)
    )
    d.start()
    try:
        d.wait_ready()
        yield d
    finally:
        code = d.shutdown()
        print(d.log())
    assert code == 0, d.log()


def traj(positions: list[float], t: float) -> dict[str, Any]:
    return {
        "joint_names": JOINTS,
        "points": [{"time_from_start": t, "positions": positions, "velocities": [0.0, 0.0]}],
    }


def test_goal_succeeds_and_a_drive_fault_aborts_naming_the_drive(
    daemon: DaemonProcess, drives: Drives
) -> None:
    with connect(daemon) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        assert p0 == pytest.approx([0.1, 0.2], abs=1e-3)
        target = [0.4, -0.1]
        result = client.send_goal(traj(target, 0.8)).wait(timeout_s=WAIT_S)
        assert result["status"] == "succeeded", result
        state = settle(sub, result["time_ns"] + 100 * MS)
        assert state["actual"]["positions"] == pytest.approx(target, abs=GOAL_TOL)
        assert drives.drives[3].motor.position == pytest.approx(target[0], abs=GOAL_TOL)

        goal = client.send_goal(traj([0.1, 0.2], 2.0))
        for feedback in goal.feedback(timeout_s=WAIT_S):
            if feedback["time_from_start"] >= 0.3:
                break
        drives.drives[7].inject_fault(0x4310)
        result = goal.wait(timeout_s=WAIT_S)
        assert result["status"] == "aborted", result
        reason = result["error_string"]
        assert "node 7" in reason and "'elbow'" in reason and "0x4310" in reason, reason
        status = client.get_status()
        assert "0x4310" in status["controller"]["fault"]

        if not hasattr(Client, "rearm"):
            pytest.skip("Client.rearm is not available in this version")
        assert client.rearm()["rearmed"] is True
        # No jump: the faulted drive (coasting, torque off) is enabled where it stands.
        jump = drives.drives[7].enable_jump_counts
        assert jump is not None and abs(jump) < 0.002 * 131072 / (2 * 3.141592653589793)
        after = settle(sub, client.hello()["now_ns"] + 40 * MS)
        assert after["holding"] is True
        assert after["desired"]["positions"] == pytest.approx(
            after["actual"]["positions"], abs=0.01
        )
        back = client.send_goal(traj([0.1, 0.2], 1.0)).wait(timeout_s=WAIT_S)
        assert back["status"] == "succeeded", back


def test_rearm_is_refused_in_one_line_while_a_drive_cannot_stay_enabled(
    daemon: DaemonProcess, drives: Drives
) -> None:
    with connect(daemon) as client:
        goal = client.send_goal(traj([0.3, 0.0], 1.0))
        for feedback in goal.feedback(timeout_s=WAIT_S):
            if feedback["time_from_start"] >= 0.2:
                break
        drives.drives[7].inject_fault(0x4310)
        assert goal.wait(timeout_s=WAIT_S)["status"] == "aborted"
        # Its enable input now opens right after each enabling (0x5441): the re-arm must not
        # report holding.
        drives.drives[7].lose_enable(1)
        with pytest.raises(RequestError) as refused:
            client.rearm()
        message = str(refused.value)
        assert "node 7" in message and "'elbow'" in message and "0x5441" in message, message
        assert "\n" not in message and "Traceback" not in message, message
        assert "node 7" in client.get_status()["controller"]["fault"]
        drives.drives[7].lose_enable(None)
        assert client.rearm()["rearmed"] is True
        for d in drives.drives.values():
            assert d.state is State.OPERATION_ENABLED
        back = client.send_goal(traj([0.1, 0.2], 1.0)).wait(timeout_s=WAIT_S)
        assert back["status"] == "succeeded", back




def test_a_rearm_after_a_failed_one_names_the_fault_it_recovered_from(
    daemon: DaemonProcess, drives: Drives
) -> None:
    """Issue 22, point 9: after a failed re-arm, ``jtc-hw rearm`` said ``re-armed after:
    re-arm failed: ...`` (why the previous attempt failed), not the drive fault it recovered
    from. ``get_status`` keeps that fault as ``controller.fault_cause`` while re-arms fail."""
    import subprocess
    import sys

    from helpers.daemon import daemon_env

    with connect(daemon) as client:
        goal = client.send_goal(traj([0.3, 0.0], 1.0))
        for feedback in goal.feedback(timeout_s=WAIT_S):
            if feedback["time_from_start"] >= 0.2:
                break
        drives.drives[7].inject_fault(0x4310)
        assert goal.wait(timeout_s=WAIT_S)["status"] == "aborted"
        cause = client.get_status()["controller"]["fault"]
        assert "0x4310" in cause
        drives.drives[7].lose_enable(1)
        with pytest.raises(RequestError):
            client.rearm()
        controller = client.get_status()["controller"]
        assert controller["fault"].startswith("re-arm failed: ")
        assert controller["fault_cause"] == cause
        drives.drives[7].lose_enable(None)
    done = subprocess.run(
        [sys.executable, "-m", "jtc_hw", "rearm", "--socket", str(daemon.socket)],
        capture_output=True, text=True, env=daemon_env(), timeout=60, stdin=subprocess.DEVNULL,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout == f"re-armed after: {cause}; holding the measured position\n"
    with connect(daemon) as client:
        controller = client.get_status()["controller"]
    assert (controller["fault"], controller["fault_cause"]) == (None, None)


def test_a_socketcand_receive_error_is_one_line_in_result_status_and_hardware(
    daemon: DaemonProcess, drives: Drives
) -> None:
    """Issue 21, point 6: the socketcand peer sends bytes python-can cannot decode (not
    ASCII); its client raises an error whose text carries a whole traceback. The goal's
    result, the status and the hardware report say in one line what failed, on which bus,
    and which drives it leaves unreachable."""
    with connect(daemon) as client:
        goal = client.send_goal(traj([0.3, 0.0], 1.5))
        for feedback in goal.feedback(timeout_s=WAIT_S):
            if feedback["time_from_start"] >= 0.2:
                break
        assert drives.server.send_raw(b"\xff\xfe< frame 183 0.0 >") == 1
        result = goal.wait(timeout_s=WAIT_S)
        assert result["status"] == "aborted", result
        status = client.get_status()
        (component,) = status["hardware"]["components"]
        texts = [result["error_string"], status["controller"]["fault"],
                 component["last_fault"]]
        for text in texts:
            assert "\n" not in text and "Traceback" not in text, text
            assert "receiving on bus 'can0'" in text, text
            assert "node 3 ('shoulder')" in text and "node 7 ('elbow')" in text, text
            assert "Failed to receive" in text, text  # python-can's reason, its first line
        report = format_hardware(hardware_report(status))
        assert "Traceback" not in report and "None" not in report, report


@pytest.fixture
def daemon_to_kill(tmp_path: Path, drives: Drives) -> Iterator[DaemonProcess]:
    """The daemon, without the clean-exit check: its loop process will be killed."""
    d = DaemonProcess(tmp_path / "d")
    d.config_path.write_text(
        yaml.safe_dump(robot_yaml(d.socket, drives.server.port), sort_keys=False)
    )
    d.start()
    try:
        d.wait_ready()
        yield d
    finally:
        d.shutdown()  # its exit status is the API process's business (not tested here)
        print(d.log())


def test_killing_the_loop_process_quick_stops_the_drives(
    daemon_to_kill: DaemonProcess, drives: Drives
) -> None:
    with connect(daemon_to_kill) as client:
        goal = client.send_goal(traj([0.8, -0.6], 1.5))
        for feedback in goal.feedback(timeout_s=WAIT_S):
            if feedback["time_from_start"] >= 0.5:
                break
        for d in drives.drives.values():
            assert d.state is State.OPERATION_ENABLED
            assert d.heartbeat_consumers == {1: (127, 0.3, True)}  # watching the daemon
            assert d.watchdog_trips == []
        os.kill(loop_process(daemon_to_kill), signal.SIGKILL)
        killed_at = time.monotonic()
        for node, d in drives.drives.items():
            trip = d.wait_watchdog_stop(WAIT_S)
            assert trip is not None, f"drive {node} did not stop by itself"
            assert trip.producer == 127 and trip.reaction is AbortConnection.QUICK_STOP
            assert trip.state_before is State.OPERATION_ENABLED
            # Caused by the kill (not an earlier stall): detected after it, a consumer time
            # after the last heartbeat the drive received.
            assert trip.detected_at >= killed_at, (trip, killed_at)
            assert trip.detected_at - trip.last_heartbeat_at >= 0.3 - 1e-3, trip
            assert trip.state_after is State.SWITCH_ON_DISABLED  # 0x605A 2: ramp, then off
            assert d.state is State.SWITCH_ON_DISABLED
