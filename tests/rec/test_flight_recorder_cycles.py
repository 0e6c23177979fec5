"""The flight recorder fed every cycle (rows of the cycle ring), read back with mcap's reader.

Rows go through a real ``CycleRing`` (written and read in this process, as the loop and the
API process do across theirs) into ``FlightRecorder.on_cycles``; the bag written on a trigger
holds one ``/joint_states`` and one ``controller_state`` per cycle from ``flight_recorder_s``
before the trigger to a second after, the goal's start and end, and the lost rows are counted.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jtc_hw.controller.joints import JointCommand, JointState
from jtc_hw.controller.trajectory import TrajectorySample
from jtc_hw.daemon.channel.cyclering import CycleRing

pytest.importorskip("rosbags")
mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

MS = 1_000_000
PERIOD_NS = 2 * MS  # 500 Hz
JOINTS = ["a", "b"]


def write(ring: CycleRing, k: int, goal: int | None = None, faulted: bool = False) -> None:
    x = np.array([k * 0.001, -k * 0.001])
    ring.write(1_000 * MS + k * PERIOD_NS, goal, goal is None, faulted, 1.0, k * 0.002,
               k * 0.002, JointState(x, x * 0.0 + 0.5),
               None if faulted else TrajectorySample(x + 0.01, x * 0.0, x * 0.0, x * 0.0),
               None if faulted else JointCommand(x + 0.01, None, None, None))


def read(bag: Path) -> list[tuple[str, Any]]:
    (path,) = bag.glob("*.mcap")
    with path.open("rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        return [(c.topic, m) for _, c, _, m in reader.iter_decoded_messages()]


def test_a_bag_of_every_cycle_before_and_after_the_trigger(tmp_path: Path) -> None:
    from jtc_hw.rec.flight import FlightRecorder

    ring = CycleRing.create(len(JOINTS), 1000)
    recorder = FlightRecorder(tmp_path, seconds=1.0, keep=3, cycle_rate_hz=500.0,
                              joint_names=JOINTS)
    since = 0
    try:
        def feed(first: int, last: int, **kwargs: Any) -> None:
            nonlocal since
            for k in range(first, last):
                write(ring, k, **kwargs)
                if k % 50 == 49:  # the API process reads every 100 ms
                    rows, since, lost = ring.read(since)
                    recorder.on_cycles(rows, ring.layout, lost)

        feed(0, 1000)  # 2 s with nothing active
        feed(1000, 1500, goal=4)  # 1 s of goal 4
        trigger_ns = 1_000 * MS + 1499 * PERIOD_NS
        path = recorder.trigger("fault", trigger_ns)
        assert path is not None
        feed(1500, 2100, faulted=True)  # faulted: measured only; the bag is due at + 1 s
        recorder.flush()
        status = recorder.status()
        assert status["last_file"] == path and status["source"] == "cycles"
        assert status["lost_cycles"] == 0
    finally:
        recorder.close()
        ring.close()
    messages = read(Path(path))
    states = [m for topic, m in messages if topic.endswith("controller_state")]
    joint_states = [m for topic, m in messages if topic == "/joint_states"]
    # From 1 s before the trigger (k = 999) to 1 s after (k = 1999): every cycle.
    ks = [round(m.feedback.positions[0] / 0.001) for m in states]
    assert ks == list(range(999, 2000))
    assert len(joint_states) == len(states)
    assert list(states[0].joint_names) == JOINTS
    controlled = states[1]  # k = 1000: goal 4 active
    assert list(controlled.reference.positions) == pytest.approx([1.01, -0.99])
    assert list(controlled.error.positions) == pytest.approx([0.01, 0.01])
    assert list(controlled.output.positions) == pytest.approx([1.01, -0.99])
    assert len(controlled.output.velocities) == 0  # not a command interface: no value
    after = states[-1]  # faulted: feedback only
    assert len(after.reference.positions) == 0 and len(after.output.positions) == 0
    assert list(after.feedback.velocities) == [0.5, 0.5]
    events = [json.loads(m.data) for topic, m in messages if topic.endswith("goal_events")]
    assert [(e["event"], e["goal_id"]) for e in events] == [("goal_started", 4),
                                                             ("goal_ended", 4)]

    # jtc-hw plot reads it: the desired line ends at the fault, the measured one goes on.
    pytest.importorskip("matplotlib")
    from PIL import Image

    from jtc_hw.rec.plot import plot_bag, read_series

    series = read_series(path, "joint_trajectory_controller")
    assert series["ref_pos"].shape == series["act_pos"].shape == (len(ks), 2)
    assert np.isnan(series["ref_pos"][-1]).all() and not np.isnan(series["act_pos"]).any()
    out = plot_bag(path, tmp_path / "fault.png")
    with Image.open(out) as image:
        assert image.format == "PNG" and image.size[0] >= 400
        colors = image.convert("RGB").getcolors(maxcolors=1 << 20)
    assert colors is not None and len(colors) > 50  # lines, labels, grid: not blank


def test_rows_lost_in_the_ring_are_counted(tmp_path: Path) -> None:
    from jtc_hw.rec.flight import FlightRecorder

    ring = CycleRing.create(len(JOINTS), 100)
    recorder = FlightRecorder(tmp_path, seconds=1.0, keep=3, cycle_rate_hz=500.0,
                              joint_names=JOINTS)
    try:
        for k in range(250):  # a reader that came 150 rows too late
            write(ring, k)
        rows, _, lost = ring.read(0)
        recorder.on_cycles(rows, ring.layout, lost)
        assert recorder.status()["lost_cycles"] == 150
    finally:
        recorder.close()
        ring.close()
