"""One run for the CLI, in MuJoCo or on Dynamixel servos: robot, scenario, controller, log, video, plot,
summary.

`run_episode` is the one runner: it checks every input, opens the backend's robot (`_Sim`: MuJoCo
directly; `_Dxl`: Dynamixel servos through `felis.drivers.ports`, a virtual bus for ``port="virtual"``),
runs the loop with the progress, tilt, log (and video) monitors, writes the log's summary and the plot,
and returns an `EpisodeResult`; the backends differ only in what they check, open and judge. Used by
``felis sim drop``, ``felis sim render``, ``felis run`` and ``felis demo``. Every input is checked
before any file is created, so bad input writes nothing; a video is written to a temporary
file and moved into place at the end, the MCAP log is written incrementally.

Drops (``Episode.drop`` = height m, roll°, pitch°, yaw°; `felis.sim.scenarios.drop`):

* ``backend="sim"``: MuJoCo places the robot and the run ends with the landing judge
  (`felis.sim.landing.assess_landing`: the landing verdict of `felis.scenarios.verdicts`, the same as
  ``felis eval landing``'s, with tilt, feet down, impact, peak force).
* ``backend="dxl"`` with ``port="virtual"``: the virtual bus's simulation holds the robot in the air
  (`felis.sim.servo_in_loop`, ``--drop``) and releases it when torque first comes on, so the run goes
  through the whole hardware path. The result reports what that path can know: the drop and the final
  tilt from the IMU (``final_tilt_deg``: the angle between the IMU's up-axis and vertical at the last
  tick; sim drops report it too, for comparison), not the simulator's landing judge.
* ``backend="dxl"`` on a real port: refused. Nobody can place the cat in the air at a set orientation
  and let go on the loop's cue; a release trigger is not built.
"""

from __future__ import annotations

import contextlib
import inspect
import math
from dataclasses import dataclass, field
from pathlib import Path

from felis.controllers import CONTROLLERS, make_controller
from felis.drivers.dynamixel.robot import DynamixelRobot
from felis.drivers.dynamixel.trace import PacketTrace, TracedBus
from felis.drivers.ports import is_virtual, open_ports
from felis.errors import ParameterError
from felis.files import check_target
from felis.logs.plot import plot_log
from felis.logs.runlog import RunLog
from felis.logs.skills import skill_channels
from felis.loop import LoopReport, run_loop
from felis.rotations import tilt_deg
from felis.spec import load_spec


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
    video_from: float = 0.0  # seconds into the run of the video's first frame
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
    live: str | None = None  # "[HOST:]PORT": serve the log's channels over the Foxglove WebSocket protocol
    on_live: object | None = None  # called with the live view's ws:// address once it listens (CLI: prints it)
    trace: Path | None = None  # dxl: write every bus packet here (`felis.drivers.dynamixel.trace`)


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


class _FinalTilt:
    """Loop monitor: the IMU's tilt at the last tick; None when that tick had no reading (a quiet sensor)."""

    def __init__(self):
        self.deg: float | None = None

    def __call__(self, state, command) -> None:
        imu = state.imu
        ok = imu is not None and all(math.isfinite(float(v)) for v in imu.quat)
        self.deg = float(tilt_deg(imu.quat)) if ok else None


def _drop_meta(info) -> dict:
    return {"height_m": info.height, "roll_deg": info.roll, "pitch_deg": info.pitch, "yaw_deg": info.yaw}


def _check(ep: Episode) -> None:
    if not (ep.duration > 0 and ep.duration <= 3600):
        raise ParameterError(f"duration must be within 0…3600 s, got {ep.duration}")
    if ep.rate_hz is not None and not 1 <= ep.rate_hz <= 1000:
        raise ParameterError(f"rate must be within 1…1000 Hz (a tick of at least 1 ms), got {ep.rate_hz:g}")
    from felis.sim.render import check_video_path

    if ep.video is not None:
        check_video_path(ep.video)
    if ep.plot is not None and Path(ep.plot).suffix.lower() != ".png":
        raise ParameterError(f"{ep.plot}: plot output must end in .png")
    if ep.log is not None and Path(ep.log).suffix.lower() != ".mcap":
        raise ParameterError(f"{ep.log}: log file must end in .mcap")
    if ep.live is not None:
        from felis.logs.live import parse_address

        parse_address(ep.live)
    for p, what in ((ep.video, "video"), (ep.plot, "plot"), (ep.log, "run log")):
        if p is not None:
            check_target(Path(p), what, ParameterError)


