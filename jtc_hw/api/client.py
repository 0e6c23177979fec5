"""A synchronous Python client for the daemon's socket API (see ``docs/protocol.md``).

Theory of operation
-------------------
One background thread reads the socket and dispatches every message as it arrives: a reply
wakes the caller waiting for it (each request carries a client-chosen ``id``), a goal's
``feedback`` / ``result`` go to its ``GoalHandle``, ``state`` events to the open
``StateSubscription``s. Callers wait on ``threading`` conditions with explicit timeouts; nothing
polls. The handle of an accepted goal is created by the reader thread as it reads the
``accepted`` reply, before it reads anything else, so no event of the goal can be missed.

Example::

    with Client.connect("/run/jtc-hw/jtc-hw.sock") as client:
        goal = client.send_goal({"joint_names": ["j1"], "points": [
            {"time_from_start": 1.0, "positions": [0.5]}]})
        print(goal.wait(timeout_s=10.0)["status"])
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import logging
import os
import socket
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..controller.messages import JointTrajectory
from ..controller.tolerances import JointTolerance
from .calls import (
    NOT_EXPECTED,
    PERMISSION,
    UNTRUSTED,
    ClientConnectionError,
    Pending,
    reply_error,
)
from .events import BINARY_MIN_POINTS, tolerances_to_json, trajectory_columns, trajectory_to_json
from .framing import BUSY, PROTOCOL_VERSION, MessageDecoder, RequestError, encode, encode_frame
from .handles import FeedbackCallback, GoalHandle, StateSubscription
from .paths import (
    client_socket_path,
    peer_pid,
    peer_problem,
    permission_problem,
    socket_problem,
)

__all__ = ["CLIENT_MAX_MESSAGE_BYTES", "DEFAULT_TIMEOUT_S", "Client", "default_socket_path"]

log = logging.getLogger("jtc_hw.client")

DEFAULT_TIMEOUT_S = 5.0
CLIENT_MAX_MESSAGE_BYTES = 64 << 20
"""Longest message the client accepts from the daemon (a large ``get_config``)."""

OPENERS: dict[str, Callable[..., Client]] = {}
"""How ``Client.connect`` opens an address of another transport, by its scheme: ``zenoh:`` is
``ZenohClient.open``, registered by :mod:`.zenoh_client` (which the package imports), so that
this module, which that one builds on, does not import it."""

TrajectoryLike = JointTrajectory | Mapping[str, Any]
ToleranceLike = JointTolerance | Mapping[str, Any]
Frame = tuple[NDArray[np.float64], list[str]]
"""A binary frame's values and column names (``framing.encode_frame``)."""


def default_socket_path() -> str:
    """``$JTC_HW_SOCKET`` if set, else where a daemon of this user puts its socket by default
    (:func:`jtc_hw.api.paths.default_socket_path`), or the system service's if nothing is
    there (:func:`jtc_hw.api.paths.client_socket_path`).
    """
    explicit = os.environ.get("JTC_HW_SOCKET")
    if explicit:
        return explicit
    return client_socket_path()


