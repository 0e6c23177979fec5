"""Speed scaling end to end on emulated Dynamixel servos (issue 12 part C).

``python -m jtc_hw run`` drives six emulated XM430 servos through the real SDK on a pty; the
commands are the CLI's (``jtc-hw speed 0.3``, ``jtc-hw pause``, ``jtc-hw resume``, in this
process). Progress is measured from the servos' positions as the driver reads them from the
emulator (the state stream's ``actual``, stamped with the daemon's clock); waits are on messages
with deadlines.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon import WAIT_S, connect, next_state, settle
from helpers.dynamixel import servos_as_hardware
from test_dynamixel_daemon import GOAL_TOL, IDS, JOINTS, START, DxlDaemon, robot

from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_OK
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator

pytestmark = pytest.mark.usefixtures("no_leaks")

DELTA = 0.5
DURATION_S = 2.0
TICK = 2 * math.pi / 4096


@pytest.fixture(scope="module")
def emulator() -> Iterator[DynamixelEmulator]:
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        yield emu


@pytest.fixture(scope="module")
def daemon(
    tmp_path_factory: pytest.TempPathFactory, emulator: DynamixelEmulator
) -> Iterator[DxlDaemon]:
    def config(sock: Path) -> dict[str, Any]:
        cfg = robot(sock, emulator.device_path)
        params = cfg["joint_trajectory_controller"]["ros__parameters"]
        params["state_publish_rate"] = 100.0
        params["speed_scaling"] = {"ramp_time": 0.5}
        return cfg

    d = DxlDaemon(tmp_path_factory.mktemp("dxl-scaling"), config)
    with d.serving():
        yield d


def goal(p0: list[float]) -> dict[str, Any]:
    return {
        "joint_names": JOINTS,
        "points": [
            {
                "time_from_start": DURATION_S,
                "positions": [p + DELTA for p in p0],
                "velocities": [0.0] * len(JOINTS),
            }
        ],
    }


def cli(d: DxlDaemon, *args: str) -> None:
    assert main([*args, "--socket", str(d.socket)]) == EXIT_OK


def progress(state: dict[str, Any], p0: list[float]) -> float:
    """Share of the motion done, from the servos' positions (the least advanced joint)."""
    return min((a - p) / DELTA for a, p in zip(state["actual"]["positions"], p0, strict=True))


def test_speed_0_3_during_a_goal_slows_it(daemon: DxlDaemon, emulator: DynamixelEmulator) -> None:
    with connect(daemon) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        handle = client.send_goal(goal(p0))
        start = next_state(sub, lambda s: s["active_goal"] is not None)["time_ns"]
        next_state(sub, lambda s: progress(s, p0) >= 0.05)
        cli(daemon, "speed", "0.3")
        half = next_state(sub, lambda s: progress(s, p0) >= 0.5, timeout_s=3 * WAIT_S)
        slowed = next_state(sub, lambda s: s["speed_scaling"]["factor"] == 0.3)
        assert slowed["speed_scaling"]["target"] == 0.3
        # As planned, halfway is 1 s after the start (a symmetric cubic). At 0.3 from about
        # 5 % on, the servos get there much later: at least 1.5 s (about 2.3 s expected).
        took_s = (half["time_ns"] - start) / 1e9
        assert took_s > 1.5, took_s
        cli(daemon, "speed", "1")
        result = handle.wait(timeout_s=3 * WAIT_S)
        assert result["status"] == "succeeded", (result, daemon.log())
        settle(sub, result["time_ns"])
    motor = emulator.positions()
    assert [motor[i] - math.pi for i in IDS] == pytest.approx(
        [p + DELTA for p in p0], abs=GOAL_TOL
    )


def test_pause_stops_smoothly_and_resume_completes(
    daemon: DxlDaemon, emulator: DynamixelEmulator
) -> None:
    with connect(daemon) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        handle = client.send_goal(goal(p0))
        before = next_state(sub, lambda s: progress(s, p0) >= 0.45, timeout_s=2 * WAIT_S)
        cli(daemon, "pause")
        states = [before]
        while states[-1]["speed_scaling"]["factor"] > 0.0:
            states.append(sub.get(timeout_s=WAIT_S))
        # Resting: 0.3 s of the daemon's clock with the servos where they stopped.
        rest = states[-1]
        still = [rest]
        while still[-1]["time_ns"] < rest["time_ns"] + 300_000_000:
            still.append(sub.get(timeout_s=WAIT_S))
        # Smooth: the servos went on forward after the request (a hold on the spot would have
        # stopped them where they were measured), never back, through intermediate speeds.
        ahead = [progress(s, p0) for s in states]
        assert all(b >= a - TICK / DELTA for a, b in zip(ahead, ahead[1:], strict=False))
        assert (ahead[-1] - ahead[0]) * DELTA > 10 * TICK, ahead
        v0 = max(abs(v) for v in before["actual"]["velocities"])
        slowing = [
            s for s in states[1:-1]
            if 0.1 * v0 < max(abs(v) for v in s["actual"]["velocities"]) < 0.9 * v0
        ]
        assert len(slowing) >= 3, [s["actual"]["velocities"] for s in states]
        positions = [s["actual"]["positions"] for s in still]
        for p in positions[1:]:
            assert p == pytest.approx(positions[0], abs=2 * TICK)
        assert client.received("result") == []
        assert still[-1]["speed_scaling"] == {"factor": 0.0, "target": 0.0}

        cli(daemon, "resume")
        result = handle.wait(timeout_s=3 * WAIT_S)
        assert result["status"] == "succeeded", (result, daemon.log())
        settle(sub, result["time_ns"] + 100_000_000)
        assert len(client.received("result")) == 1
    motor = emulator.positions()
    assert [motor[i] - math.pi for i in IDS] == pytest.approx(
        [p + DELTA for p in p0], abs=GOAL_TOL
    )
