"""The ROS 2 side of the tests: an independent rmw_zenoh client, built on zenoh-ros2-sdk.

Issue 25 asks for a second implementation of the rmw_zenoh protocol, not written here, to play
the ROS 2 workstation in the tests: ``zenoh-ros2-sdk`` (0.1.8, pure Python, from the package
index). Nothing of ``jtc_hw.daemon.transports.ros2`` is imported: where the two agree on the
wire it is because both follow rmw_zenoh, not because they share code.

Theory of operation
-------------------
The sdk does the wire: key expressions ``<domain>/<name>/<dds type>/<RIHS01 hash>``, the
``@ros2_lv/...`` liveliness tokens (one NN token per entity, then its MP/MS/SS/SC token), the
33-byte attachment (u64 sequence number, u64 source timestamp in ns, u8 GID length 16, the
16-byte GID, little-endian) on every sample, query and reply, CDR via rosbags. This module
fixes what it lacks for our tests::

    Ros2Peer ── one sdk ZenohSession (peer mode, connect <endpoint>, listen tcp/localhost:0)
      │  store      = Types(distro): rosbags' store of the distro + control_msgs of the distro
      │               (.msg/.srv/.action text) + what rosidl makes of an action + CancelGoal
      │  hashes     = the sdk's own RIHS01 code, given rosidl-style text made from the store
      │               (Humble: TypeHashNotSupported)
      │  graph      = a liveliness subscriber (history on): nodes(), topics(), actions(), waits
      └─ entities   = sdk publishers, subscribers, service clients/servers, built on demand

* **Offline.** The sdk loads a definition it does not know by cloning its package's git
  repository (``message_registry.get_registry()`` -> ``_cache.clone_to_cache``). Importing this
  module replaces that registry with one that raises :class:`OfflineTypeError`, and every
  entity is created with its type registered beforehand and its hash given, so the sdk never
  reaches for a definition.
* **Two peers in one process.** The sdk keeps one session per process
  (``ZenohSession.get_instance``); entities look it up once, when built. Each peer opens its
  own session and makes it the current one, under a lock, while it builds an entity.
* **Hashes.** The sdk hashes a message from its ``.msg`` text and a service from its two
  halves (with ``service_msgs/msg/ServiceEventInfo`` written out as rosidl has it: ``char`` is
  ``uint8``). Its service hash spells the request ``<pkg>/srv/<Name>_Request``, which is wrong
  for an action's services (``<pkg>/action/<Name>_SendGoal_Request``):
  :meth:`Types.service_hash` builds the same description with the right names from the
  sdk's parts (checked against rosidl's own output: tests/daemon/ros2/test_peer.py).
* **Actions** (the sdk has none) are what rclcpp_action makes of them: the services
  ``<action>/_action/send_goal``, ``cancel_goal`` (``action_msgs/srv/CancelGoal``) and
  ``get_result``, the topics ``<action>/_action/feedback`` (``<Type>_FeedbackMessage``) and
  ``<action>/_action/status`` (``action_msgs/msg/GoalStatusArray``, transient local, depth 1).
  ``ros2 action list`` finds an action by its feedback topic; :meth:`Ros2Peer.actions` too.
* **Transient local** subscriptions (the status topic) get the last samples as rmw_zenoh's
  do, by asking the publisher's cache (the sdk queries ``<key>/@adv/pub/<zid>/**``, the
  AdvancedPublisher's), once, when declared.
* **Bad input** for the tests: a payload given as ``bytes`` is sent as it is, and a
  ``type_hash`` may replace the type's own.
* **A process of its own**: ``python -m helpers.ros2_peer`` (from tests/), :func:`main`.

Everything that waits, waits on an event (a reply, a sample, a graph change) with a timeout.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore
from zenoh_ros2_sdk import _cache, message_registry, utils
from zenoh_ros2_sdk.attachment import Attachment
from zenoh_ros2_sdk.discovery import _parse_liveliness_keyexpr
from zenoh_ros2_sdk.publisher import ROS2Publisher
from zenoh_ros2_sdk.qos import QosDurability, QosProfile
from zenoh_ros2_sdk.service_client import ROS2ServiceClient
from zenoh_ros2_sdk.service_server import ROS2ServiceServer
from zenoh_ros2_sdk.session import ZenohSession
from zenoh_ros2_sdk.subscriber import ROS2Subscriber

FJT = "control_msgs/action/FollowJointTrajectory"
"""The action type upstream's JTC serves."""

STATUS_QOS = QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1)
"""rcl_action's status topic QoS (``rcl_action_qos_profile_status_default``)."""

# GoalStatus values (action_msgs/msg/GoalStatus.msg)
STATUS_UNKNOWN, STATUS_ACCEPTED, STATUS_EXECUTING, STATUS_CANCELING = 0, 1, 2, 3
STATUS_SUCCEEDED, STATUS_CANCELED, STATUS_ABORTED = 4, 5, 6

# -- the type store -------------------------------------------------------------------------

DISTROS = ("humble", "jazzy", "kilted", "rolling")
NO_HASH = "TypeHashNotSupported"
"""What Humble's rmw_zenoh writes where later distros write a RIHS01 hash."""

