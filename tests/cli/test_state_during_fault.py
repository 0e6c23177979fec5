"""``jtc-hw state`` during a hardware fault on emulated Dynamixel servos: the loop publishes no
state then, and ``state`` used to wait out its 10 s timeout and print a traceback (``--watch``
printed nothing). It shows the fault and the held position instead, and ``--watch`` returns to
the joint table after a re-arm."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from helpers.daemon import WAIT_S, DaemonProcess, connect, daemon_env
from helpers.dynamixel import DAEMON_TEST_TIMEOUT_MS, servos_as_hardware

from jtc_hw.drivers.dynamixel.control_table import HardwareError
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator

from conftest import ROOT, make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

JOINTS = ["joint1", "joint2", "joint3"]
IDS = [1, 2, 3]


@pytest.fixture
def faulted(tmp_path: Path) -> Iterator[tuple[DaemonProcess, DynamixelEmulator]]:
    with servos_as_hardware(IDS, initial_positions={i: math.pi for i in IDS}) as emulator:
        d = DaemonProcess(tmp_path)
        params = {
            "port": emulator.device_path, "baud_rate": 4_000_000, "ids": IDS,
            "model": "XM430-W350", "offset": -math.pi,
            # The emulator shares this process: allow for its thread being starved.
            "timeout_ms": DAEMON_TEST_TIMEOUT_MS, "max_retries": 1, "latency_timer_warn": False,
            "watchdog_s": 1.0,
        }
        hardware = [{"name": "arm", "kind": "dynamixel", "joints": JOINTS, "params": params}]
        d.config_path.write_text(yaml.safe_dump(
            make_robot_config(d.socket, JOINTS, hardware, update_rate=200), sort_keys=False
        ))
        d.start()
        try:
            d.wait_ready()
            with connect(d) as client:
                emulator.raise_hardware_error(2, HardwareError.OVERLOAD)
                deadline = time.monotonic() + WAIT_S
                # No goal: no event to wait on. (While the loop reports the fault, a status
                # may come without its controller section.)
                while client.get_status().get("controller", {}).get("fault") is None:
                    assert time.monotonic() < deadline, "the overload was not reported"
                    time.sleep(0.01)
            yield d, emulator
        finally:
            code = d.shutdown()
        assert code == 0, f"the daemon exited with {code}:\n{d.log()}"


def jtc_hw(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "jtc_hw", *args], capture_output=True, text=True, cwd=ROOT,
        env=daemon_env(), timeout=60, stdin=subprocess.DEVNULL,
    )


def test_state_shows_the_fault_and_watch_returns_to_the_table_after_a_rearm(
    faulted: tuple[DaemonProcess, DynamixelEmulator],
) -> None:
    d, _ = faulted
    # --timeout 60: were the fault not noticed, this would fail on the timeout, not pass.
    once = jtc_hw("state", "--socket", str(d.socket), "--timeout", "60")
    assert once.returncode == 0, once.stderr
    assert "Traceback" not in once.stderr
    assert "FAULT (controller stopped, hardware not read): dynamixel hardware 'arm': servo 2 " \
        "(joint 'joint2'): hardware error: overload" in once.stdout
    rows = [line.split() for line in once.stdout.splitlines()[1:4]]
    assert [r[0] for r in rows] == JOINTS and all(r[2] == "-" for r in rows)
    assert [float(r[1]) for r in rows] == pytest.approx([0.0, 0.0, 0.0], abs=0.01)

    as_json = jtc_hw("state", "--json", "--socket", str(d.socket), "--timeout", "60")
    message = json.loads(as_json.stdout)
    assert message["event"] == "fault" and "servo 2" in message["fault"]
    assert message["joint_names"] == JOINTS and message["active"] is False

    watch = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "state", "--watch", "--json", "--socket", str(d.socket),
         "--timeout", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=daemon_env(),
    )
    try:
        assert watch.stdout is not None
        assert json.loads(watch.stdout.readline())["event"] == "fault"
        rearm = jtc_hw("rearm", "--socket", str(d.socket))
        assert rearm.returncode == 0, rearm.stderr
        while True:  # fault lines until the re-arm is seen, then state events
            message = json.loads(watch.stdout.readline())
            if message["event"] == "state":
                break
            assert message["event"] == "fault"
        assert message["joint_names"] == JOINTS and message["holding"] is True
    finally:
        watch.terminate()
        _, err = watch.communicate(timeout=30)
    assert "Traceback" not in err
