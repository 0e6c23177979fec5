"""``jtc-hw``: run the daemon, check a configuration, and talk to a running daemon.

Exit status: 0 success; 1 a goal ended without success (aborted, canceled); 2 bad input
(configuration, trajectory file), a socket whose listener is not trusted, a socket you may
not connect to (permission denied), or the daemon answered and refused (rejected goal, bad
request, not active); 3 only when no daemon answers (none running, no reply).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from .errors import ConfigurationError, GoalRejected, JtcHwError

EXIT_OK, EXIT_GOAL_FAILED, EXIT_BAD_INPUT, EXIT_NO_DAEMON = 0, 1, 2, 3

EXIT_CODES_HELP = (
    "Exit status: 0 success; 1 the goal aborted or was canceled; 2 bad input, or the daemon "
    "answered and refused the request (rejected goal, bad request), or the socket is not "
    "served by a daemon you trust, or you may not connect to it (permission denied); 3 no "
    "daemon answers."
)
"""The exit statuses of ``send``, the client command that waits for a goal's result."""

CLIENT_EXIT_HELP = (
    "Exit status: 0 success; 2 bad input (an unreadable --config or --zenoh-config), the "
    "socket is not served by a daemon you trust or you may not connect to it (permission "
    "denied), or the daemon answered and refused the request; 3 no daemon answers."
)
"""The exit statuses of the client commands that start or wait for no goal (no exit 1)."""

_EXIT_HELP = {
    "run": (
        "Exit status: 0 stopped cleanly (SIGTERM/SIGINT); 1 the daemon failed while running "
        "(see its log); 2 it could not start (bad configuration, socket or device in use)."
    ),
    "check": "Exit status: 0 the configuration is valid; 2 it is not (the error names the key).",
    "demo": (
        "Exit status: 0 the goal succeeded; 1 it aborted or was canceled; 2 bad configuration, "
        "or --config's socket is already served by a running daemon (the demo sends nothing "
        "to a daemon it did not start); 3 the daemon or emulator did not start or stopped "
        "with an error."
    ),
    "emulate": "Exit status: 0 stopped by Ctrl-C/SIGTERM; 2 bad emulator options.",
    "send": EXIT_CODES_HELP,
    "cancel": (
        "Exit status: 0 the cancel was requested, or no goal is executing; 1 that goal is not "
        "executing; 2 bad input, a socket you may not connect to (permission denied) or not "
        "served by a daemon you trust, or the daemon answered and refused the request; 3 no "
        "daemon answers."
    ),
}
"""Each command's exit statuses where they are not :data:`CLIENT_EXIT_HELP`'s."""

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
  jtc-hw fleet --watch         the daemons on Zenoh, one line each (docs/zenoh.md)

Client commands find the daemon's socket from --socket, else --config's daemon.socket,
else $JTC_HW_SOCKET, else the default path (see 'jtc-hw check' for a config's path). A socket
is used only if the process behind it runs as you, root, or a member of --config's
daemon.socket_group; at the default path the file must be yours or root's too. With --tcp
[HOST:PORT] they reach the TCP endpoint, with --config's token (or $JTC_HW_TOKEN).
With --zenoh PREFIX (and --zenoh-config FILE) they reach the daemon at that Zenoh prefix;
commands there need its token (--zenoh-token-file FILE or $JTC_HW_ZENOH_TOKEN).
"""


# -- trajectory files -------------------------------------------------------------------------


def load_goal_file(path: str) -> dict[str, Any]:
    """Read a trajectory from YAML, JSON or CSV into the protocol's goal form.

    YAML/JSON: either a trajectory (``joint_names``, ``points``) or a goal wrapping one
    (``trajectory``, optional ``path_tolerance``, ``goal_tolerance``, ``goal_time_tolerance``),
    in the protocol's form or as ROS 2 prints them (``ros2 topic echo`` of a JointTrajectory,
    a FollowJointTrajectory goal: ``header``, ``{sec, nanosec}`` durations; see
    :mod:`jtc_hw.api.goal_files`).
    CSV: a header ``time_from_start,<joint>,...`` (positions); columns may also be named
    ``<joint>.position``, ``<joint>.velocity``, ``<joint>.acceleration``, ``<joint>.effort``.

    Raises:
        ConfigurationError: unreadable file or malformed content, naming the line/field.
    """
    from .config.reading import decode_text

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
        from .api.goal_files import split_documents
        from .config.reading import load_yaml

        # ros2 topic echo ends each message with '---'.
        data = load_yaml(split_documents(text, path), path)  # strict, alias expansion bounded
    if not isinstance(data, dict):
        raise ConfigurationError("expected a mapping with joint_names and points", path)
    from .api.goal_files import ros_goal

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


# -- helpers ----------------------------------------------------------------------------------


def _socket(args: argparse.Namespace) -> tuple[str, bool]:
    """The daemon's socket, and whether it was named (not found by the default rule)."""
    from .api.client import default_socket_path
    from .api.paths import client_socket_path
    from .api.paths import default_socket_path as default_rule

    if getattr(args, "socket", None):
        return str(args.socket), True
    if getattr(args, "config", None):
        from .daemon.robot import load_robot

        path = load_robot(args.config).daemon.socket
        if path == default_rule():  # not in the file: the default place, or the service's
            return client_socket_path(), False
        return path, True
    return default_socket_path(), bool(os.environ.get("JTC_HW_SOCKET"))


