"""Issue 11 point 6 on the client side: a result's ``error_string`` is upstream's text and the
per-joint ``details`` travel beside it, through the socket protocol, the Python client and the
command line (section 7 step 8d of jtc_upstream_behaviour.md)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.fake_backend import ServerThread

from jtc_hw import ErrorCode, GoalResult, GoalStatus, JointTolerance
from jtc_hw.api.client import Client
from jtc_hw.api.events import result_event
from jtc_hw.api.framing import encode
from jtc_hw.cli.common import EXIT_GOAL_FAILED, EXIT_OK, goal_result
from jtc_hw.controller.messages import JointTrajectory, TrajectoryPoint
from jtc_hw.daemon.settings import DaemonSettings

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

PATH_VIOLATION = "Aborted due to path tolerance violation"


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[ServerThread]:
    srv = ServerThread(DaemonSettings(socket=str(tmp_path / "d.sock")))
    yield srv
    srv.close()


def test_the_result_message_carries_details_beside_the_error_string() -> None:
    """Section 7 step 8d: the ``result`` event has upstream's ``error_string`` and our
    ``details``."""
    result = GoalResult(
        3,
        GoalStatus.ABORTED,
        ErrorCode.PATH_TOLERANCE_VIOLATED,
        PATH_VIOLATION,
        42,
        "joint 'j2' position error +0.06 exceeds 0.05",
    )
    assert json.loads(encode(result_event(result))) == {
        "event": "result",
        "goal_id": 3,
        "status": "aborted",
        "error_code": -4,
        "error_string": PATH_VIOLATION,
        "details": "joint 'j2' position error +0.06 exceeds 0.05",
        "time_ns": 42,
    }


def test_a_client_gets_upstreams_string_and_the_failing_joint(
    daemon: ServerThread, tmp_path: Path
) -> None:
    """Section 7 step 8d, end to end through the real server and client: a path violation on
    j2 gives exactly upstream's text, and ``details`` names j2."""
    with Client.connect(tmp_path / "d.sock", timeout_s=5.0) as client:
        goal = client.send_goal(
            JointTrajectory(["j1", "j2"], [TrajectoryPoint(1.0, [0.0, 1.0])]),
            path_tolerance=[JointTolerance("j2", position=0.05)],
        )
        client.sim("mirror", freeze=True)
        daemon.call(daemon.backend.step, 0.5)
        result = goal.wait(timeout_s=5.0)
    assert (result["status"], result["error_code"], result["error_string"]) == (
        "aborted",
        -4,
        PATH_VIOLATION,
    )
    assert result["details"].startswith("joint 'j2' position error")
    assert "j1" not in result["details"]


class _Finished:
    """A goal handle whose goal has already ended (what ``goal_result`` reads of one)."""

    def __init__(self, result: dict[str, Any]) -> None:
        self._result = result

    def feedback(self, timeout_s: float) -> Iterator[dict[str, Any]]:
        return iter(())

    def wait(self, timeout_s: float) -> dict[str, Any]:
        return self._result


def test_the_command_line_prints_the_details_under_the_result(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Section 7 step 8d: ``jtc-hw send`` prints upstream's text, then the details."""
    aborted = {
        "event": "result", "goal_id": 7, "status": "aborted", "error_code": -4,
        "error_string": PATH_VIOLATION, "details": "joint 'j2' position error +0.06 exceeds 0.05",
        "time_ns": 1,
    }
    assert goal_result(_Finished(aborted), 1.0, True, 1.0) == EXIT_GOAL_FAILED
    assert capsys.readouterr().out == (
        f"goal 7 aborted (error_code -4): {PATH_VIOLATION}\n"
        "  joint 'j2' position error +0.06 exceeds 0.05\n"
    )
    succeeded = dict(aborted, status="succeeded", error_code=0,
                     error_string="Goal successfully reached!", details="")
    assert goal_result(_Finished(succeeded), 1.0, True, 1.0) == EXIT_OK
    assert capsys.readouterr().out == (
        "goal 7 succeeded (error_code 0): Goal successfully reached!\n"
    )
