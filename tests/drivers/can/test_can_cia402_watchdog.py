"""The CiA 402 heartbeat watchdog: the drives stop by themselves when the daemon falls silent.

The emulated drives (``Cia402DriveEmulator``) consume heartbeats as CiA 301 says (0x1016,
monitoring from the first heartbeat on) and react to a loss as CiA 402 says (EMCY 0x8130, then
0x6007: quick stop per 0x605A / 0x6085, fault per 0x605E, or Disable Voltage). The first tests
talk to one drive with ``canopen`` as the master; the others run the real driver
(``Cia402Hardware``), whose cycle produces the heartbeat, against two drives. Everything goes
through python-can ``virtual`` buses on one channel, as over a wire; nothing is mocked. "The
daemon dies" is the test no longer calling the driver. Waits are on conditions (the emulator's
record of a stop, a state) with deadlines; nothing sleeps.
"""

from __future__ import annotations

import math
import struct
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import canopen
import pytest
from canopen.sdo.exceptions import SdoAbortedError
from test_can_cia402 import BOUND_S, CPR, NODES, Rig, hold

from jtc_hw.controller.joints import JointCommand
from jtc_hw.drivers.can.cia402 import codec as c4
from jtc_hw.drivers.can.cia402.codec import AbortConnection, State
from jtc_hw.drivers.can.cia402.emulator import DEFAULT_EDS, Cia402DriveEmulator, NmtState
from jtc_hw.drivers.can.cia402.hardware import Cia402Hardware
from jtc_hw.errors import ConfigurationError, HardwareError, MotorFault
from jtc_hw.hardware import LifecycleState

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

MASTER = 127
HEARTBEAT = 0x700 + MASTER
QUICK_STOP_DECELERATION = 2_000_000 * 2 * math.pi / CPR  # the EDS default 0x6085, rad/s^2


def channel() -> str:
    return f"cia402-wd-{uuid.uuid4().hex[:8]}"


def frames(bus: can.BusABC) -> list[can.Message]:
    """Every frame queued on ``bus`` so far, oldest first."""
    out = []
    while (msg := bus.recv(timeout=0.0)) is not None:
        out.append(msg)
    return out


def next_frame(bus: can.BusABC, cob_id: int) -> can.Message:
    """The next frame with ``cob_id`` on ``bus`` (waiting, bounded)."""
    deadline = time.monotonic() + BOUND_S
    while time.monotonic() < deadline:
        msg = bus.recv(timeout=0.05)
        if msg is not None and msg.arbitration_id == cob_id:
            return msg
    raise AssertionError(f"no frame 0x{cob_id:03X} within the bound")


# -- the drive as a heartbeat consumer, with canopen as the master ---------------------------------


class Master:
    """One emulated drive (node 3) and canopen's network as its master, plus a listener."""

    def __init__(self, eds: str | Path | None = None) -> None:
        name = channel()
        self.drive_bus = can.Bus(interface="virtual", channel=name)
        self.drive = Cia402DriveEmulator(self.drive_bus, 3, eds=eds)
        self.listener = can.Bus(interface="virtual", channel=name)
        self.network = canopen.Network()
        self.node = self.network.add_node(3, str(DEFAULT_EDS))
        self.network.connect(interface="virtual", channel=name)
        self.drive.start()
        assert bytes(next_frame(self.listener, 0x703).data) == b"\x00"  # its boot-up

    def write(self, index: int, sub: int, fmt: str, value: int) -> None:
        self.node.sdo.download(index, sub, struct.pack(fmt, value))

    def beat(self, node_id: int = MASTER, state: int = NmtState.OPERATIONAL) -> None:
        self.network.send_message(0x700 + node_id, bytes((state,)))

    def close(self) -> None:
        try:
            self.network.disconnect()
        finally:
            self.drive.stop()
            self.listener.shutdown()
            self.drive_bus.shutdown()


