"""The hardware contract: the base class every component derives from.

The lifecycle's states and transition table are in :mod:`.lifecycle`, the shared parameter
rows in :mod:`.params`; :mod:`jtc_hw.hardware` exports them with the base class, as the contract.

Theory of operation
-------------------
A :class:`HardwareInterface` is one component (a bus, a motor group, a simulator) serving some
joints in SI units. It follows ros2_control's ``SystemInterface`` lifecycle::

    UNCONFIGURED --configure()--> INACTIVE --activate()--> ACTIVE
    UNCONFIGURED <--cleanup()---- INACTIVE <--deactivate()- ACTIVE
    any state --shutdown()--> FINALIZED

``read`` is allowed while INACTIVE or ACTIVE (the daemon shows positions of a disarmed robot),
``write`` only while ACTIVE. The base class owns the policy, as python-can's ``BusABC`` does:
the transition guard (:data:`~.lifecycle.TRANSITIONS`, one table), parameter validation
against the kind's :attr:`HardwareInterface.PARAMS` schema, wrapping of foreign exceptions in
:class:`~jtc_hw.errors.HardwareError` naming the component, fault bookkeeping and counters.
Drivers implement the underscore primitives (``_read``, ``_write`` and, if they need them,
``_configure``, ``_activate``, ``_deactivate``, ``_cleanup``).

A failed ``configure``/``activate`` leaves the state unchanged. A failed ``deactivate`` or
``cleanup`` still leaves the state it aims at: the component stops accepting writes (the safe
side for us) and the error reports that the device may not have performed its safe action.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar, Final

import numpy as np

from ..config.schema import ParamKind, ParamSpec, check_value, validate_params
from ..config.values import describe, did_you_mean
from ..controller.config import COMMAND_INTERFACE_TYPES, STATE_INTERFACE_TYPES
from ..controller.joints import F64, JointCommand, JointState
from ..errors import ConfigurationError, HardwareError, JtcHwError, add_note
from .lifecycle import _ALLOWED, LifecycleState, SafeAction, _lifecycle_error
from .params import COMMON_PARAMS, MISS_RATE_WINDOW

__all__ = [
    "NO_DEVICE_WATCHDOG",
    "DeviceName",
    "DeviceWatchdog",
    "HEALTH_FIELDS",
    "HardwareInterface",
    "one_line",
]

_log = logging.getLogger("jtc_hw.hardware")


HEALTH_FIELDS: Final[tuple[str, ...]] = (
    "motor", "joint", "model", "firmware", "mode", "torque_enabled", "temperature_c",
    "voltage_v", "errors", "last_fault",
)
"""The keys of one motor's entry in :meth:`HardwareInterface.health` (``None``: unknown)."""


MONITOR_RETRY_NS = 1_000_000_000
"""After a failed :meth:`HardwareInterface.monitor` (a device silent while faulted), how long the
next attempt waits, ns."""


def one_line(exc: BaseException) -> str:
    """An exception's text as one line, for messages a client sees.

    Libraries' messages may span lines; python-can's socketcand client even appends a whole
    traceback to its errors ("Failed to receive: ... Traceback (most recent call last): ...").
    The first non-empty line before any traceback is kept (the type name if there is none).
    """
    text = str(exc).split("Traceback (most recent call last)", 1)[0]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


@dataclass(frozen=True)
class DeviceWatchdog:
    """What stops a component's motors when the daemon stops commanding them.

    Attributes:
        timeout_s: the device-side timeout armed on activate; ``None``: (some of) the devices
            have none and keep their last command if the daemon dies.
        mechanism: one line for ``jtc-hw check`` and ``docs/safety.md``: what it is and what
            the device does on expiry (e.g. "Dynamixel Bus Watchdog 100 ms: servos stop").
        unprotected: joints whose motors have no watchdog (mixed models on one component).
    """

    timeout_s: float | None
    mechanism: str
    unprotected: tuple[str, ...] = ()

    @property
    def complete(self) -> bool:
        """Every motor of the component stops by itself."""
        return self.timeout_s is not None and not self.unprotected


NO_DEVICE_WATCHDOG: Final = DeviceWatchdog(
    None, "no device-side watchdog: motors keep their last command if the daemon dies"
)


