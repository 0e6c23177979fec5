"""What the emulators' command lines share (drivers/emulation_cli.py): the ``--ids`` syntax and
the ``--priority`` option."""

from __future__ import annotations

import argparse

import pytest

from jtc_hw.drivers.emulation_cli import apply_priority, parse_ids


def test_ranges_lists_and_hex() -> None:
    assert parse_ids("1-3,7") == [1, 2, 3, 7]
    assert parse_ids(" 4 ") == [4]
    assert parse_ids("0x10-0x12,1") == [16, 17, 18, 1]
    assert parse_ids("1,,2,") == [1, 2]


@pytest.mark.parametrize("bad", ["", ",", "3-1", "1,1", "1-3,2", "x", "1-", "-1", "010"])
def test_malformed_is_refused(bad: str) -> None:
    with pytest.raises(ValueError):
        parse_ids(bad)


def test_a_family_range_is_checked() -> None:
    assert parse_ids("0,252", valid=range(253)) == [0, 252]
    assert parse_ids("300") == [300]  # no range given: CAN ids are the bus's business
    with pytest.raises(ValueError, match=r"in 0\.\.252"):
        parse_ids("250-253", valid=range(253))


def test_a_priority_out_of_range_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser(prog="jtc-hw emulate x")
    with pytest.raises(SystemExit) as stop:
        apply_priority(parser, 100)
    assert stop.value.code == 2
    assert "jtc-hw emulate x: error: --priority must be 0..99, got 100" in capsys.readouterr().err


def test_priority_0_leaves_normal_scheduling_silently(capsys: pytest.CaptureFixture[str]) -> None:
    apply_priority(argparse.ArgumentParser(prog="jtc-hw emulate x"), 0)
    assert capsys.readouterr().err == ""
