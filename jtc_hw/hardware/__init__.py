"""The hardware contract: what every driver implements, and how kinds are found and combined.

- :mod:`.interface`: :class:`HardwareInterface`, the ros2_control lifecycle every component
  follows, with the policy (transition guard, parameter validation, error wrapping) in the base
  class and the I/O in the driver's underscore primitives; :mod:`.lifecycle`: its states and
  transition table; :mod:`.params`: the parameter rows kinds share.
- :class:`ParamSpec`, :func:`param_table`, :func:`validate_params`: how a kind declares its
  ``params`` (docs/drivers.md), the one schema engine of :mod:`jtc_hw.config.schema`.
- :mod:`.components`: :class:`HardwareSet`, several components forming the controller's joints.
- :mod:`.registry`: kinds by name (built-in, the ``jtc_hw.hardware`` entry-point group,
  :func:`register_hardware`), created lazily.
- :mod:`.mirror`: simulated joints (imported on use, through the registry).
- :mod:`.timing`: timer slack, for anything that paces a bus (drivers, emulators, the loop).

Drivers import what they need from here: ``from jtc_hw.hardware import HardwareInterface``.
"""

from ..config.schema import ParamKind, ParamSpec, param_table, validate_params
from ..controller.joints import JointCommand, JointState
from .components import HardwareSet
from .interface import (
    HEALTH_FIELDS,
    NO_DEVICE_WATCHDOG,
    DeviceName,
    DeviceWatchdog,
    HardwareInterface,
    one_line,
)
from .lifecycle import TRANSITIONS, LifecycleState, SafeAction
from .params import (
    COMMON_PARAMS,
    DEFAULT_WATCHDOG_S,
    JOINT_MAPPING_PARAMS,
    MIN_WATCHDOG_PERIODS,
    WATCHDOG_PARAM,
    health_params,
    miss_rate_param,
)
from .registry import (
    BUILTIN_HARDWARE,
    ENTRY_POINT_GROUP,
    HardwareSpec,
    available_hardware,
    check_hardware_kind,
    create_hardware,
    hardware_class,
    register_hardware,
    unregister_hardware,
)

__all__ = [
    "BUILTIN_HARDWARE",
    "COMMON_PARAMS",
    "DEFAULT_WATCHDOG_S",
    "ENTRY_POINT_GROUP",
    "HEALTH_FIELDS",
    "JOINT_MAPPING_PARAMS",
    "MIN_WATCHDOG_PERIODS",
    "NO_DEVICE_WATCHDOG",
    "TRANSITIONS",
    "WATCHDOG_PARAM",
    "DeviceName",
    "DeviceWatchdog",
    "HardwareInterface",
    "HardwareSet",
    "HardwareSpec",
    "JointCommand",
    "JointState",
    "LifecycleState",
    "ParamKind",
    "ParamSpec",
    "SafeAction",
    "available_hardware",
    "check_hardware_kind",
    "create_hardware",
    "hardware_class",
    "health_params",
    "miss_rate_param",
    "one_line",
    "param_table",
    "register_hardware",
    "unregister_hardware",
    "validate_params",
]
