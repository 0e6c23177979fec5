"""The loop process: what runs in the real-time process, and nothing else of the daemon.

- :mod:`.cycle`: ``loop_main`` (the process's entry point, the spawn target of
  :class:`~jtc_hw.daemon.core.supervision.LoopProcess`) and ``ControlLoop`` (one cycle: drain
  the inbox, read, update, write, publish).
- :mod:`.clock`: absolute deadlines (``Ticker``); :mod:`.stats`: overrun accounting
  (``LoopStats``); :mod:`.outbox`: the loop's queue to the API process, written without ever
  blocking.

Besides these it imports only the shared rooms below it: :mod:`jtc_hw.daemon.channel` (the
records, the pipe's inbox, the cycle ring) and the daemon's top-level helpers both processes
use (:mod:`~jtc_hw.daemon.robot`, :mod:`~jtc_hw.daemon.locks`, :mod:`~jtc_hw.daemon.realtime`,
:mod:`~jtc_hw.daemon.logs`). Nothing is imported here.
"""