def _trusted_group(args: argparse.Namespace) -> str | None:
    """``daemon.socket_group`` of ``--config``: the group whose members' daemons are
    trusted (a service user's)."""
    if not getattr(args, "config", None):
        return None
    from .daemon.robot import load_robot

    return load_robot(args.config).daemon.socket_group


def _tcp(args: argparse.Namespace) -> tuple[tuple[str, int], str]:
    """``--tcp``'s address (else ``--config``'s ``daemon.tcp``) and the token (``--config``'s,
    else ``$JTC_HW_TOKEN``).

    Raises:
        ConfigurationError: no address or port, or no token; names what to give.
    """
    tcp = None
    if getattr(args, "config", None):
        from .daemon.robot import load_robot

        tcp = load_robot(args.config).daemon.tcp
    host, port = (tcp.host, tcp.port) if tcp is not None else ("127.0.0.1", 0)
    if args.tcp:
        host, _, number = str(args.tcp).rpartition(":")
        if not host or not number.isdigit() or not 0 < int(number) < 65536:
            raise ConfigurationError(f"--tcp {args.tcp}: expected HOST:PORT, e.g. 127.0.0.1:7400")
        host, port = host.strip("[]"), int(number)
    if not port:
        raise ConfigurationError(
            "--tcp: no port: give --tcp HOST:PORT (the daemon logs 'listening on tcp ...'), or "
            "--config of a daemon whose daemon.tcp.port is set"
        )
    token = tcp.token if tcp is not None else os.environ.get("JTC_HW_TOKEN", "")
    if not token:
        raise ConfigurationError(
            "--tcp: no token: give --config FILE (its daemon.tcp.token) or set JTC_HW_TOKEN"
        )
    return (host, port), token


def _connect(args: argparse.Namespace, hello: bool = True) -> Any:
    from .api.client import PERMISSION, UNTRUSTED, Client, ClientConnectionError

    if getattr(args, "zenoh", None):
        from .cli_fleet import connect_zenoh

        return connect_zenoh(args, hello, _NoDaemon)
    if getattr(args, "tcp", None) is not None:
        address, token = _tcp(args)
        try:
            return Client.connect(tcp=address, token=token, timeout_s=args.timeout, hello=hello)
        except ClientConnectionError as exc:
            raise _NoDaemon(str(exc)) from exc
    path, named = _socket(args)
    try:
        return Client.connect(path, timeout_s=args.timeout, hello=hello, check_owner=not named,
                              trusted_group=_trusted_group(args))
    except ClientConnectionError as exc:
        if exc.code in (UNTRUSTED, PERMISSION):  # a daemon may run: not "is it running?"
            raise ConfigurationError(str(exc)) from exc
        # The client's message ends with its own "is the daemon running?": say it once.
        reason = str(exc).removesuffix("; is the daemon running?")
        raise _NoDaemon(
            f"cannot reach a jtc-hw daemon at {path}: {reason}. Is it running "
            "('jtc-hw run CONFIG', or 'systemctl status jtc-hw')? Use --socket to point at it."
        ) from exc
    except (OSError, JtcHwError) as exc:
        raise _NoDaemon(
            f"cannot reach a jtc-hw daemon at {path}: {exc}. Is it running "
            "('jtc-hw run CONFIG', or 'systemctl status jtc-hw')? Use --socket to point at it."
        ) from exc


class _NoDaemon(Exception):
    pass


def _fmt(values: Sequence[float | None] | None, width: int = 9) -> str:
    if values is None:
        return "-"
    return " ".join(f"{v:{width}.4f}" if v is not None else f"{'nan':>{width}}" for v in values)


class Progress:
    """A one-line progress bar: time along the trajectory and the tracking error."""

    def __init__(self, total_s: float, stream: Any = None, width: int = 30) -> None:
        self.total_s = max(total_s, 1e-9)
        self.stream = stream or sys.stdout
        self.width = width
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._last_print = 0.0

    def update(self, feedback: dict[str, Any]) -> None:
        t = max(0.0, float(feedback.get("time_from_start") or 0.0))
        errors = [
            abs(e) for e in (feedback.get("error", {}).get("positions") or []) if e is not None
        ]
        worst = max(errors, default=0.0)
        frac = min(t / self.total_s, 1.0)
        filled = round(frac * self.width)
        line = (
            f"[{'#' * filled}{'.' * (self.width - filled)}] {t:6.2f}/{self.total_s:.2f} s"
            f"  max |error| {worst:.4f}"
        )
        if self.tty:
            self.stream.write("\r" + line)
            self.stream.flush()
        elif time.monotonic() - self._last_print >= 0.5:
            self._last_print = time.monotonic()
            print(line, file=self.stream)

    def finish(self) -> None:
        if self.tty:
            self.stream.write("\n")


# -- commands ---------------------------------------------------------------------------------


def _print_warnings(warnings: Sequence[str], stream: Any = None) -> None:
    # Under systemd, stderr goes to the journal: "<4>" gives the line warning priority.
    prefix = "<4>" if os.environ.get("JOURNAL_STREAM") and stream is sys.stderr else ""
    for warning in warnings:
        print(f"{prefix}warning: {warning}", file=stream or sys.stdout)


def cmd_run(args: argparse.Namespace) -> int:
    from .daemon.robot import load_robot, security_warnings
    from .daemon.service import run

    _print_warnings(security_warnings(load_robot(args.config_file, args.controller)), sys.stderr)
    return run(args.config_file, args.controller)


