"""``felis replay LOG``: a run's sent commands played again on a robot, in MuJoCo (``--backend sim``) or on
Dynamixel servos (``--backend dxl --port PATH|virtual``), then what the robot did compared with the original.

The replay is a controller like any other (`felis.controllers.replay.ReplayController`: a minimum-jerk
approach from the present pose to the log's first commanded pose, then the logged commands interpolated at
loop time × ``--speed``), run by `felis.loop.run_loop` through the safety layer, on the robot that
`felis run` opens (`felis.cli.episode`'s backends: the same checks, calibration, EEPROM check, virtual bus).
It writes its own log (``--log``; default beside LOG, ``STEM-replay-BACKEND.mcap``) whose summary, like
``--json``, holds the per-joint position error of the replay's measured joint states against the original's,
aligned in log time after the approach (`felis.logs.compare.position_error`).

Refused in one line, before anything is opened or written: a log of another robot (``--robot`` differs from
the log's, or the log's joints are not the description's), a log with no sent commands (a ``felis monitor``
recording), a log of felis 0.2's form (`felis.logs.reader.read_log` says what to do), ``--speed`` above 1 on
servos, a window (``--from``/``--to``) outside the log's commands.
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from felis.cli import output

if TYPE_CHECKING:  # annotations only: the modules load when the command runs
    from felis.controllers.replay import Commands, ReplayController
    from felis.logs.compare import Comparison
    from felis.logs.reader import LogData
    from felis.spec import RobotSpec
from felis.cli.args import backend_args, finite, trace_option
from felis.errors import ParameterError, UnknownRobotError

MAX_SPEED = 10.0  # in simulation; on servos at most 1 (the recorded speed)
MAX_APPROACH_S = 60.0


def register(sub) -> None:
    """Add ``felis replay``."""
    p = sub.add_parser("replay", help="replay a run log's commands on a robot and compare with the original")
    p.add_argument("file", type=Path, metavar="LOG", help="a run log (.mcap) from `felis run --log` and the like")
    p.add_argument("--robot", help="robot name or description .toml (default: the log's robot; must match it)")
    backend_args(p, imu_help="dxl: serial device of the cat's IMU (logged; the replay does not steer by it)")
    trace_option(p)
    p.add_argument("--servo-params", type=Path, metavar="FILE",
                   help="simulated servos' parameters from `felis sysid` (sim backend or --port virtual)")
    p.add_argument("--speed", type=finite, default=1.0,
                   help=f"playback speed (default 1; at most 1 on servos, {MAX_SPEED:g} in simulation)")
    p.add_argument("--from", dest="t_from", type=finite, metavar="S",
                   help="start at this run time of the log (s; default: its first command)")
    p.add_argument("--to", dest="t_to", type=finite, metavar="S",
                   help="end at this run time of the log (s; default: its last command)")
    p.add_argument("--approach", type=finite, metavar="S",
                   help="seconds to move to the first pose (default: from the distance, peak speed a quarter of "
                        "each joint's maximum, at least 0.5 s)")
    p.add_argument("--log", type=Path, help="the replay's own log (.mcap; default: beside LOG, "
                   "STEM-replay-BACKEND.mcap)")
    p.add_argument("--json", action="store_true", help="print the run report and the comparison as JSON")
    p.set_defaults(func=cmd_replay)


# ----------------------------------------------------------------------------- checks (nothing opened yet)
def check_options(args, backend: str) -> Path:
    """The options alone, before the log is read; returns the replay's log path."""
    if backend == "sim" and args.port is not None:
        raise ParameterError("--port needs --backend dxl")
    if backend == "sim" and (args.robot_id or args.calibration or args.imu_port or getattr(args, "trace", None)):
        raise ParameterError("--robot-id, --calibration, --imu-port and --trace are for servos: they need --backend "
                             "dxl")
    if not 0 < args.speed <= MAX_SPEED:
        raise ParameterError(f"--speed must be within 0…{MAX_SPEED:g} (1: as recorded), got {args.speed:g}")
    if backend == "dxl" and args.speed > 1:
        raise ParameterError(f"--speed {args.speed:g} on servos: a replay on hardware runs at most at the recorded "
                             "speed (--speed ≤ 1); replay faster with --backend sim")
    if args.approach is not None and not 0 < args.approach <= MAX_APPROACH_S:
        raise ParameterError(f"--approach must be within 0…{MAX_APPROACH_S:g} s, got {args.approach:g}")
    log = args.log if args.log is not None else args.file.with_name(f"{args.file.stem}-replay-{backend}.mcap")
    if log.suffix.lower() != ".mcap":
        raise ParameterError(f"{log}: the replay's log must end in .mcap")
    if log.resolve() == args.file.resolve():
        raise ParameterError(f"{log}: the replay's log would overwrite the log it replays; give another --log")
    return log


