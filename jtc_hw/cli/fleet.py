"""``jtc-hw fleet``: the daemons on Zenoh, one line each (docs/zenoh.md).

``jtc-hw fleet`` lists the daemons a Zenoh session sees (their liveliness tokens under
``--prefix``, default ``jtc/**``), one line each: prefix, joints, active goal, fault, loop
rate. The list comes from two wildcard queries answered by every daemon at once
(``<pattern>/rpc/hello`` and ``<pattern>/rpc/get_status``). ``--watch`` keeps a live table:
liveliness changes (a daemon starting, stopping, dying) redraw it at once, the state stream
gives each robot's active goal and state rate, ``fault`` events its fault, and the status
(loop rate) is asked again every :data:`STATUS_REFRESH_S`. ``--json``: one JSON object per
robot (with ``--watch``: one ``{"time", "robots"}`` object per redraw).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from typing import Any, Final

from ..api.zenoh_client import open_session
from ..errors import ConfigurationError

__all__ = ["STATUS_REFRESH_S", "add_parsers", "cmd_fleet"]

STATUS_REFRESH_S: Final = 5.0
"""How often ``--watch`` asks every daemon for its status again."""
DEFAULT_PATTERN: Final = "jtc/**"


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "fleet",
        help="list the daemons on Zenoh with their state (--watch: live table)",
        description=(
            "List the jtc-hw daemons a Zenoh session sees, one line each: prefix, joints, "
            "active goal, fault, loop rate. --watch redraws as daemons come and go."
        ),
    )
    p.add_argument("--prefix", default=DEFAULT_PATTERN,
                   help=f"key expression of the daemons to list (default {DEFAULT_PATTERN})")
    p.add_argument("--zenoh-config", metavar="FILE",
                   help="Zenoh configuration (default: connect to a router on "
                   "tcp/127.0.0.1:7447)")
    p.add_argument("--watch", action="store_true", help="keep a live table")
    p.add_argument("--interval", type=float, default=1.0,
                   help="--watch: seconds between redraws (default 1)")
    p.add_argument("--json", action="store_true", help="JSON lines instead of a table")
    p.add_argument("--timeout", type=float, default=2.0,
                   help="seconds to wait for the daemons' answers (default 2)")
    p.set_defaults(func=cmd_fleet)


def _prefix_of(key: str, suffix: str) -> str:
    return key[: -len(suffix)] if key.endswith(suffix) else key


class _Fleet:
    """What a session knows of the daemons (updated from Zenoh's threads)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.changed = threading.Event()
        self.live: set[str] = set()
        self.rows: dict[str, dict[str, Any]] = {}
        self.states: dict[str, list[int]] = {}  # prefix -> recent state times (ns)

    def row(self, prefix: str) -> dict[str, Any]:
        return self.rows.setdefault(prefix, {
            "prefix": prefix, "joints": None, "goal": None, "fault": None, "loop_hz": None,
            "state_hz": None})

    def on_liveliness(self, sample: Any) -> None:
        prefix = str(sample.key_expr)
        with self.lock:
            if str(sample.kind).endswith("DELETE"):
                self.live.discard(prefix)
                self.rows.pop(prefix, None)
                self.states.pop(prefix, None)
            else:
                self.live.add(prefix)
                self.row(prefix)
        self.changed.set()

    def on_reply(self, reply: Any) -> None:
        sample = reply.ok
        if sample is None:
            return
        try:
            message = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        key = str(sample.key_expr)
        with self.lock:
            if key.endswith("/rpc/hello"):
                row = self.row(_prefix_of(key, "/rpc/hello"))
                row["joints"] = len(message.get("joint_names") or [])
            elif key.endswith("/rpc/get_status"):
                row = self.row(_prefix_of(key, "/rpc/get_status"))
                controller = message.get("controller") or {}
                row["goal"] = controller.get("active_goal")
                row["fault"] = controller.get("fault")
                row["loop_hz"] = (message.get("loop") or {}).get("rate_hz")

    def on_state(self, sample: Any) -> None:
        prefix = _prefix_of(str(sample.key_expr), "/state")
        try:
            message = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with self.lock:
            if prefix not in self.live:
                return
            row = self.row(prefix)
            row["joints"] = len(message.get("joint_names") or [])
            row["goal"] = message.get("active_goal")
            times = self.states.setdefault(prefix, [])
            times.append(int(message.get("time_ns", 0)))
            del times[:-50]
            if len(times) >= 2 and times[-1] > times[0]:
                row["state_hz"] = (len(times) - 1) / ((times[-1] - times[0]) / 1e9)

    def on_event(self, sample: Any) -> None:
        try:
            message = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if message.get("event") != "fault":
            return
        prefix = _prefix_of(str(sample.key_expr), "/events")
        with self.lock:
            if prefix in self.live:
                self.row(prefix)["fault"] = message.get("fault")

    def snapshot(self) -> list[dict[str, Any]]:
        with self.lock:
            return [dict(self.rows[p]) for p in sorted(self.live) if p in self.rows]


def _query_all(session: Any, pattern: str, timeout_s: float) -> list[Any]:
    """Ask every daemon under ``pattern`` for hello and status at once; the reply handlers."""
    return [session.get(f"{pattern}/rpc/{op}", timeout=timeout_s)
            for op in ("hello", "get_status")]


def _drain(handlers: list[Any], fleet: _Fleet) -> None:
    for handler in handlers:
        for reply in handler:
            fleet.on_reply(reply)


def _table(rows: list[dict[str, Any]], watch: bool) -> list[str]:
    header = f"{'PREFIX':<32} {'JOINTS':>6} {'GOAL':>6} {'LOOP':>8}"
    header += f" {'STATE':>8}" if watch else ""
    lines = [header + "  FAULT"]
    for r in rows:
        loop = f"{r['loop_hz']:g} Hz" if r["loop_hz"] else "?"
        line = (f"{r['prefix']:<32} {r['joints'] if r['joints'] is not None else '?':>6} "
                f"{r['goal'] if r['goal'] is not None else '-':>6} {loop:>8}")
        if watch:
            line += f" {format(r['state_hz'], '.0f') + ' Hz' if r['state_hz'] else '?':>8}"
        lines.append(line + f"  {r['fault'] or '-'}")
    if not rows:
        lines.append("(no daemon)")
    return lines


def cmd_fleet(args: argparse.Namespace) -> int:
    """``jtc-hw fleet [--prefix PATTERN] [--zenoh-config FILE] [--watch] [--json]``.

    Raises:
        ClientConnectionError: eclipse-zenoh is missing or no session can be opened.
        ConfigurationError: an unreadable Zenoh configuration.
    """
    try:
        session = open_session(args.zenoh_config)
    except ValueError as exc:  # an unreadable configuration: bad input, said as such
        raise ConfigurationError(str(exc), "--zenoh-config") from None
    fleet = _Fleet()
    pattern = args.prefix.rstrip("/")
    try:
        if not args.watch:
            for reply in session.liveliness().get(pattern, timeout=args.timeout):
                if reply.ok is not None:
                    fleet.live.add(str(reply.ok.key_expr))
            if fleet.live:
                _drain(_query_all(session, pattern, args.timeout), fleet)
            for p in fleet.live:
                fleet.row(p)
            rows = fleet.snapshot()
            for line in ([json.dumps(r) for r in rows] if args.json else _table(rows, False)):
                print(line)
            return 0
        return _watch(session, pattern, fleet, args)
    finally:
        session.close()


def _watch(session: Any, pattern: str, fleet: _Fleet, args: argparse.Namespace) -> int:
    declared = [
        session.liveliness().declare_subscriber(pattern, fleet.on_liveliness, history=True),
        session.declare_subscriber(f"{pattern}/state", fleet.on_state),
        session.declare_subscriber(f"{pattern}/events", fleet.on_event),
    ]
    tty = sys.stdout.isatty() and not args.json
    drawn = 0
    next_status = 0.0
    try:
        while True:
            now = time.monotonic()
            if now >= next_status:
                next_status = now + STATUS_REFRESH_S
                threading.Thread(target=_refresh, args=(session, pattern, fleet, args.timeout),
                                 daemon=True).start()
            rows = fleet.snapshot()
            if args.json:
                print(json.dumps({"time": time.time(), "robots": rows}), flush=True)
            else:
                lines = _table(rows, True)
                if tty and drawn:
                    sys.stdout.write(f"\x1b[{drawn}F\x1b[J")
                print("\n".join(lines), flush=True)
                drawn = len(lines)
            fleet.changed.wait(args.interval)
            fleet.changed.clear()
    except KeyboardInterrupt:
        return 0
    finally:
        for entity in declared:
            entity.undeclare()


def _refresh(session: Any, pattern: str, fleet: _Fleet, timeout_s: float) -> None:
    """Ask every daemon's hello and status again (a thread: the replies take their time)."""
    try:
        _drain(_query_all(session, pattern, timeout_s), fleet)
    except Exception:  # the session closed under us (Ctrl-C)
        return
    fleet.changed.set()
