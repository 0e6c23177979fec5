#!/usr/bin/env python3
"""Zenoh's own query round trip on this machine: the floor under every ROS 2 and Zenoh figure.

A Zenoh router on a free loopback port (what ``rmw_zenohd`` is to a ROS 2 graph), a server
process whose queryable replies at once from Zenoh's callback thread (16 bytes), and this
process sending ``--queries`` queries of ``--bytes`` bytes one after another (2 ms apart), each
timed from ``get`` to the first reply's arrival in the reply callback: what a ROS 2 service or
action request costs before any work at either end. Per mode:

  client  both sessions clients of the router: every message through it (``daemon.ros2``'s
          default, as the issue asks)
  peer    both peers, connected directly on loopback once the router's gossip has introduced
          them (rmw_zenoh's own session default)

and with the server's replies sent ``express`` (no batching) or not. The socket's round trip,
for comparison, is printed too: the same request and reply over a Unix socket pair between the
two processes.

docs/benchmarks.md ("The ROS 2 transport") compares ``bench/goal_latency.py --transport socket
ros2`` against these figures: what the ROS 2 path costs beyond the socket's that no code of ours
can remove.

Usage:  python bench/zenoh_rtt.py [--queries N] [--bytes N] [--modes client peer] [--json]
Needs jtc_hw[zenoh] (eclipse-zenoh).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import socket
import statistics
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

KEY = "bench/rtt"
REPLY = b"r" * 16
GAP_S = 0.002
TIMEOUT_S = 5.0


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def config(mode: str, endpoint: str) -> Any:
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    if mode == "router":
        c.insert_json5("listen/endpoints", json.dumps([endpoint]))
    else:
        c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    if mode == "peer":  # reachable directly, as rmw_zenoh's sessions listen on loopback
        c.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    return c


def serve(endpoint: str, mode: str, express: bool, ready: Any, stop: Any, sock: Any) -> None:
    """The server process: a queryable replying at once, and the socket's echo."""
    import zenoh

    session = zenoh.open(config(mode, endpoint))

    def reply(query: Any) -> None:
        query.reply(query.key_expr, REPLY, express=express)
        query.drop()

    queryable = session.declare_queryable(KEY, reply, complete=True)

    def echo() -> None:
        while True:
            data = sock.recv(1 << 20)
            if not data:
                return
            sock.sendall(REPLY)

    threading.Thread(target=echo, daemon=True).start()
    ready.set()
    stop.wait(600)
    queryable.undeclare()
    session.close()


def timed(send: Callable[[], None], queries: int) -> list[float]:
    """Microseconds per round trip of ``send`` (which returns once the reply arrived)."""
    times = []
    for _ in range(queries):
        begin = time.perf_counter_ns()
        send()
        times.append((time.perf_counter_ns() - begin) / 1e3)
        time.sleep(GAP_S)
    return times


def measure(mode: str, express: bool, args: argparse.Namespace) -> dict[str, Any]:
    import zenoh

    endpoint = free_endpoint()
    router = zenoh.open(config("router", endpoint))
    ctx = multiprocessing.get_context("spawn")  # never fork a process that runs Zenoh
    ready, stop = ctx.Event(), ctx.Event()
    mine, theirs = socket.socketpair()
    server = ctx.Process(target=serve, args=(endpoint, mode, express, ready, stop, theirs),
                         daemon=True)
    server.start()
    theirs.close()
    session = zenoh.open(config(mode, endpoint))
    payload = b"q" * args.bytes
    try:
        if not ready.wait(30):
            raise RuntimeError("the server process did not start")

        def query() -> None:
            first = threading.Event()

            def on_reply(reply: Any) -> None:
                first.set()

            session.get(KEY, zenoh.handlers.Callback(on_reply, lambda: None), payload=payload,
                        timeout=TIMEOUT_S)
            if not first.wait(TIMEOUT_S):
                raise RuntimeError("no reply")

        deadline = time.monotonic() + 30
        while True:  # until the queryable is reachable through the router
            try:
                query()
                break
            except RuntimeError:
                if time.monotonic() > deadline:
                    raise
        zenoh_us = timed(query, args.queries)

        def over_socket() -> None:
            mine.sendall(payload)
            mine.recv(1 << 20)

        socket_us = timed(over_socket, args.queries)
    finally:
        stop.set()
        mine.close()
        server.join(10)
        session.close()
        router.close()
    return {
        "bench": "zenoh_rtt", "mode": mode, "express": express, "bytes": args.bytes,
        "queries": args.queries,
        "zenoh_p50_us": round(statistics.median(zenoh_us), 1),
        "zenoh_p90_us": round(sorted(zenoh_us)[int(0.9 * len(zenoh_us))], 1),
        "socket_p50_us": round(statistics.median(socket_us), 1),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--queries", type=int, default=300, help="round trips per row (300)")
    parser.add_argument("--bytes", type=int, default=400, help="query payload (400, a "
                        "2-point FollowJointTrajectory goal)")
    parser.add_argument("--modes", nargs="+", choices=("client", "peer"),
                        default=["client", "peer"])
    parser.add_argument("--json", action="store_true", help="one JSON object per row")
    args = parser.parse_args(argv)
    try:
        import zenoh  # noqa: F401
    except ImportError:
        print("zenoh_rtt needs eclipse-zenoh: pip install 'jtc_hw[zenoh]'", file=sys.stderr)
        return 2
    rows = [measure(mode, express, args) for mode in args.modes for express in (False, True)]
    if args.json:
        for row in rows:
            print(json.dumps(row))
        return 0
    print(f"Zenoh query round trip through a router on loopback, {args.bytes}-byte query, "
          f"{args.queries} queries per row; Python {sys.version.split()[0]}")
    print(f"{'mode':>7} {'express':>8} {'zenoh p50':>10} {'p90':>8} {'socket p50':>11}")
    for r in rows:
        print(f"{r['mode']:>7} {str(r['express']):>8} {r['zenoh_p50_us']:>8.0f}us "
              f"{r['zenoh_p90_us']:>6.0f}us {r['socket_p50_us']:>9.0f}us")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
