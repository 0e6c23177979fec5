"""A documented default is the default: YAML comments in README, docs/ and config/ that call a
value of ``limits.time_scaling`` the default name the one the schema gives."""

from __future__ import annotations

import re
from pathlib import Path

from jtc_hw.config.controller import LIMITS_PARAMETERS

ROOT = Path(__file__).resolve().parents[1]
# "time_scaling: reject  # fit (the default ...)" or "# ...; default fit"
LINE = re.compile(r"time_scaling: \w+\s*#(?P<comment>.*)")
CALLED_DEFAULT = re.compile(r"(\w+) \(the default|default:? (\w+)")


def documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
            *sorted((ROOT / "config").glob("*.yaml")), *sorted((ROOT / "examples").glob("*"))]


def test_comments_call_the_schema_default_the_default() -> None:
    default = LIMITS_PARAMETERS["time_scaling"].default
    seen, wrong = 0, []
    for path in documents():
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            match = LINE.search(line)
            if match is None:
                continue
            for named in CALLED_DEFAULT.findall(match["comment"]):
                seen += 1
                if default not in named:
                    wrong.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert seen, "no comment names a default: the pattern no longer matches the documents"
    assert not wrong, f"the default is {default!r}:\n" + "\n".join(wrong)
