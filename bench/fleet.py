#!/usr/bin/env python3
"""State delivery to a remote client over Zenoh, for a fleet of daemons on this machine.

Starts ``--robots`` N daemons (``python -m jtc_hw run``, the demo arm on simulated (mirror)
joints at ``--update-rate``, state published at ``--state-rate``), each on Zenoh
(``daemon.zenoh``: prefix ``jtc/bench/r<i>``, listening on its own loopback port), and one
fleet client in this process: a Zenoh peer connected to every daemon, subscribed to
``jtc/bench/*/state`` (one subscriber for the whole fleet, as ``jtc-hw fleet --watch``),
decoding every message as a client must to use it.

Measured over ``--duration`` seconds, after one second of warm-up:

- ``state_hz_per_robot``: messages received per robot per second.
- ``delivered_pct``: received / published. What was published is read off the messages'
  ``seq`` (the number the daemon's Zenoh interface gives each state it has from the loop):
  per robot, last minus first received, plus one. Loss anywhere after the loop's snapshot
  reached the API process (the daemon's outbox, Zenoh, this client) shows. (A state the loop
  itself skips, overrunning on a loaded machine, is never published: not counted.)
- ``latency_p50_ms`` / ``latency_p99_ms``: arrival (this process, CLOCK_MONOTONIC) minus the
  state's ``time_ns`` (the loop's snapshot, same clock: same machine): the loop's pipe to the
  API process, the API process's tap and outbox, Zenoh over loopback TCP, and this client's
  callback, up to the decoded message.
- ``client_cpu_pct``: CPU time of this process (the client) during the run, % of one core.

The machine is shared: the daemons' loops, their API processes and the client compete for the
same CPUs; the figures are this machine's under that load, not the protocol's limits.

Usage:  python bench/fleet.py [--robots 8] [--duration 5] [--state-rate 50]
            [--update-rate 250] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jtc_hw.api.zenoh_client import open_session  # noqa: E402
from jtc_hw.cli.demo import demo_config  # noqa: E402

START_TIMEOUT_S = 60.0
WARM_UP_S = 1.0
KEYS = ("robots", "state_hz_per_robot", "delivered_pct", "latency_p50_ms", "latency_p99_ms",
        "client_cpu_pct")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Fleet:
    """N daemons on Zenoh, in a temporary directory."""

    def __init__(self, robots: int, update_rate: int, state_rate: float) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="jtc-hw-fleet-")
        self.dir = Path(self._tmp.name)
        self.update_rate, self.state_rate = update_rate, state_rate
        self.env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
        self.endpoints: list[str] = [""] * robots
        self.logs = [self.dir / f"r{i}.log" for i in range(robots)]
        self.processes: list[subprocess.Popen[bytes] | None] = [None] * robots
        for i in range(robots):
            self._spawn(i)

    def _spawn(self, i: int) -> None:
        """Start daemon ``i`` on a port free now."""
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        config = demo_config(str(self.dir / f"r{i}.sock"), update_rate=self.update_rate)
        config["joint_trajectory_controller"]["ros__parameters"][
            "state_publish_rate"] = self.state_rate
        config["daemon"].update({
            "flight_recorder_s": 0,
            "zenoh": {"prefix": f"jtc/bench/r{i}", "listen": [endpoint],
                      "token": secrets.token_hex(16)},  # the bench only watches
        })
        path = self.dir / f"r{i}.yaml"
        path.write_text(yaml.safe_dump(config))
        with open(self.logs[i], "wb") as out:
            self.processes[i] = subprocess.Popen(
                [sys.executable, "-m", "jtc_hw", "run", str(path)], stdout=out,
                stderr=subprocess.STDOUT, env=self.env)
        self.endpoints[i] = endpoint

    def wait_ready(self) -> None:
        """Until every daemon serves on Zenoh; one whose port was taken meanwhile (by another
        process on this shared machine) is started again on another.

        Raises:
            RuntimeError: one exited otherwise or did not start in time (its log is quoted).
        """
        deadline = time.monotonic() + START_TIMEOUT_S
        waiting = set(range(len(self.processes)))
        while waiting:
            for i in list(waiting):
                log = self.logs[i].read_text(errors="replace")
                process = self.processes[i]
                assert process is not None
                if "zenoh: serving under" in log:
                    waiting.discard(i)
                elif process.poll() is not None and "Address already in use" in log:
                    self._spawn(i)
                elif process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"daemon r{i} did not start:\n{log[-2000:]}")
            time.sleep(0.1)  # polling the daemons' logs for their start-up line

    def close(self) -> None:
        live = [p for p in self.processes if p is not None]
        for p in live:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in live:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self._tmp.cleanup()


class Receiver:
    """The fleet client's state subscriber: arrival latency and stamps per robot."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.recording = False
        self.latencies_ns: list[int] = []
        self.seqs: dict[str, list[int]] = {}

    def on_state(self, sample: Any) -> None:
        arrived = time.monotonic_ns()
        message = json.loads(sample.payload.to_bytes())
        if not self.recording:
            return
        with self.lock:
            self.latencies_ns.append(arrived - int(message["time_ns"]))
            self.seqs.setdefault(str(sample.key_expr), []).append(int(message["seq"]))


