"""``jtc-hw`` commands of this issue, in process: ``stop``, the socket checks of client
commands, goal files read with alias expansion bounded, and the token warning of ``check``."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers.fake_backend import TOKEN, ServerThread

from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_BAD_INPUT, EXIT_OK
from jtc_hw.cli.goals import load_goal_file
from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.daemon.settings import DaemonSettings
from jtc_hw.errors import ConfigurationError

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

CONFIG = "joints: [j1]\ncommand_interfaces: [position]\nstate_interfaces: [position]\n"


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[ServerThread]:
    srv = ServerThread(DaemonSettings(socket=str(tmp_path / "d.sock"), max_clients=1))
    yield srv
    srv.close()


def test_stop_cancels_the_goal(
    daemon: ServerThread, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    backend = daemon.backend
    traj = JointTrajectory(["j1", "j2"], [TrajectoryPoint(5.0, [0.5, -0.5])])
    goal_id = daemon.call(lambda: backend.ctrl.send_goal(backend.t, traj))
    assert main(["stop", "--socket", str(tmp_path / "d.sock")]) == EXIT_OK
    assert capsys.readouterr().out == (
        "stopped: holding the measured position (an active goal ends canceled)\n"
    )
    results = daemon.call(backend.step, 0.02)
    assert [(r.goal_id, r.status.value) for r in results if hasattr(r, "status")] == [
        (goal_id, "canceled")
    ]
    daemon.call(lambda: backend.ctrl.deactivate(backend.t, "hardware fault: test"))
    assert main(["stop", "--socket", str(tmp_path / "d.sock")]) == EXIT_OK
    assert "nothing to stop: the controller is not active" in capsys.readouterr().out


@pytest.mark.skipif(os.geteuid() != 0, reason="makes a socket of another user: needs root")
def test_client_commands_refuse_a_squatted_default_socket(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    runtime = tmp_path / "xdg"
    runtime.mkdir(0o700)
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.delenv("JTC_HW_SOCKET", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    srv = ServerThread(DaemonSettings(socket=str(runtime / "jtc-hw.sock")))
    try:
        assert main(["status"]) == EXIT_OK  # ours: used
        capsys.readouterr()
        os.chown(runtime / "jtc-hw.sock", 65534, -1)
        for command in (["stop"], ["status"], ["rearm"]):
            assert main(command) == EXIT_BAD_INPUT
            err = capsys.readouterr().err
            assert err.startswith(f"error: refusing the daemon socket {runtime}/jtc-hw.sock: ")
            assert "belongs to uid 65534" in err and "--socket PATH" in err
        monkeypatch.setenv("JTC_HW_SOCKET", str(runtime / "jtc-hw.sock"))
        assert main(["stop"]) == EXIT_OK  # named deliberately
    finally:
        srv.close()


def test_goal_files_are_read_with_alias_expansion_bounded(tmp_path: Path) -> None:
    levels = ["a: &a [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]"]
    for i, name in enumerate("bcdefg"):
        prev = "abcdefg"[i]
        levels.append(f"{name}: &{name} [{', '.join(['*' + prev] * 10)}]")
    bomb = tmp_path / "goal.yaml"
    bomb.write_text("\n".join(levels) + "\njoint_names: [j1]\npoints: *g\n")
    with pytest.raises(ConfigurationError, match="expand it by .* nodes, more than the"):
        load_goal_file(str(bomb))
    duplicate = tmp_path / "dup.yaml"
    duplicate.write_text("joint_names: [j1]\njoint_names: [j2]\npoints: []\n")
    with pytest.raises(ConfigurationError, match="found duplicate key 'joint_names'"):
        load_goal_file(str(duplicate))
    fine = tmp_path / "fine.yaml"
    fine.write_text(
        "joint_names: [j1]\npoints:\n"
        "  - {time_from_start: 1.0, positions: [0.5], velocities: &zero [0.0]}\n"
        "  - {time_from_start: 2.0, positions: [0.0], velocities: *zero}\n"
    )
    assert load_goal_file(str(fine))["trajectory"]["points"][1]["velocities"] == [0.0]


def test_check_and_run_warn_of_a_token_others_can_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(CONFIG + f"daemon: {{socket: {tmp_path}/d.sock, tcp: {{token: {TOKEN}}}}}\n")
    path.chmod(0o644)
    assert main(["check", str(path)]) == EXIT_OK
    out = capsys.readouterr().out
    assert f"warning: {path} holds the TCP token (daemon.tcp.token)" in out
    assert f"chmod 600 {path}" in out
    path.chmod(0o600)
    assert main(["check", str(path)]) == EXIT_OK
    assert "TCP token" not in capsys.readouterr().out
    # (run prints the same warning to its log: tests/daemon/test_stop_under_flood.py)


def test_check_warns_of_a_socket_mode_that_lets_every_user_in(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(CONFIG + f"daemon: {{socket: {tmp_path}/d.sock, socket_mode: 0o777}}\n")
    assert main(["check", str(path)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "warning: daemon.socket_mode 0777 lets every user of this machine connect" in out
    path.write_text(CONFIG + f"daemon: {{socket: {tmp_path}/d.sock, socket_mode: 0o660}}\n")
    assert main(["check", str(path)]) == EXIT_OK
    assert "socket_mode" not in capsys.readouterr().out
    # (run prints the same warning to its log: tests/daemon/test_stop_under_flood.py)


def test_check_says_what_stops_each_components_motors(
    capsys: pytest.CaptureFixture[str],
) -> None:
    root = Path(__file__).resolve().parents[2] / "config"
    assert main(["check", str(root / "dynamixel-arm-emulated.yaml")]) == EXIT_OK
    out = capsys.readouterr().out
    assert "watchdog      Dynamixel Bus Watchdog 100 ms" in out
    assert "warning" not in out
    assert main(["check", str(root / "can-mit-leg-emulated.yaml")]) == EXIT_OK
    out = capsys.readouterr().out
    assert "warning: hardware 'leg': no device-side watchdog for joints hip_roll," in out
    assert "motors keep their last command if the daemon dies" in out


def test_check_refuses_what_run_would_refuse_in_the_hardware_parameters(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    hardware = "hardware:\n  - {name: m, kind: mirror, joints: [j1], params: {lag_s: slow}}\n"
    config = tmp_path / "bad.yaml"
    config.write_text(CONFIG + "update_rate: 100\n" + hardware)
    assert main(["check", str(config)]) == 2
    err = capsys.readouterr().err
    assert "hardware[0].params.lag_s" in err and "OK" not in err


def test_check_resolves_the_speed_scaling_interfaces(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """As ``run`` would: an interface no component offers is refused, naming those offered."""
    hardware = "hardware:\n  - {name: m, kind: mirror, joints: [j1]}\n"
    config = tmp_path / "robot.yaml"
    config.write_text(CONFIG + hardware + "speed_scaling: {state_interface: m/speed_scaling_factor,"
                      " command_interface: m/speed_scaling_factor}\n")
    assert main(["check", str(config)]) == EXIT_OK
    assert ("speed scaling   read from m/speed_scaling_factor, asked through "
            "m/speed_scaling_factor") in capsys.readouterr().out
    config.write_text(CONFIG + hardware + "speed_scaling: {state_interface: m/speed}\n")
    assert main(["check", str(config)]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "speed_scaling.state_interface" in err
    assert "mirror hardware 'm' offers no scalar state interface 'speed'" in err
    assert "scalar state interfaces of this robot: m/speed_scaling_factor" in err
