"""Servo-in-the-loop: the virtual bus's servos backed by the MuJoCo model, so the whole hardware code path
(`felis.drivers.dynamixel`, the SDK, the pty, the byte-level servos) drives a simulated robot.

`MujocoBackend` implements the drivers' `felis.drivers.virtual.HornBackend` seam (the drivers never import
the simulation); `virtual_bus` builds a robot's bus with it (``sim=True``) or without, checking every option
once; ``python -m felis.sim.servo_in_loop OPTIONS_JSON`` is the child entry `felis.drivers.virtual.spawn`
starts for a simulated bus: it builds the bus here and serves it with `felis.drivers.virtual.process.main`.
The drop checks that need the simulation (`check_drop`, `check_floating_base`) live here; the drop's own
limits are `felis.scenarios.drop`'s.

Servo-in-the-loop (`virtual_bus` with ``sim=True``): the horn is the MuJoCo joint. A thread
steps `felis.sim.robot.MujocoRobot` so that simulated time follows the wall clock (whole model
timesteps, woken every `MujocoBackend.POLL_S` = 1 ms or model step, whichever is longer, and at most
`MujocoBackend.MAX_LAG_S` = 20 ms of them per iteration; a longer lag is skipped, not caught up, and counted in
``stats.sim_lag_s``). The servos boot with Goal Position at the model's initial pose. Each iteration
copies Goal Position (through the mounting, below), the Torque Enable mask (always the full mask) and
Profile Velocity (``dq_max``, None when all are 0; a 0 among others is unlimited) into a
`felis.hal.Command` when any servo's memory changed, and copies the quantised q, dq and effort back
into every servo's present items. The firmware's controller that a servo's memory sets (operating mode 3, 4
or 5, Position P/I/D, Feedforward gains, PWM Limit, Goal Current in mode 5:
`felis.drivers.virtual.VirtualServo.firmware_controller`) becomes its joint's MuJoCo controller when those
bytes change, so gains a host writes (`felis.drivers.dynamixel.DynamixelRobot` writes the description's,
sysid its trial gains) act on the simulated joint as on the real one, and until a host writes them the joint
runs the factory gains the servo boots with; the model carries the integral and feedforward actuators of every
joint for that (``full_controller``). A joint given fitted ``servo_params`` keeps its fitted controller.
Velocity mode (1) is emulated on a bare servo only: a simulated joint keeps its position controller.
▸ Lockstep (``lockstep=True``, in this process: the balance evaluation's
``--lockstep``): no thread; the host's loop steps the simulation by each tick (`MujocoBackend.advance`, called by
the `Lockstep` robot wrapper, whose states carry the simulated time), so a host slowed by a loaded machine costs no
simulated time. ``servo_params`` and ``fixed_base`` pass through to the model
(`felis.sim.robot.MujocoRobot`: per-joint servo parameters, the robot hung on a stand). Mounting, per joint::

    θ = direction·q / m_per_rad + zero + mount_offset          (JointSpec fields; offset default 0)

IMU (a robot whose description has one, e.g. the cat): a BNO08x in UART-RVC mode
(`felis.drivers.imu.RvcEmulator`, 100 Hz) on ``bus.imu_port`` reports the model's IMU site (orientation
q_wb, specific force accel_b). ▸ While the robot is held (before torque first comes on) it is still in
the operator's hands: the accelerometer reads the reaction to gravity, accel_b = R(q_wb)ᵀ·(−g), not the
free fall a forward pass of the start pose shows (the cat's feet start 1 mm above the floor). ▸ Once
released, each sample's accelerometer reads the mean specific force over the sample period, like the
sensor's own low-pass filter: accel_b = R(q_wb)ᵀ·((v(t) − v(t₀))/(t − t₀) − g), v the IMU site's world
velocity and t₀ the previous sample's simulated time. An instantaneous reading would alias: the samples
follow the wall clock, and a landing's impact, a few milliseconds long, falls between them. Each axis
saturates at ±8 g (``ACCEL_RANGE_G``, the BNO08x accelerometer's full scale), as the real sensor does.

Drop (``drop=(height m, roll°, pitch°, yaw°)``, ``felis virtual-bus --sim --drop H,R,P,Y``): before the
servos and the IMU first publish, `felis.sim.scenarios.drop` places the floating base at rest, turned by
roll, pitch, yaw, its lowest point ``height`` above the floor. The operator holds it there (the servos
read the held joints, the IMU the turned orientation and the reaction to gravity) until torque first
comes on: that is the release, and free fall starts with the physics. A drop needs the floating base
(not ``fixed_base``); `check_drop` validates it (also in the parent, `spawn`).
``imu_mount`` / ``imu_drift`` (`felis.drivers.imu.SensorMount`) simulate a mis-mounted sensor whose
orientation drifts: q_ws = q_wb ⊗ q_bs ⊗ exp(ω_d·t), accel_s = R(q_bs)ᵀ·accel_b, t on the sample clock.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace

import mujoco
import numpy as np

from felis.drivers.virtual import VirtualBus, VirtualServo, check_imu_mount
from felis.drivers.virtual.memory import OPERATING_MODE
from felis.drivers.virtual.process import main
from felis.errors import ParameterError
from felis.hal import Command
from felis.rotations import quat_conj, quat_rotate
from felis.scenarios.drop import drop_from_values
from felis.sim.robot import MujocoRobot, load_model, model_path
from felis.sim.scenarios import drop as place
from felis.sim.scenarios import set_pose
from felis.sim.servo_file import load_servo_params
from felis.spec import RobotSpec, load_spec


def virtual_bus(spec_or_name: RobotSpec | str, *, baud: int = 1_000_000, sim: bool = False, wire_time: bool = False,
                faults=None, seed: int = 0, mount_offsets: Mapping[str, float] | None = None,
                servo_params: Mapping[str, object] | None = None, fixed_base: bool = False,
                imu_mount: Sequence[float] | None = None, imu_drift: Sequence[float] | None = None,
                drop: Sequence[float] | None = None, lockstep: bool = False) -> VirtualBus:
    """`VirtualBus.for_robot` (one servo per joint, set up as a calibrated robot's, in the description's operating
    mode), with ``sim=True`` backed by the MuJoCo model (and the cat's IMU on ``bus.imu_port`` when started).

    ``mount_offsets`` (joint -> rad) simulates an uncalibrated assembly. With ``sim=True``,
    ``servo_params`` (joint -> `felis.sim.servo.ServoParams`) replaces the datasheet servo model of
    those joints (e.g. deliberately wrong parameters for a system-identification test) and
    ``fixed_base`` hangs a floating-base robot on a stand (`felis.sim.robot.MujocoRobot`).
    ``imu_mount`` (unit quaternion w, x, y, z: the sensor in the body frame) and ``imu_drift``
    (sensor-frame rad/s, 3-vector) simulate a mis-mounted, drifting IMU (module doc; needs sim=True
    and a robot with an IMU). ``drop`` (height m, roll°, pitch°, yaw°) holds the robot in the air,
    turned, until torque first comes on (module doc; needs sim=True and the floating base). ``lockstep``: the
    simulation does not follow the wall clock but steps as the host's loop ticks (`Lockstep`, module doc; sim=True,
    in this process).
    """
    spec = spec_or_name if isinstance(spec_or_name, RobotSpec) else load_spec(spec_or_name)
    if (servo_params or fixed_base) and not sim:
        raise ParameterError("servo parameters and a fixed base apply to the simulation: they need sim=True "
                             "(--sim)")
    if lockstep and not sim:
        raise ParameterError("lockstep steps the simulation with the host's loop: it needs sim=True (--sim)")
    drop = check_drop(drop, sim=sim, fixed_base=fixed_base)
    if drop is not None:
        check_floating_base(spec)
    mount = None
    if imu_mount is not None or imu_drift is not None:
        if not sim or spec.sensors.imu is None:
            raise ParameterError("an IMU mount or drift needs the simulated IMU: sim=True (--sim) and a robot "
                                 f"with an IMU ({spec.name} {'has one' if spec.sensors.imu else 'has none'})")
        mount = check_imu_mount(imu_mount, imu_drift)

    def backend(bus: VirtualBus) -> MujocoBackend:
        return MujocoBackend(bus, servo_params=servo_params, fixed_base=fixed_base, drop=drop, lockstep=lockstep)

    bus = VirtualBus.for_robot(spec, baud=baud, wire_time=wire_time, faults=faults, seed=seed,
                               mount_offsets=mount_offsets, backend=backend if sim else None, imu_mount=mount)
    for j, s in zip(spec.joints, bus.servos, strict=True):  # as a set-up robot holds it (felis check-eeprom)
        if s.get("operating_mode") != j.operating_mode:
            s.set("operating_mode", j.operating_mode)
    return bus


def bus_from_options(options: Mapping[str, object]) -> VirtualBus:
    """The bus `felis.drivers.virtual.spawn`'s JSON options describe (the child's builder)."""
    servo_params = None
    if options.get("servo_params"):
        servo_params = load_servo_params(options["servo_params"], load_spec(options["robot"]))
    return virtual_bus(options["robot"], baud=options["baud"], sim=bool(options.get("sim")),
                       wire_time=options["wire_time"], faults=options["faults"] or None, seed=options["seed"],
                       servo_params=servo_params, fixed_base=bool(options.get("fixed_base")),
                       imu_mount=options.get("imu_mount"), imu_drift=options.get("imu_drift"), drop=options.get("drop"))


def check_drop(drop: Sequence[float] | None, *, sim: bool = True,
               fixed_base: bool = False) -> tuple[float, float, float, float] | None:
    """A drop (height m, roll°, pitch°, yaw°) as four floats, checked by `felis.scenarios.drop_from_values`
    (and that it can apply: the simulation, a floating base); None passes. ParameterError, one line."""
    if drop is None:
        return None
    d = drop_from_values(drop)
    values = (d.height_m, d.roll_deg, d.pitch_deg, d.yaw_deg)
    if not sim:
        raise ParameterError("a drop places the simulated robot in the air: it needs sim=True (--sim)")
    if fixed_base:
        raise ParameterError("a drop needs the floating base: it cannot be combined with a fixed base (--fixed-base)")
    return values


def check_floating_base(robot: RobotSpec | str) -> None:
    """ParameterError unless the robot's MuJoCo model has a floating base (a drop needs one)."""
    spec = robot if isinstance(robot, RobotSpec) else load_spec(robot)
    if not (load_model(model_path(spec)).jnt_type == mujoco.mjtJoint.mjJNT_FREE).any():
        raise ParameterError(f"{spec.name} is fixed to the world: only a free-floating robot can be dropped")



