"""Device and socket locks (jtc_hw.daemon.locks): one daemon per hardware."""

from __future__ import annotations

import fcntl
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from jtc_hw.daemon import locks
from jtc_hw.daemon.locks import DeviceBusy, acquire, lock_devices, lock_file_name
from jtc_hw.drivers.can.bus import THIS_HOST, BusSettings, bus_keys
from jtc_hw.drivers.can.cia402.hardware import Cia402Hardware
from jtc_hw.drivers.can.mit.hardware import MitHardware
from jtc_hw.drivers.dynamixel.hardware import DynamixelHardware
from jtc_hw.errors import CommunicationError, HardwareError

from conftest import ROOT

WAIT_S = 10.0


@pytest.fixture
def lock_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    directory = tmp_path / "locks"
    monkeypatch.setenv(locks.LOCK_DIR_ENV, str(directory))
    return directory


@pytest.mark.parametrize(
    ("name", "file"),
    [
        ("/dev/ttyUSB0", "dev-ttyUSB0.lock"),
        ("/dev/serial/by-path/pci-0000:00:14.0-usb-0:1:1.0-port0",
         "dev-serial-by%2Dpath-pci%2D0000%3A00%3A14.0%2Dusb%2D0%3A1%3A1.0%2Dport0.lock"),
        ("can:socketcand:127.0.0.1:29536:can0", "can:socketcand:127.0.0.1:29536:can0.lock"),
        ("can:virtual:bus 1", "can:virtual:bus%201.lock"),
        ("ethercat0", ":ethercat0.lock"),
        ("/.hidden", "%2Ehidden.lock"),
    ],
)
def test_lock_file_names_are_readable(name: str, file: str) -> None:
    assert lock_file_name(name) == file
    assert "/" not in lock_file_name(name)


def test_lock_file_names_never_collide() -> None:
    names = ["/dev/a-b", "/dev/a/b", "/dev/a%2Db", "dev-a-b", "/dev-a-b", "x", "/x", ":x",
             "can:x", "/can:x", "/dev/tty.usb", "/dev/tty%2Eusb", "/.x", "/%2Ex"]
    files = [lock_file_name(n) for n in names]
    assert len(set(files)) == len(names), dict(zip(names, files))


def test_a_second_lock_names_the_holder_and_a_released_one_is_free(tmp_path: Path) -> None:
    path = str(tmp_path / "dev-x.lock")
    with acquire("/dev/x", path, config="/etc/a.yaml", pid=4242) as held:
        assert Path(path).read_text() == "4242\n/etc/a.yaml\n"
        with pytest.raises(DeviceBusy) as busy:
            acquire("/dev/x", path, config="/etc/b.yaml")
        message = str(busy.value)
        assert message.startswith("/dev/x is already driven by pid 4242 (/etc/a.yaml)")
        assert path in message and "\n" not in message
        assert (busy.value.pid, busy.value.config) == (4242, "/etc/a.yaml")
        assert held.held
    assert not held.held
    assert not Path(path).exists()  # removed on release
    with acquire("/dev/x", path, config=None) as again:
        assert Path(path).read_text() == f"{os.getpid()}\n\n"
        assert again.held


def test_the_kernel_releases_the_lock_of_a_killed_holder(lock_dir: Path) -> None:
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(
            """
            import sys, time
            from jtc_hw.daemon.locks import lock_devices
            lock_devices(["/dev/ttyTEST-killed"], config="/srv/holder.yaml")
            print("locked", flush=True)
            time.sleep(60)
            """
        )],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, locks.LOCK_DIR_ENV: str(lock_dir)},
    )
    try:
        assert holder.stdout is not None
        assert holder.stdout.readline() == "locked\n"
        with pytest.raises(DeviceBusy) as busy:
            lock_devices(["/dev/ttyTEST-killed"], config="/srv/second.yaml")
        assert f"by pid {holder.pid} (/srv/holder.yaml)" in str(busy.value)
        holder.send_signal(signal.SIGKILL)
        holder.wait(WAIT_S)
        # Its file is still there (nobody removed it), but nobody holds it any more.
        assert (lock_dir / lock_file_name("/dev/ttyTEST-killed")).exists()
        (held,) = lock_devices(["/dev/ttyTEST-killed"], config="/srv/second.yaml")
        held.release()
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait(WAIT_S)
        if holder.stdout is not None:
            holder.stdout.close()


