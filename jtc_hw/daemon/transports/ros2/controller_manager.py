"""What ``/controller_manager/list_controllers`` answers: our controllers as upstream lists them.

Theory of operation
-------------------
ROS 2's tools find a robot's controllers by asking its controller manager first:
``ros2 control list_controllers`` and rqt_joint_trajectory_controller call
``<ns>/controller_manager/list_controllers`` (``controller_manager_msgs/srv/ListControllers``,
``types.py``) and keep the controllers of type
``joint_trajectory_controller/JointTrajectoryController`` that are ``active``, taking the joints
from their command interfaces (``joint1/position``). The transport has no controller manager
(there is nothing to load, switch or unload), only this one service on a node named
``controller_manager`` (``daemon.ros2.controller_manager``), answered from the daemon's
configuration and status (``get_config``, ``get_status``), as upstream's would be:

- the trajectory controller: ``name`` its node's name, ``state`` ``active`` while
  ``get_status`` says the controller is active and not faulted, else ``inactive``;
  ``update_rate`` the loop's (Jazzy and later; uint16); ``claimed_interfaces`` and
  ``required_command_interfaces`` ``<joint>/<interface>`` for every joint and configured command
  interface, joint by joint as upstream's ``command_interface_configuration`` names them, then
  ``speed_scaling.command_interface`` if one is configured; ``required_state_interfaces`` the
  same for the state interfaces (and ``speed_scaling.state_interface``). rqt takes the joints
  from the ``<joint>/position`` state interfaces, which every configuration has;
- the broadcaster, when ``daemon.ros2.joint_state_broadcaster`` makes its node:
  ``joint_state_broadcaster/JointStateBroadcaster``, the state interfaces required and none
  claimed (a broadcaster claims no command interface), active while the daemon runs.

Every other field (``is_async``, chaining, exported and reference interfaces) is empty or
false: the daemon's controllers are neither asynchronous nor chainable.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

from ....api.requests import GetConfig, GetStatus
from .messages import Messages, make

if TYPE_CHECKING:
    from ...core.requests import Caller, Requests

__all__ = [
    "BROADCASTER_TYPE",
    "CONTROLLER_MANAGER_NODE",
    "CONTROLLER_STATE",
    "JTC_TYPE",
    "LIST_CONTROLLERS",
    "ControllerEntry",
    "controllers",
    "list_controllers",
    "list_controllers_response",
]

CONTROLLER_MANAGER_NODE: Final = "controller_manager"
LIST_CONTROLLERS: Final = "controller_manager_msgs/srv/ListControllers"
CONTROLLER_STATE: Final = "controller_manager_msgs/msg/ControllerState"
JTC_TYPE: Final = "joint_trajectory_controller/JointTrajectoryController"
BROADCASTER_TYPE: Final = "joint_state_broadcaster/JointStateBroadcaster"
BROADCASTER_NODE: Final = "joint_state_broadcaster"
_UINT16_MAX: Final = 0xFFFF


@dataclass(frozen=True)
class ControllerEntry:
    """One ``ControllerState`` of the response (the fields we fill)."""

    name: str
    state: str
    type: str
    update_rate: int
    claimed_interfaces: tuple[str, ...] = ()
    required_command_interfaces: tuple[str, ...] = ()
    required_state_interfaces: tuple[str, ...] = ()


def _interfaces(joints: Sequence[str], interfaces: Iterable[str]) -> tuple[str, ...]:
    """``<joint>/<interface>``, joint by joint (upstream's interface configuration order)."""
    kinds = list(interfaces)
    return tuple(f"{joint}/{kind}" for joint in joints for kind in kinds)


def _rate(value: Any) -> int:
    """The update rate as a ``uint16`` (0 if unknown)."""
    try:
        return max(0, min(_UINT16_MAX, round(float(value))))
    except (TypeError, ValueError):
        return 0


def controllers(node_name: str, joints: Sequence[str], config: Mapping[str, Any],
                status: Mapping[str, Any], broadcaster: bool) -> list[ControllerEntry]:
    """The controllers to list (module docstring).

    Args:
        node_name: the trajectory controller's node name.
        joints: its joints, in order.
        config: ``get_config``'s ``controller`` section (``command_interfaces``,
            ``state_interfaces``, ``update_rate``, ``speed_scaling``).
        status: ``get_status``'s reply (its ``controller`` section says ``active``, ``fault``).
        broadcaster: whether the ``joint_state_broadcaster`` node exists.
    """
    controller = status.get("controller") or {}
    active = bool(controller.get("active")) and not controller.get("fault")
    rate = _rate(config.get("update_rate"))
    state = _interfaces(joints, config.get("state_interfaces") or ())
    scaling = config.get("speed_scaling") or {}
    command = _interfaces(joints, config.get("command_interfaces") or ()) + tuple(
        filter(None, [scaling.get("command_interface")]))
    jtc_state = state + tuple(filter(None, [scaling.get("state_interface")]))
    entries = [ControllerEntry(node_name, "active" if active else "inactive", JTC_TYPE, rate,
                               claimed_interfaces=command if active else (),
                               required_command_interfaces=command,
                               required_state_interfaces=jtc_state)]
    if broadcaster:
        entries.append(ControllerEntry(BROADCASTER_NODE, "active", BROADCASTER_TYPE, rate,
                                       required_state_interfaces=state))
    return entries


def list_controllers_response(messages: Messages, entries: Sequence[ControllerEntry]) -> bytes:
    """``ListControllers``' response (CDR) of ``entries``, in the distro's ``ControllerState``
    (Humble's has no ``update_rate``: :func:`.messages.make` leaves it out).

    Raises:
        KeyError: the distro's store lacks controller_manager_msgs (``types.py``).
    """
    store = messages.store
    states = [make(store, CONTROLLER_STATE, name=e.name, state=e.state, type=e.type,
                   update_rate=e.update_rate, claimed_interfaces=list(e.claimed_interfaces),
                   required_command_interfaces=list(e.required_command_interfaces),
                   required_state_interfaces=list(e.required_state_interfaces))
              for e in entries]
    return messages.response(LIST_CONTROLLERS, controller=states)


async def list_controllers(requests: Requests, caller: Caller, messages: Messages,
                           node_name: str, broadcaster: bool) -> bytes:
    """The response to a ``list_controllers`` call, from ``get_config`` and ``get_status`` as
    the request layer answers them (a failed one: its section taken as empty)."""
    config = await requests.answer(caller, GetConfig())
    status = await requests.answer(caller, GetStatus())
    section = config.message.get("config", {}).get("controller", {}) if config.ok else {}
    entries = controllers(node_name, requests.backend.joint_names, section,
                          status.message if status.ok else {}, broadcaster)
    return list_controllers_response(messages, entries)
