"""The ``jtc-hw emulate can`` process (``python -m jtc_hw.drivers.can.emulator``): emulated CAN
motors of either protocol, served to other processes.

``main(argv)`` runs emulators in a process (MIT-mode motors:
:class:`~jtc_hw.drivers.can.mit.emulator.MitBusEmulator`; CiA 402 drives:
:class:`~jtc_hw.drivers.can.cia402.emulator.Cia402DriveEmulator`), behind a socketcand
server (default) so that other processes reach them with python-can's stock ``socketcand``
interface, or on the kernel's SocketCAN devices (``--interface socketcan --channel vcan0``:
every process on the host reaches them there), until SIGINT/SIGTERM.
With ``--events`` it prints, after its connect line, one JSON line per motor event
(``{"event": "enabled"|"disabled"|"timeout", "channel": ..., "id": ..., "t": ...}``, ``t`` on
the system-wide monotonic clock, so another process can compare it with its own times), and
looks for expired timeouts every 5 ms.
A running process takes fault commands on a unix socket (``--control PATH``): one line per
command, answered with one line (``ok`` or ``error: ...``); ``brownout ID OFF_S [CHANNEL]``
browns motor ``ID`` out for ``OFF_S`` seconds (the channel may be left out when there is
one). ``--fault brownout:ID:OFF_S@AFTER_S`` schedules the same ``AFTER_S`` seconds after the
connect line.
The process runs at SCHED_FIFO priority 1 where permitted (``--priority N``; 0: normal
scheduling), as the motors it stands for are not slowed down by a busy host: normally
scheduled, its replies came late on a loaded machine and counted as missed
(:func:`~jtc_hw.drivers.emulation_cli.realtime_priority`).
With ``--one-thread`` the emulators start no threads (``start(push=True, thread=False)``; CiA
402 drives ``start(push=True)``): the server's single thread reads every client, the frames
reach the emulators in it, and it releases every bus's due replies (each emulator keeps its
own heap of due replies and its own wire, so the buses stay independent and concurrent). A
process serving several buses then keeps one busy thread: no interpreter lock to contend for,
no thread hand-over.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import can

from ..emulation_cli import DEFAULT_PRIORITY, apply_priority, parse_ids
from ..motor_model import MotorParams
from .cia402.emulator import Cia402DriveEmulator
from .emulation import ControlSocket
from .mit.codec import MODEL_PRESETS
from .mit.emulator import EmulatorEvent, MitBusEmulator
from .socketcand import SocketcandServer

__all__ = ["build_parser", "control_command", "main"]

_EVENTS_POLL_S = 0.005  # `--events`: how often the process looks for expired timeouts


def build_parser() -> argparse.ArgumentParser:
    """The ``jtc-hw emulate can`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="jtc-hw emulate can",
        description="Emulate CAN motors (MIT mode or CiA 402 drives) and serve them over "
        "socketcand on 127.0.0.1, on SocketCAN devices (vcan0, ...), or on an in-process "
        "python-can virtual bus.",
    )
    parser.add_argument("--protocol", choices=("mit", "cia402"), default="mit")
    parser.add_argument("--ids", action="append", default=None,
                        help="motor ids / node ids, e.g. 1-6 (repeat once per --channel)")
    parser.add_argument("--model", default="AK80-9",
                        help=f"MIT motor model: {', '.join(MODEL_PRESETS)}")
    parser.add_argument("--bitrate", type=int, default=1_000_000)
    parser.add_argument("--pace", action="store_true",
                        help="deliver replies no earlier than the wire at --bitrate would")
    parser.add_argument("--socketcand-port", type=int, default=0,
                        help="TCP port of the socketcand server (0: any free port)")
    parser.add_argument("--interface", choices=("socketcand", "virtual", "socketcan"),
                        default="socketcand",
                        help="socketcand: serve over TCP; virtual: in-process bus only; "
                        "socketcan: join the kernel's CAN network devices named by --channel "
                        "(vcan0, can0; other processes reach the motors there)")
    parser.add_argument("--channel", action="append", default=None,
                        help="bus channel name (repeatable; default can0)")
    parser.add_argument("--one-thread", action="store_true",
                        help="socketcand: serve every channel, and release every emulator's "
                        "replies, from one thread (no threads of the emulators' own)")
    parser.add_argument("--priority", type=int, default=None, metavar="N",
                        help=f"SCHED_FIFO priority of the process, 1..99, 0: normal "
                        f"scheduling (default: {DEFAULT_PRIORITY} where permitted, so that a "
                        "busy host does not delay the replies as it would never delay real "
                        "motors)")
    parser.add_argument("--master-id", type=lambda s: int(s, 0), default=0,
                        help="MIT reply arbitration id")
    parser.add_argument("--events", action="store_true",
                        help="MIT: after the connect line, print one JSON line per motor "
                        "event: {\"event\": \"enabled\"|\"disabled\"|\"timeout\", "
                        "\"channel\": ..., \"id\": ..., \"t\": monotonic s}")
    parser.add_argument("--control", metavar="PATH", default=None,
                        help="MIT: take fault commands on this unix socket, one line each, "
                        "answered ok or error: ...: 'brownout ID OFF_S [CHANNEL]' (the motor "
                        "loses power for OFF_S s, then restarts disabled, out of motor mode)")
    parser.add_argument("--fault", action="append", default=[], metavar="SPEC",
                        help="MIT: schedule a fault, e.g. brownout:3:0.05@2 (motor 3 browns "
                        "out for 0.05 s, 2 s after the connect line); repeatable")
    return parser


def control_command(line: str, emulators: Mapping[str, MitBusEmulator]) -> str:
    """Apply one control command to the emulators by channel; the answer line.

    Raises:
        ValueError: not a known command, a bad value, an unknown channel or motor.
    """
    words = line.split()
    if not words or words[0] != "brownout" or len(words) not in (3, 4):
        raise ValueError(f"unknown command {line!r}; expected: brownout ID OFF_S [CHANNEL]")
    if len(words) == 4:
        channel = words[3]
    elif len(emulators) == 1:
        (channel,) = emulators
    else:
        raise ValueError(f"give the channel, one of {', '.join(emulators)}")
    if channel not in emulators:
        raise ValueError(f"unknown channel {channel!r}; known: {', '.join(emulators)}")
    emulator = emulators[channel]
    motor_id = int(words[1], 0)
    if motor_id not in emulator.ids:
        raise ValueError(f"no motor {motor_id} on channel {channel!r}")
    emulator.brown_out(motor_id, float(words[2]))
    return "ok"


def _scheduled_faults(specs: Sequence[str]) -> list[tuple[float, str]]:
    """``brownout:ID:OFF_S@AFTER_S`` -> ``(after_s, "brownout ID OFF_S")``, soonest first.

    Raises:
        ValueError: not of that form.
    """
    faults = []
    for spec in specs:
        what, _, after = spec.partition("@")
        parts = what.split(":")
        if parts[0] != "brownout" or len(parts) not in (3, 4) or not after:
            raise ValueError(f"--fault {spec!r}: expected brownout:ID:OFF_S[:CHANNEL]@AFTER_S")
        faults.append((float(after), " ".join(parts)))
    return sorted(faults)


def _pairs(
    channels: Sequence[str] | None, ids: Sequence[str] | None
) -> list[tuple[str, list[int]]]:
    channels = list(channels or ["can0"])
    id_texts = list(ids or ["1-6"])
    if len(id_texts) == 1 and len(channels) > 1:
        every = parse_ids(id_texts[0])
        per = math.ceil(len(every) / len(channels))
        return [(ch, every[i * per:(i + 1) * per]) for i, ch in enumerate(channels)]
    if len(id_texts) != len(channels):
        raise ValueError("give one --ids per --channel (or a single --ids to split evenly)")
    return [(ch, parse_ids(t)) for ch, t in zip(channels, id_texts, strict=True)]


def _event_printer(
    channel: str, ready: threading.Event, lock: threading.Lock
) -> Callable[[EmulatorEvent], None]:
    def on_event(event: EmulatorEvent) -> None:
        ready.wait()
        line = json.dumps({"event": event.kind, "channel": channel, "id": event.motor_id,
                           "t": event.t})
        with lock:  # one line at a time, from whichever thread noticed the event
            print(line, flush=True)

    return on_event


def main(argv: Sequence[str] | None = None) -> int:
    """Run the emulators until SIGINT/SIGTERM; print one line saying how to connect.

    Returns:
        The exit status (0; 2 for bad arguments or a CAN device that cannot be opened).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        pairs = _pairs(args.channel, args.ids)
    except ValueError as exc:
        parser.error(str(exc))
    if args.protocol == "mit" and args.model not in MODEL_PRESETS:
        parser.error(f"unknown --model {args.model!r}; known: {', '.join(MODEL_PRESETS)}")
    try:
        scheduled = _scheduled_faults(args.fault)
    except ValueError as exc:
        parser.error(str(exc))
    if (scheduled or args.control) and args.protocol != "mit":
        parser.error("--fault and --control are for MIT motors (--protocol mit)")
    apply_priority(parser, args.priority)  # before any thread starts: they inherit it

    tag = uuid.uuid4().hex[:8]
    # The python-can channel each bus opens: a private virtual one behind socketcand, else
    # the name given (a virtual channel, or a SocketCAN device).
    virtual = {ch: (f"emu-{tag}-{ch}" if args.interface == "socketcand" else ch)
               for ch, _ in pairs}
    bus_interface = "socketcan" if args.interface == "socketcan" else "virtual"
    buses: list[can.BusABC] = []
    emulators: list[Any] = []
    by_channel: dict[str, MitBusEmulator] = {}
    server = None
    control: ControlSocket | None = None
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    events = args.events and args.protocol == "mit"
    ready = threading.Event()  # events wait for the connect line, which comes first
    print_lock = threading.Lock()
    try:
        for ch, ids in pairs:
            try:
                bus = can.Bus(interface=bus_interface, channel=virtual[ch])
            except (OSError, can.CanError) as exc:  # SocketCAN: no such device, no AF_CAN
                print(f"jtc-hw emulate can: cannot open {bus_interface} channel {ch!r} "
                      f"({exc}); check `ip link show {ch}` (a vcan: modprobe vcan; ip link "
                      f"add dev {ch} type vcan; ip link set up {ch})", file=sys.stderr)
                return 2
            buses.append(bus)
            if args.protocol == "mit":
                by_channel[ch] = MitBusEmulator(
                    bus, ids, args.model, bitrate=args.bitrate, pace=args.pace,
                    master_id=args.master_id,
                    on_event=_event_printer(ch, ready, print_lock) if events else None)
                emulators.append(by_channel[ch])
            else:
                # One bus object per channel: its drives share one receive thread and one
                # modelled wire, as drives on one cable do.
                pace = args.bitrate if args.pace else None
                # 0.5 ms physics sub-steps, as for the MIT motors (a quarter of the default's
                # CPU, stable at these gains).
                physics = MotorParams(max_step_s=0.0005)
                emulators.extend(
                    Cia402DriveEmulator(bus, node, pace_bitrate=pace, motor_params=physics)
                    for node in ids)
        one_thread = args.one_thread and args.interface == "socketcand"
        timers: list[Any] = []
        for emulator in emulators:
            if args.protocol == "mit" and args.interface == "socketcand":
                # Nothing else in this process uses the bus: frames from the socketcand
                # clients are handled in the server's reading thread (no hand-over).
                emulator.start(push=True, thread=not one_thread)
                timers.append(emulator)
            elif one_thread:
                emulator.start(push=True)
                if all(emulator.timer() is not t for t in timers):
                    timers.append(emulator.timer())  # one per bus: its drives share it
            else:
                emulator.start()
        if args.interface == "socketcand":
            server = SocketcandServer(port=args.socketcand_port, channels=virtual,
                                      timers=timers if one_thread else None)
            server.start()
            print(f"interface=socketcand host={server.host} port={server.port} "
                  f"channel={','.join(virtual)}", flush=True)
        else:
            print(f"interface={args.interface} channel={','.join(virtual)}", flush=True)
        if args.control:
            control = ControlSocket(args.control,
                                    lambda line: control_command(line, by_channel))
        ready.set()
        started = time.monotonic()
        while not stop.wait(_EVENTS_POLL_S if events or scheduled else None):
            while scheduled and time.monotonic() - started >= scheduled[0][0]:
                _, command = scheduled.pop(0)
                try:
                    control_command(command, by_channel)
                except ValueError as exc:
                    print(f"jtc-hw emulate can: --fault: {exc}", file=sys.stderr)
            if events:
                # An expired CAN timeout needs no frame to happen: look for them regularly
                # (the events carry the modelled instant, not when they were noticed).
                for emulator in emulators:
                    emulator.check_timeouts()
    finally:
        if control is not None:
            control.close()
        if server is not None:
            server.stop()
        for emulator in emulators:
            emulator.stop()
        for bus in buses:
            bus.shutdown()
    return 0


if __name__ == "__main__":  # pragma: no cover - `python -m jtc_hw.drivers.can.emulator`
    sys.exit(main())
