"""Shared helpers: configurations, a simulated clock, a mirror joint set, and leak checks.

Heavier helpers live in ``tests/helpers/`` (the daemon as a subprocess, a stand-in backend).
"""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jtc_hw import JointCommand, JointState, JointTrajectoryController, Trajectory, load_config
from jtc_hw.api import Client
from jtc_hw.cli.demo import DEMO_LOOP_PRIORITY, fifo_permitted
from jtc_hw.controller.config import COMMAND_INTERFACE_TYPES, ControllerConfig
from jtc_hw.hardware.mirror import MirrorHardware

ROOT = Path(__file__).resolve().parents[1]
"""The repository checkout."""

# A background job of a non-interactive shell (.ci/run starts both suites with '&') inherits
# SIGINT ignored, and so would every process a test starts: a command the tests stop the way
# a terminal's Ctrl-C does (``jtc-hw state --watch``, ``jtc-hw plot --live``) would then run on.
# The tests model an operator at a terminal: SIGINT raises KeyboardInterrupt here, and the
# processes started from here begin with its default action (exec resets a handled signal).
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

S = 1_000_000_000  # ns per second
MS = 1_000_000

TEST_LOOP_REALTIME: dict[str, Any] = (
    {"priority": DEMO_LOOP_PRIORITY} if fifo_permitted(DEMO_LOOP_PRIORITY) else {}
)
"""``daemon.realtime`` of every test daemon built by :func:`make_robot_config`: its loop at
the SCHED_FIFO priority ``jtc-hw demo`` takes, where this user may have it (as on a robot), else
normally scheduled. Issue 22: beside busy processes a normally scheduled loop stalled 100-200 ms,
and goals at test speeds broke their path tolerance; what such a test is about is the daemon,
not the host's scheduler. Tests of the unprivileged case set ``realtime`` themselves."""


def make_config(
    joints: Sequence[str] = ("j1", "j2"),
    command_interfaces: Sequence[str] = ("position",),
    state_interfaces: Sequence[str] = ("position", "velocity"),
    **params: Any,
) -> ControllerConfig:
    mapping: dict[str, Any] = {
        "joints": list(joints),
        "command_interfaces": list(command_interfaces),
        "state_interfaces": list(state_interfaces),
    }
    mapping.setdefault("update_rate", 100.0)
    mapping.update(params)
    return load_config(mapping)


def make_robot_config(
    socket_path: str | Path,
    joints: Sequence[str],
    hardware: Sequence[dict[str, Any]],
    *,
    command_interfaces: Sequence[str] = ("position",),
    controller: Mapping[str, Any] | None = None,
    update_rate: int = 500,
    goal_time: float = 0.5,
    path_tolerance: float = 0.05,
    goal_tolerance: float = 0.01,
    **daemon: Any,
) -> dict[str, Any]:
    """A robot file (upstream controller layout plus ``hardware`` and ``daemon``) as a mapping.

    Position + velocity state, state at 50 Hz and feedback at 20 Hz, the same path and goal
    tolerance on every joint, the loop at :data:`TEST_LOOP_REALTIME`; ``controller`` adds or
    overrides controller parameters. Every daemon test builds its file here.
    """
    return {
        "controller_manager": {"ros__parameters": {"update_rate": update_rate}},
        "joint_trajectory_controller": {
            "ros__parameters": {
                "joints": list(joints),
                "command_interfaces": list(command_interfaces),
                "state_interfaces": ["position", "velocity"],
                "state_publish_rate": 50.0,
                "action_monitor_rate": 20.0,
                "constraints": {
                    "stopped_velocity_tolerance": 0.05,
                    "goal_time": goal_time,
                    **{j: {"trajectory": path_tolerance, "goal": goal_tolerance} for j in joints},
                },
                **(controller or {}),
            }
        },
        "hardware": list(hardware),
        "daemon": {"socket": str(socket_path), "realtime": dict(TEST_LOOP_REALTIME), **daemon},
    }


