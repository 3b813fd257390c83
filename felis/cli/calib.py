"""Calibration commands: ``felis setup-motors``, ``felis calibrate``, ``felis calibration …``,
``felis check-eeprom``. All of them take ``--yes`` (no prompts: for scripts) and ``--json``.

The work is done by `felis.calib`; this module parses arguments, opens the bus (``--port virtual``
spawns a virtual bus for the robot) and prints.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from felis.cli import output
from felis.cli.args import baud_rate, json_option, open_bus, trace_option
from felis.errors import CalibrationError, ParameterError


def _names(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected joint names like fl_pitch,fl_roll, got {text!r}")
    return names


def _operator(args):
    from felis.calib.operator import ConsoleOperator

    return ConsoleOperator(yes=args.yes, sweep_s=getattr(args, "sweep_s", 10.0), quiet=args.json)


def _emit(args, obj, human) -> None:
    """JSON with --json, else ``human`` through the console (text with markup, or a table)."""
    output.out(args, obj, human, rich=True)


def _spec(args):
    from felis.spec import load_spec

    return load_spec(args.robot)


def _path(args, spec) -> Path:
    from felis.calib.calfile import calibration_path, check_robot_id

    if getattr(args, "file", None):
        if args.id is not None:
            check_robot_id(args.id)
        return Path(args.file)
    if args.id is None:
        raise ParameterError("give the robot's id (--id NAME): a calibration belongs to one physical robot")
    return calibration_path(spec.name, args.id)


def _bus(args):
    """The bus on ``--port`` (`felis.drivers.ports.Ports`); ``virtual`` spawns one for ``--robot`` (backed by
    MuJoCo when the IMU is wanted)."""
    args.robot = args.robot or "cat"
    return open_bus(args, sim=bool(getattr(args, "imu", False) or getattr(args, "imu_only", False)))


def _diff_table(diffs, title: str, left: str, right: str):
    from rich.table import Table
    t = Table(title=title)
    for col in ("joint", "ID", "item", left, right):
        t.add_column(col)
    for d in diffs:
        t.add_row(d.joint, str(d.servo_id), d.item, str(d.motor), str(d.expected))
    return t


# ----------------------------------------------------------------------------- setup-motors
def cmd_setup_motors(args) -> int:
    from felis.calib.setup import select_joints, setup_motors

    spec = _spec(args)
    select_joints(spec, args.motors)  # check names before touching the bus
    baud = args.baud
    args.baud = 57_600  # the bus starts at the factory rate; set-up searches every rate anyway
    with _bus(args) as ports:
        bus = ports.bus
        done = setup_motors(bus, spec, _operator(args), joints=args.motors, baud=baud)
    _emit(args, {"robot": spec.name, "motors": [d.as_dict() for d in done]},
          f"{len(done)} servo(s) set up: " + ", ".join(f"{d.joint} = ID {d.id}" for d in done))
    return 0


# ----------------------------------------------------------------------------- calibrate
def cmd_calibrate(args) -> int:
    from felis.calib.joints import calibrate

    spec = _spec(args)
    if args.id is None:
        raise ParameterError("give the robot's id (--id NAME): a calibration belongs to one physical robot")
    path = _path(args, spec)
    from felis.calib.setup import select_joints

    select_joints(spec, args.joints)  # names checked before the bus opens
    op = _operator(args)
    out: dict = {"robot": spec.name, "robot_id": args.id, "file": str(path)}
    with _bus(args) as ports:
        bus = ports.bus
        if not args.imu_only:
            cal, written = calibrate(bus, spec, args.id, op, joints=args.joints, path=path, sweep=not args.no_sweep)
            out["joints"] = {n: {"offset": jc.offset, "range": list(jc.range)} for n, jc in cal.joints.items()
                             if args.joints is None or n in args.joints}
        if args.imu or args.imu_only:
            out["imu"] = _calibrate_imu(args, spec, path, op, ports.imu_port)
    _emit(args, out, f"calibration of {spec.name} {args.id!r} saved to {path}")
    return 0


def _calibrate_imu(args, spec, path: Path, op, port: str | None) -> dict:
    from felis.calib.calfile import load, save
    from felis.calib.imu import estimate_mounting
    from felis.drivers.imu import ImuReader

    if spec.sensors.imu is None:
        raise ParameterError(f"the {spec.name} has no IMU in its description")
    if not port:
        raise ParameterError("the IMU step needs --imu-port PATH (the BNO08x's UART-RVC serial port)")
    cal = load(path, spec)  # joints first: the IMU goes into a complete file
    op.wait(f"Stand the {spec.name} still on a level surface")
    with ImuReader(port) as reader:
        m = estimate_mounting(reader, seconds=args.imu_s)
    from dataclasses import replace

    save(replace(cal, imu=m.to_dict()), path)
    op.say(f"IMU mounting: tilt {m.tilt_deg:.2f}°, gyro bias {[round(float(b), 5) for b in m.gyro_bias]} rad/s")
    return m.to_dict()


# ----------------------------------------------------------------------------- calibration …
def cmd_cal_show(args) -> int:
    from rich.table import Table

    from felis.calib.calfile import horn_of_tick, load, q_of_tick

    spec = _spec(args)
    path = _path(args, spec)
    cal = load(path, spec, complete=False)
    if args.json:
        output.print_json({"file": str(path), **cal.to_dict()})
        return 0
    t = Table(title=f"{cal.robot} {cal.robot_id!r}: {path} ({cal.created})")
    for col in ("joint", "ID", "model", "fw", "offset", "dir", "range (ticks)", "range (joint)"):
        t.add_column(col)
    for j in spec.joints:
        jc = cal.joints.get(j.name)
        if jc is None:
            t.add_row(j.name, str(j.servo_id), "[red]not calibrated[/]", "", "", "", "", "")
            continue
        lo, hi = sorted((q_of_tick(j, jc.range[0]), q_of_tick(j, jc.range[1])))
        unit, k = ("mm", 1000.0) if j.kind == "prismatic" else ("°", 57.29577951308232)
        off_deg = horn_of_tick(2048 + jc.offset) * 57.29577951308232
        t.add_row(j.name, str(jc.id), jc.model, str(jc.firmware), f"{jc.offset:+d} ({off_deg:+.1f}°)",
                  f"{jc.direction:+d}", f"{jc.range[0]}…{jc.range[1]}", f"{lo * k:+.1f}…{hi * k:+.1f}{unit}")
    c = output.console()
    c.print(t)
    c.print(f"IMU: {cal.imu if cal.imu else 'not calibrated (felis calibrate --imu-only)'}")
    return 0


def cmd_cal_diff(args) -> int:
    from felis.calib.calfile import load
    from felis.calib.eeprom import diff_calibration

    spec = _spec(args)
    cal = load(_path(args, spec), spec, complete=False)
    with _bus(args) as ports:
        bus = ports.bus
        diffs = diff_calibration(bus, spec, cal)
    _emit(args, {"same": not diffs, "differences": [d.as_dict() for d in diffs]},
          "motors and file agree" if not diffs else _diff_table(diffs, "calibration: motors vs file", "motors",
                                                                 "file"))
    return 0


def cmd_cal_apply(args) -> int:
    from felis.calib.calfile import load
    from felis.calib.eeprom import apply_calibration, diff_calibration

    spec = _spec(args)
    path = _path(args, spec)
    cal = load(path, spec, complete=False)
    op = _operator(args)
    with _bus(args) as ports:
        bus = ports.bus
        diffs = diff_calibration(bus, spec, cal)
        if not diffs:
            _emit(args, {"same": True, "applied": []}, "motors and file agree: nothing to apply")
            return 0
        if not args.json:
            op.say(_diff_table(diffs, "calibration: motors vs file", "motors", "file"))
        target = "the motors' EEPROM (torque goes off)" if args.prefer == "file" else str(path)
        if not op.confirm(f"write {len(diffs)} difference(s) into {target}?"):
            raise CalibrationError("not applied: the operator declined")
        done, _ = apply_calibration(bus, spec, cal, args.prefer, path)
    _emit(args, {"same": False, "prefer": args.prefer, "applied": [d.as_dict() for d in done]},
          f"applied {len(done)} difference(s), preferring the {args.prefer}")
    return 0


def cmd_cal_export(args) -> int:
    from felis.calib.calfile import copy_out, load

    spec = _spec(args)
    path = _path(args, spec)
    cal = load(path, spec)
    if args.out == "-":
        output.print_json(cal.to_dict())
        return 0
    dst = copy_out(path, args.out)
    _emit(args, {"exported": str(dst)}, f"exported {path} → {dst}")
    return 0


def cmd_cal_import(args) -> int:
    from dataclasses import replace

    from felis.calib.calfile import calibration_path, check_robot_id, load, save
    from felis.spec import load_spec

    src = Path(args.source)
    cal = load(src)
    spec = load_spec(args.robot or cal.robot)
    if args.id is not None:
        cal = replace(cal, robot_id=check_robot_id(args.id))
    cal.check(spec, str(src))
    dst = calibration_path(spec.name, cal.robot_id)
    if dst.exists() and not _operator(args).confirm(f"replace {dst} (the current one is kept as a backup)?"):
        raise CalibrationError("not imported: the operator declined")
    save(cal, dst)
    _emit(args, {"imported": str(dst), "robot": spec.name, "robot_id": cal.robot_id}, f"imported {src} → {dst}")
    return 0


def cmd_cal_list(args) -> int:
    from felis.calib.calfile import config_dir, stale_temps

    root = config_dir()
    files = sorted(f for f in root.glob("*/*.json") if not f.name.endswith(".poses.json")) if root.is_dir() else []
    rows = [{"robot": f.parent.name, "robot_id": f.stem, "file": str(f)} for f in files]
    temps = [str(t) for d in (root.glob("*") if root.is_dir() else []) for t in stale_temps(d)]
    _emit(args, {"dir": str(root), "calibrations": rows, "stale_temps": temps},
          "\n".join([f"{r['robot']:6} {r['robot_id']:20} {r['file']}" for r in rows] or [f"none in {root}"]))
    return 0


# ----------------------------------------------------------------------------- check-eeprom
def cmd_check_eeprom(args) -> int:
    spec = _spec(args)
    cal = None
    if args.id is not None or args.file:
        from felis.calib.calfile import load

        cal = load(_path(args, spec), spec)
    with _bus(args) as ports:
        bus = ports.bus
        diffs = eeprom_check(bus, spec, cal, _operator(args), show=not args.json)
    _emit(args, {"ok": not diffs, "differences": [d.as_dict() for d in diffs], "applied": bool(diffs)},
          "EEPROM settings as expected" if not diffs else f"applied {len(diffs)} setting(s)")
    return 0


def eeprom_check(bus, spec, cal, op, *, show: bool = True) -> list:
    """Check the EEPROM settings; show the differences and apply them when the operator agrees.

    Used by ``felis check-eeprom`` and when ``felis run --backend dxl`` connects. Declining leaves the
    servos as they are and stops (`CalibrationError`).
    """
    from felis.calib.eeprom import apply, check_settings

    diffs = check_settings(bus, spec, cal)
    if not diffs:
        return []
    if show:
        op.say(_diff_table(diffs, "EEPROM settings: motors vs expected", "motors", "expected"))
    if not op.confirm(f"write {len(diffs)} EEPROM setting(s) (torque goes off on those servos)?"):
        raise CalibrationError(f"{len(diffs)} EEPROM setting(s) differ and were not applied "
                               "(`felis check-eeprom --yes` applies them)")
    apply(bus, spec, diffs)
    return diffs


# ----------------------------------------------------------------------------- parser
def register(sub) -> None:
    """Add the calibration commands to the ``felis`` parser."""

    def common(sp, *, bus: bool = True, need_id: bool = False):
        sp.add_argument("--robot", default="cat", help="robot name (cat, arm) or a description .toml (default cat)")
        if bus:
            sp.add_argument("--port", help="serial device, or 'virtual' for a virtual bus (default $FELIS_PORT)")
            sp.add_argument("--baud", type=baud_rate, default=1_000_000, help="the robot's baud rate (default 1000000)")
            trace_option(sp)
        sp.add_argument("--id", required=need_id, help="the robot's id: names its calibration file")
        sp.add_argument("--file", help="calibration file path (default: the config directory, by robot and id)")
        sp.add_argument("--yes", action="store_true", help="no prompts: answer yes and go on (for scripts)")
        json_option(sp)

    sm = sub.add_parser("setup-motors", help="give new servos their joint's ID and baud rate, one at a time")
    sm.add_argument("--robot", default="cat", help="robot name (default cat)")
    sm.add_argument("--motors", type=_names, help="only these joints (comma-separated); default all")
    sm.add_argument("--port", help="serial device, or 'virtual' (default $FELIS_PORT)")
    sm.add_argument("--baud", type=baud_rate, default=1_000_000, help="baud rate to set (default 1000000)")
    sm.add_argument("--yes", action="store_true", help="no prompts (the servo is already the only one connected)")
    trace_option(sm)
    json_option(sm)
    sm.set_defaults(func=cmd_setup_motors)

    ca = sub.add_parser("calibrate", help="record joint zeros (reference pose) and ranges (sweep); IMU mounting")
    common(ca, need_id=True)
    ca.add_argument("--joints", type=_names, help="only these joints (the rest of the file is kept)")
    ca.add_argument("--no-sweep", action="store_true", help="keep the description's limits as ranges")
    ca.add_argument("--sweep-s", type=float, default=10.0, help="with --yes: sweep recording time (default 10 s)")
    ca.add_argument("--imu", action="store_true", help="then estimate the IMU mounting (cat still, level)")
    ca.add_argument("--imu-only", action="store_true", help="only the IMU mounting step")
    ca.add_argument("--imu-port", help="serial device of the BNO08x (UART-RVC)")
    ca.add_argument("--imu-s", type=float, default=2.0, help="IMU averaging time (default 2 s)")
    ca.set_defaults(func=cmd_calibrate)

    cal = sub.add_parser("calibration", help="calibration files: show, diff, apply, export, import, list")
    cs = cal.add_subparsers(dest="action", metavar="ACTION")

    def missing(_args) -> int:
        cal.print_usage(sys.stderr)
        print(f"{cal.prog}: error: choose an action: show, diff, apply, export, import, list", file=sys.stderr)
        return 2

    cal.set_defaults(func=missing)
    sh = cs.add_parser("show", help="print a calibration file")
    common(sh, bus=False)
    sh.set_defaults(func=cmd_cal_show)
    df = cs.add_parser("diff", help="compare a calibration file with what the motors hold")
    common(df)
    df.set_defaults(func=cmd_cal_diff)
    ap = cs.add_parser("apply", help="resolve differences: --prefer file (write motors) or motors (rewrite file)")
    common(ap)
    ap.add_argument("--prefer", required=True, choices=["file", "motors"], help="which side wins")
    ap.set_defaults(func=cmd_cal_apply)
    ex = cs.add_parser("export", help="copy a calibration file out ('-' for standard output)")
    common(ex, bus=False)
    ex.add_argument("out", help="destination path, or -")
    ex.set_defaults(func=cmd_cal_export)
    im = cs.add_parser("import", help="check a calibration file and store it in the config directory")
    im.add_argument("source", help="calibration file to import")
    im.add_argument("--robot", help="robot (default: the file's)")
    im.add_argument("--id", help="store under this robot id instead of the file's")
    im.add_argument("--yes", action="store_true", help="replace an existing calibration without asking")
    json_option(im)
    im.set_defaults(func=cmd_cal_import)
    ls = cs.add_parser("list", help="calibration files in the config directory")
    ls.add_argument("--yes", action="store_true", help="accepted for symmetry (list never asks)")
    json_option(ls)
    ls.set_defaults(func=cmd_cal_list)

    ce = sub.add_parser("check-eeprom", help="compare servo EEPROM settings with the robot's; apply on confirmation")
    common(ce)
    ce.set_defaults(func=cmd_check_eeprom)
