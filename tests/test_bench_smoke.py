"""The in-process benchmarks still run on today's API (they are not tests: no figure is asserted).

A bench that configures joint limits or speed scaling broke silently once the controller
started checking goals against the limits; running each with a few cycles catches that. The
daemon benches (goal_latency, failsafe, loop_jitter) start real daemons and are left out.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from conftest import ROOT


@pytest.mark.parametrize(
    ("script", "args", "key"),
    [
        ("update_cost.py", ["--cycles", "50", "--joints", "6"], "case"),
        ("stop_cost.py", ["--repeat", "1", "--joints", "6"], "kind"),
        ("ring_write.py", ["--cycles", "300", "--joints", "6"], "write_median_us"),
    ],
)
def test_bench_runs_and_prints_json_lines(script: str, args: list[str], key: str) -> None:
    done = subprocess.run(
        [sys.executable, str(ROOT / "bench" / script), *args, "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    rows = [json.loads(line) for line in done.stdout.splitlines() if line.strip()]
    assert rows and all(row["joints"] == 6 and key in row for row in rows)