def cmd_check(args: argparse.Namespace) -> int:
    from .controller.parameters import explain
    from .daemon.robot import create_hardware_set, load_robot, security_warnings

    robot = load_robot(args.config_file, args.controller)
    # Creating the components checks their parameters as `run` will (no I/O: nothing is
    # opened before configure) and tells what stops each one's motors if the daemon dies.
    hardware = create_hardware_set(robot)
    c = robot.controller
    print(f"{args.config_file}: OK")
    print(f"  controller      {c.name}: {len(c.joints)} joints ({', '.join(c.joints)})")
    print(f"  update_rate     {c.update_rate:g} Hz (period {1e3 / c.update_rate:.3f} ms)")
    print(
        f"  interfaces      command [{', '.join(c.command_interfaces)}], "
        f"state [{', '.join(c.state_interfaces)}]"
    )
    law = "PID (gains per joint)" if c.use_pid else "desired values forwarded"
    print(f"  control law     {law}; interpolation {c.interpolation_method}")
    print(f"  tolerances      {'joint':<14} {'path':>8} {'goal':>8}   (0: not checked)")
    for j in c.joints:
        jc = c.constraints.joints[j]
        print(f"                  {j:<14} {jc.trajectory:>8g} {jc.goal:>8g}")
    print(
        f"                  goal_time {c.constraints.goal_time:g} s, "
        f"stopped_velocity_tolerance {c.constraints.stopped_velocity_tolerance:g}"
    )
    _print_limits(c)
    watchdog_warnings = []
    for component in hardware.components:
        print(f"  hardware        {component.name}: {component.kind}, "
              f"joints {', '.join(component.joints)}")
        watchdog = component.device_watchdog()
        print(f"    watchdog      {watchdog.mechanism}")
        if watchdog.timeout_s is None or watchdog.unprotected:
            joints = watchdog.unprotected or component.joints
            watchdog_warnings.append(
                f"hardware '{component.name}': no device-side watchdog for joints "
                f"{', '.join(joints)}: motors keep their last command if the daemon dies; "
                "prefer position commands with low gains for them (docs/safety.md)"
            )
    d = robot.daemon
    print(f"  socket          {d.socket} (mode {d.socket_mode:o})")
    tcp = f"; tcp {d.tcp.host}:{d.tcp.port} max {d.tcp.max_clients}" if d.tcp else ""
    idle = f"{d.idle_timeout_s:g} s" if d.idle_timeout_s else "never"
    print(f"  clients         unix max {d.max_clients} (+2 for its user and root){tcp}; "
          f"idle timeout {idle}")
    rt = d.realtime
    print(
        f"  realtime        priority {rt.priority or 'normal'}, lock_memory {rt.lock_memory}, "
        f"cpu_affinity {list(rt.cpu_affinity) or 'any'}"
    )
    view = d.foxglove  # the live view (docs/foxglove.md)
    print("  live view       " + (
        f"Foxglove WebSocket ws://{view.host}:{view.port}, "
        f"{f'{view.rate:g} Hz' if view.rate else 'every state'}" if view else
        "off (daemon.foxglove)"))
    from .cli_fleet import check_line  # the Zenoh interface (docs/zenoh.md)

    print(check_line(d, c.name))
    from .rec.cli import check_lines  # flight recorder, record (issue 13, rec)

    for line in check_lines(d):
        print(line)
    from .daemon.systemd_units import private_tmp_warnings

    _print_warnings(
        [*explain(c), *_limits_warnings(robot), *security_warnings(robot), *watchdog_warnings,
         *private_tmp_warnings(args.config_file, d.socket)]
    )
    return EXIT_OK


def _print_limits(c: Any) -> None:
    """``check``'s joint limits table (the controller's, YAML and URDF merged)."""
    if not c.limits:
        print("  limits          none: goals are not checked against joint limits")
        return
    print(
        f"  limits          {'joint':<14} {'position':>17} {'velocity':>9} {'accel.':>9} "
        f"{'jerk':>9}   (-: unlimited); time_scaling {c.time_scaling}"
    )

    def number(value: float | None) -> str:
        return "-" if value is None else f"{value:g}"

    for joint in c.joints:
        lim = c.limits.get(joint)
        if lim is None:
            continue
        position = "-" if lim.position is None else f"[{lim.position[0]:g}, {lim.position[1]:g}]"
        print(
            f"                  {joint:<14} {position:>17} {number(lim.velocity):>9} "
            f"{number(lim.acceleration):>9} {number(lim.jerk):>9}"
        )


def _limits_warnings(robot: Any) -> list[str]:
    """Joints whose hardware ``position_limits`` are narrower than the controller's range:
    a goal the controller accepts could then be clamped by the driver."""
    from .daemon.robot import joint_position_limits

    warnings = []
    for joint, (low, high) in joint_position_limits(robot).items():
        lim = robot.controller.limits.get(joint)
        if lim is None or lim.position is None:
            continue
        if low > lim.position[0] or high < lim.position[1]:
            warnings.append(
                f"limits.{joint}.position: [{lim.position[0]:g}, {lim.position[1]:g}] reaches "
                f"beyond the hardware's position_limits [{low:g}, {high:g}]: goals within the "
                "controller's range could be clamped by the driver; narrow the controller's "
                "range (the hardware's is the last line of defence, it should be the wider)"
            )
    return warnings


