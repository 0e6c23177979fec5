"""Recording on a full disk (issue 21 point 8): ``jtc-hw record``, ``daemon.record`` and the
flight recorder, writing into a small tmpfs that fills up for real (``helpers.small_disk``):
the kernel's ENOSPC comes through rosbags' own writes. Each time the bag is closed with the
rows written before the failure, read back by the independent ``mcap`` reader; one line says
what happened; the daemon and its loop carry on."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers.daemon import ROOT, WAIT_S, DaemonProcess, connect, daemon_env, loop_process, traj
from helpers.small_disk import small_disk

pytest.importorskip("rosbags")
mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

from jtc_hw.rec.bag import RESERVE_NAME, BagRecorder, RecordingFailed  # noqa: E402
from jtc_hw.rec.flight import FlightRecorder  # noqa: E402

pytestmark = pytest.mark.usefixtures("no_leaks")

FULL = "No space left on device"
FAST_STATES = {"state_publish_rate": 250.0}
"""The daemons publish fast, so that a few hundred kB fill up in a second or two."""


def positions(bag: Path) -> list[list[float]]:
    """``/joint_states`` positions of ``bag``, read with mcap's reader (not rosbags)."""
    (path,) = bag.glob("*.mcap")
    with path.open("rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        return [list(m.position) for _, _, _, m in
                reader.iter_decoded_messages(topics=["/joint_states"])]


def assert_closed(bag: Path) -> dict[str, Any]:
    """The bag is finished: its files and no reserve; its metadata."""
    assert sorted(os.listdir(bag)) == sorted([f"{bag.name}.mcap", "metadata.yaml"])
    assert not (bag / RESERVE_NAME).exists()
    info: dict[str, Any] = yaml.safe_load((bag / "metadata.yaml").read_text())
    return info["rosbag2_bagfile_information"]


def state(n: int) -> dict[str, Any]:
    return {"time_ns": 1_000_000_000 + n * 2_000_000, "joint_names": ["j1", "j2"],
            "actual": {"positions": [float(n), 0.5], "velocities": [0.0, 0.0]},
            "desired": {"positions": [float(n), 0.5]}, "active_goal": None}


def test_a_bag_on_a_full_disk_keeps_every_row_before_the_failure(tmp_path: Path) -> None:
    with small_disk(tmp_path / "disk", "1m") as disk:
        recorder = BagRecorder(disk / "bag", "jtc", 0)
        n = 0
        with pytest.raises(RecordingFailed) as failed:
            for n in range(1_000_000):  # ~1 kB a row: the disk is full long before
                recorder.state(state(n))
        message = str(failed.value)
        assert "\n" not in message
        assert message.startswith(f"writing the bag {disk / 'bag'} failed while writing /")
        assert FULL in message and "it is closed and readable" in message
        recorder.state(state(n + 1))  # the bag is closed: nothing more, no second error
        recorder.close()
        info = assert_closed(disk / "bag")
        rows = positions(disk / "bag")
        # Rows 0 .. n-1 complete; row n's /joint_states too if its controller_state failed.
        assert n > 100 and n <= len(rows) <= n + 1
        assert [r[0] for r in rows] == [float(k) for k in range(len(rows))]
        assert info["message_count"] == sum(recorder.counts.values())


def test_jtc_hw_record_on_a_full_disk_says_so_in_one_line(tmp_path: Path) -> None:
    d = DaemonProcess(tmp_path / "d", controller=FAST_STATES)
    with d.serving(), small_disk(tmp_path / "disk", "384k") as disk:
        loop = loop_process(d)
        done = subprocess.run(
            [sys.executable, "-m", "jtc_hw", "record", str(disk / "run"), "--socket",
             str(d.socket)],
            capture_output=True, text=True, timeout=120, cwd=ROOT, env=daemon_env())
        assert done.returncode == 4, done.stderr
        (line,) = done.stderr.splitlines()
        assert line.startswith(f"error: writing the bag {disk / 'run'} failed while ")
        assert FULL in line and "closed and readable" in line
        assert_closed(disk / "run")
        assert len(positions(disk / "run")) > 10
        # The daemon carries on, its loop process the same.
        with connect(d) as client:
            result = client.send_goal(traj([0.1] * 6, 0.3)).wait(timeout_s=WAIT_S)
            assert result["status"] == "succeeded", result
        assert loop_process(d) == loop
    assert "Traceback" not in d.log()


def test_daemon_record_on_a_full_disk_stops_and_the_daemon_carries_on(tmp_path: Path) -> None:
    with small_disk(tmp_path / "disk", "384k") as disk:
        d = DaemonProcess(tmp_path / "d", controller=FAST_STATES, record=str(disk / "runs"))
        d.start()
        try:
            d.wait_ready()
            loop = loop_process(d)
            with connect(d) as client, client.subscribe_state() as sub:
                stopped = None
                for _ in range(250 * 60):  # states, each an upper bound on waiting: ~60 s
                    sub.get(timeout_s=WAIT_S)
                    stopped = client.get_status()["recording"]["stopped"]
                    if stopped:
                        break
                assert stopped is not None and FULL in stopped, d.log()
                result = client.send_goal(traj([0.1] * 6, 0.3)).wait(timeout_s=WAIT_S)
                assert result["status"] == "succeeded", result
                assert client.get_status()["controller"].get("fault") is None
                bag = Path(client.get_status()["recording"]["file"])
            assert loop_process(d) == loop
        finally:
            code = d.shutdown()
        assert code == 0, d.log()
        log = d.log()
        assert log.count("recording stopped: ") == 1 and "Traceback" not in log, log
        (line,) = [x for x in log.splitlines() if "recording stopped: " in x]
        assert f"writing the bag {bag} failed while" in line and FULL in line
        assert_closed(bag)
        assert len(positions(bag)) > 10


def test_the_flight_recorder_on_a_full_disk_logs_one_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with small_disk(tmp_path / "disk", "1m") as disk:
        recorder = FlightRecorder(disk / "flight", seconds=30.0, keep=3,
                                  controller="jtc")
        try:
            for n in range(10_000):  # 20 s at 500 Hz, ~1 kB a state: more than the disk
                recorder.on_state(state(n))
            with caplog.at_level(logging.INFO, logger="jtc_hw.flight_recorder"):
                path = recorder.trigger("aborted", state(9_999)["time_ns"])
                recorder.flush(timeout_s=60.0)
        finally:
            recorder.close()
        assert path is not None and recorder.errors == 1
        errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
        (line,) = errors
        assert line.startswith(f"flight recorder: writing the bag {path} failed while ")
        assert FULL in line and "\n" not in line
        assert_closed(Path(path))
        rows = positions(Path(path))
        assert len(rows) > 100 and [r[0] for r in rows] == [r[0] for r in
                                                            sorted(rows, key=lambda r: r[0])]
