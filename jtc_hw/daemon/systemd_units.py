"""The systemd units installed on this machine that run a given robot file, and what their
sandbox hides from clients.

The shipped unit (config/jtc-hw.service) has ``PrivateTmp=yes``: the service sees a /tmp of
its own, so a socket a robot file puts under /tmp is invisible to every client outside it.
``jtc-hw check FILE`` looks in systemd's unit directories for a unit whose ``ExecStart=``
runs ``jtc-hw run FILE`` (the same file, however spelt) and warns if that unit has private
/tmp and the file's socket is under /tmp. Drop-ins (``*.service.d/``) are not read. No
exception leaves here: an unreadable unit is skipped.
"""

from __future__ import annotations

import os
import shlex
from collections.abc import Sequence
from typing import Final

__all__ = ["UNIT_DIRS", "private_tmp_warnings"]

UNIT_DIRS: Sequence[str] = (
    "/etc/systemd/system", "/run/systemd/system", "/usr/local/lib/systemd/system",
    "/usr/lib/systemd/system", "/lib/systemd/system",
)
"""Where systemd finds system units, highest precedence first."""

_TRUE: Final = {"yes", "true", "on", "1"}


def _runs(exec_start: str, config: str) -> bool:
    try:
        words = shlex.split(exec_start.lstrip("-@:+!"))
    except ValueError:
        return False
    return any(
        word == "run" and i + 1 < len(words)
        and os.path.realpath(words[i + 1]) == config
        for i, word in enumerate(words)
    )


def private_tmp_warnings(
    config_path: str, socket_path: str, unit_dirs: Sequence[str] | None = None
) -> list[str]:
    """One warning per installed unit that runs ``config_path`` with ``PrivateTmp=`` on while
    ``socket_path`` is under /tmp; none otherwise. ``unit_dirs``: default :data:`UNIT_DIRS`."""
    if not os.path.normpath(socket_path).startswith("/tmp/"):
        return []
    config = os.path.realpath(config_path)
    warnings = []
    for directory in UNIT_DIRS if unit_dirs is None else unit_dirs:
        try:
            names = sorted(n for n in os.listdir(directory) if n.endswith(".service"))
        except OSError:
            continue
        for name in names:
            unit = os.path.join(directory, name)
            try:
                with open(unit, encoding="utf-8") as f:
                    lines = [line.strip() for line in f]
            except (OSError, UnicodeDecodeError):
                continue
            settings: dict[str, str] = {}
            for line in lines:
                key, sep, value = line.partition("=")
                if sep and not line.startswith(("#", ";")):
                    settings[key.strip()] = value.strip()
            if _runs(settings.get("ExecStart", ""), config) and (
                settings.get("PrivateTmp", "").lower() in _TRUE
            ):
                warnings.append(
                    f"daemon.socket {socket_path} is under /tmp, but {unit} runs this file "
                    "with PrivateTmp=yes: no client outside the service can see it. Remove "
                    "daemon.socket (the unit's /run/jtc-hw/jtc-hw.sock, found by every "
                    "client) or put it outside /tmp (docs/systemd.md)"
                )
    return warnings
