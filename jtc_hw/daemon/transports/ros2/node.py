"""The daemon as upstream's controller in a ROS 2 graph, over rmw_zenoh's wire (API process).

Theory of operation
-------------------
``daemon.ros2`` (``jtc_hw.daemon.ros2_config``) starts a :class:`Ros2Interface` next to the
socket server: one Zenoh session, as an ``rmw_zenoh`` context, holding the nodes and entities
upstream's ``joint_trajectory_controller`` (node ``<c>``, the controller's name) and
``joint_state_broadcaster`` have, named as they name them (``<ns>``: ``daemon.ros2.namespace``)::

    /<ns>/joint_states                         MP sensor_msgs/JointState (the broadcaster)
    /<ns>/<c>/controller_state                 MP control_msgs/JointTrajectoryControllerState
    /<ns>/<c>/joint_trajectory                 MS trajectory_msgs/JointTrajectory -> SendTrajectory
    /<ns>/<c>/speed_scaling_input              MS control_msgs/SpeedScalingFactor (Jazzy+,
                                                  transient local) -> SetSpeedScaling
    /<ns>/<c>/query_state                      SS control_msgs/QueryTrajectoryState -> QueryState
    /<ns>/<c>/get_parameters, set_parameters,  SS rcl_interfaces (``ros2 param``; params.py)
              list_parameters                     -> GetParameters / SetParameters
    /<ns>/<c>/follow_joint_trajectory/_action/ send_goal, cancel_goal, get_result (SS);
                                               feedback, status (MP; status transient local)
    /<ns>/controller_manager/list_controllers  SS controller_manager_msgs (controller_manager.py)

Each entity is a Zenoh publisher, subscriber or queryable on ``<domain>/<name>/<type>/<hash>``
plus a liveliness token under ``@ros2_lv`` (``wire.py``), declared last so that a peer that
sees a token finds the entity; the nodes' own tokens (``NN``) make ``ros2 node list`` show
them. Every sample and reply carries the attachment (sequence number, source timestamp, GID):
a publisher its own GID and counter, a reply the request's sequence number and client GID.

Requests go through the request layer (``jtc_hw.daemon.core.requests``) as the socket's do,
with a :class:`~jtc_hw.daemon.core.requests.Caller` per request whose outlet discards: what a
goal produces later reaches this transport as an observer of the backend (states, goal
events), like ``zenoh_iface``. The action server's bookkeeping (UUIDs, statuses, kept results,
cancel rules) is ``actions.GoalBook``; the messages are built in ``messages.py``.

A goal: ``send_goal``'s request is decoded in Zenoh's thread (``cdr``: numpy columns, no
Python object per number), handed to the event loop, answered by ``Requests.answer``; accepted,
the UUID is bound to our goal id and the response (accepted, stamp) queued before anything else
is awaited, then the status array (EXECUTING). Feedback goes out on ``_action/feedback``, the
result ends the goal: status array (SUCCEEDED 4, CANCELED 5, ABORTED 6 as upstream sets them)
and the parked ``get_result`` requests answered with upstream's ``error_code`` and
``error_string`` (the socket result's, ``jtc_hw.api.events.result_event``). rmw_zenoh's clients
send ``get_result`` with no timeout (``rmw_client_data.cpp``: the ``_action/get_result`` querier
waits forever), so a query waits here until the result exists; results are kept for
rclcpp_action's ``result_timeout`` (15 min, ``actions.RESULT_TIMEOUT_NS``). A client that dies
mid-goal changes nothing: the goal runs to its result, kept for whoever asks.

Bad input (malformed CDR, a sequence length beyond the buffer, NaN, an unknown joint, a
payload longer than ``daemon.max_message_bytes``, refused from its length before it is
copied): a goal gets upstream's reject (``accepted: false``; the reason is logged), a topic
sample is dropped and counted (``get_status``'s ``ros2`` section). A sample of another type
(or of another distro's hash) is on another key: nothing here hears it. A query without an
rmw_zenoh attachment (no sequence number to answer with) is dropped unanswered and counted.
Nothing raises into Zenoh's threads (``outbox.guard``); nothing moves.

Threads (as ``zenoh_iface``): Zenoh calls back in its threads, which decode and hand the work
to the event loop; everything sent to Zenoh goes through one bounded outbox drained by a thread
of ours (states and feedback dropped beyond :data:`OUTBOX_SIZE` waiting, replies and results
only beyond :data:`OUTBOX_HARD_CAP`), where the periodic messages are also encoded. The event
loop never waits on Zenoh and the control loop never sees any of it.

Stamps are ROS time, the system clock (upstream stamps with its node's clock); a
``query_state`` time, and a trajectory's non-zero ``header.stamp`` (``cdr``: its start), are
converted to the daemon clock by the offset between the two at arrival.
"""

