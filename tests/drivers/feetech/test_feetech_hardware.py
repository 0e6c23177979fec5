"""The ``feetech`` hardware and its bus, called directly, on an emulator in this process.

The emulator's thread answers at a real-time priority where permitted (as servos answer
whatever the host's load); the driver is Feetech's SDK through :mod:`jtc_hw.drivers.feetech.bus`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from helpers.hardware_threads import start_as_hardware

from jtc_hw.drivers.feetech.codec import StatusError
from jtc_hw.drivers.feetech.emulator import FeetechEmulator
from jtc_hw.errors import CommunicationError, ConfigurationError, MotorFault
from jtc_hw.hardware import JointCommand, SafeAction, create_hardware
from jtc_hw.hardware.registry import HardwareSpec

pytest.importorskip("scservo_sdk", reason="feetech-servo-sdk (jtc_hw[feetech]) is missing")
from jtc_hw.drivers.feetech import control_table as ct  # noqa: E402
from jtc_hw.drivers.feetech.bus import FeetechBus, ServoCommunicationError  # noqa: E402
from jtc_hw.drivers.feetech.hardware import FeetechHardware  # noqa: E402

pytestmark = pytest.mark.usefixtures("no_leaks")

IDS = [1, 2, 3]
JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex"]
START = {1: 2048 + 200, 2: 2048 - 300, 3: 2048 + 500}
STEP = 2 * math.pi / 4096
#: Generous: the emulator shares this process with the test on a possibly busy machine; no test
#: here is about how soon a silence is noticed.
TIMEOUT_MS = 250.0
WAIT_S = 10.0


def now_ns() -> int:
    return time.monotonic_ns()


def emulator(ids: list[int], model: str = "STS3215", **kwargs: Any) -> FeetechEmulator:
    emu = FeetechEmulator(ids, model, **kwargs)
    start_as_hardware(emu.start)
    return emu


@pytest.fixture
def emu() -> Iterator[FeetechEmulator]:
    with emulator(IDS, initial_positions=START) as e:
        yield e


@pytest.fixture
def make(emu: FeetechEmulator) -> Iterator[Callable[..., FeetechHardware]]:
    made: list[FeetechHardware] = []

    def build(**params: Any) -> FeetechHardware:
        base: dict[str, Any] = {"port": emu.device_path, "ids": IDS, "offset": -math.pi,
                                "timeout_ms": TIMEOUT_MS}
        base.update(params)
        hw = FeetechHardware("arm", JOINTS, ("position",), ("position", "velocity"), base)
        made.append(hw)
        return hw

    yield build
    for hw in made:
        try:
            hw.shutdown(now_ns())
        except Exception:  # noqa: BLE001 - a test that broke the bus on purpose
            pass


def joint(steps: int) -> float:
    return (steps - 2048) * STEP


def served(hw: FeetechHardware) -> None:
    """Return once the emulator has served everything sent before: a Sync Write has no reply,
    but a read of servo 1 behind it is answered only after it (one wire, served in order)."""
    assert hw.bus is not None
    hw.bus.read_bytes(IDS[0], 56, 2)


def test_the_kind_is_registered_and_refuses_bad_parameters() -> None:
    spec = HardwareSpec("arm", "feetech", ("a",), ("position",), ("position", "velocity"),
                        {"port": "/dev/null", "ids": [1], "offset": -math.pi})
    assert isinstance(create_hardware(spec), FeetechHardware)
    with pytest.raises(ConfigurationError, match="each joint needs its own servo"):
        FeetechHardware("arm", ["a", "b"], ("position",), ("position",),
                        {"port": "/dev/null", "ids": [1, 1]})
    with pytest.raises(ConfigurationError, match="different byte orders"):
        FeetechHardware("arm", ["a", "b"], ("position",), ("position",),
                        {"port": "/dev/null", "ids": [1, 2], "model": ["STS3215", "SCS0009"]})
    with pytest.raises(ConfigurationError, match="outside the servo's 0..4095; adjust offset"):
        FeetechHardware("arm", ["a"], ("position",), ("position",),
                        {"port": "/dev/null", "ids": [1], "position_limits": [[-1.0, 1.0]]})
    assert FeetechHardware.schema()["baud_rate"].default == 1_000_000
    assert "watchdog_s" not in FeetechHardware.schema()  # there is none to arm


def test_read_write_and_the_profile_left_to_the_trajectory(
    make: Callable[..., FeetechHardware], emu: FeetechEmulator
) -> None:
    hw = make()
    hw.configure()
    for i in IDS:  # no ramp, the servo's top speed; nothing stored in EEPROM
        assert emu.register(i, "acceleration") == 0 and emu.register(i, "goal_velocity") == 0
        assert emu.register(i, "return_delay_time") == 0
        assert emu.stored_register(i, "return_delay_time") == 250
    held = hw.activate(now_ns())
    assert held.positions == pytest.approx([joint(START[i]) for i in IDS], abs=1e-9)
    assert all(emu.register(i, "torque_enable") == 1 for i in IDS)
    state = hw.read(now_ns())
    assert state.positions == pytest.approx([joint(START[i]) for i in IDS], abs=1e-9)
    target = np.array([0.1, -0.2, 0.3])
    hw.write(now_ns(), JointCommand(target, None, None, None))
    served(hw)
    assert [emu.register(i, "goal_position") for i in IDS] == [
        round(t / STEP) + 2048 for t in target]
    deadline = time.monotonic() + WAIT_S
    while not np.allclose(hw.read(now_ns()).positions, target, atol=2 * STEP):
        assert time.monotonic() < deadline, hw.last_positions
    health = hw.health()
    assert [m["motor"] for m in health["motors"]] == IDS
    assert health["bus"]["timeouts"] == 0


def test_a_failed_read_raises_and_never_becomes_a_command(
    make: Callable[..., FeetechHardware], emu: FeetechEmulator
) -> None:
    """Servo 2 falls silent: the read raises naming it, the last good positions stay as they
    were, and the hold that follows sends servo 2 nothing (it keeps its last goal, the last
    command) and the others where they stand: no stale or zero position reaches a servo."""
    hw = make()
    hw.configure()
    hw.activate(now_ns())
    before = hw.read(now_ns()).positions
    last_goal = emu.register(2, "goal_position")
    emu.set_silent(2, True)
    with pytest.raises(CommunicationError, match=r"servo 2 \(joint 'shoulder_lift'\).*"
                                                 r"after 2 attempts: timeout \(no reply\)"):
        hw.read(now_ns())
    assert hw.last_positions == pytest.approx(before, abs=0.0)
    hw.deactivate(now_ns())  # hold
    served(hw)
    assert emu.register(2, "goal_position") == last_goal
    for i in (1, 3):
        assert abs(emu.register(i, "goal_position") - emu.positions()[i]) <= 2
    assert hw.health()["bus"]["retries"] >= 1


def test_overload_is_a_motor_fault_and_a_rearm_switches_the_servo_back_on(
    make: Callable[..., FeetechHardware], emu: FeetechEmulator
) -> None:
    hw = make()
    hw.configure()
    hw.activate(now_ns())
    emu.block(3)
    hw.write(now_ns(), JointCommand(np.array([joint(START[i]) + 0.3 for i in IDS]),
                                    None, None, None))
    emu.wait_protection(3, StatusError.OVERLOAD, timeout_s=WAIT_S)
    with pytest.raises(MotorFault, match=r"servo 3 \(joint 'elbow_flex'\): overload"):
        hw.read(now_ns())
    hw.deactivate(now_ns())
    assert "overload" in hw.status()["details"]["servos"]["3"]["fault"]
    with pytest.raises(MotorFault, match="servo 3"):
        hw.activate(now_ns())  # only a rearm clears it
    emu.block(3, False)
    hw.recover()
    hw.activate(now_ns())
    assert emu.register(3, "torque_enable") == 1 and emu.register(3, "status") == 0


def test_an_overheated_servo_is_refused_by_the_rearm_until_it_cools(
    make: Callable[..., FeetechHardware], emu: FeetechEmulator
) -> None:
    hw = make(safe_action="torque_off")
    hw.configure()
    hw.activate(now_ns())
    emu.set_temperature(1, 75.0)
    with pytest.raises(MotorFault, match=r"servo 1 \(joint 'shoulder_pan'\): overheating"):
        hw.read(now_ns())
    hw.deactivate(now_ns())  # torque_off
    assert [emu.register(i, "torque_enable") for i in IDS] == [0, 0, 0]
    with pytest.raises(MotorFault, match="still reports overheating"):
        hw.recover()
    emu.set_temperature(1, 40.0)
    hw.recover()
    hw.activate(now_ns())
    assert [emu.register(i, "torque_enable") for i in IDS] == [1, 1, 1]


# -- the bus's traps ---------------------------------------------------------------------------


def test_the_sdks_process_global_byte_order_does_not_reach_our_words() -> None:
    """A second bus of SCS servos makes PacketHandler(1), which flips the SDK's global byte
    order; the STS bus made before still reads its model numbers and positions right."""
    with emulator([1, 2], "STS3215", initial_positions={1: 1000, 2: 3000}) as sts, \
            emulator([1, 2], "SCS0009", initial_positions={1: 100, 2: 900}) as scs:
        sts_bus = FeetechBus(sts.device_path, 1_000_000, ct.STS_SMS, timeout_ms=TIMEOUT_MS)
        scs_bus = FeetechBus(scs.device_path, 1_000_000, ct.SCS, timeout_ms=TIMEOUT_MS)
        sts_bus.open()
        scs_bus.open()
        try:
            assert [sts_bus.ping(i) for i in (1, 2)] == [777, 777]
            assert [scs_bus.ping(i) for i in (1, 2)] == [1284, 1284]
            sts_read = sts_bus.group_read([1, 2], 56, 2)
            assert [int.from_bytes(sts_read.data[i], "little") for i in (1, 2)] == [1000, 3000]
            # SCS: no Sync Read; read one at a time, big-endian words.
            scs_read = scs_bus.group_read([1, 2], 56, 2)
            assert [int.from_bytes(scs_read.data[i], "big") for i in (1, 2)] == [100, 900]
            assert scs.stats()["packets_served"] >= 4
        finally:
            sts_bus.close()
            scs_bus.close()


def test_a_group_read_is_all_or_nothing_and_names_the_silent_servo(
    emu: FeetechEmulator,
) -> None:
    bus = FeetechBus(emu.device_path, 1_000_000, ct.STS_SMS, timeout_ms=TIMEOUT_MS)
    bus.open()
    try:
        assert set(bus.group_read(IDS, 56, 2).data) == set(IDS)
        emu.set_silent(2, True)
        with pytest.raises(ServoCommunicationError, match="servo 2 .*timeout") as info:
            bus.group_read(IDS, 56, 2)
        assert info.value.servo_id == 2
        emu.set_silent(2, False)
        emu.corrupt_checksum(3, 1)
        with pytest.raises(ServoCommunicationError, match="servo 3 .*corrupt"):
            bus.group_read(IDS, 56, 2)
        # A late reply is not taken for the next request's answer.
        assert set(bus.group_read(IDS, 56, 2).data) == set(IDS)
        assert bus.stats.timeouts == 1 and bus.stats.checksum_errors == 1
    finally:
        bus.close()


def test_a_hold_reads_fresh_positions(
    make: Callable[..., FeetechHardware], emu: FeetechEmulator
) -> None:
    """Deactivated mid-move, the servos are given where they stand, read at that moment, not
    the last command nor the last position the loop read."""
    hw = make()
    hw.configure()
    hw.activate(now_ns())
    hw.read(now_ns())
    move = round(1.5 / STEP)
    hw.write(now_ns(), JointCommand(np.array([joint(START[i] + move) for i in IDS]),
                                    None, None, None))
    deadline = time.monotonic() + WAIT_S
    while abs(emu.positions()[1] - START[1]) < 100:  # under way
        assert time.monotonic() < deadline
        time.sleep(0.002)  # watching the emulated motor move
    hw.deactivate(now_ns())
    served(hw)
    assert hw.safe_action is SafeAction.HOLD
    goals = {i: emu.register(i, "goal_position") for i in IDS}
    assert all(START[i] + 50 < goals[i] < START[i] + move for i in IDS), goals
    deadline = time.monotonic() + WAIT_S
    while any(abs(emu.positions()[i] - goals[i]) > 2 for i in IDS):  # and stay there
        assert time.monotonic() < deadline, (emu.positions(), goals)
        time.sleep(0.005)  # watching the emulated motors come to rest


def test_health_reports_temperature_voltage_status_and_warns_at_temperature_warn_c(
    make: Callable[..., FeetechHardware], emu: FeetechEmulator
) -> None:
    hw = make(health_period_s=0.05, temperature_warn_c=60.0, voltage_range=[11.0, 13.0])
    hw.configure()
    hw.activate(now_ns())
    emu.set_temperature(2, 65.0)  # warm, below the servo's own 70 degC protection
    emu.set_supply_voltage(3, 15.0)  # above its Max Input Voltage (14 V): the voltage bit
    command = JointCommand(hw.read(now_ns()).positions, None, None, None)
    deadline = time.monotonic() + WAIT_S
    while True:
        hw.write(now_ns(), command)  # the health block is read after a write, when due
        motors = {m["motor"]: m for m in hw.health()["motors"]}
        if motors[2]["temperature_c"] == 65 and motors[3]["voltage_v"] == 15.0:
            break
        assert time.monotonic() < deadline, motors
        time.sleep(0.01)  # the next health slot
    warnings = hw.health()["warnings"]
    assert any("motor 2 (joint 'shoulder_lift'): temperature 65 degC" in w for w in warnings)
    assert any("motor 3 (joint 'elbow_flex'): supply 15 V outside" in w for w in warnings)
    assert motors[3]["errors"] == ["status: input voltage out of range"]
    assert motors[1]["temperature_c"] == 35 and motors[1]["voltage_v"] == 12.0
    assert motors[1]["current_a"] is not None and motors[1]["stale"] is False
    hw.read(now_ns())  # the voltage bit is a warning, no fault: the servo keeps driving
    assert hw.health()["bus"]["crc_errors"] == 0


def test_scs_servos_big_endian_and_read_one_at_a_time() -> None:
    """SCS0009: 1024 steps over 300 degrees, big-endian words, no Sync Read."""
    with emulator([1, 2], "SCS0009", initial_positions={1: 512, 2: 700}) as scs:
        step = ct.MODELS["SCS0009"].rad_per_step
        hw = FeetechHardware("hand", ["a", "b"], ("position",), ("position", "velocity"),
                             {"port": scs.device_path, "ids": [1, 2], "model": "SCS0009",
                              "offset": -512 * step, "timeout_ms": TIMEOUT_MS})
        try:
            hw.configure()
            hw.activate(now_ns())
            assert hw.read(now_ns()).positions == pytest.approx([0.0, 188 * step], abs=1e-9)
            served_before = scs.stats()["packets_served"]
            hw.read(now_ns())
            assert scs.stats()["packets_served"] - served_before == 2  # one READ per servo
            target = np.array([0.2, -0.2])
            hw.write(now_ns(), JointCommand(target, None, None, None))
            deadline = time.monotonic() + WAIT_S
            while not np.allclose(hw.read(now_ns()).positions, target, atol=2 * step):
                assert time.monotonic() < deadline, hw.last_positions
        finally:
            hw.shutdown(now_ns())
