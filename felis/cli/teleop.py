"""``felis teleop``: a leader arm drives a follower (``--leader-port``), or the keyboard jogs it (``--keyboard``).

The follower runs through `felis.loop.run_loop` on the wall clock, in MuJoCo (``--backend sim``) or on Dynamixel
servos (``--backend dxl --port PATH|virtual``): the safety layer clamps every target and the watchdog runs. Each
tick reads the leader (`felis.drivers.dynamixel.leader.LeaderArm`: one sync read of its torque-off chain) and maps
it onto the follower's joints (`felis.controllers.teleop`, ``--map``), or applies the keys typed
(`felis.cli.keys.Keyboard`, the terminal in cbreak mode, restored on every way out).

Order of opening, so bad input writes nothing and arms nothing: every option and file is checked, the mapping is
resolved against both descriptions, then the leader is opened (a missing servo is one line), then the keyboard,
the follower, and the log. Ending: the run's duration, ``q`` on the keyboard (exit 0), Ctrl-C or any signal (130),
a leader lost past its tolerance or any failure the loop stops on (1, one line); the follower's torque goes off
and is read back on every path, and both buses are closed.
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path

from felis.cli import output
from felis.cli.args import baud_rate, finite, live_option, trace_option
from felis.controllers.teleop import RAMP_S, JogController, TeleopController, parse_map, resolve_map
from felis.errors import ParameterError

LEADER = "arm-leader"  # the default leader description
KEYS_HELP = ("keys: 1-9 select a joint, x/y/z a tool axis (through the learned IK); + - or the arrows move it by a "
             "step; o/c open/close the gripper; q or Esc ends the run (Ctrl-C too)")
MAX_DURATION = 24 * 3600.0


def register(sub) -> None:
    """Add ``felis teleop``."""
    p = sub.add_parser("teleop", help="teleoperate the arm: a leader arm drives a follower, or jog it by keyboard")
    p.add_argument("--robot", default="arm", help="the follower: robot name or a description .toml (default arm)")
    p.add_argument("--backend", default="sim", choices=["sim", "dxl"],
                   help="sim: the follower in MuJoCo; dxl: Dynamixel servos on --port (default sim)")
    p.add_argument("--port", help="dxl: the follower's serial device, or 'virtual' (a virtual bus backed by MuJoCo)")
    p.add_argument("--baud", type=baud_rate, default=1_000_000, help="dxl: the follower's baud rate (default 1000000)")
    p.add_argument("--robot-id", help="dxl: the follower's calibration by robot id (`felis calibrate --id`)")
    p.add_argument("--calibration", type=Path, metavar="FILE", help="dxl: the follower's calibration file")
    p.add_argument("--yes", action="store_true", help="dxl: apply the follower's EEPROM setting differences without "
                   "asking")
    p.add_argument("--leader-port", help="the leader arm's serial device (its own bus)")
    p.add_argument("--leader-robot", default=LEADER, help=f"the leader's description (default {LEADER})")
    p.add_argument("--leader-baud", type=baud_rate, default=1_000_000, help="the leader's baud rate (default 1000000)")
    p.add_argument("--leader-calibration", type=Path, metavar="FILE", help="the leader's calibration file")
    p.add_argument("--map", metavar="L=F[*S+O],…",
                   help="leader joint → follower joint, optionally scaled and offset: follower = S·leader + O "
                        "(default: the joints with the same names, else the same order)")
    p.add_argument("--ramp", type=finite, default=RAMP_S,
                   help=f"seconds to blend from the follower's pose to the leader's at the start (default {RAMP_S:g})")
    p.add_argument("--keyboard", action="store_true",
                   help="jog the follower from the keyboard instead: 1-9 joint, x/y/z tool axis (learned IK), +/- or "
                        "arrows to move, o/c gripper, q to quit")
    p.add_argument("--rate", type=finite, help="control rate in Hz (default: the follower description's)")
    p.add_argument("--duration", type=finite, default=3600.0, help="seconds before the run ends by itself "
                   "(default 3600; Ctrl-C ends it earlier)")
    p.add_argument("--log", type=Path, help="write an MCAP log here (.mcap): the follower and the leader")
    live_option(p)
    trace_option(p)  # the follower's bus (dxl)
    p.add_argument("--json", action="store_true", help="print the run report as JSON")
    p.set_defaults(func=cmd_teleop)


# ------------------------------------------------------------------------------------------------ checks
def _check(args) -> None:
    """Every option on its own, before anything is loaded or opened."""
    from felis.files import check_target
    if args.backend == "sim" and args.port is not None:
        raise ParameterError("--port is the follower's bus: it needs --backend dxl")
    if args.backend == "sim" and (args.calibration is not None or args.robot_id is not None):
        raise ParameterError("--calibration and --robot-id calibrate the follower's servos: they need --backend dxl")
    if args.calibration is not None and args.robot_id is not None:
        raise ParameterError("give the follower's calibration as --robot-id or --calibration, not both")
    if args.backend == "sim" and args.trace is not None:
        raise ParameterError("--trace records the follower's Dynamixel bus: it needs --backend dxl")
    if args.keyboard and args.leader_port is not None:
        raise ParameterError("--keyboard jogs the follower by itself: give --keyboard or --leader-port, not both")
    if not args.keyboard and args.leader_port is None:
        raise ParameterError("give --leader-port PATH (the leader arm's bus; `felis find-port`) or --keyboard")
    if args.keyboard and (args.map is not None or args.leader_calibration is not None):
        raise ParameterError("--map and --leader-calibration belong to a leader arm (--leader-port)")
    if args.backend == "dxl" and args.leader_port is not None and args.port == args.leader_port:
        raise ParameterError(f"the leader and the follower are both on {args.port}: each needs its own bus")
    if args.rate is not None and not 1 <= args.rate <= 1000:
        raise ParameterError(f"--rate must be within 1…1000 Hz, got {args.rate:g}")
    if not 0 < args.duration <= MAX_DURATION:
        raise ParameterError(f"--duration must be within 0…{MAX_DURATION:g} s, got {args.duration:g}")
    if not (math.isfinite(args.ramp) and 0 <= args.ramp <= 10):
        raise ParameterError(f"--ramp must be within 0…10 s, got {args.ramp:g}")
    if args.live is not None:
        from felis.logs.live import parse_address

        parse_address(args.live)
    if args.log is not None:
        if args.log.suffix.lower() != ".mcap":
            raise ParameterError(f"{args.log}: the log file must end in .mcap")
        check_target(args.log, "run log", ParameterError)


def _calibration(path: Path | None, spec):
    """A calibration file for ``spec`` as `DynamixelRobot` takes it (None without one)."""
    if path is None:
        return None
    from felis.calib.calfile import load

    return load(path, spec).for_robot(spec)


# ------------------------------------------------------------------------------------------------ the command
def cmd_teleop(args) -> int:
    from felis.cli.results import exit_code
    from felis.spec import load_spec

    _check(args)
    spec = load_spec(args.robot)
    leader_spec = mapping = leader_cal = None
    if not args.keyboard:
        leader_spec = load_spec(args.leader_robot)
        mapping = resolve_map(parse_map(args.map) if args.map is not None else None, leader_spec, spec)
        leader_cal = _calibration(args.leader_calibration, leader_spec)
    if args.calibration is not None or args.robot_id is not None:  # a bad file is one line before anything opens
        from felis.calib.calfile import calibration_path, load

        load(args.calibration or calibration_path(spec.name, args.robot_id), spec)
    follower_cal = None  # read with the follower's EEPROM check when it opens (`_follower`)
    res = _run(args, spec, leader_spec, mapping, leader_cal, follower_cal)
    if args.json:
        output.print_json(res.as_dict())
    else:
        from felis.cli.results import print_result

        console = output.console()
        print_result(res, console)
        console.print(summary_line(res.controller))
    return exit_code(res.report)


def summary_line(summary: dict | None) -> str:
    """One line on how the follower tracked (leader) or what was typed (keyboard)."""
    if not summary:
        return "teleop: nothing to report"
    if summary.get("source") == "keyboard":
        return (f"jog: {summary['presses']} keys ({summary['ignored']} ignored), ended in {summary['mode']} space"
                + (f", {summary['unreachable_frames']} IK frames unreachable" if summary["unreachable_frames"] else ""))
    if "lag_ms" not in summary:
        return (f"teleop: {summary.get('samples', 0)} ticks after the ramp: too few to measure the follower's lag "
                f"(leader reads failed: {summary.get('leader_failed_reads', 0)})")
    deg = summary.get("rms_deg_after_lag")
    err = f"{deg:.2f}°" if deg is not None else f"{summary['rms_after_lag']:.4g}"
    return (f"teleop: mapping {summary['mapping']}; follower lag {summary['lag_ms']:.0f} ms, RMS error {err} after "
            f"removing it ({summary['samples']} ticks; leader reads failed: {summary.get('leader_failed_reads', 0)})")


class _LeaderLog:
    """Loop monitor: the leader's joint positions on ``/leader`` at each tick (its own names)."""

    def __init__(self, log, controller, names):
        self.log, self.controller, self.names = log, controller, list(names)

    def __call__(self, state, command) -> None:
        q = self.controller.leader_q
        if q is not None:
            self.log.message("/leader", state.t, {"joints": self.names, "position": [float(v) for v in q]})


