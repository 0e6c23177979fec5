"""The running service: the control loop process, the socket server and their wiring.

- :mod:`.service`: ``run()``: start-up, signals, systemd notification, shutdown.
- :mod:`.robot`: the robot YAML file (controller, hardware, daemon settings).
- :mod:`.loop`, :mod:`.clock`, :mod:`.loopstats`, :mod:`.realtime`: the loop process: absolute
  deadlines, overrun accounting, real-time set-up.
- :mod:`.backend`: the API process's side of the loop (planning against a replica).
- :mod:`.requests`: every operation, no transport (a request in, its reply out).
- :mod:`.transports`: the registry of transports (the socket server, Zenoh).
- :mod:`.server`, :mod:`.connection`: the asyncio socket server and one client connection.
- :mod:`.sdnotify`: the systemd notify protocol.
- :mod:`.liveview`: the Foxglove live view (``daemon.foxglove``), a tap on the backend.

Nothing is imported here, so that the loop process loads only what it runs.
"""