@pytest.fixture
def master() -> Iterator[Master]:
    m = Master()
    try:
        yield m
    finally:
        m.close()


def test_monitoring_starts_with_the_first_heartbeat_and_a_loss_is_an_emcy(master: Master) -> None:
    master.write(c4.CONSUMER_HEARTBEAT_TIME, 1, "<I", c4.encode_consumer_entry(MASTER, 50))
    # Configured, not monitoring: before the first heartbeat the producer's state is unknown.
    assert master.drive.heartbeat_consumers == {1: (MASTER, 0.05, False)}
    frames(master.listener)
    master.beat()
    trip = master.drive.wait_watchdog_stop(BOUND_S)
    assert trip is not None
    assert trip.producer == MASTER and trip.consumer_time_s == 0.05
    # The event comes no earlier than the consumer time after the last heartbeat.
    assert trip.detected_at - trip.last_heartbeat_at >= 0.05 - 1e-3
    assert trip.state_before is State.SWITCH_ON_DISABLED
    # The EDS default 0x6007 is 1, "fault signal": Fault, error code 0x8130.
    assert trip.reaction is AbortConnection.FAULT
    assert master.drive.wait_state(State.FAULT, BOUND_S)
    assert master.drive.error_code == c4.EMCY_HEARTBEAT
    # EMCY 0x8130, error register generic + communication, the lost node id.
    emcy = next_frame(master.listener, 0x83)
    assert bytes(emcy.data) == bytes.fromhex("308111") + bytes((MASTER,)) + bytes(4)
    assert int(master.node.sdo[c4.ERROR_REGISTER].raw) == 0x11
    # Monitoring stopped with the event; the consumer is armed again by the next heartbeat.
    assert master.drive.heartbeat_consumers[1][2] is False


def test_consumer_entry_rules(master: Master) -> None:
    master.write(c4.CONSUMER_HEARTBEAT_TIME, 1, "<I", c4.encode_consumer_entry(MASTER, 100))
    with pytest.raises(SdoAbortedError) as refused:  # one node id, two entries: CiA 301 abort
        master.write(c4.CONSUMER_HEARTBEAT_TIME, 2, "<I", c4.encode_consumer_entry(MASTER, 200))
    assert refused.value.code == 0x06040043
    master.write(c4.CONSUMER_HEARTBEAT_TIME, 2, "<I", c4.encode_consumer_entry(5, 200))
    assert master.drive.heartbeat_consumers == {1: (MASTER, 0.1, False), 2: (5, 0.2, False)}
    master.write(c4.CONSUMER_HEARTBEAT_TIME, 2, "<I", c4.encode_consumer_entry(5, 0))  # unused
    assert master.drive.heartbeat_consumers == {1: (MASTER, 0.1, False)}
    # Option codes outside the profile's values are refused.
    for index, bad in ((c4.ABORT_CONNECTION_OPTION, 4), (c4.QUICK_STOP_OPTION, 9),
                       (c4.FAULT_REACTION_OPTION, -1)):
        with pytest.raises(SdoAbortedError) as refused:
            master.write(index, 0, "<h", bad)
        assert refused.value.code == 0x06090030
    # NMT reset communication restores the (default: unused) entries.
    master.network.nmt.send_command(c4.NMT_RESET_COMMUNICATION)
    deadline = time.monotonic() + BOUND_S
    while master.drive.heartbeat_consumers and time.monotonic() < deadline:
        master.listener.recv(timeout=0.01)  # waiting for the drive to process the NMT frame
    assert master.drive.heartbeat_consumers == {}


