"""Plot a recording: per joint, desired vs actual over time, goal events marked.

Reads the bag with ``rosbags``' reader and draws with matplotlib (Agg: no display needed). Both
are optional extras, imported lazily; without them ``PlotUnavailable`` carries the install hint.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

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
        ``events`` (a list of (t, text)), ``waypoints`` (a list of (t, joint, position) of the
        recorded commands' points), ``tolerances`` (the configured ones, by joint).

    Raises:
        RecordingUnavailable: rosbags is not installed.
        ConfigurationError: the path is not a bag, or holds no controller state.
    """
    import numpy as np

    store = typestore()
    from rosbags.highlevel import AnyReader

    state_topic = f"/{controller}/controller_state"
    events_topic = f"/{controller}/goal_events"
    commands_topic = f"/{controller}/joint_trajectory"
    # (wall ns, joint name, position) of every commanded waypoint that has positions
    raw_waypoints: list[tuple[int, str, float]] = []
    stamps: list[int] = []
    rows: dict[str, list[Any]] = {"ref_pos": [], "act_pos": [], "ref_vel": [], "act_vel": []}
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
                stamp = command.header.stamp.sec * 1_000_000_000 + command.header.stamp.nanosec
                start = stamp or timestamp  # 0: "start now", when the daemon accepted it
                for point in command.points:
                    at = start + point.time_from_start.sec * 1_000_000_000 \
                        + point.time_from_start.nanosec
                    for name, value in zip(command.joint_names, point.positions, strict=False):
                        raw_waypoints.append((at, str(name), float(value)))
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
    finally:
        reader.close()
    if not stamps:
        raise ConfigurationError(
            f"{bag} has no {state_topic} messages: record with 'jtc-hw record', or give "
            "--controller-name")
    t0 = stamps[0]
    series: dict[str, Any] = {
        "t": (np.array(stamps, dtype=np.int64) - t0) / 1e9,
        "joints": joints,
        "tolerances": _tolerances(Path(bag)),
        "events": [((ts - t0) / 1e9, _event_label(text)) for ts, text in raw_events],
        "waypoints": [((at - t0) / 1e9, name, value) for at, name, value in raw_waypoints],
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


def _tolerances(bag: Path) -> dict[str, dict[str, float]]:
    """The configured tolerances the recorder stored in ``metadata.yaml`` (none: ``{}``)."""
    import yaml

    try:
        info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        return dict(json.loads(info.get("custom_data", {})[TOLERANCES_KEY]))
    except (OSError, KeyError, TypeError, ValueError, AttributeError):
        return {}


def _event_label(text: str) -> str:
    try:
        event = json.loads(text)
    except ValueError:
        return text
    return f"{event.get('event', '?')} {event.get('goal_id', '')}".strip()


def plot_bag(
    bag: str | Path, out: str | Path, joints: Sequence[str] | None = None,
    controller: str = "joint_trajectory_controller",
) -> Path:
    """Draw the bag's desired vs actual positions (and velocities) per joint into ``out``.

    Raises:
        PlotUnavailable: matplotlib is not installed.
        RecordingUnavailable: rosbags is not installed.
        ConfigurationError: not a bag, no controller state, or an unknown joint in ``joints``.
    """
    try:
        import matplotlib
    except ImportError as exc:
        raise PlotUnavailable(PLOT_HINT) from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    fig, axes = plt.subplots(len(chosen), columns, sharex=True, squeeze=False,
                             figsize=(6 * columns, 2.2 * len(chosen) + 0.6))
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
            for when, label in series["events"]:
                ax.axvline(when, color="tab:gray", linewidth=0.8)
                if row == 0:
                    ax.annotate(label, (when, 1.0), xycoords=("data", "axes fraction"),
                                fontsize=7, rotation=90, va="top")
            ax.set_ylabel(f"{joint}\n{what}")
            ax.grid(True, alpha=0.3)
    axes[0][0].legend(loc="best", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out
