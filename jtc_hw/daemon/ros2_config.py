"""The ``daemon.ros2`` section: the daemon as upstream's controller in a ROS 2 graph (rmw_zenoh).

``daemon.ros2`` (absent: no ROS 2) starts the transport of ``jtc_hw.daemon.transports.ros2``
(docs/ros2.md)::

    daemon:
      ros2:
        domain_id: 0                    # ROS_DOMAIN_ID of the workstations
        namespace: ""                   # the nodes' namespace ("" or /robot1)
        controller_name: arm_controller # default: the controller's name in this file
        distro: jazzy                   # humble | jazzy | kilted | rolling: message layouts
        joint_state_broadcaster: true   # a second node publishing /joint_states
        controller_manager: true        # a node answering list_controllers (ros2 control)
        zenoh:                          # the session, as rmw_zenoh's nodes open theirs
          mode: client                  # client of the router (rmw_zenohd), or peer
          connect: [tcp/127.0.0.1:7447]
          listen: []                    # default: none
          config: /etc/jtc-hw/ros2-zenoh.json5   # optional Zenoh configuration file

The defaults are what an ``rmw_zenoh`` node does out of the box: a Zenoh client of the router
on ``tcp/127.0.0.1:7447`` (``ros2 run rmw_zenoh_cpp rmw_zenohd``), domain 0. The session is
made and checked by :mod:`.zenoh_config`, ``daemon.zenoh``'s (one code for both): nothing
listens unless asked, no multicast scouting, and a listen endpoint that is not loopback is
refused without TLS or authentication in the configuration file. ROS 2 has no credential of
its own: whoever reaches the Zenoh network of the domain commands the robot, as with upstream's
controller (docs/ros2.md, "Security").
"""

from __future__ import annotations

import multiprocessing
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Final

from ..config.schema import ParamKind, ParamSpec, param_table
from ..errors import ConfigurationError
from .zenoh_config import LOOP_PROCESS, MODES, ZenohSettings, check_security

__all__ = [
    "DEFAULT_CONNECT",
    "DISTROS",
    "INSTALL_HINT",
    "ROS2_PARAMETERS",
    "ROS2_ZENOH_PARAMETERS",
    "Ros2Settings",
    "ros2_settings",
]

INSTALL_HINT: Final = "pip install 'jtc_hw[ros2]'"
DISTROS: Final = ("humble", "jazzy", "kilted", "rolling")
"""The ROS 2 distributions whose message layouts and type hashes the transport speaks."""
DEFAULT_CONNECT: Final = ("tcp/127.0.0.1:7447",)
"""rmw_zenoh's router on this machine (its session default, ``tcp/localhost:7447``)."""
MAX_DOMAIN_ID: Final = 232
"""Largest ``ROS_DOMAIN_ID`` ROS 2 accepts."""

_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")

ROS2_ZENOH_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("mode", ParamKind.STRING, "client",
              "Zenoh session mode: client of the router (rmw_zenoh's default), or peer",
              choices=MODES),
    ParamSpec("connect", ParamKind.STRINGS, DEFAULT_CONNECT,
              "Zenoh endpoints to connect to: the rmw_zenoh router"),
    ParamSpec("listen", ParamKind.STRINGS, (),
              "Zenoh endpoints to listen on (default: none); a non-loopback one needs TLS or "
              "authentication in config"),
    ParamSpec("config", ParamKind.STRING, None,
              "Zenoh configuration file (JSON5), passed through: TLS, authentication",
              nullable=True),
)
"""``daemon.ros2.zenoh.*``."""

ROS2_PARAMETERS: Final[Mapping[str, ParamSpec]] = param_table(
    ParamSpec("domain_id", ParamKind.INT, 0, "ROS_DOMAIN_ID of the graph", minimum=0,
              maximum=MAX_DOMAIN_ID),
    ParamSpec("namespace", ParamKind.STRING, "",
              "namespace of the nodes (\"\": none; e.g. /robot1)"),
    ParamSpec("controller_name", ParamKind.STRING, None,
              "the controller node's name, which prefixes its topics and action (default: the "
              "controller's name in this file)", nullable=True),
    ParamSpec("distro", ParamKind.STRING, "jazzy",
              "ROS 2 distribution of the workstations: message layouts and type hashes",
              choices=DISTROS),
    ParamSpec("joint_state_broadcaster", ParamKind.BOOL, True,
              "publish /joint_states from a second node named joint_state_broadcaster"),
    ParamSpec("controller_manager", ParamKind.BOOL, True,
              "a node named controller_manager answering list_controllers, which ros2 control "
              "and rqt_joint_trajectory_controller ask first"),
    ParamSpec("zenoh", ParamKind.SECTION, MappingProxyType({}),
              "the Zenoh session (rmw_zenoh's defaults: client of tcp/127.0.0.1:7447)",
              nullable=True, fields=ROS2_ZENOH_PARAMETERS),
)
"""``daemon.ros2.*``."""


