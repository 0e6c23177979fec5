"""The daemon's ways in: every transport is one module over the request layer, registered here.

Theory of operation
-------------------
A transport is a peer over the request layer (``jtc_hw.daemon.core.requests`` draws them);
what it adds is its own (framing, authentication, slots, key expressions), and it never
reaches into another transport. Adding one is one module (or package: ``ros2/``) and one
line::

    1. transports/<name>.py: a class with ``async start()`` and ``async close()``
       (``Transport``) over a ``Requests``; a ``Caller`` per client or per request, its
       ``Outlet`` delivering the goal events and states the layer routes to it;
    2. here: an opener ``(Wiring) -> Transport | None`` (``None``: not configured) and its
       ``Registration`` in ``TRANSPORTS``.

The daemon (``jtc_hw.daemon.service``) starts the registered transports in this order after the
loop process, and closes them in the reverse order after the loop has stopped (so that the last
goal results reach every transport's clients). Nothing else names a transport.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from ..core.requests import Requests
from .server import Server
from .zenoh_iface import ZenohInterface

if TYPE_CHECKING:
    from ..settings import DaemonSettings

__all__ = ["TRANSPORTS", "Registration", "Transport", "Wiring"]


class Transport(Protocol):
    """One way in to the request layer, as the daemon starts and stops it."""

    async def start(self) -> None:
        """Serve from now on (bind, listen, declare; register any ``get_status`` section).

        Raises:
            JtcHwError: it cannot serve (said in one line, naming the setting); ``OSError``
                likewise for an address that cannot be bound.
        """

    async def close(self) -> None:
        """Stop serving, after letting its clients read what is queued. Idempotent. Never
        raises: errors while closing are logged."""


@dataclass(frozen=True)
class Wiring:
    """What a transport is built from.

    Attributes:
        requests: the request layer every transport shares.
        daemon: the robot file's ``daemon`` settings (each transport reads its own).
        controller: the controller's name (Zenoh's default prefix).
        add_observer: the backend's, for a transport that publishes all it observes (Zenoh).
        status: the backend's ``get_status`` facts, for a transport that watches them.
    """

    requests: Requests
    daemon: DaemonSettings
    controller: str
    add_observer: Callable[[Any], None]
    status: Callable[[], dict[str, Any]]


@dataclass(frozen=True)
class Registration:
    """A transport in ``TRANSPORTS``.

    Attributes:
        name: what it is called (``socket``, ``zenoh``).
        open: its transport for these settings, ``None`` when they do not ask for it.
        failure: how the daemon's log line begins when it cannot start.
    """

    name: str
    open: Callable[[Wiring], Transport | None]
    failure: str = "cannot start"


def _socket(wiring: Wiring) -> Transport:
    """The unix socket and TCP (``daemon.socket``, ``daemon.tcp``): always."""
    return Server(wiring.requests.backend, wiring.daemon, wiring.requests)


def _zenoh(wiring: Wiring) -> Transport | None:
    """Zenoh (``daemon.zenoh``), off when absent."""
    settings = wiring.daemon.zenoh
    if settings is None:
        return None
    return ZenohInterface(settings, wiring.controller, wiring.requests, wiring.status,
                          add_observer=wiring.add_observer)


def _ros2(wiring: Wiring) -> Transport | None:
    """ROS 2 over rmw_zenoh (``daemon.ros2``), off when absent."""
    settings = wiring.daemon.ros2
    if settings is None:
        return None
    from .ros2.node import Ros2Interface  # numpy, and rosbags when started: only if asked

    return Ros2Interface(settings, wiring.controller, wiring.requests,
                         add_observer=wiring.add_observer)


TRANSPORTS: tuple[Registration, ...] = (
    Registration("socket", _socket, "cannot open the socket"),
    Registration("zenoh", _zenoh),
    Registration("ros2", _ros2),
)
"""Every transport, in the order they start (closed in the reverse order)."""
