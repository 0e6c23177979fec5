"""``python -m jtc_hw``: run a goal on simulated joints and print what happened.

A stand-in until the daemon's ``jtc-hw demo`` exists: six ideal position-controlled joints,
a three-point trajectory, progress every 0.25 s, and the goal's result.
"""

from __future__ import annotations

import numpy as np

from . import (
    GoalFeedback,
    GoalResult,
    JointState,
    JointTrajectory,
    JointTrajectoryController,
    TrajectoryPoint,
    load_config,
)

JOINTS = [f"joint{i}" for i in range(1, 7)]
RATE_HZ = 100.0


def main() -> int:
    """Run the demo; the exit status is 0 when the goal succeeds."""
    config = load_config(
        {
            "joints": JOINTS,
            "command_interfaces": ["position"],
            "state_interfaces": ["position", "velocity"],
            "update_rate": RATE_HZ,
            "action_monitor_rate": 4.0,
            "constraints": {
                "goal_time": 0.5,
                **{j: {"trajectory": 0.05, "goal": 0.01} for j in JOINTS},
            },
        }
    )
    ctrl = JointTrajectoryController(config)
    period = round(1e9 / RATE_HZ)
    now = 0
    positions = np.zeros(len(JOINTS))
    velocities = np.zeros(len(JOINTS))
    ctrl.activate(now, JointState(positions, velocities))
    goal = JointTrajectory(
        JOINTS,
        [
            TrajectoryPoint(1.0, np.linspace(0.2, 0.7, 6), np.full(6, 0.3)),
            TrajectoryPoint(2.0, np.linspace(0.5, -0.5, 6), np.zeros(6)),
            TrajectoryPoint(3.0, np.zeros(6), np.zeros(6)),
        ],
    )
    goal_id = ctrl.send_goal(now, goal)
    print(f"jtc_hw demo: goal {goal_id} accepted, 3 points over 3.0 s on 6 simulated joints")
    print(f"{'t [s]':>6}  {'joint1 [rad]':>12}  {'joint6 [rad]':>12}  {'max |error|':>11}")
    while True:
        out = ctrl.update(now, period, JointState(positions, velocities))
        for event in out.events:
            if isinstance(event, GoalFeedback):
                print(
                    f"{event.time_from_start:6.2f}  {event.actual_positions[0]:12.4f}  "
                    f"{event.actual_positions[-1]:12.4f}  {np.abs(event.error[0]).max():11.2e}"
                )
            elif isinstance(event, GoalResult):
                print(
                    f"goal {event.goal_id} {event.status.value} "
                    f"(error_code {int(event.error_code)}): {event.error_string}"
                )
                return 0 if event.error_code == 0 else 1
        # Ideal joints: they reach the commanded position by the next cycle.
        assert out.command.positions is not None
        velocities = (out.command.positions - positions) * RATE_HZ
        positions = out.command.positions
        now += period


if __name__ == "__main__":
    raise SystemExit(main())
