"""``felis run CONTROLLER --robot R``: one controller on a robot, in MuJoCo (``--backend sim``) or on
Dynamixel servos (``--backend dxl --port PATH|virtual``), with an optional drop, log and report
(`felis.cli.episode`). Options that belong to one controller (``--policy``, ``--trajectory``,
``--base`` …) are refused with any other, in one line.
"""

from __future__ import annotations

from pathlib import Path

from felis.cli.args import backend_args, finite, live_option, trace_option
from felis.cli.results import episode, report
from felis.errors import ParameterError


def register(sub) -> None:
    """Add ``felis run``."""
    run = sub.add_parser("run", help="run a controller on a robot")
    run.add_argument("controller", help="controller name: hold, stand, sit, zero, arm-track, step-in-place, balance, "
                     "landing")
    run.add_argument("--robot", required=True, help="robot name (cat, arm) or a description .toml")
    backend_args(run)
    run.add_argument("--duration", type=finite, help="seconds (default 3; arm-track: the trajectory's length; "
                     "landing with --height: the fall √(2h/g) + 2 s)")
    run.add_argument("--height", type=finite, help="drop the robot: its lowest point this high above the floor (m); "
                     "sim, or dxl with --port virtual (held until torque comes on)")
    run.add_argument("--roll", type=finite, default=0.0, help="with --height: initial roll (deg, default 0)")
    run.add_argument("--pitch", type=finite, default=0.0, help="with --height: initial pitch (deg, default 0)")
    run.add_argument("--yaw", type=finite, default=0.0, help="with --height: initial yaw (deg, default 0)")
    run.add_argument("--policy", type=Path, metavar="caps+library|library|shipped|caps|FILE",
                     help="landing: caps+library (the default: at 1 m and 3 m a vote by attitude between the cap "
                     "policy made for that height and the motion library), library (the shipped motion library), "
                     "shipped (the "
                     "evolved nets), "
                     "caps (the shipped cap policy: closed-loop nets imitated from the library, then evolved; or "
                     "a file from bench/landing_caps.py), "
                     "a policy file from `felis train landing` (.npz), a motion library from `felis train "
                     "landing-library` (.json), a vote from bench/landing_vote.py (.json) or a whole-body motion "
                     "(.json) searched for one drop "
                     "(docs/landing.md)")
    run.add_argument("--hold", type=finite, metavar="S",
                     help="arm-track: seconds at the first point before tracking, while the servos' I terms take up "
                          "gravity (the demo holds 6 s: median error 0.8 mm against 2.4 mm without)")
    run.add_argument("--trajectory", metavar="circle|figure8|FILE.csv",
                     help="arm-track: the tool-point trajectory (CSV t,x,y,z at 100 Hz; default figure8)")
    run.add_argument("--weights", type=Path, metavar="FILE", help="arm-track: IK weights (default: the shipped ones)")
    run.add_argument("--base", choices=["stand", "step-in-place"],
                     help="balance: the controller the monitor guards (default stand)")
    run.add_argument("--reaction", choices=["none", "brace", "crouch", "step", "selector"],
                     help="balance: what the cat does when the monitor warns (default none)")
    run.add_argument("--gate", choices=["clock", "phase", "none"],
                     help="balance: what feeds the monitor's gait gate: the base's own clock (default), the learned "
                     "phase estimator (shipped weights) or nothing")
    run.add_argument("--selector", type=Path, metavar="FILE",
                     help="balance: a selector file for --reaction selector (default: the shipped one)")
    run.add_argument("--log", type=Path, help="write an MCAP log here (.mcap)")
    trace_option(run)
    live_option(run)
    run.add_argument("--rate", type=finite, help="control rate in Hz (default: the description's, 100)")
    run.add_argument("--clock", choices=["sim", "wall"], default="sim",
                     help="sim: as fast as possible; wall: real time (default sim)")
    run.add_argument("--json", action="store_true", help="print the run report as JSON")
    run.add_argument("--servo-params", type=Path, metavar="FILE",
                     help="simulated servos' parameters from `felis sysid` (sim backend or --port virtual)")
    run.set_defaults(func=cmd_run)


def drop_args(args) -> tuple[float, float, float, float] | None:
    """``--height/--roll/--pitch/--yaw`` as a drop (height m, roll°, pitch°, yaw°), or None without a height."""
    if args.height is None:
        if any(v != 0 for v in (args.roll, args.pitch, args.yaw)):
            raise ParameterError("--roll/--pitch/--yaw need --height (the drop height in metres)")
        return None
    return (args.height, args.roll, args.pitch, args.yaw)


def cmd_run(args) -> int:
    from felis.controllers.arm_track import run_time, trajectory_from
    from felis.rotations import G
    backend = "dxl" if args.backend in ("dxl", "dynamixel") else args.backend
    if backend == "sim" and args.port is not None:
        raise ParameterError("--port needs --backend dxl")
    if backend == "sim" and args.trace is not None:
        raise ParameterError("--trace records the Dynamixel bus: it needs --backend dxl")
    if backend == "sim" and (args.robot_id or args.calibration):
        raise ParameterError("--robot-id and --calibration calibrate servos: they need --backend dxl")
    options: dict = {}
    duration = args.duration
    if args.controller == "arm-track":
        traj = trajectory_from(args.trajectory or "figure8")
        options = {"trajectory": traj, "weights": args.weights, "hold": args.hold or 0.0}
        if duration is None:
            duration = run_time(traj, hold=args.hold or 0.0)
    elif args.trajectory is not None or args.weights is not None or args.hold is not None:
        raise ParameterError("--trajectory, --weights and --hold belong to the arm-track controller")
    if args.controller == "balance":
        options = {"base": args.base or "stand", "reaction": args.reaction or "none", "selector": args.selector,
                   "gate": args.gate or "clock"}
    elif args.base is not None or args.reaction is not None or args.selector is not None or args.gate is not None:
        raise ParameterError("--base, --reaction, --selector and --gate belong to the balance controller")
    drop = drop_args(args)
    if args.controller == "landing":
        # drop_height: where the robot reports no height (dxl), the controller predicts it by free fall
        options = {"policy": args.policy, "drop_height": None if drop is None else drop[0]}
        if duration is None and drop is not None:
            duration = (2 * max(drop[0], 0.0) / G) ** 0.5 + 2.0  # the fall, the bounce, then settled
    elif args.policy is not None:
        raise ParameterError("--policy belongs to the landing controller")
    duration = 3.0 if duration is None else duration
    res = episode(args, robot=args.robot, controller=args.controller, duration=duration, log=args.log, drop=drop,
                  clock="wall" if backend == "dxl" else args.clock, rate_hz=args.rate, backend=backend,
                  port=args.port, baud=args.baud, imu_port=args.imu_port, servo_params=args.servo_params,
                  robot_id=args.robot_id, calibration=args.calibration, yes=args.yes, controller_options=options,
                  trace=args.trace)
    return report(args, res)
