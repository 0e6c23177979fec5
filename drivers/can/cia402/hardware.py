"""CiA 402 servo drives on CANopen (kind ``can-cia402``): cyclic synchronous position / velocity.

Theory of operation
-------------------
Configuration (``configure``: :mod:`~jtc_hw.drivers.can.cia402.sdo`) sets every drive up
with ``canopen``'s SDO client while a python-can ``Notifier`` thread feeds it: NMT reset and
boot-up, device type, PDO mapping, mode of operation, 0x6007, a 0x1016 consumer entry, start.
The Notifier is then stopped: in cyclic operation the driver owns the bus receive (``bus.py``'s
non-blocking drain), so the control-loop process has no second Python thread competing for
the interpreter lock.

The cycle (layouts and state machine from :mod:`~jtc_hw.drivers.can.cia402.codec`):

* ``write``: late frames (answers to the previous SYNC that came after its read) are taken
  and counted, then per bus every drive's RPDO1 (controlword, target), one SYNC and, every
  ``watchdog_s / 4``, the daemon's heartbeat; buses are independent wires, so they all
  transmit at once (their frames interleaved).
* ``read``: if no SYNC is outstanding (the first read, reads while inactive) one is sent; then
  per bus the TPDOs answering it are collected, bounded by the bus's ``receive_timeout``;
  the newest frame per TPDO is kept. A drive with no answer for ``feedback_timeout_s`` is a
  :class:`~jtc_hw.errors.CommunicationError`; while active, a drive in Fault (error code from
  its TPDO), out of Operation Enabled or in the wrong mode is a :class:`~jtc_hw.errors.MotorFault`.
  Each names the node id, joint and bus.

Feedback is therefore sampled at the previous cycle's SYNC (CiA 402's usual one-cycle
latency). ``activate`` walks each drive through the state machine with checked transitions
(Switch On Disabled -> Ready to Switch On -> Switched On -> Operation Enabled), seeding the
target position from the measured one right before Enable Operation, so nothing jumps.
``recover`` (the explicit re-arm) sends a fault reset (controlword bit 7 rising edge) to every
faulted drive and checks that it left Fault. Safe actions: ``hold`` leaves the drives in
Operation Enabled holding the last target (CSV: target velocity 0); ``torque_off`` sends
Disable Voltage and checks Switch On Disabled.

Heartbeat watchdog: ``activate`` first arms every drive's consumer entry (the daemon's
``master_node_id``, ``watchdog_s`` in ms; SDO, with a Notifier for that moment only), so
that whatever it enables stops by itself unless the daemon goes on commanding it: the cycle
produces the heartbeat, a failed activation stops producing it. After the walk to Operation
Enabled one more exchange must show every drive enabled, powered (statusword bit 4), in its
mode and without a heartbeat event, else activation fails with one line naming the drive:
the daemon never reports holding what is not. ``deactivate`` performs the safe action, then
disarms (entry time 0, a heartbeat before each SDO request), so a clean stop does not trip
the drives; if the safe action fails it leaves them armed and stops feeding them. An EMCY
0x8130 from a drive (it lost the heartbeat: a stalled loop) is a fault naming it while active,
even before its statusword shows the stop.

Units (per joint; formula symmetric for commands)::

    joint = direction * (2*pi * counts / counts_per_revolution) / gear_ratio + offset

velocities the same with counts/s (``velocity_unit: counts_per_second``) or motor rpm.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from itertools import zip_longest
from pathlib import Path
from typing import Any, ClassVar

import can
import canopen
import numpy as np
from canopen.network import MessageListener
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from jtc_hw.errors import CommunicationError, ConfigurationError, HardwareError, MotorFault
from jtc_hw.hardware import (
    JOINT_MAPPING_PARAMS,
    WATCHDOG_PARAM,
    DeviceName,
    DeviceWatchdog,
    HardwareInterface,
    JointCommand,
    JointState,
    LifecycleState,
    ParamKind,
    ParamSpec,
    SafeAction,
    one_line,
    param_table,
)

from .. import bus as canbus
from . import codec as c4
from .drives import Drive, DriveBus
from .sdo import DriveSetup

__all__ = ["Cia402Hardware"]

# A logger name is public (log filters name it): the one from before drivers/can/ was split.
_log = logging.getLogger("jtc_hw.drivers.can.cia402")

_SDO_NOTIFIER_CYCLE_S = 0.005  # SDO sessions of activate / deactivate: stop them sooner
_FAULTY = (c4.State.FAULT, c4.State.FAULT_REACTION_ACTIVE)
# Health: the error register 0x1001 is no PDO object; in cyclic operation one expedited SDO
# upload request (client -> server 0x600 + node, answer on 0x580 + node: ``Drive.sdo_tx``,
# ``Drive.sdo_rx``) goes out after a cycle's SYNC at a low rate, and the answer is taken with
# the TPDOs (the driver owns the bus receive then: canopen's SDO client, which blocks, is not
# used).
_SDO_UPLOAD = 0x40  # ccs 2: initiate upload; scs 2 answers (0x4F for one expedited byte)
_SDO_ABORT = 0x80
_HEARTBEATS_PER_WATCHDOG = 4
"""The master's heartbeat goes out every watchdog_s / 4 (see ``Cia402Hardware``)."""
_REACTIONS = {
    "quick_stop": c4.AbortConnection.QUICK_STOP,
    "fault": c4.AbortConnection.FAULT,
    "disable_voltage": c4.AbortConnection.DISABLE_VOLTAGE,
}
_REACTION_TEXT = {
    c4.AbortConnection.QUICK_STOP: "quick stop (0x605A, decelerating with 0x6085)",
    c4.AbortConnection.FAULT: "fault reaction (0x605E), then Fault",
    c4.AbortConnection.DISABLE_VOLTAGE: "Disable Voltage (power stage off at once: it coasts)",
}


