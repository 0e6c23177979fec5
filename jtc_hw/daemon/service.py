"""The daemon: wiring of the loop process, the socket server, systemd notification and signals.

Start-up: load and check the configuration -> start the loop process (hardware configured and
active, controller holding) -> open the socket -> ``READY=1``. While running, ``WATCHDOG=1`` is
sent only while the loop process is alive and reporting. SIGTERM / SIGINT: ``STOPPING=1``, the
loop gives the active goal its result, holds, applies the hardware's safe action and exits; then
the socket is closed (its file removed) and the daemon exits 0.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import sys
from typing import Any

from .backend import LoopBackend
from .robot import RobotConfig, load_robot
from .sdnotify import Notifier

log = logging.getLogger("jtc_hw.daemon")

_JOURNAL_PRIORITY = {
    logging.DEBUG: 7,
    logging.INFO: 6,
    logging.WARNING: 4,
    logging.ERROR: 3,
    logging.CRITICAL: 2,
}


class _JournalFormatter(logging.Formatter):
    """``<priority>message`` lines: journald reads the priority prefix from a stream."""

    def format(self, record: logging.LogRecord) -> str:
        prio = _JOURNAL_PRIORITY.get(record.levelno, 6)
        return f"<{prio}>{record.name}: {super().format(record)}"


def setup_logging(level: str = "info", stream: Any = None) -> None:
    """Log to stderr; with journald (``JOURNAL_STREAM`` set) use priority prefixes."""
    handler = logging.StreamHandler(stream or sys.stderr)
    if os.environ.get("JOURNAL_STREAM"):
        handler.setFormatter(_JournalFormatter("%(message)s"))
    else:
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(getattr(logging, level.upper(), logging.INFO))


class Daemon:
    """One running daemon (used by ``jtc-hw run`` and by tests in-process)."""

    def __init__(self, robot: RobotConfig, source: str | dict[str, Any]) -> None:
        self.robot = robot
        self.source = source
        self.notifier = Notifier()
        self.backend = LoopBackend(robot, source)
        self._stop = asyncio.Event()
        self._reason = "daemon stopping"
        self._failed = False

    def request_stop(self, reason: str, failed: bool = False) -> None:
        """Begin an orderly shutdown (idempotent)."""
        if not self._stop.is_set():
            self._reason = reason
            self._failed = failed
            log.info("%s", reason)
            self._stop.set()

    async def run(self) -> int:
        """Serve until a signal or a loop failure; returns the exit status."""
        from .server import Server

        aio = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            aio.add_signal_handler(
                sig, self.request_stop, f"daemon stopping ({signal.Signals(sig).name})"
            )
        settings = self.robot.daemon
        try:
            await self.backend.start()
        except Exception as exc:
            log.error("cannot start: %s", exc)
            await self.backend.stop("start-up failed")
            return 2
        server = Server(self.backend, settings)
        try:
            await server.start()
        except Exception as exc:
            log.error("cannot open the socket: %s", exc)
            await self.backend.stop("start-up failed")
            return 2
        c = self.robot.controller
        kinds = ", ".join(sorted({h.kind for h in self.robot.hardware}))
        status = f"{len(c.joints)} joints at {c.update_rate:g} Hz on {kinds}; socket {server.path}"
        log.info("ready: %s", status)
        self.notifier.ready(status=status)
        watchdog = aio.create_task(self._watchdog())
        try:
            await self._stop.wait()
        finally:
            watchdog.cancel()
            self.notifier.stopping(status=self._reason)
            code = await self.backend.stop(self._reason)
            await server.close()
            # asyncio restores the default (fatal) handlers when its loop closes: a second
            # SIGTERM now must not turn a clean stop into death by signal.
            for sig in (signal.SIGTERM, signal.SIGINT):
                aio.remove_signal_handler(sig)
                signal.signal(sig, signal.SIG_IGN)
        if self._failed or code not in (0, None):
            return 1
        log.info("stopped cleanly")
        return 0

    async def _watchdog(self) -> None:
        interval = self.notifier.watchdog_interval_s or 0.5
        while True:
            await asyncio.sleep(interval)
            if not self.backend.alive:
                self.request_stop("the control loop process exited", failed=True)
                return
            silent_s = (self.backend.now_ns() - self.backend.last_heard_ns) / 1e9
            if silent_s < 2.0:
                self.notifier.watchdog()
            else:
                log.error(
                    "the control loop has been silent for %.1f s; watchdog withheld", silent_s
                )


def run(config_path: str, controller_name: str | None = None) -> int:
    """``jtc-hw run``: load, check and serve. Returns the process exit status."""
    robot = load_robot(config_path, controller_name)
    setup_logging(robot.daemon.log_level)
    source = os.path.abspath(config_path)
    return asyncio.run(Daemon(robot, source).run())
