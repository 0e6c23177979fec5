"""The flight recorder: the last seconds of state, written as a bag when something goes wrong.

Theory of operation
-------------------
Runs in the API process (``LoopBackend`` feeds it; the loop never does). It keeps in memory
every cycle's state (rows of the loop's cycle ring, ``jtc_hw.daemon.channel.cyclering``, copied
by :meth:`FlightRecorder.on_cycles` into a preallocated array of ``flight_recorder_s`` + 1.5
seconds at the cycle rate; made without a cycle rate, it keeps the published states of
:meth:`FlightRecorder.on_state` instead), the accepted commands and the goal events of the last
``flight_recorder_s`` seconds plus one. ``trigger(reason)`` (an abort, a hardware fault, a
rearm, SIGTERM) names the bag at once, so that the goal's result can name it, and writes it once
a state one second after the trigger has arrived (``flush`` writes at once, for a shutdown):
the bag covers ``flight_recorder_s`` before and a second after. Writing happens in a worker
thread, never in the event loop. Only the newest ``flight_recorder_keep`` bags are kept.

Time: daemon clock (CLOCK_MONOTONIC) mapped to wall time by one offset measured at start.

Without ``rosbags`` the recorder is off (``available`` is False) and says so once, at INFO: the
plain install is a supported way to run, not a fault (``daemon.record``, which asks for
recording, is refused without it). A trigger for something that went wrong is logged as a
WARNING, a routine one (:data:`ROUTINE_TRIGGERS`) at INFO. A bag whose writing fails (a full
disk) is closed with what it holds (``jtc_hw.rec.bag``), logged and counted in ``errors``; the
next trigger tries again (the disk may have room by then). Nothing of it reaches the loop, which
never waits for the recorder.
"""

from __future__ import annotations

import collections
import logging
import math
import re
import shutil
import threading
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from .bag import BagRecorder, CycleRowLayout, RecordingFailed

log = logging.getLogger("jtc_hw.flight_recorder")

AFTER_NS = 1_000_000_000
"""How long after a trigger the bag goes on."""

CYCLE_MARGIN_S = 0.5
"""Seconds of cycles kept beyond the window and the second after (rows arrive in batches)."""

NAME_PATTERN = re.compile(r"^\d{8}T\d{6}\.\d{3}Z-[a-z_]+$")
"""A flight recorder bag's directory name: UTC time of the trigger, reason."""


ROUTINE_TRIGGERS = frozenset({"shutdown"})
"""Trigger reasons that are part of normal operation: their bag is announced at INFO."""


def bag_name(wall_ns: int, reason: str) -> str:
    """``20261201T224833.123Z-aborted``: sorts by time, says why."""
    seconds, rest = divmod(wall_ns, 1_000_000_000)
    stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime(seconds))
    slug = re.sub(r"[^a-z_]+", "_", reason.lower()).strip("_") or "trigger"
    return f"{stamp}.{rest // 1_000_000:03d}Z-{slug}"


