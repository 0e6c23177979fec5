"""Hardware contract: lifecycle guard, parameter schema, HardwareSet mapping, registry."""

from __future__ import annotations

import importlib.metadata
import json
import logging
import math
import sys
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from jtc_hw.controller.joints import JointCommand, JointState
from jtc_hw.errors import (
    CommunicationError,
    ConfigurationError,
    ControllerStateError,
    HardwareError,
)
from jtc_hw.hardware import (
    BUILTIN_HARDWARE,
    ENTRY_POINT_GROUP,
    TRANSITIONS,
    HardwareInterface,
    HardwareSet,
    HardwareSpec,
    LifecycleState,
    ParamKind,
    ParamSpec,
    SafeAction,
    available_hardware,
    check_hardware_kind,
    create_hardware,
    hardware_class,
    param_table,
    register_hardware,
    unregister_hardware,
    validate_params,
)
from jtc_hw.hardware.mirror import MirrorHardware

UNC, INA, ACT, FIN = (
    LifecycleState.UNCONFIGURED,
    LifecycleState.INACTIVE,
    LifecycleState.ACTIVE,
    LifecycleState.FINALIZED,
)
NAN = math.nan


class Recorder(HardwareInterface):
    """Records primitive calls; ``fail[primitive]`` is raised by that primitive."""

    kind: ClassVar[str] = "recorder"
    PARAMS: ClassVar[Mapping[str, ParamSpec]] = param_table(
        ParamSpec("gain", ParamKind.FLOAT, 1.0, "a number", minimum=0.0, maximum=10.0),
        ParamSpec("retries", ParamKind.INT, 3, "an integer", minimum=0),
        ParamSpec("verbose", ParamKind.BOOL, False, "a flag"),
        ParamSpec("mode", ParamKind.STRING, "fast", "a choice", choices=("fast", "slow")),
        ParamSpec("offsets", ParamKind.FLOAT, 0.0, "per joint", per_joint=True),
        ParamSpec("limits", ParamKind.RANGE, (-math.inf, math.inf), "per joint range",
                  per_joint=True, nullable=True),
        ParamSpec("ids", ParamKind.INTS, (), "ids", minimum=1, unique=True),
    )

    def __init__(
        self,
        name: str = "rec",
        joints: Sequence[str] = ("a", "b"),
        command_interfaces: Sequence[str] = ("position",),
        state_interfaces: Sequence[str] = ("position", "velocity"),
        params: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__(name, joints, command_interfaces, state_interfaces, params or {})
        self.calls: list[tuple[Any, ...]] = []
        self.fail: dict[str, BaseException] = {}
        self.positions = np.arange(len(self.joints), dtype=float) + 1.0
        self.held = self.nan_command()
        self.bad_state: JointState | None = None

    def _maybe_fail(self, name: str) -> None:
        if name in self.fail:
            raise self.fail[name]

    def _configure(self) -> None:
        self.calls.append(("configure",))
        self._maybe_fail("configure")

    def _activate(self, now_ns: int) -> JointCommand:
        self.calls.append(("activate", now_ns))
        self._maybe_fail("activate")
        return self.held

    def _read(self, now_ns: int) -> JointState:
        self.calls.append(("read", now_ns))
        self._maybe_fail("read")
        if self.bad_state is not None:
            return self.bad_state
        return JointState(self.positions.copy(), self.positions * 10.0)

    def _write(self, now_ns: int, command: JointCommand) -> None:
        self.calls.append(("write", now_ns, command))
        self._maybe_fail("write")

    def _deactivate(self, now_ns: int, action: SafeAction) -> None:
        self.calls.append(("deactivate", now_ns, action))
        self._maybe_fail("deactivate")

    def _cleanup(self) -> None:
        self.calls.append(("cleanup",))
        self._maybe_fail("cleanup")


def bring_to(hw: Any, state: LifecycleState) -> None:
    if state is FIN:
        hw.shutdown(0)
        return
    if state in (INA, ACT):
        hw.configure()
    if state is ACT:
        hw.activate(0)


def call(hw: Any, method: str) -> Any:
    if method in ("activate", "read", "deactivate"):
        return getattr(hw, method)(1)
    if method == "write":
        return hw.write(1, JointCommand([0.0, 0.0]))
    return getattr(hw, method)()


METHODS = ("configure", "activate", "read", "write", "deactivate", "cleanup")

# Every call the lifecycle forbids, with the advice the error must give.
WRONG_ORDER = {
    (UNC, "activate"): "call configure() first",
    (UNC, "read"): "call configure() first",
    (UNC, "write"): "call configure() and activate() first",
    (UNC, "deactivate"): "call configure() and activate() first",
    (UNC, "cleanup"): "call configure() first",
    (INA, "configure"): "call cleanup() first",
    (INA, "write"): "call activate() first",
    (INA, "deactivate"): "call activate() first",
    (ACT, "configure"): "call deactivate() and cleanup() first",
    (ACT, "activate"): "call deactivate() first",
    (ACT, "cleanup"): "call deactivate() first",
    **{(FIN, m): "it was shut down; create a new instance" for m in METHODS},
}


# --------------------------------------------------------------------------------------------
# Lifecycle
# --------------------------------------------------------------------------------------------


def test_wrong_order_table_covers_every_forbidden_call() -> None:
    allowed = {(s, m) for (s, m) in TRANSITIONS} | {(INA, "read"), (ACT, "read"), (ACT, "write")}
    every = {(s, m) for s in LifecycleState for m in METHODS}
    assert set(WRONG_ORDER) == every - allowed


@pytest.mark.parametrize(("state", "method"), sorted(WRONG_ORDER, key=str))
def test_wrong_order_call_raises_and_changes_nothing(state: LifecycleState, method: str) -> None:
    hw = Recorder()
    bring_to(hw, state)
    before = list(hw.calls)
    with pytest.raises(ControllerStateError) as info:
        call(hw, method)
    assert str(info.value) == (
        f"recorder hardware 'rec': cannot call {method}() while {state.value}; "
        f"{WRONG_ORDER[state, method]}"
    )
    assert hw.state is state
    assert hw.calls == before
    assert hw.last_fault is None


def test_full_lifecycle_leaves_documented_states_and_calls_primitives() -> None:
    hw = Recorder(params={"safe_action": "torque_off"})
    assert hw.state is UNC
    hw.configure()
    assert hw.state is INA
    state = hw.read(5)  # reading a disarmed robot is allowed
    np.testing.assert_array_equal(state.positions, [1.0, 2.0])
    held = hw.activate(10)
    assert hw.state is ACT
    assert held.positions is not None and np.isnan(held.positions).all()
    assert held.velocities is None and held.effort is None
    command = JointCommand([0.5, NAN])
    hw.write(11, command)
    hw.read(12)
    hw.deactivate(13)
    assert hw.state is INA
    hw.cleanup()
    assert hw.state is UNC
    assert hw.calls == [
        ("configure",),
        ("read", 5),
        ("activate", 10),
        ("write", 11, command),
        ("read", 12),
        ("deactivate", 13, SafeAction.TORQUE_OFF),
        ("cleanup",),
    ]
    assert hw.status()["counters"] == {
        "reads": 2, "writes": 1, "read_errors": 0, "write_errors": 0, "activations": 1,
    }


def test_configure_and_activate_failures_leave_the_state_unchanged() -> None:
    hw = Recorder()
    hw.fail["configure"] = OSError("no such port /dev/ttyUSB0")
    with pytest.raises(HardwareError) as info:
        hw.configure()
    assert str(info.value) == (
        "recorder hardware 'rec': configure failed: OSError: no such port /dev/ttyUSB0"
    )
    assert isinstance(info.value.__cause__, OSError)
    assert hw.state is UNC
    del hw.fail["configure"]
    hw.configure()
    hw.fail["activate"] = CommunicationError("motor 3 does not answer")
    with pytest.raises(CommunicationError, match="motor 3 does not answer"):
        hw.activate(0)
    assert hw.state is INA
    assert hw.last_fault == "motor 3 does not answer"


def test_deactivate_and_cleanup_failures_still_leave_their_target_state() -> None:
    hw = Recorder()
    bring_to(hw, ACT)
    hw.fail["deactivate"] = RuntimeError("torque off not acknowledged")
    with pytest.raises(HardwareError, match="deactivate failed: RuntimeError: torque off"):
        hw.deactivate(1)
    assert hw.state is INA
    with pytest.raises(ControllerStateError):
        hw.write(2, JointCommand([0.0, 0.0]))
    hw.fail["cleanup"] = ValueError("close failed")
    with pytest.raises(HardwareError, match="cleanup failed"):
        hw.cleanup()
    assert hw.state is UNC


def test_jtc_hw_errors_pass_through_foreign_ones_are_wrapped() -> None:
    hw = Recorder(name="gripper")
    bring_to(hw, ACT)
    original = CommunicationError("timeout on id 4")
    hw.fail["read"] = original
    with pytest.raises(CommunicationError) as info:
        hw.read(1)
    assert info.value is original
    hw.fail["read"] = KeyError("x")
    with pytest.raises(HardwareError) as wrapped:
        hw.read(2)
    assert str(wrapped.value) == "recorder hardware 'gripper': read failed: KeyError: 'x'"
    hw.fail["write"] = ZeroDivisionError("division by zero")
    with pytest.raises(HardwareError, match="'gripper': write failed: ZeroDivisionError"):
        hw.write(3, JointCommand([0.0, 0.0]))
    assert hw.state is ACT  # the caller decides what a fault means
    status = hw.status()
    assert status["last_fault"] == (
        "recorder hardware 'gripper': write failed: ZeroDivisionError: division by zero"
    )
    assert status["counters"]["read_errors"] == 2
    assert status["counters"]["write_errors"] == 1


@pytest.mark.parametrize(
    "bad",
    [
        JointState([1.0, 2.0, 3.0], [0.0, 0.0, 0.0]),
        JointState([1.0, 2.0]),  # velocity state configured but missing
        JointState([1.0, 2.0], [0.0]),
    ],
)
def test_read_rejects_a_state_of_the_wrong_shape(bad: JointState) -> None:
    hw = Recorder()
    bring_to(hw, ACT)
    hw.bad_state = bad
    with pytest.raises(HardwareError, match="does not match its 2 joints .* driver bug"):
        hw.read(1)


def test_activate_fills_missing_held_values_and_rejects_wrong_sizes() -> None:
    hw = Recorder(command_interfaces=("position", "velocity"))
    hw.configure()
    hw.held = JointCommand(positions=[0.1, 0.2], effort=[9.0, 9.0])
    held = hw.activate(0)
    np.testing.assert_array_equal(held.positions, [0.1, 0.2])
    assert held.velocities is not None and np.isnan(held.velocities).all()
    assert held.effort is None  # not a configured interface
    hw.deactivate(1)
    hw.held = JointCommand(positions=[0.1, 0.2, 0.3])
    hw.calls.clear()
    with pytest.raises(HardwareError, match="returned 3 position values for 2 joints"):
        hw.activate(2)
    assert hw.state is INA
    assert hw.calls == [("activate", 2), ("deactivate", 2, SafeAction.HOLD)]


def test_shutdown_from_any_state_is_final_and_idempotent() -> None:
    hw = Recorder()
    bring_to(hw, ACT)
    hw.shutdown(7)
    assert hw.state is FIN
    assert hw.calls[-2:] == [("deactivate", 7, SafeAction.HOLD), ("cleanup",)]
    hw.shutdown(8)
    assert hw.state is FIN
    fresh = Recorder()
    fresh.shutdown(0)
    assert fresh.state is FIN and fresh.calls == []


def test_shutdown_attempts_both_steps_and_raises_the_first_error() -> None:
    hw = Recorder()
    bring_to(hw, ACT)
    hw.fail["deactivate"] = RuntimeError("first")
    hw.fail["cleanup"] = RuntimeError("second")
    with pytest.raises(HardwareError, match="first") as info:
        hw.shutdown(1)
    assert hw.state is FIN
    assert any("second" in note for note in info.value.__notes__)


def test_status_is_json_able() -> None:
    hw = Recorder(joints=("x",))
    status = hw.status()
    assert json.loads(json.dumps(status)) == status
    assert status == {
        "name": "rec",
        "kind": "recorder",
        "state": "unconfigured",
        "joints": ["x"],
        "command_interfaces": ["position"],
        "state_interfaces": ["position", "velocity"],
        "safe_action": "hold",
        "last_fault": None,
        "counters": {
            "reads": 0, "writes": 0, "read_errors": 0, "write_errors": 0, "activations": 0,
        },
        "details": {},
        # A kind without health readings: its joints as motors, nothing known, no bus.
        "health": {
            "motors": [{
                "motor": "x", "joint": "x", "model": None, "firmware": None, "mode": None,
                "torque_enabled": None, "temperature_c": None, "voltage_v": None,
                "errors": [], "last_fault": None,
            }],
            "bus": None,
            "warnings": [],
        },
    }
    assert repr(hw) == "<Recorder 'rec' (recorder) unconfigured joints=[x]>"


# --------------------------------------------------------------------------------------------
# Constructor and parameter schema
# --------------------------------------------------------------------------------------------


def error_of(**kwargs: Any) -> ConfigurationError:
    with pytest.raises(ConfigurationError) as info:
        Recorder(**kwargs)
    return info.value


def test_a_subclass_must_declare_its_kind() -> None:
    class NoKind(HardwareInterface):
        def _read(self, now_ns: int) -> JointState:
            raise NotImplementedError

        def _write(self, now_ns: int, command: JointCommand) -> None:
            raise NotImplementedError

    with pytest.raises(TypeError, match="NoKind must declare a non-empty 'kind'"):
        NoKind("n", ["a"], ["position"], ["position"], {})


@pytest.mark.parametrize(
    ("kwargs", "path", "message"),
    [
        ({"name": ""}, "name", "expected a non-empty component name, got '' (str)"),
        ({"joints": []}, "joints", "must not be empty"),
        ({"joints": "a"}, "joints", "expected a list of strings, got 'a' (str)"),
        ({"joints": ["a", "a"]}, "joints", "contains 'a' more than once"),
        ({"joints": ["a", 3]}, "joints", "element 1 is 3 (int)"),
        ({"command_interfaces": ["positon"]}, "command_interfaces",
         "recorder hardware 'rec' does not support the 'positon' interface; it supports "
         "[position, velocity, acceleration, effort]; did you mean 'position'?"),
        ({"state_interfaces": ["effort"]}, "state_interfaces",
         "does not support the 'effort' interface"),
        ({"state_interfaces": ["velocity"]}, "state_interfaces",
         "recorder hardware 'rec': the state interfaces must include 'position', got [velocity]"),
    ],
)
def test_constructor_checks_names_and_interfaces(
    kwargs: dict[str, Any], path: str, message: str
) -> None:
    error = error_of(**kwargs)
    assert error.path == path
    assert message in str(error)


def test_a_kind_may_restrict_its_interfaces() -> None:
    class PositionOnly(Recorder):
        kind: ClassVar[str] = "position-only"
        COMMAND_INTERFACES: ClassVar[tuple[str, ...]] = ("position",)

    with pytest.raises(ConfigurationError) as info:
        PositionOnly(command_interfaces=["effort"])
    assert str(info.value) == (
        "command_interfaces: position-only hardware 'rec' does not support the 'effort' "
        "interface; it supports [position]"
    )


@pytest.mark.parametrize(
    ("params", "path", "message"),
    [
        ({"gian": 1.0}, "params.gian",
         "unknown parameter 'gian' of recorder hardware 'rec'; did you mean 'gain'?"),
        ({"zzz": 1}, "params.zzz", "known parameters: safe_action, gain, retries, verbose"),
        ({"gain": "1.0"}, "params.gain", "expected a number, got '1.0' (str)"),
        ({"gain": True}, "params.gain", "expected a number, got True (bool)"),
        ({"gain": math.nan}, "params.gain", "expected a finite number, got nan"),
        ({"gain": -1}, "params.gain", "must be between 0 and 10, got -1"),
        ({"gain": 11.5}, "params.gain", "must be between 0 and 10, got 11.5"),
        ({"retries": 2.5}, "params.retries", "expected an integer, got 2.5 (float)"),
        ({"retries": -1}, "params.retries", "must be >= 0, got -1"),
        ({"verbose": "true"}, "params.verbose",
         "expected true or false, got 'true' (str); write true without quotes"),
        ({"mode": "fats"}, "params.mode",
         "'fats' is not allowed; allowed values: 'fast', 'slow'; did you mean 'fast'?"),
        ({"safe_action": "torque-off"}, "params.safe_action",
         "allowed values: 'hold', 'torque_off'; did you mean 'torque_off'?"),
        ({"offsets": [1.0]}, "params.offsets",
         "has 1 entries but the component has 2 joints (a, b); give one per joint"),
        ({"offsets": [1.0, "x"]}, "params.offsets[1]", "(joint 'b') expected a number"),
        ({"offsets": {"c": 1.0}}, "params.offsets.c",
         "'c' is not one of this component's joints (a, b)"),
        ({"limits": [[1.0, 0.0], None]}, "params.limits[0]", "min 1 is greater than max 0"),
        ({"limits": [1.0, 2.0, 3.0]}, "params.limits", "has 3 entries"),
        ({"limits": [[0.0, 1.0], [0.0]]}, "params.limits[1]",
         "expected a [min, max] pair of numbers, got [0.0] (list)"),
        ({"ids": [1, 1]}, "params.ids", "contains 1 more than once"),
        ({"ids": [1, 0]}, "params.ids", "element 1: must be >= 1, got 0"),
        ({"ids": 3}, "params.ids", "expected a list of integers, got 3 (int)"),
        ({1: 2}, "params", "keys must be strings, got 1 (int); quote it"),
    ],
)
def test_params_are_checked_against_the_schema(
    params: dict[Any, Any], path: str, message: str
) -> None:
    error = error_of(params=params)
    assert error.path == path
    assert message in str(error)


def test_params_are_normalised_with_defaults() -> None:
    hw = Recorder(params={"gain": 2, "offsets": 0.5, "limits": {"b": [-1, 1]}})
    assert dict(hw.params) == {
        "safe_action": "hold",
        "gain": 2.0,
        "retries": 3,
        "verbose": False,
        "mode": "fast",
        "offsets": (0.5, 0.5),
        "limits": ((-math.inf, math.inf), (-1.0, 1.0)),
        "ids": (),
    }
    assert isinstance(hw.params["gain"], float)
    assert hw.safe_action is SafeAction.HOLD
    with pytest.raises(TypeError):
        hw.params["gain"] = 3.0  # type: ignore[index]
    per_list = Recorder(params={"offsets": {"b": 2.0}, "limits": [None, [0, math.inf]]})
    assert per_list.params["offsets"] == (0.0, 2.0)
    assert per_list.params["limits"] == ((-math.inf, math.inf), (0.0, math.inf))
    assert Recorder(params={"limits": None}).params["limits"] == ((-math.inf, math.inf),) * 2


def test_validate_params_required_sections_and_free_mappings() -> None:
    inner = param_table(ParamSpec("token", ParamKind.STRING, "", "secret", required=True))
    table = param_table(
        ParamSpec("tcp", ParamKind.SECTION, None, "endpoint", nullable=True, fields=inner),
        ParamSpec("extra", ParamKind.SECTION, {}, "anything"),
    )
    assert dict(validate_params(table, None)) == {"tcp": None, "extra": {}}
    result = validate_params(table, {"tcp": {"token": "t"}, "extra": {"a": [1, {"b": 2}]}})
    assert dict(result["tcp"]) == {"token": "t"}
    assert result["extra"]["a"][0] == 1 and result["extra"]["a"][1]["b"] == 2
    assert isinstance(result["extra"]["a"], tuple)
    with pytest.raises(ConfigurationError) as info:
        validate_params(table, {"tcp": {}}, "daemon")
    assert str(info.value) == "daemon.tcp.token: missing required parameter 'token' (secret)"
    with pytest.raises(ConfigurationError, match="daemon: expected a mapping, got 3 \\(int\\)"):
        validate_params(table, 3, "daemon")  # type: ignore[arg-type]
    with pytest.raises(ConfigurationError, match="extra: expected a mapping"):
        validate_params(table, {"extra": [1]})
    with pytest.raises(ValueError, match="duplicate parameter names"):
        param_table(inner["token"], inner["token"])


# --------------------------------------------------------------------------------------------
# HardwareSet
# --------------------------------------------------------------------------------------------

CONTROLLER_JOINTS = ("j1", "j2", "j3", "j4", "j5")


@pytest.fixture
def interleaved() -> tuple[Recorder, Recorder, HardwareSet]:
    """j3, j1, j5 on 'arm' (in that order) and j4, j2 on 'gripper'."""
    arm = Recorder("arm", ("j3", "j1", "j5"), ("position", "velocity"))
    gripper = Recorder("gripper", ("j4", "j2"), ("position", "velocity"))
    arm.positions = np.array([3.0, 1.0, 5.0])
    gripper.positions = np.array([4.0, 2.0])
    return arm, gripper, HardwareSet([arm, gripper], CONTROLLER_JOINTS)


def test_set_reads_in_controller_order_once_per_component(
    interleaved: tuple[Recorder, Recorder, HardwareSet],
) -> None:
    arm, gripper, hw = interleaved
    hw.configure()
    hw.activate(0)
    state = hw.read(10)
    np.testing.assert_array_equal(state.positions, [1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(state.velocities, [10.0, 20.0, 30.0, 40.0, 50.0])
    assert state.accelerations is None
    assert [c for c in arm.calls if c[0] == "read"] == [("read", 10)]
    assert [c for c in gripper.calls if c[0] == "read"] == [("read", 10)]


def test_set_splits_writes_into_each_components_order(
    interleaved: tuple[Recorder, Recorder, HardwareSet],
) -> None:
    arm, gripper, hw = interleaved
    hw.configure()
    hw.activate(0)
    hw.write(20, JointCommand([0.1, 0.2, 0.3, NAN, 0.5], [1.0, 2.0, 3.0, 4.0, 5.0]))
    (_, t_arm, to_arm), = [c for c in arm.calls if c[0] == "write"]
    (_, t_grip, to_gripper), = [c for c in gripper.calls if c[0] == "write"]
    assert t_arm == t_grip == 20
    np.testing.assert_array_equal(to_arm.positions, [0.3, 0.1, 0.5])
    np.testing.assert_array_equal(to_arm.velocities, [3.0, 1.0, 5.0])
    np.testing.assert_array_equal(to_gripper.positions, [NAN, 0.2])
    np.testing.assert_array_equal(to_gripper.velocities, [4.0, 2.0])
    assert to_arm.accelerations is None and to_gripper.effort is None


def test_set_activate_merges_held_commands(
    interleaved: tuple[Recorder, Recorder, HardwareSet],
) -> None:
    arm, gripper, hw = interleaved
    arm.held = JointCommand([0.3, 0.1, 0.5], [3.0, 1.0, 5.0])
    gripper.held = JointCommand([NAN, 0.2])  # holds no velocity command
    hw.configure()
    held = hw.activate(0)
    np.testing.assert_array_equal(held.positions, [0.1, 0.2, 0.3, NAN, 0.5])
    np.testing.assert_array_equal(held.velocities, [1.0, NAN, 3.0, NAN, 5.0])
    assert held.accelerations is None and held.effort is None
    assert hw.state is ACT


def test_set_with_one_component_in_controller_order_passes_through() -> None:
    only = Recorder("only", ("j1", "j2"))
    hw = HardwareSet([only], ("j1", "j2"))
    hw.configure()
    hw.activate(0)
    command = JointCommand([1.0, 2.0])
    hw.write(1, command)
    assert only.calls[-1] == ("write", 1, command)
    np.testing.assert_array_equal(hw.read(2).positions, [1.0, 2.0])


def test_set_configure_failure_rolls_back_the_components_done(
    interleaved: tuple[Recorder, Recorder, HardwareSet],
) -> None:
    arm, gripper, hw = interleaved
    gripper.fail["configure"] = OSError("port busy")
    with pytest.raises(HardwareError, match="'gripper': configure failed: OSError: port busy"):
        hw.configure()
    assert arm.state is UNC and gripper.state is UNC and hw.state is UNC
    assert arm.calls == [("configure",), ("cleanup",)]


def test_set_activate_failure_rolls_back_and_notes_rollback_errors(
    interleaved: tuple[Recorder, Recorder, HardwareSet],
) -> None:
    arm, gripper, hw = interleaved
    hw.configure()
    gripper.fail["activate"] = CommunicationError("gripper silent")
    arm.fail["deactivate"] = CommunicationError("arm silent too")
    with pytest.raises(CommunicationError, match="gripper silent") as info:
        hw.activate(5)
    assert arm.state is INA and gripper.state is INA and hw.state is INA
    assert arm.calls[-1] == ("deactivate", 5, SafeAction.HOLD)
    assert info.value.__notes__ == ["rolling back 'arm' failed: arm silent too"]


def test_set_deactivate_reaches_every_component_even_if_one_fails(
    interleaved: tuple[Recorder, Recorder, HardwareSet],
) -> None:
    arm, gripper, hw = interleaved
    hw.configure()
    hw.activate(0)
    arm.fail["deactivate"] = CommunicationError("arm: no ack")
    gripper.fail["deactivate"] = CommunicationError("gripper: no ack")
    with pytest.raises(CommunicationError, match="arm: no ack") as info:
        hw.deactivate(9)
    assert info.value.__notes__ == ["also: CommunicationError: gripper: no ack"]
    assert gripper.calls[-1] == ("deactivate", 9, SafeAction.HOLD)
    assert hw.state is INA
    hw.cleanup()
    assert hw.state is UNC
    hw.shutdown(10)
    assert hw.state is FIN


def test_set_guard_touches_no_component(
    interleaved: tuple[Recorder, Recorder, HardwareSet],
) -> None:
    arm, gripper, hw = interleaved
    gripper.configure()
    with pytest.raises(ControllerStateError) as info:
        hw.configure()
    assert str(info.value) == (
        "hardware set (component 'gripper'): cannot call configure() while inactive; "
        "call cleanup() first"
    )
    assert arm.calls == []
    assert hw.state is UNC  # the least advanced
    with pytest.raises(ControllerStateError, match="cannot call activate\\(\\) while unconfigured"):
        hw.activate(0)
    with pytest.raises(ControllerStateError, match="'arm': cannot call read"):
        hw.read(0)


def test_set_status_lists_components(
    interleaved: tuple[Recorder, Recorder, HardwareSet],
) -> None:
    _, _, hw = interleaved
    status = hw.status()
    assert json.loads(json.dumps(status)) == status
    assert status["state"] == "unconfigured"
    assert status["joints"] == list(CONTROLLER_JOINTS)
    assert [c["name"] for c in status["components"]] == ["arm", "gripper"]
    assert [c.name for c in hw.components] == ["arm", "gripper"]
    assert hw.component("gripper") is hw.components[1]
    with pytest.raises(ConfigurationError) as info:
        hw.component("griper")
    assert str(info.value) == (
        "hardware: no hardware component named 'griper'; components: arm, gripper; "
        "did you mean 'gripper'?"
    )
    assert repr(hw) == "<HardwareSet unconfigured [arm, gripper]>"


@pytest.mark.parametrize(
    ("components", "message"),
    [
        ([], "a hardware set needs at least one component"),
        ([("arm", ("j1", "j2", "j3")), ("arm", ("j4", "j5"))],
         "two components are named 'arm'; names must be unique"),
        ([("arm", ("j1", "j2", "j3")), ("hand", ("j3", "j4", "j5"))],
         "joint 'j3' is provided by both 'arm' and 'hand'; each joint belongs to exactly one"),
        ([("arm", ("j1", "j2", "j33", "j4", "j5"))],
         "component 'arm' provides 'j33', which is not a controller joint "
         "(joints: j1, j2, j3, j4, j5); did you mean 'j3'?"),
        ([("arm", ("j1", "j2")), ("hand", ("j4",))],
         "controller joints 'j3', 'j5' not provided by any component (arm: [j1, j2]; "
         "hand: [j4])"),
    ],
)
def test_set_checks_the_joint_mapping(
    components: list[tuple[str, tuple[str, ...]]], message: str
) -> None:
    with pytest.raises(ConfigurationError) as info:
        HardwareSet([Recorder(name, joints) for name, joints in components], CONTROLLER_JOINTS)
    assert info.value.path == "hardware"
    assert message in str(info.value)


def test_set_requires_the_same_interfaces_everywhere() -> None:
    with pytest.raises(ConfigurationError, match="component 'hand' has interfaces command"):
        HardwareSet(
            [Recorder("arm", ("j1",)), Recorder("hand", ("j2",), ("position", "velocity"))],
            ("j1", "j2"),
        )


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------


@pytest.fixture
def module_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """ACT directory on sys.path for throw-away driver modules (removed afterwards)."""
    monkeypatch.syspath_prepend(str(tmp_path))
    before = set(sys.modules)
    yield tmp_path
    for name in set(sys.modules) - before:
        if name.startswith("jtc_hw_test_"):
            del sys.modules[name]


@pytest.fixture
def registered() -> Iterator[list[str]]:
    """Kinds registered by a test, unregistered afterwards."""
    kinds: list[str] = []
    yield kinds
    for kind in kinds:
        unregister_hardware(kind)


def spec(kind: str, path: str = "", **params: Any) -> HardwareSpec:
    return HardwareSpec("dev", kind, ("a", "b"), ("position",), ("position",), params, path)


DRIVER = """\
from typing import ClassVar
from jtc_hw.hardware import HardwareInterface
from jtc_hw.controller.joints import JointState

IMPORTED = True


class Driver(HardwareInterface):
    kind: ClassVar[str] = "third-party"

    def _read(self, now_ns):
        return JointState([0.0] * len(self.joints))

    def _write(self, now_ns, command):
        pass
"""


def test_builtin_kinds_are_lazy_import_strings() -> None:
    assert dict(BUILTIN_HARDWARE) == {
        "mirror": "jtc_hw.hardware.mirror:MirrorHardware",
        "dynamixel": "jtc_hw.drivers.dynamixel.hardware:DynamixelHardware",
        "feetech": "jtc_hw.drivers.feetech.hardware:FeetechHardware",
        "can-mit": "jtc_hw.drivers.can.mit.hardware:MitHardware",
        "can-cia402": "jtc_hw.drivers.can.cia402.hardware:Cia402Hardware",
    }
    assert {"mirror", "dynamixel", "feetech", "can-mit", "can-cia402"} <= set(
        available_hardware())
    assert hardware_class("mirror") is MirrorHardware
    hw = create_hardware(spec("mirror", lag_s=0.5))
    assert isinstance(hw, MirrorHardware) and hw.state is UNC and hw.params["lag_s"] == 0.5


def test_a_registered_string_is_imported_only_when_created(
    module_dir: Path, registered: list[str]
) -> None:
    (module_dir / "jtc_hw_test_lazy.py").write_text(DRIVER)
    register_hardware("lazy", "jtc_hw_test_lazy:Driver")
    registered.append("lazy")
    assert "lazy" in available_hardware()
    check_hardware_kind("lazy")
    assert "jtc_hw_test_lazy" not in sys.modules
    hw = create_hardware(spec("lazy"))
    assert "jtc_hw_test_lazy" in sys.modules
    assert type(hw).__name__ == "Driver" and hw.status()["kind"] == "third-party"


def test_a_registered_class_overrides_a_builtin_until_unregistered() -> None:
    register_hardware("mirror", Recorder)
    try:
        assert isinstance(create_hardware(spec("mirror")), Recorder)
    finally:
        unregister_hardware("mirror")
    assert hardware_class("mirror") is MirrorHardware


def test_entry_points_add_kinds(
    module_dir: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    (module_dir / "jtc_hw_test_plugin.py").write_text(DRIVER)
    calls: list[str] = []

    def entry_points(*, group: str) -> list[importlib.metadata.EntryPoint]:
        calls.append(group)
        return [
            importlib.metadata.EntryPoint("acme-arm", "jtc_hw_test_plugin:Driver", group),
            importlib.metadata.EntryPoint("mirror", "jtc_hw_test_plugin:Driver", group),
        ]

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    with caplog.at_level(logging.WARNING, logger="jtc_hw.hardware"):
        assert "acme-arm" in available_hardware()
    assert calls == [ENTRY_POINT_GROUP]
    assert "entry point 'mirror' (jtc_hw_test_plugin:Driver) is ignored" in caplog.text
    assert type(create_hardware(spec("acme-arm"))).__name__ == "Driver"
    assert hardware_class("mirror") is MirrorHardware


def test_unknown_kind_lists_the_available_ones() -> None:
    with pytest.raises(ConfigurationError) as info:
        create_hardware(spec("mirorr", "hardware[2]"))
    assert info.value.path == "hardware[2].kind"
    message = str(info.value)
    assert message.startswith("hardware[2].kind: unknown hardware kind 'mirorr'; available kinds: ")
    assert "can-cia402, can-mit, dynamixel" in message and "mirror" in message
    assert message.endswith("; did you mean 'mirror'?")
    with pytest.raises(ConfigurationError, match="unknown hardware kind 3"):
        check_hardware_kind(3)


MISSING_SDK = """\
import jtc_hw_no_such_sdk_xyz  # an optional dependency that is not installed

class Driver:
    pass
"""


def test_a_missing_optional_dependency_names_the_extra_to_install(
    module_dir: Path, registered: list[str]
) -> None:
    (module_dir / "jtc_hw_test_needs_sdk.py").write_text(MISSING_SDK)
    register_hardware("fancy-bus", "jtc_hw_test_needs_sdk:Driver", extra="fancy")
    registered.append("fancy-bus")
    with pytest.raises(ConfigurationError) as info:
        create_hardware(spec("fancy-bus", "hardware[0]"))
    assert str(info.value) == (
        "hardware[0].kind: hardware kind 'fancy-bus' needs the package "
        "'jtc_hw_no_such_sdk_xyz', which is not installed: pip install 'jtc_hw[fancy]'"
    )
    assert isinstance(info.value.__cause__, ModuleNotFoundError)
    register_hardware("other-bus", "jtc_hw_test_needs_sdk:Driver")
    registered.append("other-bus")
    with pytest.raises(ConfigurationError, match="install the distribution that provides the "
                       "module 'jtc_hw_no_such_sdk_xyz'"):
        hardware_class("other-bus")


@pytest.mark.parametrize(("kind", "extra"), [("dynamixel", "dynamixel"), ("can-mit", "can"),
                                             ("can-cia402", "can")])
def test_builtin_driver_kinds_name_their_extra(
    kind: str, extra: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    def import_module(name: str) -> Any:
        raise ModuleNotFoundError("No module named 'vendor_sdk'", name="vendor_sdk")

    monkeypatch.setattr("jtc_hw.hardware.registry.importlib.import_module", import_module)
    with pytest.raises(ConfigurationError, match=f"pip install 'jtc_hw\\[{extra}\\]'$"):
        hardware_class(kind)


def test_broken_registrations_are_explained(module_dir: Path, registered: list[str]) -> None:
    (module_dir / "jtc_hw_test_broken.py").write_text(
        "NotADriver = int\nraise_me = 1\n"
    )
    (module_dir / "jtc_hw_test_crash.py").write_text("raise RuntimeError('boom')\n")
    cases = {
        "gone": ("jtc_hw_test_nonexistent_module:X", "module 'jtc_hw_test_nonexistent_module' "
                 "does not exist; this installation does not provide it"),
        "no-attr": ("jtc_hw_test_broken:Missing", "module 'jtc_hw_test_broken' has no "
                    "attribute 'Missing'"),
        "not-a-driver": ("jtc_hw_test_broken:NotADriver",
                         "'jtc_hw_test_broken:NotADriver' is not a HardwareInterface subclass"),
        "crash": ("jtc_hw_test_crash:X",
                  "importing 'jtc_hw_test_crash' failed: RuntimeError: boom"),
    }
    for kind, (target, message) in cases.items():
        register_hardware(kind, target)
        registered.append(kind)
        with pytest.raises(ConfigurationError) as info:
            hardware_class(kind)
        assert message in str(info.value), kind
    with pytest.raises(ConfigurationError, match="expected 'module:Class', got 'nocolon'"):
        register_hardware("bad", "nocolon")
    with pytest.raises(TypeError, match="HardwareInterface subclass or a 'module:Class'"):
        register_hardware("bad", int)
    with pytest.raises(ConfigurationError, match="expected a non-empty kind"):
        register_hardware("", Recorder)
    with pytest.raises(KeyError):
        unregister_hardware("never-registered")


def test_create_hardware_prefixes_parameter_errors_with_the_spec_path() -> None:
    with pytest.raises(ConfigurationError) as info:
        create_hardware(spec("mirror", "hardware[1]", lag_s=-1))
    assert info.value.path == "hardware[1].params.lag_s"
    assert str(info.value) == "hardware[1].params.lag_s: must be >= 0, got -1"
    with pytest.raises(ConfigurationError) as unprefixed:
        create_hardware(spec("mirror", lag_s=-1))
    assert unprefixed.value.path == "params.lag_s"


def test_create_hardware_wraps_a_crashing_constructor(registered: list[str]) -> None:
    class Crashes(Recorder):
        kind: ClassVar[str] = "crashes"

        def __init__(self, *args: Any) -> None:
            raise RuntimeError("cannot allocate")

    register_hardware("crashes", Crashes)
    registered.append("crashes")
    with pytest.raises(HardwareError, match="crashes hardware 'dev': creating it failed: "
                       "RuntimeError: cannot allocate"):
        create_hardware(spec("crashes"))


def test_hardware_spec_freezes_its_fields() -> None:
    s = HardwareSpec(
        "x", "mirror", ["a"], ["position"], ["position"], {"l": [1, {"m": 2}]}  # type: ignore[arg-type]
    )
    assert s.joints == ("a",) and s.command_interfaces == ("position",)
    assert s.params["l"] == (1, s.params["l"][1]) and s.params["l"][1]["m"] == 2
    with pytest.raises(TypeError):
        s.params["l"] = 2  # type: ignore[index]


def test_per_joint_strings_ints_and_required_mappings() -> None:
    table = param_table(
        ParamSpec("ids", ParamKind.INT, 0, "motor id", minimum=1, per_joint=True, required=True),
        ParamSpec("model", ParamKind.STRING, "xm430", "model", choices=("xm430", "xl330"),
                  per_joint=True),
    )
    joints = ("a", "b")
    values = validate_params(table, {"ids": {"a": 1, "b": 2}, "model": {"b": "xl330"}},
                             joints=joints)
    assert (values["ids"], values["model"]) == ((1, 2), ("xm430", "xl330"))
    with pytest.raises(ConfigurationError) as info:
        validate_params(table, {"ids": {"a": 1}}, "params", joints=joints)
    assert str(info.value) == (
        "params.ids: gives no value for 'b'; this parameter is required for every joint"
    )
    with pytest.raises(ConfigurationError) as model:
        validate_params(table, {"ids": [1, 2], "model": ["xm430", "xl320"]}, "p", joints=joints)
    assert str(model.value) == (
        "p.model[1]: (joint 'b') 'xl320' is not allowed; allowed values: 'xm430', 'xl330'; "
        "did you mean 'xl330'?"
    )
    with pytest.raises(ValueError, match="'x': STRINGS cannot be per joint"):
        param_table(ParamSpec("x", ParamKind.STRINGS, (), "x", per_joint=True))


def test_integer_choices_and_the_shared_joint_mapping_rows() -> None:
    from jtc_hw.hardware import JOINT_MAPPING_PARAMS

    schema = param_table(*JOINT_MAPPING_PARAMS)
    joints = ("a", "b")
    ok = validate_params(schema, {"direction": [1, -1], "gear_ratio": 2.0}, "params",
                         joints=joints)
    assert ok["direction"] == (1, -1) and ok["gear_ratio"] == (2.0, 2.0)
    assert ok["offset"] == (0.0, 0.0)
    with pytest.raises(ConfigurationError, match=r"params\.direction\[1\]: \(joint 'b'\) "
                       r"must be 1 or -1, got 0"):
        validate_params(schema, {"direction": [1, 0]}, "params", joints=joints)
    with pytest.raises(ConfigurationError, match=r"params\.direction\.a: must be 1 or -1, got 2"):
        validate_params(schema, {"direction": {"a": 2}}, "params", joints=joints)


def test_a_foreign_error_is_wrapped_in_one_line_without_a_traceback() -> None:
    from jtc_hw.hardware import one_line

    text = "Failed to receive: reset\nTraceback (most recent call last):\n  File x\nOSError: y"
    assert one_line(OSError(text)) == "Failed to receive: reset"
    assert one_line(OSError("\n  \n")) == "OSError"
    assert one_line(ValueError("first\nsecond")) == "first"
