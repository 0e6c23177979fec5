"""``jtc-hw emulate``: emulated motors speaking the real wire protocol, to test without a robot.

Each bus's emulator is a driver module with its own ``main(argv)`` (and ``--help``); this
command only picks it. The module is imported by name when the command runs (start-up time:
the drivers and their SDKs are not loaded by the other commands).
"""

from __future__ import annotations

import argparse
import importlib
from typing import Any

__all__ = ["add_parsers", "cmd_emulate"]

EMULATE_EXIT_HELP = "Exit status: 0 stopped by Ctrl-C/SIGTERM; 2 bad emulator options."

_EMULATORS = {
    "dynamixel": "jtc_hw.drivers.dynamixel.emulator",
    "feetech": "jtc_hw.drivers.feetech.emulator",
    "can": "jtc_hw.drivers.can.emulator",
}


def cmd_emulate(args: argparse.Namespace) -> int:
    module = importlib.import_module(_EMULATORS[args.bus])
    rest = list(args.args)
    if rest[:1] == ["--"]:
        rest = rest[1:]
    return int(module.main(rest))


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "emulate",
        help="run an emulated motor bus (Dynamixel or Feetech on a pty, CAN motors) to test "
        "without a robot",
        description=(
            "Run emulated motors speaking the real wire protocol, until Ctrl-C. "
            "'jtc-hw emulate dynamixel --ids 1-6 --model XM430-W350' opens a pseudo-terminal "
            "and prints its path: put it as the 'port' of a dynamixel hardware component. "
            "'jtc-hw emulate feetech --ids 1-6 --model STS3215' serves Feetech STS/SCS "
            "servos (LeRobot's SO-101 arm) the same way, at 1 Mbit/s unless --baud says "
            "otherwise. "
            "'jtc-hw emulate can --protocol mit --ids 1-6' serves MIT-mode motors (or "
            "--protocol cia402 drives) and prints how python-can connects to them. "
            "'jtc-hw emulate dynamixel --help' lists each emulator's options."
        ),
        epilog=EMULATE_EXIT_HELP,
    )
    p.add_argument("bus", choices=sorted(_EMULATORS), help="which bus to emulate")
    p.add_argument("args", nargs=argparse.REMAINDER, help="the emulator's options (see its --help)")
    p.set_defaults(func=cmd_emulate)