def measure(args: argparse.Namespace, note: Any) -> dict[str, Any]:
    note(f"starting {args.robots} daemons")
    fleet = Fleet(args.robots, args.update_rate, args.state_rate)
    try:
        fleet.wait_ready()
        session = open_session({"connect/endpoints": fleet.endpoints,
                                "scouting/gossip/enabled": False})
        try:
            receiver = Receiver()
            sub = session.declare_subscriber("jtc/bench/*/state", receiver.on_state)
            live: set[str] = set()
            seen = threading.Condition()

            def up(sample: Any) -> None:
                with seen:
                    live.add(str(sample.key_expr))
                    seen.notify_all()

            tokens = session.liveliness().declare_subscriber("jtc/bench/*", up, history=True)
            with seen:
                if not seen.wait_for(lambda: len(live) == args.robots, START_TIMEOUT_S):
                    raise RuntimeError(f"the client sees {len(live)} of {args.robots} daemons")
            tokens.undeclare()
            time.sleep(WARM_UP_S)  # a benchmark's warm-up: subscriptions settle
            note(f"measuring {args.duration:g} s")
            cpu0, wall0 = time.process_time(), time.monotonic()
            receiver.recording = True
            time.sleep(args.duration)  # the measured run: the subscriber works meanwhile
            receiver.recording = False
            cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
            sub.undeclare()
        finally:
            session.close()
    finally:
        fleet.close()
    with receiver.lock:
        received = sum(len(s) for s in receiver.seqs.values())
        published = sum(max(s) - min(s) + 1 for s in receiver.seqs.values() if s)
        latencies = np.array(receiver.latencies_ns, dtype=float) / 1e6
    return {
        "robots": args.robots,
        "state_hz_per_robot": round(received / wall / args.robots, 1),
        "delivered_pct": round(100.0 * received / published, 2) if published else 0.0,
        "latency_p50_ms": round(float(np.percentile(latencies, 50)), 2) if received else None,
        "latency_p99_ms": round(float(np.percentile(latencies, 99)), 2) if received else None,
        "client_cpu_pct": round(100.0 * cpu / wall, 1),
        "_robots_heard": len(receiver.seqs),
        "_duration_s": round(wall, 2),
        "_latency_max_ms": round(float(latencies.max()), 2) if received else None,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=8, help="daemons (default 8)")
    parser.add_argument("--duration", type=float, default=5.0,
                        help="seconds measured (default 5)")
    parser.add_argument("--state-rate", type=float, default=50.0,
                        help="state_publish_rate of each daemon, Hz (default 50)")
    parser.add_argument("--update-rate", type=int, default=250,
                        help="each daemon's loop rate, Hz (default 250)")
    parser.add_argument("--json", action="store_true",
                        help="one JSON object: " + ", ".join(KEYS))
    args = parser.parse_args(argv)
    if args.robots < 1 or args.duration <= 0 or args.state_rate <= 0:
        parser.error("--robots, --duration and --state-rate must be positive")

    def note(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    row = measure(args, note)
    if args.json:
        print(json.dumps({k: row[k] for k in KEYS}))
        return 0
    print(f"state delivery over Zenoh (loopback) to one fleet client; {args.robots} mirror "
          f"daemons at {args.update_rate} Hz publishing state at {args.state_rate:g} Hz; "
          f"{row['_duration_s']:g} s; Python {sys.version.split()[0]}, {os.cpu_count()} CPUs "
          "(shared machine)")
    print(f"{'robots':>6}  {'state Hz/robot':>14}  {'delivered':>9}  {'p50 ms':>7}  "
          f"{'p99 ms':>7}  {'max ms':>7}  {'client CPU':>10}")
    print(f"{row['robots']:>6}  {row['state_hz_per_robot']:>14g}  {row['delivered_pct']:>8g}%  "
          f"{row['latency_p50_ms']:>7}  {row['latency_p99_ms']:>7}  {row['_latency_max_ms']:>7}  "
          f"{row['client_cpu_pct']:>9g}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
