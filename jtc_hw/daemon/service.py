"""The daemon: wiring of the loop process, the socket server, systemd notification and signals.

Start-up: load and check the configuration -> lock the socket path (``<socket>.lock``: a second
daemon on the same socket stops here, before its loop process exists) -> start the loop process
(which locks every device, then configures and activates the hardware; the controller holds) ->
open the socket -> ``READY=1``. While running, ``WATCHDOG=1`` is sent only while the loop process
is alive and reporting. SIGTERM / SIGINT: ``STOPPING=1``, the loop gives the active goal its
result, holds, applies the hardware's safe action and exits; then the socket is closed (its file
removed) and the daemon exits 0. If the loop process dies instead, every goal it had gets an
``ABORTED`` result, clients get up to ``close_timeout_s`` to read it, and the daemon exits 1 so
that its service manager restarts it.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import JtcHwError
from .core.backend import LoopBackend
from .locks import DeviceLock, acquire, socket_lock_path
from .logs import quiet_third_party_loggers
from .robot import RobotConfig, load_robot
from .sdnotify import Notifier
from .transports.unix_socket import make_socket_directory

if TYPE_CHECKING:
    from .core.requests import Requests
    from .transports.registry import Transport

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
    quiet_third_party_loggers()  # canopen's INFO lines unless jtc-hw -v


class Daemon:
    """One running daemon (used by ``jtc-hw run`` and by tests in-process)."""

    def __init__(self, robot: RobotConfig, source: str | dict[str, Any]) -> None:
        self.robot = robot
        self.notifier = Notifier()
        self.backend = LoopBackend(robot, source)
        self._stop = asyncio.Event()
        self._reason = "daemon stopping"
        self._failed = False
        self.transports: list[Transport] = []  # started (jtc_hw.daemon.transports.registry)

    def request_stop(self, reason: str, failed: bool = False) -> None:
        """Begin an orderly shutdown (idempotent)."""
        if not self._stop.is_set():
            self._reason = reason
            self._failed = failed
            log.info("%s", reason)
            self._stop.set()

    async def run(self) -> int:
        """Serve until a signal or a loop failure; returns the exit status (0: stopped
        cleanly; 1: the loop failed while serving; 2: could not start)."""
        aio = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            aio.add_signal_handler(
                sig, self.request_stop, f"daemon stopping ({signal.Signals(sig).name})"
            )
        try:
            socket_lock = self._lock_socket()
        except JtcHwError as exc:
            log.error("cannot start: %s", exc)
            return 2
        try:
            return await self._serve(aio)
        finally:
            socket_lock.release()

    def _lock_socket(self) -> DeviceLock:
        """One daemon per socket path, decided before the loop process (and its hardware)
        exists: two daemons started together would otherwise both configure the hardware and
        only then find the socket taken.

        Raises:
            DeviceBusy: another daemon holds it ("... is already served by pid N (config)").
            HardwareError: the lock file cannot be created.
            ConfigurationError: the socket's directory cannot be created.
        """
        path = self.robot.daemon.socket
        # The mode the server would give it (first come makes it): not world-listable.
        make_socket_directory(
            Path(path).parent, self.robot.daemon.socket_mode, self.robot.daemon.socket_group
        )
        return acquire(path, socket_lock_path(path), config=self.robot.source_path,
                       what="served")

    async def _serve(self, aio: asyncio.AbstractEventLoop) -> int:
        # Here, not at the top: the CLI's other commands import this module (start-up time).
        from .core.requests import Requests
        from .transports.registry import TRANSPORTS, Wiring

        settings = self.robot.daemon
        try:
            await self.backend.start()
        except Exception as exc:
            log.error("cannot start: %s", exc)
            await self.backend.stop("start-up failed", record=False)
            return 2
        requests = Requests(self.backend, settings.max_message_bytes)
        wiring = Wiring(requests, settings, self.robot.controller.name, self.backend.add_observer,
                        self.backend.status)
        for registration in TRANSPORTS:
            transport = registration.open(wiring)
            if transport is None:
                continue
            try:
                await transport.start()
            except Exception as exc:
                log.error("%s: %s", registration.failure, exc)
                await transport.close()
                await self._close_transports(requests)
                await self.backend.stop("start-up failed", record=False)
                return 2
            self.transports.append(transport)
        live = await self._start_live_view()
        if live is False:
            await self._close_transports(requests)
            await self.backend.stop("start-up failed", record=False)
            return 2
        c = self.robot.controller
        kinds = ", ".join(sorted({h.kind for h in self.robot.hardware}))
        status = (
            f"{len(c.joints)} joints at {c.update_rate:g} Hz on {kinds}; socket "
            f"{Path(settings.socket)}"
        )
        log.info("ready: %s", status)
        self.notifier.ready(status=status)
        watchdog = aio.create_task(self._watchdog())
        death = aio.create_task(self._loop_death())
        try:
            await self._stop.wait()
        finally:
            watchdog.cancel()
            death.cancel()
            self.notifier.stopping(status=self._reason)
            code = await self.backend.stop(self._reason)
            if live is not None:
                await live.close()
            # After the loop's stop: its last results reach every transport's clients.
            await self._close_transports(requests)
            # asyncio restores the default (fatal) handlers when its loop closes: a second
            # SIGTERM now must not turn a clean stop into death by signal.
            for sig in (signal.SIGTERM, signal.SIGINT):
                aio.remove_signal_handler(sig)
                signal.signal(sig, signal.SIG_IGN)
        if self._failed or code not in (0, None):
            return 1
        log.info("stopped cleanly")
        return 0

    async def _start_live_view(self) -> Any:
        """The live view if ``daemon.foxglove`` asks for one (None: off; False: it could not
        start, which is logged)."""
        settings = self.robot.daemon.foxglove
        if settings is None:
            return None
        # Start-up time: the live view's module only for daemon.foxglove (the foxglove extra).
        from .transports.liveview import LiveView

        c = self.robot.controller
        live = LiveView(settings, c.name, c.joints, c.state_publish_rate, self.backend.status)
        try:
            live.start()
        except JtcHwError as exc:
            log.error("cannot start: %s", exc)
            return False
        self.backend.add_observer(live)
        return live

    async def _close_transports(self, requests: Requests) -> None:
        """Close the started transports, the last started first, then the request layer."""
        while self.transports:
            await self.transports.pop().close()
        requests.close()

    async def _loop_death(self) -> None:
        """Exit (non-zero) as soon as the loop process ends without being asked to: the
        backend has given every goal its result by then; the server's close lets clients
        read it."""
        await self.backend.wait_exited()
        self._loop_ended()

    def _loop_ended(self) -> None:
        self.request_stop(
            f"{self.backend.death or 'the control loop process exited'}; exiting so that the "
            "service manager restarts the daemon",
            failed=True,
        )

    async def _watchdog(self) -> None:
        interval = self.notifier.watchdog_interval_s or 0.5
        clock = asyncio.get_running_loop().time
        previous = clock()
        while True:
            await asyncio.sleep(interval)
            now = clock()
            late_s, previous = now - previous - interval, now
            if not self.backend.alive:
                self._loop_ended()
                return
            if late_s > 1.0:
                # This process did not run (stopped, starved): the loop's messages are waiting
                # unread, so its silence says nothing yet. Judge at the next round.
                continue
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
