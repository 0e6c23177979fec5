"""Every cycle's state, from the loop process to the API process, through shared memory.

Theory of operation
-------------------
The flight recorder wants each cycle of the seconds before an abort, not only the states
published at ``state_publish_rate``. Pickling a message per cycle through the loop's outbox would
cost the loop a few tens of microseconds and a system call per cycle; instead the loop writes one
fixed-size row of float64 per cycle into a single-producer/single-consumer ring in
``multiprocessing.shared_memory``, a numpy view over it:

- **Layout** (:class:`CycleLayout`): a header of ``HEADER_SLOTS`` int64 (magic, version,
  capacity, row width, joints, the write count), then ``capacity`` rows. A row holds the scalar
  columns of ``SCALARS`` (its sequence number and the cycle's deadline as int64 bit patterns,
  the rest float64) and one block of ``joints`` values per name of ``BLOCKS``. A missing value
  (an interface that is not configured, no active goal) is NaN.
- **Writer** (the loop process, :meth:`CycleRing.write`): fills row ``count % capacity`` in
  place, then its sequence number, then publishes ``count + 1`` in the header. No lock, no
  system call, no allocation: a few numpy slice assignments (``bench/ring_write.py`` measures
  them).
- **Reader** (the API process, :meth:`CycleRing.read`, every ``READ_PERIOD_S``): copies the rows
  between what it has and the published count, then checks each copied row's sequence number
  and the count again: a row the writer overwrote meanwhile (the reader fell more than
  ``capacity`` rows behind) is dropped and counted as overrun, never taken for a newer cycle.
  The ring holds ``RING_S`` seconds, many reader periods.
- **States** (decisions 49): after the rows, ``STATE_SLOTS`` state slots. At each
  ``state_publish_rate`` cycle the loop adds one (:meth:`CycleRing.write_state`: its row's
  number and what a ``State`` holds that the row does not: error, command, which arrays are
  None, speed scaling target, trajectory time), marking it -1 while writing it and publishing
  the count of states in the header. The API process (:meth:`CycleRing.read_states`) copies a
  slot and its row and trusts them only if neither was rewritten meanwhile; the pair becomes
  the very ``State`` the loop used to pickle into its pipe. The error and command are in the
  slots only: the rows of other cycles do not carry them.
- **Ownership**: the API process creates the segment (``jtc_hw_<pid>_<random>`` in
  ``/dev/shm``) before it starts the loop process, which attaches by name; the API process
  unlinks it when the loop has ended (the daemon's stop, SIGTERM included). If the API process
  dies without that, multiprocessing's resource tracker unlinks it; if the tracker dies too
  (SIGKILL of the whole process group), the next daemon to start removes every
  ``jtc_hw_<pid>_*`` segment whose process no longer exists (:func:`remove_stale`).

Ordering: the reader trusts a row once the count and its sequence number say it is complete.
On x86-64 stores become visible in program order; on weaker memory models (aarch64) a reader
could in theory see the count before a row's values, which the sequence check does not fully
exclude; the interpreter's work between the stores makes it unlikely, and a torn row could only
affect one sample of a recording, never control.
"""

from __future__ import annotations

import contextlib
import math
import os
import secrets
from dataclasses import dataclass
from multiprocessing import shared_memory
from typing import Any

import numpy as np

from ...controller.joints import JointCommand
from ...errors import JtcHwError
from .messages import State

MAGIC = 0x4A54435249  # "JTCRI"
VERSION = 2
HEADER_SLOTS = 8
_H_MAGIC, _H_VERSION, _H_CAPACITY, _H_WIDTH, _H_JOINTS, _H_COUNT, _H_STATES = range(7)

STATE_SLOTS = 16
"""States the ring holds (0.3 s at 50 Hz): the API process reads them about once each."""

