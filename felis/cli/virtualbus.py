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

Serving is `felis.drivers.virtual.process.serve` (with its `summary` line), as in a spawned bus; it lowers
Python's thread switch interval to 0.5 ms: the server thread shares the GIL with
the simulation and IMU threads, and a reply must not wait the default 5 ms for it.
"""

from __future__ import annotations

import contextlib

from felis.cli.args import live_option


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
    live_option(p)
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
    from felis.drivers.virtual.process import serve, summary
    from felis.sim.servo_in_loop import virtual_bus

    faults = parse_fault_plan(args.faults) if args.faults else None
    drop = _drop(getattr(args, "drop", None))
    servo_params = None
    if getattr(args, "servo_params", None):
        from felis.sim.servo_file import load_servo_params
        from felis.spec import load_spec

        servo_params = load_servo_params(args.servo_params, load_spec(args.robot))
    imu = _imu_options(args)
    bus = virtual_bus(args.robot, baud=args.baud, sim=args.sim, wire_time=args.wire_time, faults=faults,
                      seed=args.seed, servo_params=servo_params,
                      fixed_base=getattr(args, "fixed_base", False), drop=drop, **imu)
    options = {"robot": args.robot, "baud": args.baud, "sim": args.sim, "wire_time": args.wire_time,
               "faults": args.faults, "fixed_base": getattr(args, "fixed_base", False),
               "servo_params": getattr(args, "servo_params", None), "imu_mount": imu.get("imu_mount"),
               "imu_drift": imu.get("imu_drift"), "drop": drop}
    line = summary(bus, options, imu_mount_text=getattr(args, "imu_mount_deg", None),
                   imu_drift_text=getattr(args, "imu_drift", None))
    if getattr(args, "live", None) is None:
        return serve(bus, line)
    with _live_view(args, bus):
        return serve(bus, line)


@contextlib.contextmanager
def _live_view(args, bus):
    """``--live``: the simulated robot (MuJoCo's truth: joints, every body, IMU, contacts) served at 100 Hz of
    simulated time to Foxglove while the bus runs (`felis.logs.live`)."""
    from felis.cli import output
    from felis.errors import ParameterError
    from felis.logs.live import LiveView
    from felis.logs.runlog import RunLog
    from felis.sim.scene import MujocoPoses, model_scene

    backend = getattr(bus, "backend", None)
    if not args.sim or backend is None:
        raise ParameterError("--live shows the simulated robot: it needs --sim")
    robot = backend.robot
    with LiveView(args.live) as view:
        log = RunLog(None, robot.spec, {"kind": "virtual-bus", "backend": "virtual-bus --sim"},
                     scene=model_scene(robot.model), poses=MujocoPoses(robot), live=view)
        next_t = [0.0]

        def observe(state) -> None:
            if state.t + 1e-9 >= next_t[0]:
                next_t[0] = state.t + 0.01
                log.state(state)

        log.state(robot.read())  # where the robot is before anything moves (physics waits for torque)
        log.flush()  # now, not with the next chunk: the physics may wait long
        output.live(view.url)
        backend.observer = observe
        try:
            yield
        finally:
            backend.observer = None
            log.close()
