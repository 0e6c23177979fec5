"""What crosses between the daemon's two processes; both of them import it.

- :mod:`.messages`: the typed records the API process and the loop process exchange.
- :mod:`.pipe`: the pipe that carries them: framing, both ends' non-blocking reader and the
  API process's plan writer.
- :mod:`.cyclering`: every cycle's row, in shared memory (the loop writes, the API process
  reads it for the flight recorder).

It imports nothing of the daemon (only the controller and the errors), so either process can
load it without the other's modules. Nothing is imported here.
"""