def test_the_drive_produces_its_own_heartbeat(master: Master) -> None:
    frames(master.listener)
    master.write(c4.PRODUCER_HEARTBEAT_TIME, 0, "<H", 20)
    beats = [next_frame(master.listener, 0x703) for _ in range(3)]
    assert [bytes(m.data) for m in beats] == [bytes((NmtState.PRE_OPERATIONAL,))] * 3
    # Never faster than the producer time, on the drive's own clock: the frames' receive
    # stamps add how late the host ran the emulator's thread after it read that clock
    # (16.5 ms between two stamps beside two busy processes, tools/ci-under-load).
    produced = master.drive.heartbeats_produced
    assert len(produced) >= 3
    gaps = [b - a for a, b in zip(produced, produced[1:], strict=False)]
    assert min(gaps) >= 0.02 - 1e-9, gaps  # float rounding of "now + producer time" only


def test_a_stored_producer_time_starts_the_heartbeat_after_the_boot_up(tmp_path: Path) -> None:
    eds = tmp_path / "beating.eds"
    text = DEFAULT_EDS.read_text()
    start = text.index("[1017]")
    end = text.index("\n\n", start)
    eds.write_text(text[:start] + text[start:end].replace("DefaultValue=0", "DefaultValue=20")
                   + text[end:])
    m = Master(eds)  # waits for the boot-up
    try:
        beat = next_frame(m.listener, 0x703)
        assert bytes(beat.data) == bytes((NmtState.PRE_OPERATIONAL,))
    finally:
        m.close()


# -- the driver: arming, producing, disarming ------------------------------------------------------


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig(channel())
    r.start()
    try:
        yield r
    finally:
        r.close()


def run(rig: Rig, command: JointCommand | None = None, *, until: Any = None) -> int:
    """Read/write cycles until ``until()`` is true (bounded); the number of cycles."""
    hw = rig.hw
    assert hw is not None
    deadline = time.monotonic() + BOUND_S
    cycles = 0
    while time.monotonic() < deadline:
        hw.read(time.monotonic_ns())
        hw.write(time.monotonic_ns(), command if command is not None else hw.nan_command())
        cycles += 1
        if until is None or until():
            return cycles
    raise AssertionError("condition not met within the bound")


def test_configure_claims_an_entry_activate_arms_it_deactivate_disarms_it(rig: Rig) -> None:
    hw = rig.make(watchdog_s=0.2)
    hw.configure()
    for d in rig.drives.values():
        assert d.heartbeat_consumers == {}  # claimed with time 0: not watching yet
        assert int(d.node.sdo[c4.ABORT_CONNECTION_OPTION].raw) == AbortConnection.QUICK_STOP
    hw.activate(time.monotonic_ns())
    for d in rig.drives.values():
        # Watching the daemon (node 127) for 200 ms, monitoring since the first heartbeat.
        assert d.heartbeat_consumers == {1: (MASTER, 0.2, True)}
        assert d.state is State.OPERATION_ENABLED
    watchdog = hw.status()["details"]["watchdog"]
    assert watchdog["armed"] is True and watchdog["heartbeat_period_s"] == 0.05
    run(rig)
    hw.deactivate(time.monotonic_ns())
    for d in rig.drives.values():
        assert d.heartbeat_consumers == {}  # time 0: the drive no longer watches
        assert d.state is State.OPERATION_ENABLED  # safe action hold: still holding
        assert d.watchdog_trips == []
    assert hw.status()["details"]["watchdog"]["armed"] is False


def test_device_watchdog_and_devices(rig: Rig) -> None:
    hw = rig.make(watchdog_s=0.25, master_node_id=100, watchdog_reaction="fault")
    watchdog = hw.device_watchdog()  # no I/O: unconfigured
    assert watchdog.timeout_s == 0.25 and watchdog.complete
    assert "0x1016" in watchdog.mechanism and "node 100" in watchdog.mechanism
    assert "0x8130" in watchdog.mechanism and "0x6007 = 1" in watchdog.mechanism
    assert "\n" not in watchdog.mechanism
    bus = f"can:virtual:{rig.channel}"
    assert [d.key for d in hw.devices()] == [
        f"{bus}:canopen-master", *(f"{bus}:canopen-node:{n}" for n in rig.drives)]
    assert hw.devices()[0].label.endswith("CANopen master (NMT, SYNC, heartbeat)")


