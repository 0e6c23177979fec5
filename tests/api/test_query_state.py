"""Issue 11, point 2 (section 16 of jtc_upstream_behaviour.md, query_state) through the socket
op, the Python client, ``jtc-hw query`` and the daemon's replica (``LoopBackend``), and point 1's
warning in ``jtc-hw check``. The server runs the real controller on a simulated clock
(``helpers.fake_backend``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers.fake_backend import ServerThread

from jtc_hw import JointTrajectory, Trajectory, TrajectoryPoint
from jtc_hw.api.client import Client
from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_OK
from jtc_hw.controller.joints import JointCommand
from jtc_hw.daemon.channel.messages import Reference, State
from jtc_hw.daemon.core.backend import LoopBackend
from jtc_hw.daemon.robot import load_robot

from conftest import make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

S = 1_000_000_000
MS = 1_000_000


def test_query_state_reply_carries_upstreams_success(daemon: ServerThread, sock: Path) -> None:
    """Section 16: success only strictly inside the trajectory; at or after the last point
    success false with the last point's values (also while holding), before the start success
    false with the measured state."""
    backend = daemon.backend
    with Client.connect(sock, timeout_s=5.0) as client:
        held = client.query_state(in_s=0.0)
        assert (held["success"], held["where"]) == (False, "after_end")
        goal = client.send_goal(JointTrajectory(["j1", "j2"], [TrajectoryPoint(1.0, [1.0, 2.0])]))
        t = backend.t
        inside = client.query_state(time_ns=t + S // 2)
        assert (inside["success"], inside["where"]) == (True, "inside")
        assert inside["positions"] == pytest.approx([0.5, 1.0])
        end = client.query_state(time_ns=t + S)
        assert (end["success"], end["where"], end["positions"]) == (False, "after_end", [1.0, 2.0])
        before = client.query_state(time_ns=t - S)
        assert (before["success"], before["where"]) == (False, "before_start")
        assert before["positions"] == [0.0, 0.0]  # the mirror's measured position
        daemon.call(backend.step, 1.1)
        assert goal.wait(timeout_s=5.0)["status"] == "succeeded"


def test_jtc_hw_query_says_when_the_time_is_outside_the_trajectory(
    daemon: ServerThread, sock: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Section 16 through ``jtc-hw query``: a time past the end is reported as success false."""
    backend = daemon.backend
    traj = JointTrajectory(["j1", "j2"], [TrajectoryPoint(1.0, [0.5, -0.5])])
    daemon.call(lambda: backend.ctrl.send_goal(backend.t, traj))
    assert main(["query", "0.5", "--socket", str(sock)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "desired state in 0.5 s:" in out and "success: false" not in out
    assert main(["query", "2", "--socket", str(sock)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "success: false (at or after the last point; these are its values)" in out


def test_loop_backend_replica_answers_query_state_as_the_controller(tmp_path: Path) -> None:
    """Section 16 in the daemon's API process: the replica reference answers, carrying the
    loop's last published measured state before the reference's start."""
    robot = load_robot(
        make_robot_config(
            tmp_path / "d.sock",
            ["j1", "j2"],
            [{"name": "m", "kind": "mirror", "joints": ["j1", "j2"]}],
        )
    )
    backend = LoopBackend(robot, str(tmp_path / "robot.yaml"))
    ref = Trajectory.constant(10 * S, [0.1, 0.2])
    backend._dispatch(Reference(1, ref, None))
    held = backend.query_state(10 * S)
    assert (held.success, held.where) == (False, "after_end")
    before = backend.query_state(9 * S)  # no state published yet: the reference's first
    assert (before.success, before.where) == (False, "before_start")
    np.testing.assert_array_equal(before.positions, [0.1, 0.2])
    state = State(
        10 * S,
        np.zeros((4, 2)),
        np.array([0.15, 0.25]),
        np.array([0.5, -0.5]),
        np.zeros((3, 2)),
        JointCommand(np.array([0.15, 0.25]), None, None, None),
        True,
        None,
        0.0,
        0.0,
        None,
        JointCommand(np.array([0.15, 0.25]), None, None, None),
        1.0,
        1.0,
        10 * S,
    )
    backend._dispatch(state)
    before = backend.query_state(9 * S)
    np.testing.assert_array_equal(before.positions, [0.15, 0.25])
    np.testing.assert_array_equal(before.velocities, [0.5, -0.5])


def test_check_warns_when_an_end_velocity_keeps_joints_moving(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Section 4.3 step 6 in ``jtc-hw check``: non-zero end velocities allowed, a velocity
    command interface and no cmd_timeout."""
    path = tmp_path / "robot.yaml"
    base = (
        "joints: [j1]\ncommand_interfaces: [position, velocity]\n"
        "state_interfaces: [position, velocity]\nallow_nonzero_velocity_at_trajectory_end: true\n"
    )
    path.write_text(base)
    assert main(["check", str(path)]) == EXIT_OK
    out = capsys.readouterr().out
    assert "a trajectory ending with a velocity keeps the joints moving" in out
    path.write_text(base + "cmd_timeout: 0.5\n")
    assert main(["check", str(path)]) == EXIT_OK
    assert "keeps the joints moving" not in capsys.readouterr().out
