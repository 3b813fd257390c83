"""``felis virtual-bus``: serve a robot's emulated Dynamixel servos on a pseudo-terminal.

::

    felis virtual-bus --robot cat|arm|FILE.toml [--sim] [--baud B] [--faults SPEC] [--wire-time] [--seed S]
                      [--servo-params FILE] [--fixed-base] [--imu-mount-deg R,P,Y] [--imu-drift X,Y,Z]
                      [--drop H,R,P,Y]

Output contract (what `felis.drivers.virtual.spawn` and scripts rely on): the FIRST line of stdout is
``port: <device path>``, then ``imu: <device path>`` when the robot has an IMU and ``--sim`` backs it,
then one human-readable summary line; each is flushed at once. The bus serves until SIGINT, SIGTERM
or SIGHUP (the terminal closed), then stops cleanly (every thread joined, ptys closed), prints its
counters to stderr (Bus Watchdog trips included) and exits 0. Bad arguments (unknown robot, baud rate
a servo lacks, malformed fault spec) are `felis.errors.FelisError`s that the CLI prints as one line.

``--sim --drop H,R,P,Y`` holds the robot in the air before release: its lowest point H m above the
floor, turned by roll R, pitch P, yaw Y degrees (`felis.sim.scenarios.drop`); the fall starts when
torque first comes on (`felis.drivers.virtual`, module doc). ``felis run … --backend dxl --port
virtual --height H`` uses it.

The process lowers Python's thread switch interval to 0.5 ms: the server thread shares the GIL with
the simulation and IMU threads, and a reply must not wait the default 5 ms for it.
"""

from __future__ import annotations

import signal
import sys
import time

SWITCH_INTERVAL_S = 0.0005


def register(sub) -> None:
    """Add ``virtual-bus`` to the ``felis`` sub-commands (``sub``: the CLI's sub-parsers action, which makes
    one-line-error parsers)."""
    p = sub.add_parser("virtual-bus", help="serve emulated Dynamixel servos of a robot on a pseudo-terminal",
                       description="Emulated Dynamixel servos (Protocol 2.0) on a pseudo-terminal: any serial "
                       "client, the dynamixel-sdk included, talks to them as to a USB adapter. Prints "
                       "'port: PATH' first; serves until Ctrl-C or SIGTERM.")
    p.add_argument("--robot", required=True, help="robot name (cat, arm) or a description .toml")
    p.add_argument("--sim", action="store_true", help="back the servos with the MuJoCo model (servo-in-the-loop)")
    p.add_argument("--baud", type=int, default=1_000_000, help="servo baud rate in bps (default 1000000)")
    p.add_argument("--faults", metavar="SPEC", help="inject faults, e.g. 'drop=0.01,corrupt=0.001,delay_ms=5,"
                   "remove=3,hwerror=5:overload,close_after=2.5,reboot=3@1.5,torque_off=7@2' (reboot/torque_off: "
                   "seconds after that servo's torque first came on)")
    p.add_argument("--wire-time", action="store_true",
                   help="deliver replies when the wire would (baud rate, return delay)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fault injection (default 0)")
    p.add_argument("--servo-params", metavar="FILE",
                   help="with --sim: servo model parameters per joint (a `felis sysid` output file)")
    p.add_argument("--fixed-base", action="store_true",
                   help="with --sim: hang a floating-base robot on a stand (base held, legs free)")
    p.add_argument("--imu-mount-deg", metavar="R,P,Y",
                   help="with --sim: the IMU mounted rotated by roll, pitch, yaw degrees in the body "
                   "(write --imu-mount-deg=-4,2,0 when the first value is negative)")
    p.add_argument("--imu-drift", metavar="X,Y,Z",
                   help="with --sim: the IMU's orientation drifts at this sensor-frame rate (rad/s)")
    p.add_argument("--drop", metavar="H,R,P,Y",
                   help="with --sim: hold the robot in the air, lowest point H m up, turned by roll, pitch, yaw "
                   "degrees; it falls when torque first comes on (floating base only)")
    p.set_defaults(func=cmd_virtual_bus)


def _numbers(option: str, text: str | None, n: int, example: str) -> tuple[float, ...] | None:
    """'a,b,…' -> ``n`` finite floats (None when the option is absent); ParameterError otherwise."""
    if text is None:
        return None
    import math

    from felis.errors import ParameterError

    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != n or not all(math.isfinite(v) for v in values):
        words = {3: "three", 4: "four"}.get(n, str(n))
        raise ParameterError(f"{option} takes {words} comma-separated numbers (e.g. {example}), got {text!r}")
    return values