def _controller(ep: Episode, spec):
    """The episode's controller; one that needs the robot's body model (the balance monitor) gets it
    from the MJCF here, the one place that wires simulation data into controllers; one that takes the drop
    height (landing: the motion library times its motion by the fall) gets the episode's drop."""
    options = dict(ep.controller_options)
    factory = CONTROLLERS.get(ep.controller)
    params = inspect.signature(factory).parameters if factory is not None else {}
    if "body" in params and "body" not in options:
        from felis.sim.bodymodel import load_body_model

        options["body"] = load_body_model(spec)
    if "drop_height" in params and options.get("drop_height") is None and ep.drop is not None:
        options["drop_height"] = float(ep.drop[0])
    return make_controller(ep.controller, **options)


def run_episode(ep: Episode) -> EpisodeResult:
    """Run ``ep`` on its backend; every input is checked before anything is created or written."""
    if ep.backend not in ("sim", "dxl"):
        raise ParameterError(f"unknown backend {ep.backend!r}: use sim or dxl")
    spec = load_spec(ep.robot)
    controller = _controller(ep, spec)
    backend = (_Dxl if ep.backend == "dxl" else _Sim)(ep, spec, controller)
    files: dict[str, str] = {}
    with contextlib.ExitStack() as stack:
        robot = backend.open(stack)
        info = backend.info
        final_tilt = _FinalTilt() if info is not None else None
        log = landing = None
        try:
            monitors = [*backend.monitors(), *([] if ep.progress is None else [ep.progress]),
                        *([] if final_tilt is None else [final_tilt])]
            if ep.log is not None or ep.live is not None:
                meta = {**backend.meta(), **ep.meta}
                if info is not None:
                    meta["drop"] = _drop_meta(info)
                scene, poses = backend.view(getattr(controller, "markers", None))
                live = None
                if ep.live is not None:
                    from felis.logs.live import LiveView

                    live = stack.enter_context(LiveView(ep.live))
                    if ep.on_live is not None:
                        ep.on_live(live.url)
                log = RunLog(ep.log, spec, meta, scene=scene, poses=poses, live=live)
                skills = skill_channels(log, controller, monitors)  # /balance, /phase when they run
                if skills is not None:
                    monitors.append(skills)
            report = run_loop(robot, controller, duration=ep.duration, rate_hz=ep.rate_hz, clock=backend.clock,
                              log=log, monitors=monitors)
            ctl = _summary(controller)
            landing = backend.verdict()
        except BaseException:
            backend.abort()
            if log is not None:
                log.close({"error": "run aborted"})
            raise
        tilt = None if final_tilt is None else final_tilt.deg
        if log is not None:
            summary = {"run": report.as_dict()}
            if landing is not None:
                summary["landing"] = landing.as_dict()
            if ctl is not None:
                summary["controller"] = ctl
            if tilt is not None and backend.logs_final_tilt:
                summary["final_tilt_deg"] = tilt
            if landing is not None:  # the verdict on a channel of its own, at the run's end
                log.message("/landing", report.sim_time_s, landing.as_dict())
            log.close(summary)
            if ep.log is not None:
                files["log"] = str(ep.log)
        backend.finish(files)
    if ep.plot is not None and ep.log is not None:
        files["plot"] = str(plot_log(ep.log, ep.plot))
    return EpisodeResult(report=report, landing=landing, drop=info, files=files, warnings=backend.warnings,
                         controller=ctl, final_tilt_deg=tilt)


def _summary(controller) -> dict | None:
    """The controller's own account of the run (e.g. arm-track's tracking error), if it keeps one."""
    return controller.summary() if callable(getattr(controller, "summary", None)) else None


