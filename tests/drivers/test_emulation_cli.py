"""The ``--ids`` syntax both emulators' command lines share (drivers/emulation_cli.py)."""

from __future__ import annotations

import pytest

from jtc_hw.drivers.emulation_cli import parse_ids


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
