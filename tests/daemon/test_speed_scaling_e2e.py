"""Speed scaling through the real daemon on simulated joints (issue 12 part C): goals planned
by the API process while the loop's trajectory time lags the clock, is paused, or ramps."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers.daemon import (
    GOAL_TOL,
    MS,
    WAIT_S,
    DaemonProcess,
    connect,
    next_state,
    settle,
    traj,
)

from jtc_hw.api import RequestError

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    # Factors above 1 (1.7 below) need the bound raised: upstream's is 1.
    scaling = {"speed_scaling": {"max_scaling_factor": 2.0}}
    d = DaemonProcess(tmp_path_factory.mktemp("scaling"), controller=scaling)
    with d.serving():
        yield d


def test_a_goal_sent_while_paused_waits_then_resume_completes_it(daemon: DaemonProcess) -> None:
    with connect(daemon) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        assert client.set_speed_scaling(0.0)["target"] == 0.0
        paused = next_state(sub, lambda s: s["speed_scaling"]["factor"] == 0.0)
        target = [p + 0.2 for p in p0]
        handle = client.send_goal(traj(target, 1.0))
        accepted = next_state(sub, lambda s: s["active_goal"] == handle.goal_id)
        # 0.5 s of the daemon's clock paused: the joints stay (but for the one period the
        # command leads by), no result, trajectory time does not move.
        later = settle(sub, accepted["time_ns"] + 500_000_000)
        assert later["actual"]["positions"] == pytest.approx(p0, abs=0.01)
        assert later["desired"]["time_from_start"] == pytest.approx(
            accepted["desired"]["time_from_start"], abs=1e-9
        )
        assert client.received("result") == []
        # The status (2 Hz) published since the pause, well over 0.5 s ago, has it too.
        assert client.get_status()["controller"]["speed_scaling"] == {
            "factor": 0.0, "target": 0.0
        }
        assert paused["speed_scaling"]["target"] == 0.0
        assert client.set_speed_scaling(resume=True)["target"] == 1.0
        result = handle.wait(timeout_s=WAIT_S)
        assert result["status"] == "succeeded", (result, daemon.log())
        state = settle(sub, result["time_ns"] + 50_000_000)
        assert state["actual"]["positions"] == pytest.approx(target, abs=GOAL_TOL)
        assert len(client.received("result")) == 1


def test_goals_planned_while_the_factor_ramps_and_lags_are_committed(
    daemon: DaemonProcess,
) -> None:
    """The API process plans in trajectory time from the loop's state: goals sent at once
    after each change of factor are accepted (no stale-plan refusals), replace each other as
    usual and the last one succeeds."""
    with connect(daemon) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        handles = []
        for k, factor in enumerate([0.3, 1.7, 0.6, 1.0]):
            client.set_speed_scaling(factor)
            handles.append(client.send_goal(traj([p + 0.05 * (k + 1) for p in p0], 0.4)))
        results = [h.wait(timeout_s=WAIT_S) for h in handles]
        assert [r["status"] for r in results] == ["canceled"] * 3 + ["succeeded"], results
        state = settle(sub, results[-1]["time_ns"] + 50_000_000)
        assert state["speed_scaling"] == {"factor": 1.0, "target": 1.0}
        assert state["actual"]["positions"] == pytest.approx(
            [p + 0.2 for p in p0], abs=GOAL_TOL
        )
        # The time lost while slowed stays lost: trajectory time lags the clock, and a goal
        # planned now is still committed without a step and finishes.
        handle = client.send_goal(traj(p0, 0.4))
        assert handle.wait(timeout_s=WAIT_S)["status"] == "succeeded"


def test_an_out_of_range_factor_is_refused_by_the_loop_and_goals_still_succeed(
    daemon: DaemonProcess,
) -> None:
    """Issue 21 point 4 through the real loop process: ``1e308`` (accepted before, after which
    every goal failed with an ``internal`` overflow) and anything above this daemon's
    ``max_scaling_factor`` (2) are ``bad_request`` naming the range; the factor in force stays
    and the next goal succeeds."""
    with connect(daemon) as client, client.subscribe_state() as sub:
        p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
        for factor in (1e308, 2.5):
            with pytest.raises(RequestError, match=r"must be a number in \[0, 2\]") as refused:
                client.set_speed_scaling(factor)
            assert refused.value.code == "bad_request"
        assert client.get_status()["controller"]["speed_scaling"]["target"] == 1.0
        handle = client.send_goal(traj([p + 0.05 for p in p0], 0.3))
        assert handle.wait(timeout_s=WAIT_S)["status"] == "succeeded", daemon.log()
        handle = client.send_goal(traj(p0, 0.3))
        assert handle.wait(timeout_s=WAIT_S)["status"] == "succeeded", daemon.log()


def _scaled_by_the_mirror(
    directory: Path, mirror_factor: float, **interfaces: str
) -> DaemonProcess:
    """A daemon whose factor is the mirror's scalar interface ``arm/speed_scaling_factor``
    (``interfaces``: ``state_interface`` / ``command_interface``), its state
    ``mirror_factor`` until written."""
    d = DaemonProcess(directory, controller={"speed_scaling": {"ramp_time": 0.0, **interfaces}})
    config = yaml.safe_load(d.config_path.read_text())
    config["hardware"][0]["params"]["speed_scaling_factor"] = mirror_factor
    d.config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    return d


def _slowed_goal(client: Any, sub: Any, factor: float) -> None:
    """A goal runs in trajectory time advancing at ``factor`` times the loop's clock (its
    states' ``time_ns``, the deadline grid) and succeeds."""
    p0 = next_state(sub, lambda s: s["active_goal"] is None)["actual"]["positions"]
    handle = client.send_goal(traj([p + 0.1 for p in p0], 0.3))
    first = next_state(sub, lambda s: s["active_goal"] == handle.goal_id
                       and s["desired"]["time_from_start"] > 0.02)
    later = next_state(sub, lambda s: s["time_ns"] >= first["time_ns"] + 100 * MS)
    assert later["active_goal"] == handle.goal_id
    assert first["speed_scaling"]["factor"] == later["speed_scaling"]["factor"] == factor
    advanced = later["desired"]["time_from_start"] - first["desired"]["time_from_start"]
    assert advanced / ((later["time_ns"] - first["time_ns"]) / 1e9) == pytest.approx(factor)
    assert handle.wait(timeout_s=WAIT_S)["status"] == "succeeded"


