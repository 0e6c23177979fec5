"""``jtc-hw send`` and ``jtc-hw cancel``: a trajectory file as a goal, watched to its result.

``send`` reads the file (:func:`load_goal_file`: YAML, JSON or CSV, in the protocol's form or
as ROS 2 prints it), sends it as a ``follow_joint_trajectory`` goal (or, with ``--topic``, on
the fire-and-forget topic interface), shows a progress bar and exits with the result: 0
succeeded, 1 aborted or canceled (Ctrl-C cancels it). ``cancel`` cancels the executing goal,
or the one named.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path
from typing import Any

from ..errors import ConfigurationError
from .common import EXIT_GOAL_FAILED, EXIT_OK, Progress, client_options, connect, goal_result

__all__ = ["EXIT_CODES_HELP", "add_parsers", "cmd_cancel", "cmd_send", "load_goal_file"]

EXIT_CODES_HELP = (
    "Exit status: 0 success; 1 the goal aborted or was canceled; 2 bad input, or the daemon "
    "answered and refused the request (rejected goal, bad request), or the socket is not "
    "served by a daemon you trust, or you may not connect to it (permission denied); 3 no "
    "daemon answers."
)
"""The exit statuses of ``send``, the client command that waits for a goal's result."""

CANCEL_EXIT_HELP = (
    "Exit status: 0 the cancel was requested, or no goal is executing; 1 that goal is not "
    "executing; 2 bad input, a socket you may not connect to (permission denied) or not "
    "served by a daemon you trust, or the daemon answered and refused the request; 3 no "
    "daemon answers."
)


def load_goal_file(path: str) -> dict[str, Any]:
    """Read a trajectory from YAML, JSON or CSV into the protocol's goal form.

    YAML/JSON: either a trajectory (``joint_names``, ``points``) or a goal wrapping one
    (``trajectory``, optional ``path_tolerance``, ``goal_tolerance``, ``goal_time_tolerance``),
    in the protocol's form or as ROS 2 prints them (:mod:`jtc_hw.api.goal_files`).
    CSV: a header ``time_from_start,<joint>,...`` (positions); columns may also be named
    ``<joint>.position``, ``<joint>.velocity``, ``<joint>.acceleration``, ``<joint>.effort``.

    Raises:
        ConfigurationError: unreadable file or malformed content, naming the line/field.
    """
    # Start-up time: imported when a file is read, after send has shown its progress bar.
    from ..api.goal_files import ros_goal, split_documents
    from ..config.reading import decode_text, load_yaml

    p = Path(path)
    try:
        text = decode_text(p.read_bytes(), path)
    except OSError as exc:
        raise ConfigurationError(f"cannot read the trajectory file: {exc.strerror}", path) from None
    if p.suffix.lower() == ".csv":
        return {"trajectory": _csv_trajectory(text, path)}
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise ConfigurationError(f"not valid JSON: {exc}", path) from None
        except RecursionError:
            raise ConfigurationError(
                "not valid JSON: nested too deeply for the interpreter's stack; flatten it", path
            ) from None
    else:
        data = load_yaml(split_documents(text, path), path)  # strict, alias expansion bounded
    if not isinstance(data, dict):
        raise ConfigurationError("expected a mapping with joint_names and points", path)
    return ros_goal(data, path)


_FIELDS = {
    "position": "positions",
    "velocity": "velocities",
    "acceleration": "accelerations",
    "effort": "effort",
}


def _csv_trajectory(text: str, path: str) -> dict[str, Any]:
    rows = list(csv.reader(line for line in text.splitlines() if line.strip()))
    if len(rows) < 2:
        raise ConfigurationError("a CSV trajectory needs a header row and at least one point", path)
    header = [h.strip() for h in rows[0]]
    if header[0] not in ("time_from_start", "time"):
        raise ConfigurationError(
            f"the first column must be time_from_start (seconds), got '{header[0]}'", path
        )
    columns: list[tuple[str, str]] = []
    for name in header[1:]:
        joint, _, field = name.rpartition(".")
        if not joint or field not in _FIELDS:
            joint, field = name, "position"
        columns.append((joint, _FIELDS[field]))
    joints = list(dict.fromkeys(j for j, _ in columns))
    points = []
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise ConfigurationError(
                f"line {line}: {len(row)} values, the header has {len(header)}", path
            )
        try:
            values = [float(v) for v in row]
        except ValueError as exc:
            raise ConfigurationError(f"line {line}: {exc}", path) from exc
        point: dict[str, Any] = {"time_from_start": values[0]}
        for (joint, field), value in zip(columns, values[1:], strict=True):
            point.setdefault(field, [math.nan] * len(joints))[joints.index(joint)] = value
        for field, vector in point.items():
            if field != "time_from_start" and any(math.isnan(v) for v in vector):
                raise ConfigurationError(f"line {line}: {field} missing for some joints", path)
        points.append(point)
    return {"joint_names": joints, "points": points}


def cmd_send(args: argparse.Namespace) -> int:
    # The bar shows at once, before the file is read and the client loads (issue 24: within
    # 100 ms of the command's start for a 20,000-point CSV; bench/send_start.py measures it).
    progress = None if args.quiet or args.topic else Progress(0.0)
    if progress is not None:
        progress.stage(f"reading {args.file}")
    try:
        return _send(args, progress)
    finally:
        if progress is not None:
            progress.clear()


