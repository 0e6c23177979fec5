"""The transports: every door a client reaches the daemon through, all in the API process.

- :mod:`.registry`: the registry of request transports (``TRANSPORTS``: one line per
  transport; ``Transport``, ``Wiring``), started by the service in its order.
- :mod:`.server`: the unix socket and TCP (NDJSON framing, slots, deadlines);
  :mod:`.connection`: one client connection; :mod:`.unix_socket`: the socket file, the peer's
  uid; :mod:`.tcp_door`: who may wait to authenticate, wrong tokens slowed.
- :mod:`.zenoh_iface`: Zenoh (key expressions, the token attachment); its settings are the
  ``daemon.zenoh`` section's (:mod:`jtc_hw.daemon.zenoh_config`, read by both processes).
- :mod:`.liveview`: the Foxglove live view (``daemon.foxglove``): a door that only publishes,
  so an observer of the backend rather than a request transport; the service starts it after
  the backend.

A transport admits and authenticates its clients, then calls the request layer
(:class:`jtc_hw.daemon.core.requests.Requests`); it imports the core, never the other way.
Nothing is imported here.
"""