class FlightRecorder:
    """Ring buffer of state snapshots and goal events, written as rosbag2/MCAP on a trigger.

    Args:
        directory: where bags go (created when the first one is written).
        seconds: how many seconds before a trigger each bag covers (0: off).
        keep: how many bags to keep (the oldest are removed).
        controller: the controller's name (topic namespace).
        tolerances: the configured tolerances per joint, stored in each bag's metadata.
    """

    def __init__(self, directory: str | Path, seconds: float, keep: int,
                 controller: str = "joint_trajectory_controller",
                 tolerances: Mapping[str, Mapping[str, float]] | None = None,
                 cycle_rate_hz: float | None = None,
                 joint_names: Sequence[str] = ()) -> None:
        self.directory = Path(directory)
        self.cycle_rate_hz = cycle_rate_hz
        self.joint_names = list(joint_names)
        # Every cycle's row (on_cycles): a circular array, allocated with the first rows.
        self._layout: CycleRowLayout | None = None
        self._cycles: Any = None
        self._cycles_stored = 0  # rows ever stored; the next goes at this modulo capacity
        self.lost_cycles = 0
        """Rows the API process could not copy out of the loop's ring in time (overruns)."""
        self.tolerances = tolerances
        self.window_ns = round(seconds * 1e9)
        self.keep = keep
        self.controller = controller
        self.offset_ns = time.time_ns() - time.monotonic_ns()
        self.available = seconds > 0
        if self.available:
            try:
                import rosbags  # noqa: F401 - an optional extra (jtc_hw[record])
            except ImportError:
                self.available = False
                log.info("flight recorder off: it needs the rosbags library "
                         "(pip install 'jtc_hw[record]'; or daemon.flight_recorder_s: 0 "
                         "to run without it and without this line)")
        self._states: collections.deque[dict[str, Any]] = collections.deque()
        self._events: collections.deque[dict[str, Any]] = collections.deque()
        self._commands: collections.deque[tuple[int, Any]] = collections.deque()
        # (bag path, write once a state is at/after this, trigger time)
        self._pending: list[tuple[Path, int, int]] = []
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="flight-recorder")
        self._lock = threading.Lock()  # the files: written by the worker, listed by status
        self.written: list[str] = []
        self.last_file: str | None = None
        self.errors = 0

    def on_state(self, snapshot: Mapping[str, Any]) -> None:
        """Keep a state snapshot; write the bags whose second after has now passed."""
        if not self.available:
            return
        t = int(snapshot["time_ns"])
        self._states.append(dict(snapshot))
        self._trim(t)
        self.poll(t)

    def on_cycles(self, rows: Any, layout: CycleRowLayout, lost: int = 0) -> None:
        """Keep every cycle's row (an array of rows of the cycle ring, in order); ``lost``:
        rows that were overwritten in the ring before they could be copied. Writes the bags
        whose second after has now passed.

        Raises:
            ValueError: rows of another layout than the first ones (a programming error).
        """
        if not self.available:
            return
        self.lost_cycles += lost
        if lost:
            log.warning("flight recorder: %d cycles lost (the API process read the loop's "
                        "cycle ring too late)", lost)
        n = len(rows)
        if n == 0:
            return
        if self._cycles is None:
            rate = self.cycle_rate_hz or 1000.0
            capacity = max(16, math.ceil((self.window_ns + AFTER_NS) / 1e9 * rate
                                         + CYCLE_MARGIN_S * rate))
            self._layout = layout
            self._cycles = np.full((capacity, layout.width), np.nan)
        capacity = len(self._cycles)
        if n > capacity:
            rows, n = rows[-capacity:], capacity
        start = self._cycles_stored % capacity
        first = min(n, capacity - start)
        self._cycles[start:start + first] = rows[:first]
        if first < n:
            self._cycles[:n - first] = rows[first:]
        self._cycles_stored += n
        assert self._layout is not None
        last = int(self._layout.times(rows[-1:])[0])
        self._trim(last)
        self.poll(last)

    def _cycle_window(self, start_ns: int, end_ns: int) -> Any:
        """A copy of the rows kept with ``start_ns <= time <= end_ns``, in order."""
        assert self._layout is not None
        capacity = len(self._cycles)
        stored = min(self._cycles_stored, capacity)
        head = self._cycles_stored % capacity
        rows = (self._cycles[:stored] if self._cycles_stored <= capacity
                else np.concatenate((self._cycles[head:], self._cycles[:head])))
        times = self._layout.times(rows)
        return rows[(times >= start_ns) & (times <= end_ns)].copy()

    def _trim(self, t: int) -> None:
        horizon = t - self.window_ns - AFTER_NS
        while self._states and self._states[0]["time_ns"] < horizon:
            self._states.popleft()
        while self._events and self._events[0]["time_ns"] < horizon:
            self._events.popleft()
        while self._commands and self._commands[0][0] < horizon:
            self._commands.popleft()

    def poll(self, now_ns: int) -> None:
        """Write the bags whose second after has passed at ``now_ns`` (daemon clock). Called
        with each state, and by a timer: a faulted loop may publish no more states."""
        due = [p for p in self._pending if now_ns >= p[1]]
        if due:
            self._pending = [p for p in self._pending if now_ns < p[1]]
            for path, end_ns, _ in due:
                self._submit(path, end_ns)

    def on_command(self, trajectory: Any, time_ns: int) -> None:
        """Keep an accepted command (``JointTrajectory``, converted only if a bag is written)."""
        if self.available:
            self._commands.append((time_ns, trajectory))

    def on_event(self, event: Mapping[str, Any]) -> None:
        """Keep a goal event (a result or feedback as the socket sends it, with ``time_ns``)."""
        if self.available:
            self._events.append(dict(event))

    def trigger(self, reason: str, now_ns: int | None = None) -> str | None:
        """Name a bag for ``reason`` now and write it a second later; its path (None: off).

        A trigger within a second of the previous one (a fault, then the abort it causes) shares
        its bag: that one already covers the second after.
        """
        if not self.available:
            return None
        now = time.monotonic_ns() if now_ns is None else now_ns
        for path, _, when in self._pending:
            if abs(now - when) < AFTER_NS:
                return str(path)
        path = self.directory / bag_name(now + self.offset_ns, reason)
        self._pending.append((path, now + AFTER_NS, now))
        level = logging.INFO if reason in ROUTINE_TRIGGERS else logging.WARNING
        log.log(level, "flight recorder: %s; writing %s", reason, path)
        return str(path)

    def flush(self, timeout_s: float = 10.0) -> None:
        """Write every pending bag now and wait for the writer.

        Raises:
            TimeoutError: the writer is still busy after ``timeout_s`` (the bags go on).
        """
        self._submit_pending()
        self._writer.submit(lambda: None).result(timeout=timeout_s)

    def close(self) -> None:
        """Write every pending bag (the shutdown's) and stop the writer thread once they are
        written, however long that takes: a machine busy enough took over 10 s for a
        932-cycle bag, and a timeout here ended the daemon with a traceback instead of the bag.
        The service manager's stop timeout bounds the wait."""
        try:
            self._submit_pending()
        finally:
            self._writer.shutdown(wait=True)

    def _submit_pending(self) -> None:
        pending, self._pending = self._pending, []
        for path, _, _ in pending:
            self._submit(path, None)

    def status(self) -> dict[str, Any]:
        """For ``get_status``: settings, the newest bag, the bags kept, write errors."""
        with self._lock:
            return {
                "enabled": self.available,
                "seconds": self.window_ns / 1e9,
                # "cycles": every cycle (at cycle_rate_hz); "states": the published ones
                "source": "cycles" if self.cycle_rate_hz else "states",
                "cycle_rate_hz": self.cycle_rate_hz,
                "lost_cycles": self.lost_cycles,
                "directory": str(self.directory),
                "keep": self.keep,
                "last_file": self.last_file,
                "files": list(self.written),
                "errors": self.errors,
            }

    def _submit(self, path: Path, end_ns: int | None) -> None:
        cycles = None
        if self._layout is not None:
            last = int(self._layout.times(self._cycles[
                (self._cycles_stored - 1) % len(self._cycles):][:1])[0])
        else:
            last = self._states[-1]["time_ns"] if self._states else 0
        end = last if end_ns is None else end_ns
        start = end - AFTER_NS - self.window_ns
        if self._layout is not None:
            cycles = self._cycle_window(start, end)  # a copy: the worker owns it
            states: list[dict[str, Any]] = []
        else:
            states = [s for s in self._states if start <= s["time_ns"] <= end]
        events = [e for e in self._events if start <= e["time_ns"] <= end]
        commands = [(t, c) for t, c in self._commands if start <= t <= end]
        future: Future[None] = self._writer.submit(self._write, path, states, events, commands,
                                                   cycles)
        del future  # errors are logged and counted by _write

    def _write(self, path: Path, states: list[dict[str, Any]],
               events: list[dict[str, Any]], commands: list[tuple[int, Any]],
               cycles: Any = None) -> None:
        layout = self._layout
        n_cycles = 0 if cycles is None else len(cycles)
        if not states and not events and not n_cycles:  # e.g. a fault before the first state
            log.info("flight recorder: nothing recorded before %s; no bag written", path.name)
            return
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            recorder = BagRecorder(path, self.controller, self.offset_ns, self.tolerances)
            try:
                items: list[tuple[int, int, Any]] = [(s["time_ns"], 0, s) for s in states]
                if n_cycles:
                    assert layout is not None
                    items += [(int(t), 0, row) for t, row in zip(
                        layout.times(cycles).tolist(), cycles, strict=True)]
                items += [(e["time_ns"], 1, e) for e in events]
                items += [(t, 2, c) for t, c in commands]
                merged = sorted(items, key=lambda item: (item[0], item[1]))
                for t, kind, message in merged:
                    if kind == 0:
                        if isinstance(message, dict):
                            recorder.state(message)
                        else:
                            assert layout is not None
                            recorder.cycle(layout, message, self.joint_names)
                    elif kind == 1:
                        recorder.goal_event(message)
                    else:
                        recorder.command(message, t)
            finally:
                recorder.close()
        except Exception as exc:  # noqa: BLE001 - a full disk must not take the daemon down
            with self._lock:
                self.errors += 1
            # A RecordingFailed's message names the bag and what it holds.
            log.error("flight recorder: %s", exc if isinstance(exc, RecordingFailed)
                      else f"could not write {path}: {exc}")
            return
        with self._lock:
            self.last_file = str(path)
            self.written.append(str(path))
        log.info("flight recorder: wrote %s (%d %s, %d events)", path,
                 n_cycles if n_cycles else len(states), "cycles" if n_cycles else "states",
                 len(events))
        self._prune()

    def _prune(self) -> None:
        bags = sorted(p for p in self.directory.iterdir()
                      if p.is_dir() and NAME_PATTERN.match(p.name))
        for old in bags[:-self.keep] if self.keep > 0 else []:
            shutil.rmtree(old, ignore_errors=True)
            with self._lock:
                if str(old) in self.written:
                    self.written.remove(str(old))
