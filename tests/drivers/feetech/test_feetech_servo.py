"""The emulated Feetech servo on a simulated clock: memory, EPROM lock, signs, protections.

No pty, no thread, no clock: every step is given its time, so the protections' timing is judged
on the servo's own stamps.
"""

from __future__ import annotations

import pytest

from jtc_hw.drivers.feetech import codec as fc
from jtc_hw.drivers.feetech import control_table as ct
from jtc_hw.drivers.feetech.servo import DEFAULTS, EmulatedServo

STS3215 = ct.MODELS["STS3215"]
SCS0009 = ct.MODELS["SCS0009"]


def servo(model: ct.Model = STS3215, position: int = 2048, servo_id: int = 1) -> EmulatedServo:
    return EmulatedServo(model, servo_id, position, now=0.0)


def write(s: EmulatedServo, name: str, value: int, now: float) -> None:
    """A WRITE of one register as the host sends it (the series' bytes)."""
    reg = s.series.register(name)
    s.write(reg.address, fc.encode_value(reg, value, s.series.byte_order), now)


def run(s: EmulatedServo, start: float, end: float, step: float = 0.005) -> float:
    t = start
    while t < end:
        t = min(end, t + step)
        s.step(t)
    return t


def test_power_on_memory_per_series_and_byte_order() -> None:
    sts, scs = servo(STS3215), servo(SCS0009, position=512)
    assert sts.read(3, 2) == bytes((0x09, 0x03))  # 777, little endian
    assert scs.read(3, 2) == bytes((0x05, 0x04))  # 1284, big endian
    assert sts.read(56, 2) == bytes((0x00, 0x08))  # 2048 mid-range
    assert scs.read(56, 2) == bytes((0x02, 0x00))  # 512 mid-range, big endian
    for s in (sts, scs):
        assert s.get("id") == 1 and s.get("baud_rate") == 0  # 1 Mbit/s
        assert s.get("return_delay_time") == 250 and s.return_delay_s() == pytest.approx(5e-4)
        assert s.get("torque_enable") == 0 and s.locked
        assert s.get("goal_position") == s.present_steps()
    assert sts.get("max_position_limit") == 4095 and scs.get("max_position_limit") == 1023
    assert DEFAULTS[ct.SeriesName.STS_SMS]["unloading_condition"] & fc.StatusError.OVERLOAD


def test_eeprom_writes_take_effect_and_are_stored_only_unlocked() -> None:
    for model, lock_address in ((STS3215, 55), (SCS0009, 48)):
        s = servo(model)
        assert s.series.lock_address == lock_address
        write(s, "max_position_limit", 3000, 0.0)  # locked: effective now ...
        assert s.get("max_position_limit") == 3000
        assert s.stored_value("max_position_limit") == model.position_max
        s.power_cycle(0.1)  # ... and gone after a power cycle
        assert s.get("max_position_limit") == model.position_max
        s.write(lock_address, bytes((0,)), 0.2)  # unlock
        write(s, "max_position_limit", 3000, 0.2)
        write(s, "id", 7, 0.2)
        assert s.id == 7
        s.power_cycle(0.3)
        assert s.get("max_position_limit") == 3000 and s.id == 7  # stored
        assert s.locked  # the lock itself is RAM: locked again after power-on


def test_read_only_registers_ignore_writes() -> None:
    s = servo()
    s.write(56, bytes((0x10, 0x00)), 0.0)  # Present Position
    s.write(3, bytes((0, 0)), 0.0)  # Model Number
    assert s.get("present_position") == 2048 and s.get("model_number") == 777


def test_position_loop_reaches_the_goal_within_its_speed_limit() -> None:
    s = servo()
    write(s, "torque_enable", 1, 0.0)
    write(s, "goal_velocity", 1000, 0.0)  # 1000 steps/s
    write(s, "goal_position", 2548, 0.0)
    t = run(s, 0.0, 0.25)
    s.refresh()
    assert 2048 < s.get("present_position") < 2548
    assert 900 <= s.get("present_velocity") <= 1010  # at its speed limit
    assert s.get("moving") == 1
    run(s, t, 1.0)
    s.refresh()
    assert abs(s.get("present_position") - 2548) <= 1 and s.get("moving") == 0


def test_sts_signs_are_sign_magnitude() -> None:
    s = servo()
    write(s, "torque_enable", 1, 0.0)
    write(s, "goal_position", 1548, 0.0)  # downward
    run(s, 0.0, 0.1)
    s.refresh()
    speed, load = s.get("present_velocity"), s.get("present_load")
    assert speed < 0
    raw_speed = int.from_bytes(s.read(58, 2), "little")
    assert raw_speed == 0x8000 | -speed  # sign in bit 15, magnitude below
    raw_load = int.from_bytes(s.read(60, 2), "little")
    assert raw_load == ((1 << 10) | -load if load < 0 else load)  # sign in bit 10
    assert raw_load < 1 << 11
    # Homing offset: sign in bit 11; Present = Actual - Homing_Offset.
    s.write(31, (0x0800 | 100).to_bytes(2, "little"), 0.2)  # -100
    assert s.get("homing_offset") == -100
    actual = round(s.motor.position / STS3215.rad_per_step)
    assert s.present_steps() == actual + 100