class Mirror:
    """The ideal simulated joints the controller tests step: the ``mirror`` hardware kind
    (:class:`~jtc_hw.hardware.mirror.MirrorHardware`, no lag, no limits), active throughout,
    on a clock of its own that each :meth:`apply` moves on by ``dt_s``.

    A position command is where the joints are at the next :meth:`state`, a velocity command
    integrates, an effort drives a unit inertia (the mirror's rules). ``p`` and ``v`` are what
    :meth:`state` returns; a test moves the joints from outside (a slip, a push) by assigning
    ``p`` or changing it in place, which the next :meth:`state` or :meth:`apply` hands to
    :meth:`MirrorHardware.displace`. ``frozen``: :meth:`MirrorHardware.set_frozen`.
    """

    def __init__(self, positions: Sequence[float]) -> None:
        joints = [f"j{i}" for i in range(len(positions))]
        self.hardware = MirrorHardware(
            "mirror", joints, COMMAND_INTERFACE_TYPES, ("position", "velocity"),
            {"initial_positions": [float(x) for x in positions]},
        )
        self._t_ns = 0
        self.hardware.configure()
        self.hardware.activate(self._t_ns)
        self._take()

    def _take(self) -> None:
        state = self.hardware.read(self._t_ns)
        assert state.velocities is not None
        self.p, self.v = state.positions, state.velocities
        self._read_p = self.p.copy()

    def _displaced(self) -> None:
        """Hand a test's change of ``p`` to the hardware (a read does not move the joints)."""
        if not np.array_equal(self.p, self._read_p):
            self.hardware.displace(self.p)
            self._take()

    @property
    def frozen(self) -> bool:
        return self.hardware.frozen

    @frozen.setter
    def frozen(self, frozen: bool) -> None:
        self.hardware.set_frozen(frozen)

    def state(self) -> JointState:
        self._displaced()
        return JointState(self.p.copy(), self.v.copy())

    def apply(self, command: JointCommand, dt_s: float) -> None:
        self._displaced()
        self.hardware.write(self._t_ns, command)
        self._t_ns += round(dt_s * S)
        self._take()


class Rig:
    """A controller, a mirror and a simulated clock stepping at the configured rate."""

    def __init__(self, config: ControllerConfig, positions: Sequence[float], t0: int = 10 * S):
        self.ctrl = JointTrajectoryController(config)
        self.mirror = Mirror(positions)
        self.now = t0
        self.period = round(S / config.update_rate)
        self.events: list[Any] = []
        self.last: Any = None
        self.ctrl.activate(self.now, self.mirror.state())

    def step(self, n: int = 1) -> Any:
        for _ in range(n):
            out = self.ctrl.update(self.now, self.period, self.mirror.state())
            self.events.extend(out.events)
            self.last = out
            self.mirror.apply(out.command, self.period / S)
            self.now += self.period
        return self.last

    def run_until(self, predicate: Any, limit_s: float = 30.0) -> Any:
        for _ in range(int(limit_s * S / self.period)):
            out = self.step()
            if predicate(out):
                return out
        raise AssertionError("condition not reached within the simulated time limit")

    def results(self, goal_id: int | None = None) -> list[Any]:
        from jtc_hw import GoalResult

        return [
            e
            for e in self.events
            if isinstance(e, GoalResult) and (goal_id is None or e.goal_id == goal_id)
        ]


