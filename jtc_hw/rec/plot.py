"""Plot a recording: per joint, desired vs actual over time, waypoints and goal events marked.

Reads the bag with ``rosbags``' reader and draws with matplotlib (Agg: no display needed). Both
are optional extras, imported lazily; without them ``PlotUnavailable`` carries the install hint.

Waypoints on the executed time base
-----------------------------------
A command's waypoint at ``time_from_start`` T is drawn when the reference actually reached it,
not at the command's start plus T: with speed scaling (and while the factor ramps) the two
differ, by T x (1 - factor) at a steady factor. ``reference.time_from_start`` of
``controller_state`` is the trajectory time of the trajectory being followed (the loop's clock
scaled by the factor, the ramp included); where it falls back, the loop switched trajectories
(a new command starts below zero, a hold after a cancel, abort or fault at zero). Each command
is followed from its switch (:func:`executed_waypoints` says which) to the next, and a waypoint
is placed where the trajectory time reaches T, interpolated between the two states around it.
Nothing is integrated, so no error accumulates, and a "start now" command needs no guess of
when the loop started it. A waypoint the reference never reached is not drawn.

Results, faults and re-arms (``goal_events`` entries with a ``text``) are marked with their text,
coloured by how they ended.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..errors import ConfigurationError
from .bag import CONTROLLER_STATE_TYPE, TOLERANCES_KEY, RecordingUnavailable, typestore

PLOT_HINT = "plotting needs matplotlib: pip install 'jtc_hw[plot]'"


class PlotUnavailable(RecordingUnavailable):
    """matplotlib is not installed."""


def read_series(bag: str | Path, controller: str) -> dict[str, Any]:
    """The controller states and goal events of a bag, as arrays.

    Returns:
        ``t`` (seconds from the first state), ``joints``, ``ref_pos``/``act_pos``/``ref_vel``/
        ``act_vel`` (arrays of shape samples × joints; velocities may have 0 columns) and
        ``events`` (a list of (t, label, kind): see :func:`_event_label`), ``waypoints`` (a
        list of (t, joint, position) of the recorded commands' points, at the time the
        reference reached them: :func:`executed_waypoints`), ``tolerances`` (the configured
        ones, by joint), ``ref_time_from_start`` and ``speed_scaling`` (per state).

    Raises:
        RecordingUnavailable: rosbags is not installed.
        ConfigurationError: the path is not a bag, or holds no controller state.
    """
    store = typestore()
    from rosbags.highlevel import AnyReader  # the optional extra, checked by typestore()

    state_topic = f"/{controller}/controller_state"
    events_topic = f"/{controller}/goal_events"
    commands_topic = f"/{controller}/joint_trajectory"
    # (log time ns, [(time_from_start ns, joint name, position)]) of every command
    raw_commands: list[tuple[int, list[tuple[int, str, float]]]] = []
    stamps: list[int] = []
    rows: dict[str, list[Any]] = {"ref_pos": [], "act_pos": [], "ref_vel": [], "act_vel": []}
    ref_tfs: list[float] = []  # reference.time_from_start of every state, seconds
    factors: list[float] = []
    joints: list[str] = []
    raw_events: list[tuple[int, str]] = []
    try:
        reader = AnyReader([Path(bag)], default_typestore=store)
        reader.open()
    except Exception as exc:  # rosbags raises its own error types for a missing/bad bag
        raise ConfigurationError(f"{bag}: not a readable rosbag2 directory ({exc})") from exc
    try:
        wanted = [c for c in reader.connections
                  if c.topic in (state_topic, events_topic, commands_topic)]
        for connection, timestamp, data in reader.messages(connections=wanted):
            if connection.topic == commands_topic:
                command: Any = reader.deserialize(data, "trajectory_msgs/msg/JointTrajectory")
                points = []
                for point in command.points:
                    at = point.time_from_start.sec * 1_000_000_000 + point.time_from_start.nanosec
                    for name, value in zip(command.joint_names, point.positions, strict=False):
                        points.append((at, str(name), float(value)))
                raw_commands.append((timestamp, points))
                continue
            if connection.topic == events_topic:
                text: Any = reader.deserialize(data, "std_msgs/msg/String")
                raw_events.append((timestamp, str(text.data)))
                continue
            msg: Any = reader.deserialize(data, CONTROLLER_STATE_TYPE)
            joints = list(msg.joint_names)
            stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            rows["ref_pos"].append(msg.reference.positions)
            rows["act_pos"].append(msg.feedback.positions)
            rows["ref_vel"].append(msg.reference.velocities)
            rows["act_vel"].append(msg.feedback.velocities)
            tfs = msg.reference.time_from_start
            ref_tfs.append(tfs.sec + tfs.nanosec / 1e9)
            factors.append(float(msg.speed_scaling_factor))
    finally:
        reader.close()
    if not stamps:
        raise ConfigurationError(
            f"{bag} has no {state_topic} messages: record with 'jtc-hw record', or give "
            "--controller-name")
    t0 = stamps[0]
    t = (np.array(stamps, dtype=np.int64) - t0) / 1e9
    series: dict[str, Any] = {
        "t": t,
        "joints": joints,
        "tolerances": _tolerances(Path(bag)),
        "events": [((ts - t0) / 1e9, *_event_label(text)) for ts, text in raw_events],
        "waypoints": executed_waypoints(
            t, np.array(ref_tfs), [((ts - t0) / 1e9, [(at / 1e9, name, value)
                                                      for at, name, value in points])
                                   for ts, points in raw_commands]),
        "ref_time_from_start": np.array(ref_tfs),
        "speed_scaling": np.array(factors),
    }
    for key, values in rows.items():
        # A sample without values (a flight recorder's cycles while faulted have no reference)
        # is NaN, which the plot leaves out; a field no sample has gives 0 columns.
        width = max(len(v) for v in values)
        table = np.full((len(values), width), np.nan)
        for i, v in enumerate(values):
            table[i, :len(v)] = v[:width]
        series[key] = table
    return series


def executed_waypoints(
    t: Any, tfs: Any, commands: Sequence[tuple[float, Sequence[tuple[float, str, float]]]],
) -> list[tuple[float, str, float]]:
    """Each command's waypoints at the time the reference reached them, as (time, joint,
    position) (see the module docstring).

    Args:
        t: the states' times (seconds, increasing).
        tfs: the states' ``reference.time_from_start`` (seconds).
        commands: (log time, [(time_from_start, joint, position)]) per command, in order.
    """
    out: list[tuple[float, str, float]] = []
    n = len(t)
    # Where the loop switched trajectories: the trajectory time falls back.
    switches = np.flatnonzero(np.diff(tfs) < 0) + 1 if n > 1 else np.zeros(0, np.int64)
    starts: list[int | None] = []
    after = 0  # a command's switch comes after the previous command's
    for logged, _ in commands:
        # The daemon logs a command once the loop confirmed it: its switch is the last one at
        # or before the log time, or (states published slower than the loop runs) the first
        # one after it.
        candidates = switches[switches >= after]
        before = candidates[t[candidates] <= logged]
        later = candidates[t[candidates] > logged]
        first = int(before[-1]) if len(before) else int(later[0]) if len(later) else None
        if first is None and not starts and n and t[0] <= logged:
            # The recording began before the first command and its trajectory time never fell
            # back: the hold before it was younger than the command's first published sample
            # (a goal sent right after the daemon started). It is followed from the start.
            first = 0
        starts.append(first)
        if first is not None:
            after = first + 1
    for k, (_, points) in enumerate(commands):
        first = starts[k]
        if first is None:
            continue  # never followed within the recording
        # The trajectory is followed until the loop switches again (another command, or a
        # hold after a cancel, an abort or a fault).
        following = switches[switches > first]
        end = int(following[0]) if len(following) else n
        for at, name, value in points:
            when = _reached(t, tfs, first, end, at)
            if when is not None:
                out.append((when, name, value))
    return out


def _reached(t: Any, tfs: Any, first: int, end: int, at: float) -> float | None:
    """The time in ``t[first:end]`` where ``tfs`` reaches ``at`` (interpolated), None if it
    does not. A waypoint before the first state's trajectory time (the loop took the command
    between two states) is placed back from that state by its trajectory time, no earlier than
    the state before."""
    after = np.flatnonzero(tfs[first:end] >= at)
    if not len(after):
        return None
    j = first + int(after[0])
    if j == first:
        previous = t[first - 1] if first > 0 else t[first]
        return float(max(previous, t[first] - (tfs[first] - at)))
    span = tfs[j] - tfs[j - 1]
    share = (at - tfs[j - 1]) / span if span > 0 else 1.0
    return float(t[j - 1] + share * (t[j] - t[j - 1]))


def _tolerances(bag: Path) -> dict[str, dict[str, float]]:
    """The configured tolerances the recorder stored in ``metadata.yaml`` (none: ``{}``)."""
    try:
        info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        return dict(json.loads(info.get("custom_data", {})[TOLERANCES_KEY]))
    except (OSError, KeyError, TypeError, ValueError, AttributeError):
        return {}


EVENT_COLOURS = {"info": "tab:gray", "ok": "tab:green", "warn": "tab:orange",
                 "error": "tab:red"}
"""How a marked event is drawn, by its kind (:func:`_event_label`)."""


def _event_label(text: str) -> tuple[str, str]:
    """A goal event's label and kind (a key of :data:`EVENT_COLOURS`): a result says its goal,
    status and text, a fault or re-arm its text."""
    try:
        event = json.loads(text)
    except ValueError:
        return text, "info"
    if not isinstance(event, dict):
        return text, "info"
    kind = str(event.get("event", "?"))
    if kind == "result":
        status = str(event.get("status", "?"))
        words = [f"goal {event.get('goal_id', '?')} {status}"]
        words += [str(event[k]) for k in ("error_string", "details") if event.get(k)]
        return ": ".join(words), {"succeeded": "ok", "aborted": "error"}.get(status, "warn")
    if kind in ("fault", "rearm"):
        return str(event.get("text") or kind), "error" if kind == "fault" else "ok"
    return f"{kind} {event.get('goal_id', '')}".strip(), "info"


LABEL_CHARS = 90
"""A mark's text is cut to this many characters (the whole text is in the bag)."""


