"""A hardware kind for daemon tests that must see whether a daemon touched its "device".

``recording`` is the simulated mirror plus two parameters: ``device``, the lock name it
reports from ``devices()`` (so the daemon locks it like a serial port or a CAN channel), and
``journal``, a file to which every lifecycle step that would do I/O on real hardware appends
one line ``<step> <pid>``. A daemon subprocess loads the kind through the real entry-point group
(:func:`install_entry_point` writes a ``.dist-info`` that ``importlib.metadata`` finds on
``PYTHONPATH``), as a third-party driver would be.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

from jtc_hw.controller.joints import JointCommand
from jtc_hw.hardware import DeviceName, ParamKind, ParamSpec, SafeAction, param_table
from jtc_hw.hardware.mirror import MirrorHardware

KIND = "recording-test"

HELPERS = Path(__file__).resolve().parent


class RecordingHardware(MirrorHardware):
    """Mirror joints that journal ``configure`` / ``activate`` / ``deactivate`` / ``cleanup``."""

    kind: ClassVar[str] = KIND

    PARAMS: ClassVar[Mapping[str, ParamSpec]] = param_table(
        *MirrorHardware.PARAMS.values(),
        ParamSpec("device", ParamKind.STRING, "", "the device lock name it reports",
                  required=True),
        ParamSpec("journal", ParamKind.STRING, "", "file the lifecycle steps are appended to",
                  required=True),
    )

    def devices(self) -> tuple[DeviceName, ...]:
        device = str(self.params["device"])
        return (DeviceName(device, device),)

    def _note(self, step: str) -> None:
        with open(self.params["journal"], "a", encoding="utf-8") as journal:
            journal.write(f"{step} {os.getpid()}\n")

    def _configure(self) -> None:
        self._note("configure")
        super()._configure()

    def _activate(self, now_ns: int) -> JointCommand:
        self._note("activate")
        return super()._activate(now_ns)

    def _deactivate(self, now_ns: int, action: SafeAction) -> None:
        self._note("deactivate")
        super()._deactivate(now_ns, action)

    def _cleanup(self) -> None:
        self._note("cleanup")
        super()._cleanup()


def install_entry_point(site: Path) -> Path:
    """Make ``site`` a path entry that registers the kind (``jtc_hw.hardware`` entry point);
    put it and :data:`HELPERS`' parent (``tests/``) on the daemon's ``PYTHONPATH``."""
    dist = site / "jtc_hw_recording_test-0.0.dist-info"
    dist.mkdir(parents=True, exist_ok=True)
    (dist / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: jtc-hw-recording-test\nVersion: 0.0\n"
    )
    (dist / "entry_points.txt").write_text(
        f"[jtc_hw.hardware]\n{KIND} = helpers.recording_hardware:RecordingHardware\n"
    )
    return site


def journal_lines(path: Path) -> list[str]:
    """The steps journaled so far."""
    try:
        return path.read_text().splitlines()
    except FileNotFoundError:
        return []


def component(device: str, journal: Path, joints: list[str], **params: Any) -> dict[str, Any]:
    """One ``hardware[]`` entry of the kind."""
    return {
        "name": "arm",
        "kind": KIND,
        "joints": joints,
        "params": {"lag_s": 0.0, "device": device, "journal": str(journal), **params},
    }
