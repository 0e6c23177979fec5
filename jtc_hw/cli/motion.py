"""``jtc-hw stop``, ``rearm``, ``speed``, ``pause`` and ``resume``: the commands that change how
the robot moves, without a goal of their own.

``stop`` holds where the joints are (and gets through a daemon whose client slots are all
taken: it sends no hello); ``rearm`` leaves a hardware fault; ``speed``, ``pause`` and
``resume`` set the speed scaling factor, which ramps within the joints' limits.
"""

from __future__ import annotations

import argparse
from typing import Any

from .common import EXIT_OK, client_options, connect

__all__ = ["add_parsers", "cmd_pause", "cmd_rearm", "cmd_resume", "cmd_speed", "cmd_stop"]


def cmd_stop(args: argparse.Namespace) -> int:
    # No hello: "stop" must be the first request to be served by a daemon whose client slots
    # are all taken.
    with connect(args, hello=False) as client:
        reply = client.stop(timeout_s=args.timeout)
        if not reply.get("stopped"):
            print(reply.get("message") or "nothing to stop")
            return EXIT_OK
        print("stopped: holding the measured position (an active goal ends canceled)")
        return EXIT_OK


def cmd_rearm(args: argparse.Namespace) -> int:
    with connect(args) as client:
        controller = client.get_status().get("controller", {})
        # After a failed re-arm, "fault" says why that one failed; the fault being recovered
        # from is "fault_cause" (a daemon before issue 22 sends only "fault").
        fault = controller.get("fault_cause") or controller.get("fault")
        reply = client.rearm(timeout_s=args.timeout)
        if not reply.get("rearmed"):
            print("nothing to re-arm: the controller is running and no fault is latched")
            return EXIT_OK
        print(f"re-armed{f' after: {fault}' if fault else ''}; holding the measured position")
        return EXIT_OK


def _set_scaling(args: argparse.Namespace, what: str, **request: Any) -> int:
    """Send ``set_speed_scaling(**request)`` and print the target (and the ramp) after ``what``."""
    with connect(args) as client:
        reply = client.set_speed_scaling(timeout_s=args.timeout, **request)
        factor, target = reply["factor"], reply["target"]
        ramp = "" if factor == target else f" (ramping from {factor:g})"
        print(f"{what}: speed scaling {target:g}{ramp}")
        return EXIT_OK


def cmd_speed(args: argparse.Namespace) -> int:
    return _set_scaling(args, "speed set", factor=args.factor)


def cmd_pause(args: argparse.Namespace) -> int:
    return _set_scaling(args, "paused ('jtc-hw resume' carries on)", factor=0.0)


def cmd_resume(args: argparse.Namespace) -> int:
    return _set_scaling(args, "resumed", resume=True)


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "stop",
        help="stop any motion and hold where the joints are",
        description=(
            "Stop any motion: the executing goal ends canceled (its client gets the result), "
            "a topic trajectory stops, and the controller holds the measured position. The "
            "daemon serves a stop even when every client slot is taken (a connection over the "
            "limit may send one stop). A stopped or faulted robot: nothing to do, exit 0."
        ),
    )
    client_options(p, cmd_stop)

    p = sub.add_parser(
        "rearm",
        help="leave a hardware fault: reboot / reset the devices and hold where they are",
        description=(
            "After a hardware fault (a motor that stopped answering or reported an error) the "
            "controller stays stopped, in the configured safe state, until a client asks to "
            "re-arm. The daemon then re-opens the devices, reboots faulted servos / resets "
            "drive faults, reads the joints and holds exactly there (no jump). Check the cause "
            "first: 'jtc-hw status' shows the fault."
        ),
    )
    client_options(p, cmd_rearm)

    scaling_help = (
        "The trajectory time of the running goal (and of every later one) advances at the "
        "factor times the clock: 1 is as planned, 0.5 half speed, 0 paused; the path is the "
        "same, only slower. A change ramps rather than steps, as fast as the joints' "
        "acceleration limits allow (joints without one: over speed_scaling.ramp_time "
        "seconds per unit of factor), on every command interface. Goal time and tolerances "
        "are judged in the slowed time, so a paused goal neither fails nor finishes; its "
        "result comes once it is resumed and done."
    )
    p = sub.add_parser(
        "speed",
        help="set the speed scaling factor (1: as planned, 0.5: half speed, 0: pause)",
        description=f"Set the speed scaling factor. {scaling_help}",
    )
    p.add_argument(
        "factor",
        type=float,
        help="the factor, in [0, 1] (up to speed_scaling.max_scaling_factor where the "
        "configuration raises it: above 1 speeds up)",
    )
    client_options(p, cmd_speed)

    p = sub.add_parser(
        "pause",
        help="bring the motion to rest along its path (speed scaling 0)",
        description=(
            "Pause: ramp the speed scaling factor to 0, so the joints decelerate to rest on "
            f"the path. 'jtc-hw resume' carries on at the factor before the pause. {scaling_help}"
        ),
    )
    client_options(p, cmd_pause)

    p = sub.add_parser(
        "resume",
        help="carry on after 'jtc-hw pause' (the speed scaling factor before it)",
        description=(
            "Resume: ramp the speed scaling factor back to the last non-zero factor set (by "
            "'jtc-hw speed', else the configured speed_scaling.initial_scaling_factor, or 1). "
            f"{scaling_help}"
        ),
    )
    client_options(p, cmd_resume)