def _run(args, spec, leader_spec, mapping, leader_cal, follower_cal):
    from felis.cli.episode import EpisodeResult
    from felis.drivers.dynamixel.leader import LeaderArm
    from felis.logs.runlog import RunLog
    from felis.loop import run_loop

    files: dict[str, str] = {}
    warnings: list[str] = []
    progress = None if args.json else output.LoopProgress(f"{spec.name} teleop", args.duration)
    with contextlib.ExitStack() as stack:
        leader = None
        if leader_spec is not None:
            leader = stack.enter_context(LeaderArm(leader_spec, args.leader_port, args.leader_baud,
                                                   calibration=leader_cal))
            controller = TeleopController(mapping, leader.read, ramp=args.ramp)
        else:
            from felis.cli.keys import Keyboard

            keyboard = stack.enter_context(Keyboard())
            controller = JogController(keyboard.keys, _solver(spec))
            if not args.json:
                output.console().print(KEYS_HELP)
        robot, scene, poses, meta = _follower(args, spec, follower_cal, stack, warnings)
        log = None
        try:
            monitors = [] if progress is None else [progress]
            if args.log is not None or args.live is not None:
                if leader is not None:
                    meta.update(leader=leader_spec.name, leader_port=args.leader_port, mapping=mapping.describe())
                live = None
                if args.live is not None:
                    from felis.logs.live import LiveView

                    live = stack.enter_context(LiveView(args.live))
                    output.live(live.url)
                log = RunLog(args.log, spec, meta, scene=scene, poses=poses, live=live)
                if leader is not None:
                    monitors.append(_LeaderLog(log, controller, leader_spec.names))
            until = (lambda state: controller.done) if args.keyboard else None
            report = run_loop(robot, controller, duration=args.duration, rate_hz=args.rate, clock="wall", log=log,
                              monitors=monitors, until=until)
        except BaseException:
            if log is not None:
                log.close({"error": "run aborted"})
            raise
        finally:
            if progress is not None:
                progress.stop()
        summary = controller.summary()
        if leader is not None:
            summary["leader_failed_reads"] = leader.failed
        if log is not None:
            log.close({"run": report.as_dict(), "controller": summary})
            if args.log is not None:
                files["log"] = str(args.log)
    return EpisodeResult(report=report, landing=None, drop=None, files=files, warnings=warnings, controller=summary)


