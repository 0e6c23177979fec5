"""The API process's core: the loop process seen from here, planning, and every operation
(its modules and what may import what: :mod:`jtc_hw.daemon`'s docstring). It opens no port and
knows no transport: the transports call :class:`.requests.Requests`. Nothing is imported here.
"""