class MujocoBackend:
    """Servo-in-the-loop: the servos' horns are the MuJoCo model's joints (module doc); a
    `felis.drivers.virtual.HornBackend`. ``robot`` is the `MujocoRobot`, ``drop_info`` the drop's placement."""

    MAX_LAG_S = 0.02  # the most simulated time one iteration catches up (module doc)
    POLL_S = 0.001  # the thread's shortest wait: simulated time follows the wall clock to within this

    def __init__(self, bus: VirtualBus, *, servo_params: Mapping[str, object] | None = None,
                 fixed_base: bool = False, drop: Sequence[float] | None = None, lockstep: bool = False):
        spec = bus.spec
        self.lockstep = lockstep
        self.sim_t = 0.0  # simulated time since the release (s)
        servos: list[VirtualServo] = bus.servos
        self.bus, self.spec, self.servos = bus, spec, servos
        self._fitted = dict(servo_params or {})
        self.robot = MujocoRobot(spec, servo=self._fitted, fixed_base=fixed_base, full_controller=True)
        self.robot.connect()
        self.robot.arm()
        self.drop_info = None
        if drop is not None:  # held in the air, turned, until torque first comes on (module doc)
            self.drop_info = place(self.robot, *drop)
        self.dt = float(self.robot.model.opt.timestep)
        self.mounts = [s.mount for s in servos]
        self._revisions: tuple[int, ...] = ()
        self._controllers: list = [None] * len(servos)  # the firmware controller each joint runs (`_sync_gains`)
        self.imu: tuple | None = None
        self._held = True  # physics waits until torque first comes on (`_run`)
        self._reaction = -np.asarray(self.robot.model.opt.gravity, dtype=float)  # specific force at rest, world
        self._site = None  # the IMU site (mean specific force per sample, module doc)
        if spec.sensors.imu is not None:
            self._site = mujoco.mj_name2id(self.robot.model, mujoco.mjtObj.mjOBJ_SITE, spec.sensors.imu)
            self._vel = np.zeros(6)
        self._site_tv: tuple[float, np.ndarray] | None = None  # (sim time, site world velocity) now
        self._sample_tv: tuple[float, np.ndarray] | None = None  # the same at the previous IMU sample
        self._stop = threading.Event()
        self.observer = None  # called with each simulated state after it is published (the sim thread)
        for s in servos:
            s.external = True
        self._publish(self.robot.read())
        for s in servos:  # boot: Goal Position = Present Position (the model's initial pose)
            s.set("goal_position", s.get("present_position"))
        self._sync_command()
        self.imu_sample = self._imu_sample if spec.sensors.imu is not None else None  # (HornBackend)
        self._thread = threading.Thread(target=self._run_guarded, name="virtual-bus sim", daemon=True)

    def start(self) -> None:
        if not self.lockstep:  # lockstep: the host's ticks step the simulation (`advance`)
            self._thread.start()

    def advance(self, dt: float) -> float:
        """Lockstep (``lockstep=True``): step the simulation by ``dt`` (whole model timesteps, at least one) now,
        in the caller's thread, and publish it; no time passes while the robot is still held (torque never on).
        The simulated time since the release."""
        if not self.lockstep:
            raise RuntimeError("advance steps a lockstep bus; this one follows the wall clock")
        with self.bus.lock:
            if self._held and any(s.torque_enabled for s in self.servos):
                self._held = False
            held = self._held
        if not held:
            self._step(max(1, round(dt / self.dt)))
        return self.sim_t

    def stop(self) -> None:
        """Stop the thread, close the model (idempotent; also when never started)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        with contextlib.suppress(Exception):
            self.robot.close()

    def _imu_sample(self):
        """The IMU site's (quat, accel) in the body frame: held still, or the mean specific force over the sample
        period (module doc); the bus's `felis.drivers.virtual.VirtualImu` mounts and saturates it."""
        with self.bus.lock:
            quat, accel = self.imu
            held = self._held
            now, before = self._site_tv, self._sample_tv
            self._sample_tv = now
        if held:  # still in the operator's hands: the accelerometer reads the reaction to gravity
            accel = quat_rotate(quat_conj(quat), self._reaction)
        elif now is not None and before is not None and now[0] > before[0]:  # mean over the sample period
            mean = (now[1] - before[1]) / (now[0] - before[0]) + self._reaction
            accel = quat_rotate(quat_conj(quat), mean)
        return quat, accel

    def pose(self, q) -> None:
        """The operator's hands on the simulated robot: joints to ``q`` (rad/m, description order), at rest.

        For calibration by hand while torque is off: physics has not started (it waits for the first
        torque enable) or the joints are unpowered. The servos then read the new angles.
        """
        with self.bus.lock:
            set_pose(self.robot, q)
            self._publish(self.robot.read())

    def _sync_command(self) -> None:
        """Servo memory → Command, when any servo changed (called with the bus lock held)."""
        revisions = tuple(s.revision for s in self.servos)
        if revisions == self._revisions:
            return
        self._revisions = revisions
        self._sync_gains()
        q = np.array([m.joint(s.goal_angle()) for s, m in zip(self.servos, self.mounts, strict=True)])
        torque = np.array([s.torque_enabled for s in self.servos], dtype=bool)
        speed = np.array([abs(s.profile_speed() * m.m_per_rad) for s, m in zip(self.servos, self.mounts,
                                                                                 strict=True)])
        dq_max = None if not speed.any() else np.where(speed > 0, speed, np.inf)
        self.robot.write(Command(q=q, dq_max=dq_max, torque=torque))

    def _sync_gains(self) -> None:
        """Each servo's firmware controller (module doc) → its joint's MuJoCo actuators, when its bytes changed
        (`firmware_controller` returns the same object while they have not). A joint with fitted ``servo_params``
        keeps its fitted controller."""
        for i, (s, m) in enumerate(zip(self.servos, self.mounts, strict=True)):
            if s.mem[OPERATING_MODE] not in (3, 4, 5) or self.spec.names[i] in self._fitted:
                continue
            fw = s.firmware_controller()
            if fw is not self._controllers[i]:
                self._controllers[i] = fw
                self.robot.set_controller(i, fw.through(m.m_per_rad))

    def _publish(self, state) -> None:
        """Sim state → servo present items (bus lock held)."""
        effort = state.effort
        for i, (s, m) in enumerate(zip(self.servos, self.mounts, strict=True)):
            theta = m.horn(float(state.q[i]))
            omega = m.direction * float(state.dq[i]) / m.m_per_rad
            tau = m.direction * float(effort[i]) * m.m_per_rad if effort is not None else 0.0
            s.set_present(theta, omega, tau)
        if state.imu is not None:
            self.imu = (state.imu.quat.copy(), state.imu.accel.copy())
            if self._site is not None:
                mujoco.mj_objectVelocity(self.robot.model, self.robot.data, mujoco.mjtObj.mjOBJ_SITE,
                                    self._site, self._vel, 0)  # [angular; linear], world axes
                self._site_tv = (state.t, self._vel[3:].copy())

    def _run_guarded(self) -> None:
        try:
            self._run()
        except Exception as e:  # noqa: BLE001 - report; the servos keep their last state
            print(f"virtual bus: simulation stopped: {type(e).__name__}: {e}", file=sys.stderr)

    def _run(self) -> None:
        dt, lock = self.dt, self.bus.lock
        # the thread wakes at most every `POLL_S` (whole steps of dt each time): a 0.5 ms model woken every step
        # takes the interpreter from the bus server twice as often as a 1 ms one, for the same physics
        poll = max(dt, self.POLL_S)
        # The operator holds the robot in its start pose until torque first comes on: physics waits, so
        # a run through the bus starts from the same state as the same run on MuJoCo directly.
        while not self._stop.is_set():
            with lock:
                if any(s.torque_enabled for s in self.servos):
                    self._held = False
                    break
            self._stop.wait(poll)
        t0 = time.perf_counter()
        while not self._stop.is_set():
            behind = time.perf_counter() - t0 - self.sim_t
            if behind < poll:
                self._stop.wait(poll - behind)
                continue
            n, most = int(behind / dt), max(1, int(round(self.MAX_LAG_S / dt)))
            if n > most:
                self.bus.stats.sim_lag_s += (n - most) * dt
                t0 += (n - most) * dt
                n = most
            self._step(n)

    def _step(self, n: int) -> None:
        """``n`` model timesteps: the servos' clocks and memory in, physics, the new state out (the bus lock is held
        around the memory, not the physics: the server answers meanwhile)."""
        with self.bus.lock:
            self.bus.housekeeping()
            self._sync_command()
        self.robot.advance(n * self.dt)
        self.sim_t += n * self.dt
        state = self.robot.read()
        with self.bus.lock:
            self._publish(state)
        observer = self.observer
        if observer is not None:  # e.g. the live view of `felis virtual-bus --sim --live`: the stepping thread only
            observer(state)


class Lockstep:
    """A host robot on a lockstep bus (``virtual_bus(..., lockstep=True)``): its ``advance`` steps the bus's
    simulation by the loop's tick (`MujocoBackend.advance`) and its states carry the simulated time since the
    release, so the loop's clock is the simulation's. The host still runs the whole hardware path on the wall
    clock (`felis.loop.run_loop` paces it), but a host slowed by a loaded machine costs no simulated time: what is
    measured (a monitor's warning ahead of a fall) is the controller's, not the machine's. Everything else is the
    robot's (``robot``, e.g. `felis.drivers.dynamixel.DynamixelRobot`)."""

    def __init__(self, robot, backend: MujocoBackend):
        if not backend.lockstep:
            raise ParameterError("Lockstep needs a lockstep bus: virtual_bus(..., sim=True, lockstep=True)")
        self._robot, self._backend = robot, backend

    def __getattr__(self, name: str):
        return getattr(self._robot, name)

    def read(self):
        return replace(self._robot.read(), t=self._backend.sim_t)

    def advance(self, dt: float) -> None:
        self._robot.advance(dt)
        self._backend.advance(dt)


if __name__ == "__main__":
    sys.exit(main(build=bus_from_options))