def _solver(spec):
    """The learned IK pipeline for tool-space jogging, where the follower has the arm's joints (else None)."""
    from felis import armkin

    if not set(armkin.JOINTS) <= set(spec.names):
        return None
    from felis.learning.ik.solver import IkSolver

    return IkSolver.load()


def _follower(args, spec, calibration, stack: contextlib.ExitStack, warnings: list[str]):
    """The follower robot, connected, with the log's scene, poses and metadata."""
    meta = {"controller": "teleop", "backend": args.backend, "source": "keyboard" if args.keyboard else "leader"}
    if args.backend == "sim":
        from felis.sim import MujocoRobot
        from felis.sim.scene import MujocoPoses, model_scene

        robot = stack.enter_context(MujocoRobot(spec))
        return robot, model_scene(robot.model), MujocoPoses(robot), meta
    from felis.drivers.dynamixel.robot import DynamixelRobot
    from felis.drivers.dynamixel.trace import PacketTrace, TracedBus
    from felis.drivers.ports import open_ports
    from felis.sim.scene import hardware_view

    trace = None if args.trace is None else stack.enter_context(PacketTrace(args.trace))  # closed after the robot
    opened = stack.enter_context(open_ports(args.port, robot=args.robot, baud=args.baud, bus=False, sim=True))
    # `felis run`'s checks: the calibration (--robot-id or --calibration) and the EEPROM settings, as it does them
    from felis.cli.episode import Episode, _connect_checks

    ep = Episode(robot=spec.name, controller="teleop", backend="dxl", port=opened.name, baud=args.baud,
                 robot_id=args.robot_id, calibration=args.calibration, yes=args.yes)
    calibration = _connect_checks(ep, spec, opened.port, trace)
    warnings.extend(ep.warnings)
    bus = None if trace is None else TracedBus(opened.port, args.baud, trace=trace)
    robot = stack.enter_context(DynamixelRobot(spec, opened.port, args.baud, calibration=calibration, bus=bus))
    warnings.extend(robot.warnings)
    meta.update(port=opened.name, baud=args.baud)
    view = hardware_view(spec)
    scene, poses = (None, None) if view is None else view
    return robot, scene, poses, meta
