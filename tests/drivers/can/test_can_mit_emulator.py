"""The MIT emulator's device-side timeout per model, its register protocol, power cycles and
events: raw frames from a peer on a python-can virtual bus (what a host sends), the emulator
answering as the firmware does.

Timeouts are checked at chosen instants (``check_timeouts(now)``) bounded by the times the
test observed around its frames, so nothing depends on how fast this machine runs.
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from helpers.can_emulator import control
from helpers.daemon import WAIT_S, daemon_env

from jtc_hw.drivers.can.mit.codec import (
    CLEAR_ERROR,
    ENTER_MOTOR_MODE,
    EXIT_MOTOR_MODE,
    MODEL_PRESETS,
    REGISTER_ID,
    REGISTER_READ,
    REGISTER_WRITE,
    MitCommand,
    RegisterFrame,
    decode_register_frame,
    decode_reply,
    encode_command,
    encode_register_frame,
    timeout_register_value,
)
from jtc_hw.drivers.can.mit.emulator import EmulatorEvent, MitBusEmulator

from conftest import ROOT

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

DM = MODEL_PRESETS["DM4310"]
AK = MODEL_PRESETS["AK80-9"]
MASTER = 0x11


class Host:
    """The host's side of a virtual bus with one emulator on it."""

    def __init__(self, ids: list[int], model: str, **kw: Any) -> None:
        channel = f"mit-emu-{uuid.uuid4().hex}"
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.peer = can.Bus(interface="virtual", channel=channel)
        self.events: list[EmulatorEvent] = []
        self.emulator = MitBusEmulator(self.peer, ids, model, on_event=self.events.append,
                                       **kw)
        self.emulator.start()

    def send(self, arbitration_id: int, data: bytes) -> can.Message | None:
        """Send one frame; the reply (``None`` if none came within a short wait)."""
        self.bus.send(can.Message(arbitration_id=arbitration_id, is_extended_id=False,
                                  data=data))
        return self.bus.recv(timeout=0.2)

    def motor(self, motor_id: int, data: bytes) -> can.Message:
        reply = self.send(motor_id, data)
        assert reply is not None, f"motor {motor_id} did not answer"
        return reply

    def register(self, frame: RegisterFrame) -> RegisterFrame | None:
        reply = self.send(REGISTER_ID, encode_register_frame(frame))
        if reply is None:
            return None
        assert reply.arbitration_id == MASTER
        return decode_register_frame(reply.data)

    def close(self) -> None:
        self.emulator.stop()
        assert self.emulator.error is None, f"the emulator failed: {self.emulator.error!r}"
        self.peer.shutdown()
        self.bus.shutdown()


@pytest.fixture
def damiao() -> Iterator[Host]:
    host = Host([1, 2], "DM4310", master_id=MASTER)
    try:
        yield host
    finally:
        host.close()


@pytest.fixture
def ak() -> Iterator[Host]:
    host = Host([1], "AK80-9")
    try:
        yield host
    finally:
        host.close()


def hold(p: float = 0.0) -> bytes:
    return encode_command(MitCommand(p, 0.0, 30.0, 1.0, 0.0), DM)


def test_damiao_timeout_register_reads_and_writes(damiao: Host) -> None:
    read = damiao.register(RegisterFrame(1, REGISTER_READ, 9))
    assert read == RegisterFrame(1, REGISTER_READ, 9, 0)  # stored: none
    counts = timeout_register_value(0.1)
    echo = damiao.register(RegisterFrame(1, REGISTER_WRITE, 9, counts))
    assert echo == RegisterFrame(1, REGISTER_WRITE, 9, counts)
    assert damiao.register(RegisterFrame(1, REGISTER_READ, 9)) == RegisterFrame(
        1, REGISTER_READ, 9, counts)
    assert damiao.emulator.timeout_s(1) == pytest.approx(0.1)
    assert damiao.emulator.timeout_s(2) == 0.0  # per motor
    assert damiao.register(RegisterFrame(2, REGISTER_READ, 7)) == RegisterFrame(
        2, REGISTER_READ, 7, MASTER)
    # Not modelled: a write to another register gets no echo (the host sees no confirmation).
    assert damiao.register(RegisterFrame(1, REGISTER_WRITE, 21, 20.0)) is None
    assert damiao.register(RegisterFrame(9, REGISTER_READ, 9)) is None  # no such motor


