"""``jtc-hw status`` and ``jtc-hw hardware``: the daemon's status reply, readable or as JSON.

``status`` prints the reply as a table (controller and any fault, loop timing, hardware
components, flight recorder, Zenoh, clients); ``--json`` prints the reply itself (without the
protocol's ``id``/``ok`` wrapper).

``hardware`` prints the motors' health: each component's
:meth:`~jtc_hw.hardware.HardwareInterface.health`, which the loop process puts in the status it
publishes at a low rate (2 Hz). This module only formats it: a table per component (the columns
of ``_COLUMNS``, the bus counters in its heading), then the warnings that the limits
``temperature_warn_c`` and ``voltage_range`` raise; ``--json`` prints it as it came.

A motor whose readings are stale (``stale``: its newest reply is older than the driver's
feedback timeout, e.g. after a bus loss) has them reported as unknown (``None``, their keys
listed in ``unknown``); they are printed as ``? (2.3 s old)`` with the age of that reply
(``age_s``), never as the last value heard. A reading the kind does not report is ``-``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping, Sequence
from typing import Any

from .common import client_options, connect

__all__ = ["add_parsers", "cmd_hardware", "cmd_status", "format_hardware", "hardware_report",
           "status_lines"]


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
        for label, stats in (("lateness   ", late), ("period work", cost)):
            lines.append(
                f"  {label}  p50 {_num(stats.get('p50'))} us, p99 {_num(stats.get('p99'))} us, "
                f"max {_num(stats.get('max'))} us"
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
    ros2 = status.get("ros2") or {}
    if ros2:
        lines.append(
            f"ros2          node {ros2.get('node', '?')} in domain {_num(ros2.get('domain_id'))}: "
            f"goals accepted {_num(ros2.get('goals_accepted', 0))}, rejected "
            f"{_num(ros2.get('goals_rejected', 0))}, running {_num(ros2.get('goals_running'))}; "
            f"samples dropped {_num(ros2.get('joint_trajectory_dropped', 0))}; "
            f"published {_num(ros2.get('published', 0))}, dropped {_num(ros2.get('dropped'))}"
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
    with connect(args) as client:
        reply = client.get_status()
    if args.json:
        print(json.dumps({k: v for k, v in reply.items() if k not in ("id", "ok")}, indent=2,
                         default=str))
    else:
        print("\n".join(status_lines(reply)))
    return 0

# -- hardware -------------------------------------------------------------------------------


_COLUMNS = (
    ("motor", "motor"), ("joint", "joint"), ("model", "model"), ("firmware", "fw"),
    ("mode", "mode"), ("torque_enabled", "torque"), ("temperature_c", "temp degC"),
    ("voltage_v", "supply V"), ("errors", "errors"), ("last_fault", "last fault"),
)


def hardware_report(status: Mapping[str, Any]) -> dict[str, Any]:
    """The health part of a ``status`` reply: ``components`` (name, kind, state, last_fault,
    motors, bus, warnings each) and ``fault`` (the controller's, or ``None``)."""
    hardware = status.get("hardware") or {}
    components = []
    for comp in hardware.get("components", []):
        health = comp.get("health") or {}
        components.append({
            "name": comp.get("name"),
            "kind": comp.get("kind"),
            "state": comp.get("state"),
            "last_fault": comp.get("last_fault"),
            "motors": health.get("motors", []),
            "bus": health.get("bus"),
            "warnings": health.get("warnings", []),
        })
    fault = (status.get("controller") or {}).get("fault")
    return {"components": components, "fault": fault}


def _cell(key: str, value: Any, motor: Mapping[str, Any]) -> str:
    if value is None:
        if key in (motor.get("unknown") or ()):
            age = motor.get("age_s")
            return "? (never heard)" if age is None else f"? ({age:.1f} s old)"
        return "-"
    if key == "torque_enabled":
        return "on" if value else "off"
    if key == "errors":
        return "; ".join(value) if value else "none"
    if key == "voltage_v":
        return f"{value:.1f}"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _table(rows: Sequence[Sequence[str]]) -> list[str]:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  " + "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip()
            for row in rows]


def format_hardware(report: Mapping[str, Any]) -> str:
    """The report of :func:`hardware_report` as text tables, one per component."""
    lines: list[str] = []
    if not report["components"]:
        lines.append("no hardware status yet (the control loop reports it twice a second; "
                     "ask again)")
    for comp in report["components"]:
        heading = f"{comp['name']} ({comp['kind']}, {comp['state']})"
        bus = comp["bus"]
        if bus:
            count = {key: "-" if bus.get(key) is None else bus[key]
                     for key in ("transactions", "timeouts", "crc_errors", "retries")}
            heading += (f"  bus: {count['transactions']} transactions, "
                        f"{count['timeouts']} timeouts, {count['crc_errors']} CRC "
                        f"errors, {count['retries']} retries")
        lines.append(heading)
        rows = [[title for _, title in _COLUMNS]]
        rows += [[_cell(key, motor.get(key), motor) for key, _ in _COLUMNS]
                 for motor in comp["motors"]]
        lines += _table(rows)
        if comp["last_fault"]:
            lines.append(f"  last fault: {comp['last_fault']}")
        for warning in comp["warnings"]:
            lines.append(f"  WARNING: {warning}")
        lines.append("")
    if report["fault"]:
        lines.append(f"controller fault: {report['fault']}")
    return "\n".join(lines).rstrip("\n")


def cmd_hardware(args: argparse.Namespace) -> int:
    with connect(args) as client:
        report = hardware_report(client.get_status())
    if args.json:
        print(json.dumps(report, default=str))
    else:
        print(format_hardware(report))
    return 0


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "status",
        help="loop statistics, hardware and controller status",
        description=(
            "Show the daemon's status as a table: controller (and any fault), loop timing, "
            "hardware components, clients."
        ),
    )
    p.add_argument("--json", action="store_true", help="print the daemon's full reply as JSON")
    client_options(p, cmd_status)

    p = sub.add_parser(
        "hardware",
        help="motor health per component and motor (temperature, voltage, errors, bus)",
        description=(
            "Print each hardware component's motors: model, firmware, mode, torque, "
            "temperature, supply voltage, errors and last fault, with the bus counters "
            "(transactions, timeouts, CRC errors, retries) and the warnings that the "
            "components' temperature_warn_c and voltage_range raise. The loop refreshes them "
            "at a low rate (status: 2 Hz; each driver reads its motors every health period). "
            "Exit status: 0 printed; 2 bad input (an unreadable --config or --zenoh-config), or "
            "a socket you may not connect to (permission denied) or not served by a daemon you "
            "trust; 3 no daemon answers."
        ),
    )
    client_options(p, cmd_hardware)
    p.add_argument("--json", action="store_true",
                   help="print the report as one JSON object instead of tables")