@dataclass(frozen=True)
class Ros2Settings:
    """``daemon.ros2``: the ROS 2 transport (``jtc_hw.daemon.transports.ros2``); one field per
    row of :data:`ROS2_PARAMETERS`, ``zenoh`` as ``daemon.zenoh``'s settings (its ``token``
    unused: ROS 2 has none), ``namespace`` normalised to ``""`` or ``/a/b``."""

    domain_id: int = 0
    namespace: str = ""
    controller_name: str | None = None
    distro: str = "jazzy"
    joint_state_broadcaster: bool = True
    controller_manager: bool = True
    zenoh: ZenohSettings = field(
        default_factory=lambda: ZenohSettings(mode="client", connect=DEFAULT_CONNECT, listen=()))

    def node_name(self, controller: str) -> str:
        """The controller node's name for a controller named ``controller`` in the file."""
        return self.controller_name or controller


def _namespace(value: str) -> str:
    """``""``, or ``/a/b`` from ``a/b`` or ``/a/b/``.

    Raises:
        ConfigurationError: a token that is not a ROS name (letters, digits, ``_``, not
            starting with a digit).
    """
    tokens = [t for t in value.strip().split("/") if t]
    for token in tokens:
        if not _NAME.fullmatch(token):
            raise ConfigurationError(
                f"{value!r}: {token!r} is not a ROS name (letters, digits and _, not starting "
                "with a digit)", "daemon.ros2.namespace", value)
    return "".join("/" + t for t in tokens)


def ros2_settings(values: Mapping[str, Any], base_dir: str) -> Ros2Settings:
    """Settings of a validated ``daemon.ros2`` mapping, checked against the security rule of
    ``daemon.zenoh`` (:func:`.zenoh_config.check_security`; as there, the loop process does
    not read the configuration file again).

    Raises:
        ConfigurationError: a bad namespace or controller name, a missing configuration file,
            a non-loopback listen endpoint without TLS or authentication, no endpoint at all.
    """
    name = values["controller_name"]
    if name is not None and not _NAME.fullmatch(name):
        raise ConfigurationError(
            f"{name!r} is not a ROS node name (letters, digits and _, not starting with a "
            "digit)", "daemon.ros2.controller_name", name)
    z = values["zenoh"]
    config = z["config"]
    if config is not None:
        if not config.strip():
            raise ConfigurationError("is empty; give a file, or remove the key",
                                     "daemon.ros2.zenoh.config", config)
        config = os.path.normpath(os.path.join(base_dir, os.path.expanduser(config)))
        if not os.path.isfile(config):
            raise ConfigurationError(f"{config} is not a file", "daemon.ros2.zenoh.config",
                                     config)
    zenoh = ZenohSettings(mode=z["mode"], connect=tuple(z["connect"]),
                          listen=tuple(z["listen"]), config=config)
    for endpoint in (*zenoh.connect, *(zenoh.listen or ())):
        if "/" not in endpoint:
            raise ConfigurationError(
                f"{endpoint!r} is not a Zenoh endpoint: write <protocol>/<address>:<port>, "
                "e.g. tcp/127.0.0.1:7447", "daemon.ros2.zenoh", endpoint)
    try:
        # Not in the loop process with a file to read (zenoh_config.zenoh_settings: why).
        if zenoh.config is None or multiprocessing.current_process().name != LOOP_PROCESS:
            check_security(zenoh)
    except ConfigurationError as exc:  # named as daemon.zenoh's keys: say ours
        text = str(exc)[len(exc.path) + 2:] if exc.path else str(exc)
        path = exc.path.replace("daemon.zenoh", "daemon.ros2.zenoh", 1)
        raise ConfigurationError(text.replace("daemon.zenoh.", "daemon.ros2.zenoh."), path,
                                 exc.value) from None
    return Ros2Settings(
        domain_id=values["domain_id"],
        namespace=_namespace(values["namespace"]),
        controller_name=name,
        distro=values["distro"],
        joint_state_broadcaster=values["joint_state_broadcaster"],
        controller_manager=values["controller_manager"],
        zenoh=zenoh,
    )
