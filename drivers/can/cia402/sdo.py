"""What the CiA 402 driver does through canopen's blocking SDO client: setting the drives up.

``configure`` (:meth:`DriveSetup.configure_bus`) uses the ``canopen`` library while a
python-can ``Notifier`` thread feeds it: per drive an NMT *reset communication* and the wait
for its boot-up message (proof that it is there, and PDO parameters back to their defaults),
an SDO check of the device type (profile 402), the PDO mapping written with canopen's PDO API (RPDO1
controlword + target position / velocity, TPDO1 statusword + position actual + torque actual,
TPDO2 velocity actual + error code + modes of operation display, all of transmission type 1:
synchronous), the mode of operation (0x6060 = 8 CSP or 9 CSV, checked in 0x6061: a refused
mode switch is an error), the abort connection option code (0x6007, ``watchdog_reaction``)
and a heartbeat consumer entry (0x1016) claimed for the daemon's node id, then NMT *start*.
The consumer entry is written with time 0 (claimed, not watching yet); activate arms it and
deactivate disarms it with :meth:`DriveSetup.write_consumer`. In cyclic operation the driver
owns the bus receive and none of this runs.
"""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass
from typing import Any

import can
import canopen
from canopen.network import MessageListener
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from jtc_hw.errors import CommunicationError, HardwareError
from jtc_hw.hardware import one_line

from .. import bus as canbus
from . import codec as c4
from .drives import Drive, DriveBus

__all__ = ["DriveSetup", "map_pdo"]

_PROFILE_402 = 402
_NOTIFIER_CYCLE_S = 0.02