RING_S = 2.0
"""Seconds of cycles the shared ring holds: 20 reader periods, so a reader delayed by a busy
API process (a large plan being fitted) still catches up without losing rows."""
READ_PERIOD_S = 0.1
"""How often the API process copies the new rows out of the ring."""

SCALARS = (
    "seq",  # int64 bits: the row's sequence number (the write count when it was written)
    "time_ns",  # int64 bits: the cycle's deadline (daemon clock)
    "active_goal",  # the active goal's id, NaN: none
    "holding",  # 1.0 while holding position, else 0.0
    "faulted",  # 1.0 while the loop is faulted (the controller stopped), else 0.0
    "speed_scaling",  # the speed scaling factor in force
    "reference_time_from_start",  # s
    "feedback_time_from_start",  # s
)
BLOCKS = (
    "measured_positions", "measured_velocities", "measured_accelerations",
    "reference_positions", "reference_velocities", "reference_accelerations",
    "reference_effort",
    "output_positions", "output_velocities", "output_accelerations", "output_effort",
)


_STATE_SCALARS = (
    "seq",  # int64 bits: the state's number (-1 while it is being written)
    "row",  # int64 bits: the sequence number of its cycle's row
    "present",  # int64 bits: which of the State's optional arrays it has (_PRESENT)
    "speed_scaling_target",
    "trajectory_time_ns",  # int64 bits
)
_PRESENT = ("measured_velocities", "measured_accelerations",
            "command_positions", "command_velocities", "command_accelerations", "command_effort",
            "output_positions", "output_velocities", "output_accelerations", "output_effort")
"""Bit ``k`` of a state's ``present``: its ``_PRESENT[k]`` is an array (else None)."""


SHM_DIR = "/dev/shm"
"""Where POSIX shared memory segments appear on Linux (for :func:`remove_stale`)."""


def remove_stale(directory: str | None = None) -> list[str]:
    """Remove the cycle rings left by daemons that no longer run (killed with their resource
    tracker) from ``directory`` (default :data:`SHM_DIR`, read at the call); the names removed.
    Never raises: a directory that cannot be listed (not Linux) or a segment that cannot be
    removed (another user's) is left alone."""
    if directory is None:
        directory = SHM_DIR
    try:
        names = os.listdir(directory)
    except OSError:
        return []
    removed = []
    for name in names:
        parts = name.split("_")
        if len(parts) != 4 or parts[:2] != ["jtc", "hw"] or not parts[2].isdigit():
            continue
        pid = int(parts[2])
        try:
            os.kill(pid, 0)
            continue  # its daemon runs (or the pid was reused: then it stays, harmlessly)
        except ProcessLookupError:
            pass
        except PermissionError:
            continue  # another user's process
        try:
            os.unlink(os.path.join(directory, name))
        except OSError:
            continue
        removed.append(name)
    return removed


@dataclass(frozen=True)
class CycleLayout:
    """Where each value sits in a row, for ``joints`` joints."""

    joints: int

    @property
    def width(self) -> int:
        """float64 values per row."""
        return len(SCALARS) + len(BLOCKS) * self.joints

    def column(self, name: str) -> int:
        """The column of a scalar of ``SCALARS``."""
        return SCALARS.index(name)

    def block(self, name: str) -> slice:
        """The columns of a per-joint block of ``BLOCKS``."""
        start = len(SCALARS) + BLOCKS.index(name) * self.joints
        return slice(start, start + self.joints)

    def times(self, rows: Any) -> Any:
        """The deadlines (int64) of ``rows`` (an array of rows)."""
        return rows[:, self.column("time_ns")].view(np.int64)

    @property
    def state_width(self) -> int:
        """float64 values per state slot: ``_STATE_SCALARS``, error ``(3, n)``, command
        ``(4, n)``."""
        return len(_STATE_SCALARS) + 7 * self.joints


