"""``felis virtual-bus``: serve a robot's emulated Dynamixel servos on a pseudo-terminal.

::

    felis virtual-bus --robot cat|arm|FILE.toml [--sim] [--baud B] [--faults SPEC] [--wire-time] [--seed S]

Output contract (what `felis.drivers.virtual.spawn` and scripts rely on): the FIRST line of stdout is
``port: <device path>``, then ``imu: <device path>`` when the robot has an IMU and ``--sim`` backs it,
then one human-readable summary line; each is flushed at once. The bus serves until SIGINT or
SIGTERM, then stops cleanly (every thread joined, ptys closed), prints its counters to stderr and
exits 0. Bad arguments (unknown robot, baud rate a servo lacks, malformed fault spec) are
`felis.errors.FelisError`s that the CLI prints as one line.

The process lowers Python's thread switch interval to 0.5 ms: the server thread shares the GIL with
the simulation and IMU threads, and a reply must not wait the default 5 ms for it.
"""

from __future__ import annotations

import signal
import sys
import threading

SWITCH_INTERVAL_S = 0.0005


def register(sub, parser_class=None) -> None:
    """Add ``virtual-bus`` to the ``felis`` sub-commands.

    ``sub`` is the CLI's sub-parsers action (it already makes one-line-error parsers); ``parser_class``
    is accepted for the registration convention and unused (this command has no sub-commands).
    """
    p = sub.add_parser("virtual-bus", help="serve emulated Dynamixel servos of a robot on a pseudo-terminal",
                       description="Emulated Dynamixel servos (Protocol 2.0) on a pseudo-terminal: any serial "
                       "client, the dynamixel-sdk included, talks to them as to a USB adapter. Prints "
                       "'port: PATH' first; serves until Ctrl-C or SIGTERM.")
    p.add_argument("--robot", required=True, help="robot name (cat, arm) or a description .toml")
    p.add_argument("--sim", action="store_true", help="back the servos with the MuJoCo model (servo-in-the-loop)")
    p.add_argument("--baud", type=int, default=1_000_000, help="servo baud rate in bps (default 1000000)")
    p.add_argument("--faults", metavar="SPEC", help="inject faults, e.g. 'drop=0.01,corrupt=0.001,delay_ms=5,"
                   "remove=3,hwerror=5:overload,close_after=2.5'")
    p.add_argument("--wire-time", action="store_true",
                   help="deliver replies when the wire would (baud rate, return delay)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fault injection (default 0)")
    p.set_defaults(func=cmd_virtual_bus)


def summary(bus, args) -> str:
    """One line: robot, servos, baud, backing, timing, faults."""
    servos = bus.servos
    models = sorted({s.model for s in servos})
    ids = sorted(s.id for s in servos)
    id_text = f"{ids[0]}…{ids[-1]}" if ids == list(range(ids[0], ids[-1] + 1)) else ", ".join(map(str, ids))
    backing = "backed by MuJoCo" if args.sim else "standalone dynamics"
    timing = "wire time modelled" if args.wire_time else "replies at once"
    faults = f"faults {args.faults}" if args.faults else "no faults"
    return (f"virtual bus: {bus.spec.name}, {len(servos)} × {'/'.join(models)} (IDs {id_text}) at {args.baud} bps, "
            f"{backing}, {timing}, {faults}; stop with Ctrl-C or SIGTERM")


def cmd_virtual_bus(args) -> int:
    from felis.drivers.virtual import VirtualBus, parse_faults

    faults = parse_faults(args.faults) if args.faults else None
    bus = VirtualBus.for_robot(args.robot, baud=args.baud, sim=args.sim, wire_time=args.wire_time, faults=faults,
                               seed=args.seed)
    done = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: done.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        bus.start()
        print(f"port: {bus.port}", flush=True)
        if bus.imu_port:
            print(f"imu: {bus.imu_port}", flush=True)
        print(summary(bus, args), flush=True)
        while not done.wait(0.2):
            pass
    finally:
        bus.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        print(f"virtual bus stopped: {bus.stats.summary()}", file=sys.stderr, flush=True)
    return 0
