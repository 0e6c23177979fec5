"""``jtc-hw state`` and ``jtc-hw status``: what the daemon is doing, readable or as JSON.

``state`` shows the controller state stream (desired, actual, error per joint). The loop sends
no state while the controller is stopped by a hardware fault (the hardware is not read then),
so ``state`` asks ``get_status`` whenever the stream is silent for a moment and shows the fault
and the position being held instead of waiting out its timeout; ``--watch`` carries on and
returns to the table once the robot is re-armed. ``--json`` prints one JSON object per line
(NDJSON): the daemon's ``state`` events as sent (docs/protocol.md), and while faulted
``{"event": "fault", "fault": ..., "joint_names": ..., "held": ...}`` lines.

``status`` prints the daemon's status reply as a table; ``--json`` prints the reply itself
(without the protocol's ``id``/``ok`` wrapper).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from datetime import datetime
from typing import Any

__all__ = ["cmd_state", "cmd_status", "print_state", "status_lines"]

QUIET_PROBE_S = 0.5
"""A state stream silent this long makes ``state`` look at the status for a fault. Longer
than any sensible ``state_publish_rate`` period (upstream's default is 50 Hz)."""

FAULT_REFRESH_S = 1.0
"""While faulted, ``state --watch`` shows the status again this often (the stream is silent)."""


def _fmt(values: Sequence[float | None] | None, width: int = 9) -> str:
    if values is None:
        return "-"
    return " ".join(f"{v:{width}.4f}" if v is not None else f"{'nan':>{width}}" for v in values)


def wall_time() -> str:
    """This machine's wall time for a header, to the millisecond (local time zone)."""
    return datetime.now().astimezone().strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]


def print_state(state: dict[str, Any], header: bool) -> None:
    """One ``state`` event as the joint table (the header row carries the wall time)."""
    names = state["joint_names"]
    if header:
        print(
            f"{'joint':<14} {'desired':>9} {'actual':>9} {'error':>9} {'velocity':>9}   "
            f"{wall_time()}"
        )
    d, a, e = state["desired"], state["actual"], state["error"]
    for i, name in enumerate(names):
        vel = (a.get("velocities") or [None] * len(names))[i]
        print(
            f"{name:<14} {_fmt([d['positions'][i]])} {_fmt([a['positions'][i]])} "
            f"{_fmt([e['positions'][i]])} {_fmt([vel])}"
        )
    goal = state.get("active_goal")
    dropped = state.get("dropped") or 0
    line = f"t={state['time_ns'] / 1e9:.3f} s  {'holding' if state['holding'] else 'moving'}"
    if goal is not None:
        line += f"  goal {goal}"
    scaling = state.get("speed_scaling")
    if scaling and (scaling["factor"] != 1.0 or scaling["target"] != 1.0):
        ramp = "" if scaling["factor"] == scaling["target"] else f" -> {scaling['target']:g}"
        line += f"  speed {scaling['factor']:.3g}{ramp}"
    if dropped:
        line += f"  ({dropped} state messages dropped: this terminal is slower than the rate)"
    print(line, flush=True)


def _fault_view(client: Any) -> dict[str, Any] | None:
    """The controller's fault and the position it holds, or None when it runs normally."""
    controller = client.get_status().get("controller", {})
    fault = controller.get("fault")
    if fault is None and controller.get("active", True):
        return None
    # The reference the controller holds; the hardware is not read while it is stopped.
    held = client.query_state(in_s=0.0)
    return {
        "event": "fault",
        "fault": fault or "the controller is not active",
        "active": bool(controller.get("active")),
        "joint_names": list(held.get("joint_names") or client.joint_names),
        "held": held.get("positions"),
    }


def _print_fault(view: dict[str, Any], as_json: bool) -> int:
    """Print a fault view; returns the number of lines printed (for --watch's redraw)."""
    if as_json:
        print(json.dumps({**view, "wall_time": wall_time()}), flush=True)
        return 1
    names, held = view["joint_names"], view["held"] or [None] * len(view["joint_names"])
    print(f"{'joint':<14} {'held':>9} {'actual':>9}   {wall_time()}")
    for name, value in zip(names, held, strict=False):
        print(f"{name:<14} {_fmt([value])} {'-':>9}")
    print(
        f"FAULT (controller stopped, hardware not read): {view['fault']}\n"
        "  'jtc-hw rearm' leaves it once the cause is removed; 'jtc-hw status' shows details",
        flush=True,
    )
    return len(names) + 3