class Client:
    """A connection to the daemon; create it with ``Client.connect``.

    Every method takes an optional ``timeout_s`` (default: the one given to ``connect``).
    Errors reported by the daemon raise ``GoalRejected`` (goal rejections, with
    ``error_code``) or ``RequestError`` (a ``ProtocolError`` with the machine ``code``), with
    the daemon's message; every request raises ``TimeoutError`` when no reply arrives within
    its timeout and ``ClientConnectionError`` when the connection is lost (the methods' Raises
    sections list what else). Methods may be called from several threads, but not from inside
    a feedback callback (it runs in the reader thread, which would then wait for itself).

    Attributes:
        info: the ``hello`` reply received at connection (joint names, rates, versions).
        binary_min_points: trajectories of this many points or more go as binary frames
            when ``info`` says protocol version 2 (docs/protocol.md, "Binary frames");
            ``None``: always JSON.
    """

    def __init__(self, sock: socket.socket, timeout_s: float, label: str) -> None:
        self._init_state(timeout_s, label)
        self._sock = sock
        self._reader = threading.Thread(
            target=self._read, name=f"jtc_hw-client-reader {label}", daemon=True
        )
        self._reader.start()

    def _init_state(self, timeout_s: float, label: str) -> None:
        """The state of every transport (a subclass may have no socket and no reader)."""
        self.timeout_s = timeout_s
        self.label = label
        self.info: dict[str, Any] = {}
        self.binary_min_points: int | None = BINARY_MIN_POINTS
        self._ids = itertools.count(1)
        self._lock = threading.Lock()  # pending, goals, subscriptions, lost
        self._send_lock = threading.Lock()
        self._pending: dict[int, Pending] = {}
        self._goals: dict[int, GoalHandle] = {}
        self._subscriptions: list[StateSubscription] = []
        self._lost: ClientConnectionError | None = None
        self._unclaimed: RequestError | None = None  # an id-less error no request waited for
        self._closing = False

    @classmethod
    def connect(
        cls,
        path: str | os.PathLike[str] | None = None,
        *,
        tcp: tuple[str, int] | None = None,
        token: str | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        hello: bool = True,
        check_owner: bool | None = None,
        zenoh_config: Any = None,
        trusted_group: str | int | None = None,
        expect_pid: int | None = None,
    ) -> Client:
        """Connect, authenticate (TCP), and say ``hello``.

        Args:
            path: the daemon's unix socket (default: ``default_socket_path()``); not with
                ``tcp``. ``"zenoh:<prefix>"``: the daemon at that Zenoh key prefix, through a
                Zenoh session (``jtc_hw.api.zenoh_client``; needs ``jtc_hw[zenoh]``).
            tcp: ``(host, port)`` of the daemon's loopback TCP endpoint.
            token: the TCP token; with ``zenoh:``, the daemon's ``daemon.zenoh.token``
                (without it the client may only watch: commands get ``unauthorized``).
            timeout_s: for connecting and the default for every request.
            hello: say ``hello`` (and fill ``info``); without it the first request is the
                caller's, e.g. a ``stop`` that must get through a daemon with every client
                slot taken (it is served over the limit; ``hello`` would get ``busy``).
            check_owner: before trusting the unix socket, check that the file belongs to this
                user or root and that its directory is theirs alone. Default: when the path
                is the default one (no ``path``, no ``$JTC_HW_SOCKET``): that path is
                guessable, so another local user could have put a socket there first.
                Whatever the path, the process listening on it (``SO_PEERCRED``) must run as
                this user, root, or a member of ``trusted_group``.
            trusted_group: a group (name or gid) whose members' daemons are trusted: the
                configuration's ``daemon.socket_group`` (a service user's daemon whose group
                may connect). ``None``: only this user's and root's.
            zenoh_config: with ``zenoh:``, the Zenoh configuration (a JSON5 file, a mapping
                of keys to values, or a ``zenoh.Config``; default: connect to a router on
                ``tcp/127.0.0.1:7447``).
            expect_pid: the unix socket must be served by this process (``SO_PEERCRED``),
                checked before any request is sent: a caller that started its own daemon
                (``jtc-hw demo``) never talks to another one that serves the same path.

        Raises:
            ValueError: both ``path`` and ``tcp``, or ``tcp`` without ``token``, or
                ``expect_pid`` with anything but a unix socket.
            ClientConnectionError: nobody listens, this user may not connect to the unix
                socket (``code`` ``permission``; the message names the socket or the
                directory that keeps them out, its owner, group and mode, and what to do),
                the daemon is busy (``code`` ``busy``),
                the socket or its listener failed the owner check (``code`` ``untrusted``;
                the message names the socket, the listener's pid and uid, and what to do),
                another process than ``expect_pid`` serves the socket (``code``
                ``not_expected``, the message names it), or the connection dropped.
            RequestError: the daemon refused the token (``unauthorized``) or the ``hello``.
            ProtocolError: the daemon speaks another protocol version.
            TimeoutError: no answer within ``timeout_s``.
        """
        if path is not None and tcp is not None:
            raise ValueError("give either a unix socket path or tcp=(host, port), not both")
        if expect_pid is not None and (tcp is not None or str(path).startswith("zenoh:")):
            raise ValueError("expect_pid checks a unix socket's peer; it cannot check tcp or zenoh")
        if isinstance(path, str) and path.startswith("zenoh:"):
            return OPENERS["zenoh:"](path.removeprefix("zenoh:"), zenoh_config=zenoh_config,
                                     timeout_s=timeout_s, hello=hello, token=token)
        address: str | tuple[str, int]
        if tcp is not None:
            if not token:
                raise ValueError("a TCP connection needs the daemon's token")
            family, address, label = socket.AF_INET, tcp, f"tcp {tcp[0]}:{tcp[1]}"
            if ":" in tcp[0]:
                family = socket.AF_INET6
        else:
            where = os.fspath(path) if path is not None else default_socket_path()
            family, address, label = socket.AF_UNIX, where, str(where)
            if check_owner is None:
                check_owner = path is None and not os.environ.get("JTC_HW_SOCKET")
            if check_owner:
                _refuse_untrusted(where, socket_problem(where))
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.settimeout(timeout_s)
            sock.connect(address)
            sock.settimeout(None)
        except OSError as exc:
            sock.close()
            if family == socket.AF_UNIX and exc.errno in (errno.EACCES, errno.EPERM):
                # The daemon may well run; this user is not let in (the socket's mode or its
                # directory's): say whose it is and how to get in, not "is it running?".
                raise ClientConnectionError(
                    f"permission denied on {permission_problem(label)}", PERMISSION
                ) from None
            hint = "" if isinstance(exc, TimeoutError) else "; is the daemon running?"
            raise ClientConnectionError(
                f"cannot connect to the daemon at {label}: {exc.strerror or exc}{hint}"
            ) from None
        try:
            if family == socket.AF_UNIX:
                _refuse_untrusted(
                    str(address), peer_problem(sock, str(address), trusted_group), listener=True
                )
            if expect_pid is not None:
                peer = peer_pid(sock)
                if peer != expect_pid:
                    by = "an unidentified process" if peer is None else f"pid {peer}"
                    raise ClientConnectionError(
                        f"{label} is served by {by}, not by the expected pid {expect_pid}",
                        NOT_EXPECTED,
                    )
        except BaseException:
            sock.close()
            raise
        client = cls(sock, timeout_s, label)
        try:
            if tcp is not None:
                assert token is not None
                client._request("auth", {"token": token}, timeout_s)
            if hello:
                client.info = client._request(
                    "hello", {"protocol_version": PROTOCOL_VERSION}, timeout_s
                )
        except RequestError as exc:
            client.close()
            if exc.code == BUSY:  # sent before any request: a refusal of the connection
                raise ClientConnectionError(f"{label}: {exc.message}", BUSY) from None
            raise
        except BaseException:
            client.close()
            raise
        return client

    # -- operations ---------------------------------------------------------------------------

    def hello(self, timeout_s: float | None = None) -> dict[str, Any]:
        """Versions, joint names, rates and the daemon clock (``now_ns``).

        Raises:
            RequestError: the daemon refused it.
        """
        return self._request("hello", {}, timeout_s)

    @property
    def joint_names(self) -> list[str]:
        """The controller's joints, from the ``hello`` at connection."""
        return list(self.info.get("joint_names", []))

    def send_goal(
        self,
        trajectory: TrajectoryLike,
        path_tolerance: Sequence[ToleranceLike] = (),
        goal_tolerance: Sequence[ToleranceLike] = (),
        goal_time_tolerance: float = 0.0,
        *,
        start_in: float | None = None,
        on_feedback: FeedbackCallback | None = None,
        feedback_maxlen: int = 1000,
        timeout_s: float | None = None,
        time_scaling: str | None = None,
    ) -> GoalHandle:
        """Send a ``follow_joint_trajectory`` goal.

        Args:
            trajectory: a ``JointTrajectory`` or its wire form (a mapping).
            path_tolerance, goal_tolerance: ``JointTolerance`` objects or their wire form.
            goal_time_tolerance: seconds allowed past the end (0: the default).
            start_in: start this many seconds after the daemon receives the goal.
            on_feedback: called with each ``feedback`` event, in the reader thread (keep it
                short; do not call client methods from it).
            feedback_maxlen: feedback events buffered for ``GoalHandle.feedback``.
            timeout_s: for the accept/reject reply.
            time_scaling: a goal beyond the joint limits: ``"fit"`` slows it down uniformly
                until it fits, ``"reject"`` refuses it (default: the daemon's
                ``limits.time_scaling``).

        Returns:
            The accepted goal's handle; with ``fit`` in effect its ``time_scale`` and
            ``duration_s`` say how it was slowed.

        Raises:
            GoalRejected: the daemon rejected the goal (``error_code`` says why).
            RequestError: the request was malformed (``bad_request``, naming the field).
            TimeoutError: no reply within the timeout (the goal may still have been accepted;
                its events are then ignored).
        """
        fields, frame = self._trajectory_fields(trajectory, start_in)
        if path_tolerance:
            fields["path_tolerance"] = _tolerances(path_tolerance)
        if goal_tolerance:
            fields["goal_tolerance"] = _tolerances(goal_tolerance)
        if goal_time_tolerance:
            fields["goal_time_tolerance"] = goal_time_tolerance
        if time_scaling is not None:
            fields["time_scaling"] = time_scaling
        pending = Pending("send_goal", on_feedback, feedback_maxlen)
        self._request("send_goal", fields, timeout_s, pending, frame)
        assert pending.goal is not None
        return pending.goal

    def cancel(self, goal_id: int, timeout_s: float | None = None) -> dict[str, Any]:
        """Cancel the executing goal ``goal_id``; its ``canceled`` result follows.

        Raises:
            RequestError: ``not_found`` when the goal is not executing.
        """
        return self._request("cancel_goal", {"goal_id": goal_id}, timeout_s)

    def send_trajectory(
        self,
        trajectory: TrajectoryLike,
        *,
        start_in: float | None = None,
        timeout_s: float | None = None,
        time_scaling: str | None = None,
    ) -> dict[str, Any]:
        """Fire-and-forget trajectory (the ``joint_trajectory`` topic); no points: stop.

        ``time_scaling`` as for ``send_goal``; with ``fit`` in effect the reply has
        ``time_scale`` and ``duration_s``.

        Raises:
            GoalRejected: the daemon refused the trajectory.
            RequestError: the request was malformed.
        """
        fields, frame = self._trajectory_fields(trajectory, start_in)
        if time_scaling is not None:
            fields["time_scaling"] = time_scaling
        return self._request("send_trajectory", fields, timeout_s, None, frame)

    def _trajectory_fields(
        self, trajectory: TrajectoryLike, start_in: float | None
    ) -> tuple[dict[str, Any], Frame | None]:
        """The request's ``trajectory`` field, and its points as a binary frame's columns when
        the daemon speaks version 2 and there are ``BINARY_MIN_POINTS`` or more (then the
        field has no ``points``; docs/protocol.md, "Binary frames")."""
        if self.binary_min_points is not None and self.info.get("protocol_version", 1) >= 2:
            binary = trajectory_columns(trajectory, start_in, self.binary_min_points)
            if binary is not None:
                head, values, columns = binary
                return {"trajectory": head}, (values, columns)
        return {"trajectory": _trajectory(trajectory, start_in)}, None

    def stop(self, timeout_s: float | None = None) -> dict[str, Any]:
        """End any motion and hold the measured position: the active goal ends ``canceled``,
        a topic trajectory stops. The daemon serves it even when every client slot is taken
        (connect with ``hello=False`` and make it the first request). The reply's ``stopped``
        is False (with a ``message``) when there was nothing to stop, the controller not being
        active (e.g. stopped by a hardware fault).

        Raises:
            RequestError: ``hardware``: the daemon could not reach its control loop;
                ``busy``: not served (it was not the first request over the limit).
        """
        return self._request("stop", {}, timeout_s)

    def query_state(
        self,
        *,
        in_s: float | None = None,
        time_ns: int | None = None,
        timeout_s: float | None = None,
    ) -> dict[str, Any]:
        """The ``query_state`` service: the desired state at ``time_ns`` (daemon clock) or
        ``in_s`` seconds from now.

        Returns:
            ``time_ns``, ``success``, ``where``, ``joint_names``, ``positions``, ``velocities``,
            ``accelerations``, ``effort``. As upstream, ``success`` is true only inside the
            trajectory: before its start (``where`` ``"before_start"``) the values are the
            measured state, at or after its last point (``"after_end"``, also while holding) the
            last point's.

        Raises:
            ValueError: not exactly one of ``in_s`` and ``time_ns``.
            RequestError: ``not_active`` when the controller is not active.
        """
        if (in_s is None) == (time_ns is None):
            raise ValueError("give exactly one of in_s (seconds from now) and time_ns")
        fields: dict[str, Any] = {"in": in_s} if in_s is not None else {"time_ns": time_ns}
        return self._request("query_state", fields, timeout_s)

    def subscribe_state(
        self, *, timeout_s: float | None = None, maxlen: int = 100, commands: bool = False
    ) -> StateSubscription:
        """Receive ``state`` events until the subscription is closed.

        Args:
            timeout_s: for the reply, and the default wait of each ``get``/iteration.
            maxlen: messages buffered here; older ones are discarded beyond it.
            commands: also receive a ``command`` event for every command the daemon accepts
                (any client's) and a ``record`` event for every goal result, hardware fault
                and re-arm, in order with the states (their ``event`` field tells them
                apart).
        """
        timeout = self.timeout_s if timeout_s is None else timeout_s
        subscription = StateSubscription(self, timeout, maxlen, commands)
        with self._lock:
            self._subscriptions.append(subscription)
        try:
            self._request("subscribe_state", {"commands": True} if commands else {}, timeout)
        except BaseException:
            with self._lock:
                self._subscriptions.remove(subscription)
            raise
        return subscription

    def _unsubscribe(self, subscription: StateSubscription, timeout_s: float | None) -> None:
        with self._lock:
            if subscription in self._subscriptions:
                self._subscriptions.remove(subscription)
            last = not self._subscriptions
            usable = self._lost is None and not self._closing
        if last and usable:
            # ClientConnectionError: the connection is gone, and with it the subscription
            with contextlib.suppress(ClientConnectionError):
                self._request("unsubscribe_state", {}, timeout_s)

    def get_status(self, timeout_s: float | None = None) -> dict[str, Any]:
        """Loop, hardware, controller and server statistics.
        """
        return self._request("get_status", {}, timeout_s)

    def get_config(self, timeout_s: float | None = None) -> dict[str, Any]:
        """The configuration in effect (the reply's ``config``).
        """
        return dict(self._request("get_config", {}, timeout_s)["config"])

    def get_parameters(
        self, names: Sequence[str] | None = None, timeout_s: float | None = None
    ) -> dict[str, Any]:
        """Controller parameter values by ROS-style name (``gains.<joint>.p``): all of them,
        or ``names``. The reply has ``parameters`` (name to value) and ``read_only`` (those of
        them that cannot change while the daemon runs).

        Raises:
            RequestError: a name is not a parameter (``bad_request``, naming it).
        """
        fields: dict[str, Any] = {} if names is None else {"names": list(names)}
        return self._request("get_parameters", fields, timeout_s)

    def set_parameters(
        self, changes: Mapping[str, Any], timeout_s: float | None = None
    ) -> dict[str, Any]:
        """Change controller parameters while the daemon runs, all or nothing, e.g.
        ``client.set_parameters({"gains.j1.p": 12.0, "constraints.goal_time": 0.5})``.

        Upstream's timing: gains from the next control cycle, default tolerances and the goal
        checks from the next goal or trajectory (the running one keeps its own), ``cmd_timeout``
        and the activation settings at the next activation. The reply has ``parameters`` (the
        new values), ``takes_effect`` (when, per name) and ``warnings`` (settings the change
        made suspicious, as ``jtc-hw check`` says).

        Raises:
            RequestError: ``bad_request``: an unknown or read-only parameter, or a value the
                configuration file would refuse (the same message); nothing changed.
        """
        return self._request("set_parameters", {"parameters": dict(changes)}, timeout_s)

    def sim(
        self,
        component: str,
        freeze: bool | None = None,
        timeout_s: float | None = None,
        *,
        fault: str | None = None,
    ) -> dict[str, Any]:
        """Freeze (or release) a simulated component's feedback, or inject a read fault that
        latches until :meth:`rearm`.

        Raises:
            RequestError: no such simulated component (``bad_request``), or it failed.
        """
        fields: dict[str, Any] = {"component": component}
        if freeze is not None:
            fields["freeze"] = freeze
        if fault is not None:
            fields["fault"] = fault
        return self._request("sim", fields, timeout_s)

    def rearm(self, timeout_s: float | None = None) -> dict[str, Any]:
        """Leave a hardware fault: the daemon reboots / fault-resets the devices, re-reads the
        joints and holds where they are (no jump). Goals can be sent again afterwards.

        Raises:
            RequestError: nothing to re-arm (the controller is running), or re-arming failed
                (the message says why; the daemon stays in its safe state).
        """
        return self._request("rearm", {}, timeout_s)

    def set_speed_scaling(
        self, factor: float | None = None, *, resume: bool = False, timeout_s: float | None = None
    ) -> dict[str, Any]:
        """Set the speed scaling factor (1: as planned, 0.5: half speed, 0: pause), or with
        ``resume=True`` go back to the factor before the pause. The factor ramps to its new
        value within the joints' acceleration limits; the state stream's ``speed_scaling``
        shows it. The reply has ``factor`` (in force now) and ``target`` (what it ramps to).

        Example::

            client.set_speed_scaling(0.0)            # pause smoothly
            client.set_speed_scaling(resume=True)    # carry on

        Raises:
            ValueError: neither or both of ``factor`` and ``resume`` given.
            RequestError: a factor out of [0, max] (max: the daemon's
                ``speed_scaling.max_scaling_factor``, 1 by default) or not a number
                (``bad_request``, naming the range).
        """
        if (factor is None) != resume:
            raise ValueError("give either a factor or resume=True")
        fields: dict[str, Any] = {"resume": True} if resume else {"factor": factor}
        return self._request("set_speed_scaling", fields, timeout_s)

    # -- lifecycle ----------------------------------------------------------------------------

    def close(self) -> None:
        """Close the connection and join the reader thread. Idempotent.

        A goal still running goes on in the daemon; its result is discarded there.
        """
        with self._lock:
            self._closing = True
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)
        if self._reader is not threading.current_thread():
            self._reader.join()
        self._sock.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Client({self.label!r})"

    # -- internals ----------------------------------------------------------------------------

    def _request(
        self,
        op: str,
        fields: dict[str, Any],
        timeout_s: float | None,
        pending: Pending | None = None,
        frame: Frame | None = None,
    ) -> dict[str, Any]:
        timeout = self.timeout_s if timeout_s is None else timeout_s
        pending = pending or Pending(op, None, 0)
        request_id = next(self._ids)
        message = {"id": request_id, "op": op, **fields}
        data = encode(message) if frame is None else encode_frame(message, *frame)
        with self._lock:
            self._check_open(op)
            self._pending[request_id] = pending
        try:
            with self._send_lock:
                self._sock.sendall(data)
        except OSError as exc:
            # The daemon closed the connection; it may have said why first ("busy"): let the
            # reader thread read that and the end of the stream.
            if self._reader is not threading.current_thread():
                self._reader.join(timeout)
            with self._lock:
                self._pending.pop(request_id, None)
                lost = self._lost
            if not pending.done.is_set():
                raise lost or ClientConnectionError(
                    f"{op}: sending to {self.label} failed: {exc}"
                ) from None
        if not pending.done.wait(timeout):
            with self._lock:
                self._pending.pop(request_id, None)
            if not pending.done.is_set():
                raise TimeoutError(f"no reply to {op!r} from {self.label} within {timeout} s")
        if pending.error is not None:
            raise pending.error
        assert pending.reply is not None
        return pending.reply

    def _check_open(self, op: str) -> None:
        """Raise why no request can be made (with ``_lock`` held): the connection is lost, or
        the client closed."""
        if self._lost is not None:
            raise self._lost
        if self._closing:
            raise ClientConnectionError(f"{op}: the client is closed")

    def _read(self) -> None:
        decoder = MessageDecoder(CLIENT_MAX_MESSAGE_BYTES, frames=False)
        reason = "the daemon closed the connection"
        try:
            while True:
                data = self._sock.recv(65536)
                for item in decoder.feed(data) if data else decoder.end():
                    if isinstance(item, RequestError):
                        reason = f"the daemon sent an unreadable message: {item.message}"
                        return
                    self._dispatch(item)
                if not data:
                    return
        except OSError as exc:
            reason = f"connection error: {exc}"
        finally:
            code = None
            with self._lock:
                if self._closing:
                    reason = "the client was closed"
                elif self._unclaimed is not None:
                    code = self._unclaimed.code
                    reason = f"{reason} ({code}: {self._unclaimed.message})"
            self._fail_all(ClientConnectionError(f"{self.label}: {reason}", code))

    def _dispatch(self, message: dict[str, Any]) -> None:
        event = message.get("event")
        if event is not None:
            self._dispatch_event(event, message)
            return
        request_id = message.get("id")
        with self._lock:
            if request_id is None and not message.get("ok", False):
                # An error the daemon could not tie to an id (a message too large to read, or
                # "busy" before any request): replies come in request order, so it answers the
                # oldest request still waiting.
                key = next(iter(self._pending), None)
            else:
                key = request_id if isinstance(request_id, int) else None
            pending = self._pending.pop(key, None) if key is not None else None
        if pending is None:
            if not message.get("ok", False):
                error = reply_error(message)
                if isinstance(error, RequestError) and request_id is None:
                    self._unclaimed = error  # e.g. "busy" before our first request was sent
            return  # otherwise a reply to a request that timed out
        if message.get("ok"):
            if pending.op == "send_goal":
                goal_id = int(message["goal_id"])
                handle = GoalHandle(self, goal_id, pending.on_feedback, pending.feedback_maxlen)
                if "time_scale" in message:
                    handle.time_scale = float(message["time_scale"])
                    handle.duration_s = float(message["duration_s"])
                with self._lock:
                    self._goals[goal_id] = handle
                pending.goal = handle
            pending.reply = message
        else:
            pending.error = reply_error(message)
        pending.done.set()

    def _dispatch_event(self, event: str, message: dict[str, Any]) -> None:
        if event in ("state", "command", "record"):
            with self._lock:
                subscriptions = list(self._subscriptions)
            for subscription in subscriptions:
                if event == "state" or subscription.commands:
                    subscription._add(message)
            return
        goal_id = message.get("goal_id")
        if not isinstance(goal_id, int):
            return
        with self._lock:
            handle = self._goals.get(goal_id)
            if handle is not None and event == "result":
                del self._goals[goal_id]
        if handle is None:
            return
        if event == "feedback":
            handle._add_feedback(message)
        elif event == "result":
            handle._set_result(message)

    def _fail_all(self, error: ClientConnectionError) -> None:
        with self._lock:
            self._lost = error
            pending, self._pending = list(self._pending.values()), {}
            goals, self._goals = list(self._goals.values()), {}
            subscriptions = list(self._subscriptions)
        for p in pending:
            p.error = error
            p.done.set()
        for goal in goals:
            goal._connection_lost(error)
        for subscription in subscriptions:
            subscription._connection_lost(error)


