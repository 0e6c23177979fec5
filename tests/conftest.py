"""Shared helpers: configurations, a simulated clock, and a mirror joint set."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import pytest

from jtc_hw import JointState, JointTrajectoryController, load_config
from jtc_hw.config import ControllerConfig

S = 1_000_000_000  # ns per second
MS = 1_000_000


def make_config(
    joints: Sequence[str] = ("j1", "j2"),
    command_interfaces: Sequence[str] = ("position",),
    state_interfaces: Sequence[str] = ("position", "velocity"),
    **params: Any,
) -> ControllerConfig:
    mapping: dict[str, Any] = {
        "joints": list(joints),
        "command_interfaces": list(command_interfaces),
        "state_interfaces": list(state_interfaces),
    }
    mapping.setdefault("update_rate", 100.0)
    mapping.update(params)
    return load_config(mapping)


class Mirror:
    """Ideal simulated joints: the command becomes the state by the next cycle.

    Position commands are taken as the position reached at the next cycle; velocity commands
    integrate; effort commands drive a unit inertia. ``frozen`` stops feedback changing.
    """

    def __init__(self, positions: Sequence[float], velocities: Sequence[float] | None = None):
        self.p = np.array(positions, dtype=float)
        self.v = np.zeros_like(self.p) if velocities is None else np.array(velocities, float)
        self.frozen = False

    def state(self) -> JointState:
        return JointState(self.p.copy(), self.v.copy())

    def apply(self, command: Any, dt_s: float) -> None:
        if self.frozen:
            return
        if command.positions is not None and not np.isnan(command.positions).any():
            new_p = command.positions.copy()
            self.v = (new_p - self.p) / dt_s
            self.p = new_p
        elif command.velocities is not None and not np.isnan(command.velocities).any():
            self.v = command.velocities.copy()
            self.p = self.p + self.v * dt_s
        elif command.effort is not None and not np.isnan(command.effort).any():
            self.v = self.v + command.effort * dt_s
            self.p = self.p + self.v * dt_s


class Rig:
    """A controller, a mirror and a simulated clock stepping at the configured rate."""

    def __init__(self, config: ControllerConfig, positions: Sequence[float], t0: int = 10 * S):
        self.ctrl = JointTrajectoryController(config)
        self.mirror = Mirror(positions)
        self.now = t0
        self.period = round(S / config.update_rate)
        self.events: list[Any] = []
        self.last: Any = None
        self.ctrl.activate(self.now, self.mirror.state())

    def step(self, n: int = 1) -> Any:
        for _ in range(n):
            out = self.ctrl.update(self.now, self.period, self.mirror.state())
            self.events.extend(out.events)
            self.last = out
            self.mirror.apply(out.command, self.period / S)
            self.now += self.period
        return self.last

    def run_until(self, predicate: Any, limit_s: float = 30.0) -> Any:
        for _ in range(int(limit_s * S / self.period)):
            out = self.step()
            if predicate(out):
                return out
        raise AssertionError("condition not reached within the simulated time limit")

    def results(self, goal_id: int | None = None) -> list[Any]:
        from jtc_hw import GoalResult

        return [
            e
            for e in self.events
            if isinstance(e, GoalResult) and (goal_id is None or e.goal_id == goal_id)
        ]


@pytest.fixture
def two_joint_config() -> ControllerConfig:
    return make_config()


def frange(start: int, stop: int, step: int) -> Iterator[int]:
    t = start
    while t <= stop:
        yield t
        t += step
