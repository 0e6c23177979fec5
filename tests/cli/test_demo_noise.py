"""What ``jtc-hw demo`` prints on a normal run: no WARNING for what is normal, and nothing in
the middle of its progress bar (issue 22, point 9).

The demo runs as a user runs it (a subprocess starting its daemon, and its emulator); its
stdout and stderr go to one pipe, unbuffered, so their order is the order a terminal shows.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DEMO_TIMEOUT_S = 120.0  # an upper bound on waiting, never a claim of speed


def demo(tmp_path: Path, *args: str, pythonpath: tuple[Path, ...] = ()) -> tuple[int, list[str]]:
    """Run ``jtc-hw demo ARGS``; its exit status and its output lines, as a terminal shows
    them (stderr into stdout, both unbuffered). The daemon's flight recorder writes in
    ``tmp_path``."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "JOURNAL_STREAM")}
    env["PYTHONPATH"] = os.pathsep.join(
        [*map(str, pythonpath), str(ROOT), *filter(None, [env.get("PYTHONPATH")])]
    )
    env.update(PYTHONUNBUFFERED="1", XDG_STATE_HOME=str(tmp_path / "state"))
    done = subprocess.run(
        [sys.executable, "-m", "jtc_hw", "demo", *args], stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True, cwd=tmp_path, env=env, timeout=DEMO_TIMEOUT_S,
        stdin=subprocess.DEVNULL,
    )
    return done.returncode, done.stdout.splitlines()


def test_a_normal_demo_logs_no_warning(tmp_path: Path) -> None:
    """With every extra installed, the normal shutdown's flight-recorder bag is INFO: a
    WARNING on every clean stop taught users to ignore warnings."""
    pytest.importorskip("rosbags")
    code, lines = demo(tmp_path)
    text = "\n".join(lines)
    assert code == 0, text
    assert [line for line in lines if "WARNING" in line] == [], text
    assert "INFO jtc_hw.flight_recorder: flight recorder: shutdown; writing " in text


def test_without_rosbags_the_demo_says_once_at_info_that_the_recorder_is_off(
    tmp_path: Path,
) -> None:
    """The plain install (no rosbags): every process of the demo finds ``import rosbags``
    failing, as in an environment without it (a ``sitecustomize`` on the path blocks it)."""
    blocker = tmp_path / "no_rosbags"
    blocker.mkdir()
    (blocker / "sitecustomize.py").write_text(
        "import sys\nsys.modules['rosbags'] = None  # import rosbags -> ImportError\n"
    )
    code, lines = demo(tmp_path, pythonpath=(blocker,))
    text = "\n".join(lines)
    assert code == 0, text
    off = [line for line in lines if "flight recorder off" in line]
    assert len(off) == 1, text
    assert "INFO jtc_hw.flight_recorder: flight recorder off: it needs the rosbags library" in (
        off[0]
    )
    assert [line for line in lines if "WARNING" in line] == [], text
    assert not (tmp_path / "state").exists()  # no recorder, no bag


def test_the_dynamixel_demo_prints_the_emulator_statistics_once_after_the_demo(
    tmp_path: Path,
) -> None:
    """The emulator's packet statistics came every 0.2 s, between the progress bar's lines;
    now once, when it stops, after the demo's own last line."""
    code, lines = demo(tmp_path, "--hardware", "dynamixel")
    text = "\n".join(lines)
    assert code == 0, text
    stats = [i for i, line in enumerate(lines) if "packets_served=" in line]
    assert len(stats) == 1, text
    stopped = [i for i, line in enumerate(lines) if "daemon stopped (SIGTERM)" in line]
    assert stopped and stats[0] > stopped[0], text
    assert "emulator | " in lines[stats[0]]


def test_the_feetech_demo_runs_the_goal_to_success_on_emulated_so101_servos(
    tmp_path: Path,
) -> None:
    """``jtc-hw demo --hardware feetech``: six emulated STS3215 at 1 Mbit/s, driven by the
    feetech kind through Feetech's SDK; the goal succeeds and the emulator reports its
    statistics once, with no error reply and no corrupt byte."""
    pytest.importorskip("scservo_sdk", reason="feetech-servo-sdk (jtc_hw[feetech]) is missing")
    code, lines = demo(tmp_path, "--hardware", "feetech")
    text = "\n".join(lines)
    assert code == 0, text
    assert any("goal 1 succeeded" in line for line in lines), text
    assert any("emulated feetech motors: " in line for line in lines), text
    stats = [line for line in lines if "packets_served=" in line]
    assert len(stats) == 1, text
    assert "errors_sent=0" in stats[0] and "checksum_errors=0" in stats[0], text