# control_msgs as each distro ships it (ros-controls/control_msgs; comments dropped, fields and
# constants as there): Jazzy = tag 5.8.0 (f901df2662f22a39a06aa04a85a34602c47e3cc0, branch
# jazzy); Humble = branch humble (2e31e46, 4.8.0+29); Kilted and Rolling = master (13dacdd,
# 6.8.0), where FollowJointTrajectory's feedback has `index` and `multi_dof_index` (6.3.0 on).
_TOLERANCES = {
    "control_msgs/msg/JointTolerance": """
string name
float64 position
float64 velocity
float64 acceleration
""",
    "control_msgs/msg/JointComponentTolerance": """
uint16 X_AXIS=1
uint16 Y_AXIS=2
uint16 Z_AXIS=3
uint16 TRANSLATION=4
uint16 ROTATION=5
string joint_name
uint16 component
float64 position
float64 velocity
float64 acceleration
""",
}
_STATE_JAZZY = """
std_msgs/Header header
string[] joint_names
trajectory_msgs/JointTrajectoryPoint reference
trajectory_msgs/JointTrajectoryPoint feedback
trajectory_msgs/JointTrajectoryPoint error
trajectory_msgs/JointTrajectoryPoint output
string[] multi_dof_joint_names
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_reference
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_feedback
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_error
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_output
float64 speed_scaling_factor
"""
_STATE_HUMBLE = """
std_msgs/Header header
string[] joint_names
trajectory_msgs/JointTrajectoryPoint reference
trajectory_msgs/JointTrajectoryPoint feedback
trajectory_msgs/JointTrajectoryPoint error
trajectory_msgs/JointTrajectoryPoint output
trajectory_msgs/JointTrajectoryPoint desired
trajectory_msgs/JointTrajectoryPoint actual
string[] multi_dof_joint_names
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_reference
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_feedback
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_error
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_output
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_desired
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_actual
"""
_SPEED_SCALING = {"control_msgs/msg/SpeedScalingFactor": "float64 factor\n"}  # Jazzy and later
# controller_manager_msgs (ros-controls/ros2_control, comments dropped): ControllerState of
# branch humble, and of jazzy / kilted / master (is_async, update_rate, exported_state_interfaces
# added); ChainConnection and ListControllers.srv the same on all four.
_CM_STATE_HUMBLE = """
string name
string state
string type
string[] claimed_interfaces
string[] required_command_interfaces
string[] required_state_interfaces
bool is_chainable
bool is_chained
string[] reference_interfaces
controller_manager_msgs/ChainConnection[] chain_connections
"""
_CM_STATE_JAZZY = """
string name
string state
string type
bool is_async
uint16 update_rate
string[] claimed_interfaces
string[] required_command_interfaces
string[] required_state_interfaces
bool is_chainable
bool is_chained
string[] exported_state_interfaces
string[] reference_interfaces
controller_manager_msgs/ChainConnection[] chain_connections
"""
_CHAIN_CONNECTION = {"controller_manager_msgs/msg/ChainConnection":
                     "string name\nstring[] reference_interfaces\n"}
_SERVICES = {  # srv type -> (request, response); the same in every distro
    "control_msgs/srv/QueryTrajectoryState": ("""
builtin_interfaces/Time time
""", """
bool success
string message
string[] name
float64[] position
float64[] velocity
float64[] acceleration
"""),
    # ros2/rcl_interfaces action_msgs/srv/CancelGoal.srv
    "action_msgs/srv/CancelGoal": ("""
action_msgs/GoalInfo goal_info
""", """
int8 ERROR_NONE=0
int8 ERROR_REJECTED=1
int8 ERROR_UNKNOWN_GOAL_ID=2
int8 ERROR_GOAL_TERMINATED=3
int8 return_code
action_msgs/GoalInfo[] goals_canceling
"""),
    "controller_manager_msgs/srv/ListControllers": (
        "", "controller_manager_msgs/ControllerState[] controller\n"),
    # ros2/example_interfaces srv/AddTwoInts.srv: the design doc's hash example
    "example_interfaces/srv/AddTwoInts": ("int64 a\nint64 b\n", "int64 sum\n"),
}
_FJT_GOAL = """
trajectory_msgs/JointTrajectory trajectory
trajectory_msgs/MultiDOFJointTrajectory multi_dof_trajectory
control_msgs/JointTolerance[] path_tolerance
control_msgs/JointComponentTolerance[] component_path_tolerance
control_msgs/JointTolerance[] goal_tolerance
control_msgs/JointComponentTolerance[] component_goal_tolerance
builtin_interfaces/Duration goal_time_tolerance
"""
_FJT_RESULT = """
int32 SUCCESSFUL=0
int32 INVALID_GOAL=-1
int32 INVALID_JOINTS=-2
int32 OLD_HEADER_TIMESTAMP=-3
int32 PATH_TOLERANCE_VIOLATED=-4
int32 GOAL_TOLERANCE_VIOLATED=-5
int32 error_code
string error_string
"""
_FJT_FEEDBACK = """
std_msgs/Header header
string[] joint_names
trajectory_msgs/JointTrajectoryPoint desired
trajectory_msgs/JointTrajectoryPoint actual
trajectory_msgs/JointTrajectoryPoint error
string[] multi_dof_joint_names
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_desired
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_actual
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_error
"""
_FJT_FEEDBACK_6_3 = """
std_msgs/Header header
string[] joint_names
trajectory_msgs/JointTrajectoryPoint desired
trajectory_msgs/JointTrajectoryPoint actual
trajectory_msgs/JointTrajectoryPoint error
int32 index
string[] multi_dof_joint_names
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_desired
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_actual
trajectory_msgs/MultiDOFJointTrajectoryPoint multi_dof_error
int32 multi_dof_index
"""
_DISTRO = {  # distro -> (rosbags store, controller_state, FJT feedback, speed scaling)
    "humble": (Stores.ROS2_HUMBLE, _STATE_HUMBLE, _FJT_FEEDBACK, False),
    "jazzy": (Stores.ROS2_JAZZY, _STATE_JAZZY, _FJT_FEEDBACK, True),
    "kilted": (Stores.ROS2_KILTED, _STATE_JAZZY, _FJT_FEEDBACK_6_3, True),
    "rolling": (Stores.ROS2_KILTED, _STATE_JAZZY, _FJT_FEEDBACK_6_3, True),
}


