"""ROS 2 interface types per distro: definitions, DDS names and RIHS01 type hashes (no I/O).

Theory of operation
-------------------
Every sample ``rmw_zenoh`` sends names its type twice: in the key expression and in the
liveliness token (:mod:`.wire`), as the DDS type name and the type hash::

    0/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_a13ee3a3...
                   `------------ dds_name -----------' `-- type_hash --'

A peer whose name or hash differs is another type: its samples never meet ours. So both must be
what ``rosidl`` generates on the workstation, for the distro it runs (:data:`DISTROS`):

- **Definitions.** rosbags' type store of the distro has the common messages (sensor_msgs,
  trajectory_msgs, action_msgs, rcl_interfaces, ...). What it lacks (control_msgs,
  controller_manager_msgs, and every service and action, which rosbags does not model) is
  declared once below, in :data:`_INTERFACES`, from the upstream ``.msg``/``.srv``/``.action``
  text of the branch that distro builds (comments dropped: they change neither bytes nor
  hashes). A ``.srv`` becomes ``X_Request``, ``X_Response`` and, on Jazzy and later,
  ``X_Event``; a ``.action`` becomes ``X_Goal``, ``X_Result``, ``X_Feedback`` and the
  generated ``X_SendGoal``, ``X_GetResult`` (both services) and ``X_FeedbackMessage``, as
  ``rosidl_parser``'s ``Action`` defines them.
  The distros differ where control_msgs does: Humble's controller state has the deprecated
  ``desired``/``actual`` and no ``speed_scaling_factor``; Kilted and Rolling (control_msgs
  >= 6.3) add ``index`` and ``multi_dof_index`` to the action's feedback; Jazzy's
  ``controller_manager_msgs/msg/ControllerState`` adds ``is_async``, ``update_rate`` and
  ``exported_state_interfaces`` to Humble's.
- **DDS names** (:meth:`RosTypes.dds_name`): ``pkg/ns/Name`` -> ``pkg::ns::dds_::Name_``.
  A service is named without ``_Request``/``_Response`` (rmw_zenoh cuts its response type's
  name at ``Response_``), so an action's goal service is
  ``control_msgs::action::dds_::FollowJointTrajectory_SendGoal_``.
- **Type hashes** (:meth:`RosTypes.type_hash`): REP-2016's RIHS01, the SHA-256 of the type
  description as ``rosidl_generator_type_description`` writes it: the type and every type it
  references (sorted by name), each field as ``{name, type: {type_id, capacity,
  string_capacity, nested_type_name}}``, default values left out, JSON with ``", "`` and
  ``": "`` separators. The description is built here (:class:`_Describer`), not with rosbags'
  ``hash_rihs01``: that one is right for messages, but hashes ``char`` as type 13 where rosidl
  has already turned a ``.msg`` ``char`` into ``uint8`` (3), which changes
  ``service_msgs/msg/ServiceEventInfo`` (``char[16] client_gid``) and with it every service's
  hash. A service is described as a type with the fields ``request_message``,
  ``response_message``, ``event_message``; an action with ``goal``, ``result``, ``feedback``,
  ``send_goal_service``, ``get_result_service``, ``feedback_message``.
  Humble has no type hashes: rmw_zenoh's humble branch writes the constant
  :data:`TYPE_HASH_NOT_SUPPORTED` where the hash goes.

Checked against (tests/daemon/ros2/test_types.py): the design doc's ``std_msgs/msg/String`` and
``example_interfaces/srv/AddTwoInts`` hashes; ``ros2 topic info -v`` output for JointState and
JointTrajectory; ``ros2 action info -v`` output in ROS 2's actions tutorial (turtlesim's
RotateAbsolute services and feedback, GoalStatusArray, CancelGoal); and every hash of a
rosidl-generated control_msgs ``follow_joint_trajectory__description.c`` (control_msgs 4.x/5.x);
every hash of a rosidl-generated controller_manager_msgs ``list_controllers__description.c``
(Jazzy's layout; tests/daemon/ros2/test_controller_manager.py).
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Final

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from ....rec.bag import CONTROLLER_STATE_MSG

__all__ = [
    "CANCEL_GOAL",
    "CONTROLLER_STATE",
    "DISTROS",
    "FOLLOW_JOINT_TRAJECTORY",
    "FJT_FEEDBACK_MESSAGE",
    "FJT_GET_RESULT",
    "FJT_SEND_GOAL",
    "GET_PARAMETERS",
    "GOAL_STATUS_ARRAY",
    "JOINT_STATE",
    "JOINT_TRAJECTORY",
    "LIST_CONTROLLERS",
    "LIST_PARAMETERS",
    "QUERY_TRAJECTORY_STATE",
    "SET_PARAMETERS",
    "SPEED_SCALING_FACTOR",
    "TYPE_HASH_NOT_SUPPORTED",
    "RosTypes",
    "ros_types",
]

DISTROS: Final = ("humble", "jazzy", "kilted", "rolling")
"""The ROS 2 distributions whose types and hashes this module knows."""
TYPE_HASH_NOT_SUPPORTED: Final = "TypeHashNotSupported"
"""What rmw_zenoh's humble branch writes where the type hash goes (its
``rmw_publisher_data.cpp``/``rmw_service_data.cpp``: a constant, Humble has no hashes)."""

# The types the transport uses, by their ROS names.
JOINT_STATE: Final = "sensor_msgs/msg/JointState"
JOINT_TRAJECTORY: Final = "trajectory_msgs/msg/JointTrajectory"
CONTROLLER_STATE: Final = "control_msgs/msg/JointTrajectoryControllerState"
SPEED_SCALING_FACTOR: Final = "control_msgs/msg/SpeedScalingFactor"
"""Jazzy and later only."""
FOLLOW_JOINT_TRAJECTORY: Final = "control_msgs/action/FollowJointTrajectory"
FJT_SEND_GOAL: Final = FOLLOW_JOINT_TRAJECTORY + "_SendGoal"
FJT_GET_RESULT: Final = FOLLOW_JOINT_TRAJECTORY + "_GetResult"
FJT_FEEDBACK_MESSAGE: Final = FOLLOW_JOINT_TRAJECTORY + "_FeedbackMessage"
GOAL_STATUS_ARRAY: Final = "action_msgs/msg/GoalStatusArray"
CANCEL_GOAL: Final = "action_msgs/srv/CancelGoal"
QUERY_TRAJECTORY_STATE: Final = "control_msgs/srv/QueryTrajectoryState"
GET_PARAMETERS: Final = "rcl_interfaces/srv/GetParameters"
SET_PARAMETERS: Final = "rcl_interfaces/srv/SetParameters"
LIST_PARAMETERS: Final = "rcl_interfaces/srv/ListParameters"
LIST_CONTROLLERS: Final = "controller_manager_msgs/srv/ListControllers"

_STORES: Final = {
    "humble": Stores.ROS2_HUMBLE,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
    "rolling": Stores.LATEST,
}
_HASHED: Final = frozenset({"jazzy", "kilted", "rolling"})


@dataclass(frozen=True)
class _Interface:
    """One upstream interface file: its ROS name, its text, the distros it is for."""

    name: str
    text: str
    distros: tuple[str, ...]
    source: str


_ALL = DISTROS
_JAZZY_ON = ("jazzy", "kilted", "rolling")

# The interfaces rosbags' stores lack, as upstream declares them (comments dropped). Each names
# the file and the branch it matches. control_msgs: ros-controls/control_msgs, branch humble
# (4.8.0) for Humble, jazzy (5.8.0) for Jazzy, master (6.8.0) for Kilted and Rolling (its
# README: Kilted is released from master).
_JOINT_TOLERANCE = """\
string name
float64 position
float64 velocity
float64 acceleration
"""
_JOINT_COMPONENT_TOLERANCE = """\
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
"""
_JTC_STATE_HUMBLE = """\
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
# Jazzy's and later (speed_scaling_factor, no desired/actual): the recordings' text, one copy.
_JTC_STATE = CONTROLLER_STATE_MSG
_FJT_GOAL_RESULT = """\
trajectory_msgs/JointTrajectory trajectory
trajectory_msgs/MultiDOFJointTrajectory multi_dof_trajectory
control_msgs/JointTolerance[] path_tolerance
control_msgs/JointComponentTolerance[] component_path_tolerance
control_msgs/JointTolerance[] goal_tolerance
control_msgs/JointComponentTolerance[] component_goal_tolerance
builtin_interfaces/Duration goal_time_tolerance
---
int32 error_code
int32 SUCCESSFUL=0
int32 INVALID_GOAL=-1
int32 INVALID_JOINTS=-2
int32 OLD_HEADER_TIMESTAMP=-3
int32 PATH_TOLERANCE_VIOLATED=-4
int32 GOAL_TOLERANCE_VIOLATED=-5
string error_string
---
"""
_FJT_FEEDBACK = """\
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
_FJT_FEEDBACK_INDEXED = """\
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
# controller_manager_msgs: ros-controls/ros2_control, branches humble, jazzy, kilted, master.
_CONTROLLER_STATE_HUMBLE = """\
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
_CONTROLLER_STATE = """\
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
_CM = "ros-controls/control_msgs control_msgs/"
_R2C = "ros-controls/ros2_control controller_manager_msgs/"
_RCL = "ros2/rcl_interfaces "
_INTERFACES: Final = (
    _Interface("control_msgs/msg/JointTolerance", _JOINT_TOLERANCE, _ALL,
               _CM + "msg/JointTolerance.msg, humble/jazzy/master (unchanged since 2021)"),
    _Interface("control_msgs/msg/JointComponentTolerance", _JOINT_COMPONENT_TOLERANCE, _ALL,
               _CM + "msg/JointComponentTolerance.msg, humble/jazzy/master (unchanged)"),
    _Interface(CONTROLLER_STATE, _JTC_STATE_HUMBLE, ("humble",),
               _CM + "msg/JointTrajectoryControllerState.msg, humble (with deprecated fields)"),
    _Interface(CONTROLLER_STATE, _JTC_STATE, _JAZZY_ON,
               _CM + "msg/JointTrajectoryControllerState.msg, jazzy (>= 5.3) and master"),
    _Interface(SPEED_SCALING_FACTOR, "float64 factor\n", _JAZZY_ON,
               _CM + "msg/SpeedScalingFactor.msg, jazzy (>= 5.3) and master"),
    _Interface(FOLLOW_JOINT_TRAJECTORY, _FJT_GOAL_RESULT + _FJT_FEEDBACK, ("humble", "jazzy"),
               _CM + "action/FollowJointTrajectory.action, humble and jazzy"),
    _Interface(FOLLOW_JOINT_TRAJECTORY, _FJT_GOAL_RESULT + _FJT_FEEDBACK_INDEXED,
               ("kilted", "rolling"),
               _CM + "action/FollowJointTrajectory.action, master (>= 6.3: index fields)"),
    _Interface("controller_manager_msgs/msg/ChainConnection",
               "string name\nstring[] reference_interfaces\n", _ALL,
               _R2C + "msg/ChainConnection.msg, humble/jazzy/kilted/master (the same)"),
    _Interface("controller_manager_msgs/msg/ControllerState", _CONTROLLER_STATE_HUMBLE,
               ("humble",), _R2C + "msg/ControllerState.msg, humble"),
    _Interface("controller_manager_msgs/msg/ControllerState", _CONTROLLER_STATE, _JAZZY_ON,
               _R2C + "msg/ControllerState.msg, jazzy, kilted and master (is_async, "
               "update_rate, exported_state_interfaces)"),
    _Interface(LIST_CONTROLLERS, "---\ncontroller_manager_msgs/ControllerState[] controller\n",
               _ALL, _R2C + "srv/ListControllers.srv, humble/jazzy/kilted/master (the same)"),
    _Interface(QUERY_TRAJECTORY_STATE, """\
builtin_interfaces/Time time
---
bool success
string message
string[] name
float64[] position
float64[] velocity
float64[] acceleration
""", _ALL, _CM + "srv/QueryTrajectoryState.srv, humble/jazzy/master (unchanged since 2021)"),
    _Interface(CANCEL_GOAL, """\
action_msgs/GoalInfo goal_info
---
int8 ERROR_NONE=0
int8 ERROR_REJECTED=1
int8 ERROR_UNKNOWN_GOAL_ID=2
int8 ERROR_GOAL_TERMINATED=3
int8 return_code
action_msgs/GoalInfo[] goals_canceling
""", _ALL, _RCL + "action_msgs/srv/CancelGoal.srv, humble..rolling (unchanged)"),
    _Interface(GET_PARAMETERS, """\
string[] names
---
rcl_interfaces/ParameterValue[] values
""", _ALL, _RCL + "rcl_interfaces/srv/GetParameters.srv, humble..rolling (unchanged)"),
    _Interface(SET_PARAMETERS, """\
rcl_interfaces/Parameter[] parameters
---
rcl_interfaces/SetParametersResult[] results
""", _ALL, _RCL + "rcl_interfaces/srv/SetParameters.srv, humble..rolling (unchanged)"),
    _Interface(LIST_PARAMETERS, """\
uint64 DEPTH_RECURSIVE=0
string[] prefixes
uint64 depth
---
rcl_interfaces/ListParametersResult result
""", _ALL, _RCL + "rcl_interfaces/srv/ListParameters.srv, humble..rolling (unchanged)"),
)

