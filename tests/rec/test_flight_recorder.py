"""The flight recorder's settings in the robot file (``daemon.flight_recorder_*``), and the
flight recorder itself in process: the window it writes, sharing a bag, bounded disk use."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from jtc_hw.daemon.robot import load_robot
from jtc_hw.errors import ConfigurationError

BASE: dict[str, Any] = {
    "joints": ["j1", "j2"],
    "command_interfaces": ["position"],
    "state_interfaces": ["position", "velocity"],
}
MS = 1_000_000


def robot(daemon: dict[str, Any], path: Path | None = None) -> Any:
    data = dict(BASE, daemon=daemon)
    if path is None:
        return load_robot(data)
    path.write_text(yaml.safe_dump(data))
    return load_robot(str(path))


@pytest.fixture(autouse=True)
def state_home(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    return tmp_path / "state"


def test_defaults(state_home: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    d = robot({}).daemon
    assert d.flight_recorder_s == 10.0 and d.flight_recorder_keep == 20
    assert d.flight_recorder_dir == str(state_home / "jtc-hw" / "flight")
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/jtc-hw:/var/lib/other")
    assert robot({}).daemon.flight_recorder_dir == "/var/lib/jtc-hw/flight"


def test_a_relative_directory_is_relative_to_the_robot_file(tmp_path: Path) -> None:
    d = robot({"flight_recorder_dir": "bags", "flight_recorder_s": 0}, tmp_path / "r.yaml").daemon
    assert d.flight_recorder_dir == str(tmp_path / "bags") and d.flight_recorder_s == 0


@pytest.mark.parametrize(("daemon", "path", "words"), [
    ({"flight_recorder_s": -1}, "daemon.flight_recorder_s", "between 0 and 3600"),
    ({"flight_recorder_s": "ten"}, "daemon.flight_recorder_s", "number"),
    ({"flight_recorder_keep": 0}, "daemon.flight_recorder_keep", ">= 1"),
    ({"flight_recorder_dir": " "}, "daemon.flight_recorder_dir", "empty"),
    ({"flight_recorder_sec": 5}, "flight_recorder_sec", "flight_recorder_s"),
])
def test_bad_values_are_named(daemon: dict[str, Any], path: str, words: str) -> None:
    with pytest.raises(ConfigurationError) as info:
        robot(daemon)
    assert path in str(info.value) and words in str(info.value), str(info.value)


# -- the recorder in process -------------------------------------------------------------------


def state(t_ns: int, x: float, goal: int | None = None) -> dict[str, Any]:
    return {
        "time_ns": t_ns, "joint_names": ["j1", "j2"],
        "desired": {"positions": [x, -x], "velocities": [0.0, 0.0], "time_from_start": 0.0},
        "actual": {"positions": [x, -x], "velocities": [0.0, None]},
        "error": {"positions": [0.0, 0.0]}, "command": {"positions": [x, -x]},
        "output": {"positions": [x, -x]}, "holding": goal is None, "active_goal": goal,
        "speed_scaling": {"factor": 1.0, "target": 1.0},
    }


def read(bag: Path) -> list[tuple[str, Any]]:
    mcap_reader = pytest.importorskip("mcap.reader")
    decoder = pytest.importorskip("mcap_ros2.decoder")
    (path,) = bag.glob("*.mcap")
    with path.open("rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[decoder.DecoderFactory()])
        return [(c.topic, m) for _, c, _, m in reader.iter_decoded_messages()]


def test_the_bag_covers_the_window_before_and_the_second_after(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    from jtc_hw.rec.flight import FlightRecorder

    recorder = FlightRecorder(tmp_path, seconds=1.0, keep=3)
    try:
        t0 = 10_000 * MS
        for i in range(200):  # 4 s at 50 Hz
            recorder.on_state(state(t0 + i * 20 * MS, i * 0.01, goal=1 if i >= 100 else None))
        trigger_ns = t0 + 199 * 20 * MS
        path = recorder.trigger("aborted", trigger_ns)
        assert path is not None and re.search(r"/\d{8}T\d{6}\.\d{3}Z-aborted$", path)
        # A fault within the second shares the bag.
        assert recorder.trigger("fault", trigger_ns + 5 * MS) == path
        recorder.on_event({"event": "result", "goal_id": 1, "status": "aborted",
                           "time_ns": trigger_ns})
        for i in range(200, 260):  # 1.2 s more: the bag is written at trigger + 1 s
            recorder.on_state(state(t0 + i * 20 * MS, i * 0.01, goal=None))
        recorder.flush()
        assert recorder.status()["last_file"] == path
    finally:
        recorder.close()
    messages = read(Path(path))
    xs = [m.feedback.positions[0] for topic, m in messages if topic.endswith("controller_state")]
    # From 1 s before the trigger (i = 149) to 1 s after (i = 249).
    assert xs == pytest.approx([i * 0.01 for i in range(149, 250)])
    events = [json.loads(m.data) for topic, m in messages if topic.endswith("goal_events")]
    assert [e["event"] for e in events] == ["goal_started", "result", "goal_ended"]


def test_only_the_newest_bags_are_kept(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    from jtc_hw.rec.flight import FlightRecorder

    recorder = FlightRecorder(tmp_path, seconds=0.5, keep=2)
    paths = []
    try:
        t = 1_000 * MS
        for _ in range(4):
            for _ in range(10):
                recorder.on_state(state(t, 0.0))
                t += 20 * MS
            paths.append(recorder.trigger("rearm", t))
            t += 2_000 * MS  # the next trigger is more than a second later: its own bag
            recorder.flush()
    finally:
        recorder.close()
    kept = sorted(str(p) for p in tmp_path.iterdir())
    assert kept == sorted(paths[-2:]) and len(set(paths)) == 4
    assert recorder.status()["files"] == paths[-2:]


def test_close_writes_the_shutdown_bag_however_long_the_writer_takes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A busy machine took over 10 s to write a shutdown bag, and ``close`` gave up with a
    TimeoutError: the daemon ended with a traceback (CI under load, issue 22). ``close`` now
    waits for the writer. Here flush's own timeout is made tiny and the writer is held until
    ``close`` has had that long: ``close`` must neither raise nor return before the bag is
    written."""
    pytest.importorskip("rosbags")
    import threading

    from jtc_hw.rec import flight

    recorder = flight.FlightRecorder(tmp_path, seconds=0.5, keep=2)
    release = threading.Event()
    write = recorder._write

    def slow_write(*args: Any, **kwargs: Any) -> Any:
        release.wait(timeout=30.0)
        return write(*args, **kwargs)

    monkeypatch.setattr(recorder, "_write", slow_write)
    real_flush = recorder.flush
    monkeypatch.setattr(recorder, "flush", lambda timeout_s=0.01: real_flush(timeout_s))
    for i in range(10):
        recorder.on_state(state(1_000 * MS + i * 20 * MS, 0.0))
    path = recorder.trigger("shutdown", 1_200 * MS)
    assert path is not None
    failures: list[BaseException] = []

    def close() -> None:
        try:
            recorder.close()
        except BaseException as exc:  # noqa: BLE001 - reported below
            failures.append(exc)

    closing = threading.Thread(target=close, name="close")
    closing.start()
    closing.join(timeout=0.2)  # well past flush's 0.01 s
    assert closing.is_alive(), "close returned before the bag was written"
    release.set()
    closing.join(timeout=30.0)
    assert not closing.is_alive() and not failures, failures
    assert recorder.last_file == path and Path(path).is_dir()


