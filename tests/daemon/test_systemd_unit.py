"""The shipped systemd unit (config/jtc-hw.service): required settings, and systemd's own check."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[2] / "config" / "jtc-hw.service"


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """Section -> key -> values (a key may repeat), ignoring comments, as systemd reads it."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        assert current is not None, f"assignment outside a section: {line!r}"
        key, sep, value = line.partition("=")
        assert sep, f"not an assignment: {line!r}"
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


@pytest.fixture(scope="module")
def unit() -> dict[str, dict[str, list[str]]]:
    return parse_unit(UNIT.read_text(encoding="utf-8"))


REQUIRED_SERVICE = {
    "Type": "notify",
    "NotifyAccess": "main",
    "ExecStart": "/usr/local/bin/jtc-hw run /etc/jtc-hw/robot.yaml",
    "WatchdogSec": "2",
    "Restart": "on-failure",
    "RestartSec": "2",
    "TimeoutStopSec": "10",
    "KillSignal": "SIGTERM",
    "RuntimeDirectory": "jtc-hw",
    "RuntimeDirectoryMode": "0750",
    "SupplementaryGroups": "dialout",
    "NoNewPrivileges": "yes",
    "ProtectSystem": "strict",
    "ProtectHome": "read-only",
    "PrivateTmp": "yes",
    "ProtectKernelTunables": "yes",
    "ProtectControlGroups": "yes",
    "RestrictAddressFamilies": "AF_UNIX AF_INET AF_INET6 AF_CAN AF_NETLINK",
    "LockPersonality": "yes",
    "LimitRTPRIO": "90",
    "LimitMEMLOCK": "infinity",
    "AmbientCapabilities": "CAP_SYS_NICE CAP_IPC_LOCK",
    # the device locks' directory, the daemons' only, writable under ProtectSystem=strict
    "ExecStartPre": "+/usr/bin/install -d -m 3770 /run/jtc-hw-locks",
    "ReadWritePaths": "-/run/jtc-hw-locks",
}


def test_the_unit_opens_the_directory_the_daemon_locks_devices_in() -> None:
    from jtc_hw.daemon.locks import LOCK_DIR

    assert REQUIRED_SERVICE["ReadWritePaths"] == f"-{LOCK_DIR}"
    assert REQUIRED_SERVICE["ExecStartPre"].endswith(f" {LOCK_DIR}")


def test_the_units_lock_directory_is_one_the_daemon_accepts(tmp_path: Path) -> None:
    """The mode the unit creates it with passes the daemon's check (no other user can use
    it to deny a start), as created by root, the unit's ``+``."""
    from jtc_hw.daemon.locks import check_directory

    words = REQUIRED_SERVICE["ExecStartPre"].split()
    mode = int(words[words.index("-m") + 1], 8)
    assert mode & 0o007 == 0  # others: nothing
    directory = tmp_path / "locks"
    directory.mkdir()
    directory.chmod(mode)
    assert check_directory(str(directory)) is None


@pytest.mark.parametrize(("key", "value"), sorted(REQUIRED_SERVICE.items()))
def test_required_service_setting(
    unit: dict[str, dict[str, list[str]]], key: str, value: str
) -> None:
    assert unit["Service"].get(key) == [value]


def test_the_documentation_is_installed_beside_the_executable(
    unit: dict[str, dict[str, list[str]]],
) -> None:
    """Documentation= names a file that ``pip install`` puts in the prefix of ExecStart's
    ``bin/jtc-hw`` (pyproject's data-files), so adjusting the one prefix keeps both true."""
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover - Python 3.10
        import tomli as tomllib

    (doc,) = unit["Unit"]["Documentation"]
    prefix = unit["Service"]["ExecStart"][0].split()[0].removesuffix("/bin/jtc-hw")
    directory, _, name = doc.removeprefix(f"file://{prefix}/").rpartition("/")
    assert doc.startswith(f"file://{prefix}/") and directory == "share/doc/jtc-hw", doc
    pyproject = tomllib.loads((UNIT.parents[1] / "pyproject.toml").read_text(encoding="utf-8"))
    installed = pyproject["tool"]["setuptools"].get("data-files", {}).get(directory, [])
    (source,) = [f for f in installed if f.rpartition("/")[2] == name] or [None]
    assert source is not None, f"pip installs no {name} to <prefix>/{directory}: {installed}"
    assert (UNIT.parents[1] / source).is_file()


def test_install_section(unit: dict[str, dict[str, list[str]]]) -> None:
    assert unit["Install"] == {"WantedBy": ["multi-user.target"]}


@pytest.mark.parametrize(
    "key",
    [
        "RestrictRealtime",  # forbids SCHED_FIFO
        "PrivateDevices",  # hides serial ports
        "DeviceAllow",  # closes the device policy
        "DevicePolicy",
        "ProtectClock",  # implies DeviceAllow=char-rtc r, closing the device policy
        "PrivateNetwork",  # SocketCAN lives in the host namespace
        "MemoryDenyWriteExecute",
    ],
)
def test_nothing_that_breaks_devices_or_realtime(
    unit: dict[str, dict[str, list[str]]], key: str
) -> None:
    assert key not in unit["Service"]


