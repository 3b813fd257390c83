"""``felis sysid``: identify the simulated servo model of a robot's joints (`felis.calib.sysid`).

::

    felis sysid --robot cat|arm [--joints NAMES] [--backend dxl|sim] [--port PATH|virtual] [--baud B]
                [--rate HZ] [--out FILE] [--record FILE.npz] [--from-recording FILE.npz]
                [--effort-weight W] [--latency-ms MS] [--hold PARAMS] [--yes] [--json]

Records step and chirp responses one joint at a time (others hold), fits per joint the firmware's Position
P, I, D Gain (control-table units), damping, armature, friction loss, torque limit and latency
(`felis.calib.sysid`; ``--hold`` keeps some at their starting values), writes a servo parameter file (default
``sysid-<robot>.json`` here, the gains as ``pid``) that ``felis run --servo-params FILE`` loads, and prints, per
joint, the starting and fitted parameters and the replay's RMS error before and after. ``--port virtual``
spawns a virtual bus backed by MuJoCo with the base held (a floating-base robot hangs on a stand);
``--backend sim`` records MuJoCo directly. Before moving real servos it says what will move and asks
for confirmation unless ``--yes``. Errors are one line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from felis.cli import output
from felis.errors import ParameterError, SysidError


def _names(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected joint or group names like fl_pitch,tail, got {text!r}")
    return names


def _held(text: str) -> list[str]:
    from felis.calib.sysid import PARAMS

    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in PARAMS]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"expected parameters among {', '.join(PARAMS)}, got {text!r}")
    return names


def _joints(spec, names: list[str] | None) -> list[str] | None:
    """Joint names from ``--joints`` (joint or group names, comma-separated), in the description's order."""
    if names is None:
        return None
    out: list[str] = []
    for n in names:
        if n in spec.names:
            out.append(n)
        elif n in spec.groups:
            out.extend(spec.groups[n])
        else:
            raise ParameterError(f"{spec.name} has no joint or group {n!r}; joints: {', '.join(spec.names)}; "
                                 f"groups: {', '.join(spec.groups)}")
    return [n for n in spec.names if n in out]


def _confirm(args, spec, joints, exc, rate) -> None:
    """Tell the operator what will move; ask unless --yes (real servos only)."""
    from felis.calib.sysid import amplitudes, hold_pose
    from felis.drivers import ports

    hold = hold_pose(spec)
    amp = max(amplitudes(spec, j, exc, hold)[1] for j in joints)
    seconds = exc.duration(len(joints))
    stand = " The robot must hang on a stand, base held, every limb free to swing." if spec.name == "cat" else ""
    text = (f"sysid will move {len(joints)} joint(s) of {spec.name} one at a time ({', '.join(joints)}): "
            f"steps up to ±{amp:.2f} rad around the hold pose at full servo speed and a chirp, about {seconds:.0f} s "
            f"at {rate:g} Hz.{stand}")
    real = args.backend == "dxl" and not ports.is_virtual(args.port)
    if not args.json:
        print(text, file=sys.stderr)
    if not real or args.yes:
        return
    if not sys.stdin.isatty():
        raise ParameterError("sysid moves the servos: confirm with --yes (no terminal to ask on)")
    answer = input("continue? [y/N] ")
    if answer.strip().lower() not in ("y", "yes"):
        raise SysidError("cancelled; nothing moved")


def _record(args, spec, joints, exc, bar):
    from felis.calib.sysid import record
    from felis.drivers import ports
    from felis.drivers.dynamixel.robot import DynamixelRobot

    servo = None
    if args.virtual_servo_params:
        from felis.sim.servo_file import load_servo_params

        servo = load_servo_params(args.virtual_servo_params, spec)
    rate = args.rate or 200.0
    progress = (lambda f: bar("recording", f)) if bar.enabled else None
    if args.backend == "sim":
        from felis.sim.robot import MujocoRobot

        with MujocoRobot(spec, servo=servo, fixed_base=True) as robot:
            return record(robot, joints, rate_hz=rate, exc=exc, backend="sim", progress=progress)
    port = ports.resolve(args.port)
    if servo is not None and not ports.is_virtual(port):
        raise ParameterError("--virtual-servo-params needs --port virtual or --backend sim")
    with ports.open_ports(port, robot=args.robot, baud=args.baud, bus=False, sim=True, fixed_base=True,
                          servo_params=args.virtual_servo_params) as opened, \
            DynamixelRobot(spec, opened.port, args.baud) as robot:
        return record(robot, joints, rate_hz=rate, exc=exc, backend=f"dxl {port}", progress=progress)


