"""Issue 11 point 8 through the real Dynamixel driver and SDK against the pty emulator: when
the daemon's loop deactivates the controller, the zeroed velocity command reaches the servos
before the driver's own safe action (section 3 of jtc_upstream_behaviour.md, deactivate).

With ``safe_action: torque_off`` the driver only switches the torque off; a servo's Goal
Velocity register then shows what was last written to it: 0 now, the moving command before.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.dynamixel import DAEMON_TEST_TIMEOUT_MS, IDS, JOINTS, OFFSET, START, servos_as_hardware

from jtc_hw.controller.goals import ErrorCode, GoalResult, GoalStatus
from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.daemon.channel.messages import Commit, Events
from jtc_hw.daemon.channel.pipe import Inbox
from jtc_hw.daemon.loop.cycle import ControlLoop
from jtc_hw.daemon.loop.outbox import Outbox
from jtc_hw.daemon.robot import load_robot
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator

from conftest import make_robot_config

RATE = 200
PERIOD_NS = 1_000_000_000 // RATE


@pytest.fixture
def emulator() -> Iterator[DynamixelEmulator]:
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        yield emu


def test_deactivation_writes_goal_velocity_zero_before_the_torque_goes_off(
    tmp_path: Path, emulator: DynamixelEmulator
) -> None:
    """Section 3 (deactivate): velocity commands are written 0 on deactivation. The loop
    writes them through the driver, then the driver's safe action (torque off) runs as
    before: the servos end with torque off and Goal Velocity 0, not their moving command."""
    params: dict[str, Any] = {
        "port": emulator.device_path,
        "baud_rate": 4_000_000,
        "ids": IDS,
        "model": "XM430-W350",
        "offset": OFFSET,
        "timeout_ms": DAEMON_TEST_TIMEOUT_MS,
        "max_retries": 1,
        "latency_timer_warn": False,
        "watchdog_s": 1.0,
        "safe_action": "torque_off",
    }
    hardware = [{"name": "arm", "kind": "dynamixel", "joints": JOINTS, "params": params}]
    robot = load_robot(make_robot_config(
        tmp_path / "x.sock", JOINTS, hardware, command_interfaces=["velocity"],
        update_rate=RATE, path_tolerance=0.0, goal_tolerance=0.0,
        controller={"gains": {j: {"p": 5.0, "ff_velocity_scale": 1.0} for j in JOINTS}},
    ))
    api, loop_end = multiprocessing.Pipe(duplex=True)
    outbox = Outbox(loop_end, 1 << 20)
    inbox = Inbox(loop_end, 1 << 20)
    api_inbox = Inbox(api, 1 << 20, framed=False)
    loop = ControlLoop(robot, outbox)
    try:
        now = time.monotonic_ns()
        loop.start(now)
        start = loop.ctrl.reference.sample(now).positions
        trajectory = JointTrajectory(JOINTS, [TrajectoryPoint(2.0, list(start + 1.0))])
        loop._handle(Commit(1, loop.ctrl.plan_goal(now, trajectory)), now)
        for _ in range(20):
            now += PERIOD_NS
            loop.cycle(now, PERIOD_NS, inbox)
            loop.serve_outbox(now)
        assert loop.fault is None
        moving = {i: emulator.register(i, "goal_velocity") for i in IDS}
        assert all(value > 0 for value in moving.values()), moving
        loop._shutdown_reason = "daemon stopping (SIGTERM)"
        loop.shutdown(now + PERIOD_NS)
        for servo_id in IDS:
            assert emulator.register(servo_id, "torque_enable") == 0, servo_id  # safe action
            assert emulator.register(servo_id, "goal_velocity") == 0, servo_id  # upstream's 0
        loop.serve_outbox(now + PERIOD_NS)
        api_inbox.pump()
        results = []
        while (message := api_inbox.pop()) is not None:
            if isinstance(message, Events):
                results += [e for e in message.events if isinstance(e, GoalResult)]
        assert [(r.status, r.error_code) for r in results] == [
            (GoalStatus.ABORTED, ErrorCode.INVALID_GOAL)
        ]
    finally:
        loop.hardware.shutdown(time.monotonic_ns())
        for box in (inbox, api_inbox):
            box.close()
        outbox.close()
        api.close()
        loop_end.close()
