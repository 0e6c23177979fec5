"""Robot configuration: hardware and daemon sections (jtc_hw.daemon.robot)."""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jtc_hw.api.paths import default_socket_path
from jtc_hw.daemon.robot import RobotConfig, create_hardware_set, load_robot
from jtc_hw.daemon.settings import DaemonSettings, RealtimeSettings, TcpSettings
from jtc_hw.errors import ConfigurationError
from jtc_hw.hardware import HardwareSpec, LifecycleState
from jtc_hw.hardware.mirror import MirrorHardware

EXAMPLE = Path(__file__).resolve().parents[2] / "config" / "mirror-arm.yaml"
TOKEN = "0123456789abcdef"

BASE: dict[str, Any] = {
    "joints": ["j1", "j2", "j3"],
    "command_interfaces": ["position"],
    "state_interfaces": ["position", "velocity"],
}


def robot(**sections: Any) -> dict[str, Any]:
    data = copy.deepcopy(BASE)
    data.update(sections)
    return data


def two_components(**changes: Any) -> list[dict[str, Any]]:
    arm: dict[str, Any] = {"name": "arm", "kind": "mirror", "joints": ["j1", "j3"]}
    hand: dict[str, Any] = {"name": "hand", "kind": "mirror", "joints": ["j2"]}
    arm.update(changes)
    return [arm, hand]


def error_of(source: Any, controller_name: str | None = None) -> ConfigurationError:
    with pytest.raises(ConfigurationError) as info:
        load_robot(source, controller_name)
    return info.value


