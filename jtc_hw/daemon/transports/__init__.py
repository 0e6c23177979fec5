"""The transports: every door a client reaches the daemon through, all in the API process (its
modules: :mod:`jtc_hw.daemon`'s docstring).

The live view (:mod:`.liveview`) is a door that only publishes, so an observer of the backend
rather than a request transport; the service starts it after the backend. The Zenoh settings
are the ``daemon.zenoh`` section's (:mod:`jtc_hw.daemon.zenoh_config`, read by both processes).

A transport admits and authenticates its clients, then calls the request layer
(:class:`jtc_hw.daemon.core.requests.Requests`); it imports the core, never the other way.
Nothing is imported here.
"""