def test_the_factor_is_read_from_a_state_interface_and_asked_through_a_command_interface(
    tmp_path: Path,
) -> None:
    """Upstream's speed_scaling.state_interface and command_interface on the mirror's scalar
    interface, looped back as GenericSystem does: the factor a client asks for is written to
    the command interface, read back from the state interface at the next cycle, and slows
    goals; the hardware's status shows both interfaces holding the factor in force. Then a
    mirror that reports 0.5 by itself, with only the state interface configured: goals run at
    0.5 and a client cannot set another factor (bad_request, naming the interface)."""
    both = {"state_interface": "arm/speed_scaling_factor",
            "command_interface": "arm/speed_scaling_factor"}
    d = _scaled_by_the_mirror(tmp_path / "both", 0.25, **both)
    with d.serving(), connect(d) as client, client.subscribe_state() as sub:
        # The command interface carries the initial factor (1) from the first cycle on.
        next_state(sub, lambda s: s["speed_scaling"] == {"factor": 1.0, "target": 1.0})
        assert client.set_speed_scaling(0.5)["target"] == 0.5  # asked of the hardware
        state = next_state(sub, lambda s: s["speed_scaling"]["factor"] == 0.5)
        assert state["speed_scaling"]["target"] == 0.5
        _slowed_goal(client, sub, 0.5)
        status = client.get_status()
        (arm,) = [c for c in status["hardware"]["components"] if c["name"] == "arm"]
        assert arm["details"]["speed_scaling_factor"] == {"state": 0.5, "command": 0.5}
        assert status["controller"]["speed_scaling"]["factor"] == 0.5

    d = _scaled_by_the_mirror(tmp_path / "state", 0.5,
                              state_interface="arm/speed_scaling_factor")
    with d.serving(), connect(d) as client, client.subscribe_state() as sub:
        _slowed_goal(client, sub, 0.5)
        with pytest.raises(RequestError, match="'arm/speed_scaling_factor' each cycle") as no:
            client.set_speed_scaling(1.0)
        assert no.value.code == "bad_request"
        assert client.get_status()["controller"]["speed_scaling"]["factor"] == 0.5
