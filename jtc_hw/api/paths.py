"""Where the daemon's socket is when nobody says: one rule for the daemon and its clients."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Final

__all__ = ["SOCKET_NAME", "default_socket_path"]

SOCKET_NAME: Final = "jtc-hw.sock"


def default_socket_path(environ: Mapping[str, str] | None = None) -> str:
    """Where the socket goes when ``daemon.socket`` is not given.

    ``$RUNTIME_DIRECTORY/jtc-hw.sock`` (systemd's ``RuntimeDirectory=``; the first one if it
    lists several), else ``$XDG_RUNTIME_DIR/jtc-hw.sock``, else ``/tmp/jtc-hw-<uid>.sock``.

    Args:
        environ: the environment to look in (default: ``os.environ``).
    """
    env = os.environ if environ is None else environ
    runtime = env.get("RUNTIME_DIRECTORY", "").split(":")[0]
    if runtime:
        return os.path.join(runtime, SOCKET_NAME)
    xdg = env.get("XDG_RUNTIME_DIR", "")
    if xdg:
        return os.path.join(xdg, SOCKET_NAME)
    return f"/tmp/jtc-hw-{os.getuid()}.sock"
