"""A small file system that fills up for real: a tmpfs of a given size mounted on a test's
directory, so that the code under test gets ENOSPC from the kernel through its own writes (no
mock of the file layer). Mounting needs root with CAP_SYS_ADMIN (the test VM, CI containers
run as root); elsewhere the test is skipped and says why."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


@contextlib.contextmanager
def small_disk(directory: Path, size: str) -> Iterator[Path]:
    """``directory`` (created) as a tmpfs of ``size`` (``mount -o size=``: ``384k``), unmounted
    on exit."""
    directory.mkdir(parents=True, exist_ok=True)
    mount = shutil.which("mount")
    if mount is None:
        pytest.skip("a full disk is simulated with a small tmpfs: no mount command here")
    done = subprocess.run([mount, "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs",
                           str(directory)], capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        pytest.skip(f"a full disk is simulated with a small tmpfs, and mounting one failed: "
                    f"{done.stderr.strip()}")
    try:
        yield directory
    finally:
        subprocess.run(["umount", "-l", str(directory)], capture_output=True, timeout=30)