def _action_parts(action_type: str) -> dict[str, str]:
    """The messages rosidl generates for an action beside its goal, result and feedback
    (rosidl_adapter's action conversion): the send_goal and get_result halves and the
    feedback message, each naming its siblings in full."""
    uid = "unique_identifier_msgs/UUID goal_id\n"
    return {
        f"{action_type}_SendGoal_Request": f"{uid}{action_type}_Goal goal\n",
        f"{action_type}_SendGoal_Response": "bool accepted\nbuiltin_interfaces/Time stamp\n",
        f"{action_type}_GetResult_Request": uid,
        f"{action_type}_GetResult_Response": f"int8 status\n{action_type}_Result result\n",
        f"{action_type}_FeedbackMessage": f"{uid}{action_type}_Feedback feedback\n",
    }


def _action_texts(action_type: str, goal: str, result: str, feedback: str) -> dict[str, str]:
    return {f"{action_type}_Goal": goal, f"{action_type}_Result": result,
            f"{action_type}_Feedback": feedback, **_action_parts(action_type)}


def _canonical(store_key: str) -> str:
    return store_key.replace("/srv/msg/", "/srv/")


_NUMPY = {"bool": np.bool_, "int8": np.int8, "uint8": np.uint8, "byte": np.uint8,
          "char": np.uint8, "octet": np.uint8, "int16": np.int16, "uint16": np.uint16,
          "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
          "float32": np.float32, "float64": np.float64}


class Types:
    """One distro's message definitions (``store``: rosbags' store of that distro plus
    control_msgs' text of that distro) and its type hashes, by the sdk's code."""

    def __init__(self, distro: str) -> None:
        if distro not in _DISTRO:
            raise ValueError(f"distro must be one of {DISTROS}, not {distro!r}")
        base, state, feedback, speed_scaling = _DISTRO[distro]
        self.distro = distro
        self.hashes = distro != "humble"
        self.store: Typestore = get_typestore(base)
        self.aliases: dict[str, str] = {}
        """Every name the sdk may look a type up by -> the store's key."""
        texts = {**_TOLERANCES, "control_msgs/msg/JointTrajectoryControllerState": state,
                 **(_SPEED_SCALING if speed_scaling else {}), **_CHAIN_CONNECTION,
                 "controller_manager_msgs/msg/ControllerState":
                     _CM_STATE_JAZZY if speed_scaling else _CM_STATE_HUMBLE}
        for srv, (req, resp) in _SERVICES.items():
            texts[f"{srv}_Request"], texts[f"{srv}_Response"] = req, resp
        texts.update(_action_texts(FJT, _FJT_GOAL, _FJT_RESULT, feedback))
        self._register(texts)
        self.aliases.update({k: k for k in self.store.types if k not in self.aliases})

    def _register(self, texts: dict[str, str]) -> None:
        for name, text in texts.items():
            found = get_types_from_msg(text, name)
            self.store.register(found)
            (key,) = found  # rosbags files <pkg>/srv/<T> under <pkg>/srv/msg/<T>
            self.aliases[name] = key
            # the sdk names a service's halves <pkg>/srv/<Name>_Request, actions' too
            pkg, _kind, base = name.split("/")
            self.aliases.setdefault(f"{pkg}/srv/{base}", key)

    def register_action(self, action_type: str, goal: str, result: str, feedback: str) -> None:
        """Add an action type (its goal, result and feedback as ``.msg`` text, nested types
        named in full) and the types rosidl generates for it."""
        self._register(_action_texts(action_type, goal, result, feedback))

    def key(self, typename: str) -> str:
        """The store's key of ``typename``.

        Raises:
            OfflineTypeError: the store does not have it.
        """
        key = self.aliases.get(typename)
        if key is None:
            raise OfflineTypeError(f"{typename}: not in the {self.distro} test type store")
        return key

    # -- hashes --
    def msg_text(self, typename: str) -> str:
        """``typename``'s fields as rosidl-style ``.msg`` text with full type names (constants
        and defaults dropped: the type hash ignores them; ``char`` written as ``uint8``, as
        rosidl has it)."""

        def spell(node: tuple[Any, Any]) -> str:
            kind, desc = node
            if kind.name == "BASE":
                base, bound = desc
                base = {"char": "uint8"}.get(base, base)
                return f"{base}<={bound}" if bound else base
            if kind.name == "NAME":
                return _canonical(desc)
            inner, size = desc
            if kind.name == "ARRAY":
                return f"{spell(inner)}[{size}]"
            return f"{spell(inner)}[<={size}]" if size else f"{spell(inner)}[]"

        _consts, fields = self.store.fielddefs[self.key(typename)]
        return "".join(f"{spell(node)} {name}\n" for name, node in fields)

    def dependencies(self, typename: str) -> dict[str, str]:
        """Every type ``typename`` refers to, transitively -> its text."""
        out: dict[str, str] = {}
        todo = [self.key(typename)]
        while todo:
            _consts, fields = self.store.fielddefs[todo.pop()]
            for _name, node in fields:
                while node[0].name in ("ARRAY", "SEQUENCE"):
                    node = node[1][0]
                if node[0].name == "NAME" and _canonical(node[1]) not in out:
                    out[_canonical(node[1])] = self.msg_text(node[1])
                    todo.append(node[1])
        return out

    def message_hash(self, typename: str) -> str:
        """The RIHS01 hash of a message type by the sdk's code (``utils.get_type_hash``);
        Humble's ``TypeHashNotSupported``.

        Raises:
            OfflineTypeError: the store does not have ``typename``.
        """
        self.key(typename)  # a type it does not have is an error in every distro
        if not self.hashes:
            return NO_HASH
        return str(utils.get_type_hash(typename, self.msg_text(typename),
                                       self.dependencies(typename)))

    def service_hash(self, srv_type: str) -> str:
        """The RIHS01 hash of a service type (an action's ``_SendGoal``/``_GetResult`` too):
        the description the sdk's ``compute_service_type_hash`` builds, with the halves named
        as rosidl names them (``<srv_type>_Request``, ``_Response``, ``_Event``); Humble's
        ``TypeHashNotSupported``.

        Raises:
            OfflineTypeError: the store does not have the service.
        """
        self.key(f"{srv_type}_Request")
        if not self.hashes:
            return NO_HASH
        req, resp, event = f"{srv_type}_Request", f"{srv_type}_Response", f"{srv_type}_Event"
        info = "service_msgs/msg/ServiceEventInfo"
        type_map: dict[str, Any] = {}
        texts = {req: self.msg_text(req), resp: self.msg_text(resp), info: self.msg_text(info),
                 **self.dependencies(req), **self.dependencies(resp),
                 **self.dependencies(info)}
        for name, text in texts.items():
            fields = utils._parse_msg_definition(text) or [
                {"name": utils.EMPTY_STRUCTURE_REQUIRED_MEMBER_NAME, "type": "uint8",
                 "is_array": False, "array_size": 0}]
            type_map[name] = utils._serialize_type_description(name, fields)
        ids = utils.FIELD_TYPE_NAME_TO_ID

        def field(name: str, type_id: str, nested: str, capacity: int = 0) -> dict[str, Any]:
            return {"name": name, "type": {"type_id": ids[type_id], "capacity": capacity,
                                           "string_capacity": 0, "nested_type_name": nested},
                    "default_value": ""}

        nested, seq = "FIELD_TYPE_NESTED_TYPE", "FIELD_TYPE_NESTED_TYPE_BOUNDED_SEQUENCE"
        type_map[event] = {"type_name": event, "fields": [
            field("info", nested, info), field("request", seq, req, 1),
            field("response", seq, resp, 1)]}
        type_map[srv_type] = {"type_name": srv_type, "fields": [
            field("request_message", nested, req), field("response_message", nested, resp),
            field("event_message", nested, event)]}
        description = utils._extract_full_type_description(srv_type, type_map)
        return str(utils._calculate_type_hash(description))

    # -- messages --
    def make(self, typename: str, **values: Any) -> Any:
        """A message of ``typename`` with ``values`` (dicts for nested messages, lists for
        sequences, made into the numpy arrays rosbags wants) and every other field
        zero/empty.

        Raises:
            OfflineTypeError: ``typename`` is not in the store.
            TypeError: a field ``typename`` does not have.
        """
        key = self.key(typename)
        _consts, fields = self.store.fielddefs[key]
        unknown = set(values) - {name for name, _node in fields}
        if unknown:
            raise TypeError(f"{typename} has no field {sorted(unknown)}")
        return self.store.types[key](
            **{name: self._value(node, values.get(name)) for name, node in fields})

    def _value(self, node: tuple[Any, Any], value: Any) -> Any:
        kind, desc = node
        if kind.name == "BASE":
            if value is not None:
                return value
            return "" if desc[0] in ("string", "wstring") else _NUMPY[desc[0]]().item()
        if kind.name == "NAME":
            if value is None or isinstance(value, dict):
                return self.make(_canonical(desc), **(value or {}))
            return value
        inner, size = desc
        length = size if kind.name == "ARRAY" else 0
        if inner[0].name == "BASE" and inner[1][0] in _NUMPY:
            return np.asarray(np.zeros(length) if value is None else value,
                              dtype=_NUMPY[inner[1][0]])
        items = list(value) if value is not None else [None] * length
        return [self._value(inner, v) for v in items]


