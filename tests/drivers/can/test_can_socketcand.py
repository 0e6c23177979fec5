"""The socketcand server against python-can's stock ``socketcand`` client interface."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator

import can
import numpy as np
import pytest
from helpers.daemon import daemon_env

from jtc_hw.controller.joints import JointCommand
from jtc_hw.drivers.can.mit.codec import ENTER_MOTOR_MODE
from jtc_hw.drivers.can.mit.emulator import MitBusEmulator
from jtc_hw.drivers.can.mit.hardware import MitHardware
from jtc_hw.drivers.can.socketcand import SocketcandServer, format_frame, parse_send

from conftest import ROOT

pytestmark = pytest.mark.usefixtures("no_leaks")  # threads, sockets, resources

WAIT_S = 5.0


@pytest.fixture
def served() -> Iterator[tuple[SocketcandServer, str]]:
    """A server exposing channel ``can0`` as a fresh virtual channel."""
    virtual = f"scd-{uuid.uuid4().hex}"
    server = SocketcandServer(port=0, channels={"can0": virtual})
    server.start()
    try:
        yield server, virtual
    finally:
        server.stop()


def client(server: SocketcandServer, channel: str = "can0") -> can.BusABC:
    return can.Bus(interface="socketcand", host="127.0.0.1", port=server.port, channel=channel)


def wait_for(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} within {WAIT_S} s")
        time.sleep(0.01)  # polling state another thread changes; nothing to block on


def recv_data(bus: can.BusABC) -> can.Message:
    while True:
        msg = bus.recv(timeout=WAIT_S)
        assert msg is not None, "no frame"
        return msg


def test_codec_elements() -> None:
    msg = can.Message(arbitration_id=0x12, is_extended_id=False, data=b"\x01\xab",
                      timestamp=12.5)
    assert format_frame(msg) == "< frame 012 12.500000 01AB >"
    ext = can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, data=b"", timestamp=1.0)
    assert format_frame(ext) == "< frame 01ABCDEF 1.000000  >"
    sent = parse_send("< send 012 2 1 ab >")
    assert sent is not None and sent.arbitration_id == 0x12 and sent.data == b"\x01\xab"
    assert not sent.is_extended_id
    assert parse_send("< send 012 3 1 ab >") is None  # length mismatch
    assert parse_send("< open can0 >") is None


def test_frames_both_ways(served: tuple[SocketcandServer, str]) -> None:
    server, virtual = served
    peer = can.Bus(interface="virtual", channel=virtual)
    bus = client(server)
    try:
        bus.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02\x03"))
        got = peer.recv(timeout=WAIT_S)
        assert got is not None
        assert (got.arbitration_id, bytes(got.data), got.is_extended_id) == (
            0x123, b"\x01\x02\x03", False)
        peer.send(can.Message(arbitration_id=0x1FFFFFF0, is_extended_id=True, data=b"\xff" * 8))
        back = recv_data(bus)
        assert (back.arbitration_id, bytes(back.data), back.is_extended_id) == (
            0x1FFFFFF0, b"\xff" * 8, True)
        peer.send(can.Message(arbitration_id=0x40, is_error_frame=True, is_extended_id=True,
                              data=bytes(8)))
        error = recv_data(bus)
        assert error.is_error_frame and error.arbitration_id == 0x40
    finally:
        bus.shutdown()
        peer.shutdown()


def test_several_clients_and_cleanup(served: tuple[SocketcandServer, str]) -> None:
    server, _ = served
    a, b = client(server), client(server)
    try:
        wait_for(lambda: server.clients == 2, "two clients connected")
        a.send(can.Message(arbitration_id=0x7, is_extended_id=False, data=b"\x07"))
        got = recv_data(b)
        assert got.arbitration_id == 0x7 and bytes(got.data) == b"\x07"
        assert a.recv(timeout=0.05) is None  # a CAN node does not receive its own frame
    finally:
        a.shutdown()
    wait_for(lambda: server.clients == 1, "the disconnected client cleaned up")
    b.shutdown()
    wait_for(lambda: server.clients == 0, "every client cleaned up")


def test_unknown_channel_is_refused(served: tuple[SocketcandServer, str]) -> None:
    server, _ = served
    # A raw socket: python-can's client leaks its socket when the handshake fails.
    with socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S) as raw:
        assert raw.recv(256) == b"< hi >"
        raw.sendall(b"< open can7 >")
        assert raw.recv(256) == b"< error no such channel can7 >"
    wait_for(lambda: server.clients == 0, "the refused client cleaned up")


def test_mit_hardware_over_socketcand(served: tuple[SocketcandServer, str]) -> None:
    server, virtual = served
    motors = can.Bus(interface="virtual", channel=virtual)
    emulator = MitBusEmulator(motors, [1, 2, 3])
    emulator.start()
    hw = MitHardware("leg", ["a", "b", "c"], ["position"], ["position", "velocity"], {
        "buses": {"can0": {"interface": "socketcand", "host": "127.0.0.1",
                           "port": server.port, "channel": "can0", "receive_timeout": 0.05}},
        "ids": [1, 2, 3],
        "feedback_timeout": 0.5,
    })
    try:
        hw.configure()
        hw.activate(time.monotonic_ns())
        t0 = time.monotonic()
        goal = np.array([0.3, -0.2, 0.1])
        while time.monotonic() - t0 < 0.6:
            s = min(1.0, (time.monotonic() - t0) / 0.2)
            hw.write(time.monotonic_ns(), JointCommand(positions=s * goal))
            state = hw.read(time.monotonic_ns())
        np.testing.assert_allclose(state.positions, goal, atol=0.01)
    finally:
        hw.shutdown(time.monotonic_ns())
        emulator.stop()
        motors.shutdown()


def _emulator(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "jtc_hw.drivers.can.emulator", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
        cwd=ROOT, env=daemon_env(),
    )


def _finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, err = proc.communicate(timeout=WAIT_S * 2)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return proc.returncode, out, err


def test_emulate_process_serves_mit_motors_until_sigterm() -> None:
    proc = _emulator("--protocol", "mit", "--ids", "1-3", "--model", "AK60-6", "--pace",
                     "--socketcand-port", "0")
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        fields = dict(f.split("=", 1) for f in line.split())
        assert fields["interface"] == "socketcand" and fields["host"] == "127.0.0.1"
        assert fields["channel"] == "can0", line
        bus = can.Bus(interface="socketcand", host=fields["host"], port=int(fields["port"]),
                      channel="can0")
        try:
            bus.send(can.Message(arbitration_id=2, is_extended_id=False, data=ENTER_MOTOR_MODE))
            reply = bus.recv(timeout=WAIT_S)
            assert reply is not None and reply.data[0] == 2 and len(reply.data) == 6
        finally:
            bus.shutdown()
    finally:
        code, _, err = _finish(proc)
    assert code == 0, err


def test_emulate_process_cia402_or_a_clear_message() -> None:
    proc = _emulator("--protocol", "cia402", "--ids", "1-2", "--socketcand-port", "0")
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
    finally:
        code, _, err = _finish(proc)
    if line:
        assert line.startswith("interface=socketcand ") and code == 0, (line, err)
    else:  # the CiA 402 emulator module is missing or broken: a clear message, status 2
        assert code == 2 and "CiA 402 emulator is not available" in err, err


@pytest.mark.parametrize("protocol", ["mit", "cia402"])
def test_one_thread_emulator_serves_two_buses_and_reconnects(protocol: str) -> None:
    """``jtc-hw emulate can --one-thread``: both channels answer from one thread, a client
    may leave and come back, SIGTERM ends it cleanly."""
    process = subprocess.Popen(
        [sys.executable, "-m", "jtc_hw", "emulate", "can", "--protocol", protocol,
         "--one-thread", "--pace", "--channel", "can0", "--ids", "1-2",
         "--channel", "can1", "--ids", "3"],
        stdout=subprocess.PIPE, text=True, env=daemon_env(), cwd=ROOT,
    )
    try:
        assert process.stdout is not None
        fields = dict(item.split("=", 1) for item in process.stdout.readline().split())
        assert fields["interface"] == "socketcand" and fields["channel"] == "can0,can1"
        for _ in range(2):  # connect, leave, come back
            buses = [
                can.Bus(interface="socketcand", host=fields["host"], port=int(fields["port"]),
                        channel=channel, tcp_tune=True)
                for channel in ("can0", "can1")
            ]
            try:
                for bus, node in zip(buses, (1, 3)):
                    if protocol == "mit":
                        ask = can.Message(arbitration_id=node, is_extended_id=False,
                                          data=ENTER_MOTOR_MODE)
                    else:  # SDO upload of the statusword (0x6041)
                        ask = can.Message(arbitration_id=0x600 + node, is_extended_id=False,
                                          data=bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]))
                    bus.send(ask)
                    deadline = time.monotonic() + WAIT_S
                    answer = None
                    while answer is None and time.monotonic() < deadline:
                        frame = bus.recv(timeout=0.5)
                        if frame is None:
                            continue
                        if protocol == "mit" or frame.arbitration_id == 0x580 + node:
                            answer = frame
                    assert answer is not None, f"no answer from node {node} ({protocol})"
                    if protocol == "mit":
                        assert answer.data[0] == node  # the reply names its motor
                    else:
                        assert answer.data[0] == 0x4B and bytes(answer.data[1:3]) == b"\x41\x60"
            finally:
                for bus in buses:
                    bus.shutdown()
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()
