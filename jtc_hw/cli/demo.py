"""``jtc-hw demo``: start a daemon on simulated joints (or emulated motors), run a goal, stop.

The demo moves only a daemon it starts itself (decision 30): with ``--config``, a socket that
a running daemon already serves is refused, and the client checks that the process serving
the socket is the daemon started here before it sends anything. On emulated motors it starts
``jtc-hw emulate`` as a second process.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import yaml

from ..api.calls import NOT_EXPECTED, ClientConnectionError
from ..api.client import Client
from ..daemon.realtime import CAP_SYS_NICE, has_capability
from ..errors import JtcHwError
from .common import EXIT_BAD_INPUT, EXIT_NO_DAEMON, goal_result

__all__ = [
    "DEMO_EMULATED_WATCHDOG_S", "DEMO_HARDWARE", "DEMO_JOINTS", "DEMO_ROS2_CONTROLLER",
    "DEMO_LOOP_PRIORITY", "add_parsers", "cmd_demo", "demo_config", "demo_goal",
    "demo_hardware", "fifo_permitted",
]

DEMO_EXIT_HELP = (
    "Exit status: 0 the goal succeeded; 1 it aborted or was canceled; 2 bad configuration, "
    "or --config's socket is already served by a running daemon (the demo sends nothing "
    "to a daemon it did not start); 3 the daemon or emulator did not start or stopped "
    "with an error."
)

# The demo is set up as a robot would be on a busy machine (issue 22): its control loop at a
# real-time priority when the user may have one, the emulated motors likewise (real motors
# are not slowed down by the host's other work), and, on emulated motors, watchdogs and
# feedback timeouts that a busy laptop keeps. Normally scheduled beside four busy processes
# on two cores, the loop woke 1.2 ms late at the median and 24 ms at p99 (255 overruns in 297
# cycles at 250 Hz), so the CiA 402 drives lost its heartbeat in every run and the MIT and
# Dynamixel demos failed one run in five or two: a demo is not a test of the watchdog.

DEMO_JOINTS = [f"joint{i}" for i in range(1, 7)]

DEMO_ROS2_CONTROLLER = "arm_controller"
"""The controller node's name with ``--ros2``: /arm_controller/follow_joint_trajectory."""

DEMO_LOOP_PRIORITY = 2
"""SCHED_FIFO priority of the demo's control loop where permitted: above its emulators'."""

DEMO_EMULATED_WATCHDOG_S = 0.5
"""Watchdogs (``watchdog_s``) and feedback timeouts of the demo's emulated motors: a busy
laptop stalls a process for tens of ms now and then, beyond the 0.1 s a real arm would use."""


def fifo_permitted(priority: int) -> bool:
    """Whether this process may ask for SCHED_FIFO ``priority`` (sched(7)): with
    CAP_SYS_NICE (root, as usual), or an ``RLIMIT_RTPRIO`` (``ulimit -r``) of at least it.

    A group without real-time CPU budget may still refuse; the daemon then runs normally
    scheduled and says so at INFO."""
    if not hasattr(os, "sched_setscheduler"):
        return False
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    if soft == resource.RLIM_INFINITY or soft >= priority:
        return True
    return has_capability(CAP_SYS_NICE)


def demo_config(
    socket_path: str,
    hardware: list[dict[str, Any]] | None = None,
    update_rate: int = 500,
    priority: int = 0,
    ros2_connect: str | None = None,
) -> dict[str, Any]:
    """A six-joint arm, by default on simulated (mirror) hardware at 500 Hz, its loop at
    SCHED_FIFO ``priority`` (0: normally scheduled). ``jtc-hw demo`` asks for
    :data:`DEMO_LOOP_PRIORITY` when this user may have it (:func:`fifo_permitted`), else 0:
    no warning, a laptop's normal state. With ``ros2_connect`` (``--ros2``), the daemon is
    also upstream's controller in ROS 2 domain 0, named :data:`DEMO_ROS2_CONTROLLER` as in
    MoveIt's configurations, a Zenoh client of that router (``daemon.ros2``, docs/ros2.md)."""
    if hardware is None:
        hardware = [
            {"name": "arm", "kind": "mirror", "joints": DEMO_JOINTS, "params": {"lag_s": 0.005}}
        ]
    return {
        "controller_manager": {"ros__parameters": {"update_rate": update_rate}},
        "joint_trajectory_controller": {
            "ros__parameters": {
                "joints": DEMO_JOINTS,
                "command_interfaces": ["position"],
                "state_interfaces": ["position", "velocity"],
                "state_publish_rate": 50.0,
                "action_monitor_rate": 10.0,
                "constraints": {
                    "stopped_velocity_tolerance": 0.05,
                    "goal_time": 0.5,
                    **{j: {"trajectory": 0.1, "goal": 0.01} for j in DEMO_JOINTS},
                },
            }
        },
        "hardware": hardware,
        "daemon": {
            "socket": socket_path,
            "realtime": {"priority": priority},
            **({} if ros2_connect is None else {
                "ros2": {"domain_id": 0, "controller_name": DEMO_ROS2_CONTROLLER,
                         "zenoh": {"mode": "client", "connect": [ros2_connect]}}}),
        },
    }