def test_the_heartbeat_follows_the_sync_at_a_quarter_of_the_watchdog_time(rig: Rig) -> None:
    listener = can.Bus(interface="virtual", channel=rig.channel)
    try:
        hw = rig.make(watchdog_s=0.2)
        hw.configure()
        hw.activate(time.monotonic_ns())
        seen: list[can.Message] = []
        driver_ids = {0x080, HEARTBEAT} | {0x200 + n for n in NODES}
        (bus,) = hw._buses.values()
        due: list[float] = []  # the driver's clock: when the next heartbeat is due, each beat

        def enough() -> bool:
            seen.extend(m for m in frames(listener) if m.arbitration_id in driver_ids)
            if not due or bus.next_beat != due[-1]:
                due.append(bus.next_beat)
            return sum(m.arbitration_id == HEARTBEAT for m in seen) >= 6

        run(rig, until=enough)
    finally:
        listener.shutdown()
    beats = [i for i, m in enumerate(seen) if m.arbitration_id == HEARTBEAT]
    for i in beats:
        assert bytes(seen[i].data) == bytes((NmtState.OPERATIONAL,))
        # One frame more in a cycle's transaction, after its SYNC.
        assert i > 0 and seen[i - 1].arbitration_id == 0x080
    # No more often than every watchdog_s / 4, judged on the driver's own clock (a beat sets
    # the next one due a period after the clock it read): the frames' stamps are taken when
    # they are sent, which a busy host delays by a varying amount after that reading.
    sent_at = [t - 0.05 for t in due]
    gaps = [b - a for a, b in zip(sent_at, sent_at[1:], strict=False)]
    assert len(gaps) >= 4 and min(gaps) >= 0.05, gaps
    # ... and not much later either: a SYNC one and a half periods after the last heartbeat
    # is followed by one (the half period: room for when the driver read its clock before
    # sending; at half the rate, every SYNC in the second half of the gap would fail this).
    last = None
    for i, m in enumerate(seen):
        if m.arbitration_id == HEARTBEAT:
            last = m.timestamp
        elif m.arbitration_id == 0x080 and last is not None and m.timestamp - last >= 0.075:
            assert i + 1 < len(seen) and seen[i + 1].arbitration_id == HEARTBEAT, i


# -- losing the daemon -----------------------------------------------------------------------------


def test_losing_the_daemon_quick_stops_moving_drives(rig: Rig) -> None:
    hw = rig.make("velocity", watchdog_s=0.05)
    hw.configure()
    hw.activate(time.monotonic_ns())
    p0 = rig.drives[3].motor.position
    run(rig, JointCommand(None, [0.5, -0.5]),
        until=lambda: abs(rig.drives[3].motor.velocity - 0.5) < 0.02
        and abs(rig.drives[3].motor.position - p0) > 0.02)
    # The daemon dies: no more cycles. CSV would keep the drives turning at 0.5 rad/s.
    for node, d in rig.drives.items():
        trip = d.wait_watchdog_stop(BOUND_S)
        assert trip is not None, node
        assert trip.producer == MASTER and trip.reaction is AbortConnection.QUICK_STOP
        assert trip.state_before is State.OPERATION_ENABLED
        assert abs(trip.velocity_at_detection) > 0.3
        assert trip.detected_at - trip.last_heartbeat_at >= 0.05 - 1e-3
        # 0x605A default 2: down the quick stop ramp (0x6085), then Switch On Disabled.
        assert trip.state_after is State.SWITCH_ON_DISABLED
        assert trip.stopped_at is not None
        ramp_s = abs(trip.velocity_at_detection) / QUICK_STOP_DECELERATION
        assert trip.stopped_at - trip.detected_at >= 0.8 * ramp_s  # a ramp, not a jolt
        assert d.error_code == c4.EMCY_HEARTBEAT
    # The daemon comes back: its next read names the cause.
    exc = rig.cycles_until_error(hold(hw))
    assert isinstance(exc, MotorFault)
    message = str(exc)
    assert "lost the daemon's heartbeat" in message and "node 3" in message, message
    assert "\n" not in message
    assert hw.status()["details"]["drives"]["shoulder"]["heartbeat_lost"] is True
    hw.deactivate(time.monotonic_ns())
    # Re-arm: cleanup -> configure -> recover -> activate brings both back, watched again.
    hw.cleanup()
    hw.configure()
    hw.recover()
    hw.activate(time.monotonic_ns())
    for d in rig.drives.values():
        assert d.state is State.OPERATION_ENABLED
        assert d.heartbeat_consumers == {1: (MASTER, 0.05, True)}
    assert hw.status()["details"]["drives"]["shoulder"]["heartbeat_lost"] is False
    run(rig, JointCommand(None, [0.0, 0.0]))


