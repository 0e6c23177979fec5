"""How fast the emulated motors stop when the daemon fails, and what an API stall costs the loop.

For each driver with a device-side watchdog (Dynamixel Bus Watchdog, Damiao CAN timeout on
MIT-mode motors, the CiA 402 heartbeat consumer), a real daemon drives emulated motors (the
emulators run in this process; the daemon reaches them through the pty / socketcand as it would
reach real ones), a goal moves them, and then:

- ``loop_sigkill``: ``kill -9`` of the control-loop process;
- ``loop_sigstop``: the loop process stopped (``kill -STOP``): the loop stalls but lives;
- ``daemon_sigkill``: ``kill -9`` of the daemon's whole process group (API and loop).

``stop_ms`` is the time from the failure (taken just before the signal) to the motors being
stopped, by the emulators' own records on the shared monotonic clock: Dynamixel, the servo at
rest after its watchdog's brake; CiA 402, the drive at rest after its quick stop; Damiao, the
timeout's expiry, when the motor disables itself (torque off: the device's documented reaction,
it does not brake). ``missed_deadlines`` is null for these: the loop is dead or frozen.

``second_daemon`` (MIT motors on socketcand): a daemon on ``host: localhost`` runs a goal and a
second ``jtc-hw run`` with ``host: 127.0.0.1`` and the same motor ids is started (issue 21):
``exit_ms`` is the time from its start to its exit, which must be status 2 with nothing sent
(``connections``: TCP connections it opened to the socketcand server, must be 0) while the
first daemon's goal succeeds.

``motor_reset`` (``can-mit``, Damiao DM4310 only): motor 3 browns out mid-goal for 20 ms (less
than ``feedback_timeout``, 0.1 s) and restarts, answering disabled. ``detect_ms`` is the time
from the emulator's first reply after the restart (its record, on the monotonic clock) to the
loop cycle that reported the fault (the aborted goal's ``time_ns``: that cycle's deadline on
the loop's clock, the same monotonic clock). ``stop_ms`` is null: a reset motor is limp.

``api_sigstop`` (mirror hardware, 1 kHz): the API process is stopped for 3 s during a goal. The
loop must not wait for it: ``missed_deadlines`` is the loop's overrun count during the stall,
next to ``baseline_missed`` for the same length of time without one (the machine's own noise);
``stop_ms`` is null (the loop keeps commanding; it aborts the goal after ``api_stall_s`` and
holds).

``zenoh_no_credentials`` (mirror hardware, needs ``jtc_hw[zenoh]``; not in the default set):
a daemon with ``daemon.zenoh`` on a loopback port runs a goal; a plain Zenoh session, as
another local user would open one, sends ``stop`` without the token and then with a wrong one.
``refusal_ms`` is the time from the query to its ``unauthorized`` reply (``wrong_token_ms``:
with a wrong token, delayed on purpose), and the goal must run on to its result
(``goal_survived``).

``stop_slots_full`` (mirror hardware): 30 TCP connections that never authenticate are held
open (each re-opened as soon as the daemon drops it) while a goal runs; ``stop_ms`` is the time
from the operator's stop over TCP (connect, ``auth`` with the token, ``stop``: what
``jtc-hw stop --tcp`` does) to its answer.

Usage::

    python bench/failsafe.py                    # every driver and failure, 3 runs each
    python bench/failsafe.py --runs 5 --json    # one JSON object per line
    python bench/failsafe.py --hardware dynamixel --failure loop_sigkill

Target (issue 10): ``stop_ms`` <= 150 with ``watchdog_s: 0.1`` for every driver that has a
watchdog.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import selectors
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jtc_hw.api.client import Client  # noqa: E402
from jtc_hw.drivers.can.cia402.emulator import Cia402DriveEmulator  # noqa: E402
from jtc_hw.drivers.can.mit.emulator import MitBusEmulator  # noqa: E402
from jtc_hw.drivers.can.socketcand import SocketcandServer  # noqa: E402
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator  # noqa: E402
from jtc_hw.errors import JtcHwError  # noqa: E402

WATCHDOG_S = 0.1
TARGET_MS = 150.0
START_TIMEOUT_S = 30.0
WAIT_S = 10.0
FAILURES = ("loop_sigkill", "loop_sigstop", "daemon_sigkill")
HARDWARE = ("dynamixel", "can-mit", "can-cia402")


def controller(joints: list[str], rate_hz: int, command: str,
               gains: dict[str, float] | None = None) -> dict[str, Any]:
    params: dict[str, Any] = {
        "joints": joints,
        "command_interfaces": [command],
        "state_interfaces": ["position", "velocity"],
        "state_publish_rate": 50.0,
        "action_monitor_rate": 20.0,
        "constraints": {"goal_time": 1.0, **{j: {"trajectory": 0.0, "goal": 0.05}
                                             for j in joints}},
    }
    if gains is not None:
        params["gains"] = {j: gains for j in joints}
    return {
        "controller_manager": {"ros__parameters": {"update_rate": rate_hz}},
        "joint_trajectory_controller": {"ros__parameters": params},
    }


class DaemonRun:
    """``python -m jtc_hw run`` on ``config`` in its own session, with its log in a file."""

    def __init__(self, config: dict[str, Any], directory: Path) -> None:
        self.socket = str(directory / "jtc-hw.sock")
        config = dict(config, daemon={**config.get("daemon", {}), "socket": self.socket})
        path = directory / "robot.yaml"
        path.write_text(yaml.safe_dump(config, sort_keys=False))
        self.log_path = directory / "daemon.log"
        self._log = open(self.log_path, "w")  # noqa: SIM115 (closed in close())
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
        for key in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "JOURNAL_STREAM"):
            env.pop(key, None)
        self.process = subprocess.Popen(
            [sys.executable, "-m", "jtc_hw", "run", str(path)],
            stdout=self._log, stderr=subprocess.STDOUT, env=env, start_new_session=True,
        )

    def connect(self) -> Client:
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"the daemon exited ({self.process.returncode}):\n"
                                   f"{self.log_path.read_text()[-3000:]}")
            try:
                return Client.connect(self.socket, timeout_s=5.0)
            except (OSError, JtcHwError):
                if time.monotonic() > deadline:
                    raise RuntimeError("the daemon did not answer") from None
                time.sleep(0.05)  # polling for the socket of a starting daemon

    def close(self) -> None:
        if self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGCONT)
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                pass
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)  # whatever is left of the group
        self.process.wait()
        self._log.close()


# -- the emulated robots ------------------------------------------------------------------------
# Each rig yields (config, stopped) where stopped(t_fail) waits for every motor to be stopped
# by its own watchdog and returns the last one's stop time (monotonic s), or None.

Rig = tuple[dict[str, Any], Callable[[float], float | None]]


@contextlib.contextmanager
def dynamixel_rig() -> Iterator[Rig]:
    ids = [1, 2, 3, 4, 5, 6]
    joints = [f"joint{i}" for i in ids]
    with DynamixelEmulator(ids, initial_positions={i: math.pi for i in ids}) as emu:
        config = controller(joints, 200, "velocity", {"p": 5.0, "ff_velocity_scale": 1.0})
        config["hardware"] = [{"name": "arm", "kind": "dynamixel", "joints": joints, "params": {
            "port": emu.device_path, "baud_rate": 4_000_000, "ids": ids,
            "model": "XM430-W350", "offset": -math.pi, "timeout_ms": 30.0, "max_retries": 1,
            "latency_timer_warn": False, "watchdog_s": WATCHDOG_S}}]

        def stopped(t_fail: float) -> float | None:
            trips = emu.wait_watchdog_stopped(ids, timeout_s=WAIT_S, since_s=t_fail)
            times = [t.stopped_s for t in trips.values() if t.stopped_s is not None]
            return max(times) if len(times) == len(ids) else None

        yield config, stopped


@contextlib.contextmanager
def can_mit_rig() -> Iterator[Rig]:
    ids = [1, 2, 3, 4, 5, 6]
    joints = [f"joint{i}" for i in ids]
    channel = f"failsafe-{uuid.uuid4().hex[:8]}"
    bus = can.Bus(interface="virtual", channel=channel)
    server = SocketcandServer(port=0, channels={"can0": channel})
    emu = MitBusEmulator(bus, ids, "DM4310", master_id=0x11)
    try:
        emu.start()
        server.start()
        config = controller(joints, 250, "position")
        config["hardware"] = [{"name": "leg", "kind": "can-mit", "joints": joints, "params": {
            "buses": {"can0": {"interface": "socketcand", "host": "127.0.0.1",
                               "port": server.port, "channel": "can0", "bitrate": 1_000_000,
                               "receive_timeout": 0.001}},
            "ids": ids, "model": "DM4310", "master_id": 0x11, "kp": 40.0, "kd": 1.0,
            "feedback_timeout": 0.1, "watchdog_s": WATCHDOG_S}}]

        def stopped(t_fail: float) -> float | None:
            expired = emu.wait_timeout_expiries(since=t_fail, timeout_s=WAIT_S)
            return max(expired.values()) if len(expired) == len(ids) else None

        yield config, stopped
    finally:
        server.stop()
        emu.stop()
        bus.shutdown()


@contextlib.contextmanager
def can_cia402_rig() -> Iterator[Rig]:
    nodes = [3, 7]
    joints = ["shoulder", "elbow"]
    channel = f"failsafe-{uuid.uuid4().hex[:8]}"
    bus = can.Bus(interface="virtual", channel=channel)
    drives = [Cia402DriveEmulator(bus, n, initial_position=0.1 * (i + 1))
              for i, n in enumerate(nodes)]
    server = SocketcandServer(port=0, channels={"can0": channel})
    try:
        for drive in drives:
            drive.start()
        server.start()
        config = controller(joints, 250, "position")
        config["hardware"] = [{"name": "arm", "kind": "can-cia402", "joints": joints, "params": {
            "buses": {"can0": {"interface": "socketcand", "channel": "can0",
                               "host": "127.0.0.1", "port": server.port,
                               "receive_timeout": 0.002, "setup_timeout": 0.5}},
            "node_id": nodes, "feedback_timeout_s": 0.25, "watchdog_s": WATCHDOG_S}}]
        seen = [len(d.watchdog_trips) for d in drives]

        def stopped(t_fail: float) -> float | None:
            times = []
            for drive, since in zip(drives, seen, strict=True):
                trip = drive.wait_watchdog_stop(WAIT_S, since=since)
                if trip is None or trip.stopped_at is None or trip.detected_at < t_fail:
                    return None
                times.append(trip.stopped_at)
            return max(times)

        yield config, stopped
    finally:
        server.stop()
        for drive in drives:
            drive.stop()
        bus.shutdown()


RIGS = {"dynamixel": dynamixel_rig, "can-mit": can_mit_rig, "can-cia402": can_cia402_rig}


def moving_goal(client: Client, duration_s: float = 4.0) -> None:
    """A slow goal started, and half a second of it run (the motors are moving)."""
    with client.subscribe_state() as sub:
        state = sub.get(timeout_s=WAIT_S)
    start = state["actual"]["positions"]
    goal = client.send_goal({"joint_names": state["joint_names"], "points": [
        {"time_from_start": duration_s, "positions": [p + 0.8 for p in start],
         "velocities": [0.0] * len(start)}]})
    for feedback in goal.feedback(timeout_s=WAIT_S):
        if feedback["time_from_start"] >= 0.5:
            return


def watchdog_run(hardware: str, failure: str) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="jtc-hw-failsafe-") as tmp, \
            RIGS[hardware]() as (config, stopped):
        daemon = DaemonRun(config, Path(tmp))
        try:
            with daemon.connect() as client:
                loop_pid = int(client.get_status()["loop_pid"])
                moving_goal(client)
                t_fail = time.monotonic()
                if failure == "loop_sigkill":
                    os.kill(loop_pid, signal.SIGKILL)
                elif failure == "loop_sigstop":
                    os.kill(loop_pid, signal.SIGSTOP)
                else:
                    os.killpg(daemon.process.pid, signal.SIGKILL)
                t_stop = stopped(t_fail)
        finally:
            daemon.close()
    return {"hardware": hardware, "failure": failure,
            "stop_ms": None if t_stop is None else round((t_stop - t_fail) * 1e3, 1),
            "missed_deadlines": None, "watchdog_ms": WATCHDOG_S * 1e3}


def motor_reset_run(hardware: str) -> dict[str, Any]:
    """A Damiao motor browns out mid-goal and restarts disabled: how soon the loop faults."""
    ids = [1, 2, 3, 4, 5, 6]
    joints = [f"joint{i}" for i in ids]
    channel = f"failsafe-{uuid.uuid4().hex[:8]}"
    bus = can.Bus(interface="virtual", channel=channel)
    server = SocketcandServer(port=0, channels={"can0": channel})
    emu = MitBusEmulator(bus, ids, "DM4310", master_id=0x11)
    detect_ms = None
    try:
        emu.start()
        server.start()
        config = controller(joints, 250, "position")
        config["hardware"] = [{"name": "leg", "kind": "can-mit", "joints": joints, "params": {
            "buses": {"can0": {"interface": "socketcand", "host": "127.0.0.1",
                               "port": server.port, "channel": "can0", "bitrate": 1_000_000,
                               "receive_timeout": 0.001}},
            "ids": ids, "model": "DM4310", "master_id": 0x11, "kp": 40.0, "kd": 1.0,
            "feedback_timeout": 0.1, "watchdog_s": WATCHDOG_S}}]
        with tempfile.TemporaryDirectory(prefix="jtc-hw-failsafe-") as tmp:
            daemon = DaemonRun(config, Path(tmp))
            try:
                with daemon.connect() as client:
                    with client.subscribe_state() as sub:
                        start = sub.get(timeout_s=WAIT_S)["actual"]["positions"]
                    goal = client.send_goal({"joint_names": joints, "points": [
                        {"time_from_start": 4.0, "positions": [p + 0.8 for p in start],
                         "velocities": [0.0] * len(start)}]})
                    for feedback in goal.feedback(timeout_s=WAIT_S):
                        if feedback["time_from_start"] >= 0.5:
                            break
                    emu.brown_out(3, 0.02)
                    result = goal.wait(timeout_s=WAIT_S)
                    replies = emu.first_replies_after_reset(3)
                    if result["status"] == "aborted" and "reset" in result["error_string"] \
                            and replies:
                        detect_ms = round((result["time_ns"] / 1e9 - replies[0]) * 1e3, 1)
                    else:
                        print(f"# motor_reset: not detected as a reset: {result}",
                              file=sys.stderr)
            finally:
                daemon.close()
    finally:
        server.stop()
        emu.stop()
        bus.shutdown()
    return {"hardware": hardware, "failure": "motor_reset", "stop_ms": None,
            "detect_ms": detect_ms, "missed_deadlines": None, "watchdog_ms": WATCHDOG_S * 1e3}


def api_stall_run(stall_s: float, priority: int) -> dict[str, Any]:
    joints = [f"joint{i}" for i in range(1, 7)]
    config = controller(joints, 1000, "position")
    config["hardware"] = [{"name": "arm", "kind": "mirror", "joints": joints,
                           "params": {"lag_s": 0.0}}]
    config["daemon"] = {"realtime": {"priority": priority}}
    with tempfile.TemporaryDirectory(prefix="jtc-hw-failsafe-") as tmp:
        daemon = DaemonRun(config, Path(tmp))
        try:
            with daemon.connect() as client:
                # The same stretch with a goal and no stall: the machine's own noise.
                moving_goal(client, duration_s=2 * stall_s + 4.0)
                baseline0 = loop_counts(client, after=loop_counts(client))  # a fresh status
                time.sleep(stall_s)
                baseline1 = loop_counts(client, after=baseline0)
                moving_goal(client, duration_s=2 * stall_s + 4.0)  # preempts: a fresh goal
                before = loop_counts(client, after=loop_counts(client))
                os.kill(daemon.process.pid, signal.SIGSTOP)
                time.sleep(stall_s)  # the stall being measured
                os.kill(daemon.process.pid, signal.SIGCONT)
                after = loop_counts(client, after=before)
        finally:
            daemon.close()
    return {"hardware": "mirror", "failure": "api_sigstop", "stop_ms": None,
            "missed_deadlines": after[1] - before[1],
            "baseline_missed": baseline1[1] - baseline0[1],
            "cycles": after[0] - before[0], "stall_s": stall_s}


def second_daemon_run() -> dict[str, Any]:
    """``second_daemon``: see the module docstring."""
    ids = [1, 2, 3, 4, 5, 6]
    joints = [f"joint{i}" for i in ids]
    channel = f"failsafe-{uuid.uuid4().hex[:8]}"
    bus = can.Bus(interface="virtual", channel=channel)
    server = SocketcandServer(port=0, channels={"can0": channel})
    emu = MitBusEmulator(bus, ids, "AK80-9")
    try:
        emu.start()
        server.start()

        def config(host: str) -> dict[str, Any]:
            config = controller(joints, 250, "position")
            config["hardware"] = [{"name": "leg", "kind": "can-mit", "joints": joints,
                                   "params": {"buses": {"can0": {
                                       "interface": "socketcand", "host": host,
                                       "port": server.port, "channel": "can0",
                                       "receive_timeout": 0.001}},
                                       "ids": ids, "kp": 40.0, "kd": 1.0,
                                       "feedback_timeout": 0.1}}]
            return config

        with tempfile.TemporaryDirectory(prefix="jtc-hw-failsafe-") as tmp:
            first_dir, second_dir = Path(tmp, "first"), Path(tmp, "second")
            first_dir.mkdir()
            second_dir.mkdir()
            first = DaemonRun(config("localhost"), first_dir)
            try:
                with first.connect() as client:
                    with client.subscribe_state() as sub:
                        start = sub.get(timeout_s=WAIT_S)["actual"]["positions"]
                    goal = client.send_goal({"joint_names": joints, "points": [
                        {"time_from_start": 6.0, "positions": [p + 0.4 for p in start]}]})
                    connections = server.connections
                    t0 = time.monotonic()
                    second = DaemonRun(config("127.0.0.1"), second_dir)
                    try:
                        code = second.process.wait(timeout=START_TIMEOUT_S)
                        exit_ms = (time.monotonic() - t0) * 1e3
                    finally:
                        second.close()
                    opened = server.connections - connections
                    result = goal.wait(timeout_s=WAIT_S + 6.0)
            finally:
                first.close()
            refusal = [line for line in (second_dir / "daemon.log").read_text().splitlines()
                       if "cannot start:" in line]
    finally:
        server.stop()
        emu.stop()
        bus.shutdown()
    return {"hardware": "can-mit", "failure": "second_daemon", "stop_ms": None,
            "exit_ms": round(exit_ms, 1), "exit_code": code, "connections": opened,
            "first_goal": result["status"], "refusal": refusal[0] if refusal else None}


STRANGERS = 30


def stop_slots_full_run() -> dict[str, Any]:
    joints = [f"joint{i}" for i in range(1, 7)]
    config = controller(joints, 500, "position")
    config["hardware"] = [{"name": "arm", "kind": "mirror", "joints": joints,
                           "params": {"lag_s": 0.0}}]
    with socket.socket() as probe:  # a free port (the daemon binds it a moment later)
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    token = uuid.uuid4().hex
    config["daemon"] = {"tcp": {"host": "127.0.0.1", "port": port, "token": token}}
    done = threading.Event()
    selector = selectors.DefaultSelector()

    def open_one() -> None:
        sock = socket.create_connection(("127.0.0.1", port), timeout=WAIT_S)
        sock.setblocking(False)
        selector.register(sock, selectors.EVENT_READ)

    def strangers() -> None:  # re-open each connection the daemon drops
        while not done.is_set():
            for key, _ in selector.select(timeout=0.1):
                sock = key.fileobj
                assert isinstance(sock, socket.socket)
                try:
                    data = sock.recv(65536)
                except OSError:
                    data = b""
                if not data:
                    selector.unregister(sock)
                    sock.close()
                    open_one()

    with tempfile.TemporaryDirectory(prefix="jtc-hw-failsafe-") as tmp:
        daemon = DaemonRun(config, Path(tmp))
        thread = threading.Thread(target=strangers)
        try:
            with daemon.connect() as client:
                moving_goal(client, duration_s=30.0)
                for _ in range(STRANGERS):
                    open_one()
                thread.start()
                time.sleep(1.5)  # the strangers fill the door and churn (not a measured wait)
                t_stop = time.monotonic()
                with Client.connect(tcp=("127.0.0.1", port), token=token, hello=False,
                                    timeout_s=WAIT_S) as operator:
                    stopped = operator.stop(timeout_s=WAIT_S)["stopped"]
                t_answer = time.monotonic()
                door = client.get_status()["server"]["tcp"]
        finally:
            done.set()
            if thread.is_alive():
                thread.join(WAIT_S)
            for key in list(selector.get_map().values()):
                selector.unregister(key.fileobj)
                key.fileobj.close()  # type: ignore[union-attr]
            selector.close()
            daemon.close()
    return {"hardware": "mirror", "failure": "stop_slots_full",
            "stop_ms": round((t_answer - t_stop) * 1e3, 1) if stopped else None,
            "missed_deadlines": None, "strangers": STRANGERS,
            "dropped_waiting": door["dropped_waiting"]}
def zenoh_no_credentials_run() -> dict[str, Any]:
    import secrets
    import socket as sockets

    from jtc_hw.api.zenoh_client import open_session

    with sockets.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    joints = [f"joint{i}" for i in range(1, 7)]
    config = controller(joints, 500, "position")
    config["hardware"] = [{"name": "arm", "kind": "mirror", "joints": joints,
                           "params": {"lag_s": 0.0}}]
    prefix = f"jtc/bench/{uuid.uuid4().hex[:8]}"
    config["daemon"] = {"zenoh": {"prefix": prefix, "listen": [endpoint],
                                  "token": secrets.token_hex(16)}}
    with tempfile.TemporaryDirectory(prefix="jtc-hw-failsafe-") as tmp:
        daemon = DaemonRun(config, Path(tmp))
        try:
            with daemon.connect() as client:
                session = open_session({"connect/endpoints": [endpoint],
                                        "scouting/multicast/enabled": False,
                                        "scouting/gossip/enabled": False})
                try:
                    goal = client.send_goal({"joint_names": joints, "points": [
                        {"time_from_start": 2.0, "positions": [0.5] * 6}]})
                    times = []
                    for token in (None, "a wrong token of sixteen+"):
                        t0 = time.monotonic()
                        replies = list(session.get(f"{prefix}/rpc/stop", payload=b"{}",
                                                   attachment=token, timeout=WAIT_S))
                        times.append((time.monotonic() - t0) * 1e3)
                        reply = json.loads(replies[0].ok.payload.to_bytes())
                        if reply.get("error", {}).get("code") != "unauthorized":
                            raise RuntimeError(f"a stop without the token was not refused: "
                                               f"{reply}")
                    result = goal.wait(timeout_s=WAIT_S)
                finally:
                    session.close()
        finally:
            daemon.close()
    return {"hardware": "mirror", "failure": "zenoh_no_credentials", "stop_ms": None,
            "refusal_ms": round(times[0], 2), "wrong_token_ms": round(times[1], 1),
            "goal_survived": result["status"] == "succeeded"}


def loop_counts(client: Client, after: tuple[int, int] | None = None) -> tuple[int, int]:
    """(cycles, overruns) from a status the loop published after ``after``'s (2 Hz)."""
    deadline = time.monotonic() + WAIT_S
    while True:
        loop = client.get_status()["loop"]
        counts = (int(loop["cycles"]), int(loop["overruns"]))
        if after is None or counts[0] > after[0] + 500:
            return counts
        if time.monotonic() > deadline:
            raise RuntimeError("the loop published no new statistics")
        time.sleep(0.1)  # the loop publishes its statistics at 2 Hz


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    keys = sorted({(r["hardware"], r["failure"]) for r in rows}, key=lambda k: (k[0], k[1]))
    for hardware, failure in keys:
        runs = [r for r in rows if (r["hardware"], r["failure"]) == (hardware, failure)]
        row: dict[str, Any] = {"hardware": hardware, "failure": failure, "runs": len(runs)}
        for field in ("stop_ms", "missed_deadlines", "baseline_missed", "exit_ms", "detect_ms",
                      "refusal_ms", "wrong_token_ms"):
            values = [r[field] for r in runs if r.get(field) is not None]
            if field in runs[0]:
                row[field] = statistics.median(values) if values else None
                if values and len(values) > 1:
                    row[f"{field}_range"] = [min(values), max(values)]
        if "goal_survived" in runs[0]:
            row["goal_survived"] = all(r["goal_survived"] for r in runs)
        if failure == "second_daemon":
            row["refused_cleanly"] = sum(r["exit_code"] == 2 and r["connections"] == 0
                                         and r["first_goal"] == "succeeded" for r in runs)
            row["refusal"] = runs[-1]["refusal"]
        elif any(r.get("stop_ms") is None for r in runs) and failure not in (
                "api_sigstop", "motor_reset"):
            row["not_stopped_runs"] = sum(r.get("stop_ms") is None for r in runs)
        out.append(row)
    return out


