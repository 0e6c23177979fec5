"""The transports: every door a client reaches the daemon through, all in the API process (its
modules: :mod:`jtc_hw.daemon`'s docstring; adding one: :mod:`.registry`). The live view
(:mod:`.liveview`) only publishes: an observer of the backend, started by the service after
it, rather than a request transport. Nothing is imported here.
"""