def robot_of(data: LogData, robot: str | None) -> RobotSpec:
    """The description to replay ``data`` on: ``robot`` (checked against the log's) or the log's own; the
    log's joints must be the description's, in order."""
    from felis.spec import load_spec
    logged = data.meta.get("robot")
    if robot is None:
        if not logged:
            raise ParameterError(f"{data.path} names no robot: give --robot NAME or --robot FILE.toml")
        try:
            spec = load_spec(str(logged))
        except UnknownRobotError:
            raise ParameterError(f"{data.path} is a log of robot {logged!r}, which has no description here: "
                                 f"give --robot FILE.toml (its description)") from None
    else:
        spec = load_spec(robot)
        if logged and spec.name != logged:
            raise ParameterError(f"{data.path} is a log of robot {logged!r}, not {spec.name!r}: replay it on the "
                                 f"{logged} (leave out --robot) or replay a log of the {spec.name}")
    if list(data.joints) != list(spec.names):
        raise ParameterError(f"{data.path}'s joints ({', '.join(data.joints)}) are not {spec.name}'s "
                             f"({', '.join(spec.names)}): it was recorded with another description; give that "
                             "one with --robot FILE.toml")
    return spec


def commands_of(data: LogData) -> Commands:
    """The log's sent commands; refused when it has none."""
    from felis.controllers.replay import Commands
    if len(data.cmd_t) == 0:
        kind = "a `felis monitor` recording: it holds what was measured, " if data.meta.get("kind") == "monitor" else ""
        raise ParameterError(f"{data.path} has no sent commands (/joint_commands) to replay ({kind}nothing was "
                             "commanded); replay a log of `felis run … --log`")
    try:
        return Commands.from_arrays(data.cmd_t, data.cmd_q)
    except ParameterError as e:
        raise ParameterError(f"{data.path}: {e}") from None


def window(commands: Commands, t_from: float | None, t_to: float | None) -> tuple[float, float]:
    """[--from, --to] within the log's commands (default: all of them)."""
    first, last = float(commands.t[0]), float(commands.t[-1])
    a = first if t_from is None else t_from
    b = last if t_to is None else t_to
    span = f"the log's commands run from {first:.3f} to {last:.3f} s"
    if not first <= a < last:
        raise ParameterError(f"--from {a:g} s is outside the replayable part: {span}")
    if not first < b <= last:
        raise ParameterError(f"--to {b:g} s is outside the replayable part: {span}")
    if a >= b:
        raise ParameterError(f"--from {a:g} s must be before --to {b:g} s")
    return a, b


def recorded_rate(data: LogData, spec: RobotSpec) -> float:
    """The loop rate the log was recorded at: its summary's, else its commands' median period, else the
    description's."""
    run = (data.summary or {}).get("run") or {}
    rate = run.get("rate_hz")
    if isinstance(rate, (int, float)) and math.isfinite(rate) and 1 <= rate <= 1000:
        return float(rate)
    if len(data.cmd_t) > 2:
        dt = float(np.median(np.diff(data.cmd_t)))
        if dt > 0 and 1 <= 1 / dt <= 1000:
            return 1 / dt
    return float(spec.rate_hz)


# ----------------------------------------------------------------------------- the run
class Trace:
    """Loop monitor: every tick's state time and measured positions."""

    def __init__(self):
        self.t: list[float] = []
        self.q: list[np.ndarray] = []

    def __call__(self, state, command) -> None:
        self.t.append(state.t)
        self.q.append(state.q)


