#!/usr/bin/env python3
"""Wake-up lateness of the real daemon's control loop, idle and under client load.

For each rate, starts ``python -m jtc_hw run`` as a subprocess on six simulated (mirror) joints
(``jtc_hw.cli.demo.demo_config`` with the rate changed; socket in a temporary directory) and runs
two scenarios on it, one after the other:

  idle    no client but the measuring one, which asks for ``get_status`` twice a second.
  loaded  8 more connections, each subscribed to ``state`` and read by its own thread, plus one
          connection sending a 2,000-point goal (``--goal-points``) every second (6 joints,
          positions and velocities
          of a smooth wave, points 1 ms apart over 2 s, stamped with the client's "now" on the
          shared CLOCK_MONOTONIC) and waiting for its acceptance. Each goal continues the wave of
          the previous one and preempts it after about 1 s plus its planning time; each would
          brake to rest in its last 0.25 s, should no successor come. Accepted goals and their
          results (canceled = preempted by the next one) are counted and reported.

Optionally (``--scenarios bare idle loaded``), ``bare`` first runs the loop's clock alone for
the same time: ``jtc_hw.daemon.loop.clock.Ticker`` in a fresh process with the same real-time set-up
(``apply_realtime``, timer slack, frozen GC) and nothing to do per cycle. What it measures is the
floor set by this machine, its kernel and the interpreter, not by jtc_hw.

Where the figures come from:

- lateness (``woke - deadline`` of each cycle) is measured by the loop itself
  (``jtc_hw.daemon.loop.stats``) and published in ``get_status()["loop"]`` every 0.5 s. Its
  percentiles cover a sliding window of the last 10 s of cycles and cannot be reset from a
  client, so ``p50``/``p99`` are those of the window that ends with the run (the run's last 10
  s; a run shorter than that is preceded by a warm-up in the same scenario so that the window
  holds nothing else); ``p99 worst`` is the largest p99 of the windows published during the
  scenario (every 10 s stretch of the run is inside one of them); ``max`` is the largest window
  maximum of those windows, which together cover the whole run (plus at most the scenario's
  warm-up). - overruns: the loop's count of skipped deadlines, end of the run minus start. -
  CPU: utime + stime from ``/proc/<pid>/stat`` before and after the run, as percent of one core,
  for the loop process (the daemon's child) and the API process (the daemon itself); also for
  this process (the clients) and, from ``/proc/stat``, for the whole machine (all processes,
  tick-sampled, so only roughly comparable), since other processes competing for the CPUs change
  the figures, above all those of a normally scheduled loop.

With ``--live-view`` the daemon also serves the Foxglove live view (``daemon.foxglove``, port
chosen freely) and a viewer (``websockets``, the protocol by hand) subscribes to every channel
and reads every message throughout idle and loaded, as Foxglove would: the figures then include
the view's cost, for docs/benchmarks.md's side-by-side comparison. ``--flight-recorder-s``
(default 10: the daemon's default, its full-rate cycle ring included; 0 off) and ``--record``
(``daemon.record`` into a temporary directory) do the same for the recorders.

With ``--zenoh`` the daemon is also on Zenoh (``daemon.zenoh``, listening on a free loopback
port) and a Zenoh session of this process subscribes to its state stream and events throughout
(needs jtc_hw[zenoh]): the same comparison for the Zenoh interface (issue 14).

With ``--ros2`` the daemon is also upstream's controller in a ROS 2 graph (``daemon.ros2``,
issue 25), a client of a Zenoh router this process runs on a free loopback port, and a Zenoh
session of this process subscribes to its ``/joint_states`` and ``controller_state`` (decoding
each with rosbags, as a ROS 2 client would) throughout: the same comparison for the ROS 2
transport.

With ``--breakdown`` the loop process times each phase of its period (``JTC_HW_LOOP_PHASES``,
``jtc_hw.daemon.loop.phases``: read, update, write, the cycle ring, the State, the statistics,
the status, the outbox, the inbox, gc, ...) and each run prints their p50, p99, max and mean
over its cycles, with ``period``, the whole work between two wake-ups; the wrappers that time
the phases add about 0.25 us per call, 3-4 us, to it. ``--joints N`` runs the daemon on N
mirror joints (default 6, the demo arm's). ``--goal-points 20000`` makes the loaded scenario's
goals 20,000 points (issue 24: the loop's figures while a large goal arrives every second).

Everything the daemon writes (its socket, configuration, log, flight recordings, the phase
file) goes into one temporary directory, removed when the daemon has stopped.

Usage:  python bench/loop_jitter.py [--duration S] [--rates 500 1000]
            [--scenarios [bare] idle loaded] [--priority N] [--cpu N] [--lock-memory]
            [--live-view] [--zenoh] [--ros2] [--flight-recorder-s S] [--record] [--breakdown]
            [--joints N] [--goal-points N] [--json]
Target: at 1 kHz, p99 lateness < 300 us and no overruns, idle and loaded.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jtc_hw.api.client import Client  # noqa: E402
from jtc_hw.cli.demo import demo_config  # noqa: E402
from jtc_hw.daemon.loop.phases import (  # noqa: E402
    COLUMNS,
    PARENT,
    PHASES_ENV,
    read_rows,
    summarise,
)
from jtc_hw.daemon.loop.stats import DEFAULT_WINDOW_S  # noqa: E402
from jtc_hw.errors import GoalRejected, JtcHwError  # noqa: E402

TARGET_RATE_HZ = 1000.0
TARGET_P99_US = 300.0
SUBSCRIBERS = 8
GOAL_POINTS = 2000
GOAL_SPACING_S = 0.001
GOAL_EVERY_S = 1.0
BRAKE_FROM_S = 1.75  # each goal follows the wave until here, then brakes to rest at its end
POLL_S = 0.5  # the loop publishes its statistics every 0.5 s
SETTLE_S = 2.0  # after a scenario is set up, before its run starts
START_TIMEOUT_S = 30.0
CLK_TCK = os.sysconf("SC_CLK_TCK")


# -- the daemon -------------------------------------------------------------------------------


def proc_cpu_s(pid: int, tid: int | None = None) -> float:
    """utime + stime of a process (or one of its threads) in seconds."""
    path = f"/proc/{pid}/stat" if tid is None else f"/proc/{pid}/task/{tid}/stat"
    fields = Path(path).read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # fields 14 and 15 of proc(5)


def machine_busy_s() -> float:
    """CPU time spent by every CPU on anything but idling, in seconds (``/proc/stat``)."""
    ticks = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return (sum(ticks[:8]) - ticks[3] - ticks[4]) / CLK_TCK  # all but idle and iowait


def ctx_switches(pid: int) -> tuple[int, int]:
    """Voluntary and involuntary context switches of a process's main thread."""
    values = {}
    for line in Path(f"/proc/{pid}/task/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        values[key] = value.strip()
    return int(values["voluntary_ctxt_switches"]), int(values["nonvoluntary_ctxt_switches"])




def free_port() -> int:
    """A TCP port free on the loopback interface now."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def default_joints(n: int) -> list[str]:
    return [f"joint{i}" for i in range(1, n + 1)]


def jitter_config(socket_path: str, joints: list[str]) -> dict[str, Any]:
    """The demo arm's configuration (``demo_config``) on ``joints`` mirror joints."""
    config = demo_config(socket_path)
    params = config["joint_trajectory_controller"]["ros__parameters"]
    demo = params["joints"]
    params["joints"] = joints
    constraints = params["constraints"]
    for joint in demo:
        per_joint = constraints.pop(joint)
    constraints.update({joint: dict(per_joint) for joint in joints})
    for component in config["hardware"]:
        component["joints"] = joints
    return config


class Daemon:
    """``python -m jtc_hw run`` on the demo arm at ``rate_hz``, in a temporary directory."""

    def __init__(
        self,
        rate_hz: float,
        priority: int,
        cpu: int | None,
        lock_memory: bool,
        daemon_settings: dict[str, Any] | None = None,
        joints: list[str] | None = None,
        breakdown: bool = False,
    ) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="jtc-hw-jitter-")
        tmp = Path(self._tmp.name)
        self.socket = str(tmp / "jtc-hw.sock")
        self.log_path = tmp / "daemon.log"
        self.phases_path = tmp / "phases.bin" if breakdown else None
        self.joints = joints or default_joints(6)
        config = jitter_config(self.socket, self.joints)
        config["controller_manager"]["ros__parameters"]["update_rate"] = rate_hz
        config["daemon"]["realtime"] = {
            "priority": priority,
            "lock_memory": lock_memory,
            "cpu_affinity": [] if cpu is None else [cpu],
        }
        config["daemon"]["flight_recorder_dir"] = str(tmp / "flight")  # removed with tmp
        config["daemon"].update(daemon_settings or {})
        self.config = config
        config_path = tmp / "robot.yaml"
        config_path.write_text(yaml.safe_dump(config))
        env = dict(
            os.environ,
            PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        )
        env.pop(PHASES_ENV, None)
        if self.phases_path is not None:
            env[PHASES_ENV] = str(self.phases_path)
        self._log = open(self.log_path, "w")  # noqa: SIM115 (closed in close())
        self.process = subprocess.Popen(
            [sys.executable, "-m", "jtc_hw", "run", str(config_path)],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=env,
        )
        self.pid = self.process.pid
        self.loop_pid = 0

    def connect(self) -> Client:
        """Wait until the daemon answers ``hello``; find the loop process.

        Raises:
            RuntimeError: the daemon exited or did not answer in time (its log is quoted).
        """
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(
                    f"the daemon exited with status {self.process.returncode}:\n{self.log_tail()}"
                )
            try:
                client = Client.connect(self.socket, timeout_s=5.0)
                break
            except (OSError, JtcHwError):
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"the daemon did not answer hello:\n{self.log_tail()}"
                    ) from None
                time.sleep(0.05)
        self.loop_pid = int(client.get_status()["loop_pid"])
        return client

    def scheduling(self) -> str:
        """How the loop process is actually scheduled (read back from the kernel)."""
        policy = os.sched_getscheduler(self.loop_pid)
        cpus = ",".join(map(str, sorted(os.sched_getaffinity(self.loop_pid))))
        if policy == os.SCHED_FIFO:
            how = f"SCHED_FIFO priority {os.sched_getparam(self.loop_pid).sched_priority}"
        elif policy == os.SCHED_OTHER:
            how = f"SCHED_OTHER (normal), nice {os.getpriority(os.PRIO_PROCESS, self.loop_pid)}"
        else:
            how = f"policy {policy}"
        locked = "unknown"
        for line in Path(f"/proc/{self.loop_pid}/status").read_text().splitlines():
            if line.startswith("VmLck:"):
                locked = line.split(":", 1)[1].strip()
        return f"{how}, CPUs {cpus}, locked memory {locked}"

    def log_tail(self, lines: int = 20) -> str:
        self._log.flush()
        return "\n".join(self.log_path.read_text().splitlines()[-lines:])

    def close(self) -> int | None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log.close()
        self._tmp.cleanup()
        return self.process.returncode

    def __enter__(self) -> Daemon:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


