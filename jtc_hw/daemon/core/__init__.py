"""The API process's core: the loop process seen from here, planning, and every operation.

- :mod:`.supervision`: ``LoopProcess``: spawns the loop process (its entry point is
  :func:`jtc_hw.daemon.loop.cycle.loop_main`), writes plans and requests to it without
  blocking, reads its messages, reports its death.
- :mod:`.backend`: ``LoopBackend``: the replica of the loop's reference, planning, the
  ``Backend`` interface; :mod:`.backend_api`: that interface (``Backend``, ``Observer``,
  ``Accepted``).
- :mod:`.observers`: who hears what the loop publishes, in order (the recorders first).
- :mod:`.requests`: every operation, no transport: a request in, its reply out.

It opens no port and knows no transport: the transports (:mod:`jtc_hw.daemon.transports`) sit
above it and call :class:`.requests.Requests`. Below it: the loop's entry point, the channel
and the daemon's top-level helpers. Nothing is imported here.
"""