# rosidl_parser's definition.py (class Action): the types it generates for every action.
_SEND_GOAL = "unique_identifier_msgs/UUID goal_id\n{action}_Goal goal\n---\n" \
             "bool accepted\nbuiltin_interfaces/Time stamp\n"
_GET_RESULT = "unique_identifier_msgs/UUID goal_id\n---\nint8 status\n{action}_Result result\n"
_FEEDBACK_MESSAGE = "unique_identifier_msgs/UUID goal_id\n{action}_Feedback feedback\n"
# rosidl (Iron and later): the service event message generated for every service.
_EVENT = "service_msgs/ServiceEventInfo info\n{srv}_Request[<=1] request\n" \
         "{srv}_Response[<=1] response\n"

# REP-2016 / type_description_interfaces/msg/FieldType: the field type ids.
_NESTED: Final = 1
_TYPE_IDS: Final = {
    "int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8,
    "uint64": 9, "float32": 10, "float64": 11, "float128": 12,
    "char": 3,  # rosidl_adapter turns a .msg char into IDL uint8 before hashing
    "bool": 15, "byte": 16, "octet": 16, "string": 17, "wstring": 18,
}
_BOUNDED_STRING: Final = 21
_ARRAY, _BOUNDED_SEQUENCE, _UNBOUNDED_SEQUENCE = 48, 96, 144


