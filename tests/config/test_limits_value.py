"""``ControllerConfig.limits``: the value all of issue 12 reads (jtc_hw.config.limits)."""

from __future__ import annotations

import pickle

import pytest

from jtc_hw import ConfigurationError
from jtc_hw.config.limits import JointLimits
from jtc_hw.controller.config import ControllerConfig


def config(**limits: JointLimits) -> ControllerConfig:
    return ControllerConfig(
        joints=("a", "b"),
        command_interfaces=("position",),
        state_interfaces=("position",),
        limits=limits,
    )


def test_limits_are_normalised_read_only_and_survive_pickling() -> None:
    cfg = config(a=JointLimits(position=(-1, 1), velocity=2, jerk=100))
    assert cfg.limits["a"] == JointLimits((-1.0, 1.0), 2.0, None, 100.0, None)
    assert "b" not in cfg.limits  # unlimited
    assert not cfg.limits["a"].empty and JointLimits().empty
    with pytest.raises(TypeError):
        cfg.limits["b"] = JointLimits()  # type: ignore[index]
    assert pickle.loads(pickle.dumps(cfg)) == cfg


@pytest.mark.parametrize(
    ("limits", "message"),
    [
        ({"x": JointLimits(velocity=1.0)}, "limits.x: 'x' is not a configured joint"),
        ({"a": JointLimits(velocity=0.0)}, "limits.a.velocity: must be a finite number > 0"),
        ({"a": JointLimits(acceleration=float("inf"))}, "limits.a.acceleration: must be"),
        ({"a": JointLimits(position=(1.0, -1.0))}, "limits.a.position: expected finite [min"),
        ({"a": JointLimits(position=(0.0,))}, "limits.a.position: expected [min, max]"),  # type: ignore[arg-type]
    ],
)
def test_bad_limits_are_refused_with_the_path(limits: dict[str, JointLimits], message: str) -> None:
    with pytest.raises(ConfigurationError) as caught:
        config(**limits)
    assert str(caught.value).startswith(message)
