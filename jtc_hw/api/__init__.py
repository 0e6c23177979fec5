"""What a client needs: the wire protocol (no I/O) and a synchronous Python client.

- :mod:`.protocol`: the requests, their checks and the error codes; :mod:`.framing`:
  newline-delimited JSON in and out (see ``docs/protocol.md``).
- :mod:`.client`: :class:`Client`; :mod:`.handles`: :class:`GoalHandle`, :class:`StateSubscription`.
- :mod:`.paths`: where the daemon's socket is by default.
"""

from . import zenoh_client  # noqa: F401 (it registers Client.connect("zenoh:..."))
from .calls import UNTRUSTED, ClientConnectionError
from .client import Client, default_socket_path
from .framing import RequestError
from .handles import GoalHandle, StateSubscription

__all__ = [
    "UNTRUSTED",
    "Client",
    "ClientConnectionError",
    "GoalHandle",
    "RequestError",
    "StateSubscription",
    "default_socket_path",
]