class RosTypes:
    """The interface types of one distro: definitions, DDS names and type hashes.

    ``typestore`` is rosbags' store of the distro with :data:`_INTERFACES` registered (services
    as ``X_Request``/``X_Response``, actions as their parts), for tests and slow paths. Build
    one with :func:`ros_types` (cached: building a store takes a while).
    """

    def __init__(self, distro: str) -> None:
        """Build the type store of ``distro``.

        Raises:
            ValueError: ``distro`` is not one of :data:`DISTROS`.
        """
        if distro not in DISTROS:
            raise ValueError(f"unknown ROS 2 distro {distro!r}: one of {', '.join(DISTROS)}")
        self.distro: Final = distro
        self.typestore: Final[Typestore] = get_typestore(_STORES[distro])
        self._services: set[str] = set()
        self._actions: set[str] = set()
        self._hashes: dict[str, str] = {}
        typesdict: dict[str, Any] = {}
        for interface in _INTERFACES:
            if distro in interface.distros:
                for name, text in self._expand(interface.name, interface.text):
                    typesdict.update(_parse(text, name))
        self.typestore.register(typesdict)

    def register(self, name: str, text: str) -> None:
        """Add one more interface from its upstream text: ``pkg/msg/X`` a ``.msg``, ``pkg/srv/X``
        a ``.srv``, ``pkg/action/X`` a ``.action`` (tests declare others' types this way).

        Raises:
            ValueError: the text has the wrong number of ``---`` sections for its kind, or
                rosbags cannot parse it.
        """
        typesdict: dict[str, Any] = {}
        for part, body in self._expand(name, text):
            typesdict.update(_parse(body, part))
        self.typestore.register(typesdict)
        self._hashes.clear()

    @property
    def hashed(self) -> bool:
        """Whether this distro has type hashes (Jazzy and later; Humble has none)."""
        return self.distro in _HASHED

    def _expand(self, name: str, text: str) -> Iterator[tuple[str, str]]:
        """The messages of one interface file: itself, or a service's or an action's parts."""
        parts = name.split("/")
        if len(parts) != 3 or not all(parts) or parts[1] not in ("msg", "srv", "action"):
            raise ValueError(f"not an interface name (package/msg|srv|action/Name): {name!r}")
        kind = parts[1]
        if kind == "msg":
            yield name, text
        elif kind == "srv":
            yield from self._service(name, text)
        else:
            goal, result, feedback = _split(text, 3, name)
            yield name + "_Goal", goal
            yield name + "_Result", result
            yield name + "_Feedback", feedback
            yield from self._service(name + "_SendGoal", _SEND_GOAL.format(action=name))
            yield from self._service(name + "_GetResult", _GET_RESULT.format(action=name))
            yield name + "_FeedbackMessage", _FEEDBACK_MESSAGE.format(action=name)
            self._actions.add(name)

    def _service(self, name: str, text: str) -> Iterator[tuple[str, str]]:
        request, response = _split(text, 2, name)
        yield name + "_Request", request
        yield name + "_Response", response
        if self.hashed:
            yield name + "_Event", _EVENT.format(srv=name)
        self._services.add(name)

    def is_service(self, ros_type: str) -> bool:
        """Whether ``ros_type`` is a service (an action's ``X_SendGoal``/``X_GetResult`` too)."""
        return ros_type in self._services or (
            ros_type.count("/") == 2 and ros_type.split("/")[1] == "srv"
            and ros_type + "_Request" in self.typestore.fielddefs
        )

    def is_action(self, ros_type: str) -> bool:
        """Whether ``ros_type`` is an action (``pkg/action/X`` itself, not one of its parts)."""
        return ros_type in self._actions

    def dds_name(self, ros_type: str) -> str:
        """The DDS type name rmw_zenoh writes in keys and tokens.

        ``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_``; a service
        ``pkg/srv/X`` -> ``pkg::srv::dds_::X_``; an action's goal service
        ``control_msgs/action/FollowJointTrajectory_SendGoal`` ->
        ``control_msgs::action::dds_::FollowJointTrajectory_SendGoal_``.

        Raises:
            KeyError: the type is unknown in this distro.
        """
        self._check_known(ros_type)
        package, namespace, name = ros_type.split("/")
        return f"{package}::{namespace}::dds_::{name}_"

    def type_hash(self, ros_type: str) -> str:
        """The type hash rmw_zenoh writes: ``RIHS01_<64 hex>``, or on Humble
        :data:`TYPE_HASH_NOT_SUPPORTED`.

        Raises:
            KeyError: the type is unknown in this distro.
        """
        self._check_known(ros_type)
        if not self.hashed:
            return TYPE_HASH_NOT_SUPPORTED
        cached = self._hashes.get(ros_type)
        if cached is None:
            cached = self._hashes[ros_type] = _Describer(self).rihs01(ros_type)
        return cached

    def request_type(self, service: str) -> str:
        """The type store's name of a service's request message (``X_Request``)."""
        return service + "_Request"

    def response_type(self, service: str) -> str:
        """The type store's name of a service's response message (``X_Response``)."""
        return service + "_Response"

    def _check_known(self, ros_type: str) -> None:
        parts = ros_type.split("/")
        if len(parts) != 3 or not all(parts):
            raise KeyError(f"not a ROS 2 type name (package/namespace/Name): {ros_type!r}")
        if not (ros_type in self.typestore.fielddefs or self.is_service(ros_type)
                or self.is_action(ros_type)):
            raise KeyError(f"unknown type {ros_type!r} in ROS 2 {self.distro}")


