"""rmw_zenoh's wire format: data keys, liveliness tokens, QoS text, attachments, GIDs (no I/O).

Theory of operation
-------------------
A ROS 2 node on ``rmw_zenoh`` (docs/design.md of ros2/rmw_zenoh at
99a6a2bd10b949052f4f12c5854825dc005e95a5; ``liveliness_utils.cpp``, ``attachment_helpers.cpp``
and ``qos.cpp`` of the same code) is nothing but Zenoh traffic of four shapes:

**Data** -- a topic's samples are ``put`` on, a service's requests are ``get`` on, one key
(:func:`topic_key`)::

    <domain>/<fully qualified name, outer slashes cut>/<DDS type>/<type hash>
    0/arm_controller/joint_trajectory/trajectory_msgs::msg::dds_::JointTrajectory_/RIHS01_179b...

A service server's queryable is declared complete, a client's ``get`` targets all complete
queryables, and the reply comes on the service's key. An action is its five parts under
``<action>/_action/`` (:func:`action_names`): the services
``send_goal``, ``cancel_goal``, ``get_result`` and the topics ``feedback``, ``status``.

**Graph** -- each node and each publisher (``MP``), subscription (``MS``), service server
(``SS``) and client (``SC``) declares one liveliness token (:class:`Entity`); ``ros2 node list``,
``topic list``, ``action list`` are built from them, and a token that vanishes (its session
dead, or undeclared) takes the entity out of the graph. There is no action kind::

    @ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>
    @ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node name>
        /<name>/<DDS type>/<type hash>/<qos>

Names are mangled (:func:`mangle`: every ``/`` becomes ``%``): the enclave and namespace are
``%`` when unset (rcl's ``/``), the topic ``/joint_states`` is ``%joint_states``. ``zid`` is the
Zenoh session id as Zenoh prints it (``str(session.info.zid())``: lowercase hex, the same text
zenoh-c gives rmw_zenoh); node and entity ids are numbers unique within the session (rmw_zenoh
draws both from one counter per session).

**QoS** -- the entity's QoS profile after rmw_zenoh adapts it (``SYSTEM_DEFAULT`` and depth 0 take
its defaults, unspecified durations become infinite), each field left empty where it equals
rmw_zenoh's default (keep last 42, reliable, volatile, infinite, automatic) (:func:`qos_text`)::

    <reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>
        :<liveliness>,<lease s>,<lease ns>
    ::,10:,:,:,,       reliable, volatile, keep last 10 (rclcpp's default, services)
    2::,5:,:,:,,       best effort, keep last 5 (sensor data)
    :1:,1:,:,:,,       transient local, keep last 1 (an action's status topic)

The numbers are rmw's enums (``rmw/types.h``): reliability 1 reliable, 2 best effort;
durability 1 transient local, 2 volatile; history 1 keep last, 2 keep all; liveliness 1
automatic, 3 manual by topic. The profiles upstream's endpoints use (ros2_controllers'
joint_trajectory_controller.cpp and joint_state_broadcaster.cpp, rcl_action's
``rcl_action_server_get_default_options``, rclcpp's parameter service)::

    /joint_states, ~/controller_state, ~/joint_trajectory   QOS_SYSTEM_DEFAULT   ::,:,:,:,,
    ~/speed_scaling_input (Jazzy+)   QOS_SYSTEM_DEFAULT, transient local         :1:,:,:,:,,
    ~/query_state, an action's three services               QOS_SERVICES         ::,10:,:,:,,
    an action's feedback topic                              QOS_DEFAULT          ::,10:,:,:,,
    an action's status topic                                QOS_ACTION_STATUS    :1:,1:,:,:,,
    ~/get_parameters, ~/set_parameters, ~/list_parameters   QOS_PARAMETERS       ::,1000:,:,:,,

**Attachment** -- every sample, request and reply carries 33 bytes, zenoh-ext's serialization
of ``(int64, int64, std::array<uint8_t, 16>)`` (:func:`encode_attachment`)::

    offset  0  int64 LE  sequence number (a request's reply echoes it)
    offset  8  int64 LE  source timestamp, ns since the UNIX epoch
    offset 16  uint8     16: the GID's length (zenoh-ext's LEB128 sequence length)
    offset 17  16 bytes  the GID of the publisher, or of the client (echoed in the reply)

rmw_zenoh counts sequence numbers from 1, per publisher and per client.
A GID is 16 bytes, unique per publisher or client (:func:`new_gid`; rmw_zenoh derives its own
from a hash of the entity's token, which only needs to be unique: a random one serves).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, replace
from enum import Enum, IntEnum
from typing import Final

__all__ = [
    "ADMIN_SPACE",
    "ATTACHMENT_SIZE",
    "DURATION_INFINITE",
    "DURATION_UNSPECIFIED",
    "GID_SIZE",
    "QOS_ACTION_STATUS",
    "QOS_DEFAULT",
    "QOS_PARAMETERS",
    "QOS_SENSOR_DATA",
    "QOS_SERVICES",
    "QOS_SYSTEM_DEFAULT",
    "ActionNames",
    "Attachment",
    "Durability",
    "Entity",
    "EntityKind",
    "History",
    "Liveliness",
    "Qos",
    "Reliability",
    "action_names",
    "decode_attachment",
    "demangle",
    "encode_attachment",
    "entity_token",
    "graph_key",
    "mangle",
    "new_gid",
    "node_token",
    "parse_qos",
    "parse_token",
    "qos_text",
    "topic_key",
]

ADMIN_SPACE: Final = "@ros2_lv"
"""The liveliness tokens' hermetic prefix."""
GID_SIZE: Final = 16
ATTACHMENT_SIZE: Final = 8 + 8 + 1 + GID_SIZE
_ATTACHMENT: Final = struct.Struct(f"<qqB{GID_SIZE}s")
_FORBIDDEN: Final = frozenset("*$?#/")  # key-expression wildcards and the chunk separator