class CycleRing:
    """The shared ring (see the module docstring); make it with :meth:`create` or
    :meth:`attach`."""

    def __init__(self, shm: shared_memory.SharedMemory, owner: bool) -> None:
        self._shm = shm
        self.owner = owner
        header = np.ndarray((HEADER_SLOTS,), dtype=np.int64, buffer=shm.buf)
        if int(header[_H_MAGIC]) != MAGIC or int(header[_H_VERSION]) != VERSION:
            raise JtcHwError(f"shared memory {shm.name} is not a jtc_hw cycle ring")
        self.capacity = int(header[_H_CAPACITY])
        self.layout = CycleLayout(int(header[_H_JOINTS]))
        width = int(header[_H_WIDTH])
        self._header = header
        self._rows = np.ndarray((self.capacity, width), dtype=np.float64, buffer=shm.buf,
                                offset=HEADER_SLOTS * 8)
        self._ints = self._rows.view(np.int64)  # the same memory: seq and time_ns columns
        self._states = np.ndarray((STATE_SLOTS, self.layout.state_width), dtype=np.float64,
                                  buffer=shm.buf, offset=(HEADER_SLOTS + self.capacity * width) * 8)
        self._state_ints = self._states.view(np.int64)
        n = self.layout.joints
        self._s_error = slice(len(_STATE_SCALARS), len(_STATE_SCALARS) + 3 * n)
        self._s_command = tuple(slice(self._s_error.stop + k * n, self._s_error.stop + (k + 1) * n)
                                for k in range(4))
        self._state_count = int(header[_H_STATES])
        layout = self.layout
        self._c_seq, self._c_time = layout.column("seq"), layout.column("time_ns")
        self._c_goal, self._c_hold = layout.column("active_goal"), layout.column("holding")
        self._c_fault = layout.column("faulted")
        self._c_scale = layout.column("speed_scaling")
        self._c_rtfs = layout.column("reference_time_from_start")
        self._c_ftfs = layout.column("feedback_time_from_start")
        # Per block, its columns: writing a row's block is one slice assignment.
        (self._s_mpos, self._s_mvel, self._s_macc, self._s_rpos, self._s_rvel, self._s_racc,
         self._s_reff, self._s_opos, self._s_ovel, self._s_oacc, self._s_oeff) = (
            layout.block(name) for name in BLOCKS)
        self._s_reference = slice(self._s_rpos.start, self._s_reff.stop)
        self._count = int(header[_H_COUNT])

    @property
    def name(self) -> str:
        """The segment's name (``/dev/shm/<name>`` on Linux)."""
        return str(self._shm.name)

    @classmethod
    def create(cls, joints: int, capacity: int) -> CycleRing:
        """A new ring for ``joints`` joints and ``capacity`` rows (the API process owns it).

        Raises:
            OSError: the segment cannot be created (``/dev/shm`` full or missing).
        """
        layout = CycleLayout(joints)
        size = (HEADER_SLOTS + capacity * layout.width + STATE_SLOTS * layout.state_width) * 8
        name = f"jtc_hw_{os.getpid()}_{secrets.token_hex(4)}"
        shm = shared_memory.SharedMemory(name=name, create=True, size=size)
        header = np.ndarray((HEADER_SLOTS,), dtype=np.int64, buffer=shm.buf)
        header[:] = 0
        header[_H_CAPACITY], header[_H_WIDTH], header[_H_JOINTS] = capacity, layout.width, joints
        header[_H_VERSION] = VERSION
        header[_H_MAGIC] = MAGIC  # last: an attach before this sees no ring
        del header
        return cls(shm, owner=True)

    @classmethod
    def attach(cls, name: str) -> CycleRing:
        """The ring the API process made (the loop process writes into it).

        Raises:
            JtcHwError: no such segment, or not a cycle ring.
        """
        try:
            shm = shared_memory.SharedMemory(name=name)
        except OSError as exc:
            raise JtcHwError(f"cannot attach the cycle ring {name}: {exc}") from exc
        return cls(shm, owner=False)

    # -- writer (the loop process) ------------------------------------------------------------

    def write(self, time_ns: int, active_goal: int | None, holding: bool, faulted: bool,
              speed_scaling: float, reference_time_from_start: float,
              feedback_time_from_start: float, measured: Any, reference: Any,
              output: Any) -> None:
        """Write one cycle's row and publish it.

        Args:
            measured: a ``JointState`` (``positions``, ``velocities``, ``accelerations``).
            reference: a ``TrajectorySample`` or None (not controlling: NaN).
            output: a ``JointCommand`` or None (NaN).

        Raises:
            ValueError: an array does not have one value per joint (a programming error).
        """
        # One row view, then a slice assignment per block: no tuple, dict or getattr per cycle.
        count = self._count
        i = count % self.capacity
        row = self._rows[i]
        nan = np.nan
        row[self._c_goal] = nan if active_goal is None else active_goal
        row[self._c_hold] = 1.0 if holding else 0.0
        row[self._c_fault] = 1.0 if faulted else 0.0
        row[self._c_scale] = speed_scaling
        row[self._c_rtfs] = reference_time_from_start
        row[self._c_ftfs] = feedback_time_from_start
        self._ints[i, self._c_time] = time_ns
        row[self._s_mpos] = measured.positions
        value = measured.velocities
        row[self._s_mvel] = nan if value is None else value
        value = measured.accelerations
        row[self._s_macc] = nan if value is None else value
        if reference is None:
            row[self._s_reference] = nan
        else:
            row[self._s_rpos] = reference.positions
            row[self._s_rvel] = reference.velocities
            row[self._s_racc] = reference.accelerations
            row[self._s_reff] = reference.effort
        if output is None:
            row[self._s_opos.start:self._s_oeff.stop] = nan
        else:
            value = output.positions
            row[self._s_opos] = nan if value is None else value
            value = output.velocities
            row[self._s_ovel] = nan if value is None else value
            value = output.accelerations
            row[self._s_oacc] = nan if value is None else value
            value = output.effort
            row[self._s_oeff] = nan if value is None else value
        self._ints[i, self._c_seq] = count  # the row is complete
        self._count = count + 1
        self._header[_H_COUNT] = count + 1  # published

    def write_state(self, error: Any, command: Any, output: Any, measured: Any,
                    speed_scaling_target: float, trajectory_time_ns: int) -> None:
        """Make the row just written a State the API process publishes (at
        ``state_publish_rate``): what its row does not hold, in a state slot.

        Args:
            error: ``(3, n)``; command, output: ``JointCommand``; measured: ``JointState``
                (only which of their arrays are None is taken from ``output`` and
                ``measured``: their values are in the row).
        """
        count = self._state_count
        i = count % STATE_SLOTS
        slot, ints = self._states[i], self._state_ints[i]
        ints[0] = -1  # being written: a reader copying it now drops it
        present = 0
        for bit, value in enumerate((
                measured.velocities, measured.accelerations, command.positions,
                command.velocities, command.accelerations, command.effort, output.positions,
                output.velocities, output.accelerations, output.effort)):
            if value is not None:
                present |= 1 << bit
        ints[1] = self._count - 1
        ints[2] = present
        slot[3] = speed_scaling_target
        ints[4] = trajectory_time_ns
        slot[self._s_error] = error.ravel()
        for where, value in zip(self._s_command, (command.positions, command.velocities,
                                                  command.accelerations, command.effort),
                                strict=True):
            if value is not None:
                slot[where] = value
        ints[0] = count  # complete
        self._state_count = count + 1
        self._header[_H_STATES] = count + 1  # published

    # -- reader (the API process) -------------------------------------------------------------

    def read_states(self, since: int) -> tuple[list[Any], int, int]:
        """The States written from number ``since`` on: ``(states, next_since, lost)``, each
        a :class:`~.messages.State` (its arrays copies), in order, and how many since
        ``since`` were overwritten (with their rows) before they could be copied."""
        end = int(self._header[_H_STATES])
        start = max(since, end - STATE_SLOTS)
        lost = start - since if end > since else 0
        states = []
        for number in range(start, end):
            i = number % STATE_SLOTS
            slot = self._states[i].copy()
            seq = int(slot.view(np.int64)[0])
            row_seq = int(slot.view(np.int64)[1])
            row = self._rows[row_seq % self.capacity].copy()
            # Each copy is trusted only if what was copied was not being rewritten meanwhile.
            if (seq != number or int(self._state_ints[i, 0]) != number
                    or int(row.view(np.int64)[self._c_seq]) != row_seq
                    or row_seq <= int(self._header[_H_COUNT]) - self.capacity):
                lost += 1
                continue
            states.append(_state_from_ring(self.layout, row, slot, self._s_error,
                                           self._s_command))
        return states, max(since, end), lost


    def read(self, since: int) -> tuple[Any, int, int]:
        """The rows written from sequence number ``since`` on, as a copy: ``(rows, next_since,
        lost)``, the complete rows in order (an array of shape ``(n, width)``), the sequence
        number to read from next, and how many rows since ``since`` were overwritten before
        they could be copied (the reader fell behind)."""
        end = int(self._header[_H_COUNT])
        start = max(since, end - self.capacity)
        if end <= start:
            return self._rows[:0].copy(), max(since, end), start - since if end > since else 0
        first, last = start % self.capacity, (end - 1) % self.capacity
        if first <= last:
            rows = self._rows[first:last + 1].copy()
        else:
            rows = np.concatenate((self._rows[first:], self._rows[:last + 1]))
        # Rows the writer may have reused while they were copied are not trusted, nor any row
        # whose sequence number is not the one expected at its place.
        after = int(self._header[_H_COUNT])
        expected = np.arange(start, end, dtype=np.int64)
        good = (rows.view(np.int64)[:, self._c_seq] == expected) & (
            expected >= after - self.capacity)
        if not good.all():
            rows = rows[good]
        lost = (start - since) + int((~good).sum())
        return rows, end, lost

    # -- ownership ----------------------------------------------------------------------------

    def close(self) -> None:
        """Release this process's mapping; the owner also removes the segment."""
        self._header = self._rows = self._ints = None
        self._shm.close()
        if self.owner:
            with contextlib.suppress(FileNotFoundError):
                self._shm.unlink()


