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

A third of the messages (``--binary``) are binary frames (protocol version 2,
docs/protocol.md "Binary frames"): plausible goals and trajectories, and the wrong kinds --
shapes that do not match the bytes, NaN and infinities, dtypes other than ``<f8``, columns
that do not match the joints, oversized attachments, lengths that lie, lengths that are no
integer, raw bytes without their newline, frames cut short. A frame that cannot be trusted
gets ``bad_frame`` and the daemon closes the connection: the fuzz then writes no more on it
(the end of the stream tells a frame cut short) and goes on with a new connection.

Each line is one complete, non-blank message, so the daemon owes it exactly one reply. Counted:
replies by code (``ok`` or the error code), replies whose id differs from the request's (where
the request's id was certain to be readable), replies missing when the connection ended or went
quiet, ``internal`` errors, events received, and the daemon's logged request failures
(tracebacks). The run is good when missing, id mismatches, internal and failures are all 0 and
the daemon exits 0 on SIGTERM afterwards.

Usage:  python bench/fuzz_protocol.py [--messages 100000] [--seed N] [--binary 0.33] [--json]
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
from helpers.fuzz import Fuzzer, Line, segments  # noqa: E402

MAX_MESSAGE_BYTES = 65536
BINARY = 1 / 3
"""Share of the messages that are binary frames (protocol version 2)."""
REPLY_TIMEOUT_S = 60.0  # the longest quiet spell accepted before replies count as missing
BATCH = 64


def send_all(sock: socket.socket, lines: list[Line], failed: list[BaseException]) -> None:
    try:
        for start in range(0, len(lines), BATCH):
            sock.sendall(b"".join(line.data for line in lines[start : start + BATCH]))
        if lines and lines[-1].closes:
            sock.shutdown(socket.SHUT_WR)  # a frame cut short is told by the stream's end
    except OSError as exc:  # the daemon closed the connection: the reader reports it
        failed.append(exc)


def run(messages: int, seed: int, binary: float = BINARY) -> dict[str, Any]:
    fuzzer = Fuzzer(seed, JOINTS, ("arm", "mirror"), MAX_MESSAGE_BYTES, binary=binary)
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
    if summary["first_problem"] or summary["tracebacks"]:
        print(f"daemon log (last 40 lines):\n{''.join(log.splitlines(True)[-40:])}",
              file=sys.stderr)
    return {"counts": counts, "summary": summary}


class _Tally:
    """What came back, over every connection."""

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self.replies = self.events = self.mismatches = self.not_closed = 0
        self.first_problem = ""

    def problem(self, text: str) -> None:
        self.first_problem = self.first_problem or text


def exchange_segment(daemon: DaemonProcess, lines: list[Line], tally: _Tally) -> bool:
    """Send ``lines`` on a connection of their own and read their replies (and, after a
    line that ``closes``, the end of the stream); False when the run must stop."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(str(daemon.socket))
    except OSError as exc:
        sock.close()
        code = daemon.proc.poll() if daemon.proc is not None else None
        tally.problem(f"cannot connect to the daemon ({exc}); its exit status: {code}")
        return False
    failed: list[BaseException] = []
    writer = threading.Thread(target=send_all, args=(sock, lines, failed), name="fuzz-writer")
    writer.start()
    stream = sock.makefile("rb")
    sock.settimeout(REPLY_TIMEOUT_S)
    got = 0
    try:
        while got < len(lines):
            try:
                data = stream.readline()
            except (TimeoutError, OSError) as exc:
                tally.problem(f"reading stopped: {exc}")
                return False
            if not data.endswith(b"\n"):
                tally.problem(f"the daemon closed the connection before the reply to "
                              f"{lines[got].data[:200]!r}")
                return False
            message = json.loads(data)
            if "event" in message:
                tally.events += 1
                continue
            line = lines[got]
            got += 1
            tally.replies += 1
            code = "ok" if message.get("ok") else message["error"]["code"]
            tally.counts[code] += 1
            problem = ""
            if line.request_id is not None and message.get("id") != line.request_id:
                tally.mismatches += 1
                problem = "id mismatch"
            if code == "internal":
                problem = "internal"
            if line.closes and code != "bad_frame":
                problem = f"{code} instead of bad_frame"
            if problem:
                tally.problem(f"{problem}: {line.data[:200]!r} -> {data[:300]!r}")
        if lines[-1].closes:  # then the daemon closes the connection (events may come first)
            try:
                while (data := stream.readline()).endswith(b"\n"):
                    tally.events += 1
            except (TimeoutError, OSError):
                tally.not_closed += 1
                tally.problem("the connection stayed open after bad_frame")
        return True
    finally:
        stream.close()
        sock.close()
        writer.join(REPLY_TIMEOUT_S)


def exchange(daemon: DaemonProcess, lines: list[Line]) -> tuple[dict[str, int], dict[str, Any]]:
    tally = _Tally()
    parts = segments(lines)
    begin = time.monotonic()
    for part in parts:
        if not exchange_segment(daemon, part, tally):
            break
    elapsed = time.monotonic() - begin
    summary = {
        "messages": len(lines),
        "binary": sum(line.binary for line in lines),
        "connections": len(parts),
        "replies": tally.replies,
        "missing": len(lines) - tally.replies,
        "id_mismatches": tally.mismatches,
        "not_closed": tally.not_closed,
        "internal": tally.counts.get("internal", 0),
        "events": tally.events,
        "seconds": round(elapsed, 1),
        "messages_per_s": round(tally.replies / elapsed) if elapsed > 0 else None,
        "first_problem": tally.first_problem or None,
    }
    return dict(sorted(tally.counts.items(), key=lambda kv: -kv[1])), summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--messages", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--binary", type=float, default=BINARY,
                        help="share of binary frames (default: a third)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    args = parser.parse_args(argv)
    result = run(args.messages, args.seed, args.binary)
    counts, summary = result["counts"], result["summary"]
    if args.json:
        for code, n in counts.items():
            print(json.dumps({"reply": code, "count": n}))
        print(json.dumps({"seed": args.seed, **summary}))
    else:
        print(f"protocol fuzz: {summary['messages']} messages ({summary['binary']} binary "
              f"frames, {summary['connections']} connections), seed {args.seed}, real daemon "
              f"(6 mirror joints, 500 Hz)")
        print(f"{'reply':<16} {'count':>8}")
        for code, n in counts.items():
            print(f"{code:<16} {n:>8}")
        for key in ("replies", "missing", "id_mismatches", "not_closed", "internal", "events",
                    "seconds",
                    "messages_per_s", "logged_failures", "tracebacks", "daemon_exit"):
            print(f"{key:<16} {summary[key]!s:>8}")
        if summary["first_problem"]:
            print(f"first problem: {summary['first_problem']}")
    bad = (summary["missing"] or summary["id_mismatches"] or summary["internal"]
           or summary["not_closed"] or summary["first_problem"] or summary["tracebacks"]
           or summary["daemon_exit"] != 0)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
