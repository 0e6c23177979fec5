"""``daemon.zenoh``'s settings and security rule (no Zenoh session: runs without the extra)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from jtc_hw.daemon.robot import load_robot
from jtc_hw.daemon.zenoh_config import default_prefix, endpoint_is_loopback
from jtc_hw.errors import ConfigurationError

from conftest import make_robot_config

TOKEN = "a token of the zenoh door"


def robot(tmp_path: Path, **zenoh: Any) -> Any:
    hardware = [{"name": "m", "kind": "mirror", "joints": ["j1"]}]
    zenoh = {"token": TOKEN, **zenoh}
    return load_robot(make_robot_config(tmp_path / "d.sock", ["j1"], hardware, zenoh=zenoh))


@pytest.mark.parametrize(("endpoint", "loopback"), [
    ("tcp/127.0.0.1:7447", True),
    ("tcp/127.3.2.1:0", True),
    ("tcp/[::1]:7447", True),
    ("tcp/localhost:7447", True),
    ("udp/127.0.0.1:7447#iface=lo", True),
    ("unixsock-stream//tmp/zenoh.sock", True),
    ("tcp/0.0.0.0:7447", False),
    ("tcp/[::]:0", False),
    ("tcp/192.168.1.20:7447", False),
    ("tls/robot.example.org:7447", False),
    ("tcp/127.0.0.1", True),
])
def test_endpoint_is_loopback(endpoint: str, loopback: bool) -> None:
    assert endpoint_is_loopback(endpoint) is loopback


def test_defaults_and_prefix(tmp_path: Path) -> None:
    assert load_robot(make_robot_config(tmp_path / "d.sock", ["j1"], [
        {"name": "m", "kind": "mirror", "joints": ["j1"]}])).daemon.zenoh is None
    z = robot(tmp_path, listen=["tcp/127.0.0.1:7447"]).daemon.zenoh
    assert z is not None and z.prefix is None and z.mode is None and not z.multicast_scouting
    prefix = z.resolved_prefix("joint_trajectory_controller")
    assert prefix == default_prefix("joint_trajectory_controller")
    assert prefix.startswith("jtc/") and prefix.endswith("/joint_trajectory_controller")
    assert prefix.count("/") == 2
    z = robot(tmp_path, prefix="jtc/lab/arm1", connect=["tcp/10.0.0.2:7447"]).daemon.zenoh
    assert z is not None and z.resolved_prefix("x") == "jtc/lab/arm1"


@pytest.mark.parametrize(("zenoh", "path", "words"), [
    ({"listen": ["tcp/0.0.0.0:7447"]}, "daemon.zenoh.listen", "neither TLS nor authentication"),
    ({"listen": ["tls/192.168.1.2:7447"]}, "daemon.zenoh.listen", "listen_certificate"),
    ({}, "daemon.zenoh", "reach nobody"),
    ({"listen": ["127.0.0.1:7447"]}, "daemon.zenoh.listen", "<protocol>/<address>:<port>"),
    ({"prefix": "jtc/*/arm", "listen": ["tcp/127.0.0.1:0"]}, "daemon.zenoh.prefix", "wildcards"),
    ({"prefix": "/jtc/arm", "listen": ["tcp/127.0.0.1:0"]}, "daemon.zenoh.prefix", "leading"),
    ({"mode": "router", "listen": ["tcp/127.0.0.1:0"]}, "daemon.zenoh.mode", "peer"),
    ({"config": "nowhere.json5", "listen": ["tcp/127.0.0.1:0"]}, "daemon.zenoh.config",
     "is not a file"),
    ({"listen": ["tcp/127.0.0.1:0"], "lease": 3}, "daemon.zenoh.lease", ""),
    ({"listen": ["tcp/127.0.0.1:0"], "token": None}, "daemon.zenoh.token", "secrets.token_hex"),
    ({"listen": ["tcp/127.0.0.1:0"], "token": "short"}, "daemon.zenoh.token", "at least 16"),
])
def test_refused(tmp_path: Path, zenoh: dict[str, Any], path: str, words: str) -> None:
    with pytest.raises(ConfigurationError) as info:
        robot(tmp_path, **zenoh)
    assert info.value.path == path, str(info.value)
    assert words in str(info.value)


def test_multicast_alone_reaches_someone(tmp_path: Path) -> None:
    z = robot(tmp_path, multicast_scouting=True).daemon.zenoh
    assert z is not None and z.multicast_scouting


def test_the_files_own_listen_endpoints_are_checked(tmp_path: Path) -> None:
    pytest.importorskip("zenoh", reason="reading a Zenoh configuration file needs jtc_hw[zenoh]")
    wide = tmp_path / "wide.json5"
    wide.write_text('{listen: {endpoints: ["tcp/0.0.0.0:7447"]}}  // JSON5, as Zenoh reads it')
    with pytest.raises(ConfigurationError, match="tcp/0.0.0.0:7447 is reachable") as info:
        robot(tmp_path, config=str(wide))
    assert info.value.path == "daemon.zenoh.listen"
    tls = tmp_path / "tls.json5"
    tls.write_text('{listen: {endpoints: ["tls/0.0.0.0:7447"]}, transport: {link: {tls: {'
                   'listen_certificate: "cert.pem", listen_private_key: "key.pem"}}}}')
    z = robot(tmp_path, config=str(tls)).daemon.zenoh
    assert z is not None and z.config == str(tls)
    # Our section's listen replaces the file's.
    assert robot(tmp_path, config=str(wide), listen=["tcp/127.0.0.1:0"]).daemon.zenoh


def test_the_loop_process_name_is_the_loops() -> None:
    from jtc_hw.daemon.loop.cycle import LOOP_PROCESS_NAME
    from jtc_hw.daemon.zenoh_config import LOOP_PROCESS

    assert LOOP_PROCESS == LOOP_PROCESS_NAME
