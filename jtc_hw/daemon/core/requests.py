"""Every operation of the protocol, with no transport: a request in, its reply out, as values.

Theory of operation
-------------------
The transports are peers over this layer; none knows another::

    unix socket --+  framing, peer uid, reserved slots       (server, unix_socket)
    TCP ----------+  framing, token handshake, slots          (server, tcp_door)
    Zenoh --------+  key expressions, token attachment        (zenoh_iface)
                  |
                  v
          Requests.answer(caller, request) -> Reply    ---->  Backend (the loop process)
          Requests.on_goal_event / on_state / ...      <----  (an Observer)
                  |
                  v
          caller.outlet.send / offer   (later messages: goal feedback and results, state,
                                        accepted commands; the transport delivers them)

A transport turns what it receives into a ``protocol.Request`` (or a ``RequestError``: bad
JSON, an unknown op) and awaits :meth:`Requests.answer` with the :class:`Caller` that stands
for its client. The answer is a :class:`Reply`: the reply message (success or error, never an
exception) and its JSON encoding, which every transport sends as it is, so the replies of every
transport are byte for byte the same. What comes later goes through the caller's
:class:`Outlet`, which the transport implements: ``send`` for what must not be dropped (goal
results, accepted commands and records), ``offer`` for what may be (``state``, ``feedback``).

A transport admits and authenticates its clients before it calls :meth:`Requests.answer`,
and answers its own refusals (``busy``, ``unauthorized``, ``idle``) with
:meth:`Requests.refuse`, so that they are logged as every other rejection.

Goal routing: a goal's events go to the caller that sent it. ``Backend.send_goal`` returns the
id and the route is registered before anything else is awaited, so no event can overtake the
registration through this layer's own scheduling. A backend may still deliver a goal's events
*before* the ``send_goal`` coroutine resumes (it resolves the id's future and then, in the same
callback, dispatches a batch of events that includes the goal's first feedback): events for a
goal id without a route are held (bounded) and delivered in the event loop's next round after
the ``accepted`` reply was returned. So the one rule for a transport: **queue a reply before
you next await** (then the reply precedes the goal's first event on the wire).

A caller that leaves while its goal runs does not stop the goal (as with a ROS action client
that vanishes): the goal runs on to its result, which is logged and discarded.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from ... import __version__
from ...api.events import command_event, feedback_event, record_event, result_event, sample_to_json
from ...api.framing import (
    BAD_REQUEST,
    GOAL_REJECTED,
    HARDWARE,
    INTERNAL,
    NOT_ACTIVE,
    NOT_FOUND,
    PROTOCOL_VERSION,
    PROTOCOL_VERSIONS,
    RequestError,
    encode,
    error_reply,
    reply,
)
from ...api.requests import (
    Auth,
    CancelGoal,
    GetConfig,
    GetParameters,
    GetStatus,
    Hello,
    QueryState,
    Rearm,
    Request,
    SendGoal,
    SendTrajectory,
    SetParameters,
    SetSpeedScaling,
    Sim,
    Stop,
    SubscribeState,
    UnsubscribeState,
)
from ...controller.goals import GoalFeedback, GoalResult
from ...controller.limits_check import scaling_fields
from ...controller.messages import JointTrajectory
from ...errors import (
    ConfigurationError,
    ControllerStateError,
    GoalRejected,
    HardwareError,
    JtcHwError,
)
from .backend_api import Accepted, Backend

__all__ = ["DISCARD", "EARLY_EVENTS", "EARLY_GOALS", "FINISHED_GOALS", "Caller", "Outlet",
           "Reply", "Requests"]

log = logging.getLogger("jtc_hw.server")

EARLY_GOALS = 64
"""Goal ids whose events are held while their route is not registered yet."""
EARLY_EVENTS = 256
"""Feedback events held per such goal (results are always held)."""
FINISHED_GOALS = 256
"""Recently finished goal ids remembered, so that a straggling event is ignored, not held."""
_RESERVED_STATE_KEYS = frozenset({"event", "dropped", "dropped_total"})

GoalEvent = GoalResult | GoalFeedback


class Outlet(Protocol):
    """Where a transport delivers one client's later messages (it implements this).

    Each message is one encoded protocol message (``framing.encode``'s bytes). Both methods are
    called in the event loop's thread and must return at once.
    """

    gone: bool
    """The client cannot be sent anything any more (disconnected)."""

    def send(self, data: bytes) -> bool:
        """Deliver a message that must not be dropped (a goal result, a command, a record);
        False if it cannot be delivered (the client is gone, or has just been disconnected as
        too slow): a result is then counted as discarded."""

    def offer(self, data: bytes) -> bool:
        """Deliver a droppable message (``state``, ``feedback``) if there is room; False if it
        was dropped (counted in the client's next ``state``)."""


class _Discard:
    """The outlet of a transport that hears what comes later as an observer of the backend
    (Zenoh, ROS 2): each request's one reply is the request's; what is routed to its caller
    later (its goal's feedback and result) the transport publishes from its observer."""

    gone = False

    def send(self, data: bytes) -> bool:
        return True

    def offer(self, data: bytes) -> bool:
        return True


DISCARD: Outlet = _Discard()
"""An :class:`Outlet` that discards (``_Discard``)."""


@dataclass(eq=False)
class Caller:
    """One client of one transport, as this layer sees it: who (for the log), where later
    messages go, what it subscribed to, its goals and what it was not sent.

    A transport makes one per client (a socket connection) or per request (a Zenoh query);
    this layer changes the fields below, the transport reads them (for its statistics, its
    idle clock).
    """

    number: int
    """The transport's number for the client (``get_status``'s ``you``)."""
    label: str
    """How log lines name the client: ``client 3 (unix pid 12 uid 1000)``."""
    outlet: Outlet
    subscribed: bool = False
    commands: bool = False
    """Subscribed with ``commands``: also every accepted command and ``record`` event."""
    goals: set[int] = field(default_factory=set)
    """Its goals still running (their events are routed to it)."""
    dropped_state: int = 0
    dropped_feedback: int = 0
    dropped_since_state: int = 0
    goals_ended_at: float = float("-inf")
    """``time.monotonic()`` when its last running goal ended (an idle clock starts then)."""

    @property
    def dropped_total(self) -> int:
        return self.dropped_state + self.dropped_feedback

    @property
    def engaged(self) -> bool:
        """Waiting for something of the daemon (state events, a goal's result): not idle."""
        return self.subscribed or bool(self.goals)


@dataclass(frozen=True)
class Reply:
    """The answer to one request: the reply message and its JSON encoding (made here once,
    so that a message that cannot be encoded is an ``internal`` error like any failure)."""

    message: dict[str, Any]
    data: bytes

    @property
    def ok(self) -> bool:
        return bool(self.message.get("ok"))


def accepted_goal(accepted: Accepted) -> tuple[int, dict[str, float]]:
    """The goal id and the ``accepted`` reply's fitting fields (``time_scale``,
    ``duration_s``; none when the goal was checked as sent) from ``Backend.send_goal``'s value."""
    if accepted.time_scaling is None:
        return accepted.goal_id, {}
    return accepted.goal_id, {
        "time_scale": accepted.time_scaling, "duration_s": accepted.duration_s}


class Requests:
    """Every operation over a ``Backend``; also an ``Observer`` of the backend.

    Example::

        requests = Requests(backend, max_message_bytes=4 << 20)
        requests.listen()
        reply = await requests.answer(caller, Stop(id=1))
        transport_send(reply.data)

    Args:
        backend: the control loop's host.
        max_message_bytes: the longest request the transports accept (told in ``hello``).
    """

    def __init__(self, backend: Backend, max_message_bytes: int) -> None:
        self.backend = backend
        self.max_message_bytes = max_message_bytes
        self.status_sections: dict[str, Callable[[], dict[str, Any]]] = {}
        """More sections of ``get_status`` by name (a transport's counters: ``zenoh``), after
        the backend's; each is called in the event loop and must not block nor raise."""
        self.server_status: Callable[[Caller], dict[str, Any]] | None = None
        """``get_status``'s last section, ``server``: the clients and their slots, as the
        socket server keeps them (``Server.stats``), for the asking caller (``you``)."""
        self._routes: dict[int, Caller] = {}
        self._early: collections.OrderedDict[int, list[GoalEvent]] = collections.OrderedDict()
        self._releasing: dict[int, list[GoalEvent]] = {}  # held, delivered after the reply
        self._finished: collections.OrderedDict[int, None] = collections.OrderedDict()
        self._subscribers: dict[Caller, None] = {}  # in the order they subscribed
        self.results_discarded = 0
        self._closed = False
        self._listening = False

    def listen(self) -> None:
        """Become an observer of the backend (goal events, state). Idempotent."""
        if not self._listening:
            self._listening = True
            self.backend.add_observer(self)

    def close(self) -> None:
        """Forget every route and subscriber; later backend events are ignored. Idempotent."""
        self._closed = True
        self._routes.clear()
        self._early.clear()
        self._releasing.clear()
        self._finished.clear()
        self._subscribers.clear()

    def leave(self, caller: Caller) -> None:
        """``caller``'s client has gone: no more state, commands or records for it. Its goals
        run on; their results are discarded (and counted) when its outlet says it is gone."""
        self._subscribers.pop(caller, None)

    @property
    def goals_routed(self) -> list[int]:
        """Goal ids whose events have a caller to go to."""
        return sorted(self._routes)

    # -- requests -----------------------------------------------------------------------------

    async def answer(self, caller: Caller, item: Request | RequestError) -> Reply:
        """Execute one request for ``caller``: its reply, success or error (logged). Never
        raises: a failure is an error reply (``internal`` for the unexpected, logged with its
        traceback)."""
        if isinstance(item, RequestError):
            return self.refuse(caller, None, item)
        try:
            message = await self._dispatch(caller, item)
            return Reply(message, encode(message))
        except RequestError as exc:
            error = exc
        except GoalRejected as exc:
            error = RequestError(GOAL_REJECTED, exc.reason, item.id, exc.error_code)
        except ControllerStateError as exc:
            error = RequestError(NOT_ACTIVE, str(exc), item.id)
        except ConfigurationError as exc:
            error = RequestError(BAD_REQUEST, str(exc), item.id)
        except HardwareError as exc:
            error = RequestError(HARDWARE, str(exc), item.id)
        except JtcHwError as exc:
            error = RequestError(INTERNAL, str(exc), item.id)
        except Exception as exc:
            log.exception("%s: %s failed", caller.label, item.op)
            text = f"internal error: {type(exc).__name__}: {exc}"
            return self.refuse(caller, item, RequestError(INTERNAL, text, item.id), logged=True)
        return self.refuse(caller, item, error)

    @staticmethod
    def refuse(
        caller: Caller,
        request: Request | None,
        error: RequestError,
        logged: bool = False,
    ) -> Reply:
        """The error reply for ``error`` (its id, else the request's), logged unless
        ``logged``: also for a transport's own refusals (``busy``, ``unauthorized``)."""
        rid = error.request_id if error.request_id is not None or request is None else request.id
        if not logged:
            op = request.op if request is not None else "request"
            log.info(
                "%s: rejected %s (id %r): %s: %s", caller.label, op, rid, error.code, error.message
            )
        message = error_reply(rid, error.code, error.message, error.error_code)
        return Reply(message, encode(message))

    async def _dispatch(self, caller: Caller, req: Request) -> dict[str, Any]:
        backend = self.backend
        match req:
            case Hello():
                asked = req.protocol_version
                if asked is not None and asked not in PROTOCOL_VERSIONS:
                    raise RequestError(
                        BAD_REQUEST,
                        f"protocol_version: this daemon speaks versions "
                        f"{', '.join(map(str, PROTOCOL_VERSIONS))} (version 1: NDJSON only, "
                        f"{PROTOCOL_VERSION}: also binary frames); the client asked for {asked}",
                        req.id,
                    )
                ours = {
                    "protocol_version": PROTOCOL_VERSION,
                    "server_version": __version__,
                    "joint_names": list(backend.joint_names),
                    "now_ns": backend.now_ns(),
                    "max_message_bytes": self.max_message_bytes,
                }
                return _merge(req.id, backend.hello(), ours)
            case Auth():
                # The transport checked any credential before the request got here.
                return reply(req.id, authenticated=True)
            case SendGoal():
                return await self._send_goal(caller, req)
            case CancelGoal():
                if not await backend.cancel_goal(req.goal_id):
                    raise RequestError(
                        NOT_FOUND,
                        f"goal {req.goal_id} is not executing (unknown, already finished or "
                        "already being canceled); nothing to cancel",
                        req.id,
                    )
                return reply(req.id, goal_id=req.goal_id, canceling=True)
            case SendTrajectory():
                traj = req.trajectory.to_joint_trajectory(backend.now_ns())
                scaling = await backend.send_trajectory(traj, time_scaling=req.time_scaling)
                return reply(req.id, stopping=not traj.points, **scaling_fields(scaling))
            case Stop():
                if not await backend.stop_motion():
                    return reply(
                        req.id,
                        stopped=False,
                        message="nothing to stop: the controller is not active (see "
                        "get_status: controller.fault)",
                    )
                return reply(req.id, stopped=True)
            case QueryState():
                t = req.resolve(backend.now_ns())
                queried = backend.query_state(t)
                return reply(
                    req.id,
                    time_ns=t,
                    success=queried.success,
                    where=queried.where,
                    joint_names=list(backend.joint_names),
                    **sample_to_json(queried),
                )
            case SubscribeState():
                caller.subscribed = True
                caller.commands = caller.commands or req.commands
                self._subscribers[caller] = None
                return reply(req.id, subscribed=True, commands=caller.commands)
            case UnsubscribeState():
                caller.subscribed = caller.commands = False
                self._subscribers.pop(caller, None)
                return reply(req.id, subscribed=False)
            case GetConfig():
                return reply(req.id, config=backend.config_dict())
            case GetStatus():
                sections = {name: get() for name, get in self.status_sections.items()}
                if self.server_status is not None:
                    sections["server"] = self.server_status(caller)
                return _merge(req.id, backend.status(), sections)
            case Sim():
                await backend.sim(req.component, req.freeze, req.fault)
                if req.fault is not None:
                    return reply(req.id, component=req.component, fault=req.fault)
                return reply(req.id, component=req.component, frozen=req.freeze)
            case GetParameters():
                return _merge(req.id, backend.get_parameters(req.names), {})
            case SetParameters():
                change = await backend.set_parameters(req.parameters)
                log.info(
                    "%s: parameters changed: %s",
                    caller.label,
                    ", ".join(f"{k}={v!r}" for k, v in change.values.items()),
                )
                return _merge(req.id, change.to_json(), {})
            case SetSpeedScaling():
                speed = await backend.set_speed_scaling(None if req.resume else req.factor)
                log.info(
                    "%s: speed scaling %s: ramping from %g to %g",
                    caller.label,
                    "resumed" if req.resume else "set",
                    speed["factor"],
                    speed["target"],
                )
                return reply(req.id, factor=speed["factor"], target=speed["target"])
            case Rearm():
                done = await backend.rearm()
                if not done:
                    return reply(req.id, rearmed=False, message="nothing to re-arm: no fault")
                return reply(req.id, rearmed=True)
        raise AssertionError(f"unhandled request {req!r}")  # pragma: no cover

    async def _send_goal(self, caller: Caller, req: SendGoal) -> dict[str, Any]:
        traj = req.trajectory.to_joint_trajectory(self.backend.now_ns())
        accepted = await self.backend.send_goal(
            traj,
            req.path_tolerance,
            req.goal_tolerance,
            req.goal_time_tolerance,
            time_scaling=req.time_scaling,
        )
        goal_id, scaled = accepted_goal(accepted)
        # Nothing may be awaited from here on: the route must exist before this task yields,
        # so that every later event of the goal finds it (module docstring).
        self._routes[goal_id] = caller
        caller.goals.add(goal_id)
        if caller.outlet.gone:
            log.info(
                "%s left before goal %d was accepted; it runs on to its result, which will "
                "be discarded",
                caller.label,
                goal_id,
            )
        log.info("%s: goal %d accepted", caller.label, goal_id)
        early = self._early.pop(goal_id, None)
        if early:
            # Delivered once the transport has queued this reply (module docstring); events
            # arriving meanwhile queue up behind them.
            self._releasing[goal_id] = early
            asyncio.get_running_loop().call_soon(self._release, goal_id)
        return reply(req.id, goal_id=goal_id, accepted=True, **scaled)

    def _release(self, goal_id: int) -> None:
        events = self._releasing.pop(goal_id, ())
        for event in events:
            caller = self._routes.get(goal_id)
            if caller is None:  # its result was among them, or the layer closed
                return
            self._route(caller, event)

    # -- Observer -----------------------------------------------------------------------------

    def on_goal_event(self, event: GoalEvent) -> None:
        """Route a goal's event to the caller that sent the goal. Never raises: a result whose
        caller has gone is logged and discarded."""
        if self._closed:
            return
        waiting = self._releasing.get(event.goal_id)
        if waiting is not None:
            waiting.append(event)
            return
        caller = self._routes.get(event.goal_id)
        if caller is None:
            if event.goal_id in self._finished:
                log.debug("ignoring a late event of finished goal %d", event.goal_id)
                return
            self._hold(event)
            return
        self._route(caller, event)

    def _route(self, caller: Caller, event: GoalEvent) -> None:
        outlet = caller.outlet
        if isinstance(event, GoalResult):
            self._routes.pop(event.goal_id, None)
            caller.goals.discard(event.goal_id)
            if not caller.goals:  # the idle clock starts when the caller's last goal ends
                caller.goals_ended_at = time.monotonic()
            self._finished[event.goal_id] = None
            if len(self._finished) > FINISHED_GOALS:
                self._finished.popitem(last=False)
            if not outlet.send(encode(result_event(event))):
                self.results_discarded += 1
                log.info(
                    "goal %d %s (%d: %s) after %s disconnected; result discarded",
                    event.goal_id,
                    event.status.value,
                    int(event.error_code),
                    event.error_string,
                    caller.label,
                )
            return
        if outlet.gone:
            return
        try:
            data = encode(feedback_event(event, self.backend.joint_names))
        except (TypeError, IndexError):
            log.exception("cannot encode feedback of goal %d; skipped", event.goal_id)
            return
        if not outlet.offer(data):
            caller.dropped_feedback += 1
            caller.dropped_since_state += 1

    def _hold(self, event: GoalEvent) -> None:
        events = self._early.get(event.goal_id)
        if events is None:
            if len(self._early) >= EARLY_GOALS:
                goal_id, lost = self._early.popitem(last=False)
                log.warning(
                    "discarded %d event(s) of goal %d: no client ever claimed the goal",
                    len(lost),
                    goal_id,
                )
            events = self._early[event.goal_id] = []
        if isinstance(event, GoalResult) or len(events) < EARLY_EVENTS:
            events.append(event)

    def _to_recorders(self, message: Callable[[], dict[str, Any]], what: str) -> None:
        """Send ``message()`` (made only if someone listens) to every caller subscribed with
        ``commands``; an unencodable one is logged as ``what`` and skipped."""
        if self._closed:
            return
        subscribers = [c for c in self._subscribers if c.commands and not c.outlet.gone]
        if not subscribers:
            return
        try:
            data = encode(message())
        except (TypeError, ValueError):
            log.exception("cannot encode %s; skipped", what)
            return
        for caller in subscribers:
            caller.outlet.send(data)

    def on_command(self, trajectory: JointTrajectory, goal_id: int | None) -> None:
        """Send an accepted command (a goal's trajectory, a topic trajectory; empty: a stop) to
        every caller subscribed with ``commands`` (``jtc-hw record``). Not droppable: a
        recording must have every command; a transport disconnects a client that stops reading,
        as for results. Never raises: a command that cannot be encoded is logged and skipped."""
        self._to_recorders(lambda: command_event(trajectory, goal_id, self.backend.now_ns()),
                           "an accepted command")

    def on_record(self, event: dict[str, Any]) -> None:
        """Send a result, fault or re-arm (a ``record`` event) to every caller subscribed with
        ``commands`` (``jtc-hw record`` writes them into its bag). Not droppable, as commands.
        Never raises: an event that cannot be encoded is logged and skipped."""
        self._to_recorders(lambda: record_event(event), "a recorded event")

    def on_state(self, snapshot: dict[str, Any]) -> None:
        """Send a state snapshot to every subscribed caller whose outlet has room, with what
        that caller was not sent since its last one (``dropped``, ``dropped_total``). Never
        raises: a snapshot that cannot be encoded is logged and skipped."""
        if self._closed:
            return
        subscribers = [c for c in self._subscribers if not c.outlet.gone]
        if not subscribers:
            return
        body = {k: v for k, v in snapshot.items() if k not in _RESERVED_STATE_KEYS}
        try:
            head = encode({"event": "state", **body})[:-2]  # without the closing "}\n"
        except TypeError:
            # Never raise into the backend's dispatch: say what is wrong and skip this one.
            log.exception("cannot encode a state snapshot; skipped")
            return
        for caller in subscribers:
            tail = b',"dropped":%d,"dropped_total":%d}\n' % (
                caller.dropped_since_state,
                caller.dropped_total,
            )
            if caller.outlet.offer(head + tail):
                caller.dropped_since_state = 0
            else:
                caller.dropped_state += 1
                caller.dropped_since_state += 1


def _merge(
    request_id: object, theirs: Mapping[str, Any], ours: Mapping[str, Any]
) -> dict[str, Any]:
    out: dict[str, Any] = {"id": request_id, "ok": True}
    out.update((k, v) for k, v in theirs.items() if k not in ("id", "ok"))
    out.update(ours)
    return out
