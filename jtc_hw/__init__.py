"""jtc_hw: ROS 2 joint_trajectory_controller semantics without ROS.

The controller core is a pure library: feed it time and state, get commands and goal events.
"""

from .config.controller import ControllerConfig
from .config.reading import load_config
from .controller.controller import JointTrajectoryController
from .controller.goals import ErrorCode, GoalFeedback, GoalResult, GoalStatus, TrajectoryStopped
from .controller.joints import JointCommand, JointState
from .controller.messages import JointTrajectory, TrajectoryPoint
from .controller.results import UpdateResult
from .controller.tolerances import JointTolerance
from .controller.trajectory import QueriedState, Trajectory, TrajectorySample
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
