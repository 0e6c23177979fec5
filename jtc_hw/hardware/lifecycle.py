"""The lifecycle every hardware component follows: its states, one transition table, the
guard's error.

ros2_control's ``SystemInterface`` lifecycle (the diagram and the rules are in
:mod:`.interface`); a call in a state that does not allow it is refused with the transitions
that would lead to one that does.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from enum import Enum
from types import MappingProxyType
from typing import Final

from ..errors import ControllerStateError


class LifecycleState(Enum):
    """Lifecycle state of a hardware component (ros2_control's primary states)."""

    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FINALIZED = "finalized"


class SafeAction(Enum):
    """What ``deactivate`` leaves the joints doing (the ``safe_action`` parameter)."""

    HOLD = "hold"
    """Keep torque on and hold the last position."""
    TORQUE_OFF = "torque_off"
    """Switch the drives off; the joints are free (and hold no command any more)."""


_U, _I, _A, _F = (
    LifecycleState.UNCONFIGURED,
    LifecycleState.INACTIVE,
    LifecycleState.ACTIVE,
    LifecycleState.FINALIZED,
)

TRANSITIONS: Final[Mapping[tuple[LifecycleState, str], LifecycleState]] = MappingProxyType({
    (_U, "configure"): _I,
    (_I, "activate"): _A,
    (_A, "deactivate"): _I,
    (_I, "cleanup"): _U,
})
"""The lifecycle transitions: (state, method) -> state left on success."""

_ALLOWED: Final[Mapping[str, frozenset[LifecycleState]]] = MappingProxyType({
    **{method: frozenset({state}) for (state, method) in TRANSITIONS},
    "read": frozenset({_I, _A}),
    "write": frozenset({_A}),
    "recover": frozenset({_I}),
})


def _steps_to(state: LifecycleState, targets: frozenset[LifecycleState]) -> list[str] | None:
    """Shortest list of transition methods leading from ``state`` into ``targets``."""
    queue: deque[tuple[LifecycleState, list[str]]] = deque([(state, [])])
    seen = {state}
    while queue:
        current, steps = queue.popleft()
        if current in targets:
            return steps
        for (source, method), target in TRANSITIONS.items():
            if source is current and target not in seen:
                seen.add(target)
                queue.append((target, [*steps, method]))
    return None


def _lifecycle_error(owner: str, method: str, state: LifecycleState) -> ControllerStateError:
    steps = _steps_to(state, _ALLOWED[method])
    if not steps:
        hint = "it was shut down; create a new instance"
    else:
        hint = "call " + " and ".join(f"{step}()" for step in steps) + " first"
    return ControllerStateError(f"{owner}: cannot call {method}() while {state.value}; {hint}")