def cmd_replay(args) -> int:
    from felis.cli.episode import Episode, EpisodeResult, _Dxl, _Sim
    from felis.cli.results import exit_code, print_result
    from felis.controllers.replay import ReplayController, approach_time
    from felis.logs.reader import read_log
    from felis.logs.runlog import RunLog
    from felis.loop import first_read, run_loop
    from felis.safety import SafetyConfig
    backend_name = "dxl" if args.backend in ("dxl", "dynamixel") else args.backend
    log_path = check_options(args, backend_name)
    data = read_log(args.file)  # LogError: missing, not MCAP, not felis's, felis 0.2's form (what to do)
    spec = robot_of(data, args.robot)
    commands = commands_of(data)
    t_from, t_to = window(commands, args.t_from, args.t_to)
    rate = recorded_rate(data, spec)
    notes = [] if data.complete else [f"{args.file} was cut off (a crash?): replaying the {data.duration:.2f} s "
                                         "it holds"]
    ep = Episode(robot=args.robot or spec.name, controller="replay", duration=(t_to - t_from) / args.speed + 1.0,
                 log=log_path, clock="wall" if backend_name == "dxl" else "sim", rate_hz=rate, backend=backend_name,
                 port=args.port, baud=args.baud, imu_port=args.imu_port, robot_id=args.robot_id,
                 calibration=args.calibration, yes=args.yes, servo_params=args.servo_params,
                 trace=getattr(args, "trace", None))
    # the backends' own checks (port, calibration, servo parameters, log path); the replay needs no IMU to steer
    # and draws no markers, so they get no controller
    backend = (_Dxl if backend_name == "dxl" else _Sim)(ep, spec, None)
    files: dict[str, str] = {}
    trace = Trace()
    progress = None
    with contextlib.ExitStack() as stack:
        robot = backend.open(stack)
        # connected, not armed: where the approach starts (read as the loop's first read is: tried again on a failure)
        present = first_read(robot, SafetyConfig().read_fail_tolerance).q
        approach = args.approach if args.approach is not None else approach_time(spec, present,
                                                                                  commands.at(t_from))
        controller = ReplayController(commands, t_from=t_from, t_to=t_to, speed=args.speed, approach_s=approach)
        duration = controller.duration + 1.0 / rate  # the last tick sends the window's last command
        plan = {"of": str(args.file), "backend": backend_name, "speed": args.speed, "from_s": round(t_from, 6),
                "to_s": round(t_to, 6), "approach_s": round(approach, 4), "rate_hz": rate}
        log = None
        try:
            scene, poses = backend.view(None)
            log = RunLog(log_path, spec, {**backend.meta(), "replay": plan}, scene=scene, poses=poses)
            monitors = [trace, *backend.monitors()]
            if not args.json:
                progress = output.LoopProgress(f"{spec.name} replay", duration)
                monitors.append(progress)
            report = run_loop(robot, controller, duration=duration, rate_hz=rate, clock=backend.clock, log=log,
                              monitors=monitors)
        except BaseException:
            backend.abort()
            if log is not None:
                log.close({"error": "replay aborted"})
            raise
        finally:
            if progress is not None:
                progress.stop()
        comparison = compare(data, spec, controller, trace)
        replay = {**plan, "position_error": comparison.as_dict()}
        log.close({"run": report.as_dict(), "replay": replay})
        files["log"] = str(log_path)
        backend.finish(files)
    res = EpisodeResult(report=report, landing=None, drop=None, files=files, warnings=[*notes, *backend.warnings])
    if args.json:
        output.print_json({**res.as_dict(), "replay": replay})
    else:
        console = output.console()
        print_result(res, console)
        print_comparison(comparison, plan, console)
    return exit_code(report)


def compare(data: LogData, spec: RobotSpec, controller: ReplayController, trace: Trace) -> Comparison:
    """The replay's measured positions against the original's at the log times they replay (after the
    approach, within the window)."""
    from felis.logs.compare import position_error
    t = np.asarray(trace.t, dtype=float)
    q = np.asarray(trace.q, dtype=float).reshape(len(t), spec.n)
    tau = controller.log_time(t - controller.t0)
    return position_error(data.t, data.q, tau, q, list(spec.names), [j.kind for j in spec.joints])


def print_comparison(c: Comparison, plan: dict, console) -> None:
    """Per joint: RMS and max position error (degrees; mm for prismatic joints)."""
    console.print(f"replayed {plan['of']} {plan['from_s']:g}…{plan['to_s']:g} s at speed {plan['speed']:g} on "
                  f"{plan['backend']} after a {plan['approach_s']:.2f} s approach")
    if c.samples == 0:
        console.print("[yellow]no comparison: the original log has no measured joint states in the window[/]")
        return
    console.print(f"position error against the original ({c.samples} ticks, {c.span[0]:.2f}…{c.span[1]:.2f} s):")
    width = max(len(j) for j in c.joints)
    for j, kind, rms, peak in zip(c.joints, c.kinds, c.rms, c.max, strict=True):
        scale, unit = (1e3, "mm") if kind == "prismatic" else (180 / math.pi, "°")
        text = "no samples" if not math.isfinite(rms) else \
            f"RMS {rms * scale:7.3f} {unit}  max {peak * scale:7.3f} {unit}"
        console.print(f"  {j:<{width}}  {text}")

