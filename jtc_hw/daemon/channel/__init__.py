"""What crosses between the daemon's two processes, which both import it (its modules:
:mod:`jtc_hw.daemon`'s docstring); it imports neither process's own modules. Nothing is
imported here.
"""