def test_damiao_disables_itself_when_its_timeout_expires(damiao: Host) -> None:
    emulator = damiao.emulator
    damiao.register(RegisterFrame(1, REGISTER_WRITE, 9, timeout_register_value(0.1)))
    assert decode_reply(damiao.motor(1, ENTER_MOTOR_MODE).data, DM).error_code == 1
    before = time.monotonic()
    damiao.motor(1, hold(0.2))
    after = time.monotonic()
    # Just short of the timeout after the last frame: still enabled.
    emulator.check_timeouts(before + 0.099)
    assert emulator.enabled(1) and emulator.timeout_expiries() == []
    # Past it: disabled, at last frame + timeout, and it says so.
    emulator.check_timeouts(after + 0.101)
    ((motor_id, t),) = emulator.timeout_expiries()
    assert motor_id == 1 and before + 0.1 - 1e-3 <= t <= after + 0.1 + 1e-3
    assert not emulator.enabled(1) and emulator.error_code(1) == 0xD
    assert emulator.enabled(2) is False and emulator.error_code(2) == 0  # never enabled
    kinds = [(e.kind, e.motor_id) for e in damiao.events]
    assert kinds == [("enabled", 1), ("timeout", 1), ("disabled", 1)]
    assert damiao.events[1].t == t == damiao.events[2].t
    # Latched: "enter motor mode" is refused until the error is cleared.
    assert decode_reply(damiao.motor(1, ENTER_MOTOR_MODE).data, DM).error_code == 0xD
    assert not emulator.enabled(1)
    damiao.motor(1, CLEAR_ERROR)
    assert decode_reply(damiao.motor(1, ENTER_MOTOR_MODE).data, DM).error_code == 1


def test_every_frame_to_the_motor_restarts_its_timeout(damiao: Host) -> None:
    emulator = damiao.emulator
    damiao.register(RegisterFrame(1, REGISTER_WRITE, 9, timeout_register_value(0.1)))
    damiao.motor(1, ENTER_MOTOR_MODE)
    before = time.monotonic()
    damiao.motor(1, hold(0.1))  # a set-point
    emulator.check_timeouts(before + 0.099)
    assert emulator.enabled(1)
    before = time.monotonic()
    damiao.register(RegisterFrame(1, REGISTER_READ, 9))  # a register request
    emulator.check_timeouts(before + 0.099)
    assert emulator.enabled(1)
    # A frame to another motor does not.
    before = time.monotonic()
    damiao.motor(2, EXIT_MOTOR_MODE)
    emulator.check_timeouts(time.monotonic() + 0.101)
    assert not emulator.enabled(1)
    ((_, t),) = emulator.timeout_expiries()
    assert t < before + 0.1


def test_a_disabled_motor_does_not_time_out(damiao: Host) -> None:
    damiao.register(RegisterFrame(1, REGISTER_WRITE, 9, timeout_register_value(0.05)))
    damiao.motor(1, ENTER_MOTOR_MODE)
    damiao.motor(1, EXIT_MOTOR_MODE)
    damiao.emulator.check_timeouts(time.monotonic() + 1.0)
    assert damiao.emulator.timeout_expiries() == [] and damiao.emulator.error_code(1) == 0


