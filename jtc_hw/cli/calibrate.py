"""``jtc-hw calibrate feetech``: each joint's zero and range by hand, written to the robot file.

The procedure and its arithmetic are the driver's (``jtc_hw.drivers.feetech.calibration``,
imported by name when the command runs: the other commands do not load the drivers); this module
asks the user, finds the hardware component in the robot file, writes ``offset``, ``direction``
and ``position_limits`` into it with everything else in the file left as written
(:mod:`jtc_hw.config.editing`), checks the result as ``jtc-hw check`` would before it replaces
the file, and prints what it wrote.

The user's Enter ends each step; it is read from standard input by a thread, so that the range
step reads the servos until the line arrives. End of input counts as Enter.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import sys
import tempfile
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..config.editing import hardware_components, set_component_params
from ..config.reading import decode_text, load_yaml
from ..errors import ConfigurationError, HardwareError
from .common import EXIT_OK

__all__ = ["add_parsers", "cmd_calibrate"]

CALIBRATE_EXIT_HELP = (
    "Exit status: 0 the file was written (or, with --dry-run, would be); 2 bad options or robot "
    "file, a joint that did not move, a range the file cannot express; 3 the bus failed (a "
    "servo did not answer).")
EXIT_BUS_FAILED = 3

_MODULE = "jtc_hw.drivers.feetech.calibration"


def _per_joint(value: Any, n: int, default: Any) -> list[Any]:
    """A parameter given once or per joint, as one value per joint."""
    if value is None:
        return [default] * n
    if isinstance(value, list):
        return list(value)
    return [value] * n


def _component(text: str, path: str, name: str | None) -> tuple[Any, dict[str, Any]]:
    """The feetech component to calibrate: its node (for editing) and its parsed entry."""
    data = load_yaml(text, path)  # strict: refuses what the composer below must not see
    if not isinstance(data, dict):
        raise ConfigurationError(f"{path}: not a robot file (a mapping with a 'hardware' list)")
    nodes = hardware_components(text, path)
    entries = data.get("hardware") or []
    by_name = {e.get("name"): e for e in entries if isinstance(e, dict)}
    feetech = [(n, node) for n, kind, node in nodes if kind == "feetech"]
    if name is not None:
        feetech = [(n, node) for n, node in feetech if n == name]
    if len(feetech) != 1:
        which = f"named {name!r} " if name else ""
        listed = ", ".join(n for n, _ in feetech) or "none"
        raise ConfigurationError(
            f"{path}: expected one hardware component of kind feetech {which}(found: {listed}); "
            "name it with --component")
    return feetech[0][1], by_name[feetech[0][0]]


class _EnterReader:
    """Standard input's lines as events: :meth:`next_enter` is set by the next Enter not yet
    claimed (at once for one typed ahead, or at the end of input)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._unclaimed = 0
        self._eof = False
        self._waiting: list[threading.Event] = []
        threading.Thread(target=self._read, daemon=True, name="calibrate-stdin").start()

    def _read(self) -> None:
        for _ in iter(sys.stdin.readline, ""):
            with self._lock:
                if self._waiting:
                    self._waiting.pop(0).set()
                else:
                    self._unclaimed += 1
        with self._lock:
            self._eof = True
            for event in self._waiting:
                event.set()
            self._waiting.clear()

    def next_enter(self) -> threading.Event:
        event = threading.Event()
        with self._lock:
            if self._unclaimed:
                self._unclaimed -= 1
                event.set()
            elif self._eof:
                event.set()
            else:
                self._waiting.append(event)
        return event


def _measure(args: argparse.Namespace, cal: Any, model: Any, ids: list[int], joints: list[str],
             directions: list[int], gears: list[float]) -> dict[str, list[Any]]:
    """Steps 1-4 of the driver's procedure on the bus; the joints' values."""
    try:
        bus_module = importlib.import_module("jtc_hw.drivers.feetech.bus")
    except ImportError as exc:
        raise ConfigurationError(f"Feetech's SDK is not installed ({exc}): pip install "
                                 "'jtc_hw[feetech]' (or calibrate --from-lerobot, which needs "
                                 "no bus)") from None
    bus = bus_module.FeetechBus(args.port, args.baud_rate, model.series, timeout_ms=50.0,
                                return_delay_us=500.0)
    enter = _EnterReader()
    bus.open()
    try:
        cal.torque_off(bus, ids)
        print(f"Torque is off on servos {', '.join(map(str, ids))}: the joints turn by hand.")
        print("1/2 Put the arm in the MIDDLE of its range (every joint halfway between its "
              "ends; the pose that will be joint 0), then press Enter.", flush=True)
        enter.next_enter().wait()
        middles = cal.read_positions(bus, ids)
        if args.write_eeprom:
            written = cal.write_homing_offsets(bus, middles, model)
            print("Homing offsets stored in the servos' EEPROM (lock opened and closed again): "
                  + ", ".join(f"servo {i}: {o}" for i, o in written.items()))
            middles = cal.read_positions(bus, ids)
        print("2/2 Move EVERY joint slowly through its WHOLE range, end to end, then press "
              "Enter.", flush=True)
        ranges = cal.record_ranges(bus, middles, model, enter.next_enter())
    finally:
        bus.close()
    ordered = [ranges[i] for i in ids]
    for joint, r in zip(joints, ordered, strict=True):
        print(f"  {joint:<14} servo {r.servo_id}: middle {r.middle}, range {r.low}..{r.high}")
    return cal.joint_values(joints, ordered, model, directions, gears,
                            math.radians(args.margin_deg))


