"""README's library snippet and the ``python -m jtc_hw`` demo run as documented."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_readme_snippet_runs_and_succeeds(capsys: pytest.CaptureFixture[str]) -> None:
    text = (ROOT / "README.md").read_text()
    (snippet,) = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    exec(compile(snippet, "README.md", "exec"), {})
    assert capsys.readouterr().out.startswith("succeeded Goal successfully reached!")


def test_demo_runs_the_daemon_and_a_goal_succeeds() -> None:
    """``jtc-hw demo``: a daemon subprocess on simulated joints, a goal, SIGTERM, exit 0."""
    done = subprocess.run(
        [sys.executable, "-m", "jtc_hw", "demo"], capture_output=True, text=True, timeout=120,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "goal 1 succeeded (error_code 0)" in done.stdout
    assert "daemon stopped (SIGTERM), exit status 0" in done.stdout
    assert "stopped cleanly" in done.stderr


@pytest.mark.parametrize("hardware", ["dynamixel", "can-mit", "can-cia402"])
def test_demo_on_emulated_motors(hardware: str) -> None:
    """``jtc-hw demo --hardware KIND``: the emulator in its own process, the daemon driving it
    through the real driver (and SDK / python-can), a goal that succeeds, a clean stop."""
    done = subprocess.run(
        [sys.executable, "-m", "jtc_hw", "demo", "--hardware", hardware],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"jtc-hw demo: emulated {hardware} motors:" in done.stdout
    assert "goal 1 succeeded (error_code 0)" in done.stdout
    assert "daemon stopped (SIGTERM), exit status 0" in done.stdout
    assert f"on {hardware}" in done.stderr and "stopped cleanly" in done.stderr
    # Third-party loggers at WARNING unless -v: canopen logged ~200 INFO lines per demo.
    assert "INFO canopen" not in done.stderr and "INFO can." not in done.stderr