class EntityKind(str, Enum):
    """The kind of a liveliness token (its sixth chunk)."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


class Reliability(IntEnum):
    """``rmw_qos_reliability_policy_e``."""

    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class Durability(IntEnum):
    """``rmw_qos_durability_policy_e``."""

    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class History(IntEnum):
    """``rmw_qos_history_policy_e``."""

    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class Liveliness(IntEnum):
    """``rmw_qos_liveliness_policy_e`` (2, manual by node, is deprecated and unused)."""

    SYSTEM_DEFAULT = 0
    AUTOMATIC = 1
    MANUAL_BY_TOPIC = 3
    UNKNOWN = 4
    BEST_AVAILABLE = 5


DURATION_UNSPECIFIED: Final = (0, 0)
"""``RMW_DURATION_UNSPECIFIED``: a QoS duration left to the middleware."""
DURATION_INFINITE: Final = (9223372036, 854775807)
"""``RMW_DURATION_INFINITE`` as (seconds, nanoseconds)."""


@dataclass(frozen=True)
class Qos:
    """A ROS 2 QoS profile (``rmw_qos_profile_t``); durations are (seconds, nanoseconds).

    The defaults are rclcpp's and rcl's default profile (``rmw_qos_profile_default``): keep
    last 10, reliable, volatile, the rest left to the middleware.
    """

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10
    deadline: tuple[int, int] = DURATION_UNSPECIFIED
    lifespan: tuple[int, int] = DURATION_UNSPECIFIED
    liveliness: Liveliness = Liveliness.SYSTEM_DEFAULT
    lease: tuple[int, int] = DURATION_UNSPECIFIED

    def adapted(self) -> Qos:
        """The profile as rmw_zenoh's ``QoS::best_available_qos`` leaves it: system defaults,
        depth 0 and unspecified durations replaced by :data:`_ZENOH_DEFAULT`'s values."""
        d = _ZENOH_DEFAULT

        def pick(value: IntEnum, default: IntEnum) -> IntEnum:
            return default if value.name in ("SYSTEM_DEFAULT", "UNKNOWN") else value

        def span(value: tuple[int, int], default: tuple[int, int]) -> tuple[int, int]:
            return default if value == DURATION_UNSPECIFIED else value

        return replace(
            self,
            reliability=Reliability(pick(self.reliability, d.reliability)),
            durability=Durability(pick(self.durability, d.durability)),
            history=History(pick(self.history, d.history)),
            depth=self.depth or d.depth,
            deadline=span(self.deadline, d.deadline),
            lifespan=span(self.lifespan, d.lifespan),
            liveliness=Liveliness(pick(self.liveliness, d.liveliness)),
            lease=span(self.lease, d.lease),
        )


