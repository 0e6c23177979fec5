"""The layering contract of ``pyproject.toml`` holds, and the checker would catch a breach.

``lint-imports`` (import-linter) reads the contracts from ``pyproject.toml``: the layers
cli > daemon > api | hardware > controller > errors, a controller without I/O, clock or thread
modules, drivers that never import the daemon, the API or the CLI, and no import circle among
the CAN emulators and their socketcand server. It runs here, so every
test run (and CI) checks it; the second test plants a forbidden import in a copy of the tree to
show that the check is not vacuous.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

LINT = (
    "import sys; from importlinter.cli import lint_imports; "
    "sys.exit(lint_imports(no_cache=True, no_logo=True))"
)


def lint_imports(checkout: Path) -> subprocess.CompletedProcess[str]:
    """``lint-imports`` on ``checkout`` (its ``jtc_hw`` and ``drivers`` come first on the path)."""
    return subprocess.run(
        [sys.executable, "-c", LINT],
        cwd=checkout,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_the_layering_contract_is_kept() -> None:
    result = lint_imports(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "4 kept, 0 broken" in result.stdout, result.stdout


@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        ("jtc_hw/controller/pid.py", "import socket", "jtc_hw.controller is not allowed to "
         "import socket"),
        ("jtc_hw/controller/trajectory.py", "import time", "jtc_hw.controller is not allowed to "
         "import time"),
        ("jtc_hw/hardware/params.py", "from jtc_hw.daemon import robot",
         "jtc_hw.hardware is not allowed to import jtc_hw.daemon"),
        ("jtc_hw/api/protocol.py", "from jtc_hw.hardware import registry",
         "jtc_hw.api is not allowed to import jtc_hw.hardware"),
        ("drivers/can/mit/codec.py", "from jtc_hw.daemon import loop",
         "drivers is not allowed to import jtc_hw.daemon"),
        ("drivers/can/socketcand.py", "from .emulator import MitBusEmulator",
         "drivers.can.socketcand is not allowed to import drivers.can.emulator"),
    ],
)
def test_a_forbidden_import_breaks_the_contract(
    tmp_path: Path, module: str, line: str, contract: str
) -> None:
    for name in ("jtc_hw", "drivers"):
        shutil.copytree(ROOT / name, tmp_path / name,
                        ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    with open(tmp_path / module, "a", encoding="utf-8") as source:
        source.write(f"\n{line}  # planted by the test\n")
    result = lint_imports(tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    assert contract in result.stdout, result.stdout