def test_scs_words_are_big_endian_with_the_scscl_direction_bits() -> None:
    s = servo(SCS0009, position=512)
    write(s, "torque_enable", 1, 0.0)
    write(s, "goal_position", 200, 0.0)
    run(s, 0.0, 0.05)
    s.refresh()
    speed = s.get("present_velocity")
    assert speed < 0
    assert int.from_bytes(s.read(58, 2), "big") == 0x8000 | -speed
    assert 200 < int.from_bytes(s.read(56, 2), "big") < 512
    assert "homing_offset" not in s.series.registers


def test_overload_switches_the_torque_off_after_protection_time() -> None:
    s = servo()
    write(s, "torque_enable", 1, 0.0)
    s.blocked = True
    write(s, "goal_position", 3000, 0.0)
    run(s, 0.0, 3.0, step=0.01)
    [event] = s.events
    assert event.error is fc.StatusError.OVERLOAD and event.torque_off
    # Protection Time 200 * 10 ms after the torque rose above Overload Torque (80 %): with no
    # speed limit the reference jumps to the goal, so the torque rises within the first step.
    assert 2.0 <= event.at_s < 2.02
    assert s.get("torque_enable") == 0
    assert s.status & fc.StatusError.OVERLOAD
    s.refresh()
    assert s.get("status") == fc.StatusError.OVERLOAD
    # Switching the torque on again clears it and holds where the shaft is.
    s.blocked = False
    write(s, "torque_enable", 1, 3.0)
    assert s.torque_on and not s.status
    assert s.get("goal_position") == s.present_steps()


def test_overload_without_unloading_limits_the_torque() -> None:
    s = servo()
    write(s, "unloading_condition", 0, 0.0)
    write(s, "torque_enable", 1, 0.0)
    s.blocked = True
    write(s, "goal_position", 3000, 0.0)
    run(s, 0.0, 2.5, step=0.01)
    [event] = s.events
    assert not event.torque_off and s.torque_on
    run(s, 2.5, 2.6, step=0.01)
    s.refresh()
    assert abs(s.get("present_load")) <= 200  # Protective Torque 20 %


def test_a_short_peak_is_not_an_overload() -> None:
    s = servo()
    write(s, "torque_enable", 1, 0.0)
    s.blocked = True
    write(s, "goal_position", 3000, 0.0)
    t = run(s, 0.0, 1.5, step=0.01)
    s.blocked = False  # the obstacle goes away before Protection Time
    run(s, t, 4.0, step=0.01)
    assert not s.events and s.torque_on


def test_overheat_unloads_until_cooled() -> None:
    s = servo()
    write(s, "torque_enable", 1, 0.0)
    s.set_temperature(75.0, 0.5)
    [event] = s.events
    assert (event.error, event.at_s, event.torque_off) == (fc.StatusError.OVERHEAT, 0.5, True)
    assert not s.torque_on
    write(s, "torque_enable", 1, 0.6)  # refused while hot
    assert not s.torque_on
    s.refresh()
    assert s.get("present_temperature") == 75 and s.get("status") == fc.StatusError.OVERHEAT
    s.set_temperature(60.0, 1.0)
    assert not s.status
    write(s, "torque_enable", 1, 1.1)
    assert s.torque_on


def test_voltage_out_of_range_is_reported_not_unloaded() -> None:
    s = servo()
    write(s, "torque_enable", 1, 0.0)
    s.set_supply(15.0, 0.1)  # Max Input Voltage 14.0 V
    assert s.status == fc.StatusError.VOLTAGE and s.torque_on
    s.refresh()
    assert s.get("present_voltage") == 150
    s.set_supply(12.0, 0.2)
    assert not s.status


def test_torque_on_holds_unless_the_same_write_gives_a_goal() -> None:
    s = servo()
    write(s, "goal_position", 3000, 0.0)  # torque off: kept, not acted on
    write(s, "torque_enable", 1, 0.1)
    assert s.get("goal_position") == 2048  # switched on where the shaft is
    write(s, "torque_enable", 0, 0.2)
    # Torque Enable (40), Acceleration (41) and Goal Position (42) in one write.
    s.write(40, bytes((1, 0)) + (2500).to_bytes(2, "little"), 0.3)
    assert s.torque_on and s.get("goal_position") == 2500
