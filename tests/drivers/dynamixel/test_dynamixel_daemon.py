"""End to end on emulated Dynamixel servos: ``python -m jtc_hw run`` with ``kind: dynamixel``.

The emulator runs in this test process (its own thread, on a pty); the daemon is a subprocess
that opens the pty with the real SDK, exactly as it would open ``/dev/ttyUSB0``. Goals go through
the real client. Waits are on messages with deadlines; nothing asserts a duration.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import (
    MS,
    WAIT_S,
    DaemonProcess,
    connect,
    loop_process,
    next_state,
    settle,
    wait_gone,
)
from helpers.daemon import (
    ConfiguredDaemon as DxlDaemon,
)
from helpers.dynamixel import DAEMON_TEST_TIMEOUT_MS, servos_as_hardware

from jtc_hw import GoalRejected
from jtc_hw.api.client import Client
from jtc_hw.api.framing import RequestError
from jtc_hw.drivers.dynamixel.control_table import HardwareError
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator

from conftest import make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

JOINTS = [f"joint{i}" for i in range(1, 7)]
IDS = list(range(1, 7))
START = {i: math.pi + 0.05 * (i - 3) for i in IDS}  # motor rad; tick 2048 (pi) is joint 0
PATH_TOL = 0.1
GOAL_TOL = 0.02


def robot(socket_path: Path, device: str, interface: str = "position",
          gains: dict[str, Any] | None = None, watchdog_s: float = 1.0) -> dict[str, Any]:
    params: dict[str, Any] = {
        "port": device,
        "baud_rate": 4_000_000,
        "ids": IDS,
        "model": "XM430-W350",
        "offset": -math.pi,
        # The emulator shares the test process: allow for its thread being starved on a loaded
        # machine (a missed reply here is a fault that the next test would inherit).
        "timeout_ms": DAEMON_TEST_TIMEOUT_MS,
        "max_retries": 1,
        "latency_timer_warn": False,
        # Long unless a test is about it: a loaded machine pausing the daemon must not trip
        # the servos' Bus Watchdog (the default 0.1 s is for real arms).
        "watchdog_s": watchdog_s,
    }
    hardware = [{"name": "arm", "kind": "dynamixel", "joints": JOINTS, "params": params}]
    return make_robot_config(
        socket_path, JOINTS, hardware, command_interfaces=[interface], update_rate=200,
        goal_time=1.0, path_tolerance=PATH_TOL, goal_tolerance=GOAL_TOL,
        controller={"gains": {j: gains for j in JOINTS}} if gains is not None else None,
    )


@pytest.fixture(scope="module")
def emulator() -> Iterator[DynamixelEmulator]:
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        yield emu


@pytest.fixture(scope="module")
def position_daemon(
    tmp_path_factory: pytest.TempPathFactory, emulator: DynamixelEmulator
) -> Iterator[DxlDaemon]:
    d = DxlDaemon(tmp_path_factory.mktemp("dxl"),
                  lambda sock: robot(sock, emulator.device_path))
    with d.serving():
        yield d


def traj(positions: list[float], t: float) -> dict[str, Any]:
    return {
        "joint_names": JOINTS,
        "points": [{"time_from_start": t, "positions": positions, "velocities": [0.0] * 6}],
    }


def run_goal(d: DaemonProcess, delta: float = 0.3, t: float = 1.5) -> tuple[Any, Any]:
    with connect(d) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        target = [p + delta for p in p0]
        result = client.send_goal(traj(target, t)).wait(timeout_s=WAIT_S)
        state = settle(sub, result["time_ns"] + 50 * MS)
    return result, (target, state)


def test_position_goal_succeeds(position_daemon: DxlDaemon, emulator: DynamixelEmulator) -> None:
    result, (target, state) = run_goal(position_daemon)
    assert result["status"] == "succeeded", (result, position_daemon.log())
    assert state["actual"]["positions"] == pytest.approx(target, abs=GOAL_TOL)
    motor = emulator.positions()
    assert [motor[i] - math.pi for i in IDS] == pytest.approx(target, abs=GOAL_TOL)


def test_fault_mid_goal_aborts_then_rearm_holds_without_a_jump(
    position_daemon: DxlDaemon, emulator: DynamixelEmulator
) -> None:
    with connect(position_daemon) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        goal = client.send_goal(traj([p - 0.4 for p in p0], 2.0))
        for feedback in goal.feedback(timeout_s=WAIT_S):
            if feedback["time_from_start"] >= 0.4:
                break
        emulator.raise_hardware_error(3, HardwareError.OVERLOAD)
        result = goal.wait(timeout_s=WAIT_S)
        assert result["status"] == "aborted", result
        assert "servo 3" in result["error_string"] and "joint3" in result["error_string"]
        assert "overload" in result["error_string"]
        status = client.get_status()
        assert "servo 3" in status["controller"]["fault"]
        assert status["controller"]["active"] is False
        with pytest.raises(GoalRejected):
            client.send_goal(traj(p0, 1.0))
        if not hasattr(Client, "rearm"):
            pytest.skip("the client has no rearm() yet")
        # Servo 3 lost its torque mid-move and coasts; wait for it to come to rest.
        deadline = time.monotonic() + WAIT_S
        while emulator.register(3, "present_velocity") != 0:
            assert time.monotonic() < deadline, "servo 3 did not come to rest"
            time.sleep(0.01)  # polling emulated physics; nothing to block on
        before = emulator.positions()
        assert client.rearm(timeout_s=WAIT_S)["rearmed"] is True
        status = client.get_status()
        assert status["controller"]["fault"] is None and status["controller"]["active"] is True
        after = settle(sub, client.hello()["now_ns"] + 50 * MS)
        assert after["holding"] is True
        # Held where the joints are (a tick or two of rounding): no jump.
        assert after["desired"]["positions"] == pytest.approx(
            after["actual"]["positions"], abs=0.01)
        assert [emulator.positions()[i] for i in IDS] == pytest.approx(
            [before[i] for i in IDS], abs=0.02)
        back = client.send_goal(traj(p0, 1.5)).wait(timeout_s=WAIT_S)
        assert back["status"] == "succeeded", back


def test_a_stalled_loop_trips_the_watchdog_then_a_rearm_holds_where_the_servos_stopped(
    position_daemon: DxlDaemon, emulator: DynamixelEmulator
) -> None:
    """The loop stopped (SIGSTOP) mid-goal for longer than the watchdog: the servos stop by
    themselves; resumed, the driver sees the expiry and the goal aborts with it; a rearm then
    holds where the servos stopped."""
    with connect(position_daemon) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        goal = client.send_goal(traj([p - 0.3 for p in p0], 2.0))
        for feedback in goal.feedback(timeout_s=WAIT_S):
            if feedback["time_from_start"] >= 0.3:
                break
        loop = loop_process(position_daemon)
        since = time.monotonic()
        os.kill(loop, signal.SIGSTOP)
        try:
            trips = emulator.wait_watchdog_stopped(IDS, timeout_s=WAIT_S, since_s=since)
        finally:
            os.kill(loop, signal.SIGCONT)
        result = goal.wait(timeout_s=WAIT_S)
        assert result["status"] == "aborted", result
        assert result["error_string"].endswith(
            "servo 1 (joint 'joint1'): bus watchdog expired (no command for 1000 ms); "
            "rearm to resume"), result
        with pytest.raises(GoalRejected):
            client.send_goal(traj(p0, 1.0))
        stopped = [trips[i].stopped_position_rad or math.nan for i in IDS]
        assert client.rearm(timeout_s=WAIT_S)["rearmed"] is True
        after = settle(sub, client.hello()["now_ns"] + 50 * MS)
        assert after["holding"] is True
        assert after["desired"]["positions"] == pytest.approx(
            after["actual"]["positions"], abs=0.01)
        assert [emulator.positions()[i] for i in IDS] == pytest.approx(stopped, abs=0.01)
        back = client.send_goal(traj(p0, 1.5)).wait(timeout_s=WAIT_S)
        assert back["status"] == "succeeded", back


def test_a_rearm_whose_servo_does_not_stay_enabled_fails_in_one_line(
    position_daemon: DxlDaemon, emulator: DynamixelEmulator
) -> None:
    """Truthful rearm: servo 3 faults again the moment its torque comes back on (a shorted
    winding); the rearm says so in one line naming it, and the next one (after the cause is
    gone) holds."""
    with connect(position_daemon) as client, client.subscribe_state() as sub:
        next_state(sub, lambda s: s["active_goal"] is None)
        emulator.raise_hardware_error(3, HardwareError.OVERLOAD)
        deadline = time.monotonic() + WAIT_S
        while client.get_status()["controller"]["fault"] is None:  # no goal: no event to wait on
            assert time.monotonic() < deadline, "the overload was not reported"
            time.sleep(0.01)
        emulator.fail_next_torque_on(3, HardwareError.ELECTRICAL_SHOCK)
        with pytest.raises(RequestError) as info:
            client.rearm(timeout_s=WAIT_S)
        message = str(info.value)
        assert "servo 3 (joint 'joint3')" in message and "electrical shock" in message
        assert "\n" not in message and "Traceback" not in message
        controller = client.get_status()["controller"]
        assert controller["active"] is False and "servo 3" in controller["fault"]
        assert client.rearm(timeout_s=WAIT_S)["rearmed"] is True
        after = settle(sub, client.hello()["now_ns"] + 50 * MS)
        assert after["holding"] is True
        assert [emulator.register(i, "torque_enable") for i in IDS] == [1] * 6


@pytest.mark.parametrize(
    ("interface", "gains"),
    [
        ("velocity", {"p": 5.0, "ff_velocity_scale": 1.0}),
        ("effort", {"p": 20.0, "d": 1.0}),
    ],
)
def test_velocity_and_current_mode_goals_succeed(
    tmp_path: Path, interface: str, gains: dict[str, float]
) -> None:
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        d = DxlDaemon(tmp_path / interface,
                      lambda sock: robot(sock, emu.device_path, interface, gains))
        d.start()
        try:
            d.wait_ready()
            result, (target, state) = run_goal(d)
        finally:
            code = d.shutdown()
        assert code == 0, d.log()
        assert result["status"] == "succeeded", (result, d.log())
        assert state["actual"]["positions"] == pytest.approx(target, abs=GOAL_TOL)


# -- fail-safe: the loop process dies -------------------------------------------------------------








def _stop_whatever_is_left(d: DaemonProcess) -> None:
    """End the daemon however it copes with its loop's death (not what this test checks)."""
    assert d.proc is not None
    if d.proc.poll() is None:
        d.proc.send_signal(signal.SIGTERM)
        try:
            d.proc.wait(timeout=STOP_WAIT_S)
        except subprocess.TimeoutExpired:
            pass
    with contextlib.suppress(ProcessLookupError):
        os.killpg(d.pid, signal.SIGKILL)
    d.proc.wait(timeout=STOP_WAIT_S)


