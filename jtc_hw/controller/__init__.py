"""The joint trajectory controller as a pure library: no I/O, no clock, no threads.

Time is a parameter (integer nanoseconds), state comes in, commands and goal events go out. The
layering contract in ``pyproject.toml`` (checked by ``lint-imports`` on every test run) keeps it
that way: nothing here imports the hardware, daemon or API layers, or a socket, thread or clock.

- :mod:`.config`: :class:`~.config.ControllerConfig` and its constants, declared, checked and
  read from files in :mod:`jtc_hw.config` (the controller reads no file);
  :mod:`.parameters`: the runtime parameters (``get_parameters`` / ``set_parameters``) and
  ``explain``.
- :mod:`.joints`: joint state and command vectors.
- :mod:`.interpolation`, :mod:`.trajectory`: splines and the immutable reference.
- :mod:`.validation`, :mod:`.tolerances`, :mod:`.pid`, :mod:`.goals`: goal checks, tolerances,
  the control law and the goal state machine.
- :mod:`.messages`: the trajectory command messages.
- :mod:`.controller`: :class:`JointTrajectoryController`, with :mod:`.speed_scaling`,
  :mod:`.stops`, :mod:`.control_law` (its mixins), :mod:`.outcomes` (what ends a command) and
  :mod:`.results` (what a cycle returns); :mod:`.planner`: the planner the daemon uses.
"""

from .controller import JointTrajectoryController
from .planner import Plan, Planner
from .results import UpdateResult

__all__ = ["JointTrajectoryController", "Plan", "Planner", "UpdateResult"]