_TYPES: dict[str, Types] = {}


def types(distro: str = "jazzy") -> Types:
    """The :class:`Types` of ``distro`` (built once).

    Raises:
        ValueError: not one of :data:`DISTROS`.
    """
    if distro not in _TYPES:
        _TYPES[distro] = Types(distro)
    return _TYPES[distro]


class OfflineTypeError(LookupError):
    """A type the store does not have: the sdk would have downloaded its definition."""


JAZZY = types("jazzy")
STORE = JAZZY.store
"""Jazzy's store (the default distro's)."""
make, msg_text, message_hash, service_hash = (
    JAZZY.make, JAZZY.msg_text, JAZZY.message_hash, JAZZY.service_hash)
register_action = JAZZY.register_action


def fields_of(msg: Any) -> dict[str, Any]:
    """A message's top-level fields (the keyword arguments the sdk builds it from)."""
    return {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}


# -- the sdk, offline -----------------------------------------------------------------------


class _OfflineRegistry:
    """Stands in for the sdk's ``MessageRegistry``: it knows nothing and fetches nothing."""

    def _refuse(self, name: str, *_args: Any, **_kwargs: Any) -> Any:
        raise OfflineTypeError(f"{name}: not in the test type store (no download, ever)")

    get_msg_file_path = get_srv_file_path = load_message_type = load_service_type = _refuse
    get_message_class = _load_dependencies = _refuse

    def is_loaded(self, _name: str) -> bool:
        return False

    def _extract_dependencies(self, *_args: Any) -> list[str]:
        return []


def _no_download(*args: Any, **_kwargs: Any) -> Any:
    raise OfflineTypeError(f"zenoh-ros2-sdk tried to fetch definitions: {args}")


message_registry._registry = _OfflineRegistry()
message_registry.clone_to_cache = message_registry.get_message_file_path = _no_download
_cache.clone_to_cache = _cache.get_message_file_path = _no_download

_CURRENT = threading.Lock()
"""Held while an entity is built on a peer's session (the sdk's one-session-per-process)."""


def _open_session(ip: str, port: int, defs: Types) -> ZenohSession:
    """The sdk's session (its bundled rmw_zenoh-like config, connect tcp/<ip>:<port>) with
    ``defs``' store as its store; the environment's ZENOH_SESSION_CONFIG_URI /
    ZENOH_CONFIG_OVERRIDE are not consulted."""
    saved = {k: os.environ.pop(k) for k in ("ZENOH_SESSION_CONFIG_URI", "ZENOH_CONFIG_OVERRIDE")
             if k in os.environ}
    try:
        session = ZenohSession(ip, port)
    finally:
        os.environ.update(saved)
    session.store = defs.store
    session._registered_types = dict(defs.aliases)
    return session


# -- the peer -------------------------------------------------------------------------------


class Ros2CallError(RuntimeError):
    """A service answered with an error reply (or a reply that did not decode)."""


