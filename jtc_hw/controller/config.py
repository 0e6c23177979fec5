"""The controller's configuration as the controller, the hardware contract and drivers import it.

:class:`ControllerConfig` and its parameters are declared, checked and frozen in
:mod:`jtc_hw.config.controller` (the one schema engine); files are read in
:mod:`jtc_hw.config.reading`. The names here stay importable where drivers import them
(``from jtc_hw.controller.config import STATE_INTERFACE_TYPES``).
"""

from ..config.controller import (
    COMMAND_INTERFACE_TYPES,
    MAX_SCALING_CEILING,
    STATE_INTERFACE_TYPES,
    ControllerConfig,
)

__all__ = [
    "COMMAND_INTERFACE_TYPES",
    "MAX_SCALING_CEILING",
    "STATE_INTERFACE_TYPES",
    "ControllerConfig",
]
