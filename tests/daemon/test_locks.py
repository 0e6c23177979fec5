"""Device and socket locks (jtc_hw.daemon.locks): one daemon per hardware."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from jtc_hw.daemon import locks
from jtc_hw.daemon.locks import DeviceBusy, acquire, lock_devices, lock_file_name
from jtc_hw.errors import HardwareError

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