class Subscription:
    """Messages of one topic as they arrive (:meth:`Ros2Peer.subscribe`)."""

    def __init__(self, peer: Ros2Peer, topic: str, msg_type: str, qos: QosProfile | None,
                 on_message: Callable[[Any], None] | None = None) -> None:
        self.messages: list[Any] = []
        self._cond = threading.Condition()
        self._then = on_message
        self._sub = peer._build(lambda: ROS2Subscriber(
            topic, msg_type, self._on_message, node_name=peer.node_name,
            namespace=peer.namespace, domain_id=peer.domain_id,
            type_hash=peer.types.message_hash(msg_type), qos=qos))

    def _on_message(self, msg: Any) -> None:
        with self._cond:
            self.messages.append(msg)
            self._cond.notify_all()
        if self._then is not None:
            self._then(msg)

    def take(self, n: int = 1, timeout: float = 5.0) -> list[Any]:
        """The first ``n`` messages, once they have come.

        Raises:
            TimeoutError: fewer than ``n`` came within ``timeout`` seconds.
        """
        with self._cond:
            if not self._cond.wait_for(lambda: len(self.messages) >= n, timeout):
                raise TimeoutError(f"{len(self.messages)} of {n} messages in {timeout} s")
            return self.messages[:n]

    def close(self) -> None:
        self._sub.close()


class _Call:
    """One request in flight: its replies (all of them) and the end of the query."""

    def __init__(self) -> None:
        self.replies: list[Any] = []
        self.errors: list[str] = []
        self.done = threading.Event()
        self._cond = threading.Condition()

    def add(self, reply: Any | None, error: str | None) -> None:
        with self._cond:
            if error is None:
                self.replies.append(reply)
            else:
                self.errors.append(error)
            self._cond.notify_all()

    def first(self, timeout: float, what: str) -> Any:
        with self._cond:
            if not self._cond.wait_for(lambda: self.replies or self.errors, timeout):
                raise TimeoutError(f"{what}: no reply in {timeout} s")
            if self.errors:
                raise Ros2CallError(f"{what}: {self.errors[0]}")
            return self.replies[0]


