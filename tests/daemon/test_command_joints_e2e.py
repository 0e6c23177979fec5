"""Issue 11, part C through the daemon: a subset of command joints end to end, the refusal of
renamed (chained) command joints, and the controller state fields of the ``state`` message
(sections 1, 12 and 16 of ../shared/reference/jtc_upstream_behaviour.md).

The daemon is a real process on mirror joints (tests/helpers/daemon.py); waits are on messages
with deadlines, and times compared are the daemon's own stamps.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from helpers.daemon import (
    GOAL_TOL,
    JOINTS,
    MS,
    PATH_TOL,
    WAIT_S,
    DaemonProcess,
    connect,
    next_state,
    settle,
    traj,
)

from jtc_hw import ConfigurationError
from jtc_hw.daemon.robot import load_robot

from conftest import make_robot_config

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

COMMANDED = JOINTS[:3]


def subset_config(socket_path: Path, command_joints: list[str]) -> dict[str, object]:
    hardware = [{"name": "arm", "kind": "mirror", "joints": JOINTS, "params": {"lag_s": 0.0}}]
    return make_robot_config(
        socket_path,
        JOINTS,
        hardware,
        path_tolerance=PATH_TOL,
        goal_tolerance=GOAL_TOL,
        controller={"command_joints": command_joints},
    )


@pytest.fixture(scope="module")
def subset_arm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    """A daemon whose controller commands joint1-3 and only monitors joint4-6."""
    d = DaemonProcess(tmp_path_factory.mktemp("subset"))
    d.config_path.write_text(yaml.safe_dump(subset_config(d.socket, COMMANDED), sort_keys=False))
    with d.serving():
        yield d


def test_subset_of_command_joints_moves_only_those(subset_arm: DaemonProcess) -> None:
    """Sections 1 and 12: commands reach the command joints only; the state's ``command`` and
    ``output`` are null for the others (section 16), which stay where they are."""
    with connect(subset_arm) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        target = [0.3, -0.3, 0.2, *p0[3:]]  # the monitored joints are asked to stay
        goal = client.send_goal(traj(target, 0.5))
        moving = next_state(sub, lambda s: s["active_goal"] == goal.goal_id)
        assert moving["command"]["positions"][3:] == [None] * 3
        assert all(isinstance(v, float) for v in moving["command"]["positions"][:3])
        result = goal.wait(timeout_s=WAIT_S)
        assert result["status"] == "succeeded", result
        state = settle(sub, result["time_ns"] + 50 * MS)
        assert state["actual"]["positions"] == pytest.approx(target, abs=GOAL_TOL)
        assert state["output"]["positions"][3:] == [None] * 3
        assert state["output"]["positions"][:3] == pytest.approx(target[:3], abs=1e-9)


def test_a_monitored_joint_that_is_asked_to_move_aborts_the_goal(
    subset_arm: DaemonProcess,
) -> None:
    """Section 1: joints outside command_joints are monitored: their tolerances still apply."""
    with connect(subset_arm) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        target = [*p0[:4], p0[4] + 0.5, p0[5]]  # joint5 is not commanded: it cannot follow
        result = client.send_goal(traj(target, 0.5)).wait(timeout_s=WAIT_S)
        assert (result["status"], result["error_code"]) == ("aborted", -4), result
        state = settle(sub, result["time_ns"])
        assert state["actual"]["positions"][4] == p0[4]


def test_state_message_carries_time_from_start_accelerations_and_output(
    subset_arm: DaemonProcess,
) -> None:
    """Section 16: reference and feedback time_from_start; feedback accelerations only with
    an acceleration state interface (null here); output of the configured interfaces."""
    with connect(subset_arm) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        start = client.hello()["now_ns"] + 200 * MS
        goal = client.send_goal(traj(p0, 1.0, start_time_ns=start))
        state = next_state(
            sub, lambda s: s["active_goal"] == goal.goal_id and s["time_ns"] >= start
        )
        expected = (state["time_ns"] - start) / 1e9
        assert state["desired"]["time_from_start"] == pytest.approx(expected, abs=1e-9)
        assert state["actual"]["time_from_start"] == pytest.approx(expected, abs=1e-9)
        assert state["actual"]["accelerations"] is None
        assert set(state["output"]) == {"positions"}
        assert goal.wait(timeout_s=WAIT_S)["status"] == "succeeded"


def test_the_daemon_refuses_renamed_command_joints(tmp_path: Path) -> None:
    """Section 1: as many command joints with other names chains to another controller in
    ros2_control; the daemon drives its hardware joints itself and says so."""
    config = subset_config(tmp_path / "d.sock", [f"other{i}" for i in range(1, 7)])
    with pytest.raises(ConfigurationError, match="command_joints: .* names other joints") as err:
        load_robot(config)
    assert "a subset of joints" in str(err.value)