def _goal_result(handle: Any, total_s: float, quiet: bool, timeout_s: float) -> int:
    progress = None if quiet else Progress(total_s)
    try:
        for feedback in handle.feedback(timeout_s=timeout_s):
            if progress is not None:
                progress.update(feedback)
        result = handle.wait(timeout_s=timeout_s)
    except KeyboardInterrupt:
        if progress is not None:
            progress.finish()
        print("interrupted: canceling the goal", file=sys.stderr)
        result = handle.cancel(timeout_s=timeout_s)
        result = handle.wait(timeout_s=timeout_s)
    if progress is not None:
        progress.finish()
    text = result["error_string"]  # empty for a cancel, as upstream's
    print(
        f"goal {result['goal_id']} {result['status']} (error_code {result['error_code']})"
        + (f": {text}" if text else "")
    )
    if result.get("details"):  # a daemon before issue 11 sends none
        print(f"  {result['details']}")
    return EXIT_OK if result["status"] == "succeeded" else EXIT_GOAL_FAILED


def cmd_send(args: argparse.Namespace) -> int:
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
    with _connect(args) as client:
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
        print(
            f"goal {handle.goal_id} accepted: {len(points)} points over {total:.2f} s"
            f"{_slowed(handle.time_scale)}"
        )
        return _goal_result(handle, total + (args.start_in or 0.0), args.quiet, args.wait)


def _slowed(factor: float | None) -> str:
    """What ``send`` adds when the daemon slowed the trajectory down to the joint limits."""
    if factor is None or factor <= 1.0:
        return ""
    return f" (slowed down {factor:.3g}x to fit the joint limits)"


def cmd_cancel(args: argparse.Namespace) -> int:
    with _connect(args) as client:
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


def cmd_query(args: argparse.Namespace) -> int:
    with _connect(args) as client:
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
            print(f"  {key:<13} {_fmt(values)}")
        print(f"  joints        {' '.join(f'{n:>9}' for n in names)}")
        return EXIT_OK


def cmd_stop(args: argparse.Namespace) -> int:
    # No hello: "stop" must be the first request to be served by a daemon whose client slots
    # are all taken.
    with _connect(args, hello=False) as client:
        reply = client.stop(timeout_s=args.timeout)
        if not reply.get("stopped"):
            print(reply.get("message") or "nothing to stop")
            return EXIT_OK
        print("stopped: holding the measured position (an active goal ends canceled)")
        return EXIT_OK


def cmd_rearm(args: argparse.Namespace) -> int:
    with _connect(args) as client:
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


def _print_scaling(reply: dict[str, Any], what: str) -> None:
    factor, target = reply["factor"], reply["target"]
    ramp = "" if factor == target else f" (ramping from {factor:g})"
    print(f"{what}: speed scaling {target:g}{ramp}")


def cmd_speed(args: argparse.Namespace) -> int:
    with _connect(args) as client:
        reply = client.set_speed_scaling(args.factor, timeout_s=args.timeout)
        _print_scaling(reply, "speed set")
        return EXIT_OK


def cmd_pause(args: argparse.Namespace) -> int:
    with _connect(args) as client:
        reply = client.set_speed_scaling(0.0, timeout_s=args.timeout)
        _print_scaling(reply, "paused ('jtc-hw resume' carries on)")
        return EXIT_OK


def cmd_resume(args: argparse.Namespace) -> int:
    with _connect(args) as client:
        reply = client.set_speed_scaling(resume=True, timeout_s=args.timeout)
        _print_scaling(reply, "resumed")
        return EXIT_OK


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
    from .config.reading import load_yaml

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
    from .api.framing import BAD_REQUEST, RequestError

    if args.action == "set":
        if not args.items or len(args.items) % 2:
            raise ConfigurationError(
                "give NAME VALUE pairs, e.g. 'jtc-hw param set gains.j1.p 12'", "param set"
            )
        changes = {
            name: _parameter_value(value, name)
            for name, value in zip(args.items[::2], args.items[1::2], strict=True)
        }
    with _connect(args) as client:
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
    _print_warnings(reply.get("warnings", ()))
    return EXIT_OK


_EMULATORS = {
    "dynamixel": "jtc_hw.drivers.dynamixel.emulator",
    "can": "jtc_hw.drivers.can.emulator",
}


def cmd_emulate(args: argparse.Namespace) -> int:
    import importlib

    module = importlib.import_module(_EMULATORS[args.bus])
    rest = list(args.args)
    if rest[:1] == ["--"]:
        rest = rest[1:]
    return int(module.main(rest))


# -- demo -------------------------------------------------------------------------------------
#
# The demo is set up as a robot would be on a busy machine (issue 22): its control loop at a
# real-time priority when the user may have one, the emulated motors likewise (real motors
# are not slowed down by the host's other work), and, on emulated motors, watchdogs and
# feedback timeouts that a busy laptop keeps. Normally scheduled beside four busy processes
# on two cores, the loop woke 1.2 ms late at the median and 24 ms at p99 (255 overruns in 297
# cycles at 250 Hz), so the CiA 402 drives lost its heartbeat in every run and the MIT and
# Dynamixel demos failed one run in five or two: a demo is not a test of the watchdog.

DEMO_JOINTS = [f"joint{i}" for i in range(1, 7)]

DEMO_LOOP_PRIORITY = 2
"""SCHED_FIFO priority of the demo's control loop where permitted: above its emulators'."""

DEMO_EMULATOR_PRIORITY = 1
"""SCHED_FIFO priority of the demo's emulator where permitted: the lowest, as ``jtc-hw
emulate can`` asks for itself, so the loop preempts it and busy programs do not."""

DEMO_EMULATED_WATCHDOG_S = 0.5
"""Watchdogs (``watchdog_s``) and feedback timeouts of the demo's emulated motors: a busy
laptop stalls a process for tens of ms now and then, beyond the 0.1 s a real arm would use."""


