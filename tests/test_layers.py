"""The layering contract of ``pyproject.toml`` holds, and the checker would catch a breach.

``lint-imports`` (import-linter) reads the contracts from ``pyproject.toml``: the layers
cli > daemon > api | hardware | rec > controller > config > errors, a controller without I/O,
clock or thread modules (nor the configuration's file reading), drivers that never import the
daemon, the API, the CLI or the recordings, a Feetech control table and codec free of the
SDK, the serial port and the clock, Feetech's SDK imported by its bus wrapper alone, the serial
emulators' shared machinery (``pty_emulator``, ``emulation_cli``) free of any device family,
the CLI's command groups independent of each other between ``cli.parser`` and ``cli.common``,
the daemon's rooms by process (service > transports > core > loop > channel | robot >
settings, every module placed), and no import circle among the CAN emulators and their
socketcand server. It runs here, so every test run (and CI) checks it; the second test plants
a forbidden import in a copy of the tree to show that the check is not vacuous.
Function-local and ``TYPE_CHECKING`` imports count.

Three rules that a contract does not state are checked on the import graph and the files
themselves: no import circle reaches any module of ``jtc_hw`` or ``drivers``, no module of the
CLI or the recordings imports a private name (``_name``) of another module, and no module
outgrows :data:`MAX_LINES` (a module that does is asking to be split by meaning).
"""

from __future__ import annotations

import ast
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
    assert "9 kept, 0 broken" in result.stdout, result.stdout


@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        ("jtc_hw/controller/pid.py", "import socket", "jtc_hw.controller is not allowed to "
         "import socket"),
        ("jtc_hw/controller/trajectory.py", "import time", "jtc_hw.controller is not allowed to "
         "import time"),
        ("jtc_hw/controller/pid.py", "from jtc_hw.config import reading",
         "jtc_hw.controller is not allowed to import jtc_hw.config.reading"),
        ("jtc_hw/config/values.py", "from jtc_hw.controller import pid",
         "jtc_hw.config is not allowed to import jtc_hw.controller"),
        ("jtc_hw/hardware/timing.py", "from jtc_hw.daemon import robot",
         "jtc_hw.hardware is not allowed to import jtc_hw.daemon"),
        ("jtc_hw/api/protocol.py", "from jtc_hw.hardware import registry",
         "jtc_hw.api is not allowed to import jtc_hw.hardware"),
        ("drivers/can/mit/codec.py", "from jtc_hw.daemon import loop",
         "drivers is not allowed to import jtc_hw.daemon"),
        ("drivers/feetech/codec.py", "import scservo_sdk",
         "drivers.feetech.codec is not allowed to import scservo_sdk"),
        ("drivers/feetech/hardware.py", "import scservo_sdk",
         "drivers.feetech.hardware is not allowed to import scservo_sdk"),
        ("drivers/pty_emulator.py", "from .feetech import codec",
         "drivers.pty_emulator is not allowed to import drivers.feetech"),
        ("drivers/motor_model.py", "from jtc_hw.rec import bag",
         "drivers is not allowed to import jtc_hw.rec"),
        ("jtc_hw/rec/flight.py", "from jtc_hw.daemon.channel.cyclering import CycleLayout",
         "jtc_hw.rec is not allowed to import jtc_hw.daemon"),
        ("jtc_hw/rec/bag.py", "from jtc_hw.api import protocol",
         "jtc_hw.rec is not allowed to import jtc_hw.api"),
        ("jtc_hw/api/client.py", "from jtc_hw.rec import bag",
         "jtc_hw.api is not allowed to import jtc_hw.rec"),
        ("jtc_hw/cli/state.py", "from .goals import load_goal_file",
         "jtc_hw.cli.state is not allowed to import jtc_hw.cli.goals"),
        ("jtc_hw/cli/common.py", "from . import record",
         "jtc_hw.cli.common is not allowed to import jtc_hw.cli.record"),
        ("drivers/can/socketcand.py", "from .emulator import MitBusEmulator",
         "drivers.can.socketcand is not allowed to import drivers.can.emulator"),
        ("jtc_hw/daemon/loop/stats.py", "from ..core import backend_api",
         "jtc_hw.daemon.loop is not allowed to import jtc_hw.daemon.core"),
        ("jtc_hw/daemon/core/requests.py", "from ..transports import server",
         "jtc_hw.daemon.core is not allowed to import jtc_hw.daemon.transports"),
        ("jtc_hw/daemon/channel/messages.py", "from ..loop import outbox",
         "jtc_hw.daemon.channel is not allowed to import jtc_hw.daemon.loop"),
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


SUBJECTS = ("jtc_hw.cli", "jtc_hw.rec")
"""The packages whose modules the private-name check below covers."""

PACKAGES = ("jtc_hw", "drivers")
"""The packages whose every module the circle check covers."""

