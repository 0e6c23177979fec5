"""``HardwareInterface.monitor``: reads while INACTIVE only, never raises, and after a failed
read waits ``MONITOR_RETRY_NS`` before the next (a device silent while faulted must not cost
every cycle its reply timeout). ``HardwareSet.monitor`` assembles the components' readings."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from jtc_hw.controller.joints import JointCommand, JointState
from jtc_hw.errors import CommunicationError
from jtc_hw.hardware import HardwareSet
from jtc_hw.hardware.interface import MONITOR_RETRY_NS, HardwareInterface

S = 1_000_000_000


class Monitored(HardwareInterface):
    kind: ClassVar[str] = "monitored"

    def __init__(self, name: str, joints: list[str], value: float) -> None:
        super().__init__(name, joints, ["position"], ["position"], {})
        self.value = value
        self.silent = False
        self.calls: list[int] = []

    def _read(self, now_ns: int) -> JointState:
        return JointState(np.full(len(self.joints), self.value))

    def _write(self, now_ns: int, command: JointCommand) -> None:
        pass

    def _monitor(self, now_ns: int) -> JointState | None:
        self.calls.append(now_ns)
        if self.silent:
            raise CommunicationError(f"{self.name}: no reply")
        return self._read(now_ns)


def test_monitor_reads_only_while_inactive_and_backs_off_after_a_failure() -> None:
    hw = Monitored("m", ["a", "b"], 0.5)
    assert hw.monitor(0) is None and hw.calls == []  # unconfigured: nothing sent
    hw.configure()
    hw.activate(0)
    assert hw.monitor(1) is None and hw.calls == []  # active: the cycle reads, not monitor
    hw.deactivate(2)
    state = hw.monitor(3)
    assert state is not None and state.positions.tolist() == [0.5, 0.5]
    hw.silent = True
    assert hw.monitor(4) is None  # failed: counted, not raised
    assert hw.status()["counters"]["read_errors"] == 1
    assert hw.monitor(4 + MONITOR_RETRY_NS - 1) is None
    assert hw.calls == [3, 4]  # not tried again within the back-off
    hw.silent = False
    assert hw.monitor(4 + MONITOR_RETRY_NS) is not None
    assert hw.monitor(5 + MONITOR_RETRY_NS) is not None  # success: every cycle again
    assert hw.calls == [3, 4, 4 + MONITOR_RETRY_NS, 5 + MONITOR_RETRY_NS]


def test_a_hardware_set_monitors_its_components_in_the_controllers_joint_order() -> None:
    left, right = Monitored("l", ["a"], 1.0), Monitored("r", ["b"], 2.0)
    hardware = HardwareSet([left, right], ["b", "a"])
    assert hardware.monitor(0) is None  # neither configured
    hardware.configure()
    right.silent = True
    state = hardware.monitor(S)
    assert state is not None
    assert np.isnan(state.positions[0]) and state.positions[1] == 1.0  # b not read
    right.silent = False
    again = hardware.monitor(3 * S)
    assert again is not None and again.positions.tolist() == [2.0, 1.0]
