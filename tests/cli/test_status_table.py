"""``jtc-hw status``'s table: the flight recorder and Zenoh lines (what ``get_status`` says
of them, readable; the raw reply stays behind ``--json``)."""

from __future__ import annotations

from jtc_hw.cli.status import status_lines


def test_the_flight_recorder_line_says_what_it_keeps_and_its_last_bag() -> None:
    lines = status_lines({"flight_recorder": {
        "enabled": True, "seconds": 10.0, "source": "cycles", "cycle_rate_hz": 200.0,
        "lost_cycles": 3, "errors": 0, "last_file": "/var/lib/jtc-hw/flight/x-aborted"}})
    line = next(x for x in lines if x.startswith("flight rec"))
    assert "10 s of every cycle (200 Hz)" in line
    assert "lost cycles 3" in line and "/var/lib/jtc-hw/flight/x-aborted" in line


def test_a_flight_recorder_that_is_off_says_so() -> None:
    lines = status_lines({"flight_recorder": {"enabled": False}})
    assert "flight rec    off" in lines


def test_the_zenoh_line_has_its_prefix_and_counters_and_is_absent_without_zenoh() -> None:
    lines = status_lines({"zenoh": {"prefix": "jtc/lab/arm1", "queries": 12, "busy": 1,
                                    "unauthorized": 3, "published": 400, "dropped": 2, "lost": 0}})
    assert (("zenoh         jtc/lab/arm1: queries 12, busy 1, unauthorized 3, published 400, "
             "dropped 2, lost 0")
            in lines)
    assert not any(x.startswith(("zenoh", "flight rec")) for x in status_lines({}))
