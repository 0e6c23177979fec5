"""MitHardware in-process against MIT emulators on python-can ``virtual`` buses.

The driver runs unmodified (real python-can, real codec); the emulator is a peer speaking the
MIT protocol with motor physics. Cycles are "write, then read": read waits (bounded) for the
replies, so the test is paced by the emulator's answers, not by sleeps.
"""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from typing import Any

import can
import numpy as np
import pytest
from helpers.daemon import WAIT_S, daemon_env

from jtc_hw.controller.joints import JointCommand
from jtc_hw.drivers.can.bus import open_bus
from jtc_hw.drivers.can.mit.codec import MODEL_PRESETS, MitReply, encode_reply, quantum
from jtc_hw.drivers.can.mit.emulator import MitBusEmulator
from jtc_hw.drivers.can.mit.hardware import MitHardware
from jtc_hw.errors import CommunicationError, ConfigurationError, HardwareError, MotorFault
from jtc_hw.hardware import HardwareSpec, create_hardware

from conftest import ROOT

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

JOINTS = [f"j{i}" for i in range(1, 7)]
IDS = [1, 2, 3, 4, 5, 6]
Q = quantum(MODEL_PRESETS["AK80-9"]).position


class Rig:
    """Emulated buses (each a virtual channel with one MitBusEmulator) and hardware on them."""

    def __init__(self) -> None:
        self.buses: list[can.BusABC] = []
        self.emulators: dict[str, MitBusEmulator] = {}
        self.channels: dict[str, str] = {}
        self.hardware: list[MitHardware] = []

    def emulate(
        self, name: str, ids: list[int], model: str = "AK80-9", **kw: Any
    ) -> MitBusEmulator:
        channel = f"mit-{name}-{uuid.uuid4().hex}"
        bus = can.Bus(interface="virtual", channel=channel)
        self.buses.append(bus)
        emulator = MitBusEmulator(bus, ids, model, **kw)
        emulator.start()
        self.emulators[name] = emulator
        self.channels[name] = channel
        return emulator

    def make(
        self,
        command_interfaces: tuple[str, ...] = ("position",),
        joints: list[str] | None = None,
        **params: Any,
    ) -> MitHardware:
        params.setdefault("ids", IDS)
        # Generous: a loaded test machine may stall this process for tens of ms.
        params.setdefault("feedback_timeout", 0.5)
        params.setdefault("watchdog_s", 1.0)  # Damiao motors' CAN timeout, idem
        params.setdefault("buses", {
            name: {"interface": "virtual", "channel": ch, "receive_timeout": 0.05}
            for name, ch in self.channels.items()
        })
        hw = MitHardware("leg", joints or JOINTS, command_interfaces, ("position", "velocity"),
                         params)
        self.hardware.append(hw)
        return hw

    def close(self) -> None:
        for hw in self.hardware:
            try:
                hw.shutdown(time.monotonic_ns())
            except HardwareError:
                pass
        for emulator in self.emulators.values():
            emulator.stop()
            assert emulator.error is None, f"the emulator failed: {emulator.error!r}"
        for bus in self.buses:
            bus.shutdown()


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig()
    try:
        yield r
    finally:
        r.close()


def now() -> int:
    return time.monotonic_ns()


def track(hw: MitHardware, goal: np.ndarray, ramp_s: float = 0.3, settle_s: float = 0.4,
          interface: str = "position") -> float:
    """Ramp from the measured position to ``goal``, then hold; the worst error while holding."""
    start = hw.read(now()).positions
    t0 = time.monotonic()
    worst = 0.0
    while True:
        t = time.monotonic() - t0
        s = min(1.0, t / ramp_s)
        target = start + s * (goal - start)
        hw.write(now(), JointCommand(positions=target))
        state = hw.read(now())
        if t > ramp_s + settle_s / 2:
            worst = max(worst, float(np.max(np.abs(state.positions - goal))))
        if t > ramp_s + settle_s:
            return worst