from __future__ import annotations

import asyncio
import collections
import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import TYPE_CHECKING, Any, Final

from ....api.requests import (
    CancelGoal,
    GetParameters,
    QueryState,
    Request,
    SendTrajectory,
    SetParameters,
    SetSpeedScaling,
)
from ....controller.goals import GoalFeedback, GoalResult
from ....controller.messages import JointTrajectory
from ....controller.trajectory import QueriedState
from ...core.requests import DISCARD, Caller, Requests
from ...ros2_config import INSTALL_HINT
from ...zenoh_config import import_zenoh, session_config
from . import actions, cdr, controller_manager, params, wire
from .actions import Goal, GoalBook
from .messages import (
    CANCEL_GOAL,
    CONTROLLER_STATE,
    FEEDBACK_MESSAGE,
    GET_PARAMETERS,
    GET_RESULT,
    JOINT_STATE,
    LIST_PARAMETERS,
    PARAMETER_VALUE,
    QUERY_STATE,
    SEND_GOAL,
    SET_PARAMETERS,
    SMALL_REQUEST_BYTES,
    SPEED_SCALING,
    STATUS_ARRAY,
    TRAJECTORY,
    Messages,
    make,
)
from .outbox import Outbox, guard, quietly
from .wire import (
    QOS_ACTION_STATUS,
    QOS_DEFAULT,
    QOS_PARAMETERS,
    QOS_SERVICES,
    QOS_SYSTEM_DEFAULT,
    Durability,
    EntityKind,
    Qos,
)

if TYPE_CHECKING:
    from ...ros2_config import Ros2Settings

log = logging.getLogger("jtc_hw.ros2")

__all__ = ["OUTBOX_HARD_CAP", "OUTBOX_SIZE", "Ros2Interface", "entity_names"]

OUTBOX_SIZE: Final = 256
"""Waiting sends above which states and feedback are dropped."""
OUTBOX_HARD_CAP: Final = 4096
"""Waiting sends above which even replies and results are dropped (and logged)."""
CLOSE_FLUSH_S: Final = 1.0
"""How long closing waits for the outbox to drain (the last results)."""
EXPIRE_EVERY_S: Final = 30.0
"""How often results older than rclcpp_action's result_timeout are forgotten."""
MAX_REQUESTS: Final = 64
"""Requests (goals, cancels, queries, topic samples) executing at once; more are dropped."""
HEARTBEAT_S: Final = 0.5
"""rmw_zenoh's sample-miss heartbeat of a reliable transient-local publisher (500 ms)."""

PUB, SUB, SERVICE = EntityKind.PUBLISHER, EntityKind.SUBSCRIPTION, EntityKind.SERVICE
QOS_SPEED_SCALING: Final = replace(QOS_SYSTEM_DEFAULT, durability=Durability.TRANSIENT_LOCAL)
"""``speed_scaling_input``: upstream's ``SystemDefaultsQoS().transient_local()`` (``wire.py``)."""


def entity_names(namespace: str, controller: str) -> dict[str, str]:
    """The fully qualified names of what the transport serves (module docstring)."""
    c = f"{namespace}/{controller}"
    action = f"{c}/follow_joint_trajectory/_action"
    return {
        "joint_states": f"{namespace}/joint_states",
        "controller_state": f"{c}/controller_state",
        "joint_trajectory": f"{c}/joint_trajectory",
        "speed_scaling_input": f"{c}/speed_scaling_input",
        "query_state": f"{c}/query_state",
        "get_parameters": f"{c}/get_parameters",
        "set_parameters": f"{c}/set_parameters",
        "list_parameters": f"{c}/list_parameters",
        "send_goal": f"{action}/send_goal",
        "cancel_goal": f"{action}/cancel_goal",
        "get_result": f"{action}/get_result",
        "feedback": f"{action}/feedback",
        "status": f"{action}/status",
        "list_controllers": f"{namespace}/controller_manager/list_controllers",
    }