def test_user_and_group_guidance_is_commented_out() -> None:
    lines = UNIT.read_text(encoding="utf-8").splitlines()
    assert "#User=jtc-hw" in lines
    assert "#Group=jtc-hw" in lines
    assert any("dialout" in line and line.startswith("#") for line in lines)
    assert any("pip install" in line and line.startswith("#") for line in lines)


def test_ambient_capabilities_stay_within_the_bounding_set(
    unit: dict[str, dict[str, list[str]]],
) -> None:
    ambient = set(unit["Service"]["AmbientCapabilities"][0].split())
    bounding = set(unit["Service"]["CapabilityBoundingSet"][0].split())
    assert ambient <= bounding


def test_rtprio_limit_allows_the_documented_priority(
    unit: dict[str, dict[str, list[str]]],
) -> None:
    assert 1 <= int(unit["Service"]["LimitRTPRIO"][0]) <= 99


def verify(path: Path) -> tuple[int, str]:
    tool = shutil.which("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze is not installed")
    proc = subprocess.run(
        [tool, "verify", str(path)], capture_output=True, text=True, timeout=120, check=False
    )
    return proc.returncode, proc.stdout + proc.stderr


def runnable_copy(tmp_path: Path, extra: str = "") -> Path:
    """The unit with ExecStart pointing at an executable that exists here (the test's python)."""
    text = UNIT.read_text(encoding="utf-8")
    lines = [
        f"ExecStart={sys.executable} -c pass" if line.startswith("ExecStart=") else line
        for line in text.splitlines()
    ]
    path = tmp_path / "jtc-hw.service"
    path.write_text("\n".join(lines) + "\n" + extra, encoding="utf-8")
    return path


def test_systemd_analyze_verify_is_clean(tmp_path: Path) -> None:
    rc, output = verify(runnable_copy(tmp_path))
    assert rc == 0, output
    # Parse problems are only warnings (exit 0) naming the file: there must be none.
    assert [line for line in output.splitlines() if "jtc-hw.service" in line] == [], output


def test_verify_would_catch_a_bad_key(tmp_path: Path) -> None:
    # Guards the check above: a typo in the unit does show up in verify's output.
    _rc, output = verify(runnable_copy(tmp_path, extra="[Service]\nWatchdogSecc=2\n"))
    assert "WatchdogSecc" in output


REAL_ROBOT_CONFIGS = ("dynamixel-arm.yaml", "can-mit-leg.yaml", "can-cia402-pair.yaml")


@pytest.mark.parametrize("name", REAL_ROBOT_CONFIGS)
def test_real_robot_examples_serve_where_clients_find_the_unit(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Run by the unit (RUNTIME_DIRECTORY=/run/jtc-hw), a real robot's example serves the
    socket a login shell's client falls back to, not one PrivateTmp would hide."""
    from jtc_hw.api.paths import ROOT_SOCKET_DIR, SOCKET_NAME
    from jtc_hw.daemon.robot import load_robot

    (runtime,) = parse_unit(UNIT.read_text(encoding="utf-8"))["Service"]["RuntimeDirectory"]
    monkeypatch.setenv("RUNTIME_DIRECTORY", f"/run/{runtime}")
    socket_path = load_robot(str(UNIT.parent / name)).daemon.socket
    assert socket_path == f"{ROOT_SOCKET_DIR}/{SOCKET_NAME}" == f"/run/{runtime}/{SOCKET_NAME}"


def test_check_warns_of_a_tmp_socket_the_units_private_tmp_hides(tmp_path: Path) -> None:
    from jtc_hw.daemon.systemd_units import private_tmp_warnings

    config = tmp_path / "robot.yaml"
    config.write_text("")
    units = tmp_path / "system"
    units.mkdir()
    text = UNIT.read_text(encoding="utf-8").replace(
        "run /etc/jtc-hw/robot.yaml", f"run {tmp_path}/./robot.yaml")
    (units / "jtc-hw.service").write_text(text)
    (warning,) = private_tmp_warnings(str(config), "/tmp/arm.sock", [str(units)])
    assert "/tmp/arm.sock is under /tmp" in warning and "PrivateTmp=yes" in warning
    assert private_tmp_warnings(str(config), "/run/jtc-hw/jtc-hw.sock", [str(units)]) == []
    other = tmp_path / "other.yaml"
    other.write_text("")
    assert private_tmp_warnings(str(other), "/tmp/arm.sock", [str(units)]) == []
    (units / "jtc-hw.service").write_text(text.replace("PrivateTmp=yes", "PrivateTmp=no"))
    assert private_tmp_warnings(str(config), "/tmp/arm.sock", [str(units)]) == []


def test_jtc_hw_check_prints_the_private_tmp_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from jtc_hw.cli import main
    from jtc_hw.daemon import systemd_units

    config = tmp_path / "robot.yaml"
    config.write_text((UNIT.parent / "mirror-arm.yaml").read_text(encoding="utf-8"))
    units = tmp_path / "system"
    units.mkdir()
    (units / "jtc-hw.service").write_text(UNIT.read_text(encoding="utf-8").replace(
        "run /etc/jtc-hw/robot.yaml", f"run {config}"))
    monkeypatch.setattr(systemd_units, "UNIT_DIRS", (str(units),))
    assert main(["check", str(config)]) == 0
    assert "warning: daemon.socket /tmp/jtc-hw-mirror-arm.sock is under /tmp, but " in (
        capsys.readouterr().out)
