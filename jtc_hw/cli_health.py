"""``jtc-hw hardware``: the motors' health, per component and motor, from the daemon's status.

The loop process puts each component's :meth:`~jtc_hw.hardware.HardwareInterface.health` in
the status it publishes at a low rate (2 Hz); the ``status`` op returns the latest. This module
only formats it: a table per component (model, firmware, mode, torque, temperature, voltage,
errors, last fault; the bus counters in the component's heading), then the warnings that the
limits ``temperature_warn_c`` and ``voltage_range`` raise. ``--json`` prints the health as it
came, one object with a ``components`` list.

A motor whose readings are stale (``stale``: its newest reply is older than the driver's
feedback timeout, e.g. after a bus loss) has them reported as unknown (``None``, their keys
listed in ``unknown``); they are printed as ``? (2.3 s old)`` with the age of that reply
(``age_s``), never as the last value heard. A reading the kind does not report is ``-``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Mapping, Sequence
from typing import Any

__all__ = ["add_hardware_parser", "format_hardware", "hardware_report"]

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


def add_hardware_parser(
    sub: Any,
    client_options: Callable[[argparse.ArgumentParser], None],
    connect: Callable[[argparse.Namespace], Any],
) -> None:
    """Register ``jtc-hw hardware`` on the CLI's subparsers.

    Args:
        sub: the ``add_subparsers()`` object of ``jtc-hw``.
        client_options: adds ``--socket``, ``--config``, ``--timeout``.
        connect: opens a client from those options (the CLI's, which maps "no daemon" to
            exit code 3).
    """
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
    client_options(p)
    p.add_argument("--json", action="store_true",
                   help="print the report as one JSON object instead of tables")

    def cmd_hardware(args: argparse.Namespace) -> int:
        with connect(args) as client:
            report = hardware_report(client.get_status())
        if args.json:
            print(json.dumps(report, default=str))
        else:
            print(format_hardware(report))
        return 0

    p.set_defaults(func=cmd_hardware)
