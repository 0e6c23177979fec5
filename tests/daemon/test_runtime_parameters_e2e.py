"""End to end: runtime parameters (issue 11 point 14) on ``python -m jtc_hw run`` over simulated
(mirror) joints, through ``jtc-hw param`` and the real ``Client``.

A change is checked once in the API process, applied by the loop process's controller and
then by the API process's planner: the loop's side shows in the rate of ``state`` messages
(``state_publish_rate``, compared on the daemon's own stamps), the planner's in the goal
checks of the next goal (jtc_upstream_behaviour.md section 7 step 2 and 8.2).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from helpers.daemon import JOINTS, DaemonProcess, connect, next_state, traj

from jtc_hw import GoalRejected
from jtc_hw.api.framing import RequestError
from jtc_hw.cli import main
from jtc_hw.cli.common import EXIT_BAD_INPUT, EXIT_OK

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    d = DaemonProcess(tmp_path_factory.mktemp("params"))
    with d.serving():
        yield d


def test_a_change_reaches_the_loop_the_planner_and_the_config(
    daemon: DaemonProcess, capsys: pytest.CaptureFixture[str]
) -> None:
    """Section 7 step 2: the loop publishes at the new rate, the next goal is checked with the
    new setting, and ``get_config``/``hello`` report it."""
    moving_end = traj([0.2] * 6, 0.5)
    moving_end["points"][0]["velocities"] = [0.1] * 6
    with connect(daemon) as client:
        assert client.get_parameters(["state_publish_rate"])["parameters"] == {
            "state_publish_rate": 50.0
        }
        first = client.send_goal(moving_end)  # allowed by default (seed 000)
        first.wait(timeout_s=10.0)

        sock = ["--socket", str(daemon.socket)]
        assert main([
            "param", "set", "state_publish_rate", "10",
            "allow_nonzero_velocity_at_trajectory_end", "false", *sock,
        ]) == EXIT_OK
        out = capsys.readouterr().out
        assert "state_publish_rate                        10.0   takes effect: next cycle" in out

        with pytest.raises(GoalRejected, match="velocit"):
            client.send_goal(moving_end)
        assert client.get_config()["controller"]["state_publish_rate"] == 10.0
        assert client.hello()["state_publish_rate"] == 10.0

        with client.subscribe_state() as sub:
            stamps = [next_state(sub, lambda s: True)["time_ns"] for _ in range(4)]
        # One state per 100 ms of daemon time (was 20 ms): exactly, on the deadline grid, or a
        # cycle more after a skipped deadline; twice that if the loop coalesced one (a lagging
        # API process on a busy machine), so the shortest gap is the one compared.
        gaps = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
        assert min(gaps) >= 100_000_000
        assert min(gaps) < 150_000_000, gaps
    assert "parameters changed: state_publish_rate=10.0" in daemon.wait_log("parameters changed")


def test_refusals_change_nothing(
    daemon: DaemonProcess, capsys: pytest.CaptureFixture[str]
) -> None:
    """Section 1: read-only parameters and bad values are refused with the file's messages."""
    sock = ["--socket", str(daemon.socket)]
    assert main(["param", "set", "joints", "[a, b]", "update_rate", "50", *sock]) \
        == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "read-only parameters joints, update_rate cannot be changed" in err
    with connect(daemon) as client:
        with pytest.raises(RequestError, match=r"^constraints\.joint1\.goal: must be >= 0"):
            client.set_parameters({"constraints.joint1.goal": -0.5})
        values = client.get_parameters(["joints", "update_rate", "constraints.joint1.goal"])
    assert values["parameters"] == {
        "joints": JOINTS, "update_rate": 500.0, "constraints.joint1.goal": 0.01,
    }


def test_the_cli_explains_itself(capsys: pytest.CaptureFixture[str]) -> None:
    """``jtc-hw param --help`` says how names, values and timing work."""
    with pytest.raises(SystemExit) as done:
        main(["param", "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    for words in ("gains.<joint>.p", "VALUE is YAML", "next goal or trajectory",
                  "Read-only parameters", "Exit status"):
        assert words in text