class Ros2Peer:
    """A ROS 2 node on rmw_zenoh, as the tests need one (see the module docstring).

    ``endpoint`` is the router's (``tcp/127.0.0.1:7447``); ``distro`` chooses the definitions
    and hashes (:class:`Types`); ``peer.types.make(...)`` builds its messages. A context
    manager, or call :meth:`close`.

    Raises:
        ValueError: a bad endpoint or distro.
    """

    def __init__(self, endpoint: str, domain_id: int = 0, node_name: str = "jtc_hw_test_peer",
                 namespace: str = "/", distro: str = "jazzy") -> None:
        proto, _, address = endpoint.partition("/")
        ip, _, port = address.rpartition(":")
        if proto != "tcp" or not ip or not port.isdigit():
            raise ValueError(f"endpoint must be tcp/<ip>:<port>, not {endpoint!r}")
        self.domain_id, self.node_name, self.namespace = domain_id, node_name, namespace
        self.types = types(distro)
        self.session = _open_session(ip.strip("[]"), int(port), self.types)
        self._entities: list[Any] = []
        self._publishers: dict[tuple[str, str, str | None], ROS2Publisher] = {}
        self._clients: dict[tuple[str, str, str | None], ROS2ServiceClient] = {}
        self._action_subs: dict[str, tuple[Subscription, Subscription]] = {}
        self._goals: dict[bytes, GoalHandle] = {}
        self._graph: dict[str, dict[str, Any]] = {}
        self._graph_cond = threading.Condition()
        self._liveliness = self.session.session.liveliness().declare_subscriber(
            f"@ros2_lv/{domain_id}/**", self._on_token, history=True)

    # -- lifetime --
    def close_entities(self) -> None:
        """Undeclare every publisher, subscription, server and client (and their tokens); the
        session and its graph stay."""
        for entity in reversed(self._entities):
            entity.close()
        self._entities.clear()
        self._publishers.clear()
        self._clients.clear()
        self._action_subs.clear()

    def close(self) -> None:
        """Undeclare every entity and token, close the session."""
        self.close_entities()
        self._liveliness.undeclare()
        self.session.close()

    def __enter__(self) -> Ros2Peer:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _build(self, factory: Callable[[], Any]) -> Any:
        with _CURRENT:
            saved, ZenohSession._instance = ZenohSession._instance, self.session
            try:
                entity = factory()
            finally:
                ZenohSession._instance = saved
        self._entities.append(entity)
        return entity

    # -- the graph (liveliness) --
    def _on_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with self._graph_cond:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._graph.pop(key, None)
            else:
                parts = key.split("/")
                if len(parts) == 9 and parts[5] == "NN":
                    self._graph[key] = {"kind": "NN", "namespace": _unmangle(parts[7]),
                                        "node_name": parts[8]}
                else:
                    parsed = _parse_liveliness_keyexpr(key)
                    if parsed is not None:
                        self._graph[key] = parsed
            self._graph_cond.notify_all()

    def _entries(self, *kinds: str) -> list[dict[str, Any]]:
        with self._graph_cond:
            return [e for e in self._graph.values() if e["kind"] in kinds]

    def tokens(self) -> list[str]:
        """The liveliness tokens alive now (their key expressions)."""
        with self._graph_cond:
            return sorted(self._graph)

    def nodes(self) -> list[str]:
        """Fully qualified node names, as ``ros2 node list`` prints them."""
        return sorted({_join(e["namespace"], e["node_name"]) for e in self._entries("NN")})

    def topics(self, include_hidden: bool = False) -> dict[str, list[str]]:
        """Topic -> its types, from publishers and subscriptions (``ros2 topic list -t``)."""
        return _names_and_types(self._entries("MP", "MS"), include_hidden)

    def publishers(self, topic: str) -> list[dict[str, Any]]:
        """The publishers of ``topic``: node, type, hash and QoS from their tokens."""
        return [e for e in self._entries("MP") if e["qualified_name"] == topic]

    def services(self, include_hidden: bool = False) -> dict[str, list[str]]:
        """Service -> its types, from servers and clients (``ros2 service list -t``)."""
        return _names_and_types(self._entries("SS", "SC"), include_hidden)

    def servers(self, service: str) -> list[dict[str, Any]]:
        """The servers of ``service`` (their parsed tokens)."""
        return [e for e in self._entries("SS") if e["qualified_name"] == service]

    def actions(self) -> dict[str, list[str]]:
        """Action -> its types, as rcl_action finds them: by ``<action>/_action/feedback``
        topics whose type is ``<Type>_FeedbackMessage`` (``ros2 action list -t``)."""
        out: dict[str, list[str]] = {}
        for topic, types in self.topics(include_hidden=True).items():
            if topic.endswith("/_action/feedback"):
                kinds = [t[: -len("_FeedbackMessage")] for t in types
                         if t.endswith("_FeedbackMessage")]
                if kinds:
                    out[topic[: -len("/_action/feedback")]] = kinds
        return out

    def wait_until(self, predicate: Callable[[], bool], timeout: float = 5.0,
                   what: str = "the graph") -> None:
        """Return once ``predicate()`` holds, tried again at every graph change.

        Raises:
            TimeoutError: it did not hold within ``timeout`` seconds.
        """
        with self._graph_cond:
            if not self._graph_cond.wait_for(predicate, timeout):
                raise TimeoutError(f"{what}: not so within {timeout} s")

    # -- topics --
    def subscribe(self, topic: str, msg_type: str, qos: QosProfile | None = None) -> Subscription:
        """Start receiving ``topic`` (close it, or it ends with the peer)."""
        return Subscription(self, topic, msg_type, qos)

    def echo(self, topic: str, msg_type: str, n: int = 1, timeout: float = 5.0) -> list[Any]:
        """``ros2 topic echo``: the next ``n`` messages of ``topic``, decoded.

        Raises:
            TimeoutError: fewer than ``n`` came within ``timeout`` seconds.
        """
        sub = self.subscribe(topic, msg_type)
        try:
            return sub.take(n, timeout)
        finally:
            sub.close()
            self._entities.remove(sub._sub)

    def _publisher(self, topic: str, msg_type: str, qos: QosProfile | None,
                   type_hash: str | None) -> ROS2Publisher:
        key = (topic, msg_type, type_hash)
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = self._build(lambda: ROS2Publisher(
                topic, msg_type, node_name=self.node_name, namespace=self.namespace,
                domain_id=self.domain_id, qos=qos,
                type_hash=type_hash or self.types.message_hash(msg_type)))
        return pub

    def wait_for_subscriber(self, topic: str, msg_type: str, timeout: float,
                            qos: QosProfile | None = None, type_hash: str | None = None) -> None:
        """Declare the publisher of ``topic`` (if not yet) and wait until a subscriber matches
        its key expression.

        Raises:
            TimeoutError: none did within ``timeout`` seconds.
        """
        pub = self._publisher(topic, msg_type, qos, type_hash)
        matched = threading.Event()
        listener = pub.pub.declare_matching_listener(
            lambda status: matched.set() if status.matching else None)
        try:
            if not (pub.pub.matching_status.matching or matched.wait(timeout)):
                raise TimeoutError(f"no subscriber on {topic} in {timeout} s")
        finally:
            listener.undeclare()

    def publish(self, topic: str, msg_type: str, msg: Any, wait_for_subscriber: float = 0.0,
                qos: QosProfile | None = None, type_hash: str | None = None) -> None:
        """Publish ``msg`` (a message of ``msg_type``, or a dict for ``types.make``, or raw
        ``bytes`` sent as the payload as they are: malformed CDR for the bad-input tests);
        first wait up to ``wait_for_subscriber`` seconds for a subscriber to match.
        ``type_hash`` replaces the type's own in the key expression and token.

        Raises:
            TimeoutError: no subscriber matched in time.
        """
        pub = self._publisher(topic, msg_type, qos, type_hash)
        if wait_for_subscriber > 0:
            self.wait_for_subscriber(topic, msg_type, wait_for_subscriber, qos, type_hash)
        if isinstance(msg, (bytes, bytearray)):
            attachment = Attachment(pub.sequence_number, time.time_ns(), pub.publisher_gid)
            pub.pub.put(bytes(msg), encoding=zenoh.Encoding("application/cdr"),
                        attachment=attachment.to_bytes())
            pub.sequence_number += 1
            return
        if isinstance(msg, dict):
            msg = self.types.make(msg_type, **msg)
        pub.publish(**fields_of(msg))

    # -- services --
    def serve(self, service: str, srv_type: str, handler: Callable[[Any], Any]) -> None:
        """Serve ``service``: ``handler(request) -> response`` (the sdk's server)."""
        self._build(lambda: ROS2ServiceServer(
            service, srv_type, handler, node_name=self.node_name, namespace=self.namespace,
            domain_id=self.domain_id, type_hash=self.types.service_hash(srv_type)))

    def _client(self, service: str, srv_type: str, type_hash: str | None) -> ROS2ServiceClient:
        key = (service, srv_type, type_hash)
        client = self._clients.get(key)
        if client is None:
            # the query's own timeout is long: every wait here has its own
            client = self._clients[key] = self._build(lambda: ROS2ServiceClient(
                service, srv_type, node_name=self.node_name, namespace=self.namespace,
                domain_id=self.domain_id, timeout=3600.0,
                type_hash=type_hash or self.types.service_hash(srv_type)))
        return client

    def request(self, service: str, srv_type: str, request: Any, decode: bool = True,
                type_hash: str | None = None) -> _Call:
        """Send a request (a message, a dict for ``types.make``, or raw ``bytes`` sent as they
        are); its replies gather in the returned call as they come (decoded, or the payload's
        bytes with ``decode=False``). ``type_hash`` replaces the type's own in the key.

        Raises:
            OfflineTypeError, TypeError: ``request`` does not make a ``<srv_type>_Request``.
        """
        client = self._client(service, srv_type, type_hash)
        store = self.types.store
        if isinstance(request, dict):
            request = self.types.make(f"{srv_type}_Request", **request)
        if isinstance(request, (bytes, bytearray)):
            cdr = bytes(request)
        else:
            cdr = bytes(store.serialize_cdr(request, client.request_store_type))
        with client._lock:
            seq = client.sequence_number
            client.sequence_number += 1
        attachment = Attachment(seq, time.time_ns(), client.client_gid).to_bytes()
        call = _Call()

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                call.add(None, reply.err.payload.to_bytes().decode(errors="replace"))
                return
            payload = reply.ok.payload.to_bytes()
            if not decode:
                call.add(payload, None)
                return
            try:
                call.add(store.deserialize_cdr(payload, client.response_store_type), None)
            except Exception as exc:  # a reply that does not decode is the server's error
                call.add(None, f"undecodable reply: {exc!r}")

        client.querier.get(zenoh.handlers.Callback(on_reply, call.done.set),
                           payload=zenoh.ZBytes(cdr),
                           encoding=zenoh.Encoding("application/cdr"),
                           attachment=zenoh.ZBytes(attachment))
        return call

    def call(self, service: str, srv_type: str, request: Any, timeout: float = 5.0) -> Any:
        """Call ``service`` and return the (first) response.

        Raises:
            TimeoutError: no reply within ``timeout`` seconds (no server, or a slow one).
            Ros2CallError: the reply was an error.
        """
        return self.request(service, srv_type, request).first(timeout, service)

    # -- actions --
    def _action_topics(self, action: str, action_type: str) -> None:
        if action in self._action_subs:
            return
        self._action_subs[action] = (
            Subscription(self, f"{action}/_action/feedback", f"{action_type}_FeedbackMessage",
                         None, self._on_feedback),
            Subscription(self, f"{action}/_action/status", "action_msgs/msg/GoalStatusArray",
                         STATUS_QOS, self._on_status))

    def _on_feedback(self, msg: Any) -> None:
        handle = self._goals.get(bytes(msg.goal_id.uuid))
        if handle is not None:
            handle._add("feedback", msg.feedback)

    def _on_status(self, msg: Any) -> None:
        for status in msg.status_list:
            handle = self._goals.get(bytes(status.goal_info.goal_id.uuid))
            if handle is not None:
                handle._add("statuses", int(status.status))

    def action_ready(self, action: str) -> bool:
        """What rclcpp_action's ``wait_for_action_server`` waits for: the action's three
        services served, and its feedback and status topics published."""
        services = ("send_goal", "cancel_goal", "get_result")
        published = {e["qualified_name"] for e in self._entries("MP")}
        return all(self.servers(f"{action}/_action/{s}") for s in services) and {
            f"{action}/_action/feedback", f"{action}/_action/status"} <= published

    def wait_for_action(self, action: str, timeout: float = 5.0) -> None:
        """Return once :meth:`action_ready`.

        Raises:
            TimeoutError: it was not within ``timeout`` seconds.
        """
        self.wait_until(lambda: self.action_ready(action), timeout, f"the action {action}")

    def send_goal(self, action: str, goal: Any, action_type: str = FJT,
                  timeout: float = 5.0) -> GoalHandle:
        """Send a goal as rclcpp_action's client does: subscribe to the action's feedback and
        status, then call ``<action>/_action/send_goal`` with a fresh goal id.
        ``handle.accepted`` says whether the server took it.

        Raises:
            TimeoutError: the send_goal service did not answer in ``timeout`` seconds.
            Ros2CallError: it answered with an error.
        """
        self._action_topics(action, action_type)
        handle = GoalHandle(self, action, action_type, uuid.uuid4().bytes)
        self._goals[handle.goal_id] = handle
        if isinstance(goal, dict):
            goal = self.types.make(f"{action_type}_Goal", **goal)
        response = self.call(f"{action}/_action/send_goal", f"{action_type}_SendGoal",
                             {"goal_id": handle._uuid(), "goal": goal}, timeout)
        handle.accepted, handle.stamp = bool(response.accepted), response.stamp
        return handle


