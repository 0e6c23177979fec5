"""The running service: the control loop process, the socket server and their wiring.

- :mod:`.service`: ``run()``: start-up, signals, systemd notification, shutdown.
- :mod:`.robot`: the robot YAML file (its hardware section); :mod:`.settings`: the
  ``daemon:`` section's tables and the frozen ``DaemonSettings``.
- :mod:`.loop`, :mod:`.clock`, :mod:`.loopstats`, :mod:`.realtime`: the loop process: absolute
  deadlines, overrun accounting, real-time set-up; :mod:`.pipe`, :mod:`.outbox`: its
  non-blocking inbox and outbox.
- :mod:`.messages`: the records the loop and the API process exchange.
- :mod:`.supervision`: the loop process seen from the API process; :mod:`.backend`: planning
  against the replica of its reference; :mod:`.observers`: who hears what the loop publishes
  (the recorders, the request layer, Zenoh, the live view).
- :mod:`.requests`: every operation, no transport (a request in, its reply out).
- :mod:`.transports`: the registry of transports (the socket server, Zenoh).
- :mod:`.server`, :mod:`.connection`: the asyncio socket server and one client connection.
- :mod:`.sdnotify`: the systemd notify protocol.
- :mod:`.liveview`: the Foxglove live view (``daemon.foxglove``), an observer of the backend.

Nothing is imported here, so that the loop process loads only what it runs.
"""