_ZENOH_DEFAULT: Final = Qos(
    Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, 42, DURATION_INFINITE,
    DURATION_INFINITE, Liveliness.AUTOMATIC, DURATION_INFINITE,
)
"""rmw_zenoh's default profile (``qos.cpp``): the values its QoS text leaves empty."""

QOS_DEFAULT: Final = Qos()
"""``rmw_qos_profile_default``: keep last 10, reliable, volatile (``rclcpp::QoS(10)``)."""
QOS_SYSTEM_DEFAULT: Final = Qos(
    Reliability.SYSTEM_DEFAULT, Durability.SYSTEM_DEFAULT, History.SYSTEM_DEFAULT, 0)
"""``rmw_qos_profile_system_default`` (``rclcpp::SystemDefaultsQoS()``, which upstream's
joint_state_broadcaster and joint_trajectory_controller publish and subscribe with)."""
QOS_SENSOR_DATA: Final = Qos(Reliability.BEST_EFFORT, Durability.VOLATILE, History.KEEP_LAST, 5)
"""``rmw_qos_profile_sensor_data``."""
QOS_SERVICES: Final = Qos(Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, 10)
"""``rmw_qos_profile_services_default`` (rcl_action's goal, cancel and result services too)."""
QOS_PARAMETERS: Final = Qos(Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, 1000)
"""``rmw_qos_profile_parameters`` (rclcpp's parameter services)."""
QOS_ACTION_STATUS: Final = Qos(
    Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, History.KEEP_LAST, 1)
"""``rcl_action_qos_profile_status_default``: an action's ``status`` topic."""


def qos_text(qos: Qos) -> str:
    """The QoS chunk of a liveliness token, as rmw_zenoh's ``qos_to_keyexpr`` writes it for
    ``qos`` once adapted (:meth:`Qos.adapted`); ``qos_text(QOS_DEFAULT) == "::,10:,:,:,,"``."""
    q, d = qos.adapted(), _ZENOH_DEFAULT

    def part(value: object, default: object) -> str:
        if value == default:
            return ""
        return str(int(value)) if isinstance(value, IntEnum) else str(value)

    return (
        f"{part(q.reliability, d.reliability)}:{part(q.durability, d.durability)}:"
        f"{part(q.history, d.history)},{part(q.depth, d.depth)}:"
        f"{part(q.deadline[0], d.deadline[0])},{part(q.deadline[1], d.deadline[1])}:"
        f"{part(q.lifespan[0], d.lifespan[0])},{part(q.lifespan[1], d.lifespan[1])}:"
        f"{part(q.liveliness, d.liveliness)},{part(q.lease[0], d.lease[0])},"
        f"{part(q.lease[1], d.lease[1])}"
    )


def parse_qos(text: str) -> Qos:
    """The QoS of a token's QoS chunk (rmw_zenoh's ``keyexpr_to_qos``): empty fields are
    rmw_zenoh's defaults.

    Raises:
        ValueError: not six ``:``-separated fields of the right shape, or a value that is not
            a number or not a known policy.
    """
    parts = text.split(":")
    if len(parts) != 6:
        raise ValueError(f"QoS text {text!r}: 6 ':'-separated fields expected")
    history, deadline, lifespan, liveliness = (p.split(",") for p in parts[2:])
    if [len(history), len(deadline), len(lifespan), len(liveliness)] != [2, 2, 2, 3]:
        raise ValueError(f"QoS text {text!r}: malformed field")
    d = _ZENOH_DEFAULT

    def num(field: str, default: int) -> int:
        if not field:
            return default
        if not field.isdigit():
            raise ValueError(f"QoS text {text!r}: {field!r} is not a number")
        return int(field)

    return Qos(
        reliability=Reliability(num(parts[0], d.reliability)),
        durability=Durability(num(parts[1], d.durability)),
        history=History(num(history[0], d.history)),
        depth=num(history[1], d.depth),
        deadline=(num(deadline[0], d.deadline[0]), num(deadline[1], d.deadline[1])),
        lifespan=(num(lifespan[0], d.lifespan[0]), num(lifespan[1], d.lifespan[1])),
        liveliness=Liveliness(num(liveliness[0], d.liveliness)),
        lease=(num(liveliness[1], d.lease[0]), num(liveliness[2], d.lease[1])),
    )


