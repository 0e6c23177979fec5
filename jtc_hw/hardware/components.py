"""A set of hardware components whose joints together are the controller's joints:
:class:`HardwareSet`."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from ..config.values import did_you_mean
from ..controller.config import COMMAND_INTERFACE_TYPES
from ..controller.joints import F64, JointCommand, JointState
from ..errors import ConfigurationError, JtcHwError, add_note
from .interface import HardwareInterface, _raise_first
from .lifecycle import _A, _ALLOWED, _F, _I, _U, LifecycleState, _lifecycle_error

__all__ = [
    "HardwareSet",
]

_RANK: Final = {_U: 0, _I: 1, _A: 2}


def _take(values: F64 | None, index: NDArray[np.intp]) -> F64 | None:
    return None if values is None else values[index]


class HardwareSet:
    """Components whose joints together are the controller's joints.

    Reads and writes fan out to each component once, mapping between the controller's joint
    order and each component's with index arrays computed here. Lifecycle methods fan out in
    component order; a failed ``configure``/``activate`` rolls back the components already
    transitioned (in reverse order), so the set is never half configured or half active.

    Args:
        components: the components (unique names, same command and state interfaces).
        joints: the controller's joints, in its order.

    Raises:
        ConfigurationError: no component, duplicate component names, components with
            different interfaces, a controller joint provided by no component or by two, or a
            component joint the controller does not have.
    """

    def __init__(self, components: Sequence[HardwareInterface], joints: Sequence[str]) -> None:
        self._components = tuple(components)
        self.joints: tuple[str, ...] = tuple(joints)
        if not self._components:
            raise ConfigurationError("a hardware set needs at least one component", "hardware")
        self._by_name: dict[str, HardwareInterface] = {}
        for comp in self._components:
            if comp.name in self._by_name:
                raise ConfigurationError(
                    f"two components are named {comp.name!r}; names must be unique",
                    "hardware",
                    comp.name,
                )
            self._by_name[comp.name] = comp
        first = self._components[0]
        self.command_interfaces: tuple[str, ...] = first.command_interfaces
        self.state_interfaces: tuple[str, ...] = first.state_interfaces
        for comp in self._components[1:]:
            if set(comp.command_interfaces) != set(first.command_interfaces) or set(
                comp.state_interfaces
            ) != set(first.state_interfaces):
                raise ConfigurationError(
                    f"component {comp.name!r} has interfaces command "
                    f"[{', '.join(comp.command_interfaces)}] / state "
                    f"[{', '.join(comp.state_interfaces)}] but {first.name!r} has command "
                    f"[{', '.join(first.command_interfaces)}] / state "
                    f"[{', '.join(first.state_interfaces)}]; all take the controller's",
                    "hardware",
                    comp.name,
                )
        position = {joint: i for i, joint in enumerate(self.joints)}
        owner: dict[str, str] = {}
        indices: list[NDArray[np.intp]] = []
        for comp in self._components:
            for joint in comp.joints:
                if joint not in position:
                    raise ConfigurationError(
                        f"component {comp.name!r} provides {joint!r}, which is not a controller "
                        f"joint (joints: {', '.join(self.joints)})"
                        f"{did_you_mean(joint, self.joints)}",
                        "hardware",
                        joint,
                    )
                if joint in owner:
                    raise ConfigurationError(
                        f"joint {joint!r} is provided by both {owner[joint]!r} and "
                        f"{comp.name!r}; each joint belongs to exactly one component",
                        "hardware",
                        joint,
                    )
                owner[joint] = comp.name
            indices.append(np.array([position[j] for j in comp.joints], dtype=np.intp))
        missing = [j for j in self.joints if j not in owner]
        if missing:
            listing = "; ".join(f"{c.name}: [{', '.join(c.joints)}]" for c in self._components)
            raise ConfigurationError(
                f"controller joint{'s' if len(missing) > 1 else ''} "
                f"{', '.join(repr(j) for j in missing)} not provided by any component "
                f"({listing})",
                "hardware",
                missing[0],
            )
        self._pairs = tuple(zip(self._components, indices, strict=True))
        self._n = len(self.joints)
        self._identity = len(self._components) == 1 and first.joints == self.joints
        if self._identity:
            # One component in the controller's order (most robots): the loop's read and write
            # of every cycle go straight to it, without a call through this set.
            self.read = first.read  # type: ignore[method-assign]
            self.write = first.write  # type: ignore[method-assign]
        self._velocity_state = "velocity" in self.state_interfaces
        self._acceleration_state = "acceleration" in self.state_interfaces
        self._command_fields = tuple(i in self.command_interfaces for i in COMMAND_INTERFACE_TYPES)

    @property
    def components(self) -> tuple[HardwareInterface, ...]:
        """The components, in the order given."""
        return self._components

    def component(self, name: str) -> HardwareInterface:
        """The component called ``name``.

        Raises:
            ConfigurationError: no component has that name (the message lists them).
        """
        found = self._by_name.get(name)
        if found is None:
            raise ConfigurationError(
                f"no hardware component named {name!r}; components: "
                f"{', '.join(self._by_name)}{did_you_mean(str(name), self._by_name)}",
                "hardware",
                name,
            )
        return found

    def scalar_interface(self, qualified: str, kind: str) -> tuple[HardwareInterface, str]:
        """The component and name of the scalar ``kind`` (``"state"`` or ``"command"``)
        interface ``qualified``, ``<component>/<name>`` (``speed_scaling.state_interface`` /
        ``command_interface``; :attr:`HardwareInterface.SCALAR_STATE_INTERFACES`).

        Raises:
            ConfigurationError: no component has that name, or it offers no such scalar
                interface; the message lists those the robot's components offer.
        """
        component, _, name = qualified.partition("/")
        offered = [
            f"{c.name}/{n}" for c in self._components
            for n in (c.SCALAR_STATE_INTERFACES if kind == "state"
                      else c.SCALAR_COMMAND_INTERFACES)
        ]
        found = self._by_name.get(component)
        if found is None or qualified not in offered:
            what = (f"no hardware component is named {component!r}" if found is None else
                    f"{found.kind} hardware {component!r} offers no scalar {kind} interface "
                    f"{name!r}")
            raise ConfigurationError(
                f"{qualified!r}: {what}; scalar {kind} interfaces of this robot: "
                f"{', '.join(offered) or 'none'}{did_you_mean(qualified, offered)}",
                f"speed_scaling.{kind}_interface",
                qualified,
            )
        return found, name

    @property
    def state(self) -> LifecycleState:
        """The components' common state (FINALIZED if any is; else the least advanced)."""
        states = [c.state for c in self._components]
        if _F in states:
            return _F
        return min(states, key=_RANK.__getitem__)

    def __repr__(self) -> str:
        return f"<HardwareSet {self.state.value} [{', '.join(c.name for c in self._components)}]>"

    def configure(self) -> None:
        """Configure every component; if one fails, clean up those already configured.

        Leaves INACTIVE on success; UNCONFIGURED if it fails.

        Raises:
            ControllerStateError: a component is not UNCONFIGURED (nothing was done).
            HardwareError: a component failed to configure (rollback errors attached as notes).
        """
        self._guard("configure")
        self._in_turn(lambda comp, _: comp.configure(), lambda comp: comp.cleanup())

    def activate(self, now_ns: int) -> JointCommand:
        """Activate every component; if one fails, deactivate those already active. Returns
        the merged held commands in the controller's joint order (``NaN`` where none).

        Leaves ACTIVE on success; INACTIVE if it fails.

        Raises:
            ControllerStateError: a component is not INACTIVE (nothing was done).
            HardwareError: a component failed to activate (rollback errors attached as notes).
        """
        self._guard("activate")
        held = [np.full(self._n, np.nan) if on else None for on in self._command_fields]

        def activate(comp: HardwareInterface, index: NDArray[np.intp]) -> None:
            command = comp.activate(now_ns)
            values = (command.positions, command.velocities, command.accelerations, command.effort)
            for merged, part in zip(held, values, strict=True):
                if merged is not None and part is not None:
                    merged[index] = part

        self._in_turn(activate, lambda comp: comp.deactivate(now_ns))
        return JointCommand(*held)

    def _in_turn(
        self,
        step: Callable[[HardwareInterface, NDArray[np.intp]], None],
        undo: Callable[[HardwareInterface], None],
    ) -> None:
        """``step`` on each component (with its joints' indices) in turn; if one fails,
        ``undo`` on those it succeeded on, last first (their errors attached as notes)."""
        done: list[HardwareInterface] = []
        for comp, index in self._pairs:
            try:
                step(comp, index)
            except BaseException as exc:
                for other in reversed(done):
                    try:
                        undo(other)
                    except Exception as rollback:  # noqa: BLE001 - reported as a note
                        add_note(exc, f"rolling back {other.name!r} failed: {rollback}")
                raise
            done.append(comp)

    def read(self, now_ns: int) -> JointState:
        """Read every component once; return the state in the controller's joint order (one
        component in that order: its own ``read``, bound in its place when the set is made).

        Raises:
            ControllerStateError: a component is not INACTIVE or ACTIVE.
            HardwareError: a component's read failed (the others after it are not read).
        """
        return self._merged((comp.read(now_ns), index) for comp, index in self._pairs)

    def monitor(self, now_ns: int) -> JointState | None:
        """Each INACTIVE component's :meth:`HardwareInterface.monitor` (the loop, while
        faulted); the state in the controller's joint order, NaN for joints not read, or
        ``None`` if none was.
        """
        parts = [(comp.monitor(now_ns), index) for comp, index in self._pairs]
        if all(part is None for part, _ in parts):
            return None
        return self._merged(parts)

    def _merged(self, parts: Iterable[tuple[JointState | None, NDArray[np.intp]]]) -> JointState:
        """The components' states in the controller's joint order (NaN for joints not read)."""
        n = self._n
        positions = np.full(n, np.nan)
        velocities = np.full(n, np.nan) if self._velocity_state else None
        accelerations = np.full(n, np.nan) if self._acceleration_state else None
        for part, index in parts:
            if part is None:
                continue
            positions[index] = part.positions
            if velocities is not None and part.velocities is not None:
                velocities[index] = part.velocities
            if accelerations is not None and part.accelerations is not None:
                accelerations[index] = part.accelerations
        return JointState(positions, velocities, accelerations)

    def write(self, now_ns: int, command: JointCommand) -> None:
        """Split the command by component and write each once (one component in the
        controller's order: its own ``write``, bound in its place when the set is made).

        Raises:
            ControllerStateError: a component is not ACTIVE.
            HardwareError: a component's write failed (the others after it are not written).
        """
        values = (command.positions, command.velocities, command.accelerations, command.effort)
        for comp, index in self._pairs:
            comp.write(now_ns, JointCommand(*(_take(v, index) for v in values)))

    def deactivate(self, now_ns: int) -> None:
        """Deactivate every component (each performs its safe action), even if one fails.

        Leaves INACTIVE.

        Raises:
            ControllerStateError: a component is not ACTIVE (nothing was done).
            HardwareError: a component's safe action failed (first error raised, others
                attached as notes).
        """
        self._guard("deactivate")
        self._fan_out(lambda comp: comp.deactivate(now_ns))

    def recover(self) -> None:
        """Clear every component's latched faults (see :meth:`HardwareInterface.recover`).

        Leaves INACTIVE.

        Raises:
            ControllerStateError: a component is not INACTIVE (nothing was done).
            HardwareError: a component could not clear its fault (every one is attempted).
        """
        self._guard("recover")
        self._fan_out(lambda comp: comp.recover())

    def cleanup(self) -> None:
        """Clean up every component, even if one fails.

        Leaves UNCONFIGURED.

        Raises:
            ControllerStateError: a component is not INACTIVE (nothing was done).
            HardwareError: a component failed to release its device.
        """
        self._guard("cleanup")
        self._fan_out(lambda comp: comp.cleanup())

    def shutdown(self, now_ns: int) -> None:
        """Shut every component down, whatever its state. Leaves FINALIZED.

        Raises:
            HardwareError: a component failed to deactivate or clean up.
        """
        self._fan_out(lambda comp: comp.shutdown(now_ns))

    def status(self) -> dict[str, Any]:
        """A JSON-able summary: ``state``, ``joints`` and each component's ``status()``."""
        return {
            "state": self.state.value,
            "joints": list(self.joints),
            "components": [c.status() for c in self._components],
        }

    def _guard(self, method: str) -> None:
        for comp in self._components:
            if comp.state not in _ALLOWED[method]:
                raise _lifecycle_error(f"hardware set (component {comp.name!r})", method,
                                       comp.state)

    def _fan_out(self, action: Callable[[HardwareInterface], None]) -> None:
        errors: list[BaseException] = []
        for comp in self._components:
            try:
                action(comp)
            except JtcHwError as exc:
                errors.append(exc)
        _raise_first(errors)