# -- the live view's viewer -------------------------------------------------------------------


class Viewer:
    """A Foxglove WebSocket client subscribed to every channel, reading in its own thread."""

    def __init__(self, daemon: Daemon) -> None:
        from websockets.sync.client import connect
        from websockets.typing import Subprotocol

        deadline = time.monotonic() + START_TIMEOUT_S
        marker = "live view (Foxglove WebSocket) on ws://"
        while True:
            found = [line for line in daemon.log_path.read_text().splitlines() if marker in line]
            if found:
                break
            if time.monotonic() > deadline:
                raise RuntimeError(f"the live view did not start:\n{daemon.log_tail()}")
            time.sleep(0.05)  # polling the daemon's log file for its start-up line
        url = "ws://" + found[0].split(marker, 1)[1].strip()
        self.ws = connect(url, subprotocols=[Subprotocol("foxglove.websocket.v1"),
                                                 Subprotocol("foxglove.sdk.v1")],
                          proxy=None, max_size=None)
        self.messages = 0
        self.bytes = 0
        self._thread = threading.Thread(target=self._read, name="viewer", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        subscribed = 0
        try:
            for frame in self.ws:
                if isinstance(frame, str):
                    op = json.loads(frame)
                    if op.get("op") == "advertise":
                        subs = [{"id": subscribed + i, "channelId": c["id"]}
                                for i, c in enumerate(op["channels"])]
                        subscribed += len(subs)
                        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                else:
                    self.messages += 1
                    self.bytes += len(frame)
        except Exception:  # the connection closed (close() or the daemon's stop)
            return

    def close(self) -> None:
        self.ws.close()
        self._thread.join(timeout=10)


class ZenohViewer:
    """A Zenoh session subscribed to the daemon's state and events (``--zenoh``)."""

    def __init__(self, endpoint: str, prefix: str) -> None:
        from jtc_hw.api.zenoh_client import open_session

        self.session = open_session({"connect/endpoints": [endpoint],
                                     "scouting/gossip/enabled": False})
        self.messages = 0
        self.subs = [self.session.declare_subscriber(f"{prefix}/{key}", self._count)
                     for key in ("state", "events")]

    def _count(self, sample: Any) -> None:
        json.loads(sample.payload.to_bytes())  # as a client would, to use it
        self.messages += 1

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


class Ros2Viewer:
    """A Zenoh router, and a session subscribed to the daemon's ``/joint_states`` and
    ``controller_state`` as a ROS 2 client (``--ros2``; needs jtc_hw[ros2])."""

    CONTROLLER = "joint_trajectory_controller"

    def __init__(self) -> None:
        import zenoh

        from jtc_hw.daemon.transports.ros2.types import ros_types
        from jtc_hw.daemon.transports.ros2.wire import topic_key

        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        configs = []
        for mode in ("router", "client"):
            config = zenoh.Config()
            config.insert_json5("mode", json.dumps(mode))
            key = "listen/endpoints" if mode == "router" else "connect/endpoints"
            config.insert_json5(key, json.dumps([self.endpoint]))
            config.insert_json5("scouting/multicast/enabled", "false")
            configs.append(config)
        self.router = zenoh.open(configs[0])
        self.session = zenoh.open(configs[1])
        types = ros_types("jazzy")
        self.store = types.typestore
        self.messages = 0
        self.subs = []
        for name, ros_type in (
                ("/joint_states", "sensor_msgs/msg/JointState"),
                (f"/{self.CONTROLLER}/controller_state",
                 "control_msgs/msg/JointTrajectoryControllerState")):
            key = topic_key(0, name, types.dds_name(ros_type), types.type_hash(ros_type))
            self.subs.append(self.session.declare_subscriber(
                key, lambda sample, t=ros_type: self._count(sample, t)))

    def _count(self, sample: Any, ros_type: str) -> None:
        self.store.deserialize_cdr(sample.payload.to_bytes(), ros_type)  # to use it
        self.messages += 1

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()
        self.router.close()


# -- the load ---------------------------------------------------------------------------------


def wave_goal(
    start_ns: int, epoch_ns: int, joint_names: list[str], points: int = GOAL_POINTS
) -> dict[str, Any]:
    """``points`` points (2,000), 1 ms apart, of q_j(t) = A_j (1 - cos w_j t) for t > 0 (0
    before), t from ``epoch_ns``.

    The wave starts at rest at 0, where the idle robot holds, and every goal continues it
    exactly up to ``BRAKE_FROM_S``, so a successor spliced in before then steps nothing. After
    that the wave's time slows down smoothly (a raised-cosine time warp) to stop at the last
    point, so a goal without a successor ends at rest.
    """
    tau = np.arange(1, points + 1) * GOAL_SPACING_S
    span = points * GOAL_SPACING_S - BRAKE_FROM_S
    u = np.clip(tau - BRAKE_FROM_S, 0.0, None)
    warp = np.where(
        tau <= BRAKE_FROM_S,
        tau,
        BRAKE_FROM_S + 0.5 * (u + span / math.pi * np.sin(math.pi * u / span)),
    )
    rate = np.where(tau <= BRAKE_FROM_S, 1.0, 0.5 * (1.0 + np.cos(math.pi * u / span)))
    t = np.clip((start_ns - epoch_ns) / 1e9 + warp, 0.0, None)[:, None]
    joints = np.arange(len(joint_names))
    amplitude = 0.2 + 0.05 * joints
    omega = 2 * math.pi * 0.25 * (1.0 + 0.1 * joints)
    positions = amplitude * (1.0 - np.cos(omega * t))
    velocities = amplitude * omega * np.sin(omega * t) * rate[:, None]
    return {
        "joint_names": joint_names,
        "start_time_ns": start_ns,
        "points": [
            {"time_from_start": float(s), "positions": p, "velocities": v}
            for s, p, v in zip(tau.tolist(), positions.tolist(), velocities.tolist(), strict=True)
        ],
    }


class Load:
    """8 state subscribers (one connection and one reading thread each) and a goal sender."""

    def __init__(self, socket_path: str, joints: list[str], points: int = GOAL_POINTS) -> None:
        self.joints = joints
        self.points = points
        self.stop = threading.Event()
        self.clients = [Client.connect(socket_path, timeout_s=10.0) for _ in range(SUBSCRIBERS)]
        self.subscriptions = [c.subscribe_state(timeout_s=2.0) for c in self.clients]
        self.received = [0] * SUBSCRIBERS
        self.dropped_daemon = [0] * SUBSCRIBERS
        self.goal_client = Client.connect(socket_path, timeout_s=10.0)
        self.goals: list[tuple[float, str, float, Any]] = []  # (sent, outcome, latency_s, handle)
        self.threads = [
            threading.Thread(target=self._read, args=(i,), name=f"subscriber-{i}", daemon=True)
            for i in range(SUBSCRIBERS)
        ]
        self.threads.append(threading.Thread(target=self._send, name="goals", daemon=True))
        for thread in self.threads:
            thread.start()

    def _read(self, i: int) -> None:
        subscription = self.subscriptions[i]
        while not self.stop.is_set():
            try:
                message = subscription.get(timeout_s=1.0)
            except (TimeoutError, StopIteration, JtcHwError):
                continue
            self.received[i] += 1
            self.dropped_daemon[i] = int(message.get("dropped_total") or 0)

    def _send(self) -> None:
        epoch = time.monotonic_ns() + round(GOAL_EVERY_S * 1e9)  # the wave starts after goal 1's
        next_s = time.monotonic()
        while not self.stop.is_set():
            sent = time.monotonic()
            handle = None
            try:
                goal = wave_goal(time.monotonic_ns(), epoch, self.joints, self.points)
                handle = self.goal_client.send_goal(goal)
                outcome = "accepted"
            except GoalRejected as exc:
                outcome = f"rejected: {exc}"
            except (TimeoutError, JtcHwError) as exc:
                outcome = f"error: {exc}"
            self.goals.append((sent, outcome, time.monotonic() - sent, handle))
            next_s += GOAL_EVERY_S
            self.stop.wait(max(0.0, next_s - time.monotonic()))
            next_s = max(next_s, time.monotonic() - GOAL_EVERY_S)  # never send a burst

    def counts(self) -> tuple[int, int, int]:
        """State messages read by the slowest subscriber, dropped by the daemon, dropped here."""
        return (
            min(self.received),
            sum(self.dropped_daemon),
            sum(s.dropped_locally for s in self.subscriptions),
        )

    def summary(
        self, begin: float, end: float, before: tuple[int, int, int], after: tuple[int, int, int]
    ) -> dict[str, Any]:
        """Goals sent in ``[begin, end)`` (monotonic seconds); state messages between the
        ``counts()`` taken ``before`` and ``after``."""
        mine = [g for g in self.goals if begin <= g[0] < end]
        accepted = [g for g in mine if g[1] == "accepted"]
        latency_ms = sorted(g[2] * 1e3 for g in accepted)
        results = Counter(
            (g[3].result or {}).get("status", "running") for g in accepted if g[3] is not None
        )
        return {
            "goals_sent": len(mine),
            "goals_accepted": len(accepted),
            "goals_rejected": sum(g[1].startswith("rejected") for g in mine),
            "goals_failed": sum(g[1].startswith("error") for g in mine),
            "goal_problems": sorted({g[1] for g in mine if g[1] != "accepted"}),
            "goal_results": dict(results),
            "accept_ms_p50": latency_ms[len(latency_ms) // 2] if latency_ms else None,
            "accept_ms_max": latency_ms[-1] if latency_ms else None,
            "goal_abort_reasons": sorted(
                {
                    str(g[3].result.get("error_string"))
                    for g in accepted
                    if g[3] is not None and (g[3].result or {}).get("status") == "aborted"
                }
            ),
            "state_per_subscriber_hz": round((after[0] - before[0]) / (end - begin), 1),
            "state_dropped_by_daemon": after[1] - before[1],
            "state_dropped_locally": after[2] - before[2],
        }

    def close(self) -> None:
        self.stop.set()
        for thread in self.threads:
            thread.join(timeout=15.0)
        for client in [*self.clients, self.goal_client]:
            client.close()


# -- one run ----------------------------------------------------------------------------------

BARE_LOOP = """
import gc, json, resource, sys, time
from jtc_hw.daemon.loop.clock import Ticker
from jtc_hw.daemon.loop.stats import LoopStats
from jtc_hw.daemon.realtime import apply_realtime
from jtc_hw.hardware.timing import reduce_timer_slack

rate, duration, priority, cpus, lock = json.loads(sys.argv[1])
apply_realtime(priority, lock, cpus)
reduce_timer_slack()
cycles = round(rate * duration)
stats = LoopStats(rate, window=cycles)
gc.collect()
gc.freeze()
gc.disable()
clock = time.monotonic_ns
before = resource.getrusage(resource.RUSAGE_SELF)
start = clock()
ticker = Ticker(round(1e9 / rate))
for _ in range(cycles):
    deadline, woke, skipped = ticker.wait()
    stats.record(woke - deadline, clock() - woke, skipped)
wall = (clock() - start) / 1e9
after = resource.getrusage(resource.RUSAGE_SELF)
cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
print(json.dumps({"stats": stats.snapshot(), "wall_s": wall, "cpu_s": cpu,
                  "switches": after.ru_nivcsw - before.ru_nivcsw}))
"""


def run_bare(rate_hz: float, args: argparse.Namespace) -> dict[str, Any]:
    """The loop's clock alone in a fresh process: this machine's floor (module docstring)."""
    settings = [
        rate_hz,
        args.duration,
        args.priority,
        [] if args.cpu is None else [args.cpu],
        args.lock_memory,
    ]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    done = subprocess.run(
        [sys.executable, "-c", BARE_LOOP, json.dumps(settings)],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    out = json.loads(done.stdout)
    loop, wall = out["stats"], out["wall_s"]
    late = loop["lateness_us"]
    return {
        "rate_hz": rate_hz,
        "scenario": "bare",
        "p50_us": late["p50"],
        "p99_us": late["p99"],
        "max_us": late["max"],
        "overruns": loop["overruns"],
        "cpu_pct": round(100 * out["cpu_s"] / wall, 1),
        "api_cpu_pct": None,
        "p99_worst_window_us": late["p99"],
        "percentile_window_s": round(loop["window_cycles"] / rate_hz, 2),
        "cycles": loop["cycles"],
        "expected_cycles": round(wall * rate_hz),
        "loop_involuntary_switches": out["switches"],
        "duration_s": round(wall, 2),
    }


def next_loop_stats(client: Client) -> dict[str, Any]:
    """The next loop statistics the loop publishes (it does every 0.5 s).

    Raises:
        RuntimeError: none within 10 s (the loop is not running).
    """
    seen = client.get_status().get("loop", {}).get("cycles")  # absent until the first one
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        time.sleep(0.05)
        loop = client.get_status().get("loop")
        if loop is not None and loop["cycles"] != seen:
            return dict(loop)
    raise RuntimeError("the loop published no statistics for 10 s")


def cpu_sample(daemon: Daemon) -> dict[str, float]:
    """Cumulative CPU seconds of the loop process (and its main thread), the API process, this
    process (the clients), and the whole machine; the loop thread's involuntary switches."""
    return {
        "loop": proc_cpu_s(daemon.loop_pid),
        "loop_main": proc_cpu_s(daemon.loop_pid, daemon.loop_pid),
        "api": proc_cpu_s(daemon.pid),
        "clients": proc_cpu_s(os.getpid()),
        "machine": machine_busy_s(),
        "switches": float(ctx_switches(daemon.loop_pid)[1]),
    }


def phase_count(daemon: Daemon) -> int:
    """Cycles the loop has written into its phase file (0 without ``--breakdown``)."""
    if daemon.phases_path is None:
        return 0
    return read_rows(daemon.phases_path, 1 << 62)[1]


def run_scenario(
    daemon: Daemon, client: Client, rate_hz: float, scenario: str, duration_s: float,
    goal_points: int = GOAL_POINTS,
) -> dict[str, Any]:
    """Set the scenario up, warm up, measure for ``duration_s``, tear it down."""
    load = Load(daemon.socket, daemon.joints, goal_points) if scenario == "loaded" else None
    try:
        # Every statistics window that begins after this many cycles is this scenario's alone.
        scenario_start = next_loop_stats(client)["cycles"]
        # A run shorter than the statistics window is preceded by enough of the same scenario
        # for the window that ends with the run to hold nothing else.
        warmup_s = max(SETTLE_S, DEFAULT_WINDOW_S - duration_s + 1.0)
        time.sleep(warmup_s)
        start = next_loop_stats(client)
        phases0 = phase_count(daemon)
        t0, cpu0 = time.monotonic(), cpu_sample(daemon)
        counts0 = load.counts() if load is not None else (0, 0, 0)
        snapshots = [start]
        while time.monotonic() < t0 + duration_s:
            time.sleep(min(POLL_S, max(0.0, t0 + duration_s - time.monotonic())))
            loop = client.get_status()["loop"]
            if loop["cycles"] != snapshots[-1]["cycles"]:
                snapshots.append(dict(loop))
        end = next_loop_stats(client)
        snapshots.append(end)
        t1, cpu1 = time.monotonic(), cpu_sample(daemon)
        phases = None
        if daemon.phases_path is not None:
            phases = summarise(read_rows(daemon.phases_path, phases0)[0])
        extra = load.summary(t0, t1, counts0, load.counts()) if load is not None else {}
    finally:
        if load is not None:
            load.close()
    wall = t1 - t0
    used = {key: cpu1[key] - cpu0[key] for key in cpu0}

    def pct(seconds: float) -> float:
        return round(100 * seconds / wall, 1)

    # Windows entirely inside the scenario; together they cover the run (module docstring).
    inside = [s for s in snapshots if s["cycles"] - s["window_cycles"] >= scenario_start]
    if not inside:
        raise RuntimeError("no statistics window lies inside the scenario; lengthen --duration")
    late, cost = end["lateness_us"], end["cost_us"]
    return {
        "rate_hz": rate_hz,
        "scenario": scenario,
        "p50_us": late["p50"],
        "p99_us": late["p99"],
        "max_us": max(s["lateness_us"]["max"] for s in inside),
        "overruns": end["overruns"] - start["overruns"],
        "cpu_pct": pct(used["loop"]),
        "api_cpu_pct": pct(used["api"]),
        "clients_cpu_pct": pct(used["clients"]),
        "machine_cpu_pct": pct(used["machine"]),
        "loop_main_thread_cpu_pct": pct(used["loop_main"]),
        "p99_worst_window_us": max(s["lateness_us"]["p99"] for s in inside),
        "percentile_window_s": round(end["window_cycles"] / rate_hz, 2),
        "worst_since_start_us": late["worst"],
        "cost_p50_us": cost["p50"],
        "cost_p99_us": cost["p99"],
        "cost_max_us": max(s["cost_us"]["max"] for s in inside),
        "overrun_cycles": end["overrun_cycles"] - start["overrun_cycles"],
        "cycles": end["cycles"] - start["cycles"],
        "expected_cycles": round(wall * rate_hz),
        "loop_involuntary_switches": round(used["switches"]),
        "duration_s": round(wall, 2),
        "warmup_s": round(warmup_s, 2),
        "joints": len(daemon.joints),
        **({} if phases is None else {"phases_us": phases}),
        **({"goal_points": goal_points} if load is not None else {}),
        **extra,
    }


def measure_rate(
    rate_hz: float, args: argparse.Namespace, note: Any
) -> tuple[str, list[dict[str, Any]]]:
    rows = []
    if "bare" in args.scenarios:
        note(f"{rate_hz:g} Hz bare: measuring {args.duration:g} s")
        rows.append(run_bare(rate_hz, args))
    settings: dict[str, Any] = {
        "flight_recorder_s": args.flight_recorder_s,
    }
    if args.live_view:
        settings["foxglove"] = {"port": 0}
    endpoint, prefix = f"tcp/127.0.0.1:{free_port()}", "jtc/bench/jitter"
    if args.zenoh:
        settings["zenoh"] = {"prefix": prefix, "listen": [endpoint],
                             "token": secrets.token_hex(16)}  # the bench only watches
    rviewer = Ros2Viewer() if args.ros2 else None
    if rviewer is not None:
        settings["ros2"] = {"zenoh": {"connect": [rviewer.endpoint]}}
    record_dir = None
    if args.record:
        record_dir = tempfile.mkdtemp(prefix="jtc-hw-jitter-record-")
        settings["record"] = record_dir
    with Daemon(rate_hz, args.priority, args.cpu, args.lock_memory, settings,
                default_joints(args.joints), args.breakdown) as daemon:
        client = daemon.connect()
        viewer = Viewer(daemon) if args.live_view else None
        zviewer = ZenohViewer(endpoint, prefix) if args.zenoh else None
        try:
            scheduling = daemon.scheduling()
            note(f"{rate_hz:g} Hz: daemon {daemon.pid}, loop {daemon.loop_pid}: {scheduling}")
            for scenario in (s for s in args.scenarios if s != "bare"):
                note(f"{rate_hz:g} Hz {scenario}: measuring {args.duration:g} s")
                seen = viewer.messages if viewer is not None else 0
                zseen = zviewer.messages if zviewer is not None else 0
                rseen = rviewer.messages if rviewer is not None else 0
                row = run_scenario(daemon, client, rate_hz, scenario, args.duration,
                                   args.goal_points)
                if viewer is not None:
                    row["live_view_messages"] = viewer.messages - seen
                if zviewer is not None:
                    row["zenoh_messages"] = zviewer.messages - zseen
                if rviewer is not None:
                    row["ros2_messages"] = rviewer.messages - rseen
                rows.append(row)
            rows = [dict(row, scheduling=scheduling, live_view=args.live_view, zenoh=args.zenoh,
                         ros2=args.ros2,
                         record=args.record, flight_recorder_s=args.flight_recorder_s)
                    for row in rows]
        finally:
            if viewer is not None:
                viewer.close()
            if zviewer is not None:
                zviewer.close()
            if rviewer is not None:
                rviewer.close()
            client.close()
            if daemon.process.poll() is not None:
                note(f"the daemon died:\n{daemon.log_tail()}")
    if record_dir is not None:
        shutil.rmtree(record_dir, ignore_errors=True)
    return scheduling, rows


# -- output -----------------------------------------------------------------------------------


def verdict(rows: list[dict[str, Any]]) -> str:
    mine = [
        r for r in rows if r["rate_hz"] == TARGET_RATE_HZ and r["scenario"] in ("idle", "loaded")
    ]
    target = f"{TARGET_RATE_HZ:g} Hz, p99 < {TARGET_P99_US:g} us, no overruns"
    if {r["scenario"] for r in mine} != {"idle", "loaded"}:
        return f"target ({target}, idle and loaded): not checked (needs both runs at 1000 Hz)"
    misses = []
    for r in mine:
        if r["p99_worst_window_us"] >= TARGET_P99_US:
            misses.append(f"{r['scenario']} p99 {r['p99_worst_window_us']:.0f} us")
        if r["overruns"]:
            misses.append(f"{r['scenario']} {r['overruns']} overruns")
    state = "MET" if not misses else "MISSED (" + "; ".join(misses) + ")"
    return f"target ({target}, idle and loaded; p99 of the worst 10 s window): {state}"


def print_table(
    rows: list[dict[str, Any]], args: argparse.Namespace, schedulings: dict[float, str]
) -> None:
    print(
        f"control-loop wake-up lateness, jtc_hw daemon on {args.joints} mirror joints, "
        f"loaded: {args.goal_points}-point goals, "
        f"{args.duration:g} s per run; Python {sys.version.split()[0]}, {os.cpu_count()} CPUs"
    )
    print(
        f"asked: --priority {args.priority} --cpu {'any' if args.cpu is None else args.cpu} "
        f"--lock-memory {args.lock_memory} --live-view {args.live_view} --zenoh {args.zenoh} "
        f"--ros2 {args.ros2}; "
        "the loop process ran with:"
    )
    for rate, how in schedulings.items():
        print(f"  {rate:g} Hz: {how}")
    print(
        "p50/p99: the loop's window of the run's last 10 s; p99w: worst 10 s window of the run; "
        "max: whole run; CPU: % of one core"
    )
    print(
        f"{'rate':>5}  {'scenario':<8}  {'p50 us':>7}  {'p99 us':>7}  {'p99w us':>7}  "
        f"{'max us':>8}  {'overruns':>8}  {'loop CPU':>8}  {'API CPU':>7}  {'goals ok':>8}"
    )
    for r in rows:
        goals = f"{r['goals_accepted']}/{r['goals_sent']}" if r["scenario"] == "loaded" else "-"
        api = "-" if r["api_cpu_pct"] is None else f"{r['api_cpu_pct']:.1f}%"
        print(
            f"{r['rate_hz']:>5g}  {r['scenario']:<8}  {r['p50_us']:>7.1f}  {r['p99_us']:>7.1f}  "
            f"{r['p99_worst_window_us']:>7.1f}  {r['max_us']:>8.1f}  {r['overruns']:>8d}  "
            f"{r['cpu_pct']:>7.1f}%  {api:>7}  {goals:>8}"
        )
    for r in rows:
        if r["scenario"] == "bare":
            print(
                f"  {r['rate_hz']:g} Hz bare: the clock alone, no daemon (percentiles over the "
                f"whole run); {r['cycles']} cycles "
                f"({r['expected_cycles']} expected); preempted "
                f"{r['loop_involuntary_switches']} times"
            )
            continue
        print(
            f"  {r['rate_hz']:g} Hz {r['scenario']}: cycle cost p50 {r['cost_p50_us']:.0f} us, "
            f"p99 {r['cost_p99_us']:.0f} us, max {r['cost_max_us']:.0f} us; "
            f"{r['cycles']} cycles ({r['expected_cycles']} expected); loop thread preempted "
            f"{r['loop_involuntary_switches']} times; CPU of the clients "
            f"{r['clients_cpu_pct']:g}%, of the whole machine ~{r['machine_cpu_pct']:g}% "
            "(tick-sampled)"
        )
        if "live_view_messages" in r:
            print(f"    live view: {r['live_view_messages']} messages to the viewer "
                  f"({r['live_view_messages'] / r['duration_s']:.0f}/s, warm-up included)")
        if "ros2_messages" in r:
            print(f"    ros2: {r['ros2_messages']} joint_states and controller_state messages "
                  f"to the subscriber ({r['ros2_messages'] / r['duration_s']:.0f}/s, warm-up "
                  "included)")
        if "zenoh_messages" in r:
            print(f"    zenoh: {r['zenoh_messages']} state and event messages to the subscriber "
                  f"({r['zenoh_messages'] / r['duration_s']:.0f}/s, warm-up included)")
        if r["scenario"] == "loaded":
            print(
                f"    goals: accepted in p50 {r['accept_ms_p50']:.0f} ms, max "
                f"{r['accept_ms_max']:.0f} ms; rejected {r['goals_rejected']}, failed "
                f"{r['goals_failed']}; results {r['goal_results']}; state "
                f"{r['state_per_subscriber_hz']:g} Hz per subscriber, dropped "
                f"{r['state_dropped_by_daemon']} (daemon) {r['state_dropped_locally']} (client)"
            )
            for problem in r["goal_problems"]:
                print(f"    {problem}")
            if r["goal_abort_reasons"]:
                print(
                    f"    {len(r['goal_abort_reasons'])} distinct abort reasons, e.g. "
                    f"{r['goal_abort_reasons'][0][:110]}"
                )
    for r in rows:
        if "phases_us" in r:
            print_phases(r)
    print(verdict(rows))


def print_phases(row: dict[str, Any]) -> None:
    """The phase table of one run (``--breakdown``)."""
    phases = row["phases_us"]
    print(
        f"{row['rate_hz']:g} Hz {row['scenario']}, {row['joints']} joints: the loop's period "
        f"phase by phase, us per cycle over {phases['period']['runs']} cycles (0 where a "
        "phase did not run; ran: cycles where it did)"
    )
    print(f"  {'phase':<16}  {'p50':>7}  {'p99':>7}  {'max':>8}  {'mean':>7}  {'ran':>6}")
    names = [*COLUMNS[1:], "cycle: rest", "period: rest", "period"]
    for name in names:
        p = phases[name]
        indent = "  " if PARENT.get(name) == "cycle" or name == "cycle: rest" else ""
        print(
            f"  {indent + name:<16}  {p['p50']:>7.1f}  {p['p99']:>7.1f}  {p['max']:>8.1f}  "
            f"{p['mean']:>7.1f}  {p['runs']:>6d}"
        )
    update, period = phases["update"]["p50"], phases["period"]
    print(
        f"  period's work p50 {period['p50']:.1f} us = {period['p50'] / update:.2f} x update() "
        f"p50 ({update:.1f} us); p99 {period['p99']:.1f} us"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--duration",
        type=float,
        default=30.0,
        metavar="S",
        help="seconds measured per run (default 30)",
    )
    parser.add_argument("--rates", type=float, nargs="+", default=[500.0, 1000.0])
    parser.add_argument(
        "--scenarios",
        nargs="+",
        choices=["bare", "idle", "loaded"],
        default=["idle", "loaded"],
        help="default: idle loaded; bare adds the loop's clock alone (this machine's floor)",
    )
    parser.add_argument(
        "--priority",
        type=int,
        default=0,
        help="daemon.realtime.priority: SCHED_FIFO 1..99, 0 normal (default)",
    )
    parser.add_argument(
        "--cpu",
        type=int,
        default=None,
        help="daemon.realtime.cpu_affinity: pin the loop to this CPU",
    )
    parser.add_argument(
        "--lock-memory",
        action="store_true",
        help="daemon.realtime.lock_memory: mlockall the loop process",
    )
    parser.add_argument(
        "--live-view",
        action="store_true",
        help="daemon.foxglove on, with a viewer subscribed to every channel (needs "
        "jtc_hw[foxglove] and websockets)",
    )
    parser.add_argument(
        "--ros2",
        action="store_true",
        help="daemon.ros2 on (a client of this process's router on loopback), with a ROS 2 "
        "subscriber to /joint_states and controller_state (needs jtc_hw[ros2])",
    )
    parser.add_argument(
        "--zenoh",
        action="store_true",
        help="daemon.zenoh on (loopback), with a Zenoh subscriber to its state and events "
        "(needs jtc_hw[zenoh])",
    )
    parser.add_argument(
        "--flight-recorder-s",
        type=float,
        default=10.0,
        metavar="S",
        help="daemon.flight_recorder_s (default 10, the daemon's default; 0: off)",
    )
    parser.add_argument(
        "--record",
        action="store_true",
        help="daemon.record on (every run recorded from its start, into a temporary "
        "directory removed afterwards; needs jtc_hw[record])",
    )
    parser.add_argument(
        "--breakdown",
        action="store_true",
        help="time each phase of the loop's period and print their p50/p99 per run",
    )
    parser.add_argument(
        "--joints",
        type=int,
        default=6,
        metavar="N",
        help="mirror joints of the daemon's arm (default 6)",
    )
    parser.add_argument(
        "--goal-points",
        type=int,
        default=GOAL_POINTS,
        metavar="N",
        help=f"points of each goal of the loaded scenario (default {GOAL_POINTS}; 20000: a "
        "large goal every second)",
    )
    parser.add_argument("--json", action="store_true", help="one JSON object per run")
    args = parser.parse_args(argv)
    if args.duration <= 0:
        parser.error("--duration must be positive")
    if args.joints < 1:
        parser.error("--joints must be at least 1")
    if args.goal_points < 2:
        parser.error("--goal-points must be at least 2")

    def note(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    rows: list[dict[str, Any]] = []
    schedulings: dict[float, str] = {}
    for rate in args.rates:
        schedulings[rate], found = measure_rate(rate, args, note)
        rows.extend(found)
    if args.json:
        for row in rows:
            print(json.dumps(row))
    else:
        print_table(rows, args, schedulings)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
