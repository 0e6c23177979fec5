"""The README's shell examples on the mirror arm run as written, in the order a user would.

Theory of operation: every fenced ``sh`` block of README.md that runs ``jtc-hw run
config/mirror-arm.yaml`` is split into commands (one a line, ``# ...`` comments dropped). The
``run`` line starts one real daemon, in the background as a user's second terminal would;
``export NAME=VALUE`` sets the environment of the commands after it; ``--watch`` commands get
SIGINT (a user's Ctrl-C) once they have printed; every other command must exit 0 with no
traceback. The commands run in a copy of ``config/`` and ``examples/`` whose ``/tmp/jtc-hw``
paths are moved to the test's own directory (the same rewrite is applied to the commands), so
that two suites running side by side, or a user's daemon, never share a socket with the test.
A failing example names its file and line on one line.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^\s*```(\S*)\s*$")


def shell_blocks(path: Path) -> list[list[tuple[int, str]]]:
    """Every ``sh`` block of ``path`` as (line number, command) pairs, comments dropped."""
    blocks: list[list[tuple[int, str]]] = []
    fence_lang: str | None = None  # the open block's language, None outside a block
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fence = FENCE.match(line)
        if fence:
            if fence_lang is None:
                fence_lang = fence.group(1)
                blocks.append([])
            else:
                fence_lang = None
            continue
        if fence_lang == "sh":
            command = line.split(" #", 1)[0].strip()
            if command and not command.startswith("#"):
                blocks[-1].append((number, command))
    return [block for block in blocks if block]


def mirror_blocks() -> list[list[tuple[int, str]]]:
    return [b for b in shell_blocks(ROOT / "README.md")
            if any(c == "jtc-hw run config/mirror-arm.yaml" for _, c in b)]


def test_readme_has_a_mirror_arm_block() -> None:
    assert mirror_blocks(), "README.md: no sh block runs 'jtc-hw run config/mirror-arm.yaml'"


def test_readme_mirror_arm_commands_run_as_written(tmp_path: Path) -> None:
    for name in ("config", "examples"):
        shutil.copytree(ROOT / name, tmp_path / name)
    private = str(tmp_path / "jtc-hw")
    for config in (tmp_path / "config").glob("*.yaml"):
        config.write_text(config.read_text().replace("/tmp/jtc-hw", private))
    bindir = Path(sys.executable).parent
    env = dict(os.environ, XDG_RUNTIME_DIR=str(tmp_path),
               PATH=f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}")
    env.pop("JTC_HW_SOCKET", None)
    daemon: subprocess.Popen[str] | None = None
    try:
        for block in mirror_blocks():
            for line, written in block:
                where = f"README.md:{line}: {written!r}"
                command = written.replace("/tmp/jtc-hw", private)
                if command.startswith("export "):
                    key, _, value = command[len("export "):].partition("=")
                    env[key] = value
                    continue
                argv = shlex.split(command)
                if argv[:2] == ["jtc-hw", "run"]:
                    daemon = subprocess.Popen(argv, cwd=tmp_path, env=env, text=True,
                                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
                    assert daemon.stderr is not None
                    for log in daemon.stderr:  # ends at EOF if the daemon dies
                        if "ready:" in log:
                            break
                    else:
                        pytest.fail(f"{where}: the daemon did not start")
                    continue
                if "--watch" in argv:
                    watch = subprocess.Popen(argv, cwd=tmp_path, env=env, text=True,
                                             stdout=subprocess.PIPE, stderr=subprocess.PIPE)
                    assert watch.stdout is not None
                    first = watch.stdout.readline()  # blocks until it prints (or exits)
                    watch.send_signal(signal.SIGINT)
                    out, err = watch.communicate(timeout=30)
                    assert first and watch.returncode == 0 and "Traceback" not in err, (
                        f"{where}: exit {watch.returncode}: {err.strip()}")
                    continue
                done = subprocess.run(argv, cwd=tmp_path, env=env, text=True,
                                      capture_output=True, timeout=60)
                assert done.returncode == 0 and "Traceback" not in done.stderr, (
                    f"{where}: exit {done.returncode}: {(done.stderr or done.stdout).strip()}")
        assert daemon is not None, "README.md: the mirror-arm block starts no daemon"
    finally:
        if daemon is not None:
            daemon.terminate()
            daemon.communicate(timeout=30)