def test_fault_reaction_on_loss_and_rearm_resets_it(rig: Rig) -> None:
    hw = rig.make(watchdog_s=0.05, watchdog_reaction="fault")
    hw.configure()
    hw.activate(time.monotonic_ns())
    run(rig)
    trip = rig.drives[7].wait_watchdog_stop(BOUND_S)
    assert trip is not None and trip.reaction is AbortConnection.FAULT
    assert trip.state_after is State.FAULT
    exc = rig.cycles_until_error(hold(hw))
    assert isinstance(exc, MotorFault) and "0x8130" in str(exc)
    hw.deactivate(time.monotonic_ns())
    hw.recover()  # fault reset
    for d in rig.drives.values():
        assert d.state is State.SWITCH_ON_DISABLED
    hw.activate(time.monotonic_ns())
    run(rig)


def test_quick_stop_that_stays_active_holds_and_is_walked_back(rig: Rig) -> None:
    for d in rig.drives.values():
        d.node.sdo[c4.QUICK_STOP_OPTION].raw = 6  # quick stop ramp, then stay (hold)
    hw = rig.make(watchdog_s=0.05)
    hw.configure()
    hw.activate(time.monotonic_ns())
    run(rig)
    trip = rig.drives[3].wait_watchdog_stop(BOUND_S)
    assert trip is not None and trip.state_after is State.QUICK_STOP_ACTIVE
    assert rig.drives[3].state is State.QUICK_STOP_ACTIVE  # holding, powered
    exc = rig.cycles_until_error(hold(hw))
    assert isinstance(exc, MotorFault) and "lost the daemon's heartbeat" in str(exc)
    hw.deactivate(time.monotonic_ns())
    hw.activate(time.monotonic_ns())  # Quick Stop Active -> Disable Voltage -> ... enabled
    for d in rig.drives.values():
        assert d.state is State.OPERATION_ENABLED


def test_a_drive_that_cannot_be_disarmed_stops_by_itself(rig: Rig) -> None:
    hw = rig.make(watchdog_s=0.05)
    hw.configure()
    hw.activate(time.monotonic_ns())
    rig.drives[3].set_silent(True)  # receives, never answers
    rig.cycles_until_error(hold(hw))
    hw.deactivate(time.monotonic_ns())  # logged, not raised: the drive stops by itself
    failures = hw.status()["details"]["watchdog"]["disarm_failures"]
    assert len(failures) == 1 and "node 3" in failures[0], failures
    trip = rig.drives[3].wait_watchdog_stop(BOUND_S)
    assert trip is not None and trip.reaction is AbortConnection.QUICK_STOP
    assert rig.drives[7].heartbeat_consumers == {}  # the other one was disarmed


# -- truthful activation ---------------------------------------------------------------------------


