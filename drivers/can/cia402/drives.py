"""What the CiA 402 driver knows of each drive and each bus: its configuration, its COB-IDs and
its newest feedback (filled by the cycle in :mod:`~jtc_hw.drivers.can.cia402.hardware`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import can
import canopen

from .. import bus as canbus
from . import codec as c4

__all__ = ["SDO_REQUEST", "SDO_RESPONSE", "Drive", "DriveBus"]

SDO_REQUEST = 0x600
"""COB-ID base of SDO requests (client -> drive): 0x600 + node id."""
SDO_RESPONSE = 0x580
"""COB-ID base of SDO answers (drive -> client): 0x580 + node id."""


@dataclass
class Drive:
    """One drive: its configuration and its newest feedback."""

    joint: str
    index: int
    node_id: int
    bus: str
    scale: c4.JointScale
    lower: float
    upper: float
    vmax: float
    tpdo1: int = 0
    tpdo2: int = 0
    rpdo1: int = 0
    emcy: int = 0
    statusword: int | None = None
    state: c4.State | None = None
    position_counts: int = 0
    torque_permille: int = 0
    velocity_value: int = 0
    error_code: int = 0
    mode_display: int = 0
    rx1_at: float = 0.0
    rx2_at: float = 0.0
    fresh: bool = False
    late: int = 0
    missed: int = 0
    last_emcy: int | None = None
    heartbeat_lost: bool = False
    consumer_sub: int = 0
    controlword: int = 0
    target: int = 0
    error_register: int | None = None  # 0x1001, read by SDO at a low rate (health)
    sdo_tx: int = 0
    sdo_rx: int = 0

    def __post_init__(self) -> None:
        self.tpdo1 = c4.tpdo_cob_id(1, self.node_id)
        self.tpdo2 = c4.tpdo_cob_id(2, self.node_id)
        self.rpdo1 = c4.rpdo_cob_id(1, self.node_id)
        self.emcy = c4.emcy_cob_id(self.node_id)
        self.sdo_tx = SDO_REQUEST + self.node_id
        self.sdo_rx = SDO_RESPONSE + self.node_id

    def who(self) -> str:
        return f"drive node {self.node_id} (joint {self.joint!r}, bus {self.bus!r})"

    def describe_state(self) -> str:
        if self.statusword is None or self.state is None:
            return "no statusword yet"
        return f"{self.state.value} (statusword 0x{self.statusword:04X})"


@dataclass
class DriveBus:
    """One CAN bus and the drives on it."""

    settings: canbus.BusSettings
    drives: list[Drive]
    health: canbus.BusHealth
    bus: can.BusABC | None = None
    keys: dict[int, tuple[Drive, int]] = field(default_factory=dict)
    sync_outstanding: bool = False
    syncs: int = 0
    opened_at: float = 0.0
    network: canopen.Network | None = None
    nodes: dict[int, canopen.RemoteNode] = field(default_factory=dict)
    next_beat: float = 0.0
    beats: int = 0
    on_frame: Any = None  # (COB-ID, frame) -> None: decodes a frame as it is received

    def __post_init__(self) -> None:
        for d in self.drives:
            self.keys[d.tpdo1] = (d, 1)
            self.keys[d.tpdo2] = (d, 2)
            self.keys[d.emcy] = (d, 0)
            self.keys[d.sdo_rx] = (d, 3)

    def key(self, msg: can.Message) -> int | None:
        cob = int(msg.arbitration_id)
        return cob if cob in self.keys else None
