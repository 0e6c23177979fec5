"""The parameter schema a hardware kind declares its ``params`` with: the one engine.

A kind declares ``PARAMS = param_table(ParamSpec(...), ...)``; the base class checks a
component's ``params`` against it with :func:`validate_params` when the component is created
(docs/drivers.md). The engine is :mod:`jtc_hw.config.schema`, the same that checks the
controller's parameters and the robot file's ``hardware:`` and ``daemon:`` sections; this module
is its face in the hardware contract (``from jtc_hw.hardware import ParamSpec``).
"""

from ..config.schema import (
    ParamKind,
    ParamSpec,
    check_value,
    freeze,
    join,
    param_table,
    validate_params,
)

__all__ = [
    "ParamKind",
    "ParamSpec",
    "check_value",
    "freeze",
    "join",
    "param_table",
    "validate_params",
]
