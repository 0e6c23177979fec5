"""How the CAN drivers tell a full transmit queue from an interface that is gone, on the host.

The kernel-side versions (``ip link set vcan0 down``, a qdisc that cannot drain) are in
``tests/drivers/can/test_vcan_hil.py`` and run inside the VM (``tools/vcan-hil``). Here python-can's
``virtual`` bus stands for the interface: a peer with room for one frame that never reads
makes every send raise ``can.CanOperationError``, as a full queue does.
"""

from __future__ import annotations

import errno
import math
import time
import uuid
from collections.abc import Iterator

import can
import pytest

from jtc_hw.controller.joints import JointCommand
from jtc_hw.drivers.can.bus import BUS_FIELDS, BusHealth, BusSettings, full_queue, send
from jtc_hw.drivers.can.mit.emulator import MitBusEmulator
from jtc_hw.drivers.can.mit.hardware import MitHardware
from jtc_hw.errors import CommunicationError

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

JOINTS = [f"j{i}" for i in range(1, 4)]
IDS = [1, 2, 3]


class RefusingBus(can.BusABC):
    """A python-can bus whose sends fail as python-can's socketcan interface reports it:
    ``CanOperationError`` carrying the errno of the failed ``send(2)``."""

    def __init__(self, code: int | None) -> None:
        super().__init__(channel="refusing")
        self.code = code

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("Failed to transmit", self.code)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


def health() -> BusHealth:
    fields = {k: v.default for k, v in BUS_FIELDS.items() if k != "options"}
    return BusHealth(BusSettings(name="can0", **fields))


@pytest.mark.parametrize("code", [errno.ENOBUFS, None])
def test_a_full_queue_is_counted_and_named(code: int | None) -> None:
    bus, h = RefusingBus(code), health()
    try:
        msg = can.Message(arbitration_id=1, data=bytes(8), is_extended_id=False)
        assert full_queue(h) is None
        assert send(bus, msg, h) is False
        assert send(bus, msg, h) is False
        assert (h.tx_overflows, h.unsent) == (2, 2)
        why = full_queue(h)
        assert why is not None and "transmit queue of bus 'can0'" in why
        assert "2 frames refused in a row" in why
    finally:
        bus.shutdown()


@pytest.mark.parametrize("code", [errno.ENETDOWN, errno.ENODEV, errno.ENXIO])
def test_an_interface_that_is_down_or_gone_is_an_error_not_a_full_queue(code: int) -> None:
    bus, h = RefusingBus(code), health()
    try:
        with pytest.raises(can.CanOperationError):
            send(bus, can.Message(arbitration_id=1, data=bytes(8), is_extended_id=False), h)
        assert (h.tx_overflows, h.unsent) == (0, 0)
    finally:
        bus.shutdown()


@pytest.fixture
def channel() -> Iterator[str]:
    yield f"send-errors-{uuid.uuid4().hex}"


def test_a_queue_that_stays_full_is_the_named_cause_of_the_no_feedback_fault(
    channel: str,
) -> None:
    """Frames that never get out reach no motor: the motors fall silent, and the fault says
    why (the queue), not "check its power"."""
    motors = can.Bus(interface="virtual", channel=channel)
    emulator = MitBusEmulator(motors, IDS, "AK80-9")
    emulator.start()
    hw = MitHardware("leg", JOINTS, ("position",), ("position", "velocity"), {
        "ids": IDS, "feedback_timeout": 0.05,
        "buses": {"can0": {"interface": "virtual", "channel": channel,
                           "receive_timeout": 0.01}},
    })
    jam: can.BusABC | None = None
    try:
        hw.configure()
        hw.activate(time.monotonic_ns())
        # The queue fills and the frames stop reaching the motors (silent from now on).
        for motor_id in IDS:
            emulator.set_silent(motor_id)
        jam = can.Bus(interface="virtual", channel=channel, rx_queue_size=1)
        deadline = time.monotonic() + 5.0
        with pytest.raises(CommunicationError) as caught:
            while time.monotonic() < deadline:
                hw.write(time.monotonic_ns(), JointCommand(positions=[math.nan] * 3))
                hw.read(time.monotonic_ns())
        message = str(caught.value)
        assert "no feedback from motor" in message
        assert "the transmit queue of bus 'can0' (virtual" in message, message
        assert "check its power" not in message
        assert hw.status()["details"]["buses"]["can0"]["unsent"] > 0
    finally:
        if jam is not None:
            jam.shutdown()
        try:
            hw.shutdown(time.monotonic_ns())
        finally:
            emulator.stop()
            motors.shutdown()
