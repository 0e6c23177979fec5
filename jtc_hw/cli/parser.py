"""``jtc-hw``'s parser, and the exit status of what a command raises.

The command groups add their subcommands (``add_parsers``) in the order ``jtc-hw --help``
lists them; :func:`parse_and_run` runs the one asked for and maps what it raises to the exit
statuses of :mod:`jtc_hw.cli` (:class:`~jtc_hw.cli.common.NoDaemon`: 3; bad input, a refused
request: 2).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from .. import __version__
from ..daemon.logs import VERBOSE_ENV
from ..errors import ConfigurationError, GoalRejected, JtcHwError
from .common import CLIENT_EXIT_HELP, EXIT_BAD_INPUT, EXIT_NO_DAEMON, EXIT_OK, NoDaemon

__all__ = ["DESCRIPTION", "build_parser", "parse_and_run"]

DESCRIPTION = """\
Drive robot joints with ROS 2 joint_trajectory_controller semantics, without ROS.

  jtc-hw demo                  start a daemon on simulated joints, run a goal, show it
  jtc-hw check robot.yaml      validate a configuration and explain it
  jtc-hw run robot.yaml        run the daemon (under systemd: see config/jtc-hw.service)
  jtc-hw send goal.yaml        send a trajectory to a running daemon and watch it
  jtc-hw state --watch         live table of the controller state
  jtc-hw stop                  stop any motion and hold (gets through a daemon with every
                               client slot taken)
  jtc-hw rearm                 leave a hardware fault, holding where the joints are
  jtc-hw speed 0.5             run the trajectory at half speed (ramps, within the limits)
  jtc-hw pause / jtc-hw resume smoothly stop along the path / carry on at the speed before
  jtc-hw param set gains.j1.p 12
                               change a controller parameter while the daemon runs
                               ('jtc-hw param get' lists them)
  jtc-hw emulate dynamixel     emulated servos on a pseudo-terminal (no robot needed)
  jtc-hw calibrate feetech robot.yaml --ids 1-6
                               each joint's zero and range by hand (LeRobot's SO-101)
  jtc-hw fleet --watch         the daemons on Zenoh, one line each (docs/zenoh.md)

Client commands find the daemon's socket from --socket, else --config's daemon.socket,
else $JTC_HW_SOCKET, else the default path (see 'jtc-hw check' for a config's path). A socket
is used only if the process behind it runs as you, root, or a member of --config's
daemon.socket_group; at the default path the file must be yours or root's too. With --tcp
[HOST:PORT] they reach the TCP endpoint, with --config's token (or $JTC_HW_TOKEN).
With --zenoh PREFIX (and --zenoh-config FILE) they reach the daemon at that Zenoh prefix;
commands there need its token (--zenoh-token-file FILE or $JTC_HW_ZENOH_TOKEN).
"""


GROUPS: dict[str, tuple[str, ...]] = {
    "run": ("run", "check"),
    "demo": ("demo",),
    "goals": ("send", "cancel"),
    "state": ("state", "query"),
    "motion": ("stop", "rearm", "speed", "pause", "resume"),
    "params": ("param",),
    "emulate": ("emulate",),
    "calibrate": ("calibrate",),
    "status": ("status", "hardware"),
    "record": ("record", "plot"),
    "fleet": ("fleet",),
}
"""The command group modules in the order ``--help`` lists them, each with its subcommands."""

def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """``jtc-hw``'s parser: the subcommands in the order ``--help`` lists them.

    With ``command`` (a subcommand's name), only the group that holds it is imported and added:
    a command starts without importing every other command's modules (the daemon, the
    recorders, plotting). Its parsing and its ``--help`` are the same as in the whole parser.
    """
    parser = argparse.ArgumentParser(
        prog="jtc-hw",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"jtc-hw {__version__}")
    parser.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        help="keep the INFO logs of third-party libraries (canopen, python-can)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for group, commands in GROUPS.items():
        if command is None or command in commands:
            importlib.import_module(f"{__package__}.{group}").add_parsers(sub)
    for command in sub.choices.values():
        # Every subcommand's --help states its exit statuses (unless its description does);
        # a command group sets its own where they are not the client commands' usual ones.
        if "Exit status" not in (command.description or "") and command.epilog is None:
            command.epilog = CLIENT_EXIT_HELP
    return parser


def parse_and_run(argv: Sequence[str] | None = None) -> int:
    """Run the command of ``argv`` (default: ``sys.argv[1:]``); its exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_command_of(argv))
    args, extra = parser.parse_known_args(argv)
    if args.verbose:
        os.environ[VERBOSE_ENV] = "1"  # inherited by the daemon and emulators we start
    if extra and args.command == "param" and not any(e.startswith("--") for e in extra):
        args.items.extend(extra)  # argparse ends a positional list at the first option
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        return int(args.func(args))
    except ConfigurationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except GoalRejected as exc:
        code = getattr(exc, "error_code", -1)
        print(f"rejected (error_code {code}): {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError:
        # The reader went away (jtc-hw state | head): not an error. Point stdout at
        # /dev/null so the interpreter's final flush does not raise again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    except (NoDaemon, JtcHwError, TimeoutError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        # The daemon answered and refused the request (bad request, not active, busy...): bad
        # input. Else nobody answers, the connection was lost, or no reply in time.
        return EXIT_BAD_INPUT if _refused(exc) else EXIT_NO_DAEMON
    except KeyboardInterrupt:
        return 130


def _command_of(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names (its first word that is not an option), if it is one;
    ``None`` for ``jtc-hw --help``, a mistyped command and the like (the whole parser)."""
    for word in argv:
        if word == "--":
            return None
        if not word.startswith("-"):
            return word if any(word in commands for commands in GROUPS.values()) else None
    return None


def _refused(exc: BaseException) -> bool:
    """Whether ``exc`` is the daemon's refusal (:class:`~jtc_hw.api.framing.RequestError`)."""
    # Imported here, once the command has failed: a command that never reached a daemon
    # (check, emulate) does not load the client's modules at start.
    from ..api.framing import RequestError

    return isinstance(exc, RequestError)