# -- configuration -------------------------------------------------------------------------------


def test_registry_and_schema_errors(rig: Rig) -> None:
    rig.emulate("can0", IDS)
    spec = HardwareSpec("leg", "can-mit", tuple(JOINTS), ("position",), ("position", "velocity"),
                        {"buses": {"can0": {"interface": "virtual", "channel": "x"}}, "ids": IDS})
    assert isinstance(create_hardware(spec), MitHardware)
    with pytest.raises(ConfigurationError, match="motor id 1 is used by j1, j2"):
        rig.make(ids=[1, 1, 3, 4, 5, 6])
    with pytest.raises(ConfigurationError, match="not one of params.buses"):
        rig.make(bus="can9")
    with pytest.raises(ConfigurationError, match="ids 1..15"):
        rig.make(model="DM4310", ids=[1, 2, 3, 4, 5, 16])
    with pytest.raises(ConfigurationError, match="does not say which bus"):
        rig.make(buses={"a": {"interface": "virtual", "channel": "a"},
                        "b": {"interface": "virtual", "channel": "b"}})
    with pytest.raises(ConfigurationError, match="acceleration"):
        rig.make(command_interfaces=("acceleration",))


def test_open_bus_errors_name_the_interface() -> None:
    with pytest.raises(ConfigurationError, match="no interface 'socketcann'"):
        open_bus("socketcann", "can0", 1_000_000)
    try:
        bus = open_bus("socketcan", "vcan0", 1_000_000)
    except CommunicationError as exc:
        assert "'socketcan'" in str(exc) and "vcan0" in str(exc)
    else:  # a kernel with SocketCAN and vcan0
        bus.shutdown()
    with pytest.raises(CommunicationError, match="socketcand server at 127.0.0.1:1"):
        open_bus("socketcand", "can0", 1_000_000, host="127.0.0.1", port=1)