def cmd_sysid(args) -> int:
    from felis.calib.sysid import Excitation, Recording, fit, fit_summary
    from felis.files import check_target
    from felis.sim.servo_file import save_servo_params
    from felis.spec import load_spec

    spec = load_spec(args.robot)
    joints = _joints(spec, args.joints)
    out = Path(args.out) if args.out else Path(f"sysid-{spec.name}.json")
    check_target(out, "servo parameters", ParameterError)
    if args.record is not None:
        if Path(args.record).suffix != ".npz":
            raise ParameterError(f"{args.record}: a recording file must end in .npz")
        check_target(Path(args.record), "recording", ParameterError)
    if args.from_recording is not None and (args.record is not None or args.port is not None):
        raise ParameterError("--from-recording fits a saved recording: it takes neither --port nor --record")
    if args.rate is not None and not 10 <= args.rate <= 1000:
        raise ParameterError(f"rate must be within 10…1000 Hz, got {args.rate:g}")
    exc = Excitation()
    bar = output.StageProgress(not args.json)
    files: dict[str, str] = {}
    try:
        if args.from_recording is not None:
            rec = Recording.load(args.from_recording, spec)
            names = joints or rec.tested
        else:
            names = joints or list(spec.names)
            _confirm(args, spec, names, exc, args.rate or 200.0)
            rec = _record(args, spec, names, exc, bar)
            if args.record is not None:
                files["recording"] = str(rec.save(args.record))
        progress = (lambda j, i, n: bar(f"fitting {j}", i / n)) if bar.enabled else None
        latency = None if args.latency_ms is None else args.latency_ms / 1000.0
        result = fit(spec, rec, names, effort_weight=args.effort_weight, latency_s=latency, fixed=args.hold or (),
                     progress=progress)
    finally:
        bar.stop()
    params = result.params
    summary = fit_summary(result)
    summary.update({"backend": rec.backend, "rate_hz": rec.rate_hz, "ticks": int(len(rec.q))})
    files["params"] = str(save_servo_params(out, spec.name, params, fit=summary))
    period = float((rec.t_write[-1, 0] - rec.t_write[0, 0]) / max(1, len(rec.q) - 1))
    info = {"ticks": int(len(rec.q)), "rate_hz": rec.rate_hz, "achieved_hz": 1.0 / period if period > 0 else None,
            "invalid_ticks": int((~rec.valid).sum()), "backend": rec.backend}
    if args.json:
        output.print_json({"robot": spec.name, "recording": info, **result.as_dict(), "files": files})
        return 0
    _print_table(result, info, files)
    return 0


def _print_table(result, info, files) -> None:
    from rich.table import Table
    console = output.console()
    if not console.is_terminal:
        console = output.console(width=160)
    t = Table(title=f"{result.robot}: servo model, datasheet → fitted", title_justify="left")
    for col in ("joint", "P", "I", "D", "damping", "armature", "friction", "torque limit", "latency (ms)",
                "step RMS (mrad)", "RMS (mrad)", "×"):
        t.add_column(col, justify="left" if col == "joint" else "right")
    for name, f in result.joints.items():
        d, p = f.default, f.fitted
        gains = [f"{a:.4g} → {b:.4g}" for a, b in zip(d.pid, p.pid, strict=True)]
        cells = [f"{getattr(d, k):.4g} → {getattr(p, k):.4g}" for k in ("damping", "armature", "frictionloss")]
        tl = f"{d.torque_limit:.4g} → {p.torque_limit:.4g}" + ("" if f.saturated else " (not reached)")
        lat = f"{1e3 * f.latency_before:.2f} → {1e3 * f.latency_after:.2f}"
        t.add_row(name, *gains, *cells, tl, lat, f"{1e3 * f.step_rms_before:.2f} → {1e3 * f.step_rms_after:.2f}",
                  f"{1e3 * f.rms_before:.2f} → {1e3 * f.rms_after:.2f}", f"{f.step_improvement:.1f}")
    console.print(t)
    achieved = f", achieved {info['achieved_hz']:.0f} Hz" if info.get("achieved_hz") else ""
    console.print(f"recording: {info['ticks']} ticks at {info['rate_hz']:g} Hz{achieved}, {info['invalid_ticks']} "
                  f"invalid, {info['backend']}; P, I, D in control-table units; units: N·m·s/rad, kg·m², N·m (m and N "
                  "for a prismatic joint); × = step RMS before / after")
    for kind, path in files.items():
        console.print(f"{kind}: {path}")
    console.print(f"use it: felis run CONTROLLER --robot {result.robot} --servo-params {files['params']}")


def register(sub) -> None:
    """Add ``felis sysid`` to the ``felis`` sub-commands."""
    p = sub.add_parser("sysid", help="identify the servo model (P, I, D gains, damping, armature, friction, "
                       "torque limit, latency) from step and chirp responses",
                       description="Record step and chirp responses one joint at a time (servos over --port, "
                       "a virtual bus with --port virtual, or MuJoCo with --backend sim), fit the MuJoCo servo "
                       "model per joint with scipy, and write a servo parameter file for `felis run "
                       "--servo-params`. Prints the fit error before and after.")
    p.add_argument("--robot", required=True, help="robot name (cat, arm) or a description .toml")
    p.add_argument("--joints", type=_names, help="joints or groups to identify, comma-separated (default: all)")
    p.add_argument("--backend", default="dxl", choices=["dxl", "sim"],
                   help="dxl: Dynamixel servos on --port (default); sim: MuJoCo directly, base held")
    p.add_argument("--port", help="dxl: serial device, or 'virtual' (virtual bus backed by MuJoCo, base held; "
                   "default $FELIS_PORT)")
    p.add_argument("--baud", type=int, default=1_000_000, help="dxl: baud rate (default 1000000)")
    p.add_argument("--rate", type=float, help="recording rate in Hz (default 200)")
    p.add_argument("--out", type=Path, help="servo parameter file to write (default sysid-<robot>.json)")
    p.add_argument("--record", type=Path, metavar="FILE.npz", help="also save the recording here")
    p.add_argument("--from-recording", type=Path, metavar="FILE.npz", help="fit a saved recording; move nothing")
    p.add_argument("--effort-weight", type=float, default=1.0,
                   help="weight of the torque (Present Current) residual; 0 = positions only (default 1)")
    p.add_argument("--latency-ms", type=float, help="starting command delay of the replay, fitted (default 0.5 on "
                   "the host's clock)")
    p.add_argument("--hold", type=_held, metavar="PARAMS", help="parameters to keep at their starting values "
                   "instead of fitting, comma-separated: p, i, d, damping, armature, frictionloss, torque_limit, "
                   "latency")
    p.add_argument("--yes", action="store_true", help="do not ask before moving the servos")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.add_argument("--virtual-servo-params", metavar="FILE", help=argparse.SUPPRESS)  # tests: a 'wrong' sim
    p.set_defaults(func=cmd_sysid)
