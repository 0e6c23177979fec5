"""``jtc-hw state`` and ``jtc-hw query``: what the controller does now, and will T seconds on.

``state`` shows the controller state stream (desired, actual, error per joint). The loop sends
no state while the controller is stopped by a hardware fault (the hardware is not read then),
so ``state`` asks ``get_status`` whenever the stream is silent for a moment and shows the fault
and the position being held instead of waiting out its timeout; ``--watch`` carries on and
returns to the table once the robot is re-armed. ``--json`` prints one JSON object per line
(NDJSON): the daemon's ``state`` events as sent (docs/protocol.md), and while faulted
``{"event": "fault", "fault": ..., "joint_names": ..., "held": ...}`` lines.

``query`` asks for the desired state T seconds from now (upstream's ``query_state``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime
from typing import Any

from .common import EXIT_OK, client_options, connect, fmt

__all__ = ["add_parsers", "cmd_query", "cmd_state", "print_state", "wall_time"]

QUIET_PROBE_S = 0.5
"""A state stream silent this long makes ``state`` look at the status for a fault. Longer
than any sensible ``state_publish_rate`` period (upstream's default is 50 Hz)."""

FAULT_REFRESH_S = 1.0
"""While faulted, ``state --watch`` shows the status again this often (the stream is silent)."""


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
            f"{name:<14} {fmt([d['positions'][i]])} {fmt([a['positions'][i]])} "
            f"{fmt([e['positions'][i]])} {fmt([vel])}"
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
        print(f"{name:<14} {fmt([value])} {'-':>9}")
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
    tty = sys.stdout.isatty() and not args.json
    with connect(args) as client:
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


def cmd_query(args: argparse.Namespace) -> int:
    with connect(args) as client:
        reply = client.query_state(in_s=args.t)
        names = client.joint_names
        print(f"desired state in {args.t:g} s:")
        where = reply.get("where")
        if where == "after_end":
            print("  success: false (at or after the last point; these are its values)")
        elif where == "before_start":
            print("  success: false (before the trajectory's start; this is the measured state)")
        for key in ("positions", "velocities", "accelerations", "effort"):
            values = reply.get(key) or reply.get("desired", {}).get(key)
            print(f"  {key:<13} {fmt(values)}")
        print(f"  joints        {' '.join(f'{n:>9}' for n in names)}")
        return EXIT_OK


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "state",
        help="print the controller state (once, or --watch)",
        description=(
            "Print the controller state: per joint desired, actual and error positions and "
            "the velocity; the header shows this machine's wall time. During a hardware fault "
            "(no state is published) it shows the fault and the held position instead."
        ),
    )
    p.add_argument("--watch", action="store_true", help="keep printing at state_publish_rate")
    p.add_argument(
        "--json",
        action="store_true",
        help="print the daemon's state messages as NDJSON (one JSON object per line)",
    )
    client_options(p, cmd_state)

    p = sub.add_parser(
        "query",
        help="desired state T seconds from now (query_state)",
        description=(
            "Ask the controller for the desired state T seconds from now, as upstream's "
            "query_state service: positions, velocities, accelerations, effort per joint."
        ),
    )
    p.add_argument("t", type=float, metavar="T", help="seconds from now")
    client_options(p, cmd_query)