def fifo_permitted(priority: int) -> bool:
    """Whether this process may ask for SCHED_FIFO ``priority`` (sched(7)): with
    CAP_SYS_NICE (root, as usual), or an ``RLIMIT_RTPRIO`` (``ulimit -r``) of at least it.

    A group without real-time CPU budget may still refuse; the daemon then runs normally
    scheduled and says so at INFO."""
    import resource

    if not hasattr(os, "sched_setscheduler"):
        return False
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    if soft == resource.RLIM_INFINITY or soft >= priority:
        return True
    try:
        with open("/proc/self/status", encoding="utf-8") as f:
            for line in f:
                if line.startswith("CapEff:"):
                    return bool(int(line.split()[1], 16) >> 23 & 1)  # CAP_SYS_NICE
    except (OSError, ValueError, IndexError):
        pass
    return False


def _schedule_fifo(pid: int, priority: int) -> bool:
    """Put every thread of process ``pid`` at SCHED_FIFO ``priority`` (threads it starts
    later inherit it); whether that was done. Refused or not permitted: left as it is,
    quietly (the demo then runs normally scheduled)."""
    if not fifo_permitted(priority):
        return False
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except (OSError, ValueError):
        tids = [pid]
    try:
        for tid in tids:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except OSError:  # EPERM (no real-time budget), ESRCH (a thread that ended meanwhile)
        return False
    return True


def demo_config(
    socket_path: str,
    hardware: list[dict[str, Any]] | None = None,
    update_rate: int = 500,
    priority: int = 0,
) -> dict[str, Any]:
    """A six-joint arm, by default on simulated (mirror) hardware at 500 Hz, its loop at
    SCHED_FIFO ``priority`` (0: normally scheduled). ``jtc-hw demo`` asks for
    :data:`DEMO_LOOP_PRIORITY` when this user may have it (:func:`fifo_permitted`), else 0:
    no warning, a laptop's normal state."""
    if hardware is None:
        hardware = [
            {"name": "arm", "kind": "mirror", "joints": DEMO_JOINTS, "params": {"lag_s": 0.005}}
        ]
    return {
        "controller_manager": {"ros__parameters": {"update_rate": update_rate}},
        "joint_trajectory_controller": {
            "ros__parameters": {
                "joints": DEMO_JOINTS,
                "command_interfaces": ["position"],
                "state_interfaces": ["position", "velocity"],
                "state_publish_rate": 50.0,
                "action_monitor_rate": 10.0,
                "constraints": {
                    "stopped_velocity_tolerance": 0.05,
                    "goal_time": 0.5,
                    **{j: {"trajectory": 0.1, "goal": 0.01} for j in DEMO_JOINTS},
                },
            }
        },
        "hardware": hardware,
        "daemon": {
            "socket": socket_path,
            "realtime": {"priority": priority},
        },
    }


DEMO_HARDWARE = ("mirror", "dynamixel", "can-mit", "can-cia402")