@dataclass(frozen=True)
class DeviceName:
    """One thing a daemon must drive alone, as the device lock knows it.

    Attributes:
        key: canonical: the same string for every spelling that reaches the same device (a
            serial port's real path, a resolved host and port, a network interface's index)
            and different for different devices; it names the lock file.
        label: what a user recognises, for messages ("bus 'can0' (socketcan can0) motor 3").
    """

    key: str
    label: str


# -- The contract ---------------------------------------------------------------------------------


def _check_names(value: Any, path: str, description: str) -> tuple[str, ...]:
    spec = ParamSpec(path, ParamKind.STRINGS, (), description, unique=True, non_empty=True)
    names: tuple[str, ...] = check_value(spec, value, path)
    return names


def _check_interfaces(
    value: Any, path: str, supported: Sequence[str], owner: str
) -> tuple[str, ...]:
    names = _check_names(value, path, path.replace("_", " "))
    for name in names:
        if name not in supported:
            raise ConfigurationError(
                f"{owner} does not support the {name!r} interface; it supports "
                f"[{', '.join(supported)}]{did_you_mean(name, supported)}",
                path,
                name,
            )
    return names


class HardwareInterface(ABC):
    """A hardware component serving some joints, with the ros2_control lifecycle.

    Subclasses declare :attr:`kind` and :attr:`PARAMS` and implement ``_read`` and ``_write``
    (the other primitives if they need them); the module docstring has the state machine and
    the policy the public methods own.

    Args:
        name: component name, unique within a robot (used in every message).
        joints: the component's joints, in the order its arrays use.
        command_interfaces: the controller's command interfaces (all joints take them).
        state_interfaces: the controller's state interfaces; must include ``position``.
        params: kind-specific parameters, checked against ``COMMON_PARAMS`` + ``PARAMS``.

    Raises:
        ConfigurationError: bad name, joints, interfaces (or one the kind does not support),
            or parameters; the path is ``name``, ``joints``, ``command_interfaces``,
            ``state_interfaces`` or ``params.<key>``.
        TypeError: the subclass does not declare ``kind``.
    """

    kind: ClassVar[str]
    """Registry name of the hardware kind (e.g. ``"mirror"``)."""

    PARAMS: ClassVar[Mapping[str, ParamSpec]] = MappingProxyType({})
    """Kind-specific parameter schema (see :func:`param_table`)."""

    COMMAND_INTERFACES: ClassVar[tuple[str, ...]] = COMMAND_INTERFACE_TYPES
    """Command interfaces the kind can serve."""

    STATE_INTERFACES: ClassVar[tuple[str, ...]] = STATE_INTERFACE_TYPES
    """State interfaces the kind can serve."""

    SCALAR_STATE_INTERFACES: ClassVar[tuple[str, ...]] = ()
    """Scalar state interfaces the kind offers beside its joints' (ros2_control's GPIO
    interfaces): a robot's speed slider, its safety controller's reduced-speed factor. The
    controller names one ``<component>/<name>`` (``speed_scaling.state_interface``) and reads
    it each cycle after ``read`` with :meth:`scalar_state`."""

    SCALAR_COMMAND_INTERFACES: ClassVar[tuple[str, ...]] = ()
    """Scalar command interfaces (``speed_scaling.command_interface``): the loop sets one each
    cycle with :meth:`set_scalar_command` before ``write``, which sends it."""

    def __init__(
        self,
        name: str,
        joints: Sequence[str],
        command_interfaces: Sequence[str],
        state_interfaces: Sequence[str],
        params: Mapping[str, Any],
    ) -> None:
        kind = getattr(type(self), "kind", None)
        if not isinstance(kind, str) or not kind:
            raise TypeError(f"{type(self).__name__} must declare a non-empty 'kind' class variable")
        if not isinstance(name, str) or not name.strip():
            raise ConfigurationError(
                f"expected a non-empty component name, got {describe(name)}", "name", name
            )
        self.name: str = name
        owner = self._owner()
        self.joints: tuple[str, ...] = _check_names(joints, "joints", "the joints of the component")
        self.command_interfaces: tuple[str, ...] = _check_interfaces(
            command_interfaces, "command_interfaces", type(self).COMMAND_INTERFACES, owner
        )
        self.state_interfaces: tuple[str, ...] = _check_interfaces(
            state_interfaces, "state_interfaces", type(self).STATE_INTERFACES, owner
        )
        if "position" not in self.state_interfaces:
            raise ConfigurationError(
                f"{owner}: the state interfaces must include 'position', got "
                f"[{', '.join(self.state_interfaces)}]",
                "state_interfaces",
                self.state_interfaces,
            )
        self.params: Mapping[str, Any] = validate_params(
            self.schema(), params, "params", joints=self.joints, owner=owner
        )
        self.safe_action: SafeAction = SafeAction(self.params["safe_action"])
        self._state = LifecycleState.UNCONFIGURED
        self._shape = (len(self.joints),)
        self._velocity_state = "velocity" in self.state_interfaces
        self._acceleration_state = "acceleration" in self.state_interfaces
        self._last_fault: str | None = None
        self._reads = 0
        self._writes = 0
        self._read_errors = 0
        self._write_errors = 0
        self._activations = 0
        self._health_warnings: dict[tuple[str, str], str] = {}
        # The miss-rate window: the bus counters (transactions, timeouts) at its start, and
        # the warning the last window left (kept until the next one closes).
        self._miss_window: tuple[int, int] | None = None
        self._miss_warning: str | None = None
        self._monitor_retry_ns: int | None = None  # after a failed monitor(): not before this

    @classmethod
    def schema(cls) -> Mapping[str, ParamSpec]:
        """The full parameter schema of the kind: ``COMMON_PARAMS`` then ``PARAMS``."""
        return MappingProxyType({**COMMON_PARAMS, **cls.PARAMS})

    @property
    def state(self) -> LifecycleState:
        """The current lifecycle state."""
        return self._state

    @property
    def last_fault(self) -> str | None:
        """Message of the last error raised by this component, if any."""
        return self._last_fault

    def __repr__(self) -> str:
        return (
            f"<{type(self).__name__} {self.name!r} ({self.kind}) {self._state.value} "
            f"joints=[{', '.join(self.joints)}]>"
        )

    # -- public lifecycle ---------------------------------------------------------------------

    def configure(self) -> None:
        """Open the device and check it (e.g. ping every motor).

        Leaves INACTIVE on success; stays UNCONFIGURED if it fails.

        Raises:
            ControllerStateError: not UNCONFIGURED.
            HardwareError: the device could not be configured.
        """
        self._guard("configure")
        self._call("configure", self._configure)
        self._state = LifecycleState.INACTIVE

    def activate(self, now_ns: int) -> JointCommand:
        """Enable the drives so that writes take effect.

        Args:
            now_ns: the loop's time, integer nanoseconds.

        Returns:
            The command values the hardware holds (for the controller's
            ``set_last_command_interface_value_as_state_on_activation``): an array for each
            configured command interface, ``NaN`` where the hardware holds none; ``None`` for
            interfaces not configured.

        Leaves ACTIVE on success; stays INACTIVE if it fails.

        Raises:
            ControllerStateError: not INACTIVE.
            HardwareError: the drives could not be enabled, or the driver returned arrays of
                the wrong size.
        """
        self._guard("activate")
        held = self._call("activate", self._activate, now_ns)
        try:
            command = self._held_command(held)
        except HardwareError as exc:
            self._last_fault = str(exc)
            try:
                self._deactivate(now_ns, self.safe_action)
            except Exception as rollback:  # noqa: BLE001 - reported as a note
                add_note(exc, f"undoing the activation failed too: {rollback!r}")
            raise
        self._state = LifecycleState.ACTIVE
        self._activations += 1
        return command

    def read(self, now_ns: int) -> JointState:
        """Read the joints' state: one bus transaction.

        Args:
            now_ns: the loop's time, integer nanoseconds.

        Returns:
            The state in this component's joint order, with velocities / accelerations when
            those state interfaces are configured.

        Leaves the state unchanged (INACTIVE or ACTIVE); an error does not change it either:
        the caller decides (typically ``deactivate``).

        Raises:
            ControllerStateError: not INACTIVE or ACTIVE.
            HardwareError: the device did not answer (``CommunicationError``), reported a
                fault (``MotorFault``), or the driver returned arrays of the wrong size.
        """
        state = self._state
        if state is not LifecycleState.ACTIVE and state is not LifecycleState.INACTIVE:
            raise _lifecycle_error(self._owner(), "read", state)
        try:
            result: JointState = self._call("read", self._read, now_ns)
        except Exception:
            self._read_errors += 1
            raise
        if (
            result.positions.shape != self._shape
            or (self._velocity_state and (
                result.velocities is None or result.velocities.shape != self._shape))
            or (self._acceleration_state and (
                result.accelerations is None or result.accelerations.shape != self._shape))
        ):
            self._read_errors += 1
            error = HardwareError(
                f"{self._owner()}: read() returned a state that does not match its "
                f"{len(self.joints)} joints and state interfaces "
                f"[{', '.join(self.state_interfaces)}]; this is a driver bug"
            )
            self._last_fault = str(error)
            raise error
        self._reads += 1
        return result

    def write(self, now_ns: int, command: JointCommand) -> None:
        """Write the commands: one bus transaction.

        ``NaN`` entries mean "do not write that joint's interface": the device keeps the
        value it holds.

        Args:
            now_ns: the loop's time, integer nanoseconds.
            command: arrays in this component's joint order, one per configured interface.

        Leaves ACTIVE (an error does not change the state; the caller decides).

        Raises:
            ControllerStateError: not ACTIVE.
            HardwareError: the device did not accept the command.
        """
        state = self._state
        if state is not LifecycleState.ACTIVE:
            raise _lifecycle_error(self._owner(), "write", state)
        try:
            self._call("write", self._write, now_ns, command)
        except Exception:
            self._write_errors += 1
            raise
        self._writes += 1

    def monitor(self, now_ns: int) -> JointState | None:
        """While INACTIVE (after a fault, the safe action applied): read what the driver can
        read without commanding anything, refreshing :meth:`health`; the loop calls it every
        cycle while faulted.

        Drivers decide what is safe to send (``_monitor``): a Dynamixel bus is read only when
        no servo's Bus Watchdog may still be armed, since any instruction packet would feed it;
        CAN drivers, whose frames are commands or whose answers need the drive active, read
        nothing (the default).

        Returns the joints' measured state if the driver read it, else ``None``. Never raises:
        a failed read is counted (``read_errors``) and gives ``None``, and the next attempt waits
        ``MONITOR_RETRY_NS`` (a silent device would otherwise cost every cycle its reply timeout);
        the next activation is what decides about the device.
        """
        if self._state is not LifecycleState.INACTIVE:
            return None
        if self._monitor_retry_ns is not None and now_ns < self._monitor_retry_ns:
            return None
        try:
            result = self._monitor(now_ns)
        except Exception:  # noqa: BLE001 - counted; a faulted component stays faulted
            self._read_errors += 1
            self._monitor_retry_ns = now_ns + MONITOR_RETRY_NS
            return None
        self._monitor_retry_ns = None
        if result is None or result.positions.shape != self._shape:
            return None
        return result

    def deactivate(self, now_ns: int) -> None:
        """Stop taking commands and perform the ``safe_action`` (hold, or torque off).

        Leaves INACTIVE, even if the safe action fails: no further writes are accepted, and
        the error tells the caller the device may not be in its safe state.

        Raises:
            ControllerStateError: not ACTIVE.
            HardwareError: the safe action could not be performed.
        """
        self._guard("deactivate")
        try:
            self._call("deactivate", self._deactivate, now_ns, self.safe_action)
        finally:
            self._state = LifecycleState.INACTIVE

    def recover(self) -> None:
        """Clear the device's latched faults: reboot a faulted servo, reset a drive's fault.

        The daemon calls it on a client's explicit re-arm request, after ``configure`` and
        before ``activate`` (which seeds the command from the measured position, so re-arming
        never jumps). Devices that latch nothing do nothing.

        Leaves INACTIVE (also when it fails: the caller keeps the controller stopped).

        Raises:
            ControllerStateError: not INACTIVE.
            HardwareError: the fault could not be cleared (the message names the motor and
                what to check).
        """
        self._guard("recover")
        self._call("recover", self._recover)
        self._last_fault = None

    def cleanup(self) -> None:
        """Release the device (close the port / bus).

        Leaves UNCONFIGURED, even if releasing fails.

        Raises:
            ControllerStateError: not INACTIVE.
            HardwareError: releasing failed.
        """
        self._guard("cleanup")
        try:
            self._call("cleanup", self._cleanup)
        finally:
            self._state = LifecycleState.UNCONFIGURED

    def shutdown(self, now_ns: int) -> None:
        """Whatever the state, deactivate and clean up as needed; final.

        Leaves FINALIZED (every later call except ``shutdown`` and ``status`` raises). Calling
        it again does nothing.

        Raises:
            HardwareError: deactivating or cleaning up failed (both are attempted; the first
                error is raised, the other attached as a note).
        """
        errors: list[HardwareError] = []
        if self._state is LifecycleState.ACTIVE:
            try:
                self.deactivate(now_ns)
            except HardwareError as exc:
                errors.append(exc)
        if self._state is LifecycleState.INACTIVE:
            try:
                self.cleanup()
            except HardwareError as exc:
                errors.append(exc)
        self._state = LifecycleState.FINALIZED
        _raise_first(errors)

    def status(self) -> dict[str, Any]:
        """A JSON-able summary for clients and logs.

        Returns:
            ``name``, ``kind``, ``state``, ``joints``, ``command_interfaces``,
            ``state_interfaces``, ``safe_action``, ``last_fault`` (message or ``None``),
            ``counters`` (reads, writes, read_errors, write_errors, activations) and
            ``details`` (whatever the driver reports, see ``_details``).
        """
        return {
            "name": self.name,
            "kind": self.kind,
            "state": self._state.value,
            "joints": list(self.joints),
            "command_interfaces": list(self.command_interfaces),
            "state_interfaces": list(self.state_interfaces),
            "safe_action": self.safe_action.value,
            "last_fault": self._last_fault,
            "counters": {
                "reads": self._reads,
                "writes": self._writes,
                "read_errors": self._read_errors,
                "write_errors": self._write_errors,
                "activations": self._activations,
            },
            "details": dict(self._details()),
            "health": self.health(),
        }

    def health(self) -> dict[str, Any]:
        """Each motor's health and the bus statistics, as last read (no I/O), with warnings.

        Drivers that read their motors' health do it at a low rate inside their cycle's
        transactions (see :meth:`_health`); this only reports. The limits
        ``temperature_warn_c`` and ``voltage_range`` (when the kind has them) turn readings into
        ``warnings``; each warning is logged once when it appears and once when it clears.

        Returns:
            ``motors``: one mapping per motor with the keys of :data:`HEALTH_FIELDS`
            (``None``: not reported by this kind); ``bus``: ``transactions``, ``timeouts``,
            ``crc_errors``, ``retries`` (``None``: no bus); ``warnings``: lines naming the
            motor, the reading and the limit. A motor's ``voltage_range_v``, if the driver
            gives one, is the range its supply is checked against (else ``voltage_range``).
        """
        motors_raw, bus = self._health()
        motors: list[dict[str, Any]] = []
        for raw in motors_raw:
            entry: dict[str, Any] = dict.fromkeys(HEALTH_FIELDS)
            entry["errors"] = []
            entry.update(raw)
            motors.append(entry)
        warnings = self._health_limits(motors, bus)
        return {"motors": motors, "bus": bus, "warnings": warnings}

    def _miss_rate(self, bus: Mapping[str, Any] | None) -> str | None:
        """The miss-rate warning (``None``: none), from ``bus``'s ``transactions`` and
        ``timeouts`` over the last window of at least :data:`MISS_RATE_WINDOW` transactions,
        against ``miss_rate_warn`` (kinds without that parameter never warn)."""
        limit = self.params.get("miss_rate_warn")
        if not limit or not bus:
            return None
        done, missed = bus.get("transactions"), bus.get("timeouts")
        if not isinstance(done, int) or not isinstance(missed, int):
            return None
        start = self._miss_window or (0, 0)
        if done < start[0] or missed < start[1]:  # counters reset
            self._miss_window = (done, missed)
            return self._miss_warning
        count, lost = done - start[0], missed - start[1]
        if count < MISS_RATE_WINDOW:
            return self._miss_warning  # the window is still open: the last verdict stands
        self._miss_window = (done, missed)
        rate = lost / count
        self._miss_warning = None if rate <= limit else (
            f"{self._owner()}: {rate * 100:.2g} % of replies missed ({lost} of {count} "
            f"transactions), above miss_rate_warn "
            f"{limit * 100:g} %: replies come later than the bus's receive timeout allows; "
            "check the bus load and wiring (or, with emulated motors, the load of their host)")
        return self._miss_warning

    def _health_limits(
        self, motors: Sequence[Mapping[str, Any]], bus: Mapping[str, Any] | None = None
    ) -> list[str]:
        """The warnings of ``motors`` and ``bus`` against the kind's limits; logs the
        changes."""
        current: dict[tuple[str, str], str] = {}
        if (missing := self._miss_rate(bus)) is not None:
            current[("bus", "miss_rate")] = missing
        hot = self.params.get("temperature_warn_c")
        for m in motors:
            label = f"{self._owner()}: motor {m['motor']} (joint {m['joint']!r})"
            temp, voltage = m["temperature_c"], m["voltage_v"]
            # A driver may give each motor its own range (e.g. from its model's supply).
            volts = m.get("voltage_range_v") or self.params.get("voltage_range")
            if hot is not None and temp is not None and temp >= hot:
                current[(str(m["motor"]), "temperature")] = (
                    f"{label}: temperature {temp:g} degC at or above temperature_warn_c "
                    f"{hot:g} degC")
            if volts is not None and voltage is not None and not (
                    volts[0] <= voltage <= volts[1]):
                current[(str(m["motor"]), "voltage")] = (
                    f"{label}: supply {voltage:g} V outside voltage_range "
                    f"[{volts[0]:g}, {volts[1]:g}] V")
            for error in m["errors"]:
                current[(str(m["motor"]), f"error:{error}")] = f"{label}: {error}"
        # Logged on a crossing only: status() runs at a low rate, but a hot motor stays hot.
        for key, text in current.items():
            if key not in self._health_warnings:
                _log.warning("%s", text)
        for key, text in self._health_warnings.items():
            if key not in current:
                _log.info("cleared: %s", text)
        self._health_warnings = current
        return list(current.values())

    def device_watchdog(self) -> DeviceWatchdog:
        """What stops this component's motors if the daemon cannot command them.

        Drivers whose devices have a watchdog arm it on activate, disarm it on a clean
        deactivate, and describe it here (no I/O: ``jtc-hw check`` calls it on an unconfigured
        component). Default: :data:`NO_DEVICE_WATCHDOG`.
        """
        return NO_DEVICE_WATCHDOG

    def devices(self) -> tuple[DeviceName, ...]:
        """The devices this component drives: the daemon takes an exclusive lock on each
        before ``configure`` so that a second daemon never touches them.

        One :class:`DeviceName` per device, its ``key`` the same for every configuration that
        reaches it however it is spelt: a serial port by its real path (``os.path.realpath``:
        ``/dev/serial/by-id/...`` and ``/dev/ttyUSB0`` are one port); a network peer by its
        resolved address and port number; a SocketCAN interface by its kernel index. Where a
        wire is shared by design (CAN: one bus, many motor ids), one name per thing that must
        be unique on it (each motor id, a bus-wide role such as the CANopen master), so that
        daemons driving different motors of one bus may run side by side. May resolve names
        (``realpath``, ``getaddrinfo``, ``if_nametoindex``) but never touches the device
        itself. Default: none (simulated).

        Raises:
            HardwareError: a name cannot be resolved (a host that does not resolve, a network
                interface that does not exist); the message names it.
        """
        return ()

    def scalar_state(self, name: str) -> float:
        """The scalar state interface ``name`` (one of :attr:`SCALAR_STATE_INTERFACES`) as the
        last ``read`` left it; no I/O. ``NaN``: not known (nothing read yet, or the device did
        not report it in that read)."""
        return float(self._scalar_state(name))

    def set_scalar_command(self, name: str, value: float) -> None:
        """Set the scalar command interface ``name`` (one of
        :attr:`SCALAR_COMMAND_INTERFACES`) to ``value``; no I/O: the next ``write`` sends it,
        in the cycle's one bus transaction where the device allows."""
        self._set_scalar_command(name, float(value))

    def nan_command(self) -> JointCommand:
        """A command holding ``NaN`` for every configured interface (``None`` for the others)."""
        return JointCommand(*(np.full(self._shape, np.nan) if iface in self.command_interfaces
                              else None for iface in COMMAND_INTERFACE_TYPES))

    # -- primitives ---------------------------------------------------------------------------

    def _configure(self) -> None:  # noqa: B027 - optional primitive, no-op by default
        """Open and check the device. Default: nothing to do."""

    def _activate(self, now_ns: int) -> JointCommand:
        """Enable the drives; return the held command values. Default: ``nan_command()``."""
        return self.nan_command()

    @abstractmethod
    def _read(self, now_ns: int) -> JointState:
        """Return the state of ``self.joints`` (one bus transaction)."""

    @abstractmethod
    def _write(self, now_ns: int, command: JointCommand) -> None:
        """Write the non-NaN entries of ``command`` (one bus transaction)."""

    def _deactivate(self, now_ns: int, action: SafeAction) -> None:  # noqa: B027
        """Perform ``action`` (hold the position, or torque off). Default: nothing to do."""

    def _monitor(self, now_ns: int) -> JointState | None:
        """While INACTIVE: read health (and state) without commanding anything (see
        :meth:`monitor`). Default: no I/O, ``None``."""
        return None

    def _recover(self) -> None:  # noqa: B027 - optional primitive, no-op by default
        """Clear latched device faults (reboot, fault reset). Default: nothing to do."""

    def _cleanup(self) -> None:  # noqa: B027 - optional primitive, no-op by default
        """Release the device. Default: nothing to do."""

    def _scalar_state(self, name: str) -> float:
        """A scalar state interface's value as of the last read (no I/O). Default: ``NaN``
        (the kind declares none)."""
        return float("nan")

    def _set_scalar_command(self, name: str, value: float) -> None:  # noqa: B027
        """Keep a scalar command interface's value for the next ``_write``. Default: nothing
        (the kind declares none)."""

    def _details(self) -> Mapping[str, Any]:
        """Driver-specific JSON-able status entries (bus statistics, temperatures, ...)."""
        return {}

    def _health(self) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
        """The motors' health as last read (no I/O) and the bus statistics.

        Default: one motor per joint with nothing known, no bus. Drivers override it with
        what their motors report (any keys of :data:`HEALTH_FIELDS`; ``errors`` a list of
        lines) and their bus counters (``transactions``, ``timeouts``, ``crc_errors``,
        ``retries``).
        """
        return [{"motor": joint, "joint": joint} for joint in self.joints], None

    # -- helpers ------------------------------------------------------------------------------

    def _owner(self) -> str:
        return f"{self.kind} hardware {self.name!r}"

    def _guard(self, method: str) -> None:
        if self._state not in _ALLOWED[method]:
            raise _lifecycle_error(self._owner(), method, self._state)

    def _call(self, method: str, function: Callable[..., Any], *args: Any) -> Any:
        """``function(*args)``; its error, a foreign one wrapped in a :class:`HardwareError`
        naming the component, is the last fault."""
        try:
            return function(*args)
        except JtcHwError as exc:
            self._last_fault = str(exc)
            raise
        except Exception as exc:
            error = HardwareError(
                f"{self._owner()}: {method} failed: {type(exc).__name__}: {one_line(exc)}"
            )
            self._last_fault = str(error)
            raise error from exc

    def _held_command(self, held: Any) -> JointCommand:
        if not isinstance(held, JointCommand):
            raise HardwareError(
                f"{self._owner()}: activate() must return a JointCommand, got "
                f"{type(held).__name__}; this is a driver bug"
            )
        fields: list[F64 | None] = []
        for iface, values in zip(
            COMMAND_INTERFACE_TYPES,
            (held.positions, held.velocities, held.accelerations, held.effort),
            strict=True,
        ):
            if iface not in self.command_interfaces:
                fields.append(None)
            elif values is None:
                fields.append(np.full(self._shape, np.nan))
            elif values.shape != self._shape:
                raise HardwareError(
                    f"{self._owner()}: activate() returned {values.size} {iface} values for "
                    f"{len(self.joints)} joints; this is a driver bug"
                )
            else:
                fields.append(values)
        return JointCommand(*fields)


def _raise_first(errors: Sequence[BaseException]) -> None:
    """Raise the first error, the others attached as notes."""
    if not errors:
        return
    first = errors[0]
    for other in errors[1:]:
        add_note(first, f"also: {type(other).__name__}: {other}")
    raise first
