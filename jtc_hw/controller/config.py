"""The controller's configuration as the controller (and a driver) imports it.

The parameters are declared, checked and frozen in :mod:`jtc_hw.config.controller` (the one
schema engine, :mod:`jtc_hw.config.schema`); files are read in :mod:`jtc_hw.config.reading`.
This module re-exports the frozen types and constants, so that the controller's modules and
drivers (``from jtc_hw.controller.config import STATE_INTERFACE_TYPES``) keep their import.
"""

from ..config.controller import (
    ALLOWED_COMMAND_INTERFACE_COMBINATIONS,
    ALLOWED_STATE_INTERFACE_COMBINATIONS,
    COMMAND_INTERFACE_TYPES,
    CONSTRAINT_PARAMETERS,
    CONTROLLER_TYPE,
    DEFAULT_CONTROLLER_NAME,
    DEFAULTS,
    GAIN_PARAMETERS,
    JOINT_CONSTRAINT_PARAMETERS,
    LIMITS_PARAMETERS,
    MAX_SCALING_CEILING,
    PARAMETERS,
    SPEED_SCALING_PARAMETERS,
    STATE_INTERFACE_TYPES,
    Constraints,
    ControllerConfig,
    Gains,
    JointConstraints,
    SpeedScaling,
)
from ..config.schema import Effect

__all__ = [
    "ALLOWED_COMMAND_INTERFACE_COMBINATIONS",
    "ALLOWED_STATE_INTERFACE_COMBINATIONS",
    "COMMAND_INTERFACE_TYPES",
    "CONSTRAINT_PARAMETERS",
    "CONTROLLER_TYPE",
    "DEFAULTS",
    "DEFAULT_CONTROLLER_NAME",
    "Constraints",
    "ControllerConfig",
    "Effect",
    "GAIN_PARAMETERS",
    "Gains",
    "JOINT_CONSTRAINT_PARAMETERS",
    "JointConstraints",
    "LIMITS_PARAMETERS",
    "MAX_SCALING_CEILING",
    "PARAMETERS",
    "SPEED_SCALING_PARAMETERS",
    "STATE_INTERFACE_TYPES",
    "SpeedScaling",
]