def _refuse_untrusted(path: str, problem: str | None, listener: bool = False) -> None:
    """Raise the refusal of ``path`` for ``problem`` (of the file or directory; with
    ``listener``, of the process listening), if any, with what to do."""
    if problem is None:
        return
    if listener:
        hint = (
            "If that daemon's user is trusted, name its group in the configuration "
            "(daemon.socket_group) and pass it (--config FILE)"
        )
    else:
        hint = (
            "If it is stale, remove it; if you trust that daemon, name its socket explicitly "
            "(--socket PATH, or JTC_HW_SOCKET=PATH)"
        )
    raise ClientConnectionError(f"refusing the daemon socket {path}: {problem}. {hint}", UNTRUSTED)


def _trajectory(trajectory: TrajectoryLike, start_in: float | None) -> dict[str, Any]:
    if isinstance(trajectory, JointTrajectory):
        return trajectory_to_json(trajectory, start_in)
    out = dict(trajectory)
    if start_in is not None:
        if "start_time_ns" in out:
            raise ValueError("give either the trajectory's start_time_ns or start_in, not both")
        out["start_in"] = start_in
    return out


def _tolerances(tolerances: Sequence[ToleranceLike]) -> list[Any]:
    return [
        tolerances_to_json([t])[0] if isinstance(t, JointTolerance) else dict(t) for t in tolerances
    ]
