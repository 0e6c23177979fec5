"""The requests of the socket API as typed values: one frozen dataclass per operation.

:mod:`.protocol` parses a message into one of these; the server acts on them. Their own
checks (a start or a time resolved against the daemon clock) raise ``RequestError``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

from ..controller.messages import JointTrajectory, PointColumns, TrajectoryPoint, seconds_to_ns
from ..controller.tolerances import JointTolerance
from .framing import BAD_REQUEST, RequestError, RequestId

MAX_NS = 2**63 - 1
"""Largest time in nanoseconds the protocol carries (int64)."""


@dataclass(frozen=True)
class _Request:
    """What every request has: ``op``, its name (a class constant), and ``id``, the client's,
    echoed in the reply."""

    op: ClassVar[str]
    id: RequestId = None


@dataclass(frozen=True)
class WireTrajectory:
    """A trajectory as received: its start is resolved by the server (``to_joint_trajectory``).

    Attributes:
        start_time_ns: absolute start on the daemon clock, if given.
        start_in: start in seconds from when the daemon received the request, if given.
    """

    joint_names: tuple[str, ...]
    points: Sequence[TrajectoryPoint]
    start_time_ns: int | None = None
    start_in: float | None = None

    def to_joint_trajectory(self, now_ns: int) -> JointTrajectory:
        """The controller's trajectory message, with ``start_in`` resolved against ``now_ns``.

        Neither start given: start time 0 ("when the controller receives it").

        Raises:
            RequestError: ``start_in`` puts the start outside the daemon clock's range, or the
                last point would be after the end of the clock's range (int64 nanoseconds).
        """
        if self.start_time_ns is not None:
            start = self.start_time_ns
        elif self.start_in is not None:
            start = now_ns + seconds_to_ns(self.start_in)
            if not 0 <= start <= MAX_NS:
                raise RequestError(
                    BAD_REQUEST,
                    f"trajectory.start_in: {self.start_in!r} s from now ({now_ns} ns) is "
                    f"{start} ns, outside the daemon clock's range 0..{MAX_NS}",
                )
        else:
            start = 0
        # Start 0 means "now": the points are then timed from now.
        check_end(self.points, start or now_ns, "trajectory.points")
        return JointTrajectory(self.joint_names, self.points, start)


@dataclass(frozen=True)
class Hello(_Request):
    """``hello``: protocol and server versions, joints, rates, the daemon clock."""

    op: ClassVar[str] = "hello"
    protocol_version: int | None = None


@dataclass(frozen=True)
class Auth(_Request):
    """``auth``: the token of a TCP connection (must be its first request)."""

    op: ClassVar[str] = "auth"
    token: str = ""

    def __repr__(self) -> str:  # never log a token
        return f"Auth(id={self.id!r}, token=<{len(self.token)} characters>)"


@dataclass(frozen=True)
class SendGoal(_Request):
    """``send_goal``: a ``follow_joint_trajectory`` action goal."""

    op: ClassVar[str] = "send_goal"
    trajectory: WireTrajectory = field(default_factory=lambda: WireTrajectory((), ()))
    path_tolerance: tuple[JointTolerance, ...] = ()
    goal_tolerance: tuple[JointTolerance, ...] = ()
    goal_time_tolerance: float = 0.0
    time_scaling: str | None = None
    """``"reject"`` or ``"fit"`` a goal beyond the joint limits; None: the daemon's
    ``limits.time_scaling``."""


@dataclass(frozen=True)
class CancelGoal(_Request):
    """``cancel_goal``: ask the executing goal ``goal_id`` to stop."""

    op: ClassVar[str] = "cancel_goal"
    goal_id: int = 0


@dataclass(frozen=True)
class SendTrajectory(_Request):
    """``send_trajectory``: the ``joint_trajectory`` topic (no points: stop)."""

    op: ClassVar[str] = "send_trajectory"
    trajectory: WireTrajectory = field(default_factory=lambda: WireTrajectory((), ()))
    time_scaling: str | None = None
    """As ``SendGoal.time_scaling``."""


@dataclass(frozen=True)
class Stop(_Request):
    """``stop``: end any motion and hold (cancel the active goal, stop a topic trajectory).

    Served even over the connection limit (see ``docs/protocol.md``).
    """

    op: ClassVar[str] = "stop"


@dataclass(frozen=True)
class QueryState(_Request):
    """``query_state``: the desired state at an absolute time or at a time from now."""

    op: ClassVar[str] = "query_state"
    time_ns: int | None = None
    in_s: float | None = None

    def resolve(self, now_ns: int) -> int:
        """The absolute time asked for.

        Raises:
            RequestError: ``in`` puts the time outside the daemon clock's range.
        """
        if self.time_ns is not None:
            return self.time_ns
        t = now_ns + seconds_to_ns(self.in_s or 0.0)
        if not 0 <= t <= MAX_NS:
            raise RequestError(
                BAD_REQUEST,
                f"in: {self.in_s!r} s from now ({now_ns} ns) is outside the daemon clock's "
                f"range 0..{MAX_NS} ns",
                self.id,
            )
        return t


@dataclass(frozen=True)
class SubscribeState(_Request):
    """``subscribe_state``: receive ``state`` events; with ``commands``, also a ``command``
    event for every command the daemon accepts (any client's goals and topic trajectories)."""

    op: ClassVar[str] = "subscribe_state"
    commands: bool = False


@dataclass(frozen=True)
class UnsubscribeState(_Request):
    """``unsubscribe_state``: stop receiving ``state`` events."""

    op: ClassVar[str] = "unsubscribe_state"


@dataclass(frozen=True)
class GetConfig(_Request):
    """``get_config``: the configuration in effect."""

    op: ClassVar[str] = "get_config"


@dataclass(frozen=True)
class GetStatus(_Request):
    """``get_status``: loop, hardware, controller and server statistics."""

    op: ClassVar[str] = "get_status"


@dataclass(frozen=True)
class Sim(_Request):
    """``sim``: freeze or release a simulated component's feedback, or inject a latched
    read fault (``fault``: its message; cleared by ``rearm``)."""

    op: ClassVar[str] = "sim"
    component: str = ""
    freeze: bool | None = False
    fault: str | None = None


@dataclass(frozen=True)
class Rearm(_Request):
    """``rearm``: leave a hardware fault (reboot / fault-reset the devices, hold the position)."""

    op: ClassVar[str] = "rearm"


@dataclass(frozen=True)
class GetParameters(_Request):
    """``get_parameters``: controller parameter values by ROS-style name (``names``: some of
    them, ``None``: all)."""

    op: ClassVar[str] = "get_parameters"
    names: tuple[str, ...] | None = None


@dataclass(frozen=True)
class SetParameters(_Request):
    """``set_parameters``: change controller parameters while running (all or nothing); the
    values are checked by the daemon as the configuration file's are."""

    op: ClassVar[str] = "set_parameters"
    parameters: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SetSpeedScaling(_Request):
    """``set_speed_scaling``: the speed scaling factor to ramp to (``factor``: 1 full speed,
    0 pause), or ``resume``: back to the factor before the pause."""

    op: ClassVar[str] = "set_speed_scaling"
    factor: float | None = None
    resume: bool = False


Request = (
    Hello
    | Auth
    | SendGoal
    | CancelGoal
    | SendTrajectory
    | Stop
    | QueryState
    | SubscribeState
    | UnsubscribeState
    | GetConfig
    | GetStatus
    | Sim
    | Rearm
    | GetParameters
    | SetParameters
    | SetSpeedScaling
)


def check_end(points: Sequence[TrajectoryPoint], start_ns: int, path: str) -> None:
    """The last point's absolute time must fit the daemon clock (int64 nanoseconds).

    Raises:
        RequestError: ``bad_request`` naming the point.
    """
    if not points:
        return
    if isinstance(points, PointColumns):  # without building a point object per point
        index = int(points.times_ns.argmax())
        last = int(points.times_ns[index])
    else:
        index = max(range(len(points)), key=lambda i: points[i].time_from_start_ns)
        last = points[index].time_from_start_ns
    end = start_ns + last
    if end > MAX_NS:
        raise RequestError(
            BAD_REQUEST,
            f"{path}[{index}].time_from_start: the point would be due at {end} ns "
            f"(start {start_ns} ns + {last} ns), after the end of "
            f"the daemon clock's range ({MAX_NS} ns); start earlier or shorten the trajectory",
        )
