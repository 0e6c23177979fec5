"""A daemon on Zenoh as a subprocess, and the Zenoh configurations of its test clients.

Every daemon runs on simulated (mirror) joints and listens on its own
``tcp/127.0.0.1:<free port>``; every session has multicast scouting and gossip off and connects
to the endpoints named, so nothing leaves this machine and tests running in parallel never see
each other's daemons.
"""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path
from typing import Any

import yaml

from jtc_hw.api.client import Client

from .daemon import WAIT_S, DaemonProcess, robot_config


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


TOKEN = "the zenoh token of the test daemons"
"""``daemon.zenoh.token`` of every test daemon."""

QUIET = {"scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}
"""Zenoh configuration of every test session: no multicast, no gossip (JSON is JSON5)."""


def session_config(*connect: str) -> dict[str, Any]:
    """A client configuration (``zenoh_config=``) connecting to ``connect`` only."""
    return {"mode": "peer", "connect/endpoints": list(connect), "listen/endpoints": [],
            "scouting/multicast/enabled": False, "scouting/gossip/enabled": False}


def write_config(path: Path, *connect: str) -> Path:
    path.write_text(json.dumps({**QUIET, "mode": "peer", "connect": {"endpoints": list(connect)},
                                "listen": {"endpoints": []}}))
    return path


class ZenohDaemon(DaemonProcess):
    """A daemon at ``jtc/test/<name>`` listening on its own loopback port."""

    def __init__(self, directory: Path, name: str) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.prefix = f"jtc/test/{name}"
        self.quiet = directory / "zenoh.json5"
        self.quiet.write_text(json.dumps(QUIET))
        super().__init__(directory)
        self.choose_port()

    def choose_port(self) -> None:
        """A free port now (and the robot file naming it)."""
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.config_path.write_text(yaml.safe_dump(robot_config(self.socket, zenoh={
            "prefix": self.prefix, "listen": [self.endpoint], "config": str(self.quiet),
            "token": TOKEN}),
            sort_keys=False))

    def client(self, token: str | None = TOKEN) -> Client:
        return Client.connect(f"zenoh:{self.prefix}", timeout_s=WAIT_S, token=token,
                              zenoh_config=session_config(self.endpoint))


PORT_ATTEMPTS = 3


def started(d: ZenohDaemon) -> ZenohDaemon:
    """Start ``d`` and wait until it serves on Zenoh. The port was free when chosen; on this
    shared machine another process may take it before the daemon binds it: then the daemon
    exits saying so, and it is started again on another port."""
    for _attempt in range(PORT_ATTEMPTS):
        d.start()
        assert d.proc is not None
        deadline = time.monotonic() + WAIT_S * 3
        while "zenoh: serving under" not in d.log() and d.proc.poll() is None:
            assert time.monotonic() < deadline, f"the daemon did not start:\n{d.log()}"
            time.sleep(0.02)  # polling another process's log file, with a deadline
        if d.proc.poll() is None:
            d.wait_ready()
            return d
        assert "Address already in use" in d.log(), d.log()
        assert d.wait_exit() == 2
        d.choose_port()
    raise AssertionError(f"no free port in {PORT_ATTEMPTS} attempts:\n{d.log()}")
