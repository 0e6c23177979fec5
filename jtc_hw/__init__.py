"""jtc_hw: ROS 2 joint_trajectory_controller semantics without ROS.

The controller core is a pure library: feed it time and state, get commands and goal events.
"""

from .config import ControllerConfig, load_config
from .controller import JointTrajectoryController, UpdateResult
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
from .goals import ErrorCode, GoalFeedback, GoalResult, GoalStatus, TrajectoryStopped
from .joints import JointCommand, JointState
from .tolerances import JointTolerance
from .trajectory import JointTrajectory, Trajectory, TrajectoryPoint, TrajectorySample

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
    "Trajectory",
    "TrajectoryPoint",
    "TrajectorySample",
    "TrajectoryStopped",
    "UpdateResult",
    "load_config",
]

__version__ = "0.1.0"