@dataclass(eq=False)
class _Entity:
    """A publisher, subscription or service server: its names, GID and sequence counter."""

    kind: EntityKind
    name: str
    ros_type: str
    node: int
    qos: Qos
    gid: bytes = field(default_factory=wire.new_gid)
    key: str = ""
    handle: Any = None
    seq: itertools.count[int] = field(default_factory=lambda: itertools.count(1))

    def attachment(self) -> bytes:
        return wire.encode_attachment(next(self.seq), time.time_ns(), self.gid)


class Ros2Interface:
    """The daemon's ROS 2 nodes (module docstring).

    Args:
        settings: ``daemon.ros2``.
        controller: the controller's name in the robot file (the node's, unless
            ``controller_name`` says otherwise).
        requests: the request layer, which executes what comes in.
        add_observer: the backend's ``add_observer``: once started, the interface observes
            the backend (states, goal events).
    """

    def __init__(self, settings: Ros2Settings, controller: str, requests: Requests,
                 add_observer: Callable[[Any], None] | None = None) -> None:
        self.settings = settings
        self.node_name = settings.node_name(controller)
        self.names = entity_names(settings.namespace, self.node_name)
        self._requests = requests
        self._add_observer = add_observer
        self.types: Any = None  # made by start() (rosbags is imported then)
        self.messages: Messages = None  # type: ignore[assignment]  # made by start()
        self.book = GoalBook()
        self._entity_ids = itertools.count(10)
        self._max_bytes = requests.max_message_bytes
        self._uuids_pending: set[bytes] = set()
        self._lock = threading.Lock()  # _inflight, from Zenoh's threads and ours
        self._session: Any = None
        self._zid = ""
        self._tokens: list[Any] = []
        self._declared: list[Any] = []
        self._entities: dict[str, _Entity] = {}
        self._outbox: Outbox | None = None
        self._aio: asyncio.AbstractEventLoop | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._expire: asyncio.TimerHandle | None = None
        self._callers = itertools.count(1)
        self._inflight = 0
        self.counters: dict[str, int] = collections.Counter()

    # -- lifecycle ----------------------------------------------------------------------------

    async def start(self) -> None:
        """Open the session, declare the entities and then their tokens; observe the backend
        and add ``ros2`` to ``get_status``.

        Raises:
            ConfigurationError: ``eclipse-zenoh`` or rosbags is missing, or the session cannot
                be opened.
        """
        from ....errors import ConfigurationError

        try:
            zenoh = import_zenoh()
            from .types import ros_types  # rosbags: only for a daemon with daemon.ros2
        except (ConfigurationError, ImportError) as exc:
            what = getattr(exc, "name", None) or "eclipse-zenoh"
            raise ConfigurationError(f"needs the {what} package: {INSTALL_HINT}, or remove "
                                     "daemon.ros2", "daemon.ros2") from None
        self.types = ros_types(self.settings.distro)
        self.messages = Messages(self.types, self._requests.backend.joint_names)
        config = session_config(self.settings.zenoh)
        self._aio = asyncio.get_running_loop()
        try:
            self._session = await self._aio.run_in_executor(None, zenoh.open, config)
        except Exception as exc:
            raise ConfigurationError(
                f"cannot open the Zenoh session: {exc}; check the endpoints (is the router, "
                "rmw_zenohd, running?)", "daemon.ros2.zenoh") from None
        self._zid = str(self._session.info.zid())
        self._outbox = Outbox(OUTBOX_SIZE, OUTBOX_HARD_CAP, "ros2")
        self._declare(zenoh)
        self._expire = self._aio.call_later(EXPIRE_EVERY_S, self._expire_results)
        if self._add_observer is not None:
            self._add_observer(self)
        self._requests.status_sections["ros2"] = self.stats
        self._put_status()
        log.info("ros2: node %s/%s in domain %d (%s), %s of %s", self.settings.namespace,
                 self.node_name, self.settings.domain_id, self.settings.distro,
                 self.settings.zenoh.mode, ", ".join(self.settings.zenoh.connect) or "none")

    def _declare(self, zenoh: Any) -> None:
        """Every entity, then the tokens: the nodes' first, each entity's after it."""
        s = self.settings
        jazzy_on = s.distro != "humble"
        node = 0
        nodes = [(0, self.node_name)]
        if s.joint_state_broadcaster:
            nodes.append((1, "joint_state_broadcaster"))
        manager = len(nodes)
        if s.controller_manager:
            nodes.append((manager, controller_manager.CONTROLLER_MANAGER_NODE))
        # QoS as upstream's nodes have them: the broadcaster's and the controller's topics
        # rclcpp::SystemDefaultsQoS(), rcl_action's defaults for the action's parts.
        self._entity(zenoh, "joint_states", PUB, JOINT_STATE,
                     1 if s.joint_state_broadcaster else node, QOS_SYSTEM_DEFAULT,
                     enabled=s.joint_state_broadcaster)
        self._entity(zenoh, "controller_state", PUB, CONTROLLER_STATE, node, QOS_SYSTEM_DEFAULT)
        self._entity(zenoh, "feedback", PUB, FEEDBACK_MESSAGE, node, QOS_DEFAULT)
        self._entity(zenoh, "status", PUB, STATUS_ARRAY, node, QOS_ACTION_STATUS)
        self._entity(zenoh, "joint_trajectory", SUB, TRAJECTORY, node, QOS_SYSTEM_DEFAULT,
                     callback=self._on_trajectory)
        self._entity(zenoh, "speed_scaling_input", SUB, SPEED_SCALING, node, QOS_SPEED_SCALING,
                     callback=self._on_speed_scaling, enabled=jazzy_on)
        self._entity(zenoh, "query_state", SERVICE, QUERY_STATE, node, QOS_SERVICES,
                     callback=partial(self._on_query, self._query_state))
        for what, service, handler in (
                ("get_parameters", GET_PARAMETERS, self._get_parameters),
                ("set_parameters", SET_PARAMETERS, self._set_parameters),
                ("list_parameters", LIST_PARAMETERS, self._list_parameters)):
            self._entity(zenoh, what, SERVICE, service, node, QOS_PARAMETERS,
                         callback=partial(self._on_query, handler))
        self._entity(zenoh, "send_goal", SERVICE, SEND_GOAL, node, QOS_SERVICES,
                     callback=self._on_send_goal)
        self._entity(zenoh, "cancel_goal", SERVICE, CANCEL_GOAL, node, QOS_SERVICES,
                     callback=partial(self._on_query, self._cancel_goal))
        self._entity(zenoh, "get_result", SERVICE, GET_RESULT, node, QOS_SERVICES,
                     callback=partial(self._on_query, self._get_result))
        self._entity(zenoh, "list_controllers", SERVICE, controller_manager.LIST_CONTROLLERS,
                     manager, QOS_SERVICES, enabled=s.controller_manager,
                     callback=partial(self._on_query, self._list_controllers))
        liveliness = self._session.liveliness()
        namespace = s.namespace or "/"  # rcl's name of no namespace
        for node_id, name in nodes:
            self._tokens.append(liveliness.declare_token(wire.node_token(
                s.domain_id, self._zid, node_id, namespace, name)))
        for entity in self._entities.values():
            token = wire.entity_token(
                entity.kind, s.domain_id, self._zid, entity.node, next(self._entity_ids),
                namespace, nodes[entity.node][1], entity.name,
                self.types.dds_name(entity.ros_type), self.types.type_hash(entity.ros_type),
                entity.qos)
            self._tokens.append(liveliness.declare_token(token))

    def _entity(self, zenoh: Any, what: str, kind: EntityKind, ros_type: str, node: int, qos: Qos,
                callback: Callable[[Any], None] | None = None, enabled: bool = True) -> None:
        if not enabled:
            return
        s = self.settings
        entity = _Entity(kind, self.names[what], ros_type, node, qos)
        entity.key = wire.topic_key(s.domain_id, entity.name, self.types.dds_name(ros_type),
                                  self.types.type_hash(ros_type))
        session = self._session
        if kind == PUB and _transient_local(qos):
            entity.handle = zenoh.ext.declare_advanced_publisher(
                session, entity.key, cache=zenoh.ext.CacheConfig(max_samples=qos.adapted().depth),
                sample_miss_detection=zenoh.ext.MissDetectionConfig(
                    sporadic_heartbeat=HEARTBEAT_S),
                publisher_detection=True)
        elif kind == PUB:
            entity.handle = session.declare_publisher(
                entity.key, congestion_control=zenoh.CongestionControl.DROP)
        elif kind == SUB and _transient_local(qos):
            entity.handle = zenoh.ext.declare_advanced_subscriber(
                session, entity.key, guard(callback, self.counters),
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True,
                                                max_samples=qos.adapted().depth),
                recovery=zenoh.ext.RecoveryConfig(heartbeat=True), subscriber_detection=True)
        elif kind == SUB:
            entity.handle = session.declare_subscriber(entity.key,
                                                       guard(callback, self.counters))
        else:
            entity.handle = session.declare_queryable(
                entity.key, guard(callback, self.counters, query=True), complete=True)
        self._declared.append(entity.handle)
        self._entities[what] = entity

    async def close(self) -> None:
        """Withdraw the tokens, send what is waiting (the last results) and close the session
        (idempotent; errors while closing are logged)."""
        session, self._session = self._session, None
        if session is None:
            return
        if self._expire is not None:
            self._expire.cancel()
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        outbox, self._outbox = self._outbox, None
        waiting = [q for g in self.book.status_list() for q in self.book.answered(g)]

        def finish() -> None:
            for token in reversed(self._tokens):
                quietly(token.undeclare)
            if outbox is not None:
                outbox.close(CLOSE_FLUSH_S)
            for query in waiting:
                quietly(query.drop)
            for entity in reversed(self._declared):
                quietly(entity.undeclare)
            session.close()

        try:
            await asyncio.get_running_loop().run_in_executor(None, finish)
        except Exception:
            log.exception("ros2: closing the session failed")
        self._tokens.clear()
        self._declared.clear()

    # -- observer (the asyncio thread; never blocks nor raises) -------------------------------

    def on_state(self, snapshot: dict[str, Any]) -> None:
        """Publish ``/joint_states`` and ``controller_state`` (encoded in the outbox)."""
        if self._outbox is not None and not self._outbox.offer(
                partial(self._put_states, snapshot, time.time_ns())):
            self.counters["states_dropped"] += 1

    def on_goal_event(self, event: GoalResult | GoalFeedback) -> None:
        """A goal's feedback or result, if the goal is ours (else held a while: it may become
        ours when its ``send_goal`` resumes)."""
        goal = self.book.by_id(event.goal_id)
        if goal is None:
            self.book.hold(event.goal_id, event)
            return
        self._goal_event(goal, event)

    def on_command(self, traj: JointTrajectory, goal_id: int | None) -> None:
        """Nothing: accepted commands are for recorders."""

    def on_record(self, event: dict[str, Any]) -> None:
        """Nothing: results come as goal events."""

    def _goal_event(self, goal: Goal, event: GoalResult | GoalFeedback) -> None:
        outbox = self._outbox
        if outbox is None:
            return
        if isinstance(event, GoalFeedback):
            if not goal.terminal and not outbox.offer(
                    partial(self._put_feedback, goal.uuid, event, time.time_ns())):
                self.counters["feedback_dropped"] += 1
            return
        if self.book.finish(event.goal_id, actions.status_code(event.status),
                            int(event.error_code), event.error_string, time.time_ns()) is None:
            return
        self.counters[f"goals_{event.status.value}"] += 1
        self._put_status()
        data = self.messages.get_result_response(goal.status, goal.error_code,
                                                 goal.error_string)
        for query, att in self.book.answered(goal):
            self._reply(query, att, data)

    # -- in the outbox's thread ---------------------------------------------------------------

    def _put(self, what: str, data: bytes) -> None:
        entity = self._entities.get(what)
        if entity is not None:
            entity.handle.put(data, attachment=entity.attachment())
            self.counters["published"] += 1

    def _put_states(self, snapshot: dict[str, Any], stamp_ns: int) -> None:
        if "joint_states" in self._entities:
            self._put("joint_states", self.messages.joint_state(snapshot, stamp_ns))
        self._put("controller_state", self.messages.controller_state(snapshot, stamp_ns))

    def _put_feedback(self, uuid: bytes, event: GoalFeedback, stamp_ns: int) -> None:
        self._put("feedback", self.messages.feedback(uuid, event, stamp_ns))

    def _put_status(self) -> None:
        """Queue the status array as the book has it now (never dropped: transient local)."""
        if self._outbox is not None:
            data = self.messages.status_array(self.book.status_list())
            self._outbox.put(partial(self._put, "status", data))

    def _send_reply(self, query: Any, att: Any, data: bytes) -> None:
        try:
            query.reply(query.key_expr, data, attachment=wire.encode_attachment(
                att.sequence_number, time.time_ns(), att.gid))
        finally:
            query.drop()

    def _reply(self, query: Any, att: Any, data: bytes) -> None:
        """Queue a reply to ``query`` (``att``: its request's attachment); any thread."""
        outbox = self._outbox
        if outbox is None or not outbox.put(partial(self._send_reply, query, att, data)):
            quietly(query.drop)

    # -- in Zenoh's threads: hand over to the event loop --------------------------------------

    def _clock_offset(self) -> int:
        """The daemon clock minus ROS time (the system clock), now: a header stamp's place on
        the daemon clock (``cdr``'s ``clock_offset_ns``). Any thread."""
        return self._requests.backend.now_ns() - time.time_ns()

    def _admit(self) -> bool:
        """Whether one more request may execute (:data:`MAX_REQUESTS`); Zenoh's threads."""
        with self._lock:
            admitted = (self._aio is not None and self._session is not None
                        and self._inflight < MAX_REQUESTS)
            if admitted:
                self._inflight += 1
            else:
                self.counters["busy"] += 1
        return admitted

    def _release(self) -> None:
        with self._lock:
            self._inflight -= 1

    def _hand(self, fn: Callable[..., Any], *args: Any) -> None:
        assert self._aio is not None
        try:
            self._aio.call_soon_threadsafe(self._run, fn, *args)
        except RuntimeError:  # the event loop is closed: the daemon is exiting
            self._release()

    def _run(self, fn: Callable[..., Any], *args: Any) -> None:
        result = fn(*args)
        if asyncio.iscoroutine(result):
            task = asyncio.get_running_loop().create_task(result)
            self._tasks.add(task)
            task.add_done_callback(self._done)
        else:
            self._release()

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        self._release()
        if not task.cancelled() and task.exception() is not None:
            log.error("ros2: a request failed", exc_info=task.exception())

    def _on_trajectory(self, sample: Any) -> None:
        if not self._admit():
            return
        try:
            trajectory = cdr.decode_joint_trajectory_message(
                _payload(sample, self._max_bytes), clock_offset_ns=self._clock_offset())
        except cdr.CdrError as exc:
            self._release()
            self._drop("joint_trajectory", f"malformed: {exc}")
            return
        self._hand(self._answer_topic, "joint_trajectory", SendTrajectory(trajectory=trajectory))

    def _on_speed_scaling(self, sample: Any) -> None:
        if not self._admit():
            return
        try:
            factor = self.messages.speed_scaling(_payload(sample, SMALL_REQUEST_BYTES))
        except cdr.CdrError as exc:
            self._release()
            self._drop("speed_scaling_input", f"malformed: {exc}")
            return
        self._hand(self._answer_topic, "speed_scaling_input", SetSpeedScaling(factor=factor))

    def _on_send_goal(self, query: Any) -> None:
        att = _attachment(query)
        if att is None or not self._admit():
            self._unanswered(query, att)
            return
        try:
            decoded: tuple[bytes, Any] | str = cdr.decode_send_goal_request(
                _payload(query, self._max_bytes), clock_offset_ns=self._clock_offset())
        except cdr.CdrError as exc:
            decoded = str(exc)
        self._hand(self._send_goal, query, att, decoded)

    def _on_query(self, handler: Callable[[Any, Any, bytes], Any], query: Any) -> None:
        att = _attachment(query)
        if att is None or not self._admit():
            self._unanswered(query, att)
            return
        try:
            payload = _payload(query, SMALL_REQUEST_BYTES)
        except cdr.CdrError:
            payload = b""  # (too long: refused as malformed by the handler's decoder)
        self._hand(handler, query, att, payload)

    def _unanswered(self, query: Any, att: Any) -> None:
        """Drop a query without a reply: no rmw_zenoh attachment (not a ROS 2 client: it has
        no sequence number to be answered with), or :data:`MAX_REQUESTS` executing."""
        if att is None:
            self.counters["requests_without_attachment"] += 1
        query.drop()

    # -- in the event loop --------------------------------------------------------------------

    def _caller(self, what: str, att: Any = None) -> Caller:
        number = next(self._callers)
        who = f" {att.gid.hex()[:8]}" if att is not None else ""
        return Caller(number, f"ros2 {what} {number}{who}", DISCARD)

    def _drop(self, topic: str, why: str) -> None:
        count = self.counters[f"{topic}_dropped"] = self.counters[f"{topic}_dropped"] + 1
        if count <= 3 or count % 100 == 0:
            log.warning("ros2: %s sample dropped (%d so far): %s", topic, count, why)

    async def _answer_topic(self, topic: str, request: Request) -> None:
        reply = await self._requests.answer(self._caller(topic), request)
        if reply.ok:
            self.counters[f"{topic}_accepted"] += 1
        else:
            self._drop(topic, reply.message["error"]["message"])

    async def _send_goal(self, query: Any, att: Any, decoded: tuple[bytes, Any] | str) -> None:
        caller = self._caller("goal", att)
        stamp = time.time_ns()
        if isinstance(decoded, str):
            reason = f"malformed goal: {decoded}"
        elif self.book.known(decoded[0]) or decoded[0] in self._uuids_pending:
            reason = f"goal UUID {decoded[0].hex()} is in use"
        else:
            uuid, request = decoded
            self._uuids_pending.add(uuid)
            try:
                reply = await self._requests.answer(caller, request)
            finally:
                self._uuids_pending.discard(uuid)
            if reply.ok:
                stamp = time.time_ns()
                goal, held = self.book.accept(uuid, int(reply.message["goal_id"]), stamp)
                # The response first, before anything else is queued or awaited.
                self._reply(query, att, self.messages.send_goal_response(True, stamp))
                self.counters["goals_accepted"] += 1
                log.info("%s: goal %s is goal %d", caller.label, uuid.hex(), goal.goal_id)
                self._put_status()
                for event in held:
                    self._goal_event(goal, event)
                return
            self.counters["goals_rejected"] += 1  # (the request layer logged why)
            self._reply(query, att, self.messages.send_goal_response(False, stamp))
            return
        self.counters["goals_rejected"] += 1
        log.info("%s: goal rejected: %s", caller.label, reason)
        self._reply(query, att, self.messages.send_goal_response(False, stamp))

    async def _cancel_goal(self, query: Any, att: Any, data: bytes) -> None:
        try:
            uuid, stamp = self.messages.cancel_request(data)
        except cdr.CdrError as exc:
            self.counters["requests_malformed"] += 1
            log.info("ros2: malformed cancel_goal: %s", exc)
            self._reply(query, att, self.messages.cancel_response(actions.ERROR_REJECTED, []))
            return
        code, targets = self.book.cancel_targets(uuid, stamp)
        caller = self._caller("cancel", att)
        canceling = []
        for goal in targets:
            reply = await self._requests.answer(caller, CancelGoal(goal_id=goal.goal_id))
            if reply.ok and not goal.terminal:
                self.book.canceling(goal)
                canceling.append(goal)
        if canceling:
            code = actions.ERROR_NONE
        self._reply(query, att, self.messages.cancel_response(code, canceling))
        if canceling:
            self._put_status()

    def _get_result(self, query: Any, att: Any, data: bytes) -> None:
        try:
            uuid = self.messages.get_result_request(data)
        except cdr.CdrError as exc:
            self.counters["requests_malformed"] += 1
            log.info("ros2: malformed get_result: %s", exc)
            self._reply(query, att, self.messages.get_result_response(actions.UNKNOWN, 0, ""))
            return
        if self.book.want_result(uuid, (query, att)):
            return  # answered with the result (on_goal_event)
        goal = self.book.get(uuid)
        if goal is not None and goal.terminal:
            data = self.messages.get_result_response(goal.status, goal.error_code,
                                                     goal.error_string)
        else:
            data = self.messages.get_result_response(actions.UNKNOWN, 0, "")
        self._reply(query, att, data)

    async def _query_state(self, query: Any, att: Any, data: bytes) -> None:
        try:
            ros_ns = self.messages.query_state_request(data)
        except cdr.CdrError as exc:
            self.counters["requests_malformed"] += 1
            self._reply(query, att, self.messages.query_state_response(None, str(exc)))
            return
        backend = self._requests.backend
        t = max(0, backend.now_ns() + ros_ns - time.time_ns())
        reply = await self._requests.answer(self._caller("query_state", att),
                                            QueryState(time_ns=t))
        if not reply.ok:
            out = self.messages.query_state_response(None, reply.message["error"]["message"])
        else:
            m = reply.message
            out = self.messages.query_state_response(QueriedState(
                m["positions"], m["velocities"], m["accelerations"], m["effort"], m["success"],
                m["where"]),
                "" if m["success"] else f"time is {m['where'].replace('_', ' ')} of the "
                "trajectory")
        self._reply(query, att, out)

    async def _list_controllers(self, query: Any, att: Any, data: bytes) -> None:
        self._reply(query, att, await controller_manager.list_controllers(
            self._requests, self._caller("list_controllers", att), self.messages,
            self.node_name, self.settings.joint_state_broadcaster))

    # -- parameters (params.py) ---------------------------------------------------------------

    async def _parameter_values(self, att: Any) -> dict[str, Any]:
        reply = await self._requests.answer(self._caller("parameters", att),
                                            GetParameters(names=None))
        return dict(reply.message.get("parameters", {})) if reply.ok else {}

    def _value(self, value: Any) -> Any:
        return make(self.messages.store, PARAMETER_VALUE, **params.to_parameter_value(value))

    async def _get_parameters(self, query: Any, att: Any, data: bytes) -> None:
        try:
            names = list(self.messages.decode(data, f"{GET_PARAMETERS}_Request").names)
        except cdr.CdrError:
            names = []
        values = await self._parameter_values(att)
        self._reply(query, att, self.messages.response(
            GET_PARAMETERS, values=[self._value(values.get(n)) for n in names]))

    async def _set_parameters(self, query: Any, att: Any, data: bytes) -> None:
        try:
            request = self.messages.decode(data, f"{SET_PARAMETERS}_Request").parameters
        except cdr.CdrError:
            request = []
        caller = self._caller("set_parameters", att)
        results = []
        for parameter in request:  # one by one, as rclcpp's service
            try:
                change = {str(parameter.name): params.from_parameter_value(parameter.value)}
            except ValueError as exc:
                results.append({"successful": False, "reason": str(exc)})
                continue
            reply = await self._requests.answer(caller, SetParameters(parameters=change))
            results.append({"successful": reply.ok, "reason": "" if reply.ok
                            else reply.message["error"]["message"]})
        self._reply(query, att, self.messages.response(SET_PARAMETERS, results=[make(
            self.messages.store, "rcl_interfaces/msg/SetParametersResult", **r)
            for r in results]))

    async def _list_parameters(self, query: Any, att: Any, data: bytes) -> None:
        try:
            request = self.messages.decode(data, f"{LIST_PARAMETERS}_Request")
            prefixes, depth = list(request.prefixes), int(request.depth)
        except cdr.CdrError:
            prefixes, depth = [], 0
        names, parents = params.list_names(await self._parameter_values(att), prefixes, depth)
        self._reply(query, att, self.messages.response(
            LIST_PARAMETERS, result={"names": names, "prefixes": parents}))

    def _expire_results(self) -> None:
        if self.book.expire(time.time_ns()):
            self._put_status()
        if self._aio is not None and self._session is not None:
            self._expire = self._aio.call_later(EXPIRE_EVERY_S, self._expire_results)

    def stats(self) -> dict[str, Any]:
        """The ``ros2`` section of ``get_status``: counters for logs and tests."""
        outbox = self._outbox
        return {
            "node": f"{self.settings.namespace}/{self.node_name}",
            "domain_id": self.settings.domain_id,
            "distro": self.settings.distro,
            "goals_running": self.book.running,
            "results_kept": self.book.kept,
            "results_waiting": self.book.waiting,
            "dropped": 0 if outbox is None else outbox.dropped,
            "lost": 0 if outbox is None else outbox.lost,
            **dict(sorted(self.counters.items())),
        }


def _transient_local(qos: Qos) -> bool:
    """Whether rmw_zenoh makes an advanced publisher / subscriber with history for ``qos``."""
    return qos.adapted().durability is Durability.TRANSIENT_LOCAL


def _payload(item: Any, limit: int) -> bytes:
    """A sample's or query's payload, refused from its length alone (never copied) when it
    is longer than ``limit``.

    Raises:
        CdrError: longer than ``limit`` bytes.
    """
    payload = item.payload
    if payload is None:
        return b""
    if len(payload) > limit:
        raise cdr.CdrError(f"{len(payload)} bytes, more than the {limit} accepted "
                           "(daemon.max_message_bytes)")
    return bytes(payload.to_bytes())


def _attachment(query: Any) -> Any:
    """The request's attachment (seq, timestamp, client GID); None if it has none (not an
    rmw_zenoh client: the query is dropped)."""
    raw = query.attachment
    if raw is None:
        return None
    try:
        return wire.decode_attachment(bytes(raw.to_bytes()))
    except ValueError:
        return None