def _triple(option: str, text: str | None) -> tuple[float, float, float] | None:
    """'a,b,c' -> three finite floats (None when the option is absent); ParameterError otherwise."""
    return _numbers(option, text, 3, "6,-4,0")


def _drop(text: str | None) -> tuple[float, float, float, float] | None:
    """--drop 'H,R,P,Y' -> (height m, roll°, pitch°, yaw°), None when absent; ParameterError otherwise."""
    return _numbers("--drop", text, 4, "1,180,0,0: height m, roll, pitch, yaw degrees")


def summary(bus, args) -> str:
    """One line: robot, servos, baud, backing, timing, faults."""
    servos = bus.servos
    models = sorted({s.model for s in servos})
    ids = sorted(s.id for s in servos)
    id_text = f"{ids[0]}…{ids[-1]}" if ids == list(range(ids[0], ids[-1] + 1)) else ", ".join(map(str, ids))
    backing = "backed by MuJoCo" if args.sim else "standalone dynamics"
    if getattr(args, "fixed_base", False):
        backing += " (fixed base)"
    if getattr(args, "servo_params", None):
        backing += f" with servo parameters from {args.servo_params}"
    if getattr(args, "imu_mount_deg", None):
        backing += f", IMU mounted at roll,pitch,yaw {args.imu_mount_deg}°"
    if getattr(args, "imu_drift", None):
        backing += f", IMU drifting {args.imu_drift} rad/s"
    drop = _drop(getattr(args, "drop", None))
    if drop is not None:
        backing += (f", held {drop[0]:g} m up at roll {drop[1]:g}° pitch {drop[2]:g}° yaw {drop[3]:g}° "
                    "until torque comes on")
    timing = "wire time modelled" if args.wire_time else "replies at once"
    faults = f"faults {args.faults}" if args.faults else "no faults"
    return (f"virtual bus: {bus.spec.name}, {len(servos)} × {'/'.join(models)} (IDs {id_text}) at {args.baud} bps, "
            f"{backing}, {timing}, {faults}; stop with Ctrl-C or SIGTERM")


def _imu_options(args) -> dict:
    """--imu-mount-deg / --imu-drift -> `VirtualBus.for_robot` keywords (the mount as a quaternion)."""
    out = {}
    mount = _triple("--imu-mount-deg", getattr(args, "imu_mount_deg", None))
    if mount is not None:
        import math

        from felis.rotations import quat_from_ypr

        roll, pitch, yaw = (math.radians(v) for v in mount)
        out["imu_mount"] = quat_from_ypr(yaw, pitch, roll)
    drift = _triple("--imu-drift", getattr(args, "imu_drift", None))
    if drift is not None:
        out["imu_drift"] = drift
    return out


def cmd_virtual_bus(args) -> int:
    from felis.drivers.virtual import parse_fault_plan
    from felis.sim.servo_in_loop import virtual_bus

    faults = parse_fault_plan(args.faults) if args.faults else None
    drop = _drop(getattr(args, "drop", None))
    servo_params = None
    if getattr(args, "servo_params", None):
        from felis.sim.servo_file import load_servo_params
        from felis.spec import load_spec

        servo_params = load_servo_params(args.servo_params, load_spec(args.robot))
    bus = virtual_bus(args.robot, baud=args.baud, sim=args.sim, wire_time=args.wire_time, faults=faults,
                      seed=args.seed, servo_params=servo_params,
                      fixed_base=getattr(args, "fixed_base", False), drop=drop, **_imu_options(args))
    # The handler only appends to a list: an Event.set() there would take the lock that the main thread's
    # own Event.wait() may hold when the signal lands, and a second signal would then deadlock the process.
    stop: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, _frame: stop.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        bus.start()
        print(f"port: {bus.port}", flush=True)
        if bus.imu_port:
            print(f"imu: {bus.imu_port}", flush=True)
        print(summary(bus, args), flush=True)
        while not stop:
            time.sleep(0.05)
    finally:
        bus.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        print(f"virtual bus stopped: {bus.stats.summary()}", file=sys.stderr, flush=True)
    return 0