CIRCLES = f"""
import grimp
graph = grimp.build_graph(*{PACKAGES!r}, cache_dir=None)
for module in sorted(graph.modules):
    for imported in sorted(graph.find_modules_directly_imported_by(module)):
        back = graph.find_shortest_chain(importer=imported, imported=module)
        if back is not None:
            print(" -> ".join((module, *back)))
"""
"""Prints each import circle through a module of :data:`PACKAGES` (grimp, as lint-imports)."""

MAX_LINES = {"jtc_hw": 800, "drivers": 1000}
"""The longest a module of each package may be, in lines."""


def import_circles(checkout: Path) -> list[str]:
    """The import circles through any module of ``jtc_hw`` or ``drivers`` in ``checkout``,
    one line each (every circle once per module on it)."""
    result = subprocess.run([sys.executable, "-c", CIRCLES], cwd=checkout, capture_output=True,
                            text=True, timeout=300, check=True)
    return result.stdout.splitlines()


def private_imports(checkout: Path) -> list[str]:
    """Where a module of the CLI or the recordings in ``checkout`` imports a ``_name`` of
    another module of ``jtc_hw``: ``path:line name``."""
    found = []
    for package in SUBJECTS:
        for path in sorted((checkout / package.replace(".", "/")).glob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if not isinstance(node, ast.ImportFrom):
                    continue
                ours = node.level > 0 or (node.module or "").split(".")[0] == "jtc_hw"
                for alias in node.names:
                    private = alias.name.startswith("_") and not alias.name.startswith("__")
                    if ours and private:
                        found.append(f"{path.relative_to(checkout)}:{node.lineno} {alias.name}")
    return found


def oversized_modules(checkout: Path) -> list[str]:
    """The modules of ``checkout`` longer than :data:`MAX_LINES` allows: ``path: n lines``."""
    found = []
    for package, limit in MAX_LINES.items():
        for path in sorted((checkout / package).rglob("*.py")):
            lines = len(path.read_text(encoding="utf-8").splitlines())
            if lines > limit:
                found.append(f"{path.relative_to(checkout)}: {lines} lines (limit {limit})")
    return found


def test_no_import_circle_reaches_any_module_of_jtc_hw_or_drivers() -> None:
    assert import_circles(ROOT) == []


def test_no_module_outgrows_its_line_limit() -> None:
    oversized = oversized_modules(ROOT)
    assert oversized == [], "split by concern: " + "; ".join(oversized)


def test_the_cli_and_the_recordings_import_no_private_name_of_another_module() -> None:
    assert private_imports(ROOT) == []


def test_a_planted_circle_or_private_import_is_found(tmp_path: Path) -> None:
    for name in PACKAGES:
        shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    with open(tmp_path / "jtc_hw/rec/bag.py", "a", encoding="utf-8") as source:
        source.write("\n\ndef _planted() -> None:\n    from . import plot  # planted by the test\n")
    with open(tmp_path / "jtc_hw/cli/state.py", "a", encoding="utf-8") as source:
        source.write("\nfrom .common import _robot  # planted by the test\n")
    with open(tmp_path / "jtc_hw/daemon/transports/connection.py", "a",
              encoding="utf-8") as source:
        source.write("\n\ndef _planted() -> None:\n"
                     "    from . import server  # planted by the test\n")
    with open(tmp_path / "jtc_hw/api/handles.py", "a", encoding="utf-8") as source:
        source.write("\nimport typing\n\nif typing.TYPE_CHECKING:\n"
                     "    from .client import Client  # planted by the test\n")
    circles = import_circles(tmp_path)
    assert "jtc_hw.rec.bag -> jtc_hw.rec.plot -> jtc_hw.rec.bag" in circles
    assert "jtc_hw.api.handles -> jtc_hw.api.client -> jtc_hw.api.handles" in circles
    assert ("jtc_hw.daemon.transports.connection -> jtc_hw.daemon.transports.server -> "
            "jtc_hw.daemon.transports.connection") in circles
    assert any(line.endswith(" _robot") for line in private_imports(tmp_path))


def test_an_oversized_module_is_named(tmp_path: Path) -> None:
    for package, limit in MAX_LINES.items():
        (tmp_path / package / "sub").mkdir(parents=True)
        (tmp_path / package / "sub" / "fits.py").write_text("x = 1\n" * limit)
        (tmp_path / package / "sub" / "big.py").write_text("x = 1\n" * (limit + 1))
    assert oversized_modules(tmp_path) == [
        "jtc_hw/sub/big.py: 801 lines (limit 800)", "drivers/sub/big.py: 1001 lines (limit 1000)"
    ]


def test_importing_the_cli_package_loads_none_of_its_commands() -> None:
    """A daemon started by the ``jtc-hw`` console script imports the script, and so
    ``jtc_hw.cli``, again in its loop process (multiprocessing's spawn runs it): that import
    must not bring the commands, the client or the recorders into the real-time process."""
    code = ("import sys, jtc_hw.cli; print(' '.join(sorted(m for m in sys.modules if "
            "m.startswith(('jtc_hw.cli', 'jtc_hw.api', 'jtc_hw.rec', 'jtc_hw.daemon')))))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60, check=True)
    assert result.stdout.split() == ["jtc_hw.cli"]
