#!/usr/bin/env python3
"""Goal acceptance latency of the real daemon, and what a huge goal costs its control loop.

Three measurements (the first by default, or when ``--sizes`` is given with the others):

``sizes``
    Starts ``python -m jtc_hw run`` on six simulated (mirror) joints (``cli.demo.demo_config``
    at ``--rate``, socket in a temporary directory) and sends goals of 2, 200, 2,000 and 20,000
    points (``--points``) with the real ``Client``: a smooth wave on all six joints, positions
    and velocities at full float precision, points 1 ms apart, small enough (0.02 rad) that a
    goal preempting the previous one never violates the path tolerance. Each goal is sent once
    the previous one was accepted plus a short pause; ``--runs`` goals per size (after one
    warm-up goal). ``accept`` is request sent (the client's ``sendall`` of the encoded request
    starts) -> ``accepted`` reply returned to the caller: parsing, validation, fitting,
    shipping the plan to the loop process and its commit. ``call`` is the whole ``send_goal``
    call, with the client encoding the request. ``overruns`` are the deadlines the loop
    skipped while the size was measured (its statistics, ``get_status()["loop"]``). Each
    size has a row per ``--encodings``: ``binary`` (the client's default: goals of 100 points
    or more as binary frames, protocol version 2) and ``ndjson`` (JSON lines only), their
    goals alternated one by one. ``--transport socket ros2`` adds a ``ros2`` row per size: the
    same goal as a ``control_msgs/action/FollowJointTrajectory`` goal through the daemon's
    ROS 2 transport (``daemon.ros2``, issue 25), alternated with the socket's; the bench runs a
    Zenoh router on a free loopback port and a Zenoh client speaking rmw_zenoh's wire
    (``jtc_hw.daemon.transports.ros2``'s keys and attachment). ``accept`` is then the
    ``send_goal`` query sent (its CDR encoded beforehand) -> the ``accepted`` response received;
    ``call`` adds the CDR encoding (rosbags' serializer: a client's cost, not the daemon's).

``huge`` (``--huge``)
    One goal of ``--huge-points`` (default 75,000) points on a fresh daemon at ``--rate``:
    six joints, positions only, rounded to 3 decimals so that the request stays close to the
    4 MiB message limit (``daemon.max_message_bytes`` is raised to fit it when it does not,
    and the row says so). Reports the acceptance time, the deadlines the loop skipped from
    sending the goal until its plan was released again (the goal is cancelled once accepted
    plus 1 s), and the loop process's resident memory before, while executing and after the
    goal ended. Meanwhile another client asks all the time: ``get_status`` (served by the API
    process's event loop) and ``cancel`` of an unknown goal (a request to the control loop
    and back); ``probe_*_ms_max`` is the longest either waited while the goal was accepted.

``breakdown`` (``--breakdown``)
    In this process, no daemon: the same code the daemon runs, stage by stage, for one goal of
    each ``--points`` size (best of several repetitions): client encoding, line framing and
    JSON decoding, request parsing, validation (``prepare``), fitting and splicing (``splice``),
    pickling the plan for the loop; and the loop side: the plan read through the loop's own
    inbox (``jtc_hw.daemon.channel.pipe.Inbox``, with the budget of one cycle at ``--rate``) from a
    pipe that another thread fills with ``send_framed``, its slowest ``pump`` (one cycle's
    share) and how many cycles it takes, and releasing the plan. ``--cprofile`` adds the top
    functions of the API-process stages under ``cProfile``. ``--limits`` gives every joint
    position, velocity, acceleration and jerk limits that the goal fits, so ``plan_goal``
    includes the check against them (issue 12), and adds the check alone (``limits_check``).

Usage:  python bench/goal_latency.py [--points 2 200 2000 20000] [--runs N] [--rate HZ]
            [--priority N] [--encodings binary ndjson] [--sizes] [--huge] [--huge-points N]
            [--huge-encoding ndjson|binary] [--breakdown] [--cprofile] [--limits] [--json]
            [--transport socket ros2]
``--json`` prints one JSON object per line instead of the tables; a ``sizes`` row holds
``{"points", "encoding", "accept_ms_p50", "accept_ms_p99", ...}``.
Targets (issue 24): 2,000 points accepted in <= 5 ms and 20,000 in <= 30 ms (medians); a
75,000-point goal costs the loop at most 5 missed deadlines at 500 Hz.
The daemons' flight recorders write into a temporary directory removed afterwards: a bench run
leaves nothing in the user's state directory.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import dataclasses
import io
import json
import math
import multiprocessing
import pickle
import pstats
import random
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from loop_jitter import Daemon, next_loop_stats  # noqa: E402

from jtc_hw.api.client import Client  # noqa: E402
from jtc_hw.api.events import BINARY_MIN_POINTS, trajectory_columns  # noqa: E402
from jtc_hw.api.framing import (  # noqa: E402
    DEFAULT_MAX_MESSAGE_BYTES,
    MessageDecoder,
    RequestError,
    encode,
    encode_frame,
)
from jtc_hw.api.protocol import parse_request  # noqa: E402
from jtc_hw.api.requests import SendGoal  # noqa: E402
from jtc_hw.cli.demo import DEMO_JOINTS  # noqa: E402
from jtc_hw.config.limits import JointLimits  # noqa: E402
from jtc_hw.controller.limits_check import check  # noqa: E402
from jtc_hw.controller.planner import Planner  # noqa: E402
from jtc_hw.controller.trajectory import Trajectory  # noqa: E402
from jtc_hw.controller.validation import prepare  # noqa: E402
from jtc_hw.daemon.channel.messages import Commit  # noqa: E402
from jtc_hw.daemon.robot import load_robot  # noqa: E402

SIZES = (2, 200, 2000, 20000)
SPACING_S = 0.001
AMPLITUDE = 0.02  # rad: a preempting goal's bridge stays well inside the path tolerance (0.1)
PHASES = (0.0, 0.5)  # successive goals alternate between these (not the same goal twice)
PAUSE_S = 0.05  # between an accepted goal and the next send, plus up to a period (dephase)
SEED = 24
HUGE_POINTS = 75000
HUGE_EXECUTE_S = 1.0  # the huge goal runs this long before it is cancelled
SETTLE_S = 1.5  # after a goal ended: the loop releases retired plans in spare cycles
TIMEOUT_S = 60.0
TARGETS = {2000: 5.0, 20000: 30.0}
"""Issue 24: median request -> accepted, ms, by goal size."""
TARGET_OVERRUNS = 5


# -- goals ------------------------------------------------------------------------------------


def wave_goal(points: int, phase: float = 0.0) -> dict[str, Any]:
    """``points`` points 1 ms apart of q_j = A sin(w_j t + phase), with velocities, 6 joints."""
    t = np.arange(1, points + 1) * SPACING_S
    joints = np.arange(len(DEMO_JOINTS))
    omega = 2 * math.pi * 0.5 * (1.0 + 0.1 * joints)
    angle = omega * t[:, None] + phase
    positions = AMPLITUDE * np.sin(angle)
    velocities = AMPLITUDE * omega * np.cos(angle)
    return {
        "joint_names": list(DEMO_JOINTS),
        "points": [
            {"time_from_start": s, "positions": p, "velocities": v}
            for s, p, v in zip(t.tolist(), positions.tolist(), velocities.tolist(), strict=True)
        ],
    }


def compact_goal(points: int) -> dict[str, Any]:
    """``points`` points 1 ms apart, positions only, rounded to 3 decimals (a short request)."""
    t = np.round(np.arange(1, points + 1) * SPACING_S, 3)
    joints = np.arange(len(DEMO_JOINTS))
    omega = 2 * math.pi * 0.5 * (1.0 + 0.1 * joints)
    positions = np.round(AMPLITUDE * 5 * np.sin(omega * t[:, None]), 3)
    return {
        "joint_names": list(DEMO_JOINTS),
        "points": [
            {"time_from_start": s, "positions": p}
            for s, p in zip(t.tolist(), positions.tolist(), strict=True)
        ],
    }


def message_limit(size: int) -> int:
    """The daemon's message limit for requests of up to ``size`` bytes: the default (4 MiB)
    when they fit, else just enough."""
    return DEFAULT_MAX_MESSAGE_BYTES if size <= DEFAULT_MAX_MESSAGE_BYTES else size + (1 << 16)


def request_bytes(goal: dict[str, Any], encoding: str = "ndjson") -> int:
    """Size of the ``send_goal`` request the client sends for ``goal``: one NDJSON line, or a
    binary frame (its line, the raw bytes and the newline; docs/protocol.md)."""
    if encoding == "binary":
        parts = trajectory_columns(goal, min_points=1)
        assert parts is not None
        head, values, columns = parts
        return len(encode_frame({"id": 1, "op": "send_goal", "trajectory": head}, values,
                                columns))
    return len(encode({"id": 1, "op": "send_goal", "trajectory": goal}))


# -- the client -------------------------------------------------------------------------------


class _StampedSocket:
    """The client's socket, remembering when the last ``sendall`` began (everything else is
    passed through): the request is then encoded and leaves the client."""

    def __init__(self, sock: Any) -> None:
        self._sock = sock
        self.sent_ns = 0

    def sendall(self, data: bytes) -> None:
        self.sent_ns = time.perf_counter_ns()
        self._sock.sendall(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)


def stamped_client(socket_path: str) -> tuple[Client, _StampedSocket]:
    """The real client, its socket wrapped to stamp the moment a request is sent."""
    client = Client.connect(socket_path, timeout_s=TIMEOUT_S)
    stamped = _StampedSocket(client._sock)  # the client's private socket: a bench looks inside
    client._sock = stamped  # type: ignore[assignment]
    return client, stamped


def timed_goal(client: Client, stamped: _StampedSocket, goal: dict[str, Any]) -> tuple[
    float, float, Any
]:
    """Send ``goal``; (accept ms: sent -> accepted, call ms: the whole call, the handle)."""
    begin = time.perf_counter_ns()
    handle = client.send_goal(goal, timeout_s=TIMEOUT_S)
    end = time.perf_counter_ns()
    return (end - stamped.sent_ns) / 1e6, (end - begin) / 1e6, handle


def percentile(values: list[float], p: float) -> float:
    """Nearest-rank percentile."""
    ordered = sorted(values)
    return ordered[max(0, math.ceil(p / 100 * len(ordered)) - 1)]


# -- sizes ------------------------------------------------------------------------------------


def runs_for(points: int, runs: int | None) -> int:
    if runs is not None:
        return runs
    return 100 if points <= 200 else 40 if points <= 2000 else 10


@contextlib.contextmanager
def bench_daemon(args: argparse.Namespace, limit: int,
                 ros2_endpoint: str | None = None) -> Iterator[Daemon]:
    """The daemon, its flight recorder writing into a temporary directory removed afterwards
    (its shutdown recording would otherwise land in the user's state directory); with
    ``ros2_endpoint``, also on ROS 2 as a client of that router."""
    settings: dict[str, Any] = {"max_message_bytes": limit}
    if ros2_endpoint is not None:
        settings["ros2"] = {"zenoh": {"connect": [ros2_endpoint]}}
        if args.ros2_mode == "peer":  # rmw_zenoh's own session default: peers, p2p on loopback
            settings["ros2"]["zenoh"].update(mode="peer", listen=["tcp/127.0.0.1:0"])
    with tempfile.TemporaryDirectory(prefix="jtc-hw-latency-flight-") as flight, Daemon(
        args.rate, args.priority, None, False,
        daemon_settings={**settings, "flight_recorder_dir": flight},
    ) as daemon:
        yield daemon


# -- ROS 2 ------------------------------------------------------------------------------------


def free_endpoint() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


class Ros2Goals:
    """A Zenoh router on a free loopback port, and a client sending FollowJointTrajectory goals
    to the daemon's ROS 2 transport as an rmw_zenoh action client does (module docstring)."""

    CONTROLLER = "joint_trajectory_controller"

    def __init__(self, mode: str = "client") -> None:
        import zenoh

        from jtc_hw.daemon.transports.ros2 import wire
        from jtc_hw.daemon.transports.ros2.types import ros_types

        self._wire = wire
        self.endpoint = free_endpoint()
        quiet = {"scouting/multicast/enabled": "false", "scouting/gossip/enabled": "false"}
        router = zenoh.Config()
        router.insert_json5("mode", '"router"')
        router.insert_json5("listen/endpoints", json.dumps([self.endpoint]))
        client = zenoh.Config()
        client.insert_json5("mode", json.dumps(mode))
        client.insert_json5("connect/endpoints", json.dumps([self.endpoint]))
        for config in (router, client):
            for key, value in quiet.items():
                config.insert_json5(key, value)
        if mode == "peer":  # as rmw_zenoh's sessions: the router's gossip tells where to dial
            client.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
            for config in (router, client):
                config.insert_json5("scouting/gossip/enabled", "true")
        self.router = zenoh.open(router)
        self.session = zenoh.open(client)
        self.types = ros_types("jazzy")
        store = self.types.typestore
        action = "control_msgs/action/FollowJointTrajectory"
        self._request = f"{action}_SendGoal_Request"
        self._response = f"{action}_SendGoal_Response"
        name = f"/{self.CONTROLLER}/follow_joint_trajectory/_action/send_goal"
        service = f"{action}_SendGoal"
        self.key = wire.topic_key(0, name, self.types.dds_name(service),
                                self.types.type_hash(service))
        self.gid = wire.new_gid()
        self.seq = 0
        self.store = store

    def encode(self, goal: dict[str, Any]) -> bytearray:
        """The ``SendGoal`` request of ``goal`` (its UUID filled in by :meth:`send`)."""
        t = self.store.types
        dur = t["builtin_interfaces/msg/Duration"]
        header = t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](0, 0), "")
        empty = np.zeros(0)
        points = [t["trajectory_msgs/msg/JointTrajectoryPoint"](
            positions=np.asarray(p["positions"], np.float64),
            velocities=np.asarray(p.get("velocities", ()), np.float64), accelerations=empty,
            effort=empty, time_from_start=dur(int(p["time_from_start"]),
                                              round(p["time_from_start"] % 1 * 1e9)))
            for p in goal["points"]]
        from jtc_hw.daemon.transports.ros2.messages import make

        msg = make(self.store, self._request, goal={
            "trajectory": t["trajectory_msgs/msg/JointTrajectory"](
                header, list(goal["joint_names"]), points)})
        return bytearray(self.store.serialize_cdr(msg, self._request))

    def send(self, request: bytearray) -> float:
        """Send a goal under a fresh UUID; ms from the query sent to the response received.

        Raises:
            RuntimeError: no response, or the goal was rejected.
        """
        import os

        request[4:20] = os.urandom(16)  # goal_id, the request's first field
        self.seq += 1
        attachment = self._wire.encode_attachment(self.seq, time.time_ns(), self.gid)
        first: list[tuple[int, Any]] = []
        done = threading.Event()

        def on_reply(reply: Any) -> None:
            if not first:  # the response's arrival, not the query's end
                first.append((time.perf_counter_ns(), reply.ok))

        import zenoh

        begin = time.perf_counter_ns()
        self.session.get(self.key, zenoh.handlers.Callback(on_reply, done.set),
                         payload=bytes(request), attachment=attachment, timeout=TIMEOUT_S)
        if not done.wait(TIMEOUT_S) or not first or first[0][1] is None:
            raise RuntimeError("no send_goal response")
        end, sample = first[0]
        response = self.store.deserialize_cdr(bytes(sample.payload.to_bytes()), self._response)
        if not response.accepted:
            raise RuntimeError("goal rejected")
        return (end - begin) / 1e6

    def wait_served(self) -> None:
        """Until the daemon's action server answers (its queryable reached the router)."""
        request = self.encode(wave_goal(2))
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            try:
                self.send(request)
                return
            except RuntimeError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)

    def close(self) -> None:
        self.session.close()
        self.router.close()


