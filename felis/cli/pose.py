"""``felis pose capture|list|show|delete|play``: teaching a robot poses by hand and playing them back.

``capture NAME`` turns torque off (read back), waits while the operator poses the robot (Enter; ``--after S`` or
``--yes`` for no keyboard), reads the calibrated joint positions (`felis.calib.teach`) and stores them in the robot's
pose file beside its calibration (`felis.calib.poses`); torque stays off. ``list``, ``show`` and ``delete`` read and
edit that file. ``play NAME… --durations T,…`` runs minimum-jerk keyframes (`felis.controllers.keyframes`) through
the control loop and its safety layer, in MuJoCo (``--backend sim``) or on the servos (``--backend dxl --port``),
with the same report, log and shutdown as ``felis run`` (`felis.cli.episode`). Poses come from the pose file first,
then from the description's ``[poses.NAME]``.

Every input (names, durations, files, the pose file's contents) is checked before a port opens or a file is
written, so bad input is one line and changes nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import math
from pathlib import Path

from felis.cli import output
from felis.cli.args import baud_rate, finite, group, json_option, live_option, trace_option
from felis.errors import CalibrationError, ParameterError

DEFAULT_DURATION = 2.0  # s per move when --durations is not given
DEFAULT_SETTLE = 0.5  # s holding the last pose before the run ends


def durations(text: str) -> list[float]:
    """``"2,1.5"`` -> [2.0, 1.5]: seconds, each finite and > 0."""
    out = []
    for part in text.split(","):
        try:
            v = float(part)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected seconds like 2,1.5, got {text!r}") from None
        if not (math.isfinite(v) and 0 < v <= 3600):
            raise argparse.ArgumentTypeError(f"each duration must be within 0…3600 s (not 0), got {part.strip()!r}")
        out.append(v)
    return out


def register(sub) -> None:
    """Add ``felis pose`` and its sub-commands."""
    g = group(sub, "pose", "teach poses by hand, list them, play them back", "pose_command",
              "capture|list|show|delete|play")

    cap = g.add_parser("capture", help="torque off, pose the robot by hand, store the pose")
    cap.add_argument("name", help="the pose's name (letters, digits, _ . -)")
    _robot_options(cap)
    _port_options(cap)
    cap.add_argument("--force", action="store_true",
                     help="store a pose named like one of the description's (it overrides it for this robot)")
    cap.add_argument("--after", type=finite, metavar="S", help="read the pose S seconds after torque goes off "
                     "(no Enter to press)")
    cap.add_argument("--yes", action="store_true", help="read the pose at once (scripts; the robot is already posed)")
    json_option(cap)
    cap.set_defaults(func=cmd_capture)

    ls = g.add_parser("list", help="the robot's poses: taught (pose file) and the description's")
    _robot_options(ls)
    json_option(ls)
    ls.set_defaults(func=cmd_list)

    sh = g.add_parser("show", help="one pose's joint positions")
    sh.add_argument("name")
    _robot_options(sh)
    json_option(sh)
    sh.set_defaults(func=cmd_show)

    de = g.add_parser("delete", help="delete a taught pose (the previous file is kept as .bak)")
    de.add_argument("name")
    _robot_options(de)
    json_option(de)
    de.set_defaults(func=cmd_delete)

    pl = g.add_parser("play", help="move through poses (minimum-jerk keyframes) through the safety layer")
    pl.add_argument("names", nargs="+", metavar="NAME", help="poses in order: taught ones first, else the "
                    "description's")
    pl.add_argument("--durations", type=durations, metavar="T,…",
                    help="seconds of each move, the first from the present pose (one value: every move; default "
                         f"{DEFAULT_DURATION:g})")
    pl.add_argument("--settle", type=finite, default=DEFAULT_SETTLE, metavar="S",
                    help=f"seconds holding the last pose before torque goes off (default {DEFAULT_SETTLE:g})")
    _robot_options(pl)
    pl.add_argument("--backend", default="sim", choices=["sim", "dxl", "dynamixel"],
                    help="sim: MuJoCo; dxl: Dynamixel servos on --port (default sim)")
    _port_options(pl)
    pl.add_argument("--yes", action="store_true", help="dxl: apply EEPROM setting differences without asking")
    pl.add_argument("--log", type=Path, help="write an MCAP log here (.mcap)")
    live_option(pl)
    pl.add_argument("--rate", type=finite, help="control rate in Hz (default: the description's)")
    pl.add_argument("--clock", choices=["sim", "wall"], default="sim",
                    help="sim backend: as fast as possible (sim) or real time (wall); dxl always runs on the wall "
                         "clock")
    json_option(pl)
    pl.set_defaults(func=cmd_play)


def _robot_options(p) -> None:
    p.add_argument("--robot", default="cat", help="robot name (cat, arm) or a description .toml (default cat)")
    p.add_argument("--robot-id", "--id", dest="robot_id", metavar="ID",
                   help="the robot's id (`felis calibrate --id`): its pose file lies beside its calibration")
    p.add_argument("--poses", type=Path, metavar="FILE", help="a pose file instead of the robot id's")


def _port_options(p) -> None:
    p.add_argument("--port", help="serial device, or 'virtual' for a virtual bus (default $FELIS_PORT)")
    p.add_argument("--baud", type=baud_rate, default=1_000_000, help="baud rate (default 1000000)")
    trace_option(p)


# ----------------------------------------------------------------------------- the pose file
def _spec(args):
    from felis.spec import load_spec

    return load_spec(args.robot)


def _source(args, spec, *, need_id: bool):
    """(path, pose file or None, robot id or None) from ``--poses``/``--robot-id``; the file is checked against
    ``spec`` and the id."""
    from felis.calib.poses import load, poses_path

    if args.poses is None and args.robot_id is None:
        if need_id:
            raise ParameterError("give the robot's id (--robot-id NAME): taught poses belong to one physical robot, "
                                 "read through its calibration")
        return None, None, None
    path = args.poses if args.poses is not None else poses_path(spec.name, args.robot_id)
    pf = load(path, spec, robot_id=args.robot_id, missing_ok=True)
    robot_id = args.robot_id or (pf.robot_id if pf is not None else None)
    if robot_id is None and need_id:
        raise ParameterError(f"{path} does not exist yet: give --robot-id NAME for the new pose file")
    if robot_id is not None:
        from felis.calib.calfile import check_robot_id

        check_robot_id(robot_id)
    return path, pf, robot_id


def _joints_text(spec, q) -> str:
    parts = []
    for j, v in zip(spec.joints, q, strict=True):
        parts.append(f"{j.name} {v * 1000:+.1f} mm" if j.kind == "prismatic" else
                     f"{j.name} {math.degrees(v):+.1f}°")
    return ", ".join(parts)


# ----------------------------------------------------------------------------- capture
def cmd_capture(args) -> int:
    from felis.calib.operator import ConsoleOperator
    from felis.calib.poses import PoseFile, check_pose_name, save, tick_in_joint_units
    from felis.calib.teach import capture
    from felis.drivers.dynamixel.robot import DynamixelRobot
    from felis.drivers.dynamixel.trace import PacketTrace, TracedBus
    from felis.drivers.ports import is_virtual, open_ports, resolve
    from felis.files import check_target

    spec = _spec(args)
    name = check_pose_name(args.name)
    path, pf, robot_id = _source(args, spec, need_id=True)
    if name in spec.poses and not args.force:
        raise ParameterError(f"{name!r} is a pose of the {spec.name}'s description: choose another name, or give "
                             f"--force to store a taught {name!r} that overrides it for {robot_id!r}")
    if args.after is not None and not 0 <= args.after <= 600:
        raise ParameterError(f"--after must be within 0…600 s, got {args.after:g}")
    port = resolve(args.port)
    cal = None
    if not is_virtual(port):  # a virtual bus's servos are mounted true: nothing to calibrate
        cal = _calibration(spec, robot_id)
    check_target(Path(path), "pose file", CalibrationError)
    op = ConsoleOperator(yes=args.yes, quiet=args.json)
    after = args.after if args.after is not None else (0.0 if args.yes else None)
    with contextlib.ExitStack() as stack:
        trace = None if args.trace is None else stack.enter_context(PacketTrace(args.trace))  # closed last
        opened = stack.enter_context(open_ports(port, robot=spec.name, baud=args.baud, bus=False))
        bus = None if trace is None else TracedBus(opened.port, args.baud, trace=trace)
        robot = DynamixelRobot(spec, opened.port, args.baud, calibration=cal, bus=bus)
        with robot:
            got = capture(robot, op, name, after_s=after)
        verified = robot.torque_off_verified
    tick = tick_in_joint_units(spec)
    outside = [f"{j.name} = {v:+.4f} (limits {j.lower:+.4f}…{j.upper:+.4f})"
               for j, v, t in zip(spec.joints, got.q, tick, strict=True) if not j.lower - t <= v <= j.upper + t]
    if outside:
        raise CalibrationError(f"pose {name!r} not stored: {'; '.join(outside)} past the description's limits; "
                               "move the joint back within them and capture again")
    replaced = pf is not None and name in pf.poses
    pf = (pf or PoseFile(robot=spec.name, robot_id=robot_id)).with_pose(spec, name, got.q)
    save(pf, path)
    created, joints = pf.poses[name]
    result = {"robot": spec.name, "robot_id": robot_id, "pose": name, "created": created, "joints": joints,
              "ticks": got.ticks, "file": str(path), "replaced": replaced, "torque_off_verified": verified}
    human = (f"{'replaced' if replaced else 'captured'} pose {name!r} of {spec.name} {robot_id!r}: "
             f"{_joints_text(spec, got.q)}\nsaved to {path}; torque off" + (" (read back)" if verified else ""))
    output.out(args, result, human)
    if not verified:
        output.error("torque off could not be verified when the port closed: check the servos (`felis torque off`)")
        return output.EXIT_ERROR
    return 0


def _calibration(spec, robot_id: str):
    """The robot's calibration for `DynamixelRobot` (poses are joint angles: they need the joints' zeros)."""
    from felis.calib.calfile import calibration_path, load

    path = calibration_path(spec.name, robot_id)
    if not path.exists():
        raise CalibrationError(f"no calibration file at {path}: poses are joint angles, which need the joints' "
                               f"zeros; run `felis calibrate --robot {spec.name} --id {robot_id}` first")
    return load(path, spec).for_robot(spec)


# ----------------------------------------------------------------------------- list, show, delete
def cmd_list(args) -> int:
    from felis.calib.poses import FILE, known_poses

    spec = _spec(args)
    path, pf, robot_id = _source(args, spec, need_id=False)
    known = known_poses(spec, pf)
    rows = [{"name": n, "source": p.source, "created": p.created,
             "overrides_description": p.source == FILE and n in spec.poses} for n, p in known.items()]
    result = {"robot": spec.name, "robot_id": robot_id, "file": None if path is None else str(path), "poses": rows}
    lines = [f"{r['name']:16} {'taught ' + (r['created'] or '') if r['source'] == FILE else 'description'}"
             + ("  (overrides the description's)" if r["overrides_description"] else "") for r in rows]
    if path is None:
        lines.append("(no --robot-id: the description's poses only)")
    elif pf is None:
        lines.append(f"(no taught poses yet: {path} does not exist)")
    output.out(args, result, "\n".join(lines))
    return 0


def cmd_show(args) -> int:
    from felis.calib.poses import check_pose_name, resolve

    spec = _spec(args)
    check_pose_name(args.name)
    path, pf, robot_id = _source(args, spec, need_id=False)
    (pose,) = resolve(spec, pf, [args.name])
    result = {"robot": spec.name, "robot_id": robot_id, "name": pose.name, "source": pose.source,
              "created": pose.created, "joints": pose.joints(spec)}
    head = f"{pose.name} ({'taught ' + (pose.created or '') if pose.source == 'file' else 'description'})"
    body = [f"  {j.name:14} {v:+.4f} {'m' if j.kind == 'prismatic' else 'rad'}"
            + ("" if j.kind == "prismatic" else f"  {math.degrees(v):+7.2f}°") for j, v in zip(spec.joints, pose.q,
                                                                                               strict=True)]
    output.out(args, result, "\n".join([head, *body]))
    return 0


def cmd_delete(args) -> int:
    from felis.calib.calfile import backup_path
    from felis.calib.poses import check_pose_name, describe, known_poses, save

    spec = _spec(args)
    name = check_pose_name(args.name)
    path, pf, robot_id = _source(args, spec, need_id=True)
    if pf is None or name not in pf.poses:
        known = known_poses(spec, pf)
        if name in spec.poses:
            raise ParameterError(f"{name!r} is a pose of the {spec.name}'s description, not a taught one: only taught "
                                 f"poses can be deleted (known: {describe(known)})")
        raise ParameterError(f"no taught pose {name!r} for the {spec.name} {robot_id!r}; known: {describe(known)}")
    save(pf.without(name), path)
    bak = backup_path(Path(path))
    output.out(args, {"robot": spec.name, "robot_id": robot_id, "deleted": name, "file": str(path),
                      "backup": str(bak)}, f"deleted pose {name!r} from {path} (previous version: {bak})")
    return 0


# ----------------------------------------------------------------------------- play
def cmd_play(args) -> int:
    from felis.calib.poses import resolve
    from felis.cli.results import episode, report
    from felis.controllers.keyframes import peak_speed
    from felis.drivers.ports import is_virtual

    spec = _spec(args)
    backend = "dxl" if args.backend in ("dxl", "dynamixel") else "sim"
    if backend == "sim" and (args.port is not None or args.trace is not None):
        raise ParameterError(f"{'--port' if args.port is not None else '--trace'} needs --backend dxl")
    _, pf, robot_id = _source(args, spec, need_id=False)
    poses = resolve(spec, pf, args.names)
    durs = args.durations or [DEFAULT_DURATION]
    if len(durs) == 1:
        durs = durs * len(poses)
    if len(durs) != len(poses):
        raise ParameterError(f"{len(poses)} pose(s) need {len(poses)} duration(s), the first for the approach from "
                             f"the present pose (or one for every move); --durations gave {len(durs)}")
    if not (math.isfinite(args.settle) and 0 <= args.settle <= 600):
        raise ParameterError(f"--settle must be within 0…600 s, got {args.settle:g}")
    for k in range(1, len(poses)):  # moves between known poses: their speed is known now (the approach's is not)
        speed = peak_speed(poses[k].q - poses[k - 1].q, durs[k])
        over = speed / spec.max_velocity
        worst = int(over.argmax())
        if over[worst] > 1:
            need = durs[k] * over[worst]
            raise ParameterError(f"{poses[k - 1].name} → {poses[k].name} in {durs[k]:g} s moves {spec.names[worst]} "
                                 f"at up to {speed[worst]:.2f}, faster than its {spec.max_velocity[worst]:.2f} per s: "
                                 f"give it at least {math.ceil(need * 10) / 10:g} s")
    dxl_id = None
    if backend == "dxl" and not is_virtual(args.port):
        dxl_id = robot_id  # taught poses are read through this calibration: play them through it too
    res = episode(args, robot=args.robot, controller="keyframes", duration=sum(durs) + args.settle, log=args.log,
                  clock="wall" if backend == "dxl" else args.clock, rate_hz=args.rate, backend=backend, port=args.port,
                  baud=args.baud, robot_id=dxl_id, yes=args.yes, trace=args.trace,
                  controller_options={"poses": [(p.name, p.q) for p in poses], "durations": durs})
    code = report(args, res)
    if not args.json and res.controller is not None:
        s = res.controller
        line = "keyframes: " + " → ".join(f"{n} ({d:g} s)" for n, d in zip(s["keyframes"], s["durations_s"],
                                                                             strict=True))
        fe = s.get("final_error")
        if fe is not None:
            line += f"; last reading vs {s['keyframes'][-1]}: max {fe['max_abs']:.4f} ({fe['joint']})"
        output.console().print(line)
    return code
