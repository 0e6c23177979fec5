"""The running service: two processes, a room for each, and what they share.

The path says where a line runs (docs/decisions.md 45)::

    service          the API process's main: start-up, signals, systemd notification, shutdown
    transports/      API process: every door a client reaches
      registry         the registry of request transports (one line per transport)
      server           unix socket and TCP: framing, slots, deadlines
      connection       one client connection
      unix_socket      the socket file, the peer's uid
      tcp_door         who may wait to authenticate; wrong tokens slowed
      zenoh_iface      Zenoh: key expressions, the token attachment
      liveview         the Foxglove live view (daemon.foxglove): publishes only
    core/            API process: the loop seen from here, planning, every operation
      supervision      the loop process: spawned, spoken to, watched
      backend          the replica of the loop's reference, planning (LoopBackend)
      backend_api      the Backend interface, Observer, Accepted
      observers        the fan-out of what the loop publishes; the recorders
      requests         every operation, no transport: a request in, its reply out
    loop/            loop process: the real-time one
      cycle            loop_main (the spawn target) and ControlLoop (one cycle)
      clock            absolute deadlines
      stats            overrun accounting
      outbox           the loop's queue to the API process, never blocking
    channel/         both processes: what crosses between them
      messages         the typed records they exchange
      pipe             framing; the non-blocking reader, the plan writer
      cyclering        every cycle's row, in shared memory (flight recorder)
    robot            both processes: the robot file (load_robot, its hardware section)
    settings         the daemon: section's tables, the frozen DaemonSettings
    zenoh_config     the daemon.zenoh section, the Zenoh session configuration
    locks  logs      both processes: device and socket locks; third-party loggers
    realtime         both processes: CPU affinity, locked memory, SCHED_FIFO, the allocator
    sdnotify         the systemd notify protocol (the service's)
    systemd_units    the installed units that run a file (the CLI's check)

The arrows point one way (import-linter's "The daemon" contract in pyproject.toml): service >
transports | sdnotify | systemd_units > core > loop > channel | robot > settings > zenoh_config
> locks | logs | realtime. The loop process loads loop/, channel/ and the modules below them,
nothing of core/ or transports/.

Nothing is imported here (nor in any subpackage's ``__init__``), so that the loop process loads
only what it runs.
"""