def _send(args: argparse.Namespace, progress: Progress | None) -> int:
    goal = load_goal_file(args.file)
    trajectory = goal["trajectory"]
    points = (trajectory.get("points") if isinstance(trajectory, dict) else None) or []
    last = points[-1] if isinstance(points, list) and points else {}
    end = last.get("time_from_start") if isinstance(last, dict) else None
    # A malformed file is for the daemon to name precisely; this is only the progress bar's end.
    total = float(end) if isinstance(end, (int, float)) and not isinstance(end, bool) else 0.0
    goal_time_tolerance = goal.get("goal_time_tolerance", 0.0)
    if not isinstance(goal_time_tolerance, (int, float)) or isinstance(
        goal_time_tolerance, bool
    ):
        raise ConfigurationError(
            f"goal_time_tolerance: expected seconds (a number) or {{sec, nanosec}}, got "
            f"{goal_time_tolerance!r}",
            args.file,
        )
    if progress is not None:
        progress.stage(f"sending {len(points)} points")
    with connect(args) as client:
        if args.topic:
            sent = client.send_trajectory(
                trajectory, start_in=args.start_in, time_scaling=args.time_scaling
            )
            total = sent.get("duration_s", total)
            print(
                f"trajectory sent ({len(points)} points, {total:.2f} s"
                f"{_slowed(sent.get('time_scale'))}), not monitored"
            )
            return EXIT_OK
        handle = client.send_goal(
            trajectory,
            goal.get("path_tolerance", ()),
            goal.get("goal_tolerance", ()),
            float(goal_time_tolerance),
            start_in=args.start_in,
            time_scaling=args.time_scaling,
        )
        if handle.duration_s is not None:
            total = handle.duration_s
        if progress is not None:
            progress.clear()
        print(
            f"goal {handle.goal_id} accepted: {len(points)} points over {total:.2f} s"
            f"{_slowed(handle.time_scale)}"
        )
        return goal_result(
            handle, total + (args.start_in or 0.0), args.quiet, args.wait, progress
        )


def _slowed(factor: float | None) -> str:
    """What ``send`` adds when the daemon slowed the trajectory down to the joint limits."""
    if factor is None or factor <= 1.0:
        return ""
    return f" (slowed down {factor:.3g}x to fit the joint limits)"


def cmd_cancel(args: argparse.Namespace) -> int:
    with connect(args) as client:
        goal_id = args.goal_id
        if goal_id is None:
            goal_id = client.get_status().get("controller", {}).get("active_goal")
            if goal_id is None:
                print("no goal is executing")
                return EXIT_OK
        reply = client.cancel(int(goal_id))
        canceled = reply.get("canceled", reply.get("ok"))
        print(f"goal {goal_id}: {'cancel requested' if canceled else 'not executing'}")
        return EXIT_OK if canceled else EXIT_GOAL_FAILED


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "send",
        help="send a trajectory file as a goal and watch it",
        description=(
            "Send a trajectory (YAML, JSON or CSV) to the daemon as a follow_joint_trajectory "
            "goal, "
            "show a progress bar (time along the trajectory, tracking error) and exit with the "
            "result. Ctrl-C cancels the goal. "
            "CSV: header 'time_from_start,<joint>,...' (positions) or '<joint>.velocity' etc. "
            "YAML/JSON: the protocol's form (seconds as numbers), what 'ros2 topic echo' prints "
            "for a trajectory_msgs/msg/JointTrajectory (header, time_from_start: {sec, "
            "nanosec}), or a control_msgs FollowJointTrajectory goal (trajectory, "
            "path_tolerance, goal_tolerance, goal_time_tolerance: {sec, nanosec})."
        ),
        epilog=EXIT_CODES_HELP,
    )
    p.add_argument(
        "file",
        metavar="FILE",
        help="the trajectory or goal: YAML/JSON (also as 'ros2 topic echo' prints a "
        "JointTrajectory, or a FollowJointTrajectory goal) or CSV; see examples/",
    )
    p.add_argument(
        "--topic",
        action="store_true",
        help="send on the fire-and-forget topic interface instead (no result)",
    )
    p.add_argument(
        "--start-in",
        type=float,
        default=None,
        metavar="S",
        help="start the trajectory S seconds from now",
    )
    p.add_argument(
        "--time-scaling",
        choices=("reject", "fit"),
        default=None,
        help="a trajectory beyond the joint limits: 'fit' slows it down uniformly until it "
        "fits, 'reject' refuses it (default: the daemon's limits.time_scaling)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--wait",
        type=float,
        default=3600.0,
        help="longest time to wait for the result (default 3600 s)",
    )
    client_options(p, cmd_send)

    p = sub.add_parser(
        "cancel",
        help="cancel the executing goal",
        description=(
            "Cancel a goal (by default the executing one): it ends canceled and the "
            "controller holds where the joints are. A goal id the daemon does not know as "
            "executing is refused (exit 2)."
        ),
        epilog=CANCEL_EXIT_HELP,
    )
    p.add_argument("goal_id", nargs="?", type=int, help="default: the executing goal")
    client_options(p, cmd_cancel)