class GoalHandle:
    """One goal: its feedback and statuses as they come, its result, its cancel."""

    def __init__(self, peer: Ros2Peer, action: str, action_type: str, goal_id: bytes) -> None:
        self.peer, self.action, self.action_type, self.goal_id = peer, action, action_type, goal_id
        self.accepted = False
        self.stamp: Any = None
        self.feedback: list[Any] = []
        self.statuses: list[int] = []
        self.result_call: _Call | None = None
        self._cond = threading.Condition()
        self._on_change: Callable[[str, Any], None] | None = None

    def _uuid(self) -> dict[str, Any]:
        return {"uuid": np.frombuffer(self.goal_id, dtype=np.uint8)}

    def _add(self, what: str, value: Any) -> None:
        with self._cond:
            getattr(self, what).append(value)
            self._cond.notify_all()
            if self._on_change is not None:
                self._on_change(what, value)

    def wait_feedback(self, n: int = 1, timeout: float = 5.0) -> list[Any]:
        """The first ``n`` feedback messages of this goal.

        Raises:
            TimeoutError: fewer came within ``timeout`` seconds.
        """
        with self._cond:
            if not self._cond.wait_for(lambda: len(self.feedback) >= n, timeout):
                raise TimeoutError(f"{len(self.feedback)} of {n} feedback messages")
            return self.feedback[:n]

    def wait_status(self, status: int, timeout: float = 5.0) -> None:
        """Return once the status topic has said ``status`` for this goal.

        Raises:
            TimeoutError: it did not within ``timeout`` seconds.
        """
        with self._cond:
            if not self._cond.wait_for(lambda: status in self.statuses, timeout):
                raise TimeoutError(f"status {status} not seen; seen {self.statuses}")

    def result(self, timeout: float = 30.0) -> tuple[int, Any]:
        """``(status, result)`` from ``_action/get_result``, once the query is over (so that
        ``len(self.result_call.replies)`` counts every reply the server sent).

        Raises:
            TimeoutError: no reply, or the query did not end, within ``timeout`` seconds.
            Ros2CallError: the reply was an error.
        """
        if self.result_call is None:
            self.result_call = self.peer.request(
                f"{self.action}/_action/get_result", f"{self.action_type}_GetResult",
                {"goal_id": self._uuid()})
        deadline = time.monotonic() + timeout
        response = self.result_call.first(timeout, f"{self.action} get_result")
        if not self.result_call.done.wait(max(0.0, deadline - time.monotonic())):
            raise TimeoutError(f"{self.action} get_result: the query did not end")
        return int(response.status), response.result

    def cancel(self, timeout: float = 5.0) -> Any:
        """Ask the server to cancel this goal; the ``CancelGoal`` response (``return_code``,
        ``goals_canceling``).

        Raises:
            TimeoutError: no reply within ``timeout`` seconds.
            Ros2CallError: the reply was an error.
        """
        return self.peer.call(f"{self.action}/_action/cancel_goal", "action_msgs/srv/CancelGoal",
                              {"goal_info": {"goal_id": self._uuid()}}, timeout)