@pytest.fixture(scope="session", autouse=True)
def private_lock_and_state_directories(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The daemons this session starts take their device locks in a directory of its own, not
    the machine's ``/run/lock/jtc-hw``: a real daemon on a developer's robot computer must not
    see tests as rivals (nor they it), and two test sessions run side by side (``.ci/run``
    runs the suite on two Pythons at once) must not refuse each other's emulated buses."""
    from jtc_hw.daemon.locks import LOCK_DIR_ENV

    private = {
        LOCK_DIR_ENV: str(tmp_path_factory.mktemp("locks")),
        # Likewise the flight recorder's default directory: a test daemon's bags are not the
        # user's (robot.py: $STATE_DIRECTORY, else $XDG_STATE_HOME/jtc-hw/flight).
        "XDG_STATE_HOME": str(tmp_path_factory.mktemp("state")),
    }
    saved = {key: os.environ.get(key) for key in (*private, "STATE_DIRECTORY")}
    os.environ.update(private)
    os.environ.pop("STATE_DIRECTORY", None)
    yield
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@pytest.fixture
def two_joint_config() -> ControllerConfig:
    return make_config()


def frange(start: int, stop: int, step: int) -> Iterator[int]:
    t = start
    while t <= stop:
        yield t
        t += step


def kinds_at(traj: Trajectory, t_ns: int) -> Any:
    """Per joint, the ``SegmentKind`` a trajectory uses at ``t_ns`` (HOLD past the end), read
    from ``Trajectory.pieces()``: the oracle of the segment-kind tests."""
    breaks, blocks, _, kinds, _ = traj.pieces()
    if not blocks.shape[0] or t_ns >= breaks[-1]:
        return np.zeros(traj.n_joints, dtype=np.int8)
    return kinds[max(int(breaks.searchsorted(t_ns, side="right")) - 1, 0)].copy()


def _socket_fds() -> set[str]:
    out = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:"):
            out.add(f"{fd}->{target}")
    return out


def _shared_memory() -> set[str]:
    """The cycle rings (``/dev/shm/jtc_hw_<pid>_*``) of this process and of the daemons it
    started (other engineers' test runs on the machine have their own pids)."""
    helpers = sys.modules.get("helpers.daemon")
    pids = {os.getpid()} | {d.pid for d in (helpers._DAEMONS if helpers else [])
                            if d.proc is not None}
    try:
        names = os.listdir("/dev/shm")
    except OSError:
        return set()
    return {n for n in names if n.startswith("jtc_hw_")
            and n.split("_")[2:3] and n.split("_")[2].isdigit() and int(n.split("_")[2]) in pids}


THREAD_END_S = 10.0
"""How long :func:`no_leaks` waits for the threads a test started to end (an upper bound on
waiting, never a claim of speed)."""


@pytest.fixture
def no_leaks() -> Iterator[None]:
    """Fail a test that leaves threads running, sockets open, unclosed resources or shared
    memory segments (a daemon's cycle ring) behind.

    Modules that start threads, sockets or processes opt in with
    ``pytestmark = pytest.mark.usefixtures("no_leaks")``.
    """
    threads = set(threading.enumerate())
    sockets = _socket_fds()
    segments = _shared_memory()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ResourceWarning)
        yield
        gc.collect()
        # What survived goes to the permanent generation, so the next test's collection (and
        # the automatic ones) walk only what was made since: with the whole session's objects a
        # full collection held the GIL 0.4-1 s on a busy machine, and an emulator thread of
        # this process (a module's servos, serving its daemon) missed its replies meanwhile.
        gc.freeze()
    # A library's helper thread may end a moment after the close that ends it (Zenoh's
    # callback threads, websockets' keepalive): waited for, with a bound, before it counts.
    deadline = time.monotonic() + THREAD_END_S
    for thread in threading.enumerate():
        if thread not in threads:
            thread.join(max(0.0, deadline - time.monotonic()))
    leaked_threads = [t.name for t in threading.enumerate() if t not in threads and t.is_alive()]
    # Likewise a socket that a library's own runtime closes after the call that closes it
    # returns (Zenoh's links, closed by its Rust threads, which threading cannot see): one
    # still open at the same bound is a leak.
    while _socket_fds() - sockets and time.monotonic() < deadline:
        time.sleep(0.01)
    leaked_sockets = _socket_fds() - sockets
    unclosed = [str(w.message) for w in caught if issubclass(w.category, ResourceWarning)]
    assert not leaked_threads, f"threads left running: {leaked_threads}"
    assert not leaked_sockets, f"sockets left open: {sorted(leaked_sockets)}"
    assert not unclosed, f"unclosed resources: {unclosed}"
    # Of the daemons started during the test: those still running keep theirs; one killed with
    # SIGKILL (its resource tracker too) leaves it to the next daemon's start
    # (cyclering.remove_stale, tests/daemon/test_cycle_ring_cleanup.py), done here instead.
    daemons = [d for d in getattr(sys.modules.get("helpers.daemon"), "_DAEMONS", [])
               if d.proc is not None]
    running = tuple(f"jtc_hw_{d.pid}_" for d in daemons if d.proc.poll() is None)
    killed = tuple(f"jtc_hw_{d.pid}_" for d in daemons if d.proc.returncode == -signal.SIGKILL)
    leaked_segments = []
    for name in sorted(_shared_memory() - segments):
        if name.startswith(killed):
            os.unlink(os.path.join("/dev/shm", name))
        elif not name.startswith(running):
            leaked_segments.append(name)
    assert not leaked_segments, f"shared memory left in /dev/shm: {leaked_segments}"


