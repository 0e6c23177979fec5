"""The loop process: what runs in the real-time process, and nothing else of the daemon (its
modules: :mod:`jtc_hw.daemon`'s docstring).

Besides these it imports only the shared rooms below it: :mod:`jtc_hw.daemon.channel` (the
records, the pipe's inbox, the cycle ring) and the daemon's top-level helpers both processes
use (:mod:`~jtc_hw.daemon.robot`, :mod:`~jtc_hw.daemon.locks`, :mod:`~jtc_hw.daemon.realtime`,
:mod:`~jtc_hw.daemon.logs`). Nothing is imported here.
"""