def test_off_when_zero(tmp_path: Path) -> None:
    from jtc_hw.rec.flight import FlightRecorder

    recorder = FlightRecorder(tmp_path / "none", seconds=0.0, keep=2)
    try:
        recorder.on_state(state(0, 0.0))
        assert recorder.trigger("aborted", 0) is None
        assert recorder.status()["enabled"] is False
    finally:
        recorder.close()
    assert not (tmp_path / "none").exists()


def test_a_normal_shutdown_is_info_and_a_fault_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 22, point 9: every clean stop logged ``flight recorder: shutdown; writing ...``
    as a WARNING. What went wrong (an abort, a fault) stays a WARNING."""
    pytest.importorskip("rosbags")
    import logging

    from jtc_hw.rec.flight import FlightRecorder

    recorder = FlightRecorder(tmp_path, seconds=0.5, keep=5)
    try:
        with caplog.at_level(logging.INFO, logger="jtc_hw.flight_recorder"):
            recorder.trigger("aborted", 1_000 * MS)
            recorder.trigger("shutdown", 5_000 * MS)  # its own bag: 4 s later
    finally:
        recorder.close()
    levels = {r.getMessage().split(";")[0]: r.levelname for r in caplog.records
              if "; writing " in r.getMessage()}
    assert levels == {"flight recorder: aborted": "WARNING",
                      "flight recorder: shutdown": "INFO"}


def test_without_rosbags_the_recorder_says_once_at_info_that_it_is_off(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The plain install is a supported way to run: it is off, said once, not a warning."""
    import logging
    import sys

    from jtc_hw.rec.flight import FlightRecorder

    monkeypatch.setitem(sys.modules, "rosbags", None)  # import rosbags -> ImportError
    with caplog.at_level(logging.INFO, logger="jtc_hw.flight_recorder"):
        recorder = FlightRecorder(tmp_path / "none", seconds=10.0, keep=2)
        try:
            assert recorder.trigger("shutdown", 0) is None
        finally:
            recorder.close()
    assert recorder.available is False
    said = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert len(said) == 1 and said[0][0] == "INFO", said
    assert said[0][1].startswith("flight recorder off: it needs the rosbags library")