# The failures measured on one rig only (not once per --hardware).
ONE_RIG: dict[str, list[str]] = {
    "api_sigstop": ["mirror"],
    "second_daemon": ["can-mit"],
    "motor_reset": ["can-mit"],  # a Damiao reply says "disabled"; others' resets look silent
    "stop_slots_full": ["mirror"],
    "zenoh_no_credentials": ["mirror"],
}


def run_one(hardware: str, failure: str, args: argparse.Namespace) -> dict[str, Any]:
    """One run of ``failure`` on ``hardware``: its row."""
    if failure == "api_sigstop":
        return api_stall_run(args.stall_s, args.priority)
    if failure == "second_daemon":
        return second_daemon_run()
    if failure == "motor_reset":
        return motor_reset_run(hardware)
    if failure == "stop_slots_full":
        return stop_slots_full_run()
    if failure == "zenoh_no_credentials":
        return zenoh_no_credentials_run()
    return watchdog_run(hardware, failure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--hardware", nargs="+", choices=HARDWARE, default=list(HARDWARE))
    parser.add_argument("--failure", nargs="+",
                        choices=(*FAILURES, *ONE_RIG),
                        default=[*FAILURES, *(f for f in ONE_RIG if f != "zenoh_no_credentials")])
    parser.add_argument("--runs", type=int, default=3, help="runs per row (median reported)")
    parser.add_argument("--stall-s", type=float, default=3.0, help="api_sigstop: stall length")
    parser.add_argument("--priority", type=int, default=80,
                        help="api_sigstop: the loop's SCHED_FIFO priority (0: normal)")
    parser.add_argument("--json", action="store_true", help="one JSON object per row")
    args = parser.parse_args(argv)
    rows: list[dict[str, Any]] = []
    for failure in args.failure:
        for hardware in ONE_RIG.get(failure, args.hardware):
            for run in range(args.runs):
                print(f"# {hardware} {failure} run {run + 1}/{args.runs}", file=sys.stderr)
                rows.append(run_one(hardware, failure, args))
    summary = summarise(rows)
    if args.json:
        for row in summary:
            print(json.dumps(row))
        return 0
    print(f"{'hardware':<12} {'failure':<15} {'stop_ms':>10} {'range':>15} "
          f"{'missed':>7} {'baseline':>9} {'runs':>5}  verdict")
    for row in summary:
        if row["failure"] == "second_daemon":
            span = row.get("exit_ms_range")
            ok = row["refused_cleanly"] == row["runs"]
            print(f"{row['hardware']:<12} {row['failure']:<15} {'exit_ms':>10} "
                  f"{row['exit_ms']:>7.1f} {'' if span is None else f'{span[0]:.1f}-{span[1]:.1f}'}"
                  f" {row['runs']:>5}  {'ok' if ok else 'FAILED'} (exit 2, nothing sent, the "
                  f"first goal succeeded: {row['refused_cleanly']}/{row['runs']})")
            continue
        stop = row.get("stop_ms")
        span = row.get("stop_ms_range")
        verdict = ""
        if row["failure"] == "motor_reset":
            detect, spread = row.get("detect_ms"), row.get("detect_ms_range")
            verdict = ("fault NOT reported" if detect is None else
                       f"fault {detect:.1f} ms after the first reply after the reset"
                       + ("" if spread is None else f" ({spread[0]:.1f}-{spread[1]:.1f})"))
        elif row["failure"] == "zenoh_no_credentials":
            verdict = (f"refused in {row['refusal_ms']:.1f} ms (wrong token: "
                       f"{row['wrong_token_ms']:.0f} ms); goal "
                       f"{'ran on' if row['goal_survived'] else 'STOPPED'}")
        elif row["failure"] != "api_sigstop":
            ok = stop is not None and not row.get("not_stopped_runs") and (
                span is None or span[1] <= TARGET_MS)
            verdict = f"{'ok' if ok else 'MISSED'} (<= {TARGET_MS:g} ms)"
        print(f"{row['hardware']:<12} {row['failure']:<15} "
              f"{'-' if stop is None else f'{stop:.1f}':>10} "
              f"{'' if span is None else f'{span[0]:.1f}-{span[1]:.1f}':>15} "
              f"{'-' if row.get('missed_deadlines') is None else row['missed_deadlines']:>7} "
              f"{'-' if row.get('baseline_missed') is None else row['baseline_missed']:>9} "
              f"{row['runs']:>5}  {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