def test_lock_devices_is_all_or_nothing(lock_dir: Path) -> None:
    (first,) = lock_devices(["/dev/b"], config="/a.yaml")
    try:
        with pytest.raises(DeviceBusy):
            lock_devices(["/dev/a", "/dev/b", "/dev/c"], config="/b.yaml")
        # /dev/a was locked, then released when /dev/b was found busy.
        taken = lock_devices(["/dev/a", "/dev/a", "/dev/c"], config="/b.yaml")  # once each
        assert [lock.name for lock in taken] == ["/dev/a", "/dev/c"]
        for lock in taken:
            lock.release()
    finally:
        first.release()
    assert lock_devices([], config=None) == []


def test_the_lock_directory_is_created_for_its_owner_and_group_only(lock_dir: Path) -> None:
    assert locks.lock_directory() == str(lock_dir)
    assert lock_dir.stat().st_mode & 0o7777 == 0o3770  # sticky, setgid, others nothing


def test_an_unusable_lock_directory_is_named(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("")
    monkeypatch.setenv(locks.LOCK_DIR_ENV, str(not_a_dir))
    with pytest.raises(HardwareError) as error:
        lock_devices(["/dev/x"], config=None)
    assert f"{locks.LOCK_DIR_ENV}={not_a_dir}: is not a directory" in str(error.value)


def test_a_symlink_planted_as_a_lock_file_is_not_followed(tmp_path: Path) -> None:
    target = tmp_path / "precious"
    target.write_text("keep me")
    link = tmp_path / "dev-x.lock"
    link.symlink_to(target)
    with pytest.raises(HardwareError) as error:
        acquire("/dev/x", str(link), config=None)
    assert str(link) in str(error.value)
    assert target.read_text() == "keep me"


# -- the lock names the device, not its spelling --------------------------------------------------


def socketcand(host: str, port: int = 29536, channel: str = "can0") -> BusSettings:
    return BusSettings("can0", "socketcand", channel, 1_000_000, host=host, port=port)


@pytest.mark.parametrize("host", ["localhost", "127.0.0.1", "127.0.1.1", "::1", "::ffff:127.0.0.1",
                                  socket.gethostname()])
def test_every_spelling_of_this_machine_names_one_socketcand_server(host: str) -> None:
    assert bus_keys(socketcand(host)) == (f"can:socketcand:{THIS_HOST}:29536:can0",)


def test_a_remote_socketcand_server_is_its_address_and_its_port_a_number() -> None:
    assert bus_keys(socketcand("192.0.2.7", 7000)) == ("can:socketcand:192.0.2.7:7000:can0",)
    assert bus_keys(socketcand("::ffff:192.0.2.7", 7000)) == bus_keys(socketcand("192.0.2.7",
                                                                                  7000))
    assert bus_keys(socketcand("192.0.2.7", 7001)) != bus_keys(socketcand("192.0.2.7", 7000))
    assert bus_keys(socketcand("192.0.2.7", channel="can1")) != bus_keys(socketcand("192.0.2.7"))


def test_a_host_that_does_not_resolve_is_a_one_line_error() -> None:
    with pytest.raises(CommunicationError) as error:
        bus_keys(socketcand("no-such-host.invalid"))
    assert "host 'no-such-host.invalid' does not resolve" in str(error.value)
    assert "\n" not in str(error.value)


def test_a_socketcan_interface_is_named_by_its_index() -> None:
    settings = BusSettings("can0", "socketcan", "lo", 1_000_000)
    assert bus_keys(settings) == (f"can:socketcan:#{socket.if_nametoindex('lo')}",)
    with pytest.raises(CommunicationError) as error:
        bus_keys(BusSettings("can0", "socketcan", "cannope9", 1_000_000))
    assert "no network interface 'cannope9'" in str(error.value)


def test_a_serial_port_is_its_real_path_and_a_symlink_to_it_collides(lock_dir: Path,
                                                                      tmp_path: Path) -> None:
    real = tmp_path / "ttyREAL"
    real.write_text("")
    link = tmp_path / "by-id-usb-FTDI"
    link.symlink_to(real)

    def arm(port: Path) -> DynamixelHardware:
        return DynamixelHardware("arm", ["a"], ["position"], ["position"],
                                 {"port": str(port), "ids": [1]})

    (held,) = lock_devices(arm(real).devices(), config="/srv/a.yaml")
    try:
        with pytest.raises(DeviceBusy) as busy:
            lock_devices(arm(link).devices(), config="/srv/b.yaml")
        assert str(busy.value).startswith(f"{link} ({real}) is already driven by pid "
                                          f"{os.getpid()} (/srv/a.yaml)")
    finally:
        held.release()


def mit(host: str, ids: list[int]) -> MitHardware:
    joints = [f"j{i}" for i in ids]
    return MitHardware("leg", joints, ["position"], ["position", "velocity"], {
        "buses": {"can0": {"interface": "socketcand", "host": host, "port": 29536,
                           "channel": "can0"}},
        "ids": ids,
    })


def test_mit_daemons_share_a_bus_with_different_ids_never_one_id(lock_dir: Path) -> None:
    first = lock_devices(mit("localhost", [1, 2]).devices(), config="/srv/a.yaml")
    try:
        others = lock_devices(mit("127.0.0.1", [3, 4]).devices(), config="/srv/b.yaml")
        for lock in others:
            lock.release()
        with pytest.raises(DeviceBusy) as busy:
            lock_devices(mit("127.0.0.1", [3, 2]).devices(), config="/srv/c.yaml")
        assert str(busy.value).startswith(
            "bus 'can0' (socketcand can0 at 127.0.0.1:29536 @ 1000 kbit/s) motor 2 is already "
            f"driven by pid {os.getpid()} (/srv/a.yaml)")
        # All or nothing: motor 3 was locked, then released when motor 2 was found busy.
        (three,) = lock_devices(mit("::1", [3]).devices(), config="/srv/d.yaml")
        three.release()
    finally:
        for lock in first:
            lock.release()


def cia402(node_ids: list[int], master_node_id: int = 127) -> Cia402Hardware:
    joints = [f"j{n}" for n in node_ids]
    return Cia402Hardware("arm", joints, ["position"], ["position", "velocity"], {
        "buses": {"can0": {"interface": "socketcand", "host": "localhost", "channel": "can0"}},
        "node_id": node_ids,
        "counts_per_revolution": 4096,
        "master_node_id": master_node_id,
    })


def test_one_canopen_master_per_bus_whatever_its_nodes(lock_dir: Path) -> None:
    first = lock_devices(cia402([1, 2]).devices(), config="/srv/a.yaml")
    try:
        # Other drives and another heartbeat id, but a second SYNC producer and NMT master.
        with pytest.raises(DeviceBusy) as busy:
            lock_devices(cia402([3, 4], master_node_id=100).devices(), config="/srv/b.yaml")
        assert "CANopen master (NMT, SYNC, heartbeat) is already driven by pid" in str(
            busy.value)
        # An MIT daemon on motor ids that are not these nodes' may share the bus.
        others = lock_devices(mit("localhost", [3]).devices(), config="/srv/c.yaml")
        for lock in others:
            lock.release()
    finally:
        for lock in first:
            lock.release()


# -- a stranger cannot deny a start; a denied start names the holder -----------------------------

NOBODY = 65534


def as_user(uid: int, gid: int, action: Callable[[], str]) -> tuple[int, Callable[[], str]]:
    """Fork a child that becomes ``uid``:``gid``, runs ``action`` and keeps whatever it
    opened (a lock) until the returned ``finish()`` is called; ``finish`` returns the line
    the child reported (``action``'s result, or the exception it raised)."""
    report_r, report_w = os.pipe()
    go_r, go_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: no pytest machinery from here on, only os._exit
        code = 0
        try:
            os.close(report_r)
            os.close(go_w)
            os.setgroups([gid])
            os.setgid(gid)
            os.setuid(uid)
            try:
                line = action()
            except Exception as exc:  # reported to the test, which asserts on it
                line = f"{type(exc).__name__}: {exc}"
            os.write(report_w, line.replace("\n", " ").encode() + b"\n")
            os.read(go_r, 1)  # hold until the test is done
        except BaseException:
            code = 1
        finally:
            os._exit(code)
    os.close(report_w)
    os.close(go_r)
    with os.fdopen(report_r, "rb") as report:
        line = report.readline().decode()  # bounded: the child writes before it waits

    def finish() -> str:
        os.write(go_w, b"x")
        os.close(go_w)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        return line.strip()

    return pid, finish


@pytest.fixture
def open_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A lock directory (not created yet) whose parents every user may traverse, as under
    ``/run``: pytest's own temporary directories are private to root."""
    if os.geteuid() != 0:
        pytest.skip("needs root to act as another user")
    base = Path(tempfile.mkdtemp(prefix="jtc-hw-locktest-"))
    base.chmod(0o755)
    directory = base / "locks"
    monkeypatch.setenv(locks.LOCK_DIR_ENV, str(directory))
    try:
        yield directory
    finally:
        shutil.rmtree(base)


def test_a_stranger_cannot_take_a_devices_lock_to_deny_a_start(open_dir: Path) -> None:
    assert locks.lock_directory() == str(open_dir)  # created by the daemon's user
    path = open_dir / lock_file_name("/dev/ttyUSB0")

    def squat() -> str:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return "holding"

    _, finish = as_user(NOBODY, NOBODY, squat)
    try:
        (held,) = lock_devices(["/dev/ttyUSB0"], config="/etc/robot.yaml")
        held.release()
    finally:
        reported = finish()
    assert reported.startswith("PermissionError"), reported


@pytest.mark.parametrize(
    ("owner", "mode", "problem"),
    [
        (NOBODY, 0o700, "belongs to user nobody (mode 0700), who could deny or allow any start"),
        (0, 0o1777, "mode 1777 lets every user in"),
        (0, 0o770, "mode 0770: a group-writable lock directory must be sticky"),
    ],
)
def test_a_lock_directory_a_stranger_could_use_is_refused_naming_why(
        open_dir: Path, owner: int, mode: int, problem: str) -> None:
    open_dir.mkdir()
    os.chown(open_dir, owner, owner)
    open_dir.chmod(mode)
    with pytest.raises(HardwareError) as error:
        lock_devices(["/dev/ttyUSB0"], config=None)
    assert f"{locks.LOCK_DIR_ENV}={open_dir}: {problem}" in str(error.value)
    assert "\n" not in str(error.value)


def test_daemons_of_two_users_in_the_directorys_group_see_each_other(open_dir: Path) -> None:
    open_dir.mkdir()
    os.chown(open_dir, 0, NOBODY)
    open_dir.chmod(0o3770)

    def drive() -> str:
        (held,) = lock_devices(["/dev/ttyUSB0"], config="/srv/nobody.yaml")
        return f"holding {held.path}"

    pid, finish = as_user(NOBODY, NOBODY, drive)
    try:
        with pytest.raises(DeviceBusy) as busy:
            lock_devices(["/dev/ttyUSB0"], config="/etc/robot.yaml")
        assert str(busy.value).startswith(
            f"/dev/ttyUSB0 is already driven by pid {pid} (/srv/nobody.yaml), user nobody; ")
        assert (busy.value.pid, busy.value.user) == (pid, "nobody")
    finally:
        reported = finish()
    assert reported.startswith("holding"), reported
    (held,) = lock_devices(["/dev/ttyUSB0"], config="/etc/robot.yaml")  # free once it ended
    held.release()


def test_a_holder_that_recorded_nothing_is_found_in_proc_locks(lock_dir: Path) -> None:
    directory = locks.lock_directory()
    path = os.path.join(directory, lock_file_name("/dev/ttyUSB0"))
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(
            f"""
            import fcntl, os, sys
            fd = os.open({path!r}, os.O_RDWR | os.O_CREAT, 0o600)
            fcntl.flock(fd, fcntl.LOCK_EX)  # and records nothing
            print("locked", flush=True)
            sys.stdin.read()
            """
        )],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdin is not None
        assert holder.stdout.readline() == "locked\n"
        with pytest.raises(DeviceBusy) as busy:
            lock_devices(["/dev/ttyUSB0"], config="/etc/robot.yaml")
        user = pwd.getpwuid(os.geteuid()).pw_name
        assert str(busy.value).startswith(
            f"/dev/ttyUSB0 is already driven by pid {holder.pid}, user {user}; "), busy.value
        assert busy.value.pid == holder.pid
    finally:
        if holder.stdin is not None:
            holder.stdin.close()
        holder.wait(WAIT_S)
        if holder.stdout is not None:
            holder.stdout.close()