def _start_emulator(
    kind: str, timeout_s: float
) -> tuple[subprocess.Popen[str], str, threading.Thread]:
    """Start ``jtc-hw emulate`` for a demo hardware kind; return it, its connection line and
    the thread forwarding its stderr (join it once the emulator has exited: its last lines).

    The emulator runs at SCHED_FIFO :data:`DEMO_EMULATOR_PRIORITY` where permitted: ``jtc-hw
    emulate can`` asks for it itself; the Dynamixel emulator is set from here, right after
    its start (before it starts any thread of its own)."""
    if kind == "dynamixel":
        # Its statistics once, when it stops: live, they interleaved with the progress bar.
        argv = ["dynamixel", "--ids", "1-6", "--model", "XM430-W350", "--baud", "4000000",
                "--stats", "exit"]
    else:
        protocol = "mit" if kind == "can-mit" else "cia402"
        argv = ["can", "--protocol", protocol, "--ids", "1-6", "--pace",
                "--interface", "socketcand", "--socketcand-port", "0"]
    emulator = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "emulate", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    if kind == "dynamixel":
        _schedule_fifo(emulator.pid, DEMO_EMULATOR_PRIORITY)
    stdout, stderr = emulator.stdout, emulator.stderr
    assert stdout is not None and stderr is not None
    forward = threading.Thread(target=_forward, args=(stderr, "  emulator | "), daemon=True)
    forward.start()
    found: list[str] = []
    reader = threading.Thread(target=lambda: found.append(stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    line = found[0].strip() if found else ""
    if not line:
        emulator.kill()
        emulator.wait()
        raise JtcHwError(f"the {kind} emulator did not start (exit status {emulator.returncode})")
    return emulator, line, forward


def demo_hardware(kind: str, line: str) -> tuple[list[dict[str, Any]], int]:
    """The demo arm's hardware section and update rate on an emulator (``line``: what
    ``jtc-hw emulate`` printed: a device path, or ``interface=... host=... port=...``).

    Watchdogs and feedback timeouts are :data:`DEMO_EMULATED_WATCHDOG_S`: the emulator and
    the daemon share a possibly busy machine (a real arm's are shorter)."""
    if kind == "dynamixel":
        params: dict[str, Any] = {
            "port": line,
            "baud_rate": 4000000,
            "ids": [1, 2, 3, 4, 5, 6],
            "model": "XM430-W350",
            "offset": -math.pi,  # the emulated servos start at tick 2048 (pi): joint zero
            "timeout_ms": 20.0,  # a pty served by another process on a possibly busy machine
            "latency_timer_warn": False,
            "watchdog_s": DEMO_EMULATED_WATCHDOG_S,
        }
        return [{"name": "arm", "kind": "dynamixel", "joints": DEMO_JOINTS, "params": params}], 200
    fields = dict(item.split("=", 1) for item in line.split() if "=" in item)
    bus = {
        "interface": "socketcand",
        "channel": fields["channel"].split(",")[0],
        "host": fields["host"],
        "port": int(fields["port"]),
        "bitrate": 1000000,
        "receive_timeout": 0.002,
        "setup_timeout": 0.5,
    }
    if kind == "can-mit":
        params = {"buses": {"can0": bus}, "ids": [1, 2, 3, 4, 5, 6], "model": "AK80-9",
                  "kp": 40.0, "kd": 1.0, "feedback_timeout": DEMO_EMULATED_WATCHDOG_S,
                  "watchdog_s": DEMO_EMULATED_WATCHDOG_S}
    else:
        params = {"buses": {"can0": bus}, "node_id": [1, 2, 3, 4, 5, 6],
                  "feedback_timeout_s": DEMO_EMULATED_WATCHDOG_S,
                  "watchdog_s": DEMO_EMULATED_WATCHDOG_S}
    return [{"name": "arm", "kind": kind, "joints": DEMO_JOINTS, "params": params}], 250


def demo_goal() -> dict[str, Any]:
    """A wave through three waypoints over 3 s, ending at rest.

    Its fastest joint peaks near 1.3 rad/s: the emulated CAN motors track a moving reference
    with a lag of a few tens of ms (their PD gains, the bus round trip), so at twice that speed
    the demo ran at the edge of its 0.1 rad path tolerance and aborted whenever the machine was
    busy; a demo shows the robot working, not the tolerance's edge."""
    return {
        "joint_names": DEMO_JOINTS,
        "points": [
            {
                "time_from_start": 1.0,
                "positions": [0.1 * (i + 1) for i in range(6)],
                "velocities": [0.1] * 6,
            },
            {
                "time_from_start": 2.0,
                "positions": [-0.05 * (i + 1) for i in range(6)],
                "velocities": [-0.1] * 6,
            },
            {"time_from_start": 3.0, "positions": [0.0] * 6, "velocities": [0.0] * 6},
        ],
    }


def _forward(stream: Any, prefix: str) -> None:
    for line in iter(stream.readline, ""):
        print(f"{prefix}{line.rstrip()}", file=sys.stderr)


def cmd_demo(args: argparse.Namespace) -> int:
    emulator = None
    forward = None
    hardware = None
    update_rate = 500
    if args.hardware != "mirror" and not args.config:
        emulator, line, forward = _start_emulator(args.hardware, args.timeout)
        print(f"jtc-hw demo: emulated {args.hardware} motors: {line}")
        hardware, update_rate = demo_hardware(args.hardware, line)
    try:
        return _demo(args, hardware, update_rate)
    finally:
        if emulator is not None:
            emulator.send_signal(signal.SIGTERM)
            try:
                emulator.wait(timeout=10)
            except subprocess.TimeoutExpired:
                emulator.kill()
                emulator.wait()
        if forward is not None:
            forward.join(5.0)  # its last lines (the statistics) after the demo's own


def _demo(args: argparse.Namespace, hardware: list[dict[str, Any]] | None, rate: int) -> int:
    """Start a daemon, send the demo goal to it and to nothing else, stop it.

    The demo moves only a robot it started: with ``--config``, a socket that a running daemon
    already serves is refused before anything starts, and whatever the configuration, the
    client checks that the process serving the socket is the daemon started here
    (``SO_PEERCRED``) before it sends a request, so a daemon that took the path meanwhile
    is never sent the wave either. Both refusals exit 2 (the configuration cannot be used
    for a demo now), like ``run`` with a socket in use.
    """
    from .api.client import NOT_EXPECTED, Client, ClientConnectionError

    with tempfile.TemporaryDirectory(prefix="jtc-hw-demo-") as tmp:
        if args.config:
            config_path = args.config
            from .daemon.locks import held_by, socket_lock_path
            from .daemon.robot import load_robot

            socket_path = load_robot(config_path).daemon.socket
            busy = held_by(socket_path, socket_lock_path(socket_path), what="served")
            if busy is not None:
                print(f"error: {_demo_refusal(config_path, str(busy))}", file=sys.stderr)
                return EXIT_BAD_INPUT
            goal = None
        else:
            socket_path = os.path.join(tmp, "jtc-hw.sock")
            config_path = os.path.join(tmp, "robot.yaml")
            priority = DEMO_LOOP_PRIORITY if fifo_permitted(DEMO_LOOP_PRIORITY) else 0
            config = demo_config(socket_path, hardware, rate, priority)
            Path(config_path).write_text(yaml.safe_dump(config))
            goal = demo_goal()
        print(f"jtc-hw demo: starting the daemon ({config_path})")
        daemon = subprocess.Popen(
            [sys.executable, "-m", "jtc_hw", "run", config_path],
            stderr=subprocess.PIPE,
            text=True,
        )
        assert daemon.stderr is not None
        threading.Thread(target=_forward, args=(daemon.stderr, "  daemon | "), daemon=True).start()
        client = None
        deadline = time.monotonic() + args.timeout
        while client is None:
            if daemon.poll() is not None:
                print(
                    f"the daemon exited with status {daemon.returncode} before it was ready",
                    file=sys.stderr,
                )
                return EXIT_NO_DAEMON
            try:
                client = Client.connect(socket_path, timeout_s=2.0, expect_pid=daemon.pid)
            except ClientConnectionError as exc:
                if exc.code == NOT_EXPECTED:  # another daemon took the path: not ours to move
                    _stop_daemon(daemon)
                    print(f"error: {_demo_refusal(config_path, str(exc))}", file=sys.stderr)
                    return EXIT_BAD_INPUT
                if time.monotonic() > deadline:
                    daemon.terminate()
                    print("the daemon did not open its socket in time", file=sys.stderr)
                    return EXIT_NO_DAEMON
                time.sleep(0.05)  # CLI polling for a socket to appear; not in library code
            except (OSError, JtcHwError):
                if time.monotonic() > deadline:
                    daemon.terminate()
                    print("the daemon did not open its socket in time", file=sys.stderr)
                    return EXIT_NO_DAEMON
                time.sleep(0.05)  # CLI polling for a socket to appear; not in library code
        try:
            names = client.joint_names
            if goal is None:
                goal = {
                    "joint_names": names,
                    "points": [
                        {
                            "time_from_start": 2.0,
                            "positions": [0.3] * len(names),
                            "velocities": [0.0] * len(names),
                        },
                        {
                            "time_from_start": 4.0,
                            "positions": [0.0] * len(names),
                            "velocities": [0.0] * len(names),
                        },
                    ],
                }
            total = goal["points"][-1]["time_from_start"]
            handle = client.send_goal(goal)
            print(
                f"goal {handle.goal_id} accepted: {len(goal['points'])} points over {total} s "
                f"on {len(names)} joints"
            )
            code = _goal_result(handle, total, False, args.timeout)
            status = client.get_status()
            loop = status.get("loop", {})
            late = loop.get("lateness_us", {})
            print(
                f"loop: {loop.get('rate_hz')} Hz, {loop.get('cycles')} cycles, "
                f"wake-up lateness p50 {late.get('p50')} us, p99 {late.get('p99')} us, "
                f"overruns {loop.get('overruns')}"
            )
        finally:
            client.close()
            status_code = _stop_daemon(daemon)
        print(f"daemon stopped (SIGTERM), exit status {status_code}")
        return code if status_code == 0 else EXIT_NO_DAEMON


def _stop_daemon(daemon: subprocess.Popen[str]) -> int:
    """SIGTERM the demo's daemon and wait for it (SIGKILL after 20 s); its exit status."""
    if daemon.poll() is None:
        daemon.send_signal(signal.SIGTERM)
    try:
        return daemon.wait(timeout=20)
    except subprocess.TimeoutExpired:
        daemon.kill()
        return daemon.wait()


def _demo_refusal(config_path: str, reason: str) -> str:
    """The one line of a demo that will not send its goal: another daemon serves the socket."""
    return (
        f"jtc-hw demo --config {config_path} sends nothing: {reason}. The demo moves only a "
        f"daemon it starts itself; to move the running one: 'jtc-hw send GOAL --config "
        f"{config_path}'"
    )


# -- parser -----------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jtc-hw",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from . import __version__

    parser.add_argument("--version", action="version", version=f"jtc-hw {__version__}")
    parser.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        help="keep the INFO logs of third-party libraries (canopen, python-can)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def client_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--socket", help="the daemon's Unix socket path")
        p.add_argument("--config", help="find the socket path in this robot configuration")
        p.add_argument("--tcp", nargs="?", const="", metavar="HOST:PORT",
                       help="reach the daemon over its TCP endpoint (default: --config's "
                       "daemon.tcp), with --config's token or $JTC_HW_TOKEN")
        p.add_argument("--zenoh", metavar="PREFIX",
                       help="reach the daemon over Zenoh at this key prefix (docs/zenoh.md)")
        p.add_argument("--zenoh-config", metavar="FILE",
                       help="Zenoh configuration for --zenoh (default: connect to a router "
                       "on tcp/127.0.0.1:7447)")
        p.add_argument("--zenoh-token-file", metavar="FILE",
                       help="file holding the daemon's daemon.zenoh.token, needed with --zenoh "
                       "to command (default: $JTC_HW_ZENOH_TOKEN; watching needs none)")
        p.add_argument(
            "--timeout",
            type=float,
            default=10.0,
            help="seconds to wait for the daemon's answers (default 10)",
        )

    p = sub.add_parser(
        "run",
        help="run the daemon",
        description=(
            "Run the daemon: start the control loop on the configured hardware, open the socket, "
            "notify systemd when ready. SIGTERM/SIGINT: the active goal gets its result, the robot "
            "holds, the hardware applies its safe action, exit 0."
        ),
    )
    p.add_argument("config_file", metavar="CONFIG", help="robot configuration (YAML)")
    p.add_argument("--controller", help="controller section to use if the file has several")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "check",
        help="validate a configuration and explain it",
        description=(
            "Validate a robot configuration (controller parameters with upstream names, hardware, "
            "daemon settings), print what it will do, and warn about settings that have no effect."
        ),
    )
    p.add_argument("config_file", metavar="CONFIG", help="robot configuration (YAML)")
    p.add_argument("--controller", help="controller section to use if the file has several")
    p.set_defaults(func=cmd_check)

    p = sub.add_parser(
        "demo",
        help="run a goal on simulated joints and show what happened",
        description=(
            "Start a daemon on simulated joints (or on --config's hardware), "
            "send a sample trajectory, show its progress and result, stop."
        ),
    )
    p.add_argument("--config", help="use this robot configuration instead of the built-in arm")
    p.add_argument(
        "--hardware",
        choices=DEMO_HARDWARE,
        default="mirror",
        help=(
            "what the built-in six-joint arm runs on: simulated joints (mirror, the default), "
            "or emulated motors speaking the real protocol, started for the demo: dynamixel "
            "(six XM430-W350 on a pseudo-terminal, through the Dynamixel SDK), can-mit (six "
            "AK80-9 in MIT mode) or can-cia402 (six CiA 402 drives), both over python-can's "
            "socketcand interface"
        ),
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=30.0,
        help="seconds to wait for the daemon (and emulator) to start and answer (default 30)",
    )
    p.set_defaults(func=cmd_demo)

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
    client_options(p)
    p.set_defaults(func=cmd_send)

    p = sub.add_parser(
        "cancel",
        help="cancel the executing goal",
        description=(
            "Cancel a goal (by default the executing one): it ends canceled and the "
            "controller holds where the joints are. A goal id the daemon does not know as "
            "executing is refused (exit 2)."
        ),
    )
    p.add_argument("goal_id", nargs="?", type=int, help="default: the executing goal")
    client_options(p)
    p.set_defaults(func=cmd_cancel)

    from .cli_state import cmd_state, cmd_status

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
    client_options(p)
    p.set_defaults(func=cmd_state)

    p = sub.add_parser(
        "query",
        help="desired state T seconds from now (query_state)",
        description=(
            "Ask the controller for the desired state T seconds from now, as upstream's "
            "query_state service: positions, velocities, accelerations, effort per joint."
        ),
    )
    p.add_argument("t", type=float, metavar="T", help="seconds from now")
    client_options(p)
    p.set_defaults(func=cmd_query)

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
    client_options(p)
    p.set_defaults(func=cmd_stop)

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
    client_options(p)
    p.set_defaults(func=cmd_rearm)

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
    client_options(p)
    p.set_defaults(func=cmd_speed)

    p = sub.add_parser(
        "pause",
        help="bring the motion to rest along its path (speed scaling 0)",
        description=(
            "Pause: ramp the speed scaling factor to 0, so the joints decelerate to rest on "
            f"the path. 'jtc-hw resume' carries on at the factor before the pause. {scaling_help}"
        ),
    )
    client_options(p)
    p.set_defaults(func=cmd_pause)

    p = sub.add_parser(
        "resume",
        help="carry on after 'jtc-hw pause' (the speed scaling factor before it)",
        description=(
            "Resume: ramp the speed scaling factor back to the last non-zero factor set (by "
            "'jtc-hw speed', else the configured speed_scaling.initial_scaling_factor, or 1). "
            f"{scaling_help}"
        ),
    )
    client_options(p)
    p.set_defaults(func=cmd_resume)

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
    client_options(p)
    p.set_defaults(func=cmd_param)

    p = sub.add_parser(
        "emulate",
        help="run an emulated motor bus (Dynamixel on a pty, CAN motors) to test without a robot",
        description=(
            "Run emulated motors speaking the real wire protocol, until Ctrl-C. "
            "'jtc-hw emulate dynamixel --ids 1-6 --model XM430-W350' opens a pseudo-terminal "
            "and prints its path: put it as the 'port' of a dynamixel hardware component. "
            "'jtc-hw emulate can --protocol mit --ids 1-6' serves MIT-mode motors (or "
            "--protocol cia402 drives) and prints how python-can connects to them. "
            "'jtc-hw emulate dynamixel --help' lists each emulator's options."
        ),
    )
    p.add_argument("bus", choices=sorted(_EMULATORS), help="which bus to emulate")
    p.add_argument("args", nargs=argparse.REMAINDER, help="the emulator's options (see its --help)")
    p.set_defaults(func=cmd_emulate)

    p = sub.add_parser(
        "status",
        help="loop statistics, hardware and controller status",
        description=(
            "Show the daemon's status as a table: controller (and any fault), loop timing, "
            "hardware components, clients."
        ),
    )
    p.add_argument("--json", action="store_true", help="print the daemon's full reply as JSON")
    client_options(p)
    p.set_defaults(func=cmd_status)
    from .cli_health import add_hardware_parser

    add_hardware_parser(sub, client_options, _connect)
    from .rec.cli import add_parsers as add_rec_parsers  # record, plot (issue 13, rec)

    add_rec_parsers(sub, client_options)
    from .cli_fleet import add_parser as add_fleet_parser

    add_fleet_parser(sub)
    for name, command in sub.choices.items():
        # Every subcommand's --help states its exit statuses (unless its description does).
        if "Exit status" not in (command.description or ""):
            command.epilog = _EXIT_HELP.get(name, CLIENT_EXIT_HELP)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``jtc-hw``."""
    from .api.framing import RequestError

    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if args.verbose:
        from .daemon.logs import VERBOSE_ENV

        os.environ[VERBOSE_ENV] = "1"  # inherited by the daemon and emulators we start
    if extra and args.func is cmd_param and not any(e.startswith("--") for e in extra):
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
    except _NoDaemon as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_NO_DAEMON
    except RequestError as exc:
        # The daemon answered and refused the request (bad request, not active, busy...).
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError:
        # The reader went away (jtc-hw state | head): not an error. Point stdout at
        # /dev/null so the interpreter's final flush does not raise again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    except (JtcHwError, TimeoutError) as exc:
        # Connection lost, or no reply in time: no daemon answers.
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_NO_DAEMON
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