@pytest.fixture(autouse=True)
def daemon_log_on_failure() -> Iterator[None]:
    """Print what the daemons logged during the test (pytest shows it when the test fails)."""
    helpers = sys.modules.get("helpers.daemon")  # not imported: no daemon was started
    daemons = helpers._DAEMONS if helpers is not None else []
    offsets = {id(d): len(d.log()) for d in daemons}
    yield
    for d in daemons:
        new = d.log()[offsets.get(id(d), 0) :]
        if new:
            print(f"--- daemon {d.config_path} stderr ---\n{new}")



def pid_controller(command: str = "effort", **gains: Any) -> JointTrajectoryController:
    """One joint ``j`` on a closed-loop command interface with ``gains`` (the rest 0), active
    at t = 0 from rest."""
    g = {"p": 0.0, "i": 0.0, "d": 0.0, "i_clamp": 0.0, "ff_velocity_scale": 0.0}
    g.update(gains)
    config = make_config(
        joints=("j",),
        command_interfaces=(command,),
        gains={"j": g},
        allow_nonzero_velocity_at_trajectory_end=True,
    )
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.0], [0.0]))
    return ctrl

# -- a socket server on a fake backend (tests/helpers/fake_backend.py), for the api tests --------


@pytest.fixture
def sock(tmp_path: Path) -> Path:
    """The server's socket path."""
    return tmp_path / "d.sock"


@pytest.fixture
def daemon(sock: Path) -> Iterator[Any]:
    """A real socket server on ``sock`` with a ``FakeBackend``, in its own thread."""
    from helpers.fake_backend import ServerThread

    from jtc_hw.daemon.settings import DaemonSettings

    srv = ServerThread(DaemonSettings(socket=str(sock)))
    yield srv
    srv.close()


@pytest.fixture
def client(daemon: Any, sock: Path) -> Iterator[Client]:
    """A ``Client`` connected to ``daemon``."""
    with Client.connect(str(sock), timeout_s=5.0) as c:
        yield c


# -- issue 15: tests marked `vcan` run on the kernel's SocketCAN devices ---------------------------

VCAN_REQUIRED_ENV = "JTC_HW_VCAN_REQUIRED"
"""Set (to 1) by ``tools/vcan-hil`` inside its VM: there a `vcan` test that skips fails."""

_IFF_UP = 0x1


def vcan_missing(channels: Sequence[str] = ("vcan0",)) -> str | None:
    """Why tests cannot use these SocketCAN devices here (``None``: they can)."""
    for channel in channels:
        flags = Path(f"/sys/class/net/{channel}/flags")
        if not flags.exists():
            return (f"no {channel} network device (needs a kernel with SocketCAN: modprobe "
                    f"vcan; ip link add dev {channel} type vcan; ip link set up {channel}; "
                    "or run tools/vcan-hil)")
        if not int(flags.read_text(), 16) & _IFF_UP:
            return f"{channel} is down (ip link set up {channel})"
    import can

    try:
        can.Bus(interface="socketcan", channel=channels[0]).shutdown()
    except (OSError, can.CanError) as exc:
        return f"cannot open socketcan {channels[0]}: {exc}"
    return None


@pytest.hookimpl(tryfirst=True)  # before the fixtures (the emulators, the daemon) are set up
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Skip a `vcan` test (``@pytest.mark.vcan`` or ``@pytest.mark.vcan("vcan0", "vcan1")``:
    the devices it needs) where the devices are missing, saying why; fail it instead under
    ``JTC_HW_VCAN_REQUIRED``, so that the SocketCAN coverage cannot vanish silently."""
    marker = item.get_closest_marker("vcan")
    if marker is None:
        return
    reason = vcan_missing(tuple(marker.args) or ("vcan0",))
    if reason is None:
        return
    if os.environ.get(VCAN_REQUIRED_ENV):
        pytest.fail(f"{VCAN_REQUIRED_ENV} is set: {reason}", pytrace=False)
    pytest.skip(reason)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[Any]:
    """Under ``JTC_HW_VCAN_REQUIRED`` a `vcan` test that skips itself (``pytest.skip`` in its
    body or a fixture) is reported as failed: the VM run must execute every one."""
    outcome = yield
    report = outcome.get_result()
    if (report.skipped and os.environ.get(VCAN_REQUIRED_ENV)
            and item.get_closest_marker("vcan") is not None):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr
        report.outcome = "failed"
        report.longrepr = f"{VCAN_REQUIRED_ENV} is set, yet this vcan test skipped: {reason}"