class _Sim:
    """MuJoCo directly (``clock`` as asked): MuJoCo places a drop, the landing judge gives the verdict, and
    the run can be filmed."""

    logs_final_tilt = False  # the landing verdict is the log's account of a drop

    def __init__(self, ep: Episode, spec, controller):
        self.ep, self.spec, self.controller = ep, spec, controller
        self.clock = ep.clock
        self.warnings: list[str] = []
        self.info = self.recorder = self.standing = self.video = None
        _check(ep)
        self.servo = None
        if ep.servo_params is not None:
            from felis.sim.servo_file import load_servo_params  # late: the simulation (MuJoCo)

            self.servo = load_servo_params(ep.servo_params, spec)

    def meta(self) -> dict:
        return {"controller": self.ep.controller, "backend": "sim"}

    def open(self, stack: contextlib.ExitStack):
        # late: MuJoCo, the landing judge and its yardstick are only needed on this backend
        from felis.learning.landing.evaluate import standing_waist_height
        from felis.sim import MujocoRobot
        from felis.sim.landing import LandingRecorder
        from felis.sim.scenarios import drop

        ep, spec = self.ep, self.spec
        self.robot = robot = stack.enter_context(MujocoRobot(spec, servo=self.servo))
        self.info = drop(robot, *ep.drop) if ep.drop is not None else None
        if self.info is not None:  # the landing verdict's yardstick, on a robot of its own: this one stays as dropped
            with MujocoRobot(spec, servo=self.servo) as stand:
                self.standing = standing_waist_height(stand)
        if self.info is not None:
            self.recorder = LandingRecorder(robot, tuple(spec.sensors.contacts)).attach()
        return robot

    def view(self, markers) -> tuple:
        """The log's scene and body poses: MuJoCo's (every body, the floor, a target path)."""
        from felis.sim.scene import MujocoPoses, model_scene

        return model_scene(self.robot.model, path=markers), MujocoPoses(self.robot)

    def monitors(self) -> list:
        ep = self.ep
        if ep.video is None:
            return []
        from felis.sim.render import VideoRecorder  # late: MuJoCo rendering

        self.video = VideoRecorder(self.robot, ep.video, fps=ep.fps, width=ep.size[0], height=ep.size[1],
                                   markers=getattr(self.controller, "markers", None), start=ep.video_from)
        return [self.video]

    def verdict(self):
        if self.info is None:
            return None
        from felis.sim.landing import assess_landing

        return assess_landing(self.robot, self.recorder, self.standing)

    def abort(self) -> None:
        if self.video is not None:
            self.video.abort()

    def finish(self, files: dict[str, str]) -> None:
        if self.video is not None:
            files["video"] = str(self.video.close())