STOP_WAIT_S = 10.0


@contextlib.contextmanager
def moving_arm(directory: Path) -> Iterator[tuple[DynamixelEmulator, DxlDaemon, Any, Any]]:
    """Emulated servos in velocity mode (Bus Watchdog 0.1 s), their daemon, a client and a goal
    half a second under way, the servos turning. On exit, whatever is left of the daemon ends."""
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        d = DxlDaemon(directory, lambda sock: robot(
            sock, emu.device_path, "velocity", {"p": 5.0, "ff_velocity_scale": 1.0},
            watchdog_s=0.1))
        d.start()
        try:
            d.wait_ready()
            with connect(d) as client:
                with client.subscribe_state() as sub:
                    p0 = next_state(sub, lambda s: s["active_goal"] is None)
                goal = client.send_goal(traj([p + 1.0 for p in p0["actual"]["positions"]], 4.0))
                for feedback in goal.feedback(timeout_s=WAIT_S):
                    if feedback["time_from_start"] >= 0.5:
                        break
                assert emu.watchdog_trips() == [], "a servo tripped while the loop was running"
                assert all(emu.register(i, "present_velocity") != 0 for i in IDS)
                yield emu, d, client, goal
        finally:
            _stop_whatever_is_left(d)


def test_sigkill_of_the_loop_in_velocity_mode_stops_the_servos_on_their_watchdog(
    tmp_path: Path,
) -> None:
    """Issue 10: the loop killed mid-goal, nothing commands the servos any more; they stop by
    themselves when their Bus Watchdog (armed by the driver, default 0.1 s) expires, and the
    client gets its goal's one result: ABORTED, naming the loop's death."""
    with moving_arm(tmp_path / "kill") as (emu, d, client, goal):
        loop = loop_process(d)
        killed = time.monotonic()
        os.kill(loop, signal.SIGKILL)
        wait_gone(loop)
        trips = emu.wait_watchdog_stopped(IDS, timeout_s=WAIT_S)
        result = goal.wait(timeout_s=WAIT_S)
        assert d.proc is not None
        assert d.proc.wait(timeout=WAIT_S) == 1, "the daemon exits non-zero"
        assert len(client.received("result", goal.goal_id)) == 1
        assert result["status"] == "aborted"
        assert result["error_string"].startswith("control loop died: killed by SIGKILL")
        assert set(trips) == set(IDS)
        for servo_id, trip in trips.items():
            # The last packet came from the loop before it died (the emulator may process it a
            # little later on a loaded machine); the servo counted the configured 0.1 s from
            # it, after the kill, was still turning, and stopped.
            assert trip.expired_s > killed, servo_id
            assert trip.timeout_s == pytest.approx(0.1), servo_id
            assert trip.expired_s == pytest.approx(trip.last_instruction_s + 0.1, abs=1e-9)
            assert trip.speed_at_expiry_rad_s > 0.05, servo_id
            assert emu.register(servo_id, "present_velocity") == 0, servo_id
            assert emu.register(servo_id, "bus_watchdog") == -1, servo_id
            assert emu.positions()[servo_id] == pytest.approx(trip.stopped_position_rad,
                                                              abs=0.01)