def cmd_calibrate(args: argparse.Namespace) -> int:
    path = args.robot_file
    try:
        text = decode_text(Path(path).read_bytes(), path)
    except OSError as exc:
        raise ConfigurationError(f"cannot read {path}: {exc.strerror}") from None
    node, entry = _component(text, path, args.component)
    params: dict[str, Any] = dict(entry.get("params") or {})
    all_joints: list[str] = list(entry.get("joints") or [])
    n = len(all_joints)
    file_ids = params.get("ids")
    ids = _ids(args.ids, file_ids, n, path)
    index = [file_ids.index(i) for i in ids] if isinstance(file_ids, list) else list(range(n))
    joints = [all_joints[k] for k in index]
    cal = importlib.import_module(_MODULE)
    table = importlib.import_module("jtc_hw.drivers.feetech.control_table")
    model = table.model_by_name(_per_joint(params.get("model"), n, "STS3215")[index[0]])
    file_dirs = _per_joint(params.get("direction"), n, 1)
    directions = ([int(d) for d in args.direction] if args.direction
                  else [int(file_dirs[k]) for k in index])
    if len(directions) != len(ids):
        raise ConfigurationError(f"--direction gives {len(directions)} values for {len(ids)} "
                                 "joints; give one per joint (1 or -1)")
    gears = [float(g) for g in _per_joint(params.get("gear_ratio"), n, 1.0)]
    gears = [gears[k] for k in index]
    if args.from_lerobot:
        try:
            source = Path(args.from_lerobot).read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigurationError(f"cannot read {args.from_lerobot}: {exc.strerror}") from None
        values = cal.from_lerobot(source, args.from_lerobot, joints, ids, model, gears,
                                  math.radians(args.margin_deg))
        print(f"From {args.from_lerobot} (LeRobot's calibration; the servos must still hold "
              "the homing offsets lerobot-calibrate stored in them):")
    else:
        if args.port is None:
            args.port = params.get("port")
        args.baud_rate = args.baud or int(params.get("baud_rate", 1_000_000))
        if not args.port:
            raise ConfigurationError("no --port and no params.port in the robot file")
        try:
            values = _measure(args, cal, model, ids, joints, directions, gears)
        except HardwareError as exc:
            hint = ("" if getattr(exc, "servo_id", None) is None else
                    "; check the baud rate and the ids (LeRobot's lerobot-setup-motors gives "
                    "them 1..6 at 1000000)")
            print(f"error: {exc}{hint}", file=sys.stderr)
            return EXIT_BUS_FAILED
    merged = _merge(params, values, index, n)
    new_text = set_component_params(text, path, node, merged)
    _check(new_text, path)
    print(f"{'Would write' if args.dry_run else 'Wrote'} to {path}, hardware component "
          f"{entry.get('name')!r}:")
    for line in cal.describe(values, joints):
        print(line)
    if not args.dry_run:
        _replace(path, new_text)
    return EXIT_OK


def _ids(given: str | None, file_ids: Any, n: int, path: str) -> list[int]:
    """The servo ids to calibrate: ``--ids`` (among the file's ids), else the file's."""
    if given is None:
        if not isinstance(file_ids, list):
            raise ConfigurationError(f"{path}: no params.ids; give --ids (e.g. 1-6)")
        return list(file_ids)
    parse_ids = importlib.import_module("jtc_hw.drivers.emulation_cli").parse_ids
    try:
        ids = parse_ids(given, range(253))
    except ValueError as exc:
        raise ConfigurationError(f"--ids: {exc}") from None
    if isinstance(file_ids, list):
        stray = [i for i in ids if i not in file_ids]
        if stray:
            raise ConfigurationError(
                f"--ids {given}: servo(s) {stray} are not in {path}'s ids {file_ids}; put them "
                "there first (one id per joint)")
    elif len(ids) != n:
        raise ConfigurationError(f"--ids {given} gives {len(ids)} servos for {n} joints")
    return ids


