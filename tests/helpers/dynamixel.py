"""A three-servo Dynamixel arm on the pty emulator, for the driver's in-process tests."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any

from helpers.hardware_threads import start_as_hardware
from jtc_hw.drivers.dynamixel.emulator import DynamixelEmulator
from jtc_hw.drivers.dynamixel.hardware import DynamixelHardware

IDS = [1, 2, 3]
JOINTS = ["shoulder", "elbow", "wrist"]
TICK = 2 * math.pi / 4096
OFFSET = -math.pi  # tick 2048 (mid-range of Position mode, pi) is joint 0
START = {1: math.pi + 0.2, 2: math.pi - 0.3, 3: math.pi + 0.5}  # motor rad
WAIT_S = 10.0


DAEMON_TEST_TIMEOUT_MS = 1000.0
"""``timeout_ms`` of a daemon driving the emulator of a test: the emulator is a thread of the
test's process, and ``.ci/run`` runs two suites side by side on 2 cores, so a reply may wait
for that thread to be scheduled (100 ms once timed out twice in a row there, faulting a shared
daemon and the tests after it). At SCHED_FIFO (:func:`servos_as_hardware`) the thread is
scheduled at once, but it still needs the GIL, which a normally scheduled thread of the test
(its client's reader, its main thread) may hold while a busy host has it descheduled: beside
two busy processes, 250 ms timed out twice in a row (tools/ci-under-load, issue 22). A
servo's answer cannot be faster than the interpreter it runs in lets it be; real servos
answer within the 5 ms default, and no test using this value is about how soon a silent servo
is noticed."""


DRIVER_TEST_TIMEOUT_MS = 250.0
"""``timeout_ms`` of a driver a test calls directly (:func:`driver_factory`): the test's
thread waits in the driver's read with the GIL released, so the emulator's thread only waits
for the host to schedule it (see :data:`DAEMON_TEST_TIMEOUT_MS`). Shorter than the daemon
tests' value, so that a silent servo's two attempts end before the 1 s Bus Watchdog."""


def now_ns() -> int:
    return time.monotonic_ns()


def servos_as_hardware(ids: list[int], **kwargs: Any) -> DynamixelEmulator:
    """A started :class:`DynamixelEmulator` (use it with ``with``) whose thread answers at a
    real-time priority (:func:`start_as_hardware`), as servos do whatever the host's load.

    Normally scheduled, it shares this process and a busy host with the test and the daemon:
    in CI a daemon's goal aborted on a 0.103 rad path error at 1 rad/s, the servo's position
    read ~100 ms late (issue 22).
    """
    emu = DynamixelEmulator(ids, **kwargs)
    start_as_hardware(emu.start)
    return emu


def emulated_arm() -> Iterator[DynamixelEmulator]:
    """The servos at ``START`` (a fixture body: ``yield from emulated_arm()``), answering at
    a real-time priority (:func:`start_as_hardware`), as servos do whatever the host's load:
    the driver tests read with short timeouts, which a normally scheduled emulator thread
    missed on a busy host (issue 22)."""
    with servos_as_hardware(IDS, initial_positions=START) as emu:
        yield emu


def driver_factory(emulator: DynamixelEmulator) -> Iterator[Callable[..., DynamixelHardware]]:
    """Build drivers on the emulator's pty, each shut down afterwards (a fixture body)."""
    made: list[DynamixelHardware] = []

    def make(
        command_interfaces: tuple[str, ...] = ("position",),
        joints: list[str] = JOINTS,
        **params: Any,
    ) -> DynamixelHardware:
        base: dict[str, Any] = {
            "port": emulator.device_path,
            "baud_rate": 4_000_000,
            "ids": IDS[: len(joints)],
            "offset": OFFSET,
            # Generous: the emulator shares this process (and the GIL) with the test, and a
            # busy host delays its thread (30 ms timed out at a load average of 10: issue
            # 22). No test using this default is about how soon a silent servo is noticed.
            "timeout_ms": DRIVER_TEST_TIMEOUT_MS,
            "latency_timer_warn": False,
            # Long: a loaded machine pausing this process must not trip the servos' watchdog;
            # the tests that let it expire choose a short one.
            "watchdog_s": 1.0,
        }
        base.update(params)
        hw = DynamixelHardware("arm", joints, command_interfaces, ("position", "velocity"), base)
        made.append(hw)
        return hw

    yield make
    for hw in made:
        try:
            hw.shutdown(now_ns())
        except Exception:  # noqa: BLE001 - a test that broke the bus on purpose
            pass