@pytest.fixture(autouse=True)
def runtime_dir(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """A known default socket directory."""
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    return tmp_path / "xdg"


# --------------------------------------------------------------------------------------------
# The example file
# --------------------------------------------------------------------------------------------


def test_example_config_loads_and_runs(runtime_dir: Path) -> None:
    cfg = load_robot(EXAMPLE)
    assert isinstance(cfg, RobotConfig)
    assert cfg.source_path == str(EXAMPLE)
    c = cfg.controller
    assert c.name == "joint_trajectory_controller"
    assert c.update_rate == 500.0
    assert c.joints == tuple(f"joint{i}" for i in range(1, 7))
    assert c.command_interfaces == ("position",)
    assert c.state_interfaces == ("position", "velocity")
    assert (c.state_publish_rate, c.action_monitor_rate) == (50.0, 20.0)
    assert c.constraints.goal_time == 0.5
    assert {(jc.trajectory, jc.goal) for jc in c.constraints.joints.values()} == {(0.05, 0.01)}
    (spec,) = cfg.hardware
    assert (spec.name, spec.kind, spec.joints, spec.path) == ("arm", "mirror", c.joints,
                                                              "hardware[0]")
    assert dict(spec.params) == {"lag_s": 0.0}
    # Its own socket (each example config has one), not the default in runtime_dir.
    assert cfg.daemon == DaemonSettings(socket="/tmp/jtc-hw-mirror-arm.sock")
    hardware = create_hardware_set(cfg)
    hardware.configure()
    hardware.activate(0)
    np.testing.assert_array_equal(hardware.read(0).positions, np.zeros(6))
    assert hardware.state is LifecycleState.ACTIVE


# --------------------------------------------------------------------------------------------
# hardware
# --------------------------------------------------------------------------------------------


def test_without_a_hardware_section_one_mirror_serves_every_joint() -> None:
    cfg = load_robot(robot())
    assert cfg.source_path is None
    assert cfg.hardware == (
        HardwareSpec("mirror", "mirror", ("j1", "j2", "j3"), ("position",),
                     ("position", "velocity"), {}, "hardware"),
    )
    assert load_robot(robot(hardware=None)).hardware == cfg.hardware
    (component,) = create_hardware_set(cfg).components
    assert isinstance(component, MirrorHardware)


def test_components_take_the_controllers_interfaces() -> None:
    data = robot(hardware=two_components(params={"lag_s": 0.1}))
    data["command_interfaces"] = ["position", "velocity"]
    cfg = load_robot(data)
    assert [(s.name, s.joints, s.path) for s in cfg.hardware] == [
        ("arm", ("j1", "j3"), "hardware[0]"),
        ("hand", ("j2",), "hardware[1]"),
    ]
    for s in cfg.hardware:
        assert s.command_interfaces == ("position", "velocity")
        assert s.state_interfaces == ("position", "velocity")
    assert dict(cfg.hardware[0].params) == {"lag_s": 0.1}
    assert dict(cfg.hardware[1].params) == {}
    hardware = create_hardware_set(cfg)
    assert [c.params["lag_s"] for c in hardware.components] == [0.1, 0.0]


def test_the_nested_layout_with_several_controllers() -> None:
    data = {
        "left": {"ros__parameters": BASE},
        "right": {"ros__parameters": {**BASE, "joints": ["r1"]}},
        "hardware": [{"name": "r", "kind": "mirror", "joints": ["r1"]}],
    }
    cfg = load_robot(data, "right")
    assert cfg.controller.name == "right"
    assert cfg.hardware[0].joints == ("r1",)


@pytest.mark.parametrize(
    ("hardware", "path", "message"),
    [
        ({"name": "arm"}, "hardware",
         "expected a list of components (each with name, kind, joints, params), got {'name': "),
        ([], "hardware",
         "lists no component; list at least one, or remove the key for the default mirror"),
        (["arm"], "hardware[0]", "expected a mapping of component 0, got 'arm' (str)"),
        (two_components(joint=["j1"]), "hardware[0].joint",
         "unknown parameter 'joint' of component 0; did you mean 'joints'?"),
        ([{"kind": "mirror", "joints": ["j1", "j2", "j3"]}], "hardware[0].name",
         "missing required parameter 'name' of component 0 (unique component name)"),
        ([{"name": "arm", "joints": ["j1", "j2", "j3"]}], "hardware[0].kind",
         "missing required parameter 'kind'"),
        ([{"name": "arm", "kind": "mirror"}], "hardware[0].joints",
         "missing required parameter 'joints'"),
        (two_components(name=""), "hardware[0].name", "expected a non-empty name"),
        (two_components(name=3), "hardware[0].name", "expected a string, got 3 (int)"),
        (two_components(name="hand"), "hardware[1].name",
         "'hand' is already the name of hardware[0]; component names must be unique"),
        (two_components(kind="mirorr"), "hardware[0].kind",
         "unknown hardware kind 'mirorr'; available kinds: "),
        (two_components(joints=["j1", "jj3"]), "hardware[0].joints",
         "'jj3' is not a controller joint (joints: j1, j2, j3); did you mean 'j3'?"),
        (two_components(joints=["j1", "j2", "j3"]), "hardware[1].joints",
         "'j2' is already provided by 'arm' (hardware[0]); each joint belongs to exactly one"),
        (two_components(joints=["j1", "j1"]), "hardware[0].joints",
         "contains 'j1' more than once"),
        (two_components(joints=[]), "hardware[0].joints", "must not be empty"),
        (two_components(joints=["j1"]), "hardware",
         "controller joint 'j3' not provided by any component; add each to the joints of one"),
        ([{"name": "arm", "kind": "mirror", "joints": ["j2"]}], "hardware",
         "controller joints 'j1', 'j3' not provided by any component"),
        (two_components(params=[1]), "hardware[0].params", "expected a mapping, got [1] (list)"),
    ],
)
def test_hardware_section_rules(hardware: Any, path: str, message: str) -> None:
    error = error_of(robot(hardware=hardware))
    assert error.path == path
    assert message in str(error)


def test_unknown_kind_lists_the_kinds() -> None:
    error = error_of(robot(hardware=two_components(kind="dynamixle")))
    assert "can-cia402, can-mit, dynamixel" in str(error)
    assert str(error).endswith("did you mean 'dynamixel'?")


def test_component_parameters_are_checked_when_created() -> None:
    cfg = load_robot(robot(hardware=two_components(params={"lag_s": -1})))
    with pytest.raises(ConfigurationError) as info:
        create_hardware_set(cfg)
    assert str(info.value) == "hardware[0].params.lag_s: must be >= 0, got -1"
    cfg = load_robot(robot(hardware=two_components(params={"lagg": 1})))
    with pytest.raises(ConfigurationError) as unknown:
        create_hardware_set(cfg)
    assert unknown.value.path == "hardware[0].params.lagg"
    assert "unknown parameter 'lagg' of mirror hardware 'arm'; did you mean 'lag_s'?" in str(
        unknown.value
    )


def test_controller_errors_come_from_load_config() -> None:
    error = error_of(robot(joints=[]))
    assert error.path == "joints"


# --------------------------------------------------------------------------------------------
# daemon
# --------------------------------------------------------------------------------------------


def test_daemon_defaults(runtime_dir: Path) -> None:
    daemon = load_robot(robot()).daemon
    assert daemon == DaemonSettings(
        socket=str(runtime_dir / "jtc-hw.sock"),
        socket_mode=0o660,
        tcp=None,
        max_clients=16,
        max_message_bytes=4_194_304,
        realtime=RealtimeSettings(priority=0, lock_memory=False, cpu_affinity=()),
        log_level="info",
    )
    assert load_robot(robot(daemon=None)).daemon == daemon
    assert load_robot(robot(daemon={"realtime": None})).daemon == daemon


def test_default_socket_path_order() -> None:
    env = {"RUNTIME_DIRECTORY": "/run/jtc-hw:/run/other", "XDG_RUNTIME_DIR": "/run/user/1000"}
    assert default_socket_path(env) == "/run/jtc-hw/jtc-hw.sock"
    assert default_socket_path({"XDG_RUNTIME_DIR": "/run/user/1000"}) == (
        "/run/user/1000/jtc-hw.sock"
    )
    assert default_socket_path({}, uid=0) == "/run/jtc-hw/jtc-hw.sock"
    assert default_socket_path({}, uid=1000) == "/tmp/jtc-hw-1000/jtc-hw.sock"
    assert default_socket_path({}) == default_socket_path({}, uid=os.geteuid())


def test_default_socket_path_reads_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RUNTIME_DIRECTORY", "/run/jtc-hw")
    assert load_robot(robot()).daemon.socket == "/run/jtc-hw/jtc-hw.sock"


def test_all_daemon_settings(tmp_path: Path) -> None:
    daemon = load_robot(robot(daemon={
        "socket": "/run/jtc/arm.sock",
        "socket_mode": "0600",
        "tcp": {"host": "::1", "port": 8765, "token": TOKEN, "max_clients": 2},
        "max_clients": 4,
        "idle_timeout_s": 60,
        "max_message_bytes": 65536,
        "realtime": {"priority": 80, "lock_memory": True, "cpu_affinity": [2, 3]},
        "log_level": "debug",
    })).daemon
    assert daemon == DaemonSettings(
        socket="/run/jtc/arm.sock",
        socket_mode=0o600,
        tcp=TcpSettings("::1", 8765, TOKEN, max_clients=2),
        max_clients=4,
        idle_timeout_s=60.0,
        max_message_bytes=65536,
        realtime=RealtimeSettings(80, True, (2, 3)),
        log_level="debug",
    )
    assert TOKEN not in repr(daemon)
    tcp = load_robot(robot(daemon={"tcp": {"token": TOKEN}})).daemon.tcp
    assert tcp == TcpSettings("127.0.0.1", 0, TOKEN, max_clients=8)
    assert load_robot(robot(daemon={"idle_timeout_s": 0})).daemon.idle_timeout_s == 0  # never
    assert load_robot(robot(daemon={"tcp": {"host": "localhost", "token": TOKEN}})).daemon.tcp


@pytest.mark.parametrize(
    ("text", "mode"),
    [("0660", 0o660), ("0o640", 0o640), ('"0600"', 0o600), ('"0o660"', 0o660), ("432", 0o660),
     ("'775'", 0o775)],
)
def test_socket_mode_from_yaml(tmp_path: Path, text: str, mode: int) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(
        "joints: [j1]\ncommand_interfaces: [position]\nstate_interfaces: [position]\n"
        f"daemon:\n  socket_mode: {text}\n"
    )
    assert load_robot(path).daemon.socket_mode == mode


def test_relative_socket_is_relative_to_the_file(tmp_path: Path) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(
        "joints: [j1]\ncommand_interfaces: [position]\nstate_interfaces: [position]\n"
        "daemon: {socket: run/jtc.sock}\n"
    )
    cfg = load_robot(str(path))
    assert cfg.source_path == str(path)
    assert cfg.daemon.socket == str(tmp_path / "run" / "jtc.sock")


def test_relative_socket_of_a_mapping_is_relative_to_the_cwd(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert load_robot(robot(daemon={"socket": "x.sock"})).daemon.socket == str(
        tmp_path / "x.sock"
    )


@pytest.mark.parametrize(
    ("daemon", "path", "message"),
    [
        ([], "daemon", "expected a mapping, got [] (list)"),
        ({"sockets": "/x"}, "daemon.sockets",
         "unknown parameter 'sockets'; did you mean 'socket'?"),
        ({"socket": 5}, "daemon.socket", "expected a string, got 5 (int)"),
        ({"socket": " "}, "daemon.socket",
         "is empty; give a path, or remove the key for the default"),
        ({"socket": "/" + "s" * 107}, "daemon.socket",
         "is 108 bytes long; a Unix socket path holds at most 107: choose a shorter directory"),
        ({"socket_mode": 660}, "daemon.socket_mode",
         "660 is not a permission mode (0 to 0o777); write it in octal: 0660 or \"0660\""),
        ({"socket_mode": "rw-rw----"}, "daemon.socket_mode",
         "expected an octal file mode such as \"0660\", got 'rw-rw----'"),
        ({"socket_mode": "0400"}, "daemon.socket_mode",
         "0o400 does not give the owner read and write permission (0o600)"),
        ({"socket_mode": 4.0}, "daemon.socket_mode", "expected a file mode"),
        ({"socket_mode": True}, "daemon.socket_mode", "expected a file mode"),
        ({"tcp": {"host": "0.0.0.0", "token": TOKEN}}, "daemon.tcp.host",
         "'0.0.0.0' is not a loopback address (127.0.0.0/8, ::1 or localhost)"),
        ({"tcp": {"host": "robot.lan", "token": TOKEN}}, "daemon.tcp.host",
         "not a loopback address"),
        ({"tcp": {"port": 8765}}, "daemon.tcp.token", "missing required parameter 'token'"),
        ({"tcp": {"token": "short"}}, "daemon.tcp.token",
         "must be at least 16 characters long, got 5; generate one with"),
        ({"tcp": {"token": TOKEN, "port": 70000}}, "daemon.tcp.port",
         "must be between 0 and 65535, got 70000"),
        ({"tcp": {"token": TOKEN, "prot": 1}}, "daemon.tcp.prot", "did you mean 'port'?"),
        ({"tcp": "127.0.0.1:8765"}, "daemon.tcp", "expected a mapping"),
        ({"max_clients": 0}, "daemon.max_clients", "must be >= 1, got 0"),
        ({"max_clients": "16"}, "daemon.max_clients", "expected an integer, got '16' (str)"),
        ({"max_message_bytes": 100}, "daemon.max_message_bytes", "must be >= 1024, got 100"),
        ({"idle_timeout_s": -1}, "daemon.idle_timeout_s", "must be >= 0, got -1"),
        ({"idle_timeout_s": "5m"}, "daemon.idle_timeout_s", "expected a number, got '5m'"),
        ({"tcp": {"token": TOKEN, "max_clients": 0}}, "daemon.tcp.max_clients",
         "must be >= 1, got 0"),
        ({"realtime": {"priority": 100}}, "daemon.realtime.priority",
         "must be between 0 and 99, got 100"),
        ({"realtime": {"priority": -1}}, "daemon.realtime.priority", "must be between 0 and 99"),
        ({"realtime": {"lock_memory": "yes"}}, "daemon.realtime.lock_memory",
         "expected true or false, got 'yes' (str)"),
        ({"realtime": {"cpu_affinity": [1, 1]}}, "daemon.realtime.cpu_affinity",
         "contains 1 more than once"),
        ({"realtime": {"cpu_affinity": [-1]}}, "daemon.realtime.cpu_affinity",
         "element 0: must be >= 0, got -1"),
        ({"realtime": {"cpu_afinity": [1]}}, "daemon.realtime.cpu_afinity",
         "did you mean 'cpu_affinity'?"),
        ({"log_level": "warn"}, "daemon.log_level",
         "'warn' is not allowed; allowed values: 'debug', 'info', 'warning', 'error'; "
         "did you mean 'warning'?"),
    ],
)
def test_daemon_section_rules(daemon: Any, path: str, message: str) -> None:
    error = error_of(robot(daemon=daemon))
    assert error.path == path
    assert message in str(error)


def test_a_short_token_is_never_echoed() -> None:
    error = error_of(robot(daemon={"tcp": {"token": "secret-ish"}}))
    assert "secret-ish" not in str(error) and error.value is None


def test_settings_check_themselves_when_built_directly() -> None:
    with pytest.raises(ConfigurationError, match="daemon.socket: expected an absolute path"):
        DaemonSettings(socket="relative.sock")
    with pytest.raises(ConfigurationError, match="daemon.tcp.host"):
        TcpSettings(host="10.0.0.2", token=TOKEN)
    assert "token" not in repr(TcpSettings(token=TOKEN))


# --------------------------------------------------------------------------------------------
# Reading files
# --------------------------------------------------------------------------------------------


def test_the_daemon_settings_reach_the_server(tmp_path: Path) -> None:
    from helpers.fake_backend import FakeBackend

    from jtc_hw.daemon.transports.server import Server

    daemon = load_robot(robot(daemon={
        "socket": str(tmp_path / "d.sock"), "max_clients": 3, "idle_timeout_s": 30,
        "tcp": {"token": TOKEN, "max_clients": 5, "auth_failure_delay_s": 0.25},
        "socket_group": "robot",
    })).daemon
    settings = Server(FakeBackend(), daemon).settings
    assert settings is daemon
    assert settings.socket_group == "robot" and settings.tcp is not None
    assert settings.tcp.auth_failure_delay_s == 0.25
    assert (settings.max_clients, settings.idle_timeout_s) == (3, 30.0)
    assert settings.tcp is not None and settings.tcp.max_clients == 5
    assert settings.tcp.auth_timeout_s == 1.0 and settings.tcp.max_unauthenticated == 16


BOMB = """\
joints: [j1]
command_interfaces: [position]
state_interfaces: [position]
hardware:
  - name: arm
    kind: mirror
    joints: [j1]
    params:
      a: &a [x, x, x, x, x, x, x, x, x, x]
      b: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]
      c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b, *b]
      d: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c, *c]
      e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d, *d]
      f: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e, *e]
      g: &g [*f, *f, *f, *f, *f, *f, *f, *f, *f, *f]
"""


def test_yaml_alias_expansion_is_bounded(tmp_path: Path) -> None:
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(BOMB)
    error = error_of(bomb)
    assert str(error) == (
        f"configuration file {bomb}: its aliases (*name) expand it by 12,345,660 nodes, more "
        "than the 1,000,000 allowed (an alias bomb?); write the repeated values out, or nest "
        "fewer aliases"
    )
    recursive = tmp_path / "recursive.yaml"
    recursive.write_text("joints: &j [j1, *j]\n")
    assert "an anchor is used inside itself (line 1, column 9)" in str(error_of(recursive))
    # Aliases within the bound are ordinary YAML.
    fine = tmp_path / "fine.yaml"
    fine.write_text(
        "joints: &j [j1, j2]\ncommand_interfaces: [position]\nstate_interfaces: [position]\n"
        "hardware: [{name: arm, kind: mirror, joints: *j}]\n"
    )
    assert load_robot(fine).hardware[0].joints == ("j1", "j2")


def test_a_tcp_token_readable_by_others_gets_a_warning(tmp_path: Path) -> None:
    from jtc_hw.daemon.robot import security_warnings

    path = tmp_path / "robot.yaml"
    path.write_text(
        "joints: [j1]\ncommand_interfaces: [position]\nstate_interfaces: [position]\n"
        f"daemon: {{tcp: {{token: {TOKEN}}}}}\n"
    )
    path.chmod(0o644)
    (warning,) = security_warnings(load_robot(path))
    assert warning == (
        f"{path} holds the TCP token (daemon.tcp.token) and is readable by its group and "
        "every user (mode 0644): whoever reads it can command the robot over TCP. Make it "
        f"private: chmod 600 {path} (owned by the daemon's user)"
    )
    path.chmod(0o640)
    assert "readable by its group (mode 0640)" in security_warnings(load_robot(path))[0]
    path.chmod(0o600)
    assert security_warnings(load_robot(path)) == []
    path.write_text("joints: [j1]\ncommand_interfaces: [position]\nstate_interfaces: [position]\n")
    path.chmod(0o644)
    assert security_warnings(load_robot(path)) == []  # no token in it


def test_file_errors(tmp_path: Path) -> None:
    missing = error_of(tmp_path / "nope.yaml")
    assert "cannot read configuration file" in str(missing)
    duplicate = tmp_path / "dup.yaml"
    duplicate.write_text("joints: [j1]\njoints: [j2]\n")
    assert "found duplicate key 'joints'" in str(error_of(duplicate))
    with pytest.raises(TypeError):
        load_robot(3)  # type: ignore[arg-type]


def test_watchdog_shorter_than_three_loop_periods_is_refused(tmp_path: Path) -> None:
    from jtc_hw.daemon.robot import create_hardware_set
    from jtc_hw.hardware import WATCHDOG_PARAM, HardwareInterface, param_table, register_hardware
    from jtc_hw.hardware.registry import unregister_hardware

    class Watched(HardwareInterface):
        kind = "watched-test"
        PARAMS = param_table(WATCHDOG_PARAM)

        def _read(self, now_ns: int) -> Any:
            raise NotImplementedError

        def _write(self, now_ns: int, command: Any) -> None:
            raise NotImplementedError

    register_hardware("watched-test", Watched)
    try:
        def robot(watchdog_s: float) -> Any:
            return load_robot({
                "joints": ["j1"], "command_interfaces": ["position"],
                "state_interfaces": ["position"], "update_rate": 100.0,
                "hardware": [{"name": "w", "kind": "watched-test", "joints": ["j1"],
                              "params": {"watchdog_s": watchdog_s}}],
            })

        assert create_hardware_set(robot(0.03)).components[0].params["watchdog_s"] == 0.03
        with pytest.raises(ConfigurationError) as caught:
            create_hardware_set(robot(0.029))
        assert caught.value.path == "hardware[0].params.watchdog_s"
        assert "shorter than 3 loop periods (30 ms at 100 Hz)" in str(caught.value)
    finally:
        unregister_hardware("watched-test")


def test_a_socket_mode_that_lets_every_user_in_gets_a_warning(tmp_path: Path) -> None:
    from jtc_hw.daemon.robot import security_warnings

    def warnings(mode: str) -> list[str]:
        path = tmp_path / "robot.yaml"
        path.write_text(
            "joints: [j1]\ncommand_interfaces: [position]\nstate_interfaces: [position]\n"
            f"daemon: {{socket: {tmp_path}/d.sock, socket_mode: '{mode}'}}\n"
        )
        return security_warnings(load_robot(path))

    assert warnings("0777") == [
        f"daemon.socket_mode 0777 lets every user of this machine connect to the daemon's "
        f"socket ({tmp_path}/d.sock) and command the robot. Use 0660 and let in those who "
        "may, through the socket's group (daemon.socket_group)"
    ]
    assert "socket_mode 0606" in warnings("0606")[0]  # any bit for others
    assert warnings("0604") != [] and warnings("0601") != []
    assert warnings("0660") == [] and warnings("0600") == []  # the group is the door


def test_speed_scaling_interfaces_are_a_components_scalar_interfaces() -> None:
    """Upstream's ``speed_scaling.state_interface`` / ``command_interface``: a component's
    scalar interface ``<component>/<name>``, resolved when the hardware is created (the daemon's
    start and ``jtc-hw check``); an unknown one is a clear error listing those offered."""
    good = {"state_interface": "hand/speed_scaling_factor",
            "command_interface": "arm/speed_scaling_factor"}
    hardware = create_hardware_set(load_robot(robot(hardware=two_components(),
                                                    speed_scaling=good)))
    component, name = hardware.scalar_interface("hand/speed_scaling_factor", "state")
    assert (component.name, name) == ("hand", "speed_scaling_factor")
    for scaling, message in [
        ({"state_interface": "hand/speed_scaling"},
         "'hand/speed_scaling': mirror hardware 'hand' offers no scalar state interface "
         "'speed_scaling'; scalar state interfaces of this robot: arm/speed_scaling_factor, "
         "hand/speed_scaling_factor; did you mean 'hand/speed_scaling_factor'?"),
        ({"command_interface": "hnad/speed_scaling_factor"},
         "'hnad/speed_scaling_factor': no hardware component is named 'hnad'"),
    ]:
        cfg = load_robot(robot(hardware=two_components(), speed_scaling=scaling))
        with pytest.raises(ConfigurationError) as info:
            create_hardware_set(cfg)
        assert message in str(info.value)
        assert info.value.path == f"speed_scaling.{next(iter(scaling))}"
