"""jtc_hw: ROS 2 joint_trajectory_controller semantics without ROS.

The controller core is a pure library: feed it time and state, get commands and goal events.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .errors import (
    CommunicationError,
    ConfigurationError,
    ControllerStateError,
    GoalRejected,
    HardwareError,
    JtcHwError,
    MotorFault,
    ProtocolError,
)

if TYPE_CHECKING:
    from .config.controller import ControllerConfig
    from .config.reading import load_config
    from .controller.controller import JointTrajectoryController
    from .controller.goals import (
        ErrorCode,
        GoalFeedback,
        GoalResult,
        GoalStatus,
        TrajectoryStopped,
    )
    from .controller.joints import JointCommand, JointState
    from .controller.messages import JointTrajectory, TrajectoryPoint
    from .controller.results import UpdateResult
    from .controller.tolerances import JointTolerance
    from .controller.trajectory import QueriedState, Trajectory, TrajectorySample

# Start-up time: the library's names load when first used (PEP 562), not when a submodule is
# imported. `jtc-hw send` imports jtc_hw.cli, which imports this package first; loading the
# controller (and numpy) here cost 80-130 ms before the command could print anything, more than
# issue 24's 100 ms for the progress bar to show.
_LAZY = {
    "ControllerConfig": ".config.controller",
    "load_config": ".config.reading",
    "JointTrajectoryController": ".controller.controller",
    "ErrorCode": ".controller.goals",
    "GoalFeedback": ".controller.goals",
    "GoalResult": ".controller.goals",
    "GoalStatus": ".controller.goals",
    "TrajectoryStopped": ".controller.goals",
    "JointCommand": ".controller.joints",
    "JointState": ".controller.joints",
    "JointTrajectory": ".controller.messages",
    "TrajectoryPoint": ".controller.messages",
    "UpdateResult": ".controller.results",
    "JointTolerance": ".controller.tolerances",
    "QueriedState": ".controller.trajectory",
    "Trajectory": ".controller.trajectory",
    "TrajectorySample": ".controller.trajectory",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value  # the next lookup finds it without coming here
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "CommunicationError",
    "ConfigurationError",
    "ControllerConfig",
    "ControllerStateError",
    "ErrorCode",
    "GoalFeedback",
    "GoalRejected",
    "GoalResult",
    "GoalStatus",
    "HardwareError",
    "JointCommand",
    "JointState",
    "JointTolerance",
    "JointTrajectory",
    "JointTrajectoryController",
    "JtcHwError",
    "MotorFault",
    "ProtocolError",
    "QueriedState",
    "Trajectory",
    "TrajectoryPoint",
    "TrajectorySample",
    "TrajectoryStopped",
    "UpdateResult",
    "load_config",
]

__version__ = "0.1.0"