def test_ak_has_no_timeout_and_keeps_its_last_command(ak: Host) -> None:
    emulator = ak.emulator
    assert not emulator.has_timeout
    assert ak.send(REGISTER_ID, encode_register_frame(RegisterFrame(1, REGISTER_WRITE, 9, 2000))
                   ) is None  # no register protocol: not answered
    ak.motor(1, ENTER_MOTOR_MODE)
    ak.motor(1, encode_command(MitCommand(0.4, 0.0, 30.0, 1.0, 0.0), AK))
    emulator.check_timeouts(time.monotonic() + 30.0)
    assert emulator.enabled(1) and emulator.timeout_expiries() == []
    assert emulator.last_command(1).position == pytest.approx(0.4, abs=1e-3)
    assert emulator.position(1) == pytest.approx(0.4, abs=0.01)  # still holding it
    with pytest.raises(ValueError, match="only Damiao"):
        MitBusEmulator(ak.peer, [2], "AK80-9", stored_timeout_s=0.1)


def test_enter_motor_mode_keeps_the_set_point_of_an_enabled_motor(ak: Host) -> None:
    emulator = ak.emulator
    ak.motor(1, encode_command(MitCommand(0.4, 0.0, 30.0, 1.0, 0.0), AK))
    assert emulator.last_command(1).kp == 0.0  # out of motor mode: answered, not taken
    ak.motor(1, ENTER_MOTOR_MODE)
    assert emulator.last_command(1).kp == 0.0  # from rest: free until a set-point
    ak.motor(1, encode_command(MitCommand(0.4, 0.0, 30.0, 1.0, 0.0), AK))
    ak.motor(1, ENTER_MOTOR_MODE)
    assert emulator.last_command(1).kp == pytest.approx(30.0, abs=0.2)
    assert emulator.last_command(1).position == pytest.approx(0.4, abs=1e-3)


def test_power_cycle_leaves_motor_mode_and_restores_the_stored_registers() -> None:
    host = Host([1], "DM4310", master_id=MASTER, stored_timeout_s=0.2)
    try:
        emulator = host.emulator
        assert emulator.timeout_s(1) == pytest.approx(0.2)
        host.register(RegisterFrame(1, REGISTER_WRITE, 9, timeout_register_value(0.05)))
        host.motor(1, ENTER_MOTOR_MODE)
        host.motor(1, hold(0.3))
        emulator.power_cycle()
        assert not emulator.enabled(1)
        assert emulator.timeout_s(1) == pytest.approx(0.2)  # the RAM value is gone
        assert emulator.last_command(1).kp == 0.0
        state = decode_reply(host.motor(1, hold(0.3)).data, DM)
        assert state.error_code == 0 and not emulator.enabled(1)  # a set-point does not enable
        assert host.events[-1].kind == "disabled"
    finally:
        host.close()


def test_a_persistent_error_refuses_enabling_until_it_ends(damiao: Host) -> None:
    damiao.emulator.set_error(2, 0x9, persistent=True)
    damiao.motor(2, CLEAR_ERROR)
    assert decode_reply(damiao.motor(2, ENTER_MOTOR_MODE).data, DM).error_code == 0x9
    damiao.emulator.set_error(2, 0)
    assert decode_reply(damiao.motor(2, ENTER_MOTOR_MODE).data, DM).error_code == 1


def test_wait_timeout_expiries(damiao: Host) -> None:
    since = time.monotonic()
    for motor_id in (1, 2):
        damiao.register(RegisterFrame(motor_id, REGISTER_WRITE, 9, timeout_register_value(0.05)))
        damiao.motor(motor_id, ENTER_MOTOR_MODE)
    found = damiao.emulator.wait_timeout_expiries(since=since, timeout_s=WAIT_S)
    assert set(found) == {1, 2}
    assert all(since + 0.05 <= t <= time.monotonic() for t in found.values())
    with pytest.raises(TimeoutError, match=r"motors \[1\]"):
        damiao.emulator.wait_timeout_expiries([1], since=time.monotonic(), timeout_s=0.05)


# -- the process ----------------------------------------------------------------------------------


