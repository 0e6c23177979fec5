"""``FakeBackend``: a small controller host implementing the server's ``Backend`` interface.

It is not a protocol mock: it runs the real ``JointTrajectoryController`` over ideal mirrored
joints, on a simulated clock the test steps, and implements what the daemon's loop backend
implements for real. Used by the server and client tests.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeVar

import numpy as np

from jtc_hw import GoalFeedback, GoalResult, JointTrajectoryController, TrajectorySample
from jtc_hw.config.controller_file import config_to_dict
from jtc_hw.controller.limits_check import TimeScaling
from jtc_hw.controller.messages import JointTrajectory
from jtc_hw.controller.parameters import ParameterChange, parameters_report
from jtc_hw.controller.tolerances import JointTolerance
from jtc_hw.daemon.core.backend_api import Accepted, Observer
from jtc_hw.daemon.settings import DaemonSettings
from jtc_hw.daemon.transports.server import Server
from jtc_hw.errors import ConfigurationError

from conftest import Mirror, S, make_config

T = TypeVar("T")

TOKEN = "0123456789abcdef-token"


class FakeBackend:
    """A controller host on a simulated clock; ``step`` runs control cycles and publishes."""

    def __init__(self, joints: Sequence[str] = ("j1", "j2"), **params: Any) -> None:
        self.config = make_config(joints, update_rate=100.0, **params)
        self.joint_names = tuple(self.config.joints)
        self.ctrl = JointTrajectoryController(self.config)
        self.mirror = Mirror([0.0] * len(joints))
        self.t = 10 * S
        self.period = S // 100
        self.ctrl.activate(self.t, self.mirror.state())
        self.listener: Observer | None = None
        self.cycles = 0
        self.early_feedback = False  # deliver a goal's first event before send_goal returns
        self.status_error: Exception | None = None
        self.config_padding = 0
        self.extra_config: Any = None
        self.stops = 0

    def now_ns(self) -> int:
        return self.t

    def hello(self) -> dict[str, Any]:
        return {"update_rate": 100.0, "state_publish_rate": 50.0, "action_monitor_rate": 20.0}

    def config_dict(self) -> dict[str, Any]:
        return {
            "controller": config_to_dict(self.config),
            "padding": "x" * self.config_padding,
            "extra": self.extra_config,
        }

    def status(self) -> dict[str, Any]:
        if self.status_error is not None:
            raise self.status_error
        return {
            "loop": {"cycles": self.cycles},
            "hardware": {"mirror": "frozen" if self.mirror.frozen else "ok"},
            "controller": {"holding": self.ctrl.holding, "active_goal": self.ctrl.active_goal},
        }

    async def send_goal(
        self,
        traj: JointTrajectory,
        path_tolerance: Sequence[JointTolerance],
        goal_tolerance: Sequence[JointTolerance],
        goal_time_tolerance: float,
        *,
        time_scaling: str | None = None,
    ) -> Accepted:
        await asyncio.sleep(0)  # the real backend waits for the loop process here
        accepted = Accepted.of(
            self.ctrl.send_goal(
                self.t,
                traj,
                path_tolerance,
                goal_tolerance,
                goal_time_tolerance,
                time_scaling=time_scaling,
            ),
            self.ctrl.last_time_scaling,
        )
        if not self.early_feedback:
            return accepted
        # The id's future is resolved and, in the same callback, the goal's first events are
        # dispatched: they reach the server before its send_goal coroutine resumes.
        reply: asyncio.Future[Accepted] = asyncio.get_running_loop().create_future()

        def deliver() -> None:
            reply.set_result(accepted)
            z = np.zeros(len(self.joint_names))
            assert self.listener is not None
            self.listener.on_goal_event(
                GoalFeedback(
                    accepted.goal_id, self.t, 0.0, TrajectorySample(z, z, z, z), z, z,
                    np.zeros((3, len(z))),
                )
            )

        asyncio.get_running_loop().call_soon(deliver)
        return await reply

    async def cancel_goal(self, goal_id: int) -> bool:
        return self.ctrl.cancel_goal(goal_id)

    async def send_trajectory(
        self, traj: JointTrajectory, *, time_scaling: str | None = None
    ) -> TimeScaling | None:
        self.ctrl.send_trajectory(self.t, traj, time_scaling=time_scaling)
        return self.ctrl.last_time_scaling if traj.points else None

    async def stop_motion(self) -> bool:
        await asyncio.sleep(0)  # the real backend waits for the loop process here
        if not self.ctrl.active:
            return False
        self.ctrl.request_stop()
        self.stops += 1
        return True

    def query_state(self, time_ns: int) -> TrajectorySample:
        return self.ctrl.query_state(time_ns)

    async def rearm(self) -> bool:
        return False

    async def set_speed_scaling(self, factor: float | None) -> dict[str, float]:
        await asyncio.sleep(0)  # the real backend waits for the loop process here
        if factor is None:
            self.ctrl.resume_speed_scaling()
        else:
            self.ctrl.set_speed_scaling(factor)
        return {
            "factor": self.ctrl.speed_scaling_factor,
            "target": self.ctrl.speed_scaling_target,
        }

    def get_parameters(self, names: Sequence[str] | None) -> dict[str, Any]:
        return parameters_report(self.ctrl.config, names)

    async def set_parameters(self, changes: Mapping[str, Any]) -> ParameterChange:
        await asyncio.sleep(0)  # the real backend waits for the loop process here
        change = self.ctrl.set_parameters(changes)
        self.config = change.config
        return change

    async def sim(self, component: str, freeze: bool | None, fault: str | None = None) -> None:
        if component != "mirror":
            raise ConfigurationError(f"no simulated component '{component}' (have: mirror)")
        self.mirror.frozen = freeze

    def add_observer(self, observer: Observer) -> None:
        self.listener = observer

    def step(self, seconds: float) -> list[GoalResult | GoalFeedback]:
        """Run control cycles for ``seconds`` of simulated time, delivering goal events."""
        delivered: list[GoalResult | GoalFeedback] = []
        for _ in range(round(seconds * S / self.period)):
            out = self.ctrl.update(self.t, self.period, self.mirror.state())
            self.mirror.apply(out.command, self.period / S)
            self.t += self.period
            self.cycles += 1
            for event in out.events:
                if isinstance(event, (GoalResult, GoalFeedback)) and self.listener is not None:
                    self.listener.on_goal_event(event)
                    delivered.append(event)
        return delivered

    def publish_state(self, seq: int = 0, pad: int = 0) -> None:
        sample = self.ctrl.query_state(self.t)
        assert self.listener is not None
        self.listener.on_state(
            {
                "time_ns": self.t,
                "seq": seq,
                "joint_names": list(self.joint_names),
                "desired": {"positions": sample.positions, "velocities": sample.velocities},
                "actual": {"positions": self.mirror.p, "velocities": self.mirror.v},
                "error": {"positions": sample.positions - self.mirror.p},
                "command": {"positions": sample.positions},
                "holding": self.ctrl.holding,
                "active_goal": self.ctrl.active_goal,
                "speed_scaling": {
                    "factor": self.ctrl.speed_scaling_factor,
                    "target": self.ctrl.speed_scaling_target,
                },
                "pad": "p" * pad,
            }
        )


class ServerThread:
    """The server on its own asyncio loop in a thread, as the daemon runs it."""

    def __init__(self, settings: DaemonSettings, backend: FakeBackend | None = None) -> None:
        self.backend = backend or FakeBackend()
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="test-server")
        self.thread.start()
        self.server = Server(self.backend, settings)
        self._await(self.server.start())

    def _await(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def call(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn`` in the server's loop thread (where the backend delivers events)."""

        async def wrapper() -> T:
            return fn(*args)

        result: T = self._await(wrapper())
        return result

    def close(self) -> None:
        self._await(self.server.close())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()