def _state_from_ring(layout: CycleLayout, row: Any, slot: Any, error: slice,
                     command: tuple[slice, ...]) -> State:
    """The :class:`~.messages.State` a row and its state slot (copies) hold: the record the
    loop would have sent, value for value."""
    present = int(slot.view(np.int64)[2])
    n = layout.joints

    def block(name: str) -> Any:
        return row[layout.block(name)]

    def given(bit: int, values: Any) -> Any:
        return values if present >> bit & 1 else None

    goal = float(row[layout.column("active_goal")])
    first = layout.block("reference_positions").start
    return State(
        int(layout.times(row[None, :])[0]),
        row[first:first + 4 * n].reshape(4, n),
        block("measured_positions"),
        given(0, block("measured_velocities")),
        slot[error].reshape(3, n),
        JointCommand(*(given(2 + k, slot[where]) for k, where in enumerate(command))),
        bool(row[layout.column("holding")]),
        None if math.isnan(goal) else int(goal),
        float(row[layout.column("reference_time_from_start")]),
        float(row[layout.column("feedback_time_from_start")]),
        given(1, block("measured_accelerations")),
        JointCommand(*(given(6 + k, block(f"output_{field}")) for k, field in enumerate(
            ("positions", "velocities", "accelerations", "effort")))),
        float(row[layout.column("speed_scaling")]),
        float(slot[3]),
        int(slot.view(np.int64)[4]),
    )
