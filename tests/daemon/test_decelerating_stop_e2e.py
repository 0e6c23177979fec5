"""Decelerating stops through the daemon (issue 12 part B): SIGTERM and the ``stop`` op.

The daemon runs as a subprocess on mirror hardware (position commands, no lag: the measured
velocity is the joint's actual rate over each cycle) with ``constraints.decelerate_on_cancel``.
The state stream is published every cycle; what it shows of the joints' velocities is checked
(a ramp down at the configured deceleration, not a step), never how long anything took.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.daemon import (
    GOAL_TOL,
    JOINTS,
    STOP_TIMEOUT_S,
    WAIT_S,
    DaemonProcess,
    connect,
    next_state,
)

from jtc_hw.api.calls import ClientConnectionError

pytestmark = pytest.mark.usefixtures("no_leaks")

DECEL = 2.0  # rad/s^2: a 1 s stop from CRUISE, long enough to be seen on a busy machine
RATE = 500
CRUISE = 2.0  # rad/s of joint1 while the stop comes


def controller_settings() -> dict[str, Any]:
    return {
        "state_publish_rate": float(RATE),
        "constraints": {
            "stopped_velocity_tolerance": 0.05,
            "goal_time": 0.5,
            "decelerate_on_cancel": True,
            # No path tolerance (0: not checked, as upstream): not what is tested here, and at
            # 2 rad/s a cycle 25 ms late broke 0.05 on a busy host, aborting the cruise goal
            # before the stop could come (issue 22).
            **{
                j: {"trajectory": 0.0, "goal": GOAL_TOL, "max_deceleration_on_cancel": DECEL}
                for j in JOINTS
            },
        },
    }


def cruise_goal() -> dict[str, Any]:
    """joint1 cruises at 2 rad/s from 0.5 s to 1.5 s (a straight quintic), the others at
    rest."""
    def point(t: float, p: float, v: float) -> dict[str, Any]:
        return {
            "time_from_start": t,
            "positions": [p] + [0.0] * 5,
            "velocities": [v] + [0.0] * 5,
            "accelerations": [0.0] * 6,
        }

    return {
        "joint_names": JOINTS,
        "points": [point(0.5, 0.5, CRUISE), point(1.5, 2.5, CRUISE), point(2.5, 3.0, 0.0)],
    }


@pytest.fixture
def decelerating_daemon(tmp_path: Path) -> Iterator[DaemonProcess]:
    d = DaemonProcess(tmp_path / "d", controller=controller_settings(), update_rate=RATE)
    d.start()
    try:
        d.wait_ready()
        yield d
    finally:
        d.shutdown()


def cruises(state: dict[str, Any]) -> bool:
    """joint1's reference is at the cruise speed. Its measured speed is CRUISE only in a cycle
    as far from the one before as that one from its own predecessor (the mirror reaches each
    command one cycle later): on a busy host, with deadlines skipped and states dropped, no
    state received in the whole second of cruise may show it (issue 22)."""
    return bool(abs(state["desired"]["velocities"][0] - CRUISE) <= 1e-9)  # as assert_ramp


def after(states: list[dict[str, Any]], t0_ns: int) -> list[dict[str, Any]]:
    return [s for s in states if s["time_ns"] >= t0_ns]


def assert_ramp(states: list[dict[str, Any]], to_rest: bool = True) -> None:
    """joint1 ramps to rest at DECEL, not a step.

    The state stream of a busy machine drops states (a slow reader gets the newest) and the
    loop may skip a deadline (skipped, not bunched: docs/decisions.md 8), so:

    - the stop's first state desires the velocity measured in that cycle (upstream 11.3),
      checked when it is known to be the first (one period after the last cruising state);
    - the commanded velocity (the desired one, the reference at each state's time) changes
      between any two states by at most DECEL times the time between them, and ends at 0 (into
      the stop too, unless the stop's reading came after a skipped deadline: docs/behaviour.md,
      "Stopping");
    - the joint (the mirror, measured) passes through intermediate speeds and (``to_rest``:
      the states received go that far) ends at rest at the held position: a hold would take
      it from cruising to 0 in one cycle;
    - where two states are consecutive cycles, each after a cycle on time, their measured
      velocities (each the motion of one period towards the position commanded the cycle
      before) differ by at most one period's worth of DECEL.
    """
    t_ns = np.array([s["time_ns"] for s in states], dtype=np.int64)
    desired = np.array([s["desired"]["velocities"][0] for s in states])
    measured = np.array([s["actual"]["velocities"][0] for s in states])
    period_ns = 1_000_000_000 // RATE
    one_period = DECEL * period_ns / 1e9 * (1 + 1e-6) + 1e-9
    regular = np.diff(t_ns) == period_ns  # regular[i]: state i + 1 is the cycle after state i
    clean = np.zeros(len(states), dtype=bool)  # measured[i] is one period's motion on time
    clean[2:] = regular[1:] & regular[:-1]
    # Upstream (section 11.3) starts the stop from the velocity measured in its first cycle:
    # the stop's first state desires that velocity. After a skipped deadline that reading is
    # not the cruise speed (the position servo caught up several periods in one), and the
    # desired velocity steps to it, as upstream's would; on time, it is the cruise speed.
    j = int(np.argmax(np.abs(desired - CRUISE) > 1e-9))  # the first stopping state received
    assert j > 0, desired
    # It is the stop's first state when it came one period after the last cruising one: no
    # cycle ran between them. A longer gap is a skipped deadline or states dropped on their
    # way (at a load average of 10 the stop's first three were, and this one desired the
    # ramp's third step, not the reading: issue 22); the ramp checks below hold either way.
    if t_ns[j] - t_ns[j - 1] == period_ns:
        assert abs(desired[j] - measured[j]) <= one_period, (desired[j], measured[j])
    allowed = DECEL * np.diff(t_ns) / 1e9 * (1 + 1e-6) + 1e-9
    checked = np.ones(len(allowed), dtype=bool)
    checked[j - 1] = bool(clean[j])  # into the stop: continuous when its reading was on time
    steps = np.abs(np.diff(desired))
    assert (steps[checked] <= allowed[checked]).all(), steps - allowed
    # At rest where the stop holds: the joint stands at the held position, and its measured
    # velocity is 0 (read on time: after a skipped deadline the last reading still holds the
    # catch-up of the periods before).
    if to_rest:
        held = states[-1]["desired"]["positions"][0]
        assert desired[-1] == 0.0 and abs(states[-1]["actual"]["positions"][0] - held) < 1e-9
        if clean[-1]:
            assert abs(measured[-1]) < 1e-9, measured[-1]
    if to_rest:
        # It went on at decreasing speed: from the first stopping state received, the
        # reference travels the ramp's remaining v^2 / (2 DECEL) to where the joint now
        # stands (a hold: nothing). Counting states that measured intermediate speeds failed
        # on a busy host, most of them dropped or late (issue 22).
        travel = held - states[j]["desired"]["positions"][0]
        ramp_rest = desired[j] ** 2 / (2 * DECEL)
        assert abs(travel - ramp_rest) <= 1e-6, (travel, ramp_rest)
    pairs = clean[1:] & clean[:-1] & regular
    measured_steps = np.abs(np.diff(measured))[pairs]
    assert (measured_steps <= one_period).all(), measured_steps.max()


def test_sigterm_mid_goal_decelerates_to_rest(decelerating_daemon: DaemonProcess) -> None:
    d = decelerating_daemon
    with connect(d) as client, client.subscribe_state() as sub:
        goal = client.send_goal(cruise_goal())
        cruising = next_state(
            sub,
            lambda s: s["active_goal"] == goal.goal_id and cruises(s),
        )
        os.kill(d.pid, signal.SIGTERM)
        result = goal.wait(timeout_s=STOP_TIMEOUT_S)
        assert (result["status"], result["error_code"]) == ("aborted", -1), result
        assert result["error_string"] == "daemon stopping (SIGTERM): decelerating to a stop"
        with pytest.raises(ClientConnectionError):  # the daemon closes it once stopped
            while True:
                sub.get(timeout_s=STOP_TIMEOUT_S)
    assert d.wait_exit() == 0
    log = d.log()
    assert "decelerating to a stop" in log and "stopped cleanly" in log
    assert "Traceback" not in log and "ERROR" not in log
    states = [m for m in client.events if m["event"] == "state"]
    # The stream received the stop's end when its last state is a period past the time the
    # ramp seen says the joint comes to rest. At a load average of 10 the daemon's last
    # states of a shutdown can be lost on their way (states are droppable, and the daemon
    # closes the connection once stopped: issue 22); that the loop cycles until it read the
    # joints at rest is then shown by test_shutdown_stop.py, not by this stream.
    # (The stop starts from the velocity measured in its first cycle: after a late cycle,
    # anything from 0 to CRUISE.)
    stop = [m for m in after(states, cruising["time_ns"]) if not cruises(m)]
    assert stop, "no state of the stop received"
    rests_at = stop[0]["time_ns"] + max(stop[0]["desired"]["velocities"][0], 0.0) / DECEL * 1e9
    to_rest = states[-1]["time_ns"] >= rests_at + 1e9 / RATE
    assert_ramp(after(states, cruising["time_ns"]), to_rest=to_rest)
    # The loop kept cycling after the result until the joints were at rest.
    assert states[-1]["time_ns"] > result["time_ns"]
    if to_rest:
        assert states[-1]["desired"]["velocities"] == [0.0] * 6
    assert [m["goal_id"] for m in client.events if m["event"] == "result"] == [goal.goal_id]


def test_stop_op_decelerates_and_the_daemon_serves_on(decelerating_daemon: DaemonProcess) -> None:
    d = decelerating_daemon
    with connect(d) as client, client.subscribe_state() as sub:
        goal = client.send_goal(cruise_goal())
        cruising = next_state(
            sub,
            lambda s: s["active_goal"] == goal.goal_id and cruises(s),
        )
        client.stop()
        result = goal.wait(timeout_s=WAIT_S)
        assert result["status"] == "canceled", result
        # At rest: a state whose velocities and desired velocities are all zero.
        rest = next_state(
            sub,
            lambda s: s["desired"]["velocities"] == [0.0] * 6
            and all(abs(x) < 1e-9 for x in s["actual"]["velocities"]),
        )
        states = [m for m in client.events if m["event"] == "state"]
        assert_ramp([s for s in after(states, cruising["time_ns"])
                     if s["time_ns"] <= rest["time_ns"]])
        # Still serving: a new goal is accepted and reached (a gentle one, from where the
        # joints rest).
        back = [p - 0.1 for p in rest["actual"]["positions"]]
        again = client.send_goal({
            "joint_names": JOINTS,
            "points": [{"time_from_start": 1.0, "positions": back}],
        })
        assert again.wait(timeout_s=WAIT_S)["status"] == "succeeded"
