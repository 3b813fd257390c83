"""One simulated run for the CLI: robot, scenario, controller, log, video, plot, summary.

Used by ``felis sim drop``, ``felis sim render``, ``felis run`` and ``felis demo``. Every input is
checked before any file is created, so bad input writes nothing; a video is written to a temporary
file and moved into place at the end, the MCAP log is written incrementally.

Drops (``Episode.drop`` = height m, roll°, pitch°, yaw°; `felis.sim.scenarios.drop`):

* ``backend="sim"``: MuJoCo places the robot and the run ends with the landing judge
  (`felis.sim.landing.assess_landing`: tilt, feet down, impact, peak force).
* ``backend="dxl"`` with ``port="virtual"``: the virtual bus's simulation holds the robot in the air
  (`felis.drivers.virtual`, ``--drop``) and releases it when torque first comes on, so the run goes
  through the whole hardware path. The result reports what that path can know: the drop and the final
  tilt from the IMU (``final_tilt_deg``: the angle between the IMU's up-axis and vertical at the last
  tick; sim drops report it too, for comparison), not the simulator's landing judge.
* ``backend="dxl"`` on a real port: refused. Nobody can place the cat in the air at a set orientation
  and let go on the loop's cue; a release trigger is not built.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from felis.controllers import make_controller
from felis.errors import ParameterError
from felis.files import check_target
from felis.loop import LoopReport, run_loop
from felis.spec import load_spec

G = 9.81  # m/s², MuJoCo's default gravity (the models')


@dataclass
class Episode:
    """What to run. ``drop`` is (height m, roll°, pitch°, yaw°) or None (start from the model's pose)."""

    robot: str = "cat"
    controller: str = "stand"
    duration: float = 2.0
    drop: tuple[float, float, float, float] | None = None
    log: Path | None = None
    video: Path | None = None
    plot: Path | None = None
    fps: float = 30.0
    size: tuple[int, int] = (640, 480)
    clock: str = "sim"
    rate_hz: float | None = None  # None: the description's rate
    progress: object | None = None  # a loop monitor that shows progress (CLI)
    meta: dict = field(default_factory=dict)
    backend: str = "sim"  # "sim": MuJoCo directly; "dxl": Dynamixel servos on ``port``
    port: str | None = None  # dxl: serial device, or "virtual" (a virtual bus backed by MuJoCo)
    baud: int = 1_000_000
    imu_port: str | None = None  # dxl: the IMU's serial device (cat)
    robot_id: str | None = None  # dxl: the robot's calibration (`felis calibrate --id`)
    calibration: Path | None = None  # dxl: a calibration file path instead of the id's
    yes: bool = False  # dxl: apply EEPROM setting differences without asking
    warnings: list[str] = field(default_factory=list)  # filled by the run: connect-time advice
    servo_params: Path | None = None  # a servo parameter file (`felis sysid`) for the simulated servos
    controller_options: dict = field(default_factory=dict)  # e.g. arm-track's trajectory


@dataclass
class EpisodeResult:
    report: LoopReport
    landing: object | None  # felis.sim.landing.Landing for drops
    drop: object | None
    files: dict[str, str]
    warnings: list[str] = field(default_factory=list)
    controller: dict | None = None  # the controller's own summary (e.g. arm-track's tracking error)
    final_tilt_deg: float | None = None  # drops: IMU up-axis vs vertical at the last tick (None: no IMU)

    def as_dict(self) -> dict:
        out = {"run": self.report.as_dict(), "files": self.files}
        if self.controller is not None:
            out["controller"] = self.controller
        if self.warnings:
            out["warnings"] = self.warnings
        if self.drop is not None:
            d = self.drop
            out["drop"] = {"height_m": d.height, "roll_deg": d.roll, "pitch_deg": d.pitch, "yaw_deg": d.yaw,
                           "free_fall_s": round(d.fall_time, 4)}
        if self.landing is not None:
            out["landing"] = self.landing.as_dict()
        if self.final_tilt_deg is not None:
            out["final_tilt_deg"] = round(self.final_tilt_deg, 3)
        return out


def tilt_deg(quat) -> float:
    """Angle (degrees) between a body's up-axis and vertical, from its orientation quaternion (w, x, y, z):
    up_z = 1 − 2(x² + y²) for a unit quaternion (normalised here)."""
    w, x, y, z = (float(v) for v in quat)
    n2 = w * w + x * x + y * y + z * z
    up_z = 1.0 - 2.0 * (x * x + y * y) / n2
    return math.degrees(math.acos(max(-1.0, min(1.0, up_z))))


class _FinalTilt:
    """Loop monitor: the IMU's tilt at the last tick; None when that tick had no reading (a quiet sensor)."""

    def __init__(self):
        self.deg: float | None = None

    def __call__(self, state, command) -> None:
        imu = state.imu
        ok = imu is not None and all(math.isfinite(float(v)) for v in imu.quat)
        self.deg = tilt_deg(imu.quat) if ok else None


def _drop_meta(info) -> dict:
    return {"height_m": info.height, "roll_deg": info.roll, "pitch_deg": info.pitch, "yaw_deg": info.yaw}


def _check(ep: Episode) -> None:
    if not (ep.duration > 0 and ep.duration <= 3600):
        raise ParameterError(f"duration must be within 0…3600 s, got {ep.duration}")
    if ep.rate_hz is not None and not 1 <= ep.rate_hz <= 1000:
        raise ParameterError(f"rate must be within 1…1000 Hz (physics runs at 1 kHz), got {ep.rate_hz:g}")
    from felis.sim.render import check_video_path

    if ep.video is not None:
        check_video_path(ep.video)
    if ep.plot is not None and Path(ep.plot).suffix.lower() != ".png":
        raise ParameterError(f"{ep.plot}: plot output must end in .png")
    if ep.log is not None and Path(ep.log).suffix.lower() != ".mcap":
        raise ParameterError(f"{ep.log}: log file must end in .mcap")
    for p, what in ((ep.video, "video"), (ep.plot, "plot"), (ep.log, "run log")):
        if p is not None:
            check_target(Path(p), what, ParameterError)


def _controller(ep: Episode, spec):
    """The episode's controller; one that needs the robot's body model (the balance monitor) gets it
    from the MJCF here, the one place that wires simulation data into controllers."""
    import inspect

    from felis.controllers import CONTROLLERS

    options = dict(ep.controller_options)
    factory = CONTROLLERS.get(ep.controller)
    if factory is not None and "body" in inspect.signature(factory).parameters and "body" not in options:
        from felis.sim.bodymodel import load_body_model

        options["body"] = load_body_model(spec)
    return make_controller(ep.controller, **options)


def run_episode(ep: Episode) -> EpisodeResult:
    if ep.backend == "dxl":
        return run_hardware(ep)
    if ep.backend != "sim":
        raise ParameterError(f"unknown backend {ep.backend!r}: use sim or dxl")
    from felis.sim import MujocoRobot
    from felis.sim.landing import ImpactRecorder, assess_landing
    from felis.sim.scenarios import drop

    spec = load_spec(ep.robot)
    controller = _controller(ep, spec)
    _check(ep)
    servo = None
    if ep.servo_params is not None:
        from felis.sim.servo_file import load_servo_params

        servo = load_servo_params(ep.servo_params, spec)
    robot = MujocoRobot(spec, servo=servo)
    files: dict[str, str] = {}
    with robot:
        info = drop(robot, *ep.drop) if ep.drop is not None else None
        recorder = ImpactRecorder(robot).attach() if info is not None else None
        monitors = [] if ep.progress is None else [ep.progress]
        final_tilt = _FinalTilt() if info is not None else None
        if final_tilt is not None:
            monitors.append(final_tilt)
        video = log = landing = None
        try:
            if ep.video is not None:
                from felis.sim.render import VideoRecorder

                video = VideoRecorder(robot, ep.video, fps=ep.fps, width=ep.size[0], height=ep.size[1],
                                      markers=getattr(controller, "markers", None))
                monitors.insert(0, video)
            if ep.log is not None:
                from felis.logs.runlog import RunLog

                meta = {"controller": ep.controller, "backend": "sim", **ep.meta}
                if info is not None:
                    meta["drop"] = _drop_meta(info)
                log = RunLog(ep.log, spec, meta)
            report = run_loop(robot, controller, duration=ep.duration, rate_hz=ep.rate_hz, clock=ep.clock,
                              log=log, monitors=monitors)
            ctl = _summary(controller)
            if info is not None:
                landing = assess_landing(robot, recorder)
        except BaseException:
            if video is not None:
                video.abort()
            if log is not None:
                log.close({"error": "run aborted"})
            raise
        if log is not None:
            summary = {"run": report.as_dict()}
            if landing is not None:
                summary["landing"] = landing.as_dict()
            if ctl is not None:
                summary["controller"] = ctl
            log.close(summary)
            files["log"] = str(ep.log)
        if video is not None:
            files["video"] = str(video.close())
    if ep.plot is not None and ep.log is not None:
        from felis.logs.plot import plot_log

        files["plot"] = str(plot_log(ep.log, ep.plot))
    return EpisodeResult(report=report, landing=landing, drop=info, files=files, controller=ctl,
                         final_tilt_deg=None if final_tilt is None else final_tilt.deg)


def _summary(controller) -> dict | None:
    """The controller's own account of the run (e.g. arm-track's tracking error), if it keeps one."""
    return controller.summary() if callable(getattr(controller, "summary", None)) else None


def run_hardware(ep: Episode) -> EpisodeResult:
    """The same run through the Dynamixel backend (wall clock). ``port="virtual"`` starts a virtual
    bus whose servos are the MuJoCo model's joints (servo-in-the-loop): the whole hardware path; a drop
    is held there in the air and falls when torque comes on (module doc)."""
    import contextlib

    from felis.drivers.dynamixel.robot import DynamixelRobot

    spec = load_spec(ep.robot)
    controller = _controller(ep, spec)
    if ep.video is not None:
        raise ParameterError("video needs the simulation backend (--backend sim)")
    if ep.port is None:
        raise ParameterError("the dxl backend needs --port PATH (see `felis find-port`) or --port virtual")
    needs_imu = bool(getattr(controller, "needs_imu", False))
    if needs_imu and not spec.sensors.imu:
        raise ParameterError(f"{ep.controller} needs an IMU and {spec.name}'s description has none")
    if needs_imu and ep.port != "virtual" and ep.imu_port is None:
        raise ParameterError(f"{ep.controller} steers by the IMU: give --imu-port PATH (the BNO08x's serial port; "
                             "`felis find-port` lists candidates)")
    info = None
    if ep.drop is not None:
        if ep.port != "virtual":
            raise ParameterError(f"a drop on real servos ({ep.port}) is not supported: nobody can place the cat in "
                                 "the air at a set orientation and let go on cue (no release trigger is built); "
                                 "use --backend sim or --port virtual")
        info = _drop_info(ep.drop, spec)
    if ep.servo_params is not None and ep.port != "virtual":
        raise ParameterError("--servo-params sets the simulated servos: use it with --backend sim or --port virtual")
    if ep.servo_params is not None:
        from felis.sim.servo_file import load_servo_params

        load_servo_params(ep.servo_params, spec)  # a bad file is one line here, not a failed child process
    _check(ep)
    files: dict[str, str] = {}
    with contextlib.ExitStack() as stack:
        port, imu_port = ep.port, ep.imu_port
        if port == "virtual":
            from felis.drivers.virtual import spawn

            vb = stack.enter_context(spawn(ep.robot, sim=True, baud=ep.baud, servo_params=ep.servo_params,
                                           drop=ep.drop))
            port, imu_port = vb.port, imu_port or vb.imu_port
        calibration = _connect_checks(ep, spec, port)
        robot = stack.enter_context(DynamixelRobot(spec, port, ep.baud, imu_port=imu_port, calibration=calibration,
                                                   imu_required=needs_imu))
        ep.warnings.extend(robot.warnings)
        log = None
        try:
            if ep.log is not None:
                from felis.logs.runlog import RunLog

                meta = {"controller": ep.controller, "backend": "dxl", "port": ep.port, "baud": ep.baud, **ep.meta}
                if info is not None:
                    meta["drop"] = _drop_meta(info)
                log = RunLog(ep.log, spec, meta)
            monitors = [] if ep.progress is None else [ep.progress]
            final_tilt = _FinalTilt() if info is not None else None
            if final_tilt is not None:
                monitors.append(final_tilt)
            report = run_loop(robot, controller, duration=ep.duration, rate_hz=ep.rate_hz, clock="wall", log=log,
                              monitors=monitors)
            ctl = _summary(controller)
        except BaseException:
            if log is not None:
                log.close({"error": "run aborted"})
            raise
        tilt = None if final_tilt is None else final_tilt.deg
        if log is not None:
            log.close({"run": report.as_dict(), **({"controller": ctl} if ctl is not None else {}),
                       **({"final_tilt_deg": tilt} if tilt is not None else {})})
            files["log"] = str(ep.log)
    if ep.plot is not None and ep.log is not None:
        from felis.logs.plot import plot_log

        files["plot"] = str(plot_log(ep.log, ep.plot))
    return EpisodeResult(report=report, landing=None, drop=info, files=files, warnings=ep.warnings, controller=ctl,
                         final_tilt_deg=tilt)


def _drop_info(drop, spec):
    """A drop checked in this process (one line, before the virtual bus starts) as a `DropInfo`; free fall
    √(2h/g) with g = `G`."""
    from felis.drivers.virtual import check_drop, check_floating_base
    from felis.sim.scenarios import DropInfo

    h, roll, pitch, yaw = check_drop(drop)
    check_floating_base(spec)
    return DropInfo(h, roll, pitch, yaw, fall_time=math.sqrt(2 * h / G))


def _connect_checks(ep: Episode, spec, port: str):
    """Before the robot connects: load its calibration (if an id or file is given) and check the servos'
    EEPROM settings, applying differences with the operator's confirmation (or ``--yes``).

    Returns the host-side calibration for `DynamixelRobot`, or None (with a warning) when uncalibrated.
    """
    from felis.calib.calfile import calibration_path, load
    from felis.calib.operator import ConsoleOperator
    from felis.cli.calib import eeprom_check
    from felis.drivers.dynamixel.bus import DynamixelBus

    cal = None
    if ep.calibration is not None or ep.robot_id is not None:
        cal = load(ep.calibration or calibration_path(spec.name, ep.robot_id), spec)
    elif ep.port != "virtual":
        ep.warnings.append(f"no calibration: joint zeros are the servos' raw centre ticks; run `felis calibrate "
                           f"--robot {spec.name} --id NAME` and pass --robot-id NAME")
    with DynamixelBus(port, ep.baud) as bus:
        bus.check_quiet()  # the IMU's port given as the bus: say so, not "two servos share an ID"
        applied = eeprom_check(bus, spec, cal, ConsoleOperator(yes=ep.yes, quiet=True))
    if applied:
        ep.warnings.append(f"applied {len(applied)} EEPROM setting(s): "
                           + ", ".join(f"{d.joint}.{d.item} {d.motor}→{d.expected}" for d in applied[:6])
                           + (" …" if len(applied) > 6 else ""))
    return cal.for_robot(spec) if cal is not None else None