class _Describer:
    """REP-2016 type descriptions of one distro's types (rosidl_generator_type_description's
    layout, written anew): ``rihs01`` hashes a message, a service or an action."""

    def __init__(self, types: RosTypes) -> None:
        self._types = types
        self._fielddefs = types.typestore.fielddefs
        self._seen: dict[str, dict[str, Any]] = {}

    def rihs01(self, ros_type: str) -> str:
        """``RIHS01_`` and the SHA-256 of ``ros_type``'s description, as hex."""
        top = self._describe(ros_type)
        referenced = [d for name, d in sorted(self._seen.items()) if name != ros_type]
        text = json.dumps(
            {"type_description": top, "referenced_type_descriptions": referenced},
            separators=(", ", ": "),
        )
        return "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()

    def _describe(self, name: str) -> dict[str, Any]:
        if name in self._seen:
            return self._seen[name]
        if self._types.is_action(name):
            fields = [
                _nested("goal", name + "_Goal"), _nested("result", name + "_Result"),
                _nested("feedback", name + "_Feedback"),
                _nested("send_goal_service", name + "_SendGoal"),
                _nested("get_result_service", name + "_GetResult"),
                _nested("feedback_message", name + "_FeedbackMessage"),
            ]
        elif self._types.is_service(name):
            fields = [
                _nested("request_message", name + "_Request"),
                _nested("response_message", name + "_Response"),
                _nested("event_message", name + "_Event"),
            ]
        else:
            members = self._fielddefs[name][1] or [
                ("structure_needs_at_least_one_member", (Nodetype.BASE, ("uint8", 0)))
            ]
            fields = [self._field(field, desc) for field, desc in members]
        description = {"type_name": name, "fields": fields}
        self._seen[name] = description
        for field in fields:
            nested = field["type"]["nested_type_name"]
            if nested:
                self._describe(nested)
        return description

    def _field(self, name: str, desc: Any) -> dict[str, Any]:
        node, rest = desc
        offset, capacity = 0, 0
        if node == Nodetype.ARRAY:
            (node, rest), capacity = rest
            offset = _ARRAY
        elif node == Nodetype.SEQUENCE:
            (node, rest), capacity = rest
            offset = _BOUNDED_SEQUENCE if capacity else _UNBOUNDED_SEQUENCE
        nested, string_capacity = "", 0
        if node == Nodetype.NAME:
            type_id, nested = _NESTED, rest
        else:
            base, bound = rest
            if base == "string" and bound:
                type_id, string_capacity = _BOUNDED_STRING, bound
            else:
                type_id = _TYPE_IDS[base]
        return {"name": name, "type": {
            "type_id": type_id + offset, "capacity": capacity,
            "string_capacity": string_capacity, "nested_type_name": nested,
        }}


