"""The records between the two processes (jtc_hw.daemon.channel.messages): they cross a pickle
intact, are matched by class, and a request's error keeps its class from the one exception
tree."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from jtc_hw.controller.joints import JointCommand
from jtc_hw.controller.limits_check import TimeScaling
from jtc_hw.daemon.channel.messages import (
    Cancel,
    Committed,
    Events,
    Exit,
    Failed,
    Fault,
    Log,
    Ready,
    Reference,
    Reply,
    Request,
    SetSpeedScaling,
    Shutdown,
    Sim,
    Stale,
    State,
    Status,
    Stop,
)
from jtc_hw.daemon.core.backend_api import Accepted
from jtc_hw.errors import (
    CommunicationError,
    ConfigurationError,
    ControllerStateError,
    GoalRejected,
    HardwareError,
    JtcHwError,
    ProtocolError,
)


def crossed(message: object) -> object:
    """``message`` as the other process gets it (the outbox's pickle protocol)."""
    return pickle.loads(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))


def state() -> State:
    z = np.zeros(2)
    command = JointCommand(z, None, None, None)
    return State(5, np.zeros((4, 2)), z, z, np.zeros((3, 2)), command, True, None, 0.0, 0.0,
                 z, command, 1.0, 1.0, 5)


@pytest.mark.parametrize(
    "message",
    [
        Ready(1, 2, 3, {"arm": "ok"}),
        Reference(1, None, 7),
        Committed(7, 1),
        Stale(7, "not active: controller stopped"),
        Reply(3, {"factor": 1.0, "target": 0.5}),
        Failed(3, GoalRejected, "the controller is not active"),
        Log(20, "line"),
        Fault("motor 1 overheated"),
        Exit(0),
        Status({"loop": {}}),
        Events(()),
        Request(4, Cancel(9)),
        Request(5, Sim("arm", True, None)),
        Request(6, Shutdown("test")),
    ],
)
def test_a_record_crosses_the_pipe_equal_and_of_its_class(message: object) -> None:
    got = crossed(message)
    assert type(got) is type(message) and got == message


def test_the_state_is_a_named_record() -> None:
    got = crossed(state())
    assert isinstance(got, State)
    match got:
        case State(time_ns=t, holding=holding, trajectory_time_ns=tau):
            assert (t, holding, tau) == (5, True, 5)


def test_the_state_crosses_with_every_array_its_own() -> None:
    """State packs its arrays into one buffer to cross (messages.State.__reduce__): each must
    come back with its values, shape and None-ness, writable, and a State holding something
    else than float64 arrays crosses as it is."""
    x = np.linspace(0.0, 1.0, 3)
    sent = State(7, np.stack((x, x + 1, x + 2, x + 3)), x + 4, x + 5,
                 np.stack((x * 2, x * 3, x * 4)), JointCommand(x + 6, None, x + 7, None),
                 False, 3, 0.5, 0.25, None, JointCommand(None, x + 8, None, x + 9), 0.5, 1.0, 9)
    got = crossed(sent)
    assert isinstance(got, State)
    for field in State._fields:
        a, b = getattr(sent, field), getattr(got, field)
        pairs = [(a, b)]
        if isinstance(a, JointCommand):
            names = ("positions", "velocities", "accelerations", "effort")
            pairs = [(getattr(a, name), getattr(b, name)) for name in names]
        for u, v in pairs:
            if isinstance(u, np.ndarray):
                assert v.shape == u.shape and v.dtype == u.dtype and np.array_equal(u, v), field
                assert v.flags.writeable, field
            else:
                assert type(v) is type(u) and v == u, field
    odd = sent._replace(positions=[1.0, 2.0, 3.0])
    assert crossed(odd).positions == [1.0, 2.0, 3.0]


def test_a_request_is_matched_by_its_op_class() -> None:
    def name(request: Request) -> str:
        match request:
            case Request(_, Cancel(goal_id)):
                return f"cancel {goal_id}"
            case Request(_, SetSpeedScaling(None)):
                return "resume"
            case Request(_, Stop()):
                return "stop"
        return "other"

    assert name(crossed(Request(1, Cancel(4)))) == "cancel 4"  # type: ignore[arg-type]
    assert name(crossed(Request(2, SetSpeedScaling(None)))) == "resume"  # type: ignore[arg-type]
    assert name(crossed(Request(3, Stop()))) == "stop"  # type: ignore[arg-type]
    assert Stop.name == "stop" and SetSpeedScaling.name == "set_speed_scaling"


@pytest.mark.parametrize(
    "raised",
    [
        GoalRejected("the controller is not active; commands are accepted once it is"),
        ControllerStateError("update: the controller is not active"),
        ConfigurationError("not a number", "speed_scaling.factor"),
        HardwareError("component 'arm' is dynamixel hardware"),
        CommunicationError("motor 3 did not answer"),
    ],
)
def test_a_failure_keeps_its_class_and_text(raised: JtcHwError) -> None:
    failed = crossed(Failed.of(8, raised))
    assert isinstance(failed, Failed) and failed.request_id == 8
    again = failed.exception()
    assert type(again) is type(raised) and str(again) == str(raised)


@pytest.mark.parametrize("raised", [JtcHwError("unknown loop request"), ProtocolError("crc")])
def test_a_failure_the_api_has_no_answer_for_is_a_hardware_error(raised: JtcHwError) -> None:
    again = Failed.of(8, raised).exception()
    assert type(again) is HardwareError and str(again) == str(raised)


def test_accepted_carries_how_the_goal_was_fitted() -> None:
    assert Accepted.of(3, None) == Accepted(3, None, None)
    assert Accepted.of(3, TimeScaling(1.5, 3.0)) == Accepted(3, 1.5, 3.0)
    with pytest.raises(AttributeError):
        Accepted(3).goal_id = 4  # type: ignore[misc]