class Lines:
    """A process's stdout lines, read by a thread, taken with a deadline."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        self._stdout = proc.stdout
        self._queue: queue.Queue[str] = queue.Queue()
        self._thread = threading.Thread(target=self._read, name="emulator-stdout")
        self._thread.start()

    def _read(self) -> None:
        for line in self._stdout:
            self._queue.put(line)

    def next(self, timeout_s: float = WAIT_S) -> str:
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            raise AssertionError(f"no line within {timeout_s} s") from None

    def join(self) -> None:
        self._thread.join(WAIT_S)


def test_emulate_process_prints_events_with_the_modelled_expiry() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw.drivers.can.emulator", "--model", "DM4310", "--ids", "1",
         "--master-id", "0x11", "--socketcand-port", "0", "--events"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
        cwd=ROOT, env=daemon_env(),
    )
    lines = Lines(proc)
    try:
        fields = dict(kv.split("=", 1) for kv in lines.next().split())
        bus = can.Bus(interface="socketcand", host="127.0.0.1", port=int(fields["port"]),
                      channel="can0")
        try:
            bus.send(can.Message(arbitration_id=REGISTER_ID, is_extended_id=False, data=(
                encode_register_frame(RegisterFrame(1, REGISTER_WRITE, 9,
                                                    timeout_register_value(0.05))))))
            before = time.monotonic()
            bus.send(can.Message(arbitration_id=1, is_extended_id=False, data=ENTER_MOTOR_MODE))
            events = [json.loads(lines.next()) for _ in range(3)]
        finally:
            bus.shutdown()
        assert [(e["event"], e["channel"], e["id"]) for e in events] == [
            ("enabled", "can0", 1), ("timeout", "can0", 1), ("disabled", "can0", 1)]
        # The modelled instant (last frame + timeout), comparable with this process's clock.
        assert events[1]["t"] == events[2]["t"] >= before + 0.05 - 1e-3
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        lines.join()
        assert proc.stderr is not None
        proc.stderr.close()
        assert proc.stdout is not None
        proc.stdout.close()


def _until_answered(host: Host, motor_id: int, data: bytes) -> can.Message:
    """Send ``data`` until the motor answers (it is browned out meanwhile)."""
    deadline = time.monotonic() + WAIT_S
    while (reply := host.send(motor_id, data)) is None:
        assert time.monotonic() < deadline, f"motor {motor_id} never answered again"
    return reply


def test_brown_out_silences_the_motor_then_it_answers_disabled(damiao: Host) -> None:
    emulator = damiao.emulator
    for motor_id in (1, 2):
        assert damiao.motor(motor_id, ENTER_MOTOR_MODE).data[0] >> 4 == 1
    damiao.register(RegisterFrame(1, REGISTER_WRITE, 9, timeout_register_value(2.0)))
    before = time.monotonic()
    emulator.brown_out(1, 0.5)
    assert damiao.send(1, hold()) is None  # unpowered: deaf and silent
    assert damiao.motor(2, hold()).data[0] >> 4 == 1  # the other motor is not affected
    reply = _until_answered(damiao, 1, hold())
    # Back as after a power-up: the state nibble says disabled, the set-point was not taken.
    assert reply.data[0] >> 4 == 0 and reply.data[0] & 0x0F == 1
    assert not emulator.enabled(1) and emulator.enabled(2)
    assert emulator.timeout_s(1) == 0.0  # the RAM value is gone: the stored one (none)
    (restart,) = emulator.restarts(1)
    assert restart >= before + 0.5
    (first,) = emulator.first_replies_after_reset(1)
    assert first >= restart
    assert [(e.kind, e.motor_id) for e in damiao.events if e.motor_id == 1][-2:] == [
        ("disabled", 1), ("reset", 1)]
    assert damiao.motor(1, ENTER_MOTOR_MODE).data[0] >> 4 == 1  # a re-arm enables it
    with pytest.raises(ValueError, match="positive"):
        emulator.brown_out(1, 0.0)


def test_ak_brown_out_answers_as_before_but_out_of_motor_mode(ak: Host) -> None:
    ak.motor(1, ENTER_MOTOR_MODE)
    assert ak.emulator.enabled(1)
    ak.emulator.brown_out(1, 0.3)
    reply = _until_answered(ak, 1, encode_command(MitCommand(0.0, 0.0, 30.0, 1.0, 0.0), AK))
    # The AK reply has no state field: nothing in it tells the reset apart.
    assert len(reply.data) == 6 and reply.data[0] == 1
    assert not ak.emulator.enabled(1) and len(ak.emulator.restarts(1)) == 1


def test_emulate_process_browns_out_on_its_control_socket_and_on_fault(
    tmp_path: Path,
) -> None:
    path = tmp_path / "emulator.sock"
    proc = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw.drivers.can.emulator", "--model", "DM4310", "--ids", "1,2",
         "--master-id", "0x11", "--socketcand-port", "0", "--events", "--control", str(path),
         "--fault", "brownout:2:0.05@0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
        cwd=ROOT, env=daemon_env(),
    )
    lines = Lines(proc)
    try:
        lines.next()  # the connect line
        first = json.loads(lines.next())  # the scheduled one
        assert (first["event"], first["id"]) == ("reset", 2)
        assert control(path, "brownout 9 0.05").startswith("error: no motor 9")
        assert control(path, "reboot 1").startswith("error: unknown command")
        before = time.monotonic()
        assert control(path, "brownout 1 0.05") == "ok"
        event = json.loads(lines.next())
        assert (event["event"], event["channel"], event["id"]) == ("reset", "can0", 1)
        assert event["t"] >= before + 0.05 - 1e-3  # the modelled instant of the restart
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        lines.join()
        assert proc.stderr is not None
        proc.stderr.close()
        assert proc.stdout is not None
        proc.stdout.close()
    assert not path.exists()  # removed on exit


def test_bus_off_puts_its_error_frame_on_the_bus_before_it_falls_silent() -> None:
    """Issue 22: the host must never see the silence of a bus-off before its error frame, or
    its feedback_timeout can expire first (a caller descheduled between the two on a busy
    host) and the bus-off reads as silent motors. Observed where it cannot race: when the
    emulator's bus is handed the error frame, the motor must still answer."""
    channel = f"mit-emu-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    answered_at_error_frame: list[bool] = []

    class Wire(can.interfaces.virtual.VirtualBus):  # type: ignore[misc]
        """The emulator's side of the bus, asking the motor once as the error frame leaves."""

        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            if msg.is_error_frame:
                host.send(can.Message(arbitration_id=1, is_extended_id=False, data=hold()))
                reply = host.recv(timeout=WAIT_S)  # an upper bound on waiting only
                answered_at_error_frame.append(reply is not None)
            super().send(msg, timeout)

    wire = Wire(channel=channel)
    emulator = MitBusEmulator(wire, [1], "DM4310", master_id=MASTER)
    emulator.start()
    try:
        host.send(can.Message(arbitration_id=1, is_extended_id=False, data=ENTER_MOTOR_MODE))
        assert host.recv(timeout=WAIT_S) is not None
        emulator.bus_off()
        assert answered_at_error_frame == [True]
        error = host.recv(timeout=WAIT_S)
        assert error is not None and error.is_error_frame
        # Then silent, until the bus is back.
        host.send(can.Message(arbitration_id=1, is_extended_id=False, data=hold()))
        assert host.recv(timeout=0.2) is None
        emulator.clear_bus_off()
        host.send(can.Message(arbitration_id=1, is_extended_id=False, data=hold()))
        assert host.recv(timeout=WAIT_S) is not None
    finally:
        emulator.stop()
        assert emulator.error is None, f"the emulator failed: {emulator.error!r}"
        wire.shutdown()
        host.shutdown()
