"""``time_scaling`` on the wire (issue 12 part A): the request field, the reply's factor and
duration, the Python client and ``jtc-hw send --time-scaling``; the real server over the
stand-in backend, whose controller has joint limits."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from helpers.fake_backend import FakeBackend, ServerThread

from jtc_hw import GoalRejected, JointTrajectory, TrajectoryPoint
from jtc_hw.api.client import Client
from jtc_hw.api.framing import RequestError
from jtc_hw.api.protocol import parse_request
from jtc_hw.api.requests import SendGoal, SendTrajectory
from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_OK
from jtc_hw.daemon.settings import DaemonSettings

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

WIRE = {"joint_names": ["j1", "j2"], "points": [{"time_from_start": 1.0, "positions": [1, 0]}]}


def test_the_request_field_is_parsed_and_checked() -> None:
    goal = parse_request({"op": "send_goal", "id": 1, "trajectory": WIRE, "time_scaling": "fit"})
    assert isinstance(goal, SendGoal) and goal.time_scaling == "fit"
    plain = parse_request({"op": "send_goal", "id": 1, "trajectory": WIRE})
    assert isinstance(plain, SendGoal) and plain.time_scaling is None
    topic = parse_request(
        {"op": "send_trajectory", "trajectory": WIRE, "time_scaling": "reject"}
    )
    assert isinstance(topic, SendTrajectory) and topic.time_scaling == "reject"
    with pytest.raises(RequestError) as bad:
        parse_request({"op": "send_goal", "id": 2, "trajectory": WIRE, "time_scaling": "fti"})
    assert bad.value.code == "bad_request" and bad.value.request_id == 2
    assert str(bad.value.message).startswith("time_scaling: 'fti' is not one of 'reject', 'fit'")
    assert "did you mean 'fit'?" in bad.value.message
    with pytest.raises(RequestError, match="time_scaling: expected a string"):
        parse_request({"op": "send_goal", "trajectory": WIRE, "time_scaling": True})


@pytest.fixture
def daemon(sock: Path) -> Iterator[ServerThread]:
    backend = FakeBackend(limits={"j1": {"velocity": 0.5}})
    srv = ServerThread(DaemonSettings(socket=str(sock)), backend)
    yield srv
    srv.close()


def fast() -> JointTrajectory:
    """1 rad in 1 s, position only (linear): 1 rad/s, twice the limit."""
    return JointTrajectory(["j1", "j2"], [TrajectoryPoint(1.0, [1.0, 0.0])])


def test_a_goal_beyond_the_limits_is_rejected_with_the_joint_and_time(client: Client) -> None:
    with pytest.raises(GoalRejected) as rejected:
        client.send_goal(fast())
    assert rejected.value.error_code == -1
    assert "joint 'j1' exceeds its velocity limit at t = 0 s" in str(rejected.value)
    assert "|velocity| 1 > 0.5" in str(rejected.value)


def test_fit_says_the_factor_and_the_new_duration(client: Client) -> None:
    handle = client.send_goal(fast(), time_scaling="fit")
    assert handle.time_scale == pytest.approx(2.0, rel=1e-6)
    assert handle.duration_s == pytest.approx(2.0, rel=1e-6)
    reply = client.send_trajectory(fast(), time_scaling="fit")
    assert reply["time_scale"] == pytest.approx(2.0, rel=1e-6)
    assert reply["duration_s"] == pytest.approx(2.0, rel=1e-6)
    # Without fit in effect the replies carry no scaling fields.
    slow = JointTrajectory(["j1", "j2"], [TrajectoryPoint(4.0, [1.0, 0.0])])
    assert client.send_goal(slow).time_scale is None
    assert "time_scale" not in client.send_trajectory(slow)


def test_jtc_hw_send_time_scaling_fit(
    daemon: ServerThread, sock: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    goal = tmp_path / "goal.yaml"
    goal.write_text(yaml.safe_dump({"trajectory": WIRE}))
    code = main(["send", str(goal), "--socket", str(sock), "--time-scaling", "fit", "--topic"])
    assert code == EXIT_OK
    out = capsys.readouterr().out
    assert "trajectory sent (1 points, 2.00 s (slowed down 2x to fit the joint limits))" in out
    assert main(["send", str(goal), "--socket", str(sock), "--topic"]) == 2
    assert "exceeds its velocity limit" in capsys.readouterr().err
