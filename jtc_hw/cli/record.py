"""``jtc-hw record`` and ``jtc-hw plot``: a running daemon into a ROS 2 bag, and a bag into a plot.

``record`` is a client of a running daemon (docs/recording.md): it subscribes to the ``state``
stream with every accepted command (``command`` events) and every goal result, hardware fault
and re-arm (``record`` events), asks ``get_status`` once a second for ``/diagnostics``, and
writes them with ``BagRecorder`` until ``--duration`` seconds of daemon time have passed or
Ctrl-C/SIGTERM, always finishing the bag so that it opens; a failed write (a full disk) ends it
with what it holds, exit status 4.

Both need optional extras (``jtc_hw[record]``: rosbags; ``jtc_hw[plot]``: matplotlib), which
:mod:`jtc_hw.rec` imports only when a bag is opened or drawn.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import time
from pathlib import Path
from types import FrameType
from typing import Any

from ..api.client import Client
from ..api.events import trajectory_from_json
from ..config.controller import DEFAULT_CONTROLLER_NAME
from ..rec.bag import BagRecorder, RecordingFailed, tolerances_from_constraints
from ..rec.continuous import DIAGNOSTICS_PERIOD_NS
from ..rec.plot import plot_bag
from .common import EXIT_BAD_INPUT, EXIT_OK, EXIT_WRITE_FAILED, client_options, connect

__all__ = ["add_parsers", "cmd_plot", "cmd_record"]

DRAIN_TIMEOUT_S = 2.0
"""After Ctrl-C: how long the recorder waits for the daemon's reply that says it has every
message sent before."""


def _terminate(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def cmd_record(args: argparse.Namespace) -> int:
    """``jtc-hw record``: see the module docstring.

    Raises:
        RecordingUnavailable: rosbags is not installed (the CLI prints its hint, exit 2).
    """
    if args.duration is not None and not args.duration > 0:
        print(f"error: --duration must be a positive number of seconds, not {args.duration}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    # SIGINT too, explicitly: Python turns it into KeyboardInterrupt only when it was not
    # ignored at start, and a shell starts background jobs (`jtc-hw record out &` in a script)
    # with SIGINT ignored; Ctrl-C or `kill -INT` must still finish the bag.
    previous = {sig: signal.signal(sig, _terminate) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        with connect(args) as client:
            before = time.time_ns()
            now_ns = int(client.hello()["now_ns"])
            offset = (before + time.time_ns()) // 2 - now_ns
            constraints = client.get_config()["controller"].get("constraints", {})
            try:
                recorder = BagRecorder(args.out, args.controller_name, offset,
                                       tolerances_from_constraints(constraints))
            except FileExistsError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return EXIT_BAD_INPUT
            except (RecordingFailed, OSError) as exc:
                print(f"error: cannot create the bag {args.out}: {exc}", file=sys.stderr)
                return EXIT_WRITE_FAILED
            try:
                try:
                    _record(client, recorder, args)
                finally:
                    recorder.close()
            except RecordingFailed as exc:
                print(f"error: {exc}", file=sys.stderr)
                return EXIT_WRITE_FAILED
            if recorder.failure is not None:  # failed while draining after Ctrl-C
                print(f"error: {recorder.failure}", file=sys.stderr)
                return EXIT_WRITE_FAILED
            counts = ", ".join(f"{topic}: {n}" for topic, n in sorted(recorder.counts.items()))
            print(f"wrote {recorder.path} ({counts})", flush=True)
            return EXIT_OK
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _record(client: Client, recorder: BagRecorder, args: argparse.Namespace) -> None:
    subscription = client.subscribe_state(maxlen=1_000_000, commands=True)
    print(f"recording to {recorder.path}", flush=True)
    end_ns: int | None = None
    next_diagnostics_ns: int | None = None

    def take(message: dict[str, Any]) -> bool:
        """Write one message; False once past ``--duration``."""
        nonlocal end_ns, next_diagnostics_ns
        if message.get("event") == "record":  # a result, fault or re-arm
            if end_ns is None or int(message["record"]["time_ns"]) <= end_ns:
                recorder.goal_event(message["record"])
            return True
        if message.get("event") == "command":
            # Accepted before the end (states lag the acceptance by a plan's lead).
            if end_ns is None or int(message["time_ns"]) <= end_ns:
                recorder.command(trajectory_from_json(message["trajectory"]),
                                 int(message["time_ns"]))
            return True
        t = int(message["time_ns"])
        if end_ns is None and args.duration is not None:
            end_ns = t + round(args.duration * 1e9)
        if end_ns is not None and t > end_ns:
            return False
        recorder.state(message)
        if next_diagnostics_ns is None:
            next_diagnostics_ns = t
        if t >= next_diagnostics_ns:
            recorder.diagnostics(client.get_status(), t)
            # On a 1 s grid from the first state: a late state does not shift the next.
            while next_diagnostics_ns <= t:
                next_diagnostics_ns += DIAGNOSTICS_PERIOD_NS
        return True

    try:
        while take(subscription.get(timeout_s=args.timeout)):
            pass
    except KeyboardInterrupt:
        # What the daemon had sent before the interrupt is written too: its reply to a request
        # comes after every event it queued before on this connection, so once get_status has
        # answered, all of it is in the subscription's buffer.
        with contextlib.suppress(Exception, KeyboardInterrupt):  # buffer empty, or gone: done
            client.get_status(timeout_s=DRAIN_TIMEOUT_S)
            while take(subscription.get(timeout_s=0)):
                pass
    finally:
        # The connection may be gone; the bag is still finished.
        with contextlib.suppress(Exception):
            subscription.close()


def cmd_plot(args: argparse.Namespace) -> int:
    """``jtc-hw plot``: write the figure and print its path.

    Raises:
        PlotUnavailable: matplotlib or rosbags is not installed (exit 2 with the hint).
    """
    out = Path(args.out) if args.out else Path(args.bag) / "plot.png"
    plot_bag(args.bag, out, joints=args.joints, controller=args.controller_name)
    print(f"wrote {out}")
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "record",
        help="record the robot's state into a ROS 2 bag (rosbag2, MCAP storage)",
        description=(
            "Record /joint_states, /<controller>/controller_state, /<controller>/joint_trajectory "
            "(every accepted command), /<controller>/goal_events and /diagnostics from a running "
            "daemon into the rosbag2 directory OUT (MCAP storage; opens in ros2 bag info/play, "
            "Foxglove, PlotJuggler). Stops after --duration seconds, or on Ctrl-C. Needs pip "
            "install 'jtc_hw[record]'. Exit status: 0 recorded, 2 bad input (OUT exists, "
            "library missing, a socket you may not connect to: permission denied), 3 no "
            "daemon, 4 writing the bag failed (a full disk: the bag is "
            "closed with the rows written before, readable)."
        ),
    )
    p.add_argument("out", metavar="OUT", help="bag directory to create (must not exist)")
    p.add_argument("--duration", type=float, default=None,
                   help="seconds to record (daemon clock); default: until Ctrl-C")
    p.add_argument("--controller-name", default=DEFAULT_CONTROLLER_NAME,
                   help=f"namespace of the controller's topics (default {DEFAULT_CONTROLLER_NAME})")
    client_options(p, cmd_record)

    p = sub.add_parser(
        "plot",
        help="plot a recording: desired vs actual per joint",
        description=(
            "Plot a bag written by 'jtc-hw record': per joint, the reference (desired) and "
            "feedback (actual) position, and velocity where recorded, over time, with the goal "
            "events marked. Needs pip install 'jtc_hw[plot]'. Exit status: 0 written; 2 bad input."
        ),
    )
    p.add_argument("bag", metavar="BAG", help="the bag directory")
    p.add_argument("--joints", nargs="+", help="joints to plot (default: all)")
    p.add_argument("--out", help="image file to write (default: BAG/plot.png)")
    p.add_argument("--controller-name", default=DEFAULT_CONTROLLER_NAME,
                   help=f"namespace of the controller's topics (default {DEFAULT_CONTROLLER_NAME})")
    p.set_defaults(func=cmd_plot)
