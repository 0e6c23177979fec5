"""Fixtures of the ROS 2 (rmw_zenoh) tests: a Zenoh router on loopback, as ``rmw_zenohd``.

rmw_zenoh's nodes are Zenoh peers that find each other through a router (its design doc,
"Router"); here the router is a Python Zenoh session in ``router`` mode on
``tcp/127.0.0.1:<free port>``, multicast scouting off, so tests running side by side never
meet. Gossip stays on, as in ``rmw_zenohd``'s config: it is how the router tells each peer
where the others listen (all on loopback).
"""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator

import pytest
import zenoh

PORT_ATTEMPTS = 3


def free_port() -> int:
    """A loopback TCP port free now (another process may take it before the router binds it:
    :func:`router` tries again)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def router(no_leaks: None) -> Iterator[str]:
    """A Zenoh router listening on a free loopback port; yields its endpoint
    (``tcp/127.0.0.1:<port>``). Closed at teardown."""
    for _attempt in range(PORT_ATTEMPTS):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps("router"))
        conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
        conf.insert_json5("connect/endpoints", "[]")
        conf.insert_json5("scouting/multicast/enabled", "false")
        try:
            session = zenoh.open(conf)
        except zenoh.ZError as exc:  # the port was taken between choosing and binding it
            last = exc
            continue
        try:
            yield endpoint
        finally:
            session.close()
        return
    raise AssertionError(f"no free port in {PORT_ATTEMPTS} attempts: {last}")