def _merge(params: Mapping[str, Any], values: Mapping[str, Sequence[Any]], index: list[int],
           n: int) -> dict[str, list[Any]]:
    """The calibrated joints' values over the file's (joints not calibrated keep theirs)."""
    defaults = {"offset": 0.0, "direction": 1, "position_limits": None}
    merged = {}
    for key, default in defaults.items():
        current = params.get(key)
        if key == "position_limits" and current is not None and (
                not current or not isinstance(current[0], list | type(None))):
            current = [current] * n  # one [min, max] for every joint
        full = _per_joint(current, n, default)
        for j, k in enumerate(index):
            value = values[key][j]
            full[k] = [round(v, 4) for v in value] if key == "position_limits" else (
                round(value, 6) if key == "offset" else value)
        merged[key] = full
    return merged


def _check(text: str, path: str) -> None:
    """Refuse to write a file ``jtc-hw check`` would refuse (a temporary copy beside it)."""
    from ..daemon.robot import create_hardware_set, load_robot  # start-up time

    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".calibrate-", suffix=".yaml", dir=directory)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        try:
            create_hardware_set(load_robot(tmp))
        except ConfigurationError as exc:
            raise ConfigurationError(f"{path} as calibrated would not load, so it was left as "
                                     f"it was: {exc}") from None
    finally:
        os.unlink(tmp)


def _replace(path: str, text: str) -> None:
    """Write ``text`` to ``path`` atomically (a reader sees the old file or the new one)."""
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".calibrate-", suffix=".yaml", dir=directory)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    mode = os.stat(path).st_mode & 0o7777
    os.chmod(tmp, mode)
    os.replace(tmp, path)


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "calibrate",
        help="record each joint's zero and range by hand (Feetech servos, LeRobot's SO-101), "
        "into the robot file",
        description=(
            "Calibrate a feetech hardware component of ROBOT_FILE as LeRobot's lerobot-calibrate "
            "does: the servos' torque goes off; you put the arm in the middle of its range "
            "(Enter: that pose is joint 0), then move every joint through its whole range "
            "(Enter). The component's offset, direction and position_limits are written into "
            "ROBOT_FILE, the rest of it left as written, and printed. Nothing is stored in the "
            "servos unless --write-eeprom. With --from-lerobot, LeRobot's calibration JSON is "
            "imported instead, without a bus. Example: 'jtc-hw calibrate feetech "
            "config/so101-follower.yaml --port /dev/ttyACM0 --ids 1-6'."
        ),
        epilog=CALIBRATE_EXIT_HELP,
    )
    p.add_argument("kind", choices=["feetech"], help="the hardware kind to calibrate")
    p.add_argument("robot_file", help="the robot YAML to update (e.g. a copy of "
                   "config/so101-follower.yaml)")
    p.add_argument("--port", help="the bus's serial device (default: the component's port)")
    p.add_argument("--baud", type=int, default=None,
                   help="bit/s (default: the component's baud_rate, else 1000000)")
    p.add_argument("--ids", help="servo ids to calibrate, e.g. 1-6 or 1,3 (default: the "
                   "component's ids; others keep their values)")
    p.add_argument("--component", help="the hardware component's name, if the file has "
                   "several of kind feetech")
    p.add_argument("--direction", nargs="+", choices=["1", "-1"], metavar="{1,-1}",
                   help="per joint direction (default: the file's); it cannot be seen by hand: "
                   "check each joint's sign with 'jtc-hw state' afterwards")
    p.add_argument("--margin-deg", type=float, default=2.0,
                   help="inset of each position limit from the end reached by hand, degrees "
                   "(default 2: a goal at a limit does not push against the stop)")
    p.add_argument("--write-eeprom", action="store_true",
                   help="also store each servo's Homing Offset in its EEPROM (through the EPROM "
                   "lock, closed again after), so that the middle pose reads the middle step; "
                   "needed when a joint's range crosses the servo's 4095/0 wrap")
    p.add_argument("--from-lerobot", metavar="FILE",
                   help="import LeRobot's calibration JSON (so101_follower form, e.g. "
                   "~/.cache/huggingface/lerobot/calibration/robots/so101_follower/ID.json); "
                   "no bus needed")
    p.add_argument("--dry-run", action="store_true", help="print what would be written only")
    p.set_defaults(func=cmd_calibrate)
