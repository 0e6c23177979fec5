#!/usr/bin/env python3
"""The protocol fuzz at full size: random and mutated lines of every op against a real daemon.

Starts ``python -m jtc_hw run`` as a subprocess on six simulated (mirror) joints at 500 Hz
(``tests/helpers/daemon.py``: the same daemon the end-to-end tests run; socket and log in a
temporary directory), opens one unix connection and pipelines ``--messages`` lines made by
``tests/helpers/fuzz.py`` (seeded: ``--seed`` replays a run), while reading what comes back.
Lines cover every operation of ``docs/protocol.md``: plausible requests, wrong and extreme
values (types, lone surrogate escapes, times at and beyond int64, values near the float64
range), missing and unknown fields, byte-level mutations, malformed JSON, over-long lines,
speed factors out of range (1e308, -1, NaN, infinity, huge integers, strings) and parameter
changes of every family with huge, NaN, negative or ill-typed values. Goals
really run (and preempt each other, get canceled, stopped, aborted by a ``sim`` freeze or
fault, re-armed).

Each line is one complete, non-blank message, so the daemon owes it exactly one reply. Counted:
replies by code (``ok`` or the error code), replies whose id differs from the request's (where
the request's id was certain to be readable), replies missing when the connection ended or went
quiet, ``internal`` errors, events received, and the daemon's logged request failures
(tracebacks). The run is good when missing, id mismatches, internal and failures are all 0 and
the daemon exits 0 on SIGTERM afterwards.

Usage:  python bench/fuzz_protocol.py [--messages 100000] [--seed N] [--json]
"""

from __future__ import annotations

import argparse
import collections
import json
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the daemon runner and the fuzz are the tests' own
sys.path.insert(0, str(ROOT))

from helpers.daemon import JOINTS, DaemonProcess  # noqa: E402
from helpers.fuzz import Fuzzer, Line  # noqa: E402

MAX_MESSAGE_BYTES = 65536
REPLY_TIMEOUT_S = 60.0  # the longest quiet spell accepted before replies count as missing
BATCH = 64


def send_all(sock: socket.socket, lines: list[Line], failed: list[BaseException]) -> None:
    try:
        for start in range(0, len(lines), BATCH):
            sock.sendall(b"".join(line.data for line in lines[start : start + BATCH]))
    except OSError as exc:  # the daemon closed the connection: the reader reports it
        failed.append(exc)


def run(messages: int, seed: int) -> dict[str, Any]:
    fuzzer = Fuzzer(seed, JOINTS, ("arm", "mirror"), MAX_MESSAGE_BYTES)
    lines = [fuzzer.line() for _ in range(messages)]
    with tempfile.TemporaryDirectory(prefix="jtc-hw-fuzz-") as tmp:
        daemon = DaemonProcess(Path(tmp), max_message_bytes=MAX_MESSAGE_BYTES)
        daemon.start()
        try:
            daemon.wait_ready()
            counts, summary = exchange(daemon, lines)
        finally:
            summary_exit = daemon.shutdown()
        log = daemon.log()
    summary["daemon_exit"] = summary_exit
    summary["logged_failures"] = sum(
        x.startswith("ERROR jtc_hw.server") and x.endswith(" failed") for x in log.splitlines()
    )
    summary["tracebacks"] = log.count("Traceback")
    return {"counts": counts, "summary": summary}


def exchange(daemon: DaemonProcess, lines: list[Line]) -> tuple[dict[str, int], dict[str, Any]]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.connect(str(daemon.socket))
    failed: list[BaseException] = []
    writer = threading.Thread(target=send_all, args=(sock, lines, failed), name="fuzz-writer")
    counts: collections.Counter[str] = collections.Counter()
    replies = events = mismatches = 0
    first_problem = ""
    begin = time.monotonic()
    writer.start()
    stream = sock.makefile("rb")
    sock.settimeout(REPLY_TIMEOUT_S)
    try:
        while replies < len(lines):
            try:
                data = stream.readline()
            except (TimeoutError, OSError) as exc:
                first_problem = first_problem or f"reading stopped: {exc}"
                break
            if not data.endswith(b"\n"):
                first_problem = first_problem or "the daemon closed the connection"
                break
            message = json.loads(data)
            if "event" in message:
                events += 1
                continue
            line = lines[replies]
            replies += 1
            code = "ok" if message.get("ok") else message["error"]["code"]
            counts[code] += 1
            problem = ""
            if line.request_id is not None and message.get("id") != line.request_id:
                mismatches += 1
                problem = "id mismatch"
            if code == "internal":
                problem = "internal"
            if problem and not first_problem:
                first_problem = f"{problem}: {line.data[:200]!r} -> {data[:300]!r}"
    finally:
        elapsed = time.monotonic() - begin
        stream.close()
        sock.close()
        writer.join(REPLY_TIMEOUT_S)
    summary = {
        "messages": len(lines),
        "replies": replies,
        "missing": len(lines) - replies,
        "id_mismatches": mismatches,
        "internal": counts.get("internal", 0),
        "events": events,
        "seconds": round(elapsed, 1),
        "messages_per_s": round(replies / elapsed) if elapsed > 0 else None,
        "first_problem": first_problem or None,
    }
    return dict(sorted(counts.items(), key=lambda kv: -kv[1])), summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--messages", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    result = run(args.messages, args.seed)
    counts, summary = result["counts"], result["summary"]
    if args.json:
        for code, n in counts.items():
            print(json.dumps({"reply": code, "count": n}))
        print(json.dumps({"seed": args.seed, **summary}))
    else:
        print(f"protocol fuzz: {summary['messages']} lines, seed {args.seed}, real daemon "
              f"(6 mirror joints, 500 Hz)")
        print(f"{'reply':<16} {'count':>8}")
        for code, n in counts.items():
            print(f"{code:<16} {n:>8}")
        for key in ("replies", "missing", "id_mismatches", "internal", "events", "seconds",
                    "messages_per_s", "logged_failures", "tracebacks", "daemon_exit"):
            print(f"{key:<16} {summary[key]!s:>8}")
        if summary["first_problem"]:
            print(f"first problem: {summary['first_problem']}")
    bad = (summary["missing"] or summary["id_mismatches"] or summary["internal"]
           or summary["tracebacks"] or summary["daemon_exit"] != 0)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
