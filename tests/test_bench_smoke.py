"""The in-process benchmarks still run on today's API (they are not tests: no figure is asserted).

A bench that configures joint limits or speed scaling broke silently once the controller
started checking goals against the limits; running each with a few cycles catches that. The
daemon benches (goal_latency, failsafe, loop_jitter) start real daemons and are left out.
"""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Any

import pytest

from conftest import ROOT


def bench_rows(script: str, *args: str) -> list[dict[str, Any]]:
    """``bench/<script> <args> --json`` run to its end (exit status 0): its JSON lines."""
    done = subprocess.run(
        [sys.executable, str(ROOT / "bench" / script), *args, "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines() if line.strip()]


@pytest.mark.parametrize(
    ("script", "args", "key"),
    [
        ("update_cost.py", ["--cycles", "50", "--joints", "6"], "case"),
        ("stop_cost.py", ["--repeat", "1", "--joints", "6"], "kind"),
        ("ring_write.py", ["--cycles", "300", "--joints", "6"], "write_median_us"),
        ("cdr_decode.py", ["--points", "50", "--repeat", "1"], "ours_ms"),
    ],
)
def test_bench_runs_and_prints_json_lines(script: str, args: list[str], key: str) -> None:
    rows = bench_rows(script, *args)
    assert rows and all(row["joints"] == 6 and key in row for row in rows)


def test_zenoh_rtt_prints_a_row_per_mode_and_express() -> None:
    """``zenoh_rtt.py`` (the floor under the ROS 2 figures): its router, server process and
    queries run to the end, one row per reply setting, with the socket's round trip beside."""
    rows = bench_rows("zenoh_rtt.py", "--queries", "20", "--modes", "client")
    assert [(row["mode"], row["express"]) for row in rows] == [("client", False),
                                                               ("client", True)]
    assert all(row["zenoh_p50_us"] > 0 and row["socket_p50_us"] > 0 for row in rows)


def test_bus_rate_breakdown_alternates_idle_and_neighbour_runs() -> None:
    """``bus_rate.py --breakdown --neighbour both``: per bit rate an idle row then a row beside
    the busy process, each with the per-cycle split; the existing keys are still there."""
    rows = bench_rows("bus_rate.py", "--bus", "dynamixel", "--bitrates", "4000000",
                      "--duration", "0.2", "--breakdown", "--neighbour", "both")
    assert [row["neighbour"] for row in rows] == [False, True]
    for row in rows:
        assert {"cycle_us", "wire_us", "ratio", "driver_cpu_us", "target_met"} <= set(row)
        parts = row["breakdown"]
        assert parts["cycles"] > 0 and parts["wire_us"] == row["wire_us"]
        # The usual cycle makes no call into dynamixel-sdk (the Sync Read request is our
        # codec's, kept): the boundary is watched, and nothing crosses it.
        assert parts["calls_per_cycle"] == 0 and parts["sdk_cpu_p50_us"] == 0
        assert 0 < parts["driver_cpu_p50_us"] < parts["cycle_p50_us"]
        assert parts["blocked_p50_us"] >= 0


def test_bus_rate_feetech_rows_put_our_driver_beside_the_sdk_loop() -> None:
    """``bus_rate.py --bus feetech``: our driver's row then the hand-written scservo_sdk loop's,
    on the same wire time; our cycle makes no SDK call, the loop's is nothing but SDK calls."""
    rows = bench_rows("bus_rate.py", "--bus", "feetech", "--duration", "0.2", "--breakdown")
    assert [(row["bus"], row["client"]) for row in rows] == [("feetech", "jtc_hw"),
                                                            ("feetech", "sdk loop")]
    ours, sdk = rows
    # Sync Read request 14 bytes, six 12-byte replies, Sync Write 26 bytes, 10 us a byte.
    assert ours["wire_us"] == sdk["wire_us"] == 1120.0
    for row in rows:
        assert row["bitrate"] == 1_000_000 and row["motors"] == 6
        assert {"cycle_us", "ratio", "driver_cpu_us", "target_met"} <= set(row)
        assert row["breakdown"]["cycles"] > 0 and row["cycle_us"] > 0
    assert ours["breakdown"]["calls_per_cycle"] == 0
    assert sdk["breakdown"]["calls_per_cycle"] > 0 and sdk["breakdown"]["sdk_p50_us"] > 0