def test_activation_is_refused_when_a_drive_drops_out_right_after_enabling(rig: Rig) -> None:
    hw = rig.make(watchdog_s=0.05)
    hw.configure()
    rig.drives[7].lose_enable(1, fault_code=None)
    with pytest.raises(HardwareError) as refused:
        hw.activate(time.monotonic_ns())
    message = str(refused.value)
    assert "activation not confirmed" in message and "node 7" in message, message
    assert "switch on disabled" in message and "\n" not in message
    assert hw.state is LifecycleState.INACTIVE
    # The activation armed the watchdog and stopped feeding it: what it enabled stops.
    trip = rig.drives[3].wait_watchdog_stop(BOUND_S)
    assert trip is not None


def test_rearm_after_a_loss_is_refused_naming_the_drive_that_faults(rig: Rig) -> None:
    hw = rig.make(watchdog_s=0.05, watchdog_reaction="fault")
    hw.configure()
    hw.activate(time.monotonic_ns())
    run(rig)
    assert rig.drives[3].wait_watchdog_stop(BOUND_S) is not None
    rig.cycles_until_error(hold(hw))
    hw.deactivate(time.monotonic_ns())
    rig.drives[3].lose_enable(1)  # its enable input opens once it is enabled: 0x5441
    hw.cleanup()
    hw.configure()
    hw.recover()
    with pytest.raises(MotorFault) as refused:
        hw.activate(time.monotonic_ns())
    message = str(refused.value)
    assert "node 3" in message and "0x5441" in message and "\n" not in message, message
    rig.drives[3].lose_enable(None)
    hw.cleanup()
    hw.configure()
    hw.recover()
    hw.activate(time.monotonic_ns())
    run(rig)


# -- configuration ---------------------------------------------------------------------------------


def test_watchdog_parameters_are_checked() -> None:
    params: dict[str, Any] = {
        "buses": {"can0": {"interface": "virtual", "channel": "unused"}},
        "node_id": [3, 127],
    }

    def make(**extra: Any) -> Cia402Hardware:
        return Cia402Hardware("arm", ["a", "b"], ["position"], ["position"],
                              {**params, **extra})

    with pytest.raises(ConfigurationError) as caught:
        make()  # the default master_node_id 127 is joint b's drive
    assert caught.value.path == "params.master_node_id"
    assert "joint 'b'" in str(caught.value) and "0x77F" in str(caught.value)
    assert make(master_node_id=100).device_watchdog().timeout_s == 0.1
    with pytest.raises(ConfigurationError) as caught:
        make(master_node_id=100, watchdog_s=0.0125)
    assert caught.value.path == "params.watchdog_s"
    assert "whole number of milliseconds" in str(caught.value)
    with pytest.raises(ConfigurationError, match="65.535 s"):
        make(master_node_id=100, watchdog_s=70.0)
    with pytest.raises(ConfigurationError, match="watchdog_reaction"):
        make(master_node_id=100, watchdog_reaction="nothing")


def test_a_drive_without_a_free_consumer_entry_is_refused(rig: Rig, tmp_path: Path) -> None:
    eds = DEFAULT_EDS.read_text()
    for sub, producer in ((1, 5), (2, 6)):
        section = f"[1016sub{sub}]"
        start = eds.index(section)
        end = eds.index("\n\n", start)
        eds = eds[:start] + eds[start:end].replace(
            "DefaultValue=0", f"DefaultValue=0x{c4.encode_consumer_entry(producer, 100):08X}"
        ) + eds[end:]
    full = tmp_path / "full.eds"
    full.write_text(eds)
    rig.drives[3].stop()
    rig.drives[3] = Cia402DriveEmulator(rig.bus, 3, eds=full)
    rig.drives[3].start()
    hw = rig.make()
    with pytest.raises(HardwareError) as refused:
        hw.configure()
    message = str(refused.value)
    assert "node 3" in message and "no free consumer heartbeat entry" in message, message
