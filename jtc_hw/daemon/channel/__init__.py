"""What crosses between the daemon's two processes; both of them import it (its modules:
:mod:`jtc_hw.daemon`'s docstring).

It imports nothing of the daemon (only the controller and the errors), so either process can
load it without the other's modules. Nothing is imported here.
"""