@dataclass(frozen=True)
class DriveSetup:
    """What ``configure`` writes into every drive, and the words its errors are told in.

    Attributes:
        owner: the hardware's name in messages (``can-cia402 hardware 'arm'``).
        eds: the drives' EDS file.
        mode: the mode of operation (CSP or CSV).
        rpdo_layout: RPDO1's mapping for that mode.
        reaction: the abort connection option code (0x6007).
        master_id: the daemon's node id, whose heartbeat the consumer entry watches.
        boot_timeout_s: how long a drive may take to boot up after a reset communication.
    """

    owner: str
    eds: str
    mode: c4.Mode
    rpdo_layout: c4.PdoLayout
    reaction: c4.AbortConnection
    master_id: int
    boot_timeout_s: float

    def configure_bus(self, b: DriveBus) -> None:
        """Reset, set up and start every drive of open bus ``b`` (see the module docstring);
        ``b.network`` / ``b.nodes`` are kept for the SDO sessions of activate / deactivate.

        Raises:
            CommunicationError: a drive sent no boot-up or stopped answering.
            HardwareError: a drive refused a setting, is no CiA 402 drive, or has no free
                consumer heartbeat entry.
        """
        assert b.bus is not None
        network = canopen.Network(b.bus)
        nodes = {d.node_id: network.add_node(d.node_id, self.eds) for d in b.drives}
        b.network, b.nodes = network, nodes  # for the SDO sessions of activate / deactivate
        booted: dict[int, bool] = {}

        def on_heartbeat(node_id: int) -> Any:
            def callback(state: int) -> None:
                if state == 0:
                    booted[node_id] = True
            return callback

        canbus.flush(b.bus)  # boot-ups and answers from before: not ours
        notifier = can.Notifier(b.bus, [MessageListener(network)], timeout=_NOTIFIER_CYCLE_S)
        try:
            for d in b.drives:
                node = nodes[d.node_id]
                node.sdo.RESPONSE_TIMEOUT = b.settings.setup_timeout
                node.nmt.add_heartbeat_callback(on_heartbeat(d.node_id))
                node.nmt.send_command(c4.NMT_RESET_COMMUNICATION)
            deadline = time.monotonic() + self.boot_timeout_s
            for d in b.drives:
                node = nodes[d.node_id]
                with node.nmt.state_update:
                    while not booted.get(d.node_id):
                        remaining = deadline - time.monotonic()
                        if remaining <= 0.0:
                            raise CommunicationError(
                                f"{self.owner}: {d.who()} sent no boot-up message within "
                                f"{self.boot_timeout_s:g} s of an NMT reset communication; "
                                "check its power, wiring, node id and that the bus runs at "
                                f"{b.settings.bitrate} bit/s"
                            )
                        node.nmt.state_update.wait(remaining)
            for d in b.drives:
                self._setup_drive(d, nodes[d.node_id])
            for d in b.drives:
                nodes[d.node_id].nmt.send_command(c4.NMT_START)
        finally:
            notifier.stop(timeout=2.0)
        # canopen's PDO maps subscribed to their frames while saving; the cycle decodes them.
        network.subscribers.clear()

    def sdo_error(self, d: Drive, what: str, exc: Exception) -> HardwareError:
        """A failed SDO transfer ``exc`` while doing ``what``, in one line naming the drive:
        a refusal (abort) is a HardwareError, silence a CommunicationError."""
        if isinstance(exc, SdoAbortedError):
            return HardwareError(
                f"{self.owner}: {d.who()} refused {what}: SDO abort 0x{exc.code:08X} "
                f"({one_line(exc)}); check that the drive supports it (EDS: {self.eds})"
            )
        return CommunicationError(
            f"{self.owner}: {d.who()} did not answer while {what} ({one_line(exc)}); "
            "check the "
            "drive's power and wiring"
        )

    def _setup_drive(self, d: Drive, node: canopen.RemoteNode) -> None:
        what = "reading the device type 0x1000"
        try:
            device_type = int(node.sdo[c4.DEVICE_TYPE].raw)
            if device_type & 0xFFFF != _PROFILE_402:
                raise HardwareError(
                    f"{self.owner}: {d.who()} is not a CiA 402 drive: device type "
                    f"0x{device_type:08X} (profile {device_type & 0xFFFF}); check the node id"
                )
            what = "mapping its PDOs"
            map_pdo(node.rpdo[1], d.rpdo1, self.rpdo_layout)
            map_pdo(node.rpdo[2], c4.rpdo_cob_id(2, d.node_id), None)
            map_pdo(node.tpdo[1], d.tpdo1, c4.TPDO_STATUS)
            map_pdo(node.tpdo[2], d.tpdo2, c4.TPDO_FEEDBACK)
            what = f"setting the mode of operation 0x6060 to {int(self.mode)} ({self.mode.name})"
            node.sdo[c4.MODES_OF_OPERATION].raw = int(self.mode)
            shown = int(node.sdo[c4.MODES_OF_OPERATION_DISPLAY].raw)
            # By index, not through the EDS: a drive's EDS need not list these objects.
            what = (f"setting the abort connection option code 0x6007 to {int(self.reaction)} "
                    f"({self.reaction.name.lower()})")
            node.sdo.download(c4.ABORT_CONNECTION_OPTION, 0, struct.pack("<h", self.reaction))
            what = "reading its consumer heartbeat time entries 0x1016"
            d.consumer_sub = self._consumer_entry(d, node)
            what = f"writing its consumer heartbeat time 0x1016:{d.consumer_sub}"
            self.write_consumer(d, node, 0)  # claimed, not watching yet: activate arms it
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise self.sdo_error(d, what, exc) from exc
        d.mode_display = shown
        if shown != int(self.mode):
            raise HardwareError(
                f"{self.owner}: {d.who()}: mode switch failed: 0x6060 was set to "
                f"{int(self.mode)} ({self.mode.name}) but 0x6061 displays {shown}; check "
                "that the drive supports cyclic synchronous modes (0x6502) and is not "
                "being commanded by another master"
            )

    def _consumer_entry(self, d: Drive, node: canopen.RemoteNode) -> int:
        """The 0x1016 sub-index to use: the one already watching the master's node id, else
        the first unused one (CiA 301 refuses two entries for one node id).

        Raises:
            HardwareError: every entry watches another node.
        """
        count = int.from_bytes(node.sdo.upload(c4.CONSUMER_HEARTBEAT_TIME, 0), "little")
        free = 0
        for sub in range(1, count + 1):
            value = int.from_bytes(node.sdo.upload(c4.CONSUMER_HEARTBEAT_TIME, sub), "little")
            entry = c4.decode_consumer_entry(value)
            if entry is None:
                free = free or sub
            elif entry[0] == self.master_id:
                return sub
        if not free:
            raise HardwareError(
                f"{self.owner}: {d.who()} has no free consumer heartbeat entry in 0x1016 "
                f"({count} entries, each watching another node) for the daemon's heartbeat "
                f"(node {self.master_id}); free one with the drive's configuration tool"
            )
        return free

    def write_consumer(self, d: Drive, node: canopen.RemoteNode, time_ms: int) -> None:
        """Write ``d``'s consumer entry: the daemon's node id, ``time_ms`` (0: not watching)."""
        value = c4.encode_consumer_entry(self.master_id, time_ms)
        node.sdo.download(c4.CONSUMER_HEARTBEAT_TIME, d.consumer_sub, struct.pack("<I", value))


def map_pdo(pdo: Any, cob_id: int, layout: c4.PdoLayout | None) -> None:
    """Map one PDO of a remote node to ``layout``, synchronous (None: disable it); saved by SDO."""
    pdo.clear()
    pdo.cob_id = cob_id
    if layout is None:
        pdo.enabled = False
    else:
        for entry in layout.entries:
            pdo.add_variable(entry.index, entry.subindex)
        pdo.trans_type = 1
        pdo.enabled = True
    pdo.save()
