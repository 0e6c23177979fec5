"""Goal files in ROS 2's own shapes, turned into the protocol's goal form.

Two shapes come straight out of a ROS 2 workspace and are accepted as they are:

* what ``ros2 topic echo`` prints for a ``trajectory_msgs/msg/JointTrajectory``: a ``header``,
  ``joint_names``, ``points`` whose ``time_from_start`` is a ``builtin_interfaces/Duration``
  (``{sec, nanosec}``) and whose unused fields are empty lists, ended by a ``---`` line;
* a ``control_msgs/action/FollowJointTrajectory`` goal (what ``ros2 action send_goal`` takes):
  ``trajectory`` (as above), ``path_tolerance`` / ``goal_tolerance`` (lists of
  ``JointTolerance``), ``goal_time_tolerance`` as a ``Duration``, and the multi-DOF fields
  upstream's controller ignores (accepted only when empty, as it refuses nothing there but we
  would silently drop them otherwise).

The protocol's own form (seconds as numbers, no header) passes through unchanged, so one
function serves every YAML/JSON goal file. The header's stamp is dropped: a saved trajectory
starts when it is sent (``jtc-hw send --start-in S`` delays it), as upstream does for a zero
stamp; a file's stamp from the past would otherwise make every point late.
"""

from __future__ import annotations

from typing import Any

from ..errors import ConfigurationError

__all__ = ["ros_goal", "split_documents"]

_NS_PER_S = 1_000_000_000
_POINT_VECTORS = ("positions", "velocities", "accelerations", "effort")
# FollowJointTrajectory goal fields with no counterpart here (multi-DOF, component-wise).
_UNSUPPORTED_GOAL_FIELDS = (
    "multi_dof_trajectory",
    "component_path_tolerance",
    "component_goal_tolerance",
)


def split_documents(text: str, path: str) -> str:
    """The text of the one non-empty YAML document in ``text``, the content of the file
    ``path`` (named in errors), as ``ros2 topic echo --once`` prints it (``---`` separators).

    Raises:
        ConfigurationError: several non-empty documents (several messages were echoed).
    """
    documents: list[list[str]] = [[]]
    for line in text.splitlines():
        if line.strip() == "---":
            documents.append([])
        else:
            documents[-1].append(line)
    filled = [d for d in documents if any(ln.strip() and not ln.lstrip().startswith("#")
                                          for ln in d)]
    if len(filled) > 1:
        raise ConfigurationError(
            f"the file holds {len(filled)} YAML documents (messages separated by '---'); keep "
            "one trajectory (ros2 topic echo --once prints one)",
            path,
        )
    return "\n".join(filled[0]) if filled else ""


def _duration(value: Any, where: str, path: str) -> Any:
    """``{sec, nanosec}`` (builtin_interfaces/Duration) as seconds; anything else unchanged
    (numbers, or a mistake for the protocol's parser to name)."""
    if not isinstance(value, dict) or not ({"sec", "nanosec"} & set(value)):
        return value
    unknown = sorted(set(value) - {"sec", "nanosec"})
    if unknown:
        raise ConfigurationError(
            f"{where}: unknown Duration field '{unknown[0]}' (expected sec and nanosec)", path
        )
    sec, nanosec = value.get("sec", 0), value.get("nanosec", 0)
    for name, number in (("sec", sec), ("nanosec", nanosec)):
        if not isinstance(number, int) or isinstance(number, bool):
            raise ConfigurationError(
                f"{where}.{name}: expected an integer, got {number!r}", path
            )
    if not 0 <= nanosec < _NS_PER_S:
        raise ConfigurationError(
            f"{where}.nanosec: {nanosec} is out of range; expected 0 to 999999999 (a "
            "Duration's nanoseconds; whole seconds go in sec)",
            path,
        )
    total_ns = sec * _NS_PER_S + nanosec
    # An integer number of seconds stays an int: the protocol reads ints exactly.
    return total_ns // _NS_PER_S if total_ns % _NS_PER_S == 0 else total_ns / _NS_PER_S


def _trajectory(data: Any, where: str, path: str) -> Any:
    if not isinstance(data, dict):
        return data  # the protocol's parser names what is wrong
    out = {k: v for k, v in data.items() if k != "header"}
    points = out.get("points")
    if isinstance(points, list):
        fixed = []
        for i, point in enumerate(points):
            if isinstance(point, dict):
                point = {
                    k: v for k, v in point.items() if not (k in _POINT_VECTORS and v == [])
                }
                if "time_from_start" in point:
                    point["time_from_start"] = _duration(
                        point["time_from_start"], f"{where}points[{i}].time_from_start", path
                    )
            fixed.append(point)
        out["points"] = fixed
    return out


def ros_goal(data: dict[str, Any], path: str) -> dict[str, Any]:
    """A goal file's decoded mapping (a trajectory, or a goal wrapping one) in the protocol's
    form, ``{"trajectory": ..., "path_tolerance": ..., ...}`` with durations in seconds, the
    header and empty per-point lists removed; ``path``, the file, is named in errors.

    Raises:
        ConfigurationError: a Duration that is not ``{sec, nanosec}`` integers, or a non-empty
            multi-DOF / component-wise field (not supported: its motion would be lost).
    """
    if "trajectory" not in data:
        return {"trajectory": _trajectory(data, "", path)}
    for field in _UNSUPPORTED_GOAL_FIELDS:
        value = data.get(field)
        if value in (None, [], {}) or (
            isinstance(value, dict) and not value.get("points") and not value.get("joint_names")
        ):
            continue
        raise ConfigurationError(
            f"{field}: not supported (jtc_hw drives joints, as upstream's "
            "joint_trajectory_controller, which ignores it); leave it empty or remove it",
            path,
        )
    goal = {k: v for k, v in data.items() if k not in _UNSUPPORTED_GOAL_FIELDS}
    goal["trajectory"] = _trajectory(data["trajectory"], "trajectory.", path)
    if "goal_time_tolerance" in goal:
        goal["goal_time_tolerance"] = _duration(
            goal["goal_time_tolerance"], "goal_time_tolerance", path
        )
    return goal