def _nested(name: str, type_name: str) -> dict[str, Any]:
    return {"name": name, "type": {
        "type_id": _NESTED, "capacity": 0, "string_capacity": 0, "nested_type_name": type_name,
    }}


def _split(text: str, parts: int, name: str) -> list[str]:
    """A ``.srv``/``.action`` text cut at its ``---`` lines."""
    sections: list[list[str]] = [[]]
    for line in text.splitlines():
        if line.strip() == "---":
            sections.append([])
        else:
            sections[-1].append(line)
    if len(sections) != parts:
        raise ValueError(f"{name}: {parts} sections expected, {len(sections)} found")
    return ["\n".join(section) + "\n" for section in sections]


def _parse(text: str, name: str) -> dict[str, Any]:
    """rosbags' parse of one message text, under ``name`` even in a ``srv`` namespace.

    rosbags files every type outside ``msg``/``action`` under ``<pkg>/<ns>/msg/``; the
    service types are moved back to ``<pkg>/srv/`` here, references included.
    """
    parsed = get_types_from_msg(text, name)

    def fix(value: Any) -> Any:
        if isinstance(value, str):
            return value.replace("/srv/msg/", "/srv/")
        if isinstance(value, tuple):
            return tuple(fix(item) for item in value)
        if isinstance(value, list):
            return [fix(item) for item in value]
        return value

    return {fix(key): fix(value) for key, value in parsed.items()}


@functools.cache
def ros_types(distro: str) -> RosTypes:
    """The (shared, cached) :class:`RosTypes` of ``distro``.

    Raises:
        ValueError: ``distro`` is not one of :data:`DISTROS`.
    """
    return RosTypes(distro)