def test_configure_fails_naming_the_silent_motor(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    emulator.set_silent(4)
    hw = rig.make()
    with pytest.raises(CommunicationError, match=r"motor 4 \(joint 'j4'\)"):
        hw.configure()
    assert hw.state.value == "unconfigured"


# -- cycles --------------------------------------------------------------------------------------


def test_activate_seeds_from_the_measured_position_and_tracks(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    start = [0.3, -0.2, 0.1, 0.0, -0.5, 1.0]
    for motor_id, p in zip(IDS, start):
        emulator.set_position(motor_id, p)
    hw = rig.make(kp=40.0, kd=1.0)
    hw.configure()
    assert not any(emulator.enabled(i) for i in IDS)  # pinging does not enter motor mode
    held = hw.activate(now())
    assert held.positions is not None
    np.testing.assert_allclose(held.positions, start, atol=Q)
    for motor_id, p in zip(IDS, start):
        assert emulator.enabled(motor_id)
        command = emulator.last_command(motor_id)
        assert command.position == pytest.approx(p, abs=2 * Q)  # no jump
        assert command.kp == pytest.approx(40.0, abs=0.2)
    goal = np.array([0.5, 0.4, -0.3, 0.2, 0.0, 0.8])
    assert track(hw, goal) < 0.01
    details = hw.status()["details"]
    assert details["buses"]["can0"]["state"] == "active"
    assert details["motors"]["j1"]["id"] == 1 and details["motors"]["j1"]["fault"] is None


def test_joint_conversion_direction_gear_offset(rig: Rig) -> None:
    emulator = rig.emulate("can0", [1, 2])
    emulator.set_position(1, 1.0)
    emulator.set_position(2, 1.0)
    hw = rig.make(joints=["a", "b"], ids=[1, 2], direction=[1, -1], gear_ratio=[2.0, 1.0],
                  offset=[0.1, 0.0])
    hw.configure()
    hw.activate(now())
    state = hw.read(now())
    # joint = direction * motor / gear + offset
    np.testing.assert_allclose(state.positions, [0.6, -1.0], atol=Q)
    hw.write(now(), JointCommand(positions=[0.2, -0.5]))
    hw.read(now())
    # motor = direction * gear * (joint - offset)
    assert emulator.last_command(1).position == pytest.approx(0.2, abs=Q)
    assert emulator.last_command(2).position == pytest.approx(0.5, abs=Q)


def test_effort_mode_sends_feed_forward_torque(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    hw = rig.make(command_interfaces=("effort",), effort_kd=0.2)
    hw.configure()
    held = hw.activate(now())
    assert held.effort is not None and np.isnan(held.effort).all()
    hw.write(now(), JointCommand(effort=[0.5, -0.5, 0.0, 1.0, math.nan, 0.0]))
    hw.read(now())
    c = emulator.last_command(1)
    assert (c.kp, c.torque) == (0.0, pytest.approx(0.5, abs=0.01))
    assert c.kd == pytest.approx(0.2, abs=0.01)
    assert emulator.last_command(2).torque == pytest.approx(-0.5, abs=0.01)
    assert emulator.last_command(5).torque == pytest.approx(0.0, abs=0.01)  # NaN: unchanged


def test_two_buses(rig: Rig) -> None:
    a = rig.emulate("can0", [1, 2, 3])
    b = rig.emulate("can1", [1, 2, 3])
    hw = rig.make(ids=[1, 2, 3, 1, 2, 3], bus=["can0"] * 3 + ["can1"] * 3)
    hw.configure()
    hw.activate(now())
    goal = np.array([0.2, 0.1, 0.0, -0.1, -0.2, 0.3])
    assert track(hw, goal) < 0.01
    assert a.position(1) == pytest.approx(0.2, abs=0.01)
    assert b.position(3) == pytest.approx(0.3, abs=0.01)


def test_stale_frames_are_flushed_on_activate(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    hw = rig.make()
    hw.configure()
    # A stale reply (motor 1 far away) queued before activation must not be taken as fresh.
    stale = can.Bus(interface="virtual", channel=rig.channels["can0"])
    try:
        data = encode_reply(MitReply(1, 5.0, 0.0, 0.0), MODEL_PRESETS["AK80-9"])
        stale.send(can.Message(arbitration_id=0, is_extended_id=False, data=data))
    finally:
        stale.shutdown()
    held = hw.activate(now())
    assert held.positions is not None
    assert held.positions[0] == pytest.approx(emulator.position(1), abs=2 * Q)


# -- faults, safe actions, re-arm ----------------------------------------------------------------


def rearm(hw: MitHardware) -> np.ndarray:
    """What the daemon's re-arm does: cleanup -> configure -> recover -> activate."""
    if hw.state.value == "active":
        hw.deactivate(now())
    hw.cleanup()
    hw.configure()
    hw.recover()
    held = hw.activate(now())
    assert held.positions is not None
    return held.positions


def run_until_fault(hw: MitHardware, limit_s: float = 5.0) -> HardwareError:
    deadline = time.monotonic() + limit_s
    target = np.full(len(hw.joints), np.nan)  # NaN: hold the current set-points
    while time.monotonic() < deadline:
        try:
            hw.read(now())
            hw.write(now(), JointCommand(positions=target))
        except HardwareError as exc:
            return exc
    raise AssertionError("no fault within the limit")


def test_silent_motor_is_a_communication_fault_then_rearm(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    hw = rig.make(feedback_timeout=0.02, safe_action="torque_off")
    hw.configure()
    hw.activate(now())
    emulator.set_silent(3)
    error = run_until_fault(hw)
    assert isinstance(error, CommunicationError)
    assert "motor 3 (joint 'j3')" in str(error) and "no feedback" in str(error)
    hw.deactivate(now())  # torque off: every motor exits motor mode
    assert not emulator.enabled(1)
    assert hw.status()["details"]["motors"]["j3"]["fault"] is not None
    emulator.set_silent(3, False)
    emulator.set_position(3, 0.7)  # moved by hand while faulted
    positions = rearm(hw)
    assert positions[2] == pytest.approx(0.7, abs=2 * Q)
    assert emulator.last_command(3).position == pytest.approx(0.7, abs=2 * Q)  # no jump
    assert hw.status()["details"]["motors"]["j3"]["fault"] is None


def test_rearm_after_a_bus_loss_and_power_cycle_enables_every_motor(rig: Rig) -> None:
    # The case, in process: every motor goes quiet (the bus is lost), then comes back
    # power-cycled (out of motor mode, no set-point); the joints sagged meanwhile. The rig's
    # generous feedback_timeout: the tracking after the re-arm is not about how soon a silent
    # motor is noticed, and 50 ms faulted it when a busy host stalled this process for 66 ms.
    emulator = rig.emulate("can0", IDS)
    hw = rig.make()
    hw.configure()
    hw.activate(now())
    for motor_id in IDS:
        emulator.set_silent(motor_id)
    error = run_until_fault(hw)
    assert isinstance(error, CommunicationError) and "\n" not in str(error)
    hw.deactivate(now())  # hold: nobody answers
    faults = {j: m["fault"] for j, m in hw.status()["details"]["motors"].items()}
    assert all(faults.values()), faults  # every motor is listed, not only the first
    emulator.power_cycle()
    sagged = [0.2, -0.1, 0.3, 0.0, 0.15, -0.25]
    for motor_id, p in zip(IDS, sagged):
        emulator.set_silent(motor_id, False)
        emulator.set_position(motor_id, p)
    held = rearm(hw)
    assert all(emulator.enabled(i) for i in IDS)  # really enabled, not just believed
    np.testing.assert_allclose(held, sagged, atol=2 * Q)  # re-seeded where they are
    for motor_id, p in zip(IDS, sagged):
        assert emulator.last_command(motor_id).position == pytest.approx(p, abs=2 * Q)
    assert track(hw, np.array(sagged) + 0.1, ramp_s=0.1, settle_s=0.3) < 0.01


def test_rearm_fails_in_one_line_naming_a_motor_that_does_not_answer(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    hw = rig.make(feedback_timeout=0.05)
    hw.configure()
    hw.activate(now())
    emulator.set_silent(4)
    assert isinstance(run_until_fault(hw), CommunicationError)
    hw.deactivate(now())
    hw.cleanup()
    emulator.power_cycle()
    with pytest.raises(CommunicationError) as caught:
        hw.configure()
    message = str(caught.value)
    assert "\n" not in message and "motor 4 (joint 'j4')" in message
    assert "check its power" in message


def test_damiao_rearm_fails_in_one_line_naming_a_motor_that_does_not_enable(rig: Rig) -> None:
    emulator = rig.emulate("can0", [1, 2, 3], "DM4310", master_id=0x11)
    hw = rig.make(joints=["a", "b", "c"], ids=[1, 2, 3], model="DM4310", master_id=0x11)
    hw.configure()
    hw.activate(now())
    emulator.set_error(2, 0x9, persistent=True)  # the supply stays too low
    assert isinstance(run_until_fault(hw), MotorFault)
    hw.deactivate(now())
    with pytest.raises(MotorFault) as caught:
        rearm(hw)
    message = str(caught.value)
    assert "\n" not in message
    assert "motor 2 (joint 'b') on bus 'can0' did not enable: it reports under-voltage" in message
    assert hw.state.value == "inactive"
    assert hw.status()["details"]["motors"]["b"]["fault"] == message
    emulator.set_error(2, 0)  # supply restored
    rearm(hw)
    assert all(emulator.enabled(i) for i in (1, 2, 3))


def test_rearm_after_hold_keeps_the_healthy_motors_set_points(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    hw = rig.make(feedback_timeout=0.02)
    hw.configure()
    hw.activate(now())
    hw.write(now(), JointCommand(positions=[0.1, 0.2, 0.3, 0.0, 0.0, 0.0]))
    hw.read(now())
    emulator.set_silent(3)
    assert isinstance(run_until_fault(hw), CommunicationError)
    hw.deactivate(now())  # hold: every answering motor keeps its PD on its last set-point
    assert emulator.enabled(1)
    before = emulator.last_command(2)
    enters = emulator.commands(2)
    emulator.set_silent(3, False)
    held = rearm(hw)
    # Motor 2 held through the fault: same set-point ("enter motor mode", which proves it is
    # enabled, keeps the set-point of a motor in motor mode), and the controller is handed
    # the held set-point, not the sagging measured position.
    assert emulator.last_command(2).position == pytest.approx(before.position, abs=1e-9)
    assert held[1] == pytest.approx(0.2, abs=Q)
    assert emulator.commands(2) > enters and emulator.enabled(2)
    assert emulator.enabled(3)  # the faulted motor re-entered motor mode


def test_a_failed_activation_switches_the_motors_off_again(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    hw = rig.make()
    hw.configure()
    emulator.set_silent(6)
    with pytest.raises(CommunicationError, match=r"motor 6 \(joint 'j6'\)"):
        hw.activate(now())
    assert hw.state.value == "inactive"
    # The answering motors confirmed "exit motor mode" before activate() raised.
    assert not any(emulator.enabled(i) for i in IDS[:5])


def test_dropped_and_late_replies_within_the_timeout_are_tolerated(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    hw = rig.make(feedback_timeout=0.5)
    for bus in hw.params["buses"].values():
        assert bus.receive_timeout == 0.05
    hw.configure()
    hw.activate(now())
    emulator.drop_replies(2, 3)
    emulator.set_reply_delay(4, 0.002)
    for _ in range(10):
        hw.write(now(), JointCommand(positions=[0.0] * 6))
        hw.read(now())
    assert hw.status()["details"]["motors"]["j2"]["missed_replies"] >= 3


def test_a_read_right_after_a_write_waits_for_the_wire_before_counting_a_miss(rig: Rig) -> None:
    """A loop catching up after a late cycle reads right after it wrote: the replies are still
    on the wire. receive_timeout (the bound for stragglers) counts from when the wire could
    have carried every set-point and its reply, so none of them is counted missed.

    At 10 kbit/s six exchanges take ~150 ms of wire, three times receive_timeout (50 ms): a
    deadline counted from the read would miss every reply of every cycle."""
    rig.emulate("can0", IDS, pace=True, bitrate=10_000)
    hw = rig.make(buses={"can0": {"interface": "virtual", "channel": rig.channels["can0"],
                                  "bitrate": 10_000, "receive_timeout": 0.05}})
    hw.configure()
    hold = hw.activate(now())
    for _ in range(3):
        hw.write(now(), JointCommand(positions=hold.positions))
        hw.read(now())
    missed = {j: m["missed_replies"] for j, m in hw.status()["details"]["motors"].items()}
    assert missed == dict.fromkeys(JOINTS, 0)
    assert hw.health()["bus"]["timeouts"] == 0


def test_full_transmit_buffer_is_counted_and_survived(rig: Rig) -> None:
    rig.emulate("can0", IDS)
    hw = rig.make()
    hw.configure()
    hw.activate(now())
    # A node that never reads, with room for one frame: once it is full, python-can's virtual
    # bus raises CanOperationError on every send (as a full transmit queue does).
    jam = can.Bus(interface="virtual", channel=rig.channels["can0"], rx_queue_size=1)
    try:
        for _ in range(5):
            hw.write(now(), JointCommand(positions=[math.nan] * 6))
            hw.read(now())
        assert hw.status()["details"]["buses"]["can0"]["tx_overflows"] >= 5 * 6 - 1
    finally:
        jam.shutdown()
    hw.write(now(), JointCommand(positions=[math.nan] * 6))
    hw.read(now())
    assert hw.status()["last_fault"] is None


def test_torque_off_safe_action_exits_motor_mode(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    hw = rig.make(safe_action="torque_off")
    hw.configure()
    hw.activate(now())
    hw.deactivate(now())
    assert not any(emulator.enabled(i) for i in IDS)
    hw.read(now())  # inactive reads still work (pings with "exit motor mode")
    assert not any(emulator.enabled(i) for i in IDS)


def test_damiao_over_temperature_and_drive_fault(rig: Rig) -> None:
    emulator = rig.emulate("can0", [1, 2], "DM4310", master_id=0x11)
    hw = rig.make(joints=["a", "b"], ids=[1, 2], model="DM4310", master_id=0x11,
                  max_temperature_c=90.0)
    hw.configure()
    hw.activate(now())
    emulator.set_temperature(2, 95)
    error = run_until_fault(hw)
    assert isinstance(error, MotorFault)
    assert "motor 2 (joint 'b')" in str(error) and "95 degC" in str(error)
    hw.deactivate(now())
    emulator.set_temperature(2, 40)
    rearm(hw)
    emulator.set_error(1, 0xA)
    error = run_until_fault(hw)
    assert isinstance(error, MotorFault) and "over-current" in str(error)
    hw.deactivate(now())
    assert not emulator.enabled(1)  # the drive switched itself off
    rearm(hw)  # FB clears the error, FC re-enters motor mode
    assert emulator.enabled(1)


def test_bus_off_is_detected_and_recovered_by_reopening(rig: Rig) -> None:
    emulator = rig.emulate("can0", IDS)
    hw = rig.make()
    hw.configure()
    hw.activate(now())
    emulator.bus_off()
    error = run_until_fault(hw)
    assert isinstance(error, CommunicationError) and "bus-off" in str(error)
    assert hw.status()["details"]["buses"]["can0"]["state"] == "bus-off"
    with pytest.raises(HardwareError):
        hw.deactivate(now())  # the safe action cannot be confirmed on a bus-off bus
    emulator.clear_bus_off()
    rearm(hw)
    details = hw.status()["details"]["buses"]["can0"]
    assert details["state"] == "active" and details["bus_offs"] == 1
    assert track(hw, np.full(6, 0.1), ramp_s=0.1, settle_s=0.3) < 0.01


def test_set_zero(rig: Rig) -> None:
    emulator = rig.emulate("can0", [1])
    emulator.set_position(1, 0.4)
    hw = rig.make(joints=["a"], ids=[1])
    hw.configure()
    hw.set_zero()
    assert hw.read(now()).positions[0] == pytest.approx(0.0, abs=Q)
    hw.activate(now())
    with pytest.raises(HardwareError, match="inactive"):
        hw.set_zero()




# -- device-side timeout (Damiao CAN timeout) -----------------------------------------------------


def test_devices_and_device_watchdog_per_model(rig: Rig) -> None:
    rig.emulate("can0", [1, 2])
    rig.emulate("can1", [1, 2], "DM4310", master_id=0x11)
    ak = rig.make(joints=["a", "b"], ids=[1, 2], bus=["can0"] * 2)
    # Only the buses its motors are on (can1 is declared, unused: not driven, not locked).
    bus0 = "can:virtual:" + rig.channels["can0"]
    assert [d.key for d in ak.devices()] == [f"{bus0}:mit:1", f"{bus0}:mit:2"]
    assert ak.devices()[1].label.endswith(f"(virtual {rig.channels['can0']} @ 1000 kbit/s) "
                                          "motor 2")
    watchdog = ak.device_watchdog()
    assert watchdog.timeout_s is None and watchdog.unprotected == ("a", "b")
    assert "no device-side watchdog: motors keep their last command if the daemon dies" in (
        watchdog.mechanism)
    dm = rig.make(joints=["a", "b"], ids=[1, 2], bus=["can1"] * 2, model="DM4310",
                  watchdog_s=0.05)
    watchdog = dm.device_watchdog()
    assert watchdog.complete and watchdog.timeout_s == 0.05
    assert "50 ms" in watchdog.mechanism and "disable" in watchdog.mechanism
    mixed = rig.make(joints=["a", "b", "c", "d"], ids=[1, 2, 1, 2],
                     bus=["can0", "can0", "can1", "can1"],
                     model=["AK80-9", "AK80-9", "DM4310", "DM4310"], master_id=[0, 0, 0x11, 0x11])
    bus1 = "can:virtual:" + rig.channels["can1"]
    assert [d.key for d in mixed.devices()] == [f"{bus0}:mit:1", f"{bus0}:mit:2",
                                                f"{bus1}:mit:1", f"{bus1}:mit:2"]
    watchdog = mixed.device_watchdog()
    assert watchdog.timeout_s == 1.0 and watchdog.unprotected == ("a", "b")
    assert not watchdog.complete and "AK motors have none" in watchdog.mechanism


def test_damiao_timeout_is_armed_on_activate_and_off_after_a_hold(rig: Rig) -> None:
    emulator = rig.emulate("can0", [1, 2], "DM4310", master_id=0x11)
    hw = rig.make(joints=["a", "b"], ids=[1, 2], model="DM4310", master_id=0x11,
                  watchdog_s=0.25)
    hw.configure()
    assert emulator.timeout_s(1) == 0.0  # nothing written while configuring
    hw.activate(now())
    assert emulator.timeout_s(1) == pytest.approx(0.25) == emulator.timeout_s(2)
    assert hw.status()["details"]["motors"]["a"]["timeout_s"] == 0.25
    hw.deactivate(now())  # hold
    assert emulator.timeout_s(1) == 0.0 == emulator.timeout_s(2)
    assert emulator.enabled(1) and emulator.enabled(2)  # holding, and will go on holding
    emulator.check_timeouts(time.monotonic() + 10.0)
    assert emulator.timeout_expiries() == [] and emulator.enabled(1)
    assert hw.status()["details"]["motors"]["a"]["timeout_s"] is None
    rearm(hw)
    assert emulator.timeout_s(1) == pytest.approx(0.25)  # armed again


def test_damiao_motors_stop_by_themselves_when_nobody_commands_them(rig: Rig) -> None:
    emulator = rig.emulate("can0", [1, 2], "DM4310", master_id=0x11)
    hw = rig.make(joints=["a", "b"], ids=[1, 2], model="DM4310", master_id=0x11,
                  watchdog_s=0.05)
    hw.configure()
    hw.activate(now())
    hw.write(now(), JointCommand(positions=[0.1, 0.1]))
    hw.read(now())
    since = time.monotonic()  # the driver goes quiet (its process hangs or dies)
    expired = emulator.wait_timeout_expiries(since=since - 0.05, timeout_s=WAIT_S)
    assert set(expired) == {1, 2}
    assert not emulator.enabled(1) and not emulator.enabled(2)
    with pytest.raises(MotorFault, match="communication lost") as caught:
        hw.read(now())  # the next read sees it
    assert "\n" not in str(caught.value)
    hw.deactivate(now())
    rearm(hw)  # FB clears 0xD, FC enables, the timeout is armed again
    assert emulator.enabled(1) and emulator.enabled(2)


def test_a_restart_after_an_expired_timeout_enables_the_motors(rig: Rig) -> None:
    # A new daemon after the old one died: no re-arm, the motors report 0xD (the timeout's
    # own latch); activate clears it rather than refusing to start.
    emulator = rig.emulate("can0", [1], "DM4310", master_id=0x11)
    old = rig.make(joints=["a"], ids=[1], model="DM4310", master_id=0x11, watchdog_s=0.05)
    old.configure()
    old.activate(now())
    emulator.wait_timeout_expiries(timeout_s=WAIT_S)
    new = MitHardware("leg2", ["a"], ("position",), ("position", "velocity"),
                      {**old.params, "buses": {"can0": {
                          "interface": "virtual", "channel": rig.channels["can0"],
                          "receive_timeout": 0.05}}})
    rig.hardware.append(new)
    new.configure()
    new.activate(now())
    assert emulator.enabled(1) and emulator.error_code(1) == 0


def test_a_motor_that_does_not_confirm_its_timeout_fails_activation(rig: Rig) -> None:
    emulator = rig.emulate("can0", [1, 2], "DM4310", master_id=0x11)
    hw = rig.make(joints=["a", "b"], ids=[1, 2], model="DM4310", master_id=0x11)
    hw.configure()
    emulator.set_silent(2)
    with pytest.raises(CommunicationError) as caught:
        hw.activate(now())
    message = str(caught.value)
    assert "\n" not in message
    assert "no answer from motor 2 (joint 'b')" in message
    assert "CAN timeout (register 9) to 1000 ms: it cannot stop by itself" in message
    assert not emulator.enabled(1)  # nothing was enabled


def test_the_python_can_traceback_never_reaches_a_message() -> None:
    # The real socketcand client against an emulator process killed mid-run (SIGKILL: its
    # sockets are reset): python-can raises errors whose text carries a whole traceback;
    # every message the driver makes stays one line, and every motor is marked faulted.
    proc = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw.drivers.can.emulator", "--ids", "1-3",
         "--socketcand-port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL, text=True,
        cwd=ROOT, env=daemon_env(),
    )
    assert proc.stdout is not None
    try:
        fields = dict(kv.split("=", 1) for kv in proc.stdout.readline().split())
        hw = MitHardware("leg", ["a", "b", "c"], ["position"], ["position", "velocity"], {
            "buses": {"can0": {"interface": "socketcand", "host": "127.0.0.1",
                               "port": int(fields["port"]), "channel": "can0",
                               "receive_timeout": 0.05}},
            "ids": [1, 2, 3], "feedback_timeout": 0.2,
        })
        try:
            hw.configure()
            hw.activate(now())
            # Frames the process never reads when it dies: the kernel resets the connection.
            proc.send_signal(signal.SIGSTOP)
            hw.write(now(), JointCommand(positions=[0.0, 0.0, 0.0]))
            proc.kill()
            proc.wait(timeout=WAIT_S)
            with pytest.raises(CommunicationError, match="Connection reset") as caught:
                hw.read(now())
            messages = [str(caught.value)] + [str(run_until_fault(hw)) for _ in range(3)]
            try:
                hw.deactivate(now())
            except HardwareError as exc:
                messages.append(str(exc))
            messages.append(str(hw.status()["last_fault"]))
            assert all("\n" not in m and "Traceback" not in m for m in messages), messages
            faults = hw.status()["details"]["motors"]
            assert all(faults[j]["fault"] for j in ("a", "b", "c")), faults
        finally:
            hw.shutdown(now())
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=WAIT_S)
        proc.stdout.close()


def test_the_shipped_configurations_load() -> None:
    from jtc_hw.daemon.robot import create_hardware_set, load_robot

    for name, timeout_s in (("can-mit-leg.yaml", None), ("can-mit-leg-emulated.yaml", None),
                            ("can-mit-dm-emulated.yaml", 0.1)):
        (component,) = create_hardware_set(load_robot(ROOT / "config" / name)).components
        assert isinstance(component, MitHardware)
        watchdog = component.device_watchdog()
        assert watchdog.timeout_s == timeout_s, name
        assert watchdog.complete == (timeout_s is not None), name
