"""``jtc-hw run`` and ``jtc-hw check``: the daemon, and what its configuration will do.

``check`` reads a robot configuration as ``run`` will (controller, hardware, daemon settings;
the hardware components are created, nothing is opened), prints what it will do, and warns
about settings that have no effect or are unsafe.

The robot file's module and the service are imported when a command runs (start-up time: with
the hardware registry they load, they cost more than the rest of ``jtc-hw``'s start, and
``--help`` and the client commands do not need them).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from ..controller.parameters import explain
from ..daemon.systemd_units import private_tmp_warnings
from .common import EXIT_OK, print_warnings

__all__ = ["add_parsers", "cmd_check", "cmd_run"]

RUN_EXIT_HELP = (
    "Exit status: 0 stopped cleanly (SIGTERM/SIGINT); 1 the daemon failed while running "
    "(see its log); 2 it could not start (bad configuration, socket or device in use)."
)
CHECK_EXIT_HELP = (
    "Exit status: 0 the configuration is valid; 2 it is not (the error names the key)."
)


def cmd_run(args: argparse.Namespace) -> int:
    from ..daemon.robot import load_robot, security_warnings  # start-up time (see above)
    from ..daemon.service import run  # start-up time

    print_warnings(security_warnings(load_robot(args.config_file, args.controller)), sys.stderr)
    return run(args.config_file, args.controller)


def cmd_check(args: argparse.Namespace) -> int:
    from ..daemon.robot import create_hardware_set, load_robot, security_warnings  # start-up time

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
    scaling = c.speed_scaling  # its interfaces resolved by create_hardware_set above
    if scaling.state_interface or scaling.command_interface:
        print(f"  speed scaling   read from {scaling.state_interface or '(none)'}, asked "
              f"through {scaling.command_interface or '(none)'}")
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
    print(_zenoh_line(d, c.name))
    print(_ros2_line(d, c.name))
    for line in _recording_lines(d):
        print(line)
    print_warnings(
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
    from ..daemon.robot import joint_position_limits  # start-up time

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


def _zenoh_line(daemon: Any, controller: str) -> str:
    """``jtc-hw check``'s line about ``daemon.zenoh``."""
    z = daemon.zenoh
    if z is None:
        return "  zenoh           off (daemon.zenoh)"
    where = ", ".join(
        part for part in (
            f"listen {', '.join(z.listen)}" if z.listen else "",
            f"connect {', '.join(z.connect)}" if z.connect else "",
            f"config {z.config}" if z.config else "",
            "multicast scouting" if z.multicast_scouting else "",
        ) if part) or "no endpoint"
    return f"  zenoh           {z.resolved_prefix(controller)} ({z.mode or 'peer'}; {where})"


def _ros2_line(daemon: Any, controller: str) -> str:
    """``jtc-hw check``'s line about ``daemon.ros2``."""
    r = daemon.ros2
    if r is None:
        return "  ros2            off (daemon.ros2)"
    z = r.zenoh
    where = ", ".join(part for part in (
        f"connect {', '.join(z.connect)}" if z.connect else "",
        f"listen {', '.join(z.listen)}" if z.listen else "",
        f"config {z.config}" if z.config else "") if part) or "no endpoint"
    broadcaster = ", /joint_states" if r.joint_state_broadcaster else ""
    return (f"  ros2            node {r.namespace}/{r.node_name(controller)}{broadcaster} in "
            f"domain {r.domain_id}, {r.distro} ({z.mode}; {where})")


def _recording_lines(daemon: Any) -> list[str]:
    """``jtc-hw check``'s lines for the flight recorder and recording settings."""
    try:
        import rosbags  # noqa: F401 - an optional extra (jtc_hw[record]): is it installed?

        missing = ""
    except ImportError:
        missing = "; OFF: needs pip install 'jtc_hw[record]'"
    lines = []
    if not daemon.flight_recorder_s:
        lines.append("  flight recorder off (daemon.flight_recorder_s: 0)")
    else:
        lines.append(
            f"  flight recorder {daemon.flight_recorder_s:g} s before each abort, fault, rearm "
            f"and SIGTERM, into {daemon.flight_recorder_dir} (keeps "
            f"{daemon.flight_recorder_keep}){missing}")
    if daemon.record is not None:
        refused = "; run REFUSES to start: needs pip install 'jtc_hw[record]'" if missing else ""
        lines.append(f"  record          every run from its start into {daemon.record}{refused}")
    return lines


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "run",
        help="run the daemon",
        description=(
            "Run the daemon: start the control loop on the configured hardware, open the socket, "
            "notify systemd when ready. SIGTERM/SIGINT: the active goal gets its result, the robot "
            "holds, the hardware applies its safe action, exit 0."
        ),
        epilog=RUN_EXIT_HELP,
    )
    _config_arguments(p, cmd_run)

    p = sub.add_parser(
        "check",
        help="validate a configuration and explain it",
        description=(
            "Validate a robot configuration (controller parameters with upstream names, hardware, "
            "daemon settings), print what it will do, and warn about settings that have no effect."
        ),
        epilog=CHECK_EXIT_HELP,
    )
    _config_arguments(p, cmd_check)


def _config_arguments(p: argparse.ArgumentParser, func: Any) -> None:
    p.add_argument("config_file", metavar="CONFIG", help="robot configuration (YAML)")
    p.add_argument("--controller", help="controller section to use if the file has several")
    p.set_defaults(func=func)
