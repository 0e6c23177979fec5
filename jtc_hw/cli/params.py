"""``jtc-hw param``: get or change the controller's parameters while the daemon runs.

Names are upstream's, dotted (``gains.j1.p``); a VALUE on the command line is YAML. The daemon
checks a change as the configuration file is checked and says when it takes effect.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from ..api.framing import BAD_REQUEST, RequestError
from ..config.reading import load_yaml
from ..errors import ConfigurationError
from .common import EXIT_BAD_INPUT, EXIT_OK, client_options, connect, print_warnings

__all__ = ["add_parsers", "cmd_param"]

_EFFECT_HINTS = {
    "next activation": (
        "the daemon activates the controller at start and on 'jtc-hw rearm' after a fault; "
        "a restart reads the configuration file again, so write the value there too"
    ),
}


def _parameter_value(text: str, name: str) -> Any:
    """A VALUE given on the command line, read as YAML (``12``, ``0.5``, ``true``, ``[a, b]``).

    Raises:
        ConfigurationError: not YAML, or a mapping (parameters are scalars or lists).
    """
    value = load_yaml(text, name)
    if isinstance(value, dict):
        raise ConfigurationError(
            f"expected a scalar or a list (YAML), got a mapping {text!r}; name each parameter "
            "with its full dotted name instead, e.g. gains.<joint>.p",
            name,
            text,
        )
    return value


def cmd_param(args: argparse.Namespace) -> int:
    if args.action == "set":
        if not args.items or len(args.items) % 2:
            raise ConfigurationError(
                "give NAME VALUE pairs, e.g. 'jtc-hw param set gains.j1.p 12'", "param set"
            )
        changes = {
            name: _parameter_value(value, name)
            for name, value in zip(args.items[::2], args.items[1::2], strict=True)
        }
    with connect(args) as client:
        try:
            if args.action == "get":
                reply = client.get_parameters(args.items or None)
            else:
                reply = client.set_parameters(changes)
        except RequestError as exc:
            if exc.code != BAD_REQUEST:
                raise
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
    values: dict[str, Any] = reply["parameters"]
    if args.json:
        print(json.dumps({k: reply[k] for k in reply if k not in ("id", "ok")}, indent=2))
        return EXIT_OK
    width = max(len(name) for name in values)
    if args.action == "get":
        fixed = set(reply.get("read_only", ()))
        for name, value in values.items():
            note = "   (read-only)" if name in fixed else ""
            print(f"{name:<{width}}  {json.dumps(value)}{note}")
        return EXIT_OK
    effects: dict[str, str] = reply.get("takes_effect", {})
    for name, value in values.items():
        effect = effects.get(name, "")
        print(f"{name:<{width}}  {json.dumps(value)}   takes effect: {effect}")
        if effect in _EFFECT_HINTS:
            print(f"{'':<{width}}  ({_EFFECT_HINTS[effect]})")
    print_warnings(reply.get("warnings", ()))
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "param",
        help="get or change controller parameters while the daemon runs",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="""\
Get or change the controller's parameters while the daemon runs, as 'ros2 param' does for
upstream's controller. Names are upstream's, dotted: cmd_timeout, constraints.goal_time,
constraints.<joint>.trajectory, constraints.<joint>.goal, gains.<joint>.p, ...

  jtc-hw param get                     every parameter and its value
  jtc-hw param get gains.j1.p          one (or several) of them
  jtc-hw param set gains.j1.p 12       change one; VALUE is YAML: 12, 0.5, true, [a, b]
  jtc-hw param set constraints.goal_time 1 cmd_timeout 2
                                       several at once (all or nothing)

A change is checked as the configuration file is (same messages) and applied with upstream's
timing: gains and state_publish_rate from the next control cycle; default tolerances
(constraints.*) and the goal checks (allow_*) from the next goal or trajectory, the running
one keeping its own; cmd_timeout, start_with_holding and
set_last_command_interface_value_as_state_on_activation at the next activation (a re-arm).
Read-only parameters (joints, interfaces, update_rate, interpolation_method,
action_monitor_rate, open_loop_control, the wraparound flags) are refused: change the file
and restart. A change lasts until the daemon stops: write it in the
configuration file to keep it.

Exit status: 0 done; 2 unknown or read-only parameter, or a bad value, or a socket you
may not connect to (permission denied) or not served by a daemon you trust; 3 no daemon.""",
    )
    p.add_argument("action", choices=("get", "set"), help="read, or change")
    p.add_argument(
        "items",
        nargs="*",
        metavar="NAME [VALUE]",
        help="get: parameter names (default: all); set: NAME VALUE pairs",
    )
    p.add_argument("--json", action="store_true", help="print the daemon's reply as JSON")
    client_options(p, cmd_param)
