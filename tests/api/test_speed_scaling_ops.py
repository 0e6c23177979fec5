"""Speed scaling over the socket (issue 12 part C): the ``set_speed_scaling`` op, the client
method and ``jtc-hw speed`` / ``pause`` / ``resume``, against the real ``Server`` on the
stand-in backend (the real controller on a simulated clock)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.fake_backend import ServerThread

from jtc_hw import JointTrajectory, TrajectoryPoint
from jtc_hw.api import Client, RequestError
from jtc_hw.api.protocol import parse_request
from jtc_hw.api.requests import SetSpeedScaling
from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_OK

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources


def test_requests_are_parsed_strictly() -> None:
    assert parse_request({"op": "set_speed_scaling", "factor": 0.5}) == SetSpeedScaling(
        None, 0.5
    )
    assert parse_request({"op": "set_speed_scaling", "factor": 0}) == SetSpeedScaling(None, 0.0)
    assert parse_request({"op": "set_speed_scaling", "id": 2, "resume": True}) == (
        SetSpeedScaling(2, None, True)
    )
    for bad, where in [
        ({"op": "set_speed_scaling"}, "give exactly one of 'factor'"),
        ({"op": "set_speed_scaling", "resume": False}, "give exactly one of 'factor'"),
        ({"op": "set_speed_scaling", "factor": 1, "resume": True}, "both were given"),
        ({"op": "set_speed_scaling", "factor": -0.1}, r"factor: must be in \[0, 1\]"),
        ({"op": "set_speed_scaling", "factor": "1"}, "factor: expected a number"),
        ({"op": "set_speed_scaling", "factor": True}, "factor: expected a number"),
        ({"op": "set_speed_scaling", "resume": "yes"}, "resume: expected true or false"),
        ({"op": "set_speed_scaling", "speed": 1}, "unknown field 'speed'"),
    ]:
        with pytest.raises(RequestError, match=where):
            parse_request(bad)


def test_client_pauses_and_resumes_the_controller(client: Client, daemon: ServerThread) -> None:
    ctrl = daemon.backend.ctrl
    reply = client.set_speed_scaling(0.4)
    assert (reply["ok"], reply["factor"], reply["target"]) == (True, 1.0, 0.4)
    reply = client.set_speed_scaling(0.0)
    assert (reply["target"], ctrl.speed_scaling_target) == (0.0, 0.0)
    reply = client.set_speed_scaling(resume=True)
    assert reply["target"] == 0.4  # the factor before the pause
    with pytest.raises(ValueError, match="either a factor or resume"):
        client.set_speed_scaling(0.5, resume=True)


def test_the_state_stream_carries_the_factor(client: Client, daemon: ServerThread) -> None:
    with client.subscribe_state() as sub:
        client.set_speed_scaling(0.5)
        daemon.call(daemon.backend.step, 0.5)  # the default ramp: 0.5 s per unit of factor
        daemon.call(daemon.backend.publish_state)
        state = sub.get(timeout_s=5.0)
    assert state["speed_scaling"] == {"factor": 0.5, "target": 0.5}


def test_cli_speed_pause_resume(
    daemon: ServerThread, sock: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    s = ["--socket", str(sock)]
    assert main(["speed", "0.5", *s]) == EXIT_OK
    assert capsys.readouterr().out.strip() == "speed set: speed scaling 0.5 (ramping from 1)"
    assert main(["pause", *s]) == EXIT_OK
    assert "paused" in capsys.readouterr().out
    assert main(["resume", *s]) == EXIT_OK
    assert capsys.readouterr().out.strip() == "resumed: speed scaling 0.5 (ramping from 1)"
    assert daemon.backend.ctrl.speed_scaling_target == 0.5


def test_cli_refuses_a_negative_factor_with_the_daemons_reason(
    daemon: ServerThread, sock: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["speed", "--socket", str(sock), "--", "-1"])
    assert code != EXIT_OK
    err = capsys.readouterr().err
    assert "must be in [0, 1]" in err and "Traceback" not in err
    assert daemon.backend.ctrl.speed_scaling_target == 1.0


def test_a_huge_factor_is_refused_with_the_range_and_goals_still_succeed(
    client: Client, daemon: ServerThread, sock: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 21 point 4: ``set_speed_scaling 1e308`` is ``bad_request`` naming the range (it
    was accepted, and every later goal failed with an ``internal`` overflow)."""
    for factor, message in [
        (1e308, r"must be a number in \[0, 1\]"),
        (1.5, r"must be a number in \[0, 1\]"),
        (10**400, "factor: .* out of the range of a float64"),
    ]:
        with pytest.raises(RequestError, match=message) as refused:
            client.set_speed_scaling(factor)
        assert refused.value.code == "bad_request"
    assert daemon.backend.ctrl.speed_scaling_target == 1.0
    assert main(["speed", "--socket", str(sock), "1e308"]) != EXIT_OK
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "[0, 1]" in err, err
    handle = client.send_goal(JointTrajectory(["j1", "j2"], [TrajectoryPoint(0.5, [0.1, 0.1])]))
    daemon.call(daemon.backend.step, 2.0)
    assert handle.wait(timeout_s=10.0)["status"] == "succeeded"


@pytest.mark.parametrize("command", ["speed", "pause", "resume"])
def test_cli_help_explains(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "ramps" in out and "acceleration limits" in out
    assert "1 is as planned" in out and "paused" in out


def test_jtc_hw_state_shows_a_factor_other_than_1(capsys: pytest.CaptureFixture[str]) -> None:
    from jtc_hw.cli.state import print_state as _print_state

    state = {
        "time_ns": 12_000_000_000,
        "joint_names": ["j1"],
        "desired": {"positions": [0.1]},
        "actual": {"positions": [0.1], "velocities": [0.0]},
        "error": {"positions": [0.0]},
        "holding": False,
        "active_goal": 3,
        "speed_scaling": {"factor": 0.42, "target": 0.0},
    }
    _print_state(state, header=False)
    assert capsys.readouterr().out.splitlines()[-1] == "t=12.000 s  moving  goal 3  speed 0.42 -> 0"
    state["speed_scaling"] = {"factor": 1.0, "target": 1.0}
    _print_state(state, header=False)
    assert capsys.readouterr().out.splitlines()[-1] == "t=12.000 s  moving  goal 3"