def measure_sizes(args: argparse.Namespace, note: Callable[[str], None]) -> list[dict[str, Any]]:
    """Per size, one row per encoding; the encodings' goals alternate, so both see the same
    machine."""
    rows = []
    limit = message_limit(
        max(request_bytes(wave_goal(p, phase)) for p in args.points for phase in PHASES)
    )
    if limit != DEFAULT_MAX_MESSAGE_BYTES:
        note(f"daemon.max_message_bytes raised to {limit} for the largest request")
    encodings = list(args.encodings)
    ros2 = Ros2Goals(args.ros2_mode) if "ros2" in args.transport else None
    if ros2 is not None:
        encodings.append("ros2")
    with contextlib.ExitStack() as stack:
        if ros2 is not None:
            stack.callback(ros2.close)
        daemon = stack.enter_context(bench_daemon(
            args, limit, None if ros2 is None else ros2.endpoint))
        daemon.connect().close()
        if ros2 is not None:
            ros2.wait_served()
        client, stamped = stamped_client(daemon.socket)
        try:
            for points in args.points:
                goals = [wave_goal(points, phase) for phase in PHASES]
                cdr = [] if ros2 is None else [ros2.encode(g) for g in goals]
                sizes = {e: len(cdr[0]) if e == "ros2" else request_bytes(goals[0], e)
                         for e in encodings}
                runs = runs_for(points, args.runs)
                note(f"{points} points: {runs} goals per encoding ("
                     + ", ".join(f"{e} {sizes[e]} bytes" for e in encodings)
                     + ")")
                for encoding in encodings:  # warm-up: each path once
                    if encoding == "ros2":
                        assert ros2 is not None
                        ros2.send(cdr[1])
                        continue
                    use_encoding(client, encoding)
                    timed_goal(client, stamped, goals[1])
                before = next_loop_stats(client)
                accept: dict[str, list[float]] = {e: [] for e in encodings}
                call: dict[str, list[float]] = {e: [] for e in encodings}
                rejected = dict.fromkeys(encodings, 0)
                dephase = random.Random(SEED)
                for i in range(runs * len(encodings)):
                    encoding = encodings[i % len(encodings)]
                    # The reply comes right after a loop cycle: a fixed pause would send every
                    # goal at one phase of the loop's period, and the median would measure the
                    # wait for the next cycle from that phase only. Goals arrive at any phase.
                    time.sleep(PAUSE_S + dephase.uniform(0.0, 1.0 / args.rate))
                    which = (i // len(encodings)) % 2
                    try:
                        if encoding == "ros2":
                            assert ros2 is not None
                            begin = time.perf_counter_ns()
                            request = ros2.encode(goals[which])
                            a = ros2.send(request)
                            c = (time.perf_counter_ns() - begin) / 1e6
                        else:
                            use_encoding(client, encoding)
                            a, c, _ = timed_goal(client, stamped, goals[which])
                    except Exception as exc:  # report it, keep measuring
                        note(f"  goal {i} ({encoding}): {type(exc).__name__}: {exc}")
                        rejected[encoding] += 1
                        continue
                    accept[encoding].append(a)
                    call[encoding].append(c)
                time.sleep(SETTLE_S)
                after = next_loop_stats(client)
                for encoding in encodings:
                    done = accept[encoding]
                    rows.append(
                        {
                            "kind": "sizes",
                            "points": points,
                            "encoding": encoding,
                            "rate_hz": args.rate,
                            "runs": len(done),
                            "failed": rejected[encoding],
                            "request_bytes": sizes[encoding],
                            "max_message_bytes": limit,
                            "accept_ms_p50": round(percentile(done, 50), 2) if done else None,
                            "accept_ms_p99": round(percentile(done, 99), 2) if done else None,
                            "accept_ms_max": round(max(done), 2) if done else None,
                            "call_ms_p50": (round(percentile(call[encoding], 50), 2)
                                            if done else None),
                            "overruns": after["overruns"] - before["overruns"],
                            "loop_cost_us_worst": after["cost_us"]["worst"],
                        }
                    )
        finally:
            client.close()
    return rows


def use_encoding(client: Client, encoding: str) -> None:
    """``binary``: the client's default (frames from 100 points on, the daemon speaking
    version 2); ``ndjson``: always JSON lines."""
    client.binary_min_points = BINARY_MIN_POINTS if encoding == "binary" else None


# -- huge -------------------------------------------------------------------------------------


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for process {pid}")


class Probe(threading.Thread):
    """Another client, asking all the time while a goal is being accepted: ``get_status``
    (answered by the API process's event loop alone) and ``cancel`` of a goal that does not
    exist (a request that travels to the control loop and back). Records how long each took."""

    def __init__(self, socket_path: str) -> None:
        super().__init__(daemon=True)
        self.client = Client.connect(socket_path, timeout_s=TIMEOUT_S)
        self.stop = threading.Event()
        self.status_ms: list[float] = []
        self.loop_ms: list[float] = []

    def run(self) -> None:
        while not self.stop.is_set():
            t0 = time.perf_counter_ns()
            self.client.get_status()
            t1 = time.perf_counter_ns()
            try:
                self.client.cancel(2**62)
            except RequestError:  # not_found: it went to the loop and back
                pass
            t2 = time.perf_counter_ns()
            self.status_ms.append((t1 - t0) / 1e6)
            self.loop_ms.append((t2 - t1) / 1e6)
            time.sleep(0.002)

    def finish(self) -> dict[str, Any]:
        self.stop.set()
        self.join(TIMEOUT_S)
        self.client.close()
        return {
            "probes": len(self.status_ms),
            "probe_status_ms_max": round(max(self.status_ms, default=0.0), 1),
            "probe_loop_ms_max": round(max(self.loop_ms, default=0.0), 1),
            "probe_loop_ms_p50": round(percentile(self.loop_ms, 50), 1) if self.loop_ms else None,
        }


def measure_huge(args: argparse.Namespace, note: Callable[[str], None]) -> dict[str, Any]:
    goal = compact_goal(args.huge_points)
    size = request_bytes(goal)
    limit = message_limit(size)
    note(f"huge: {args.huge_points} points, {size} bytes (message limit {limit})")
    with bench_daemon(args, limit) as daemon:
        daemon.connect().close()
        client, stamped = stamped_client(daemon.socket)
        use_encoding(client, args.huge_encoding)
        try:
            timed_goal(client, stamped, wave_goal(200))  # warm-up: every code path once
            time.sleep(SETTLE_S)
            before = next_loop_stats(client)
            rss_before = rss_kib(daemon.loop_pid)
            api_rss_before = rss_kib(daemon.pid)
            probe = Probe(daemon.socket)
            probe.start()
            accept, call, handle = timed_goal(client, stamped, goal)
            probed = probe.finish()
            time.sleep(HUGE_EXECUTE_S)
            during = next_loop_stats(client)
            rss_during = rss_kib(daemon.loop_pid)
            handle.cancel(timeout_s=TIMEOUT_S)
            result = handle.wait(TIMEOUT_S)
            time.sleep(SETTLE_S)
            after = next_loop_stats(client)
            rss_after = rss_kib(daemon.loop_pid)
            api_rss_after = rss_kib(daemon.pid)
        finally:
            client.close()
    return {
        "kind": "huge",
        "points": args.huge_points,
        "rate_hz": args.rate,
        "request_bytes": size,
        "max_message_bytes": limit,
        "accept_ms": round(accept, 1),
        "call_ms": round(call, 1),
        "overruns_until_executing": during["overruns"] - before["overruns"],
        "overruns": after["overruns"] - before["overruns"],
        "loop_cost_us_worst": after["cost_us"]["worst"],
        "loop_rss_mb_before": round(rss_before / 1024, 1),
        "loop_rss_mb_during": round(rss_during / 1024, 1),
        "loop_rss_mb_after": round(rss_after / 1024, 1),
        "api_rss_mb_before": round(api_rss_before / 1024, 1),
        "api_rss_mb_after": round(api_rss_after / 1024, 1),
        "result": result.get("status"),
        **probed,
    }


# -- breakdown --------------------------------------------------------------------------------


def best_ms(fn: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    """Best wall time of ``repeat`` calls, and the last call's value."""
    best = math.inf
    value = None
    for _ in range(repeat):
        t0 = time.perf_counter_ns()
        value = fn()
        best = min(best, (time.perf_counter_ns() - t0) / 1e6)
    return best, value


def loop_side(plan_message: Commit, rate_hz: float) -> dict[str, float]:
    """The plan read through the loop's inbox, once a period, from a pipe that another thread
    fills with ``send_framed`` (as the API process does).

    Returns the slowest ``pump`` (one cycle's read, ms), how many cycles the plan took to
    arrive, and the time to release the plan once received.
    """
    from jtc_hw.daemon.channel.pipe import Inbox, send_framed
    from jtc_hw.daemon.core.supervision import _grow_send_buffer
    from jtc_hw.daemon.loop.cycle import INBOX_SPARE, inbox_budget

    period_ns = round(1e9 / rate_hz)
    parent, child = multiprocessing.Pipe(duplex=True)
    _grow_send_buffer(parent)  # as the API process does
    inbox = Inbox(child, inbox_budget(period_ns))
    sender = threading.Thread(target=send_framed, args=(parent, plan_message), daemon=True)
    worst, cycles = 0.0, 0
    deadline = time.monotonic_ns()
    sender.start()
    try:
        while not inbox.waiting:
            deadline += period_ns
            time.sleep(max(0.0, (deadline - time.monotonic_ns()) / 1e9))
            t0 = time.perf_counter_ns()
            inbox.pump(deadline + round((1 - INBOX_SPARE) * period_ns))
            worst = max(worst, (time.perf_counter_ns() - t0) / 1e6)
            cycles += 1
        received = inbox.pop()
        sender.join()
        t0 = time.perf_counter_ns()
        del received
        release = (time.perf_counter_ns() - t0) / 1e6
    finally:
        inbox.close()
        parent.close()
        child.close()
    return {"pump_ms_max": worst, "cycles": cycles, "release_ms": release}


def breakdown(points: int, args: argparse.Namespace) -> dict[str, Any]:
    from jtc_hw.cli.demo import demo_config

    config = load_robot(demo_config("/nonexistent/bench.sock")).controller
    if args.limits:  # generous: the goal fits, and every limit is checked on every segment
        bounds = JointLimits((-10.0, 10.0), 10.0, 1e4, 1e9)
        config = dataclasses.replace(config, limits={j: bounds for j in config.joints})
    planner = Planner(config)
    goal = wave_goal(points)
    message = {"id": 1, "op": "send_goal", "trajectory": goal}
    repeat = 7 if points <= 2000 else 3
    now = 10**12
    reference = Trajectory.constant(now, np.zeros(len(DEMO_JOINTS)))
    stages: dict[str, float] = {}
    stages["client_encode_ms"], line = best_ms(lambda: encode(message), repeat)
    limit = max(DEFAULT_MAX_MESSAGE_BYTES, len(line))  # as the bench's daemon is configured
    stages["decode_ms"], decoded = best_ms(lambda: MessageDecoder(limit).feed(line)[0], repeat)
    stages["parse_ms"], request = best_ms(lambda: parse_request(decoded), repeat)
    assert isinstance(request, SendGoal)
    trajectory = request.trajectory.to_joint_trajectory(now)
    stages["prepare_ms"], prepared = best_ms(lambda: prepare(config, trajectory), repeat)
    stages["splice_ms"], _ = best_ms(
        lambda: reference.splice(now, prepared, config.interpolation_method, planner.wraparound),
        repeat,
    )
    stages["plan_goal_ms"], plan = best_ms(
        lambda: planner.plan_goal(reference, 1, now, trajectory), repeat
    )
    if planner.limits is not None:
        table, columns = planner.limits, np.arange(len(config.joints))
        starts = np.zeros(len(config.joints))
        stages["limits_check_ms"], found = best_ms(
            lambda: check(plan.reference, now, table, columns, starts), repeat
        )
        assert not found, found
    buffers: list[pickle.PickleBuffer] = []

    def dump() -> bytes:
        buffers.clear()
        return pickle.dumps(Commit(1, plan), protocol=5, buffer_callback=buffers.append)

    stages["pickle_ms"], head = best_ms(dump, repeat)
    plan_bytes = len(head) + sum(b.raw().nbytes for b in buffers)
    raw = [b.raw() for b in buffers]
    stages["unpickle_ms"], _ = best_ms(lambda: pickle.loads(head, buffers=raw), repeat)
    loop = loop_side(Commit(1, plan), args.rate)
    row: dict[str, Any] = {
        "kind": "breakdown",
        "points": points,
        "request_bytes": len(line),
        "plan_bytes": plan_bytes,
        "plan_inband_bytes": len(head),
        **{k: round(v, 3) for k, v in stages.items()},
        "api_total_ms": round(
            stages["decode_ms"] + stages["parse_ms"] + stages["plan_goal_ms"]
            + stages["pickle_ms"],
            3,
        ),
        "loop_pump_ms_max": round(loop["pump_ms_max"], 3),
        "loop_cycles_to_receive": loop["cycles"],
        "loop_release_ms": round(loop["release_ms"], 3),
    }
    if args.cprofile:
        profile = cProfile.Profile()
        profile.enable()
        for _ in range(repeat):
            item = MessageDecoder(limit).feed(line)[0]
            req = parse_request(item)
            assert isinstance(req, SendGoal)
            planner.plan_goal(reference, 1, now, req.trajectory.to_joint_trajectory(now))
        profile.disable()
        out = io.StringIO()
        pstats.Stats(profile, stream=out).sort_stats("tottime").print_stats(14)
        row["cprofile"] = out.getvalue()
    return row


# -- output -----------------------------------------------------------------------------------


def print_tables(rows: list[dict[str, Any]]) -> None:
    sizes = [r for r in rows if r["kind"] == "sizes"]
    if sizes:
        print(
            f"goal acceptance, daemon on {len(DEMO_JOINTS)} mirror joints at "
            f"{sizes[0]['rate_hz']:g} Hz; accept = request sent -> accepted reply, call = "
            "the whole send_goal (client encoding too)"
        )
        print(
            f"{'points':>7}  {'encoding':>8}  {'bytes':>9}  {'runs':>4}  {'accept p50':>10}  "
            f"{'p99':>8}  {'max':>8}  {'call p50':>8}  {'overruns':>8}"
        )
        for r in sizes:
            print(
                f"{r['points']:>7}  {r['encoding']:>8}  {r['request_bytes']:>9}  {r['runs']:>4}  "
                f"{r['accept_ms_p50']:>8.2f}ms  {r['accept_ms_p99']:>6.2f}ms  "
                f"{r['accept_ms_max']:>6.2f}ms  {r['call_ms_p50']:>6.2f}ms  {r['overruns']:>8}"
                + (f"  ({r['failed']} failed)" if r["failed"] else "")
            )
        for points, target_ms in TARGETS.items():
            for r in sizes:
                if r["points"] == points and r["accept_ms_p50"] is not None:
                    ok = r["accept_ms_p50"] <= target_ms
                    print(f"target ({points} points accepted in <= {target_ms:g} ms median, "
                          f"{r['encoding']}): {'MET' if ok else 'MISSED'}")
    for r in rows:
        if r["kind"] == "huge":
            print(
                f"huge goal: {r['points']} points ({r['request_bytes']} bytes, message limit "
                f"{r['max_message_bytes']}) at {r['rate_hz']:g} Hz: accepted in "
                f"{r['accept_ms']:.0f} ms (call {r['call_ms']:.0f} ms); loop overruns "
                f"{r['overruns']} ({r['overruns_until_executing']} by 1 s into it), worst "
                f"cycle {r['loop_cost_us_worst']:.0f} us; loop RSS {r['loop_rss_mb_before']} -> "
                f"{r['loop_rss_mb_during']} -> {r['loop_rss_mb_after']} MB (before, running, "
                f"after); API RSS {r['api_rss_mb_before']} -> {r['api_rss_mb_after']} MB; "
                f"result {r['result']}; meanwhile another client's get_status waited at most "
                f"{r['probe_status_ms_max']} ms, a request to the loop {r['probe_loop_ms_max']} "
                f"ms ({r['probes']} of each)"
            )
            ok = r["overruns"] <= TARGET_OVERRUNS and r["rate_hz"] == 500
            print(
                f"target (<= {TARGET_OVERRUNS} missed deadlines at 500 Hz): "
                f"{'MET' if ok else 'MISSED' if r['rate_hz'] == 500 else 'not checked'}"
            )
    parts = [r for r in rows if r["kind"] == "breakdown"]
    if parts:
        print("breakdown, in process (best of several), ms:")
        keys = [
            "client_encode_ms", "decode_ms", "parse_ms", "prepare_ms", "splice_ms",
            "plan_goal_ms", "limits_check_ms", "pickle_ms", "unpickle_ms", "api_total_ms",
            "loop_pump_ms_max",
            "loop_cycles_to_receive", "loop_release_ms", "request_bytes", "plan_bytes",
            "plan_inband_bytes",
        ]
        print(f"{'stage':<24}" + "".join(f"{r['points']:>12}" for r in parts))
        for key in keys:
            if any(key in r for r in parts):
                print(f"{key:<24}" + "".join(f"{r.get(key, '-'):>12}" for r in parts))
        for r in parts:
            if "cprofile" in r:
                print(f"cProfile, {r['points']} points, API-process stages:\n{r['cprofile']}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, nargs="+", default=list(SIZES))
    parser.add_argument("--runs", type=int, default=None, help="goals per size (default 10-100)")
    parser.add_argument("--rate", type=float, default=500.0, help="update_rate, Hz (500)")
    parser.add_argument("--priority", type=int, default=0, help="daemon.realtime.priority")
    parser.add_argument(
        "--encodings", nargs="+", choices=("binary", "ndjson"), default=["binary", "ndjson"],
        help="how the client sends goals of 100+ points: binary frames (protocol version 2) "
        "or NDJSON; each size gets a row per encoding, their goals alternated")
    parser.add_argument("--huge-encoding", choices=("binary", "ndjson"), default="ndjson")
    parser.add_argument("--huge", action="store_true", help="measure one huge goal")
    parser.add_argument("--huge-points", type=int, default=HUGE_POINTS)
    parser.add_argument("--breakdown", action="store_true", help="stages, in process")
    parser.add_argument("--cprofile", action="store_true", help="with --breakdown")
    parser.add_argument(
        "--limits", action="store_true", help="with --breakdown: every joint has position, "
        "velocity, acceleration and jerk limits (the goal fits them; plan_goal checks it)"
    )
    parser.add_argument(
        "--sizes", action="store_true", help="measure the sizes too (the default without "
        "--huge or --breakdown)"
    )
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    parser.add_argument(
        "--transport", nargs="+", choices=("socket", "ros2"), default=["socket"],
        help="ros2: also a row per size through the daemon's ROS 2 transport (needs "
        "jtc_hw[ros2]; the bench runs its own Zenoh router)")
    parser.add_argument(
        "--ros2-mode", choices=("client", "peer"), default="client",
        help="with --transport ros2: the daemon's and the bench's Zenoh sessions as clients of "
        "the router (daemon.ros2's default: every message through the router), or as peers "
        "listening on loopback that the router's gossip joins directly (rmw_zenoh's sessions)")
    args = parser.parse_args(argv)
    if any(p < 1 for p in args.points) or args.huge_points < 1:
        parser.error("point counts must be >= 1")

    def note(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    rows: list[dict[str, Any]] = []
    if args.breakdown:
        rows.extend(breakdown(points, args) for points in args.points)
    if args.sizes or not (args.huge or args.breakdown):
        rows.extend(measure_sizes(args, note))
    if args.huge:
        rows.append(measure_huge(args, note))
    if args.json:
        for row in rows:
            print(json.dumps({k: v for k, v in row.items() if k != "cprofile"}))
    else:
        print_tables(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
