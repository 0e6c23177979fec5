"""Time parameters fit the controller's int64 nanoseconds (found by the protocol fuzz: a
``cmd_timeout`` of 1e308 s set at runtime crashed the control loop at the next re-arm,
``round(inf)``)."""

from __future__ import annotations

import pytest

from jtc_hw import JointState, JointTrajectoryController, load_config
from jtc_hw.config.controller import MAX_SECONDS
from jtc_hw.errors import ConfigurationError

BASE = {"joints": ["a"], "command_interfaces": ["position"], "state_interfaces": ["position"]}


@pytest.mark.parametrize("section", [{"cmd_timeout": 1e308},
                                     {"constraints": {"goal_time": 1e308}}])
def test_a_time_beyond_int64_nanoseconds_is_refused_naming_the_bound(section: dict) -> None:
    with pytest.raises(ConfigurationError, match="must be at most 9.22337e"):
        load_config({**BASE, **section})


def test_the_longest_time_allowed_still_activates() -> None:
    config = load_config({**BASE, "cmd_timeout": MAX_SECONDS,
                          "constraints": {"goal_time": MAX_SECONDS / 2}})
    ctrl = JointTrajectoryController(config)
    ctrl.activate(0, JointState([0.0], None))
    assert ctrl.active