def mangle(name: str) -> str:
    """A name as one key-expression chunk: every ``/`` replaced by ``%``."""
    return name.replace("/", "%")


def demangle(chunk: str) -> str:
    """The name of a mangled chunk: every ``%`` replaced by ``/``."""
    return chunk.replace("%", "/")


def topic_key(domain_id: int, fq_name: str, dds_type: str, type_hash: str) -> str:
    """The data key of a topic or service: ``<domain>/<name>/<DDS type>/<type hash>``, the
    name's leading and trailing ``/`` cut.

    Raises:
        ValueError: a negative domain, or an empty or wildcard chunk.
    """
    name = fq_name[1:] if fq_name.startswith("/") else fq_name
    name = name[:-1] if name.endswith("/") else name
    if domain_id < 0 or not name or any(not c or c in ("*", "**") for c in name.split("/")):
        raise ValueError(f"invalid topic key: domain {domain_id}, name {fq_name!r}")
    for chunk in (dds_type, type_hash):
        _check_chunk(chunk)
    return f"{domain_id}/{name}/{dds_type}/{type_hash}"


def graph_key(domain_id: int) -> str:
    """The key expression of every liveliness token of a domain (to subscribe or ``get``)."""
    return f"{ADMIN_SPACE}/{domain_id}/**"


@dataclass(frozen=True)
class Entity:
    """A node, publisher, subscription, service server or client, as its token names it.

    ``enclave`` and ``namespace`` are rcl's (``/`` when unset); ``name`` is the topic's or
    service's fully qualified name; ``name``, ``dds_type``, ``type_hash`` and ``qos`` are
    ``None`` for a node (whose ``entity_id`` is its ``node_id``).
    """

    domain_id: int
    zid: str
    node_id: int
    entity_id: int
    kind: EntityKind
    namespace: str
    node_name: str
    enclave: str = "/"
    name: str | None = None
    dds_type: str | None = None
    type_hash: str | None = None
    qos: Qos | None = None

    @property
    def token(self) -> str:
        """The liveliness token's key expression.

        Raises:
            ValueError: a chunk would be empty or hold a wildcard, or a node carries topic
                fields, or an endpoint lacks them.
        """
        node = [ADMIN_SPACE, str(self.domain_id), self.zid, str(self.node_id),
                str(self.entity_id), self.kind.value, mangle(self.enclave),
                mangle(self.namespace), mangle(self.node_name)]
        topic = (self.name, self.dds_type, self.type_hash, self.qos)
        if self.kind is EntityKind.NODE:
            if any(v is not None for v in topic) or self.entity_id != self.node_id:
                raise ValueError("a node's token has no topic and its entity id is its node id")
            chunks = node
        else:
            if self.name is None or self.dds_type is None or self.type_hash is None \
                    or self.qos is None:
                raise ValueError(f"a {self.kind.name.lower()}'s token needs name, type, hash, QoS")
            chunks = node + [mangle(self.name), mangle(self.dds_type), mangle(self.type_hash),
                             qos_text(self.qos)]
        for chunk in chunks[2:]:
            _check_chunk(chunk)
        if self.domain_id < 0 or self.node_id < 0 or self.entity_id < 0:
            raise ValueError("domain, node and entity ids are not negative")
        return "/".join(chunks)


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node_name: str,
               enclave: str = "/") -> str:
    """A node's liveliness token (kind ``NN``).

    Raises:
        ValueError: as :attr:`Entity.token`.
    """
    return Entity(domain_id, zid, node_id, node_id, EntityKind.NODE, namespace, node_name,
                  enclave).token