def _unmangle(mangled: str) -> str:
    return "/" if mangled in ("", "%") else mangled.replace("%", "/")


def _join(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def _names_and_types(entries: list[dict[str, Any]], include_hidden: bool) -> dict[str, list[str]]:
    out: dict[str, set[str]] = {}
    for e in entries:
        name = e["qualified_name"]
        if include_hidden or not any(part.startswith("_") for part in name.split("/")):
            out.setdefault(name, set()).add(utils.dds_to_ros_type(e["dds_type"]))
    return {name: sorted(types) for name, types in sorted(out.items())}


@contextmanager
def peer(endpoint: str, **kwargs: Any) -> Iterator[Ros2Peer]:
    """A :class:`Ros2Peer` for a ``with`` block."""
    p = Ros2Peer(endpoint, **kwargs)
    try:
        yield p
    finally:
        p.close()


# -- a second process -------------------------------------------------------------------------


def plain(msg: Any) -> Any:
    """A decoded message as JSON-ready data (dicts, lists, numbers, strings)."""
    if dataclasses.is_dataclass(msg) and not isinstance(msg, type):
        return {f.name: plain(getattr(msg, f.name)) for f in dataclasses.fields(msg)}
    if isinstance(msg, np.ndarray):
        return msg.tolist()
    if isinstance(msg, (list, tuple)):
        return [plain(m) for m in msg]
    return msg.item() if isinstance(msg, np.generic) else msg


def main(argv: list[str] | None = None) -> int:
    """``python -m helpers.ros2_peer`` (from tests/): the peer as a process of its own, e.g.
    the workstation's ``ros2`` in an end-to-end test. One JSON object per line on stdout.

    Exit status: 0 done; 1 a goal rejected or not SUCCEEDED; 2 a timeout.
    """
    import argparse
    import json

    parser = argparse.ArgumentParser(prog="python -m helpers.ros2_peer")
    parser.add_argument("--endpoint", default="tcp/127.0.0.1:7447")
    parser.add_argument("--domain-id", type=int, default=0)
    parser.add_argument("--distro", default="jazzy", choices=DISTROS)
    parser.add_argument("--timeout", type=float, default=10.0)
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("nodes", "topics", "actions"):
        sub.add_parser(name, help=f"wait for --until, then print {name} (ros2 ... list)") \
            .add_argument("--until", default="", help="a name to wait for")
    echo = sub.add_parser("echo", help="print the next N messages of a topic")
    echo.add_argument("topic")
    echo.add_argument("type")
    echo.add_argument("-n", type=int, default=1)
    goal = sub.add_parser("send_goal", help="send a goal (JSON), print feedback and result")
    goal.add_argument("action")
    goal.add_argument("goal", help="the goal as JSON, as make() takes it")
    goal.add_argument("--type", default=FJT)
    args = parser.parse_args(argv)

    printing = threading.Lock()

    def out(obj: Any) -> None:
        # One write per line, under a lock: feedback is printed from the sdk's thread while
        # the main thread prints the result (print's two writes interleaved two lines).
        with printing:
            sys.stdout.write(json.dumps(obj) + "\n")
            sys.stdout.flush()

    with Ros2Peer(args.endpoint, domain_id=args.domain_id, distro=args.distro,
                  node_name="jtc_hw_test_cli") as p:
        try:
            if args.command in ("nodes", "topics", "actions"):
                listing = getattr(p, args.command)
                if args.until:
                    p.wait_until(lambda: args.until in listing(), args.timeout, args.until)
                out(listing())
            elif args.command == "echo":
                sub_ = p.subscribe(args.topic, args.type)
                for msg in sub_.take(args.n, args.timeout):
                    out(plain(msg))
            else:
                p.wait_until(lambda: bool(p.servers(f"{args.action}/_action/send_goal")),
                             args.timeout, "the action server")  # the stand-in's: no topics
                handle = p.send_goal(args.action, json.loads(args.goal), args.type, args.timeout)
                out({"accepted": handle.accepted})
                if not handle.accepted:
                    return 1
                printed = 0

                def print_feedback(_what: str, _value: Any) -> None:
                    nonlocal printed
                    with handle._cond:  # reentrant: _add calls this holding it
                        while printed < len(handle.feedback):
                            out({"feedback": plain(handle.feedback[printed])})
                            printed += 1

                handle._on_change = print_feedback
                status, result = handle.result(3600.0)
                print_feedback("", None)
                out({"status": status, "result": plain(result)})
                return 0 if status == STATUS_SUCCEEDED else 1
        except TimeoutError as exc:
            print(f"timeout: {exc}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