class _Dxl:
    """Dynamixel servos on ``ep.port`` (wall clock); ``virtual`` starts a virtual bus whose servos are the
    MuJoCo model's joints (servo-in-the-loop): the whole hardware path; a drop is held there in the air and
    falls when torque comes on (module doc). No landing judge: the IMU's final tilt is the verdict."""

    clock = "wall"
    logs_final_tilt = True

    def __init__(self, ep: Episode, spec, controller):
        self.ep, self.spec = ep, spec
        self.warnings = ep.warnings
        if ep.video is not None:
            raise ParameterError("video needs the simulation backend (--backend sim)")
        if ep.port is None:
            raise ParameterError("the dxl backend needs --port PATH (see `felis find-port`) or --port virtual")
        virtual = is_virtual(ep.port)
        self.needs_imu = needs_imu = bool(getattr(controller, "needs_imu", False))
        if needs_imu and not spec.sensors.imu:
            raise ParameterError(f"{ep.controller} needs an IMU and {spec.name}'s description has none")
        if needs_imu and not virtual and ep.imu_port is None:
            raise ParameterError(f"{ep.controller} steers by the IMU: give --imu-port PATH (the BNO08x's serial "
                                 "port; `felis find-port` lists candidates)")
        self.info = None
        if ep.drop is not None:
            if not virtual:
                raise ParameterError(f"a drop on real servos ({ep.port}) is not supported: nobody can place the cat "
                                     "in the air at a set orientation and let go on cue (no release trigger is "
                                     "built); use --backend sim or --port virtual")
            self.info = _drop_info(ep.drop, spec)
        if ep.servo_params is not None and not virtual:
            raise ParameterError("--servo-params sets the simulated servos: use it with --backend sim or --port "
                                 "virtual")
        if ep.servo_params is not None:
            from felis.sim.servo_file import load_servo_params  # late: the simulation (MuJoCo)

            load_servo_params(ep.servo_params, spec)  # a bad file is one line here, not a failed child process
        if ep.trace is not None:
            PacketTrace(ep.trace)  # checks the path, creates nothing: a bad one is one line before anything starts
        _check(ep)

    def meta(self) -> dict:
        return {"controller": self.ep.controller, "backend": "dxl", "port": self.ep.port, "baud": self.ep.baud}

    def open(self, stack: contextlib.ExitStack):
        ep, spec = self.ep, self.spec
        # the trace is closed (flushed) last: after the robot's torque-off on every way out
        trace = None if ep.trace is None else stack.enter_context(PacketTrace(ep.trace))
        opened = stack.enter_context(open_ports(ep.port, robot=ep.robot, baud=ep.baud, imu_port=ep.imu_port,
                                                bus=False, sim=True, servo_params=ep.servo_params, drop=ep.drop))
        calibration = _connect_checks(ep, spec, opened.port, trace)
        bus = None if trace is None else TracedBus(opened.port, ep.baud, trace=trace)
        robot = stack.enter_context(DynamixelRobot(spec, opened.port, ep.baud, imu_port=opened.imu_port, bus=bus,
                                                   calibration=calibration, imu_required=self.needs_imu))
        ep.warnings.extend(robot.warnings)
        return robot

    def view(self, markers) -> tuple:
        """The log's scene and body poses on servos: the body model from joint angles and the IMU
        (`felis.sim.scene.hardware_view`; none for a fixed-base robot)."""
        from felis.sim.scene import hardware_view

        found = hardware_view(self.spec)
        return (None, None) if found is None else found

    def monitors(self) -> list:
        return []

    def verdict(self):
        return None

    def abort(self) -> None:
        pass

    def finish(self, files: dict[str, str]) -> None:
        pass


def _drop_info(drop, spec):
    """A drop checked in this process (one line, before the virtual bus starts) as a `felis.scenarios.Drop`
    (free fall √(2h/g), g = `felis.rotations.G`)."""
    from felis.scenarios import Drop
    from felis.sim.servo_in_loop import check_drop, check_floating_base

    h, roll, pitch, yaw = check_drop(drop)
    check_floating_base(spec)
    return Drop(roll, pitch, yaw, h)


def _connect_checks(ep: Episode, spec, port: str, trace: PacketTrace | None = None):
    """Before the robot connects: load its calibration (if an id or file is given) and check the servos'
    EEPROM settings, applying differences with the operator's confirmation (or ``--yes``).

    Returns the host-side calibration for `DynamixelRobot`, or None (with a warning) when uncalibrated.
    """
    from felis.calib.calfile import calibration_path, load
    from felis.calib.operator import ConsoleOperator
    from felis.cli.calib import eeprom_check

    cal = None
    if ep.calibration is not None or ep.robot_id is not None:
        cal = load(ep.calibration or calibration_path(spec.name, ep.robot_id), spec)
    elif not is_virtual(ep.port):
        ep.warnings.append(f"no calibration: joint zeros are the servos' raw centre ticks; run `felis calibrate "
                           f"--robot {spec.name} --id NAME` and pass --robot-id NAME")
    # quiet_check: the IMU's port given as the bus is named so, not as "two servos share an ID"
    with open_ports(port, baud=ep.baud, quiet_check=True, trace=trace) as opened:
        applied = eeprom_check(opened.bus, spec, cal, ConsoleOperator(yes=ep.yes, quiet=True))
    if applied:
        ep.warnings.append(f"applied {len(applied)} EEPROM setting(s): "
                           + ", ".join(f"{d.joint}.{d.item} {d.motor}→{d.expected}" for d in applied[:6])
                           + (" …" if len(applied) > 6 else ""))
    return cal.for_robot(spec) if cal is not None else None
