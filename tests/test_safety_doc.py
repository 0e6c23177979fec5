"""docs/safety.md names, for each failure, the tests that show it: those tests exist."""

from __future__ import annotations

import re

from conftest import ROOT

ROWS = ("loop death", "loop stall", "API death", "API stall", "motor silent", "bus loss",
        "motor power cycle", "client vanishes", "socket flood", "second daemon", "SIGTERM",
        "SIGKILL")


def test_every_failure_has_a_row_and_every_cited_test_exists() -> None:
    text = (ROOT / "docs" / "safety.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| **")]
    for failure in ROWS:
        row = next((r for r in rows if r.startswith(f"| **{failure}**")), None)
        assert row is not None, f"docs/safety.md has no row for {failure!r}"
        assert "tests/" in row, f"the {failure!r} row names no test"
    cited = set(re.findall(r"`(tests/[\w/]+\.py)(?:::(\w+))?`", text))
    assert cited
    for path, name in cited:
        source = (ROOT / path).read_text()
        if name:
            assert re.search(rf"^def {name}\(", source, re.M), f"{path}::{name} does not exist"
