"""The API process's core: the loop process seen from here, planning, and every operation
(its modules: :mod:`jtc_hw.daemon`'s docstring).

It opens no port and knows no transport: the transports (:mod:`jtc_hw.daemon.transports`) sit
above it and call :class:`.requests.Requests`. Below it: the loop's entry point, the channel
and the daemon's top-level helpers. Nothing is imported here.
"""