DEMO_HARDWARE = ("mirror", "dynamixel", "feetech", "can-mit", "can-cia402")


def _start_emulator(
    kind: str, timeout_s: float
) -> tuple[subprocess.Popen[str], str, threading.Thread]:
    """Start ``jtc-hw emulate`` for a demo hardware kind; return it, its connection line and
    the thread forwarding its stderr (join it once the emulator has exited: its last lines).

    The emulator runs at SCHED_FIFO where permitted: ``jtc-hw emulate`` asks for its default
    priority itself (``drivers/emulation_cli.py``)."""
    if kind == "dynamixel":
        # Its statistics once, when it stops: live, they interleaved with the progress bar.
        argv = ["dynamixel", "--ids", "1-6", "--model", "XM430-W350", "--baud", "4000000",
                "--stats", "exit"]
    elif kind == "feetech":  # LeRobot's SO-101: six STS3215 at their factory 1 Mbit/s
        argv = ["feetech", "--ids", "1-6", "--model", "STS3215", "--baud", "1000000",
                "--stats", "exit"]
    else:
        protocol = "mit" if kind == "can-mit" else "cia402"
        argv = ["can", "--protocol", protocol, "--ids", "1-6", "--pace",
                "--interface", "socketcand", "--socketcand-port", "0"]
    emulator = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "emulate", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    stdout, stderr = emulator.stdout, emulator.stderr
    assert stdout is not None and stderr is not None
    forward = threading.Thread(target=_forward, args=(stderr, "  emulator | "), daemon=True)
    forward.start()
    found: list[str] = []
    reader = threading.Thread(target=lambda: found.append(stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    line = found[0].strip() if found else ""
    if not line:
        emulator.kill()
        emulator.wait()
        raise JtcHwError(f"the {kind} emulator did not start (exit status {emulator.returncode})")
    return emulator, line, forward


def demo_hardware(kind: str, line: str) -> tuple[list[dict[str, Any]], int]:
    """The demo arm's hardware section and update rate on an emulator (``line``: what
    ``jtc-hw emulate`` printed: a device path, or ``interface=... host=... port=...``), with
    watchdogs and feedback timeouts of :data:`DEMO_EMULATED_WATCHDOG_S`."""
    if kind == "dynamixel":
        params: dict[str, Any] = {
            "port": line,
            "baud_rate": 4000000,
            "ids": [1, 2, 3, 4, 5, 6],
            "model": "XM430-W350",
            "offset": -math.pi,  # the emulated servos start at tick 2048 (pi): joint zero
            "timeout_ms": 20.0,  # a pty served by another process on a possibly busy machine
            "latency_timer_warn": False,
            "watchdog_s": DEMO_EMULATED_WATCHDOG_S,
        }
        return [{"name": "arm", "kind": "dynamixel", "joints": DEMO_JOINTS, "params": params}], 200
    if kind == "feetech":
        # No watchdog_s: these servos have none. 100 Hz as config/so101-follower.yaml: a read
        # and a write of six servos take about 1.2 ms of wire at 1 Mbit/s.
        params = {
            "port": line,
            "baud_rate": 1000000,
            "ids": [1, 2, 3, 4, 5, 6],
            "model": "STS3215",
            "offset": -math.pi,  # the emulated servos start at step 2048 (pi): joint zero
            "return_delay_time_us": 0,
            # A pty served by another process on a possibly busy machine: with 20 ms and one
            # retry the demo aborted on a missing reply beside two test suites on two cores.
            "timeout_ms": 50.0,
            "max_retries": 2,
        }
        return [{"name": "arm", "kind": "feetech", "joints": DEMO_JOINTS, "params": params}], 100
    fields = dict(item.split("=", 1) for item in line.split() if "=" in item)
    bus = {
        "interface": "socketcand",
        "channel": fields["channel"].split(",")[0],
        "host": fields["host"],
        "port": int(fields["port"]),
        "bitrate": 1000000,
        "receive_timeout": 0.002,
        "setup_timeout": 0.5,
    }
    if kind == "can-mit":
        params = {"buses": {"can0": bus}, "ids": [1, 2, 3, 4, 5, 6], "model": "AK80-9",
                  "kp": 40.0, "kd": 1.0, "feedback_timeout": DEMO_EMULATED_WATCHDOG_S,
                  "watchdog_s": DEMO_EMULATED_WATCHDOG_S}
    else:
        params = {"buses": {"can0": bus}, "node_id": [1, 2, 3, 4, 5, 6],
                  "feedback_timeout_s": DEMO_EMULATED_WATCHDOG_S,
                  "watchdog_s": DEMO_EMULATED_WATCHDOG_S}
    return [{"name": "arm", "kind": kind, "joints": DEMO_JOINTS, "params": params}], 250


def demo_goal() -> dict[str, Any]:
    """A wave through three waypoints over 3 s, ending at rest.

    Its fastest joint peaks near 1.3 rad/s: the emulated CAN motors track a moving reference
    with a lag of a few tens of ms (their PD gains, the bus round trip), so at twice that speed
    the demo ran at the edge of its 0.1 rad path tolerance and aborted whenever the machine was
    busy; a demo shows the robot working, not the tolerance's edge."""
    return {
        "joint_names": DEMO_JOINTS,
        "points": [
            {
                "time_from_start": 1.0,
                "positions": [0.1 * (i + 1) for i in range(6)],
                "velocities": [0.1] * 6,
            },
            {
                "time_from_start": 2.0,
                "positions": [-0.05 * (i + 1) for i in range(6)],
                "velocities": [-0.1] * 6,
            },
            {"time_from_start": 3.0, "positions": [0.0] * 6, "velocities": [0.0] * 6},
        ],
    }


def _forward(stream: Any, prefix: str) -> None:
    for line in iter(stream.readline, ""):
        print(f"{prefix}{line.rstrip()}", file=sys.stderr)


def cmd_demo(args: argparse.Namespace) -> int:
    if args.ros2 and args.config:
        print("error: --ros2 runs the built-in arm; for your robot file, add a daemon.ros2 "
              "section to it (docs/ros2.md)", file=sys.stderr)
        return EXIT_BAD_INPUT
    emulator = None
    forward = None
    hardware = None
    update_rate = 500
    if args.hardware != "mirror" and not args.config:
        emulator, line, forward = _start_emulator(args.hardware, args.timeout)
        print(f"jtc-hw demo: emulated {args.hardware} motors: {line}")
        hardware, update_rate = demo_hardware(args.hardware, line)
    try:
        return _demo(args, hardware, update_rate)
    finally:
        if emulator is not None:
            _stop(emulator, 10.0)
        if forward is not None:
            forward.join(5.0)  # its last lines (the statistics) after the demo's own


def _demo(args: argparse.Namespace, hardware: list[dict[str, Any]] | None, rate: int) -> int:
    """Start a daemon, send the demo goal to it and to nothing else (module docstring; the
    peer check is ``SO_PEERCRED``), stop it. Both refusals exit 2 (the configuration cannot be
    used for a demo now), like ``run`` with a socket in use.
    """
    with tempfile.TemporaryDirectory(prefix="jtc-hw-demo-") as tmp:
        if args.config:
            config_path = args.config
            from ..daemon.locks import held_by, socket_lock_path  # start-up time
            from ..daemon.robot import load_robot  # start-up time

            socket_path = load_robot(config_path).daemon.socket
            busy = held_by(socket_path, socket_lock_path(socket_path), what="served")
            if busy is not None:
                print(f"error: {_demo_refusal(config_path, str(busy))}", file=sys.stderr)
                return EXIT_BAD_INPUT
            goal = None
        else:
            socket_path = os.path.join(tmp, "jtc-hw.sock")
            config_path = os.path.join(tmp, "robot.yaml")
            priority = DEMO_LOOP_PRIORITY if fifo_permitted(DEMO_LOOP_PRIORITY) else 0
            config = demo_config(socket_path, hardware, rate, priority,
                                 args.ros2_connect if args.ros2 else None)
            Path(config_path).write_text(yaml.safe_dump(config))
            goal = demo_goal()
            if args.ros2:
                print(f"jtc-hw demo: ROS 2 domain 0 through the router {args.ros2_connect}: "
                      f"node /{DEMO_ROS2_CONTROLLER}, /joint_states, action "
                      f"/{DEMO_ROS2_CONTROLLER}/follow_joint_trajectory")
        print(f"jtc-hw demo: starting the daemon ({config_path})")
        daemon = subprocess.Popen(
            [sys.executable, "-m", "jtc_hw", "run", config_path],
            stderr=subprocess.PIPE,
            text=True,
        )
        assert daemon.stderr is not None
        threading.Thread(target=_forward, args=(daemon.stderr, "  daemon | "), daemon=True).start()
        client = None
        deadline = time.monotonic() + args.timeout
        while client is None:
            if daemon.poll() is not None:
                print(
                    f"the daemon exited with status {daemon.returncode} before it was ready",
                    file=sys.stderr,
                )
                return EXIT_NO_DAEMON
            try:
                client = Client.connect(socket_path, timeout_s=2.0, expect_pid=daemon.pid)
            except (OSError, JtcHwError) as exc:
                if isinstance(exc, ClientConnectionError) and exc.code == NOT_EXPECTED:
                    # another daemon took the path: not ours to move
                    _stop(daemon)
                    print(f"error: {_demo_refusal(config_path, str(exc))}", file=sys.stderr)
                    return EXIT_BAD_INPUT
                if time.monotonic() > deadline:
                    daemon.terminate()
                    print("the daemon did not open its socket in time", file=sys.stderr)
                    return EXIT_NO_DAEMON
                time.sleep(0.05)  # CLI polling for a socket to appear; not in library code
        try:
            names = client.joint_names
            if goal is None:  # --config's joints: to 0.3 and back, at rest at each point
                points = [
                    {"time_from_start": t, "positions": [p] * len(names),
                     "velocities": [0.0] * len(names)}
                    for t, p in ((2.0, 0.3), (4.0, 0.0))
                ]
                goal = {"joint_names": names, "points": points}
            total = goal["points"][-1]["time_from_start"]
            handle = client.send_goal(goal)
            print(
                f"goal {handle.goal_id} accepted: {len(goal['points'])} points over {total} s "
                f"on {len(names)} joints"
            )
            code = goal_result(handle, total, False, args.timeout)
            status = client.get_status()
            loop = status.get("loop", {})
            late = loop.get("lateness_us", {})
            print(
                f"loop: {loop.get('rate_hz')} Hz, {loop.get('cycles')} cycles, "
                f"wake-up lateness p50 {late.get('p50')} us, p99 {late.get('p99')} us, "
                f"overruns {loop.get('overruns')}"
            )
        finally:
            client.close()
            status_code = _stop(daemon)
        print(f"daemon stopped (SIGTERM), exit status {status_code}")
        return code if status_code == 0 else EXIT_NO_DAEMON


def _stop(process: subprocess.Popen[str], timeout_s: float = 20.0) -> int:
    """SIGTERM the demo's daemon or emulator and wait for it (SIGKILL after ``timeout_s``);
    its exit status."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.wait()


def _demo_refusal(config_path: str, reason: str) -> str:
    """The one line of a demo that will not send its goal: another daemon serves the socket."""
    return (
        f"jtc-hw demo --config {config_path} sends nothing: {reason}. The demo moves only a "
        f"daemon it starts itself; to move the running one: 'jtc-hw send GOAL --config "
        f"{config_path}'"
    )


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "demo",
        help="run a goal on simulated joints and show what happened",
        description=(
            "Start a daemon on simulated joints (or on --config's hardware), "
            "send a sample trajectory, show its progress and result, stop."
        ),
        epilog=DEMO_EXIT_HELP,
    )
    p.add_argument("--config", help="use this robot configuration instead of the built-in arm")
    p.add_argument(
        "--hardware",
        choices=DEMO_HARDWARE,
        default="mirror",
        help=(
            "what the built-in six-joint arm runs on: simulated joints (mirror, the default), "
            "or emulated motors speaking the real protocol, started for the demo: dynamixel "
            "(six XM430-W350 on a pseudo-terminal, through the Dynamixel SDK), feetech (six "
            "STS3215 at 1 Mbit/s, LeRobot's SO-101 servos, through Feetech's SDK), can-mit (six "
            "AK80-9 in MIT mode) or can-cia402 (six CiA 402 drives), both over python-can's "
            "socketcand interface"
        ),
    )
    p.add_argument(
        "--ros2",
        action="store_true",
        help=(
            "also serve the arm as upstream's joint_trajectory_controller in ROS 2 domain 0 "
            f"(node /{DEMO_ROS2_CONTROLLER}, /joint_states, the "
            f"/{DEMO_ROS2_CONTROLLER}/follow_joint_trajectory action) over rmw_zenoh. Needs "
            "jtc_hw[ros2] and a Zenoh router on "
            "tcp/127.0.0.1:7447 (on a ROS 2 machine: ros2 run rmw_zenoh_cpp rmw_zenohd); "
            "docs/ros2.md"
        ),
    )
    p.add_argument(
        "--ros2-connect",
        default="tcp/127.0.0.1:7447",
        metavar="ENDPOINT",
        help="with --ros2: the router to connect to (default tcp/127.0.0.1:7447)",
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=30.0,
        help="seconds to wait for the daemon (and emulator) to start and answer (default 30)",
    )
    p.set_defaults(func=cmd_demo)