def _shorten(label: str) -> str:
    return label if len(label) <= LABEL_CHARS else label[:LABEL_CHARS - 1] + "\u2026"


def plot_bag(
    bag: str | Path, out: str | Path, joints: Sequence[str] | None = None,
    controller: str = "joint_trajectory_controller",
) -> Path:
    """Draw the bag's desired vs actual positions (and velocities) per joint into ``out``
    (:func:`build_figure`'s figure, which says what it raises)."""
    fig = build_figure(bag, joints, controller)
    out = Path(out)
    fig.savefig(out, dpi=80)
    return out


def build_figure(
    bag: str | Path, joints: Sequence[str] | None = None,
    controller: str = "joint_trajectory_controller",
) -> Any:
    """The figure :func:`plot_bag` writes (a ``matplotlib.figure.Figure``, not registered with
    pyplot): per joint a row of axes, position (and velocity); the waypoints are the line
    labelled ``waypoints``, each event a vertical line and, in the first row, its text.

    Raises:
        PlotUnavailable: matplotlib is not installed.
        RecordingUnavailable: rosbags is not installed.
        ConfigurationError: not a bag, no controller state, or an unknown joint in ``joints``.
    """
    try:  # matplotlib is an optional extra (jtc_hw[plot])
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise PlotUnavailable(PLOT_HINT) from exc

    series = read_series(bag, controller)
    names: list[str] = series["joints"]
    chosen = list(joints) if joints else names
    unknown = [j for j in chosen if j not in names]
    if unknown:
        raise ConfigurationError(
            f"--joints: {', '.join(unknown)} not in the recording (its joints: "
            f"{', '.join(names)})")
    velocity = series["ref_vel"].shape[1] == len(names) and series["act_vel"].shape[1] == len(
        names)
    columns = 2 if velocity else 1
    fig = Figure(figsize=(6 * columns, 2.2 * len(chosen) + 0.6))
    axes = fig.subplots(len(chosen), columns, sharex=True, squeeze=False)
    t = series["t"]
    for row, joint in enumerate(chosen):
        i = names.index(joint)
        panels = [("position", "ref_pos", "act_pos")]
        if velocity:
            panels.append(("velocity", "ref_vel", "act_vel"))
        for col, (what, ref, act) in enumerate(panels):
            ax = axes[row][col]
            band = series["tolerances"].get(joint, {}).get("path", 0.0)
            if what == "position" and band > 0:  # the configured path tolerance (0: none)
                ax.fill_between(t, series[ref][:, i] - band, series[ref][:, i] + band,
                                color="tab:blue", alpha=0.15, linewidth=0,
                                label=f"path tolerance ±{band:g}")
            ax.plot(t, series[ref][:, i], label="desired", color="tab:blue")
            ax.plot(t, series[act][:, i], label="actual", color="tab:orange", linestyle="--")
            marks = [(at, v) for at, name, v in series["waypoints"] if name == joint]
            if what == "position" and marks:
                ax.plot([m[0] for m in marks], [m[1] for m in marks], linestyle="none",
                        marker="o", color="tab:green", markersize=4, label="waypoints")
            for when, label, kind in series["events"]:
                colour = EVENT_COLOURS[kind]
                ax.axvline(when, color=colour, linewidth=0.8 if kind == "info" else 1.2)
                if row == 0:
                    ax.annotate(_shorten(label), (when, 1.0),
                                xycoords=("data", "axes fraction"), fontsize=7, rotation=90,
                                va="top", color=colour if kind != "info" else "black")
            ax.set_ylabel(f"{joint}\n{what}")
            ax.grid(True, alpha=0.3)
    axes[0][0].legend(loc="best", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    fig.tight_layout()
    return fig
