"""End to end: joint limits on ``python -m jtc_hw run`` over simulated (mirror) joints
(issue 12 part A). The API process's planner checks goals against the robot file's limits,
rejects one whose spline overshoots, slows one sent with ``time_scaling: fit`` (the reply says
by how much), and the loop then executes the slowed reference: its published desired velocity
stays within the limit."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import yaml
from helpers.daemon import JOINTS, WAIT_S, DaemonProcess, connect

from jtc_hw import GoalRejected

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

LIMIT = 0.5  # rad/s on joint1


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    d = DaemonProcess(tmp_path_factory.mktemp("limits"))
    robot = yaml.safe_load(d.config_path.read_text())
    robot["limits"] = {JOINTS[0]: {"velocity": LIMIT, "acceleration": 4.0}}
    d.config_path.write_text(yaml.safe_dump(robot, sort_keys=False))
    with d.serving():
        yield d


def overshooting(target: float) -> dict[str, object]:
    """Waypoint velocities of 0.45 rad/s at most, but the cubic lead-in from rest to
    (0.6 rad, 0.45 rad/s) in 1 s peaks at 0.81 rad/s (t = 0.6 s), beyond the 0.5 rad/s limit."""
    zeros = [0.0] * 6
    return {
        "joint_names": JOINTS,
        "points": [
            {"time_from_start": 1.0, "positions": [target] + zeros[1:],
             "velocities": [0.45] + zeros[1:]},
            {"time_from_start": 2.0, "positions": [target + 0.1] + zeros[1:],
             "velocities": zeros},
        ],
    }


def test_a_goal_beyond_the_limits_is_rejected_and_fit_slows_it(daemon: DaemonProcess) -> None:
    with connect(daemon) as client:
        with pytest.raises(GoalRejected) as rejected:
            client.send_goal(overshooting(0.6))
        message = str(rejected.value)
        assert "joint 'joint1' exceeds its velocity limit at t = " in message
        assert "in the lead-in" in message and "> 0.5 per second" in message

        with client.subscribe_state(timeout_s=WAIT_S, maxlen=10_000) as states:
            handle = client.send_goal(overshooting(0.6), time_scaling="fit")
            assert handle.time_scale is not None and handle.time_scale > 1.0
            assert handle.duration_s == pytest.approx(2.0 * handle.time_scale, rel=1e-6)
            result = handle.wait(timeout_s=WAIT_S + handle.duration_s)
            peak = 0.0
            while True:  # every state published up to the result
                try:
                    state = states.get(timeout_s=0.0)
                except TimeoutError:
                    break
                peak = max(peak, abs(state["desired"]["velocities"][0]))
        assert result["status"] == "succeeded", result
        assert 0.3 < peak <= LIMIT * (1 + 1e-6)
        assert client.get_config()["controller"]["limits"]["joint1"]["velocity"] == LIMIT
