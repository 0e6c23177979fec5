"""``daemon.record: DIR``: the daemon records everything it publishes from its start.

One bag per daemon run, ``DIR/<UTC start time>Z-run``, fed by ``LoopBackend`` in the API process
(the loop never sees it): every published state, every goal result, and ``get_status`` once a
second as ``/diagnostics``. Serialising and writing happen in a worker thread, in order, so the
event loop only queues the snapshot. Closed (its ``metadata.yaml`` written) when the daemon
stops.

A write that fails (a full disk) stops the recording for the rest of the run: the bag is closed
with what it holds (``jtc_hw.rec.bag``), one line in the log says so, and nothing more is queued.
The daemon and its loop carry on: they never wait for the recorder.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from .bag import BagRecorder, RecordingFailed
from .flight import bag_name

log = logging.getLogger("jtc_hw.record")

DIAGNOSTICS_PERIOD_NS = 1_000_000_000


class ContinuousRecorder:
    """Records the daemon's run into one bag (see the module docstring).

    Args:
        directory: where the run's bag is created.
        controller: the controller's name (topic namespace).
        status: returns the daemon's ``get_status`` reply (for ``/diagnostics``).
        tolerances: the configured tolerances per joint, stored in the bag's metadata.
    """

    def __init__(self, directory: str | Path, controller: str,
                 status: Callable[[], Mapping[str, Any]],
                 tolerances: Mapping[str, Mapping[str, float]] | None = None) -> None:
        """Create the bag.

        Raises:
            RecordingUnavailable: rosbags is not installed.
            OSError: the directory cannot be created.
        """
        offset = time.time_ns() - time.monotonic_ns()
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        self.path = directory / (bag_name(time.time_ns(), "run"))
        self._recorder = BagRecorder(self.path, controller, offset, tolerances)
        self._status = status
        self._next_diagnostics_ns = 0
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="record")
        self.errors = 0
        self.stopped: str | None = None  # why the recording ended early (a full disk...)
        log.info("recording to %s", self.path)

    def on_state(self, snapshot: Mapping[str, Any]) -> None:
        """Queue a state (and, once a second, the status) for writing."""
        if self.stopped is not None:
            return
        t = int(snapshot["time_ns"])
        self._worker.submit(self._guarded, self._recorder.state, dict(snapshot))
        if t >= self._next_diagnostics_ns:
            self._next_diagnostics_ns = t + DIAGNOSTICS_PERIOD_NS
            self._worker.submit(self._guarded, self._recorder.diagnostics, self._status(), t)

    def on_command(self, trajectory: Any, time_ns: int) -> None:
        """Queue an accepted command (``JointTrajectory``) for writing."""
        if self.stopped is not None:
            return
        self._worker.submit(self._guarded, self._recorder.command, trajectory, time_ns)

    def on_event(self, event: Mapping[str, Any]) -> None:
        """Queue a goal event for writing."""
        if self.stopped is not None:
            return
        self._worker.submit(self._guarded, self._recorder.goal_event, dict(event))

    def _guarded(self, write: Callable[..., None], *args: Any) -> None:
        if self.stopped is not None:  # queued before the failure
            return
        try:
            write(*args)
        except RecordingFailed as exc:
            self.stopped = str(exc)
            log.error("recording stopped: %s", exc)
        except Exception as exc:  # noqa: BLE001 - a bad message must not take the daemon down
            self.errors += 1
            if self.errors == 1:
                log.error("recording to %s failed: %s", self.path, exc)

    def close(self) -> None:
        """Write what is queued and finish the bag."""
        self._worker.submit(self._guarded, lambda: self._recorder.close())
        self._worker.shutdown(wait=True)
        if self.stopped is not None:
            return  # said when it stopped
        log.info("recorded %s (%s)", self.path, ", ".join(
            f"{topic}: {n}" for topic, n in sorted(self._recorder.counts.items())))