def _watchdog_ms(watchdog_s: float) -> int:
    """``watchdog_s`` as the consumer heartbeat time of 0x1016 (whole ms, 16 bits).

    Raises:
        ConfigurationError: not a whole number of milliseconds, or above 65.535 s.
    """
    ms = round(watchdog_s * 1000.0)
    if abs(ms - watchdog_s * 1000.0) > 1e-6:
        raise ConfigurationError(
            f"{watchdog_s:g} s is not a whole number of milliseconds, and the drives count "
            f"their consumer heartbeat time (0x1016) in ms; use {max(ms, 1) / 1000:g}",
            "params.watchdog_s", watchdog_s,
        )
    if ms > 0xFFFF:
        raise ConfigurationError(
            f"{watchdog_s:g} s is longer than the 65.535 s a drive's consumer heartbeat time "
            "(0x1016, 16 bits of ms) can hold",
            "params.watchdog_s", watchdog_s,
        )
    return ms


class Cia402Hardware(HardwareInterface):
    """CiA 402 drives over CANopen in cyclic synchronous position or velocity mode.

    The mode follows the command interface: ``position`` -> CSP (8), ``velocity`` -> CSV (9).
    See the module docstring for the cycle, the state machine handling and the heartbeat
    watchdog.

    The master's heartbeat goes out every ``watchdog_s / 4``: a drive then trips between
    ``3/4 * watchdog_s`` (minus a cycle) and ``watchdog_s`` after the daemon's last cycle, so
    a loop that is late by up to half the watchdog time never trips it, and the heartbeat
    costs one 1-byte frame per quarter watchdog time (at 0.1 s and 1 Mbit/s, 0.2 % of the
    bus), not one per cycle. A shorter producer time would tolerate longer stalls for more
    bus load; ``watchdog_s`` of at least 3 loop periods (checked by the robot file) keeps a
    heartbeat in at least every third cycle.

    Raises:
        ConfigurationError: invalid parameters, duplicate node ids on a bus, a
            ``master_node_id`` that a drive on some bus uses, a ``watchdog_s`` that is not a
            whole number of milliseconds (or above 65.535 s), or both ``position`` and
            ``velocity`` command interfaces.
    """

    kind: ClassVar[str] = "can-cia402"
    COMMAND_INTERFACES: ClassVar[tuple[str, ...]] = ("position", "velocity")
    STATE_INTERFACES: ClassVar[tuple[str, ...]] = ("position", "velocity")

    PARAMS: ClassVar[Mapping[str, ParamSpec]] = param_table(
        canbus.buses_param(),
        canbus.joint_bus_param(),
        ParamSpec("node_id", ParamKind.INT, None, "per joint: CANopen node id of its drive",
                  minimum=1, maximum=127, per_joint=True, required=True),
        ParamSpec("counts_per_revolution", ParamKind.INT, 131072,
                  "per joint: position counts per motor revolution (the position factor)",
                  minimum=1, per_joint=True),
        *JOINT_MAPPING_PARAMS,
        ParamSpec("position_limits", ParamKind.RANGE, (-math.inf, math.inf),
                  "per joint [min, max] position commands are clamped to, rad (null: none)",
                  per_joint=True, nullable=True),
        ParamSpec("velocity_limit", ParamKind.FLOAT, 0.0,
                  "per joint: velocity commands are clamped to +-this, rad/s (0: none)",
                  minimum=0.0, per_joint=True),
        ParamSpec("velocity_unit", ParamKind.STRING, "counts_per_second",
                  "unit of 0x606C / 0x60FF: counts_per_second or rpm (motor)",
                  choices=("counts_per_second", "rpm")),
        ParamSpec("feedback_timeout_s", ParamKind.FLOAT, 0.05,
                  "s without a TPDO from a drive before it is a communication fault",
                  minimum=0.001, maximum=10.0),
        ParamSpec("boot_timeout_s", ParamKind.FLOAT, 2.0,
                  "s to wait for a drive's boot-up after NMT reset communication",
                  minimum=0.01, maximum=60.0),
        ParamSpec("transition_timeout_s", ParamKind.FLOAT, 0.5,
                  "s a drive may take for one state-machine transition or fault reset",
                  minimum=0.001, maximum=10.0),
        ParamSpec("eds", ParamKind.STRING, "",
                  "EDS file of the drives (empty: the shipped jtc_hw_drive.eds)"),
        WATCHDOG_PARAM,
        ParamSpec("master_node_id", ParamKind.INT, 127,
                  "node id of the daemon's heartbeat (COB-ID 0x700 + id), which each drive's "
                  "consumer (0x1016) watches; no drive on a bus may use it",
                  minimum=1, maximum=127),
        ParamSpec("watchdog_reaction", ParamKind.STRING, "quick_stop",
                  "what a drive does when the daemon's heartbeat stops (0x6007): quick_stop "
                  "(0x605A / 0x6085), fault (0x605E, then Fault) or disable_voltage (coast)",
                  choices=tuple(_REACTIONS)),
        ParamSpec("health_period_s", ParamKind.FLOAT, 1.0,
                  "how often each drive's error register (0x1001) is read by SDO, s (one "
                  "request frame after a cycle's SYNC, one drive at a time)",
                  minimum=0.01, maximum=60.0),
    )

    def __init__(
        self,
        name: str,
        joints: Sequence[str],
        command_interfaces: Sequence[str],
        state_interfaces: Sequence[str],
        params: Mapping[str, Any],
    ) -> None:
        super().__init__(name, joints, command_interfaces, state_interfaces, params)
        p = self.params
        if len(self.command_interfaces) != 1:
            raise ConfigurationError(
                f"{self._owner()}: CiA 402 cyclic synchronous modes take one command "
                f"interface, position (CSP) or velocity (CSV); got "
                f"[{', '.join(self.command_interfaces)}]",
                "command_interfaces", list(self.command_interfaces),
            )
        self.mode = (
            c4.Mode.CYCLIC_SYNC_POSITION if self.command_interfaces[0] == "position"
            else c4.Mode.CYCLIC_SYNC_VELOCITY
        )
        self._csp = self.mode is c4.Mode.CYCLIC_SYNC_POSITION
        self._rpdo_layout = c4.RPDO_CSP if self._csp else c4.RPDO_CSV
        buses: Mapping[str, canbus.BusSettings] = p["buses"]
        bus_of = canbus.joint_buses(self.joints, p["bus"], buses)
        eds = str(p["eds"] or c4.DEFAULT_EDS)
        if p["eds"] and not Path(p["eds"]).is_file():
            raise ConfigurationError(f"no such EDS file {p['eds']!r}", "params.eds", p["eds"])
        drives: list[Drive] = []
        for i, joint in enumerate(self.joints):
            direction = p["direction"][i]
            low, high = p["position_limits"][i]
            vmax = p["velocity_limit"][i]
            drives.append(Drive(
                joint=joint, index=i, node_id=p["node_id"][i], bus=bus_of[i],
                scale=c4.JointScale(p["counts_per_revolution"][i], p["gear_ratio"][i],
                                    direction, p["offset"][i], p["velocity_unit"]),
                lower=low, upper=high, vmax=vmax if vmax > 0.0 else math.inf,
            ))
        self._drives = drives
        self._buses: dict[str, DriveBus] = {}
        for name_, settings in buses.items():
            on = [d for d in drives if d.bus == name_]
            seen: dict[int, str] = {}
            for d in on:
                if d.node_id in seen:
                    raise ConfigurationError(
                        f"joints {seen[d.node_id]!r} and {d.joint!r} both use node id "
                        f"{d.node_id} on bus {name_!r}; node ids must be unique per bus",
                        f"params.node_id.{d.joint}", d.node_id,
                    )
                seen[d.node_id] = d.joint
            if on:
                self._buses[name_] = b = DriveBus(settings, on, canbus.BusHealth(settings))
                b.on_frame = functools.partial(self._take_one, b)
        self._feedback_timeout_s: float = p["feedback_timeout_s"]
        self._transition_timeout_s: float = p["transition_timeout_s"]
        self._last_fault_by_node: dict[int, str] = {}
        self._watchdog_ms = _watchdog_ms(p["watchdog_s"])
        self._heartbeat_period_s = self._watchdog_ms / 1000.0 / _HEARTBEATS_PER_WATCHDOG
        self._master_id: int = p["master_node_id"]
        for d in drives:
            if d.node_id == self._master_id:
                raise ConfigurationError(
                    f"master_node_id {self._master_id} is also the node id of joint "
                    f"{d.joint!r} on bus {d.bus!r}: its drive's heartbeats and the daemon's "
                    f"would share COB-ID 0x{c4.bootup_cob_id(self._master_id):03X}; choose an "
                    "id no drive uses",
                    "params.master_node_id", self._master_id,
                )
        self._reaction = _REACTIONS[p["watchdog_reaction"]]
        self._sdo = DriveSetup(self._owner(), eds, self.mode, self._rpdo_layout, self._reaction,
                               self._master_id, p["boot_timeout_s"])
        self._armed = False  # the drives' consumers watch our heartbeat (0x1016 written)
        self._feeding = False  # we produce it (active, or activating / deactivating)
        self._disarm_failures: list[str] = []
        self._health_slot_s: float = p["health_period_s"] / max(1, len(drives))
        self._next_health = 0.0
        self._health_turn = 0
        self._sdo_aborts = 0

    # -- lifecycle primitives ---------------------------------------------------------------------

    def _configure(self) -> None:
        try:
            for b in self._buses.values():
                b.health = canbus.BusHealth(b.settings)
                b.bus = canbus.open_settings(b.settings)  # socketcand: tcp_tune on
                b.opened_at = time.monotonic()
                b.sync_outstanding = False
                self._sdo.configure_bus(b)
        except BaseException:
            self._cleanup()
            raise
        for d in self._drives:
            d.statusword = d.state = None
            d.rx1_at = d.rx2_at = 0.0
            d.fresh = False
            d.last_emcy = None
            d.heartbeat_lost = False

    def _activate(self, now_ns: int) -> JointCommand:
        for b in self._buses.values():
            self._flush(b)
        for d in self._drives:
            d.heartbeat_lost = False
        # Armed first: whatever this activation leaves enabled stops by itself if the daemon
        # does not go on commanding it (a failed activation stops feeding the heartbeat).
        self._arm()
        try:
            self._exchange(send_rpdo=False)  # with the first heartbeat: monitoring starts
            for d in self._drives:
                if d.state in _FAULTY:
                    raise self._fault(
                        d, "cannot enable a drive in fault; re-arm to fault-reset it")
                d.target = d.position_counts if self._csp else 0
                if d.state is c4.State.OPERATION_ENABLED:
                    d.controlword = c4.encode_controlword(c4.Command.ENABLE_OPERATION)
            self._walk_to_enabled()
            self._confirm_enabled()
        except BaseException:
            self._feeding = False
            raise
        held = np.array(
            [d.scale.position(d.target) for d in self._drives] if self._csp
            else [0.0] * len(self._drives), dtype=np.float64,
        )
        return JointCommand(held, None) if self._csp else JointCommand(None, held)

    def _walk_to_enabled(self) -> None:
        """Step every drive to Operation Enabled, checking each transition."""
        step_started = {d.node_id: time.monotonic() for d in self._drives}
        expected: dict[int, tuple[c4.State, c4.Command, c4.State]] = {}
        while True:
            pending = [d for d in self._drives if d.state is not c4.State.OPERATION_ENABLED]
            if not pending:
                return
            for d in pending:
                assert d.state is not None
                if d.state in _FAULTY:
                    raise self._fault(d, "went to fault while being enabled")
                command = c4.PATH_TO_OPERATION_ENABLED.get(d.state)
                if command is None:
                    # Not Ready to Switch On: the drive leaves it by itself.
                    expected.pop(d.node_id, None)
                    continue
                if command is c4.Command.ENABLE_OPERATION and self._csp:
                    d.target = d.position_counts  # seed: enabling must not jump
                d.controlword = c4.encode_controlword(command)
                previous = expected.get(d.node_id)
                if previous is None or previous[0] is not d.state:
                    step_started[d.node_id] = time.monotonic()
                expected[d.node_id] = (d.state, command, c4.expected_after(d.state, command))
            self._exchange(send_rpdo=True)
            now = time.monotonic()
            for d in pending:
                step = expected.get(d.node_id)
                if step is None:
                    if now - step_started[d.node_id] > self._transition_timeout_s:
                        raise HardwareError(
                            f"{self._owner()}: {d.who()} stayed {d.describe_state()} for "
                            f"{self._transition_timeout_s:g} s; check its power stage supply"
                        )
                    continue
                before, command, want = step
                if d.state is want or d.state is before and (
                    now - step_started[d.node_id] <= self._transition_timeout_s
                ):
                    continue
                if d.state in _FAULTY:
                    raise self._fault(d, f"went to fault on {command.value}")
                raise HardwareError(
                    f"{self._owner()}: {d.who()}: transition failed: {command.value} "
                    f"(controlword 0x{c4.encode_controlword(command):04X}) from "
                    f"{before.value} should lead to {want.value}, but the drive reports "
                    f"{d.describe_state()} after {now - step_started[d.node_id]:.3f} s; "
                    "check enable inputs (STO), DC link voltage and the drive's own errors"
                )

    def _confirm_enabled(self) -> None:
        """One more exchange (with a heartbeat) after enabling: every drive must answer it in
        Operation Enabled, powered (statusword bit 4, voltage enabled), in the configured mode
        and without a heartbeat event: what the daemon reports as holding is true.

        Raises:
            CommunicationError: a drive did not answer.
            MotorFault: a drive is in fault or lost the heartbeat.
            HardwareError: a drive left Operation Enabled, has no power or changed mode.
        """
        self._exchange(send_rpdo=True)
        for d in self._drives:
            if d.heartbeat_lost:
                raise self._heartbeat_fault(d)
            if d.state in _FAULTY:
                raise self._fault(d, "went to fault right after it was enabled")
            problem = ""
            if d.state is not c4.State.OPERATION_ENABLED:
                problem = (f"is {d.describe_state()} right after it was enabled, not operation "
                           "enabled; check its enable inputs (STO) and the drive's own errors")
            elif d.statusword is not None and not d.statusword & c4.SW_VOLTAGE_ENABLED:
                problem = (f"reports operation enabled without voltage enabled (statusword "
                           f"0x{d.statusword:04X}, bit 4): check its power stage supply")
            elif d.mode_display != int(self.mode):
                problem = (f"displays mode {d.mode_display} in 0x6061 right after it was "
                           f"enabled, not {int(self.mode)} ({self.mode.name})")
            if problem:
                message = f"{self._owner()}: activation not confirmed: {d.who()} {problem}"
                self._last_fault_by_node[d.node_id] = message
                raise HardwareError(message)

    def _deactivate(self, now_ns: int, action: SafeAction) -> None:
        try:
            self._safe_action(action)
        except BaseException:
            # The safe action may not have happened: the watchdog stays armed, and with no
            # more heartbeats the drives stop by themselves.
            self._feeding = False
            raise
        self._disarm()

    def _safe_action(self, action: SafeAction) -> None:
        if action is SafeAction.HOLD:
            if self._csp:
                for b in self._buses.values():
                    self._flush(b)
                return  # the drives hold the last target in Operation Enabled
            for d in self._drives:
                d.target = 0
            self._exchange(send_rpdo=True, strict=False)
            return
        for d in self._drives:
            d.controlword = c4.encode_controlword(c4.Command.DISABLE_VOLTAGE)
        deadline = time.monotonic() + self._transition_timeout_s
        while True:
            self._exchange(send_rpdo=True, strict=False)
            left = [
                d for d in self._drives
                if d.state is not c4.State.SWITCH_ON_DISABLED and d.state not in _FAULTY
            ]
            if not left:
                break
            if time.monotonic() > deadline:
                d = left[0]
                raise CommunicationError(
                    f"{self._owner()}: torque off failed: {d.who()} is "
                    f"{d.describe_state()} after Disable Voltage; it may still hold torque: "
                    "check it and its wiring"
                )
        for b in self._buses.values():
            self._flush(b)

    # -- the heartbeat watchdog --------------------------------------------------------------------

    @contextmanager
    def _sdo_session(self, b: DriveBus) -> Iterator[dict[int, canopen.RemoteNode]]:
        """canopen's SDO clients of ``b``'s drives, fed by a Notifier thread for the session
        only (in cyclic operation the driver receives frames itself, with no second thread)."""
        bus, network = self._bus_of(b), b.network
        if network is None:
            raise CommunicationError(f"{self._owner()}: {b.settings.describe()} is not set up")
        for node in b.nodes.values():
            network.subscribe(node.sdo.tx_cobid, node.sdo.on_response)
        notifier = can.Notifier(bus, [MessageListener(network)], timeout=_SDO_NOTIFIER_CYCLE_S)
        try:
            yield b.nodes
        finally:
            notifier.stop(timeout=2.0)
            network.subscribers.clear()
            self._flush(b)  # answers to nothing of ours from the session: not cycle feedback

    def _send_heartbeat(self, b: DriveBus) -> None:
        self._send(b, can.Message(arbitration_id=c4.bootup_cob_id(self._master_id),
                                  is_extended_id=False,
                                  data=c4.encode_heartbeat(c4.NmtState.OPERATIONAL)))
        b.next_beat = time.monotonic() + self._heartbeat_period_s
        b.beats += 1

    def _arm(self) -> None:
        """Every drive's consumer entry: the daemon's node id, ``watchdog_s``. Monitoring
        starts with the next heartbeat, which the next exchange sends.

        Raises:
            HardwareError: a drive refused the entry or did not answer.
        """
        for b in self._buses.values():
            with self._sdo_session(b) as nodes:
                for d in b.drives:
                    try:
                        self._sdo.write_consumer(d, nodes[d.node_id], self._watchdog_ms)
                    except (SdoAbortedError, SdoCommunicationError) as exc:
                        raise self._sdo.sdo_error(
                            d, f"arming its heartbeat consumer 0x1016:{d.consumer_sub}", exc
                        ) from exc
        self._armed = self._feeding = True
        for b in self._buses.values():
            b.next_beat = 0.0  # due at once

    def _disarm(self) -> None:
        """Every drive's consumer entry back to time 0, a heartbeat before each SDO request so
        that the drives not yet disarmed keep theirs. A drive that stopped answering, or does
        not confirm, stays armed and stops by itself: logged, not raised (it is the safe side)."""
        if not self._armed:
            self._feeding = False
            return
        failures: list[str] = []
        now = time.monotonic()
        for b in self._buses.values():
            if b.bus is None or b.health.state == "bus-off":
                failures.extend(f"{d.who()} is on a bus that is off" for d in b.drives)
                continue
            done: set[int] = set()
            try:
                with self._sdo_session(b) as nodes:
                    for d in b.drives:
                        if d.rx1_at == 0.0 or now - d.rx1_at > self._feedback_timeout_s:
                            failures.append(f"{d.who()} is not answering")
                        else:
                            self._send_heartbeat(b)
                            try:
                                self._sdo.write_consumer(d, nodes[d.node_id], 0)
                            except (SdoAbortedError, SdoCommunicationError) as exc:
                                failures.append(f"{d.who()} did not confirm "
                                                f"({one_line(exc)})")
                        done.add(d.node_id)
            except (HardwareError, can.CanError, OSError) as exc:
                failures.extend(f"{d.who()}: {b.settings.describe()} failed "
                                f"({one_line(exc)})"
                                for d in b.drives if d.node_id not in done)
        self._armed = self._feeding = False
        self._disarm_failures = failures
        for failure in failures:
            _log.warning(
                "%s: disarming the heartbeat watchdog failed: %s; it stops by itself within "
                "%d ms (0x6007: %s)", self._owner(), failure, self._watchdog_ms,
                _REACTION_TEXT[self._reaction],
            )

    def device_watchdog(self) -> DeviceWatchdog:
        """Each drive's heartbeat consumer (see the class docstring); no I/O."""
        return DeviceWatchdog(
            self._watchdog_ms / 1000.0,
            f"CiA 402 heartbeat consumer 0x1016 on every drive, {self._watchdog_ms} ms, fed "
            f"by the daemon (node {self._master_id}, every "
            f"{self._heartbeat_period_s * 1e3:g} ms): on loss each drive sends EMCY 0x8130 "
            f"and applies 0x6007 = {int(self._reaction)}, {_REACTION_TEXT[self._reaction]}",
        )

    def devices(self) -> tuple[DeviceName, ...]:
        """Per bus, the CANopen master role, then one lock per drive's node id
        (``BusSettings.device_names``).

        The master role is exclusive on a bus (CiA 301): this driver is the NMT master (it
        resets and starts nodes), the SYNC producer (COB-ID 0x80; a second producer would
        double the rate every synchronous PDO follows) and the heartbeat producer the drives'
        consumers watch (``master_node_id``: another daemon's heartbeat would keep a dead
        daemon's drives enabled). So two CiA 402 daemons never share a bus; the node ids
        also keep a daemon of another kind off these drives' ids.

        Raises:
            CommunicationError: a bus cannot be named (unknown interface, unresolved host).
        """
        return tuple(dict.fromkeys(
            name
            for b in self._buses.values()
            for name in b.settings.device_names({
                "canopen-master": "CANopen master (NMT, SYNC, heartbeat)",
                **{f"canopen-node:{d.node_id}": f"drive node {d.node_id}" for d in b.drives},
            })
        ))

    def _recover(self) -> None:
        for d in self._drives:
            d.heartbeat_lost = False
        self._exchange(send_rpdo=False)
        faulted = [d for d in self._drives if d.state in _FAULTY]
        if not faulted:
            return
        for d in faulted:
            d.controlword = c4.encode_controlword(c4.Command.DISABLE_VOLTAGE)
        self._exchange(send_rpdo=True)  # bit 7 low first: the reset acts on its rising edge
        for d in faulted:
            d.controlword = c4.encode_controlword(c4.Command.FAULT_RESET)
        deadline = time.monotonic() + self._transition_timeout_s
        while True:
            self._exchange(send_rpdo=True)
            left = [d for d in faulted if d.state in _FAULTY]
            if not left or time.monotonic() > deadline:
                break
        for d in faulted:
            d.controlword = c4.encode_controlword(c4.Command.DISABLE_VOLTAGE)
        self._exchange(send_rpdo=True)
        for d in faulted:
            if d.state in _FAULTY:
                raise self._fault(
                    d, "fault reset did not clear the fault: its cause persists; check the "
                    "drive (temperature, supply, motor) before re-arming again",
                )
            self._last_fault_by_node.pop(d.node_id, None)

    def _cleanup(self) -> None:
        # Armed drives (a failed activation or safe action) stay armed: with no heartbeat they
        # stop by themselves.
        self._armed = self._feeding = False
        for b in self._buses.values():
            bus, b.bus = b.bus, None
            b.network, b.nodes = None, {}
            canbus.close_bus(bus)
            b.sync_outstanding = False

    # -- the cycle --------------------------------------------------------------------------------

    def _read(self, now_ns: int) -> JointState:
        self._send_cycle(
            [b for b in self._buses.values() if not b.sync_outstanding], send_rpdo=False
        )
        start = time.monotonic()
        for b in self._buses.values():
            # Until a drive has answered once, wait as long as during setup.
            first = any(d.rx1_at == 0.0 for d in b.drives)
            wait = b.settings.setup_timeout if first else b.settings.receive_timeout
            self._collect(b, start + wait)
            b.sync_outstanding = False
        now = time.monotonic()
        active = self.state is LifecycleState.ACTIVE
        for d in self._drives:
            self._check(d, now, active)
        n = len(self._drives)
        positions = np.empty(n)
        velocities = np.empty(n) if self._velocity_state else None
        for d in self._drives:
            positions[d.index] = d.scale.position(d.position_counts)
            if velocities is not None:
                velocities[d.index] = d.scale.velocity(d.velocity_value)
        return JointState(positions, velocities)

    def _check(self, d: Drive, now: float, active: bool) -> None:
        if active and d.heartbeat_lost:
            # First: the drive may still answer (or even show Operation Enabled again, were
            # its quick stop left by our next Enable Operation), but it did stop by itself.
            raise self._heartbeat_fault(d)
        age = now - d.rx1_at if d.rx1_at else math.inf
        if age > self._feedback_timeout_s:
            raise self._comm_lost(d, age)
        if not active:
            return
        if d.state in _FAULTY:
            raise self._fault(d, "reported a fault")
        if d.state is not c4.State.OPERATION_ENABLED:
            raise self._fault(
                d, f"left Operation Enabled (now {d.describe_state()}): quick stop or "
                "an enable input went off",
            )
        if d.mode_display != int(self.mode):
            raise self._fault(
                d, f"changed its mode of operation: 0x6061 displays {d.mode_display}, "
                f"expected {int(self.mode)} ({self.mode.name})",
            )

    def _write(self, now_ns: int, command: JointCommand) -> None:
        values = command.positions if self._csp else command.velocities
        if values is not None:
            for d in self._drives:
                v = float(values[d.index])
                if not math.isfinite(v):
                    continue  # NaN: the drive keeps its target
                if self._csp:
                    d.target = d.scale.position_counts(min(max(v, d.lower), d.upper))
                else:
                    d.target = d.scale.velocity_value(max(-d.vmax, min(d.vmax, v)))
        for b in self._buses.values():
            self._drain_late(b)
            b.sync_outstanding = True
        self._send_cycle(list(self._buses.values()), send_rpdo=True)
        self._request_health()

    def _request_health(self) -> None:
        """Every health slot, one expedited SDO upload request of 0x1001 to the next drive.

        After the SYNC (the set-points and the sampling instant are not delayed); the answer
        arrives with a later cycle's TPDOs. One frame, not a transaction the cycle waits for.
        """
        now = time.monotonic()
        if now < self._next_health or not self._drives:
            return
        self._next_health = now + self._health_slot_s
        d = self._drives[self._health_turn % len(self._drives)]
        self._health_turn += 1
        index = c4.ERROR_REGISTER
        self._send(self._buses[d.bus], can.Message(
            arbitration_id=d.sdo_tx, is_extended_id=False,
            data=bytes([_SDO_UPLOAD, index & 0xFF, index >> 8, 0, 0, 0, 0, 0]),
        ))

    # -- bus helpers ------------------------------------------------------------------------------

    def _bus_of(self, b: DriveBus) -> can.BusABC:
        if b.bus is None:
            raise CommunicationError(f"{self._owner()}: {b.settings.describe()} is not open")
        return b.bus

    def _bus_error(self, b: DriveBus, what: str, exc: BaseException) -> CommunicationError:
        """A failure of bus ``b`` as a whole, in one line: what failed, on which bus, the
        drives it leaves unreachable, and the library's reason cut to its first line
        (python-can's socketcand client appends a whole traceback to its errors)."""
        drives = ", ".join(f"node {d.node_id} ({d.joint!r})" for d in b.drives)
        return CommunicationError(
            f"{self._owner()}: {what} on {b.settings.describe()} failed, drives {drives} "
            f"unreachable: {one_line(exc)}; check the interface and its connection")

    def _send(self, b: DriveBus, msg: can.Message) -> bool:
        try:
            return canbus.send(self._bus_of(b), msg, b.health)
        except can.CanError as exc:
            raise self._bus_error(b, "sending", exc) from exc

    def _send_cycle(self, buses: Sequence[DriveBus], *, send_rpdo: bool) -> None:
        """Every drive's RPDO1 (optionally), one SYNC and, when due, the daemon's heartbeat,
        on each of ``buses``.

        The buses' frames are interleaved: each wire starts carrying its first frame at once
        instead of after the other buses' frames were handed over.
        """
        queues: list[list[can.Message]] = []
        now = time.monotonic()
        for b in buses:
            frames: list[can.Message] = []
            for d in b.drives:
                d.fresh = False
                if send_rpdo:
                    frames.append(can.Message(
                        arbitration_id=d.rpdo1, is_extended_id=False,
                        data=self._rpdo_layout.encode(d.controlword, d.target),
                    ))
            frames.append(
                can.Message(arbitration_id=c4.SYNC_COB_ID, is_extended_id=False, data=b"")
            )
            if self._feeding and now >= b.next_beat:
                # After the SYNC: the set-points and the sampling instant are not delayed;
                # at worst the drives' answers wait for this one frame.
                frames.append(can.Message(
                    arbitration_id=c4.bootup_cob_id(self._master_id), is_extended_id=False,
                    data=c4.encode_heartbeat(c4.NmtState.OPERATIONAL),
                ))
                b.next_beat = now + self._heartbeat_period_s
                b.beats += 1
            queues.append(frames)
            b.syncs += 1
        for row in zip_longest(*queues):
            for b, msg in zip(buses, row, strict=True):
                if msg is not None:
                    self._send(b, msg)

    def _collect(self, b: DriveBus, deadline: float) -> None:
        latest: dict[int, can.Message] = {}
        want = {d.tpdo1 for d in b.drives} | {d.tpdo2 for d in b.drives}
        try:
            # Each frame is decoded as it is received (on_frame), while the others are still
            # on the wire: after the last one only its own decoding is left.
            result = canbus.collect_until(self._bus_of(b), latest, want, deadline, b.key,
                                          b.on_frame)
        except can.CanError as exc:
            raise self._bus_error(b, "receiving", exc) from exc
        self._take(b, latest, result, decoded=True)
        for d in b.drives:
            if not d.fresh:
                d.missed += 1
        b.health.check(self._bus_of(b), self._owner())

    def _take(self, b: DriveBus, latest: Mapping[int, can.Message], result: Any,
              decoded: bool = False) -> None:
        """Count what a drain saw and decode its newest frames (``decoded``: already done
        as they were received)."""
        for err in result.errors:
            b.health.note_error_frame(err)
        b.health.rx_frames += result.stored
        if not decoded:
            now = time.monotonic()
            for cob, msg in latest.items():
                self._take_one(b, cob, msg, now)

    def _take_one(self, b: DriveBus, cob: int, msg: can.Message, now: float = 0.0) -> None:
        """Decode one frame of ``b`` (``cob``: a key of ``b.keys``) received at ``now``
        (0: now)."""
        d, which = b.keys[cob]
        data = bytes(msg.data)
        now = now or time.monotonic()
        try:
            if which == 1:
                d.statusword, d.position_counts, d.torque_permille = c4.TPDO_STATUS.decode(data)
                d.state = c4.decode_statusword(d.statusword)
                d.rx1_at = now
                d.fresh = True
            elif which == 2:
                d.velocity_value, d.error_code, d.mode_display = c4.TPDO_FEEDBACK.decode(data)
                d.rx2_at = now
            elif which == 3:
                self._take_sdo(d, data)
            elif len(data) >= 2:
                d.last_emcy = int.from_bytes(data[:2], "little")
                if d.last_emcy == c4.EMCY_HEARTBEAT:
                    d.heartbeat_lost = True
        except Exception as exc:  # noqa: BLE001 - a garbled frame is a protocol fault
            raise CommunicationError(
                f"{self._owner()}: {d.who()} sent a frame the configured mapping cannot "
                f"decode ({one_line(exc)}); another master may have remapped its PDOs"
            ) from exc

    def _take_sdo(self, d: Drive, data: bytes) -> None:
        """An SDO answer: the error register if it is the upload of 0x1001:00 (anything else,
        e.g. a late answer to configure's canopen session, is not ours and is left alone)."""
        if len(data) < 5 or data[1] | data[2] << 8 != c4.ERROR_REGISTER or data[3] != 0:
            return
        if data[0] & 0xE0 == _SDO_UPLOAD and data[0] & 0x02:  # expedited upload answer
            d.error_register = data[4]
        elif data[0] == _SDO_ABORT:
            self._sdo_aborts += 1

    def _drain_late(self, b: DriveBus) -> None:
        """Take the answers that came after the last read's window, counting them as late.

        They are still the newest feedback (a cycle shorter than the bus needs makes every
        answer late; dropping them would starve the driver of feedback), and they are taken
        before the next SYNC, so an answer is never mistaken for one to a later SYNC.
        """
        latest: dict[int, can.Message] = {}
        try:
            result = canbus.drain_latest(self._bus_of(b), latest, b.key)
        except can.CanError as exc:
            raise self._bus_error(b, "receiving", exc) from exc
        self._take(b, latest, result)
        for cob in latest:
            d, which = b.keys[cob]
            if which == 1:
                d.late += 1

    def _flush(self, b: DriveBus) -> None:
        if b.bus is None:
            return
        try:
            b.health.stale_flushed += canbus.flush(b.bus)
        except can.CanError as exc:
            raise self._bus_error(b, "flushing", exc) from exc
        b.sync_outstanding = False

    def _exchange(self, *, send_rpdo: bool, strict: bool = True) -> None:
        """One RPDO + SYNC round on every bus, waiting (bounded) for every drive's TPDOs.

        Raises:
            CommunicationError: with ``strict``, a drive did not answer.
        """
        self._send_cycle(list(self._buses.values()), send_rpdo=send_rpdo)
        deadline = time.monotonic() + max(b.settings.setup_timeout for b in self._buses.values())
        for b in self._buses.values():
            self._collect(b, deadline)
            b.sync_outstanding = False
        if strict:
            for d in self._drives:
                if not d.fresh:
                    raise self._comm_lost(d, None)

    # -- errors -----------------------------------------------------------------------------------

    def _comm_lost(self, d: Drive, age: float | None) -> CommunicationError:
        b = self._buses[d.bus]
        if age is None:
            what = f"did not answer a SYNC within {b.settings.setup_timeout:g} s"
        elif d.rx1_at == 0.0:
            what = f"sent no TPDO in {age:.3f} s since the bus was opened"
        else:
            what = (
                f"sent no TPDO for {age:.3f} s (feedback_timeout_s {self._feedback_timeout_s:g}; "
                f"{d.late} late, {d.missed} missed answers)"
            )
        why = canbus.full_queue(b.health)
        message = f"{self._owner()}: {d.who()} {what}; " + (why or (
            f"check its power, CAN wiring and termination, node id and bit rate "
            f"({b.settings.bitrate} bit/s)"))
        self._last_fault_by_node[d.node_id] = message
        return CommunicationError(message)

    def _heartbeat_fault(self, d: Drive) -> MotorFault:
        return self._fault(
            d, f"lost the daemon's heartbeat (none for {self._watchdog_ms} ms, watchdog_s) and "
            f"stopped by itself with 0x6007 {_REACTION_TEXT[self._reaction]}: the control loop "
            "stalled or its frames did not reach the drive; re-arm when it runs again",
        )

    def _fault(self, d: Drive, what: str) -> MotorFault:
        code = d.error_code or d.last_emcy or 0
        message = (
            f"{self._owner()}: {d.who()} {what}: state {d.describe_state()}, error code "
            f"{c4.describe_error(code)}"
        )
        self._last_fault_by_node[d.node_id] = message
        return MotorFault(message)

    # -- status -----------------------------------------------------------------------------------

    def _health(self) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
        """Statusword and error code from the TPDOs of every cycle, the error register from
        the low-rate SDO reads; CiA 402 has no standard temperature or supply objects.

        ``age_s`` is the age of the drive's newest TPDO1. Older than ``feedback_timeout_s``
        (``stale``: true, e.g. after a bus loss), or none yet, the drive's readings are shown
        as unknown (``None``, listed in ``unknown``), not as the last ones heard: a drive
        that lost power is not "enabled". ``mode`` is the configured mode of operation."""
        now = time.monotonic()
        motors: list[dict[str, Any]] = []
        for d in self._drives:
            heard = d.rx1_at != 0.0
            fresh = heard and now - d.rx1_at <= self._feedback_timeout_s
            errors = []
            if fresh and d.error_code:
                errors.append(f"error code 0x{d.error_code:04X}: {c4.describe_error(d.error_code)}")
            if fresh and d.error_register:
                errors.append(f"error register 0x{d.error_register:02X}")
            if d.heartbeat_lost:
                errors.append("lost the daemon's heartbeat")
            state = d.state if fresh else None
            statusword = d.statusword if fresh else None
            error_register = d.error_register if fresh else None
            motors.append({
                "motor": d.node_id,
                "joint": d.joint,
                "mode": self.mode.name.lower(),
                "torque_enabled": (None if state is None
                                   else state is c4.State.OPERATION_ENABLED),
                "state": None if state is None else state.value,
                "statusword": None if statusword is None else f"0x{statusword:04X}",
                "error_code": f"0x{d.error_code:04X}" if fresh else None,
                "error_register": None if error_register is None
                else f"0x{error_register:02X}",
                "age_s": round(now - d.rx1_at, 3) if heard else None,
                "stale": not fresh,
                "unknown": [] if fresh else ["torque_enabled", "state", "statusword",
                                             "error_code", "error_register"],
                "errors": errors,
                "last_fault": self._last_fault_by_node.get(d.node_id),
            })
        healths = [b.health for b in self._buses.values()]
        bus = {
            "transactions": sum(b.syncs for b in self._buses.values()),
            "timeouts": sum(d.missed for d in self._drives),
            # The CAN controller checks CRCs itself; what reaches us is its error frames.
            "crc_errors": sum(h.error_frames for h in healths),
            "retries": None,  # cyclic PDOs are never resent: the next SYNC supersedes
            "sdo_aborts": self._sdo_aborts,
        }
        return motors, bus

    def _details(self) -> Mapping[str, Any]:
        now = time.monotonic()
        return {
            "mode": self.mode.name.lower(),
            "watchdog": {
                "timeout_s": self._watchdog_ms / 1000.0,
                "heartbeat_period_s": self._heartbeat_period_s,
                "master_node_id": self._master_id,
                "reaction": self._reaction.name.lower(),
                "armed": self._armed,
                "feeding": self._feeding,
                "disarm_failures": list(self._disarm_failures),
            },
            "buses": {name: {**b.health.as_dict(), "syncs": b.syncs, "heartbeats": b.beats}
                      for name, b in self._buses.items()},
            "drives": {
                d.joint: {
                    "node_id": d.node_id,
                    "bus": d.bus,
                    "state": None if d.state is None else d.state.value,
                    "statusword": None if d.statusword is None else f"0x{d.statusword:04X}",
                    "error_code": f"0x{d.error_code:04X}",
                    "error": c4.describe_error(d.error_code),
                    "last_emcy": None if d.last_emcy is None else f"0x{d.last_emcy:04X}",
                    "heartbeat_lost": d.heartbeat_lost,
                    "consumer_entry": f"0x1016:{d.consumer_sub}" if d.consumer_sub else None,
                    "mode_display": d.mode_display,
                    "torque_permille": d.torque_permille,
                    "feedback_age_s": None if d.rx1_at == 0.0 else round(now - d.rx1_at, 6),
                    "late": d.late,
                    "missed": d.missed,
                    "last_fault": self._last_fault_by_node.get(d.node_id),
                }
                for d in self._drives
            },
        }