def cmd_state(args: argparse.Namespace) -> int:
    """``jtc-hw state [--watch] [--json]``.

    Raises:
        TimeoutError: no state and no fault within ``--timeout`` (the daemon does not answer).
    """
    from .cli import _connect

    tty = sys.stdout.isatty() and not args.json
    with _connect(args) as client:
        subscription = client.subscribe_state()
        try:
            drawn = 0  # lines of the last table, for redrawing it in place
            deadline = time.monotonic() + args.timeout
            while True:
                try:
                    state = subscription.get(timeout_s=min(QUIET_PROBE_S, args.timeout))
                except TimeoutError:
                    view = _fault_view(client)
                    if view is None:
                        if time.monotonic() > deadline:
                            raise
                        continue
                    if args.watch and drawn and tty:
                        sys.stdout.write(f"\x1b[{drawn}A\x1b[J")
                    drawn = _print_fault(view, args.json)
                    if not args.watch:
                        return 0
                    time.sleep(FAULT_REFRESH_S)  # the stream is silent: refresh at a low rate
                    deadline = time.monotonic() + args.timeout
                    continue
                deadline = time.monotonic() + args.timeout
                if args.json:
                    print(json.dumps(state), flush=True)
                else:
                    if args.watch and drawn and tty:
                        sys.stdout.write(f"\x1b[{drawn}A\x1b[J")
                    print_state(state, header=True)
                    drawn = len(state["joint_names"]) + 2
                if not args.watch:
                    return 0
        except KeyboardInterrupt:
            return 0
        finally:
            subscription.close()


def _num(value: Any, unit: str = "") -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.6g}{unit}"
    return f"{value}{unit}"


def status_lines(status: dict[str, Any]) -> list[str]:
    """The ``get_status`` reply as readable lines (fields a daemon lacks are skipped)."""
    lines: list[str] = []
    server = status.get("server", {})
    alive = "alive" if status.get("alive", True) else "NOT ALIVE"
    lines.append(
        f"daemon        jtc-hw {server.get('version', '?')} (protocol "
        f"{server.get('protocol_version', '?')}), loop pid {status.get('loop_pid', '?')}, {alive}"
    )
    c = status.get("controller", {})
    if c:
        if c.get("fault"):
            state = f"FAULT: {c['fault']}"
        elif not c.get("active", True):
            state = "inactive"
        else:
            state = "active, " + ("holding" if c.get("holding") else "moving")
        goal = c.get("active_goal")
        scaling = c.get("speed_scaling") or {}
        extra = f", goal {goal}" if goal is not None else ""
        if scaling and scaling.get("target", 1.0) != 1.0:
            extra += f", speed scaling {scaling.get('factor')} -> {scaling.get('target')}"
        lines.append(f"controller    {state}{extra}")
    loop = status.get("loop", {})
    if loop:
        late, cost = loop.get("lateness_us", {}), loop.get("cost_us", {})
        lines.append(
            f"loop          {_num(loop.get('rate_hz'), ' Hz')}, {_num(loop.get('cycles'))} "
            f"cycles, overruns {_num(loop.get('overruns'))}"
        )
        lines.append(
            f"  lateness    p50 {_num(late.get('p50'))} us, p99 {_num(late.get('p99'))} us, "
            f"max {_num(late.get('max'))} us"
        )
        lines.append(
            f"  cycle cost  p50 {_num(cost.get('p50'))} us, p99 {_num(cost.get('p99'))} us, "
            f"max {_num(cost.get('max'))} us"
        )
    hardware = status.get("hardware", {})
    if hardware:
        lines.append(f"hardware      {hardware.get('state', '?')}")
        for comp in hardware.get("components", []):
            lines.append(
                f"  {comp.get('name', '?'):<11} {comp.get('kind', '?')}, "
                f"{comp.get('state', '?')}, joints {', '.join(comp.get('joints', []))}, "
                f"safe action {comp.get('safe_action', '?')}"
            )
            counters = comp.get("counters") or {}
            if counters:
                lines.append(
                    "    counters  " + ", ".join(f"{k} {v}" for k, v in counters.items())
                )
            if comp.get("last_fault"):
                lines.append(f"    last fault  {comp['last_fault']}")
    flight = status.get("flight_recorder") or {}
    if flight:
        if not flight.get("enabled"):
            lines.append("flight rec    off")
        else:
            rate = flight.get("cycle_rate_hz")
            every = f"every cycle ({_num(rate, ' Hz')})" if rate else "published states"
            lines.append(
                f"flight rec    last {_num(flight.get('seconds'), ' s')} of {every}, "
                f"lost cycles {_num(flight.get('lost_cycles'))}, write errors "
                f"{_num(flight.get('errors'))}; last bag {flight.get('last_file') or '-'}"
            )
    zenoh = status.get("zenoh") or {}
    if zenoh:
        lines.append(
            f"zenoh         {zenoh.get('prefix', '?')}: queries {_num(zenoh.get('queries'))}, "
            f"busy {_num(zenoh.get('busy'))}, unauthorized {_num(zenoh.get('unauthorized'))}, "
            f"published {_num(zenoh.get('published'))}, "
            f"dropped {_num(zenoh.get('dropped'))}, lost {_num(zenoh.get('lost'))}"
        )
    if server:
        clients = server.get("clients", [])
        lines.append(
            f"clients       {len(clients)} connected (max {_num(server.get('max_clients'))} "
            f"+{_num(server.get('reserved_clients'))} reserved), "
            f"{_num(server.get('connections_total'))} since start"
        )
    lines.append("(jtc-hw status --json: the full reply)")
    return lines


def cmd_status(args: argparse.Namespace) -> int:
    """``jtc-hw status [--json]``."""
    from .cli import _connect

    with _connect(args) as client:
        reply = client.get_status()
    if args.json:
        print(json.dumps({k: v for k, v in reply.items() if k not in ("id", "ok")}, indent=2,
                         default=str))
        return 0
    print("\n".join(status_lines(reply)))
    return 0