def test_sigkill_of_the_whole_daemon_stops_the_servos_on_their_watchdog(tmp_path: Path) -> None:
    """docs/safety.md, SIGKILL: API process and loop killed at once (what systemd does after
    TimeoutStopSec); nothing is left to command the servos, their watchdogs stop them."""
    with moving_arm(tmp_path / "killall") as (emu, d, _client, _goal):
        loop = loop_process(d)
        killed = time.monotonic()
        os.killpg(d.pid, signal.SIGKILL)
        wait_gone(loop)
        trips = emu.wait_watchdog_stopped(IDS, timeout_s=WAIT_S)
        assert set(trips) == set(IDS)
        for servo_id, trip in trips.items():
            assert trip.expired_s > killed, servo_id  # not a trip while the daemon ran
            assert emu.register(servo_id, "present_velocity") == 0, servo_id


def test_sigkill_of_the_api_process_lets_the_loop_stop_the_servos_itself(
    tmp_path: Path,
) -> None:
    """docs/safety.md, API death: the loop sees its pipe end, ends the goal, holds (the
    component's safe action), disarms the watchdogs of a clean stop and exits; no trip."""
    with moving_arm(tmp_path / "api") as (emu, d, _client, _goal):
        loop = loop_process(d)
        os.kill(d.pid, signal.SIGKILL)
        wait_gone(loop)  # the loop process noticed and finished by itself
        for servo_id in IDS:
            assert emu.register(servo_id, "bus_watchdog") == 0, servo_id  # disarmed cleanly
            assert emu.register(servo_id, "goal_velocity") == 0, servo_id  # the hold
            assert emu.register(servo_id, "torque_enable") == 1, servo_id
        # The servos brake on their velocity profile to a stop (emulated time runs on).
        deadline = time.monotonic() + WAIT_S
        while any(emu.register(i, "present_velocity") != 0 for i in IDS):
            assert time.monotonic() < deadline, "the servos did not come to rest"
            time.sleep(0.01)  # watching the emulated motors decelerate
        assert emu.watchdog_trips() == [], "the loop stopped the servos, not their watchdogs"


def test_a_missing_serial_device_is_one_error_line(tmp_path: Path) -> None:
    """Issue 22, point 9: a port that does not exist was reported three times, as ERROR lines
    from the loop, the backend and the daemon. Once now: the daemon's ``cannot start``."""
    missing = tmp_path / "ttyUSB-unplugged"
    d = DxlDaemon(tmp_path / "d", lambda sock: robot(sock, str(missing)))
    d.start()
    assert d.wait_exit() == 2
    log = d.log()
    mentions = [line for line in log.splitlines() if str(missing) in line]
    assert len(mentions) == 1, log
    assert mentions[0].startswith("ERROR jtc_hw.daemon: cannot start: Dynamixel bus "), log
    assert "cannot open the port" in mentions[0] and "Traceback" not in log
    assert [line for line in log.splitlines() if line.startswith("ERROR")] == mentions, log
    assert d.leftovers() == {}