def entity_token(kind: EntityKind, domain_id: int, zid: str, node_id: int, entity_id: int,
                 namespace: str, node_name: str, name: str, dds_type: str, type_hash: str,
                 qos: Qos, enclave: str = "/") -> str:
    """A publisher's, subscription's, service server's or client's liveliness token.

    Raises:
        ValueError: ``kind`` is ``NODE`` (use :func:`node_token`), or as :attr:`Entity.token`.
    """
    if kind is EntityKind.NODE:
        raise ValueError("a node's token is node_token()'s")
    return Entity(domain_id, zid, node_id, entity_id, kind, namespace, node_name, enclave,
                  name, dds_type, type_hash, qos).token


def parse_token(token: str) -> Entity:
    """The entity a liveliness token names (rmw_zenoh's ``Entity::make(keyexpr)``).

    Raises:
        ValueError: not under :data:`ADMIN_SPACE`, an unknown kind, a chunk missing, empty or
            not a number where one is due, extra chunks, or a malformed QoS.
    """
    parts = token.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or not all(parts):
        raise ValueError(f"not an rmw_zenoh liveliness token: {token!r}")
    try:
        kind = EntityKind(parts[5])
    except ValueError:
        raise ValueError(f"unknown entity kind {parts[5]!r} in {token!r}") from None
    if not (parts[1].isdigit() and parts[3].isdigit() and parts[4].isdigit()):
        raise ValueError(f"domain, node and entity ids must be numbers: {token!r}")
    domain_id, zid, node_id, entity_id = int(parts[1]), parts[2], int(parts[3]), int(parts[4])
    enclave, namespace, node_name = (demangle(p) for p in parts[6:9])
    if kind is EntityKind.NODE:
        if len(parts) != 9:
            raise ValueError(f"a node's token has 9 chunks: {token!r}")
        return Entity(domain_id, zid, node_id, entity_id, kind, namespace, node_name, enclave)
    if len(parts) != 13:
        raise ValueError(f"an endpoint's token has 13 chunks: {token!r}")
    name, dds_type, type_hash = (demangle(p) for p in parts[9:12])
    return Entity(domain_id, zid, node_id, entity_id, kind, namespace, node_name, enclave,
                  name, dds_type, type_hash, parse_qos(parts[12]))


@dataclass(frozen=True)
class ActionNames:
    """The services and topics an action is made of (rcl_action's names)."""

    send_goal: str
    cancel_goal: str
    get_result: str
    feedback: str
    status: str


def action_names(action: str) -> ActionNames:
    """The five names under ``<action>/_action/`` (``action`` fully qualified)."""
    base = action.rstrip("/") + "/_action/"
    return ActionNames(base + "send_goal", base + "cancel_goal", base + "get_result",
                       base + "feedback", base + "status")


@dataclass(frozen=True)
class Attachment:
    """What every sample, request and reply carries besides its payload."""

    sequence_number: int
    source_timestamp_ns: int
    gid: bytes


def encode_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33 attachment bytes (layout: the module docstring).

    Raises:
        ValueError: ``gid`` is not :data:`GID_SIZE` bytes, or a number does not fit an int64.
    """
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, not {len(gid)}")
    try:
        return _ATTACHMENT.pack(sequence_number, source_timestamp_ns, GID_SIZE, bytes(gid))
    except struct.error as exc:
        raise ValueError(f"attachment field out of range: {exc}") from None


def decode_attachment(data: bytes | bytearray | memoryview) -> Attachment:
    """The attachment of a sample, request or reply.

    Raises:
        ValueError: not :data:`ATTACHMENT_SIZE` bytes, or a GID length other than 16 (an old
            rmw_zenoh's keyed layout, or not rmw_zenoh at all).
    """
    if len(data) != ATTACHMENT_SIZE:
        raise ValueError(f"an attachment is {ATTACHMENT_SIZE} bytes, not {len(data)}")
    sequence_number, timestamp, length, gid = _ATTACHMENT.unpack(bytes(data))
    if length != GID_SIZE:
        raise ValueError(f"attachment GID length {length}, {GID_SIZE} expected")
    return Attachment(sequence_number, timestamp, gid)


def new_gid() -> bytes:
    """A fresh random GID for a publisher or client."""
    return os.urandom(GID_SIZE)


def _check_chunk(chunk: str) -> None:
    if not chunk or any(c in _FORBIDDEN for c in chunk):
        raise ValueError(f"invalid key-expression chunk {chunk!r}")
