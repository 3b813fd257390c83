"""The horn of an emulated servo (`HornModel`, inherited by `VirtualServo`): how the horn angle shows in the
control table, how the horn moves on its own, and the Bus Watchdog that stops it; `Mount` maps the horn to
its joint.

Position frame: the horn angle θ (rad, 0 at the centre tick 2048, positive counter-clockwise) gives

    Present Position = 2048 + s·round(θ / (2π/4096)) + Homing Offset      s = −1 if Drive Mode bit 0 else +1

and Goal Position is read in the same frame. Present Velocity = s·ω in 0.229 rpm units; Present
Current = s·τ / kt in the model's current unit with kt = stall torque / stall current (XL330 1.47 A,
XM430 2.3 A); the XL430's address 126 is Present Load = s·τ / stall torque in 0.1 %. Moving = 1 while
|Present Velocity| > Moving Threshold. Present Input Voltage is the datasheet's nominal supply,
Present Temperature a constant 32 °C, Realtime Tick counts milliseconds mod 32768.

Standalone dynamics (no simulation): the firmware's controller (`Firmware`, below) drives the horn through the
same MuJoCo actuators the simulated robots use (`add_controller`, `configure_joint`), here on a one-joint model:
the horn alone (the servo's reflected rotor inertia, back-EMF damping, no load, no gear friction and no gravity, so
an unloaded horn comes to rest exactly on its goal). It is stepped lazily at 1 kHz from the wall clock (or any
``clock``) whenever the servo is accessed, in whole physics steps; a horn at rest on its goal is not stepped.
Torque (and so current) is the motor torque: the actuators' force minus the back-EMF. Torque off: the horn
stays where it is.

The firmware's position controller (ROBOTIS e-Manual, X series, "Position PID Gain (80, 82, 84), Feedforward
1st/2nd Gains (88, 90)" and its control block diagram; e.g. https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/)::

    PWM = KPP·e + KPI·Σe + KPD·Δe + KFF1·v_d + KFF2·a_d,   clipped at ±PWM Limit (±885 = full duty)
    KPP = P/128   KPI = I/65536   KPD = D/16   KFF1 = FF1/4   KFF2 = FF2/4

with e = p_d − p in ticks, Σ and Δ per control period ("the constant in each equation includes the sampling
time"), and (p_d, v_d, a_d) from the profile generator (`Profile`). A geared DC motor at duty u/885 gives
τ = τ_stall·u/885 − (τ_stall/ω_no_load)·ω, so in SI, per radian of horn and with c = τ_stall·(4096/2π)/885::

    kp = c·P/128     ki = c·I/65536 / T     kd = c·D/16 · T     kff1 = c·FF1/4 · T     kff2 = c·FF2/4 · T²

(T = `POSITION_LOOP_S`), the force clamped at ±τ_stall·PWM Limit/885, plus joint damping τ_stall/ω_no_load
(back-EMF). Operating modes: 3 (position) and 4 (extended position: the same controller, no one-turn limit);
5 (current-based position): the same controller, its output also capped at Goal Current's torque
(kt·Goal Current, kt = stall torque / stall current); 1 (velocity): the velocity PI controller
(KVP = Velocity P/128, KVI = Velocity I/65536, error in 0.229 rpm units): its integral of the velocity error is
the position error against the integrated velocity trajectory, so it runs as the same actuators with
kp = c'·KVI/T and kv = c'·KVP (c' = τ_stall/885/(0.229 rpm in rad/s)) on that trajectory.

Still approximate (docs/servo-model.md): T is not published (ROBOTIS: the loop is "much faster than 1 kHz",
DynamixelSDK issue #534); 1 ms is assumed, the physics step, so I and D read in control-table units depend on it;
the controller runs continuously at the physics rate, the firmware's sampled D kick on a goal step is left out;
the anti-windup (the e-Manual's Ka) is a clamp of the integral at the PWM limit; β (the FF units) is taken as
ticks per control period; the motor's electrical time constant is ignored (current follows voltage at once);
in mode 5 the current loop's compensation of back-EMF is not modelled (the back-EMF damping stays) and the cap
applies to the controller's output.
"""

from __future__ import annotations

import copy
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field

from felis.drivers.dynamixel.controltable import CENTRE_TICK, address, control_table
from felis.drivers.virtual.memory import (
    BUS_WATCHDOG,
    DRIVE_MODE,
    GOAL_CURRENT,
    GOAL_POSITION,
    GOAL_VELOCITY,
    HOMING_OFFSET,
    ID,
    MOVING,
    MOVING_THRESHOLD,
    OPERATING_MODE,
    POSITION_MODES,
    PRESENT_CURRENT,
    PROFILE_VELOCITY,
    REALTIME_TICK,
    TORQUE_ENABLE,
    WATCHDOG_ERROR,
    WATCHDOG_UNIT_S,
)
from felis.errors import ParameterError
from felis.servos import PWM_LIMIT, RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, TICKS_PER_REV, ServoModel

CENTRE = CENTRE_TICK
POSITION_LOOP_S = 1e-3  # assumed period of the firmware's position loop (module doc: not published)
PHYSICS_DT = 1e-3  # the standalone horn's physics step (the arm's MJCF model uses the same; the cat's, 0.5 ms)
RAD_S2_PER_ACCEL_UNIT = 214.577 * 2.0 * math.pi / 3600.0  # Profile Acceleration unit, 214.577 rev/min²
# Rough reflected rotor inertia (kg·m²) and gear friction (N·m) per model, refined by sysid.
ARMATURE = {"XL330-M288-T": 5e-4, "XL430-W250-T": 5e-3, "XM430-W350-T": 1e-2}
FRICTION = {"XL330-M288-T": 0.005, "XL430-W250-T": 0.01, "XM430-W350-T": 0.02}

_PRESENT = struct.Struct("<hii")  # present current/load, velocity, position (at `PRESENT_CURRENT`)
I32 = struct.Struct("<i")
U16 = struct.Struct("<H")
I16 = struct.Struct("<h")
# the controller's items (addresses from the control table, as `felis.drivers.virtual.memory` takes them)
_GAINS = tuple(address(n) for n in ("position_p_gain", "position_i_gain", "position_d_gain", "feedforward_1st_gain",
                                    "feedforward_2nd_gain"))
VELOCITY_I, VELOCITY_P, PWM_LIMIT_ADDR, PROFILE_ACCELERATION = (
    address(n) for n in ("velocity_i_gain", "velocity_p_gain", "pwm_limit", "profile_acceleration"))
_CTL_SPAN = (min(VELOCITY_I, VELOCITY_P, *_GAINS), max(VELOCITY_I, VELOCITY_P, *_GAINS) + 2)  # the gains' bytes


@dataclass(frozen=True)
class Mount:
    """How a servo horn drives its joint: θ = direction·q/m_per_rad + zero + offset (rad)."""

    direction: int = 1
    zero: float = 0.0
    m_per_rad: float = 1.0
    offset: float = 0.0

    def horn(self, q: float) -> float:
        """Joint position (rad or m) → horn angle θ (rad around tick 2048)."""
        return self.direction * q / self.m_per_rad + self.zero + self.offset

    def joint(self, theta: float) -> float:
        """Horn angle θ → joint position."""
        return self.direction * (theta - self.zero - self.offset) * self.m_per_rad


# ============================================================== the firmware's controller (module doc)
def pwm_scale(servo: ServoModel) -> float:
    """c = τ_stall·(4096/2π)/885: N·m per radian of error for one PWM unit per tick (module doc)."""
    return servo.stall_torque * (TICKS_PER_REV / (2.0 * math.pi)) / PWM_LIMIT


@dataclass(frozen=True)
class Gains:
    """The position controller's control-table values (raw units): Position P/I/D Gain, Feedforward 1st/2nd Gain."""

    p: float
    i: float = 0.0
    d: float = 0.0
    ff1: float = 0.0
    ff2: float = 0.0

    @staticmethod
    def factory(model: str | int) -> Gains:
        """The model's factory values (its control table's defaults)."""
        t = control_table(model)
        return Gains(*(float(t.item(n).default) for n in ("position_p_gain", "position_i_gain", "position_d_gain",
                                                          "feedforward_1st_gain", "feedforward_2nd_gain")))


@dataclass(frozen=True)
class Controller:
    """The controller in SI per radian of horn (module doc): what the MuJoCo actuators run.

    force = kp·(p_d − p) + ki·∫(p_d − p)dt + kd·(v_d − v) + kff1·v_d + kff2·a_d, clipped at ±torque_limit;
    the integral is clamped at ±imax (anti-windup: ki·imax = torque_limit)."""

    kp: float  # N·m/rad
    ki: float = 0.0  # N·m/(rad·s)
    kd: float = 0.0  # N·m·s/rad
    kff1: float = 0.0  # N·m·s/rad (on the desired velocity)
    kff2: float = 0.0  # N·m·s²/rad (on the desired acceleration)
    torque_limit: float = math.inf  # N·m: PWM Limit's torque, or Goal Current's in mode 5

    @property
    def imax(self) -> float:
        return self.torque_limit / self.ki if self.ki > 0 and math.isfinite(self.torque_limit) else 0.0

    def through(self, m_per_rad: float) -> Controller:
        """The same controller seen through a transmission of ``m_per_rad`` (prismatic joint: force = τ/r)."""
        r2 = m_per_rad**2
        return Controller(self.kp / r2, self.ki / r2, self.kd / r2, self.kff1 / r2, self.kff2 / r2,
                          self.torque_limit / m_per_rad)


def factory_current_limit(model: str | int) -> float | None:
    """The model's factory Current Limit (A), or None where it has none (XL430)."""
    item = control_table(model).items.get("current_limit")
    return None if item is None else item.default * item.scale


def position_controller(servo: ServoModel, gains: Gains, *, pwm_limit: float = PWM_LIMIT,
                        current_limit_a: float | None = None) -> Controller:
    """Modes 3, 4, 5 (module doc): the e-Manual's KPP = P/128, KPI = I/65536, KPD = D/16, KFF = FF/4 in SI, per
    radian of horn; the output clipped at PWM Limit's torque and, in mode 5, at ``current_limit_a`` (Goal
    Current, A) times kt = stall torque / stall current."""
    c, T = pwm_scale(servo), POSITION_LOOP_S
    limit = servo.stall_torque * min(max(pwm_limit, 0.0), PWM_LIMIT) / PWM_LIMIT
    if current_limit_a is not None and servo.stall_current:
        limit = min(limit, servo.stall_torque / servo.stall_current * abs(current_limit_a))
    return Controller(kp=c * gains.p / 128.0, ki=c * gains.i / 65536.0 / T, kd=c * gains.d / 16.0 * T,
                      kff1=c * gains.ff1 / 4.0 * T, kff2=c * gains.ff2 / 4.0 * T * T, torque_limit=limit)


def velocity_controller(servo: ServoModel, p_gain: float, i_gain: float, *, pwm_limit: float = PWM_LIMIT) -> Controller:
    """Mode 1 (module doc): PWM = KVP·e_v + KVI·Σe_v (KVP = P/128, KVI = I/65536, e_v in 0.229 rpm units) run on the
    integrated velocity trajectory: kp = c'·KVI/T on its position error, kd = c'·KVP on its velocity error."""
    c = servo.stall_torque / PWM_LIMIT / RAD_S_PER_VELOCITY_UNIT
    limit = servo.stall_torque * min(max(pwm_limit, 0.0), PWM_LIMIT) / PWM_LIMIT
    return Controller(kp=c * i_gain / 65536.0 / POSITION_LOOP_S, kd=c * p_gain / 128.0, torque_limit=limit)


@dataclass
class Profile:
    """The profile generator (e-Manual, "Profile Velocity (112)", "Profile Acceleration (108)", Drive Mode bit 2):
    the desired trajectory (p_d, v_d, a_d) as constant-acceleration segments ``(t, p, v, a)`` from ``t``, then at
    rest on ``goal`` from ``end`` (``math.inf``: never, as in velocity mode).

    Velocity-based: Profile Velocity 0 is a step (no profile); Profile Acceleration 0 a rectangle (constant speed);
    both set, a trapezoid reaching the goal after d/v + v/a, or a triangle (2·√(d/a)) when d < v²/a.
    Time-based: Profile Velocity is the move's total time, Profile Acceleration its acceleration time (at most
    half of it). A new goal starts a new profile from the desired state of the last one (position and velocity),
    or from the present position at rest."""

    goal: float
    end: float = -math.inf
    segments: list[tuple[float, float, float, float]] = field(default_factory=list)

    def active(self, t: float) -> bool:
        return t < self.end

    def sample(self, t: float) -> tuple[float, float, float]:
        """(p_d, v_d, a_d) at time ``t``."""
        if t >= self.end or not self.segments:
            return self.goal, 0.0, 0.0
        seg = self.segments[0]
        for s in self.segments:
            if s[0] <= t:
                seg = s
            else:
                break
        t0, p, v, a = seg
        u = max(t - t0, 0.0)
        return p + v * u + 0.5 * a * u * u, v + a * u, a

    @staticmethod
    def step(goal: float) -> Profile:
        return Profile(goal)

    @staticmethod
    def move(t0: float, p0: float, v0: float, goal: float, vmax: float, amax: float) -> Profile:
        """Velocity-limited (``vmax``), acceleration-limited (``amax``; inf: a rectangle) move from (p0, v0) at t0."""
        if not vmax > 0 or not math.isfinite(vmax):
            return Profile.step(goal)
        segs: list[tuple[float, float, float, float]] = []
        t, p, v = t0, p0, v0
        if not math.isfinite(amax):  # rectangle: constant speed, no acceleration phases
            d = goal - p
            if d == 0.0:
                return Profile(goal, t0, [(t0, goal, 0.0, 0.0)])
            sgn = 1.0 if d > 0 else -1.0
            return Profile(goal, t0 + abs(d) / vmax, [(t0, p0, sgn * vmax, 0.0)])
        a = amax
        d = goal - p
        sgn = 1.0 if d > 0 else -1.0 if d < 0 else (-1.0 if v > 0 else 1.0)
        if v * sgn < 0 or v * v / (2 * a) > abs(d) + 1e-12:  # moving away or overshooting: stop first
            tb = abs(v) / a
            acc = -a if v > 0 else a
            segs.append((t, p, v, acc))
            p += v * tb / 2
            t += tb
            v = 0.0
            d = goal - p
            sgn = 1.0 if d >= 0 else -1.0
        dist, u0 = abs(d), abs(v)
        vc = min(vmax, math.sqrt(a * dist + u0 * u0 / 2))
        t1 = abs(vc - u0) / a
        d1 = (vc + u0) / 2 * t1
        t3 = vc / a
        d3 = vc * vc / (2 * a)
        t2 = max(dist - d1 - d3, 0.0) / vc if vc > 0 else 0.0
        segs.append((t, p, sgn * u0, sgn * (a if vc >= u0 else -a)))
        segs.append((t + t1, p + sgn * d1, sgn * vc, 0.0))
        segs.append((t + t1 + t2, p + sgn * (d1 + vc * t2), sgn * vc, -sgn * a))
        return Profile(goal, t + t1 + t2 + t3, segs)

    @staticmethod
    def timed(t0: float, p0: float, goal: float, total_s: float, accel_s: float) -> Profile:
        """Time-based profile from rest: the move takes ``total_s``, accelerating for ``accel_s`` (≤ total/2)."""
        if not total_s > 0:
            return Profile.step(goal)
        ta = min(max(accel_s, 0.0), total_s / 2)
        d = goal - p0
        if ta == 0.0:
            return Profile(goal, t0 + total_s, [(t0, p0, d / total_s, 0.0)])
        v = d / (total_s - ta)
        a = v / ta
        return Profile(goal, t0 + total_s, [(t0, p0, 0.0, a), (t0 + ta, p0 + v * ta / 2, v, 0.0),
                                            (t0 + total_s - ta, goal - v * ta / 2, v, -a)])

    @staticmethod
    def velocity(t0: float, p0: float, v0: float, v_goal: float, amax: float) -> Profile:
        """Velocity mode: the velocity trajectory ramps from v0 to ``v_goal`` at ``amax`` (inf: at once); its
        integral is the position reference. Never at rest."""
        if not math.isfinite(amax) or amax <= 0 or v0 == v_goal:
            return Profile(math.nan, math.inf, [(t0, p0, v_goal, 0.0)])
        tr = abs(v_goal - v0) / amax
        acc = amax if v_goal > v0 else -amax
        return Profile(math.nan, math.inf, [(t0, p0, v0, acc), (t0 + tr, p0 + (v0 + v_goal) / 2 * tr, v_goal, 0.0)])


def profile_for(mode: int, drive_mode: int, profile_velocity: int, profile_acceleration: int, t0: float,
                p0: float, v0: float, goal: float) -> Profile:
    """The profile a new goal starts (raw Profile Velocity / Acceleration, Drive Mode; `Profile`). ``goal`` is a
    position (rad of horn) in modes 3, 4, 5 and a velocity (rad/s) in mode 1."""
    acc = profile_acceleration * RAD_S2_PER_ACCEL_UNIT if profile_acceleration else math.inf
    if mode == 1:
        return Profile.velocity(t0, p0, v0, goal, acc)
    if drive_mode & 4:  # time-based: ms
        return Profile.timed(t0, p0, goal, profile_velocity / 1000.0, profile_acceleration / 1000.0)
    if not profile_velocity:
        return Profile.step(goal)
    return Profile.move(t0, p0, v0, goal, profile_velocity * RAD_S_PER_VELOCITY_UNIT, acc)


# -------------------------------------------------------------- the controller as MuJoCo actuators
def add_controller(ms, joint: str, *, integral: bool, feedforward: bool) -> None:
    """`mujoco.MjSpec` edit: the actuators that complete ``joint``'s position actuator (named ``joint``: kp on the
    position error, kd as its velocity gain) into the firmware's controller: ``<joint>_i``, MuJoCo's ``pid``
    actuator with its integral only (ki, imax; its control is the same setpoint), and ``<joint>_ff``, a motor
    whose control is the feedforward torque kd·v_d + kff1·v_d + kff2·a_d. The joint's total actuator force is
    clamped (``actuatorfrcrange``) by `configure_joint`. Both run inside the physics step (no Python per step)."""
    import mujoco

    if integral:
        a = ms.add_actuator(name=joint + "_i", target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_pid(kp=0.0, kv=0.0, ki=1.0, imax=1.0, ctrlspec=1)  # input "pos"; values set by configure_joint
    if feedforward:
        a = ms.add_actuator(name=joint + "_ff", target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_motor()
    for j in ms.joints:
        if j.name == joint:
            j.actfrclimited = mujoco.mjtLimited.mjLIMITED_TRUE
            j.actfrcrange = [-1e9, 1e9]


@dataclass(frozen=True)
class JointActuators:
    """Where one joint's controller lives in a compiled model: actuator ids (-1: absent), its dof and joint ids."""

    position: int
    integral: int
    feedforward: int
    joint: int
    dof: int

    @staticmethod
    def find(m, joint: str, position: str | None = None) -> JointActuators:
        import mujoco

        O = mujoco.mjtObj
        aid = mujoco.mj_name2id(m, O.mjOBJ_ACTUATOR, position or joint)
        jid = mujoco.mj_name2id(m, O.mjOBJ_JOINT, joint)
        return JointActuators(aid, mujoco.mj_name2id(m, O.mjOBJ_ACTUATOR, joint + "_i"),
                              mujoco.mj_name2id(m, O.mjOBJ_ACTUATOR, joint + "_ff"), jid, int(m.jnt_dofadr[jid]))


def configure_joint(m, acts: JointActuators, ctl: Controller, on: bool = True) -> None:
    """Put ``ctl`` into the compiled model ``m`` (torque off: every gain 0). An integral gain with no integral
    actuator, or feedforward gains with no feedforward actuator, are ValueError (the model was built without)."""
    if ctl.ki > 0 and acts.integral < 0:
        raise ValueError("this model has no integral actuator for the joint (built with I = 0)")
    k = 1.0 if on else 0.0
    lim = ctl.torque_limit if math.isfinite(ctl.torque_limit) else 1e9
    a = acts.position
    m.actuator_gainprm[a, 0] = k * ctl.kp
    m.actuator_biasprm[a, 1] = -k * ctl.kp
    m.actuator_biasprm[a, 2] = -k * ctl.kd
    m.actuator_forcerange[a] = (-lim, lim)
    m.actuator_forcelimited[a] = 1
    if acts.integral >= 0:
        i = acts.integral
        m.actuator_gainprm[i, 0] = k * ctl.ki
        m.actuator_biasprm[i, 1:3] = 0.0
        m.actuator_dynprm[i, 0] = ctl.imax if ctl.ki > 0 else 1.0
        m.actuator_forcerange[i] = (-lim, lim)
        m.actuator_forcelimited[i] = 1
    if acts.feedforward >= 0:
        m.actuator_forcerange[acts.feedforward] = (-lim, lim)
        m.actuator_forcelimited[acts.feedforward] = 1
    m.jnt_actfrcrange[acts.joint] = (-lim, lim)
    m.jnt_actfrclimited[acts.joint] = 1


class HornSim:
    """The standalone horn (module doc): a one-joint MuJoCo model of ``servo`` (its armature and back-EMF damping,
    no load), driven by the firmware's controller."""

    _templates: dict = {}  # model name → compiled one-joint model (copied per servo: compiling costs ms)

    @classmethod
    def template(cls, servo: ServoModel):
        """The compiled one-joint model of ``servo`` (once per model and process). `VirtualServo` asks for it when
        it is made, so that neither ``import mujoco`` nor the compile falls on the first reply after torque on."""
        m = cls._templates.get(servo.name)
        if m is None:
            import mujoco

            ms = mujoco.MjSpec()
            ms.option.timestep = PHYSICS_DT
            ms.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
            ms.option.gravity = [0.0, 0.0, 0.0]
            ms.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
            body = ms.worldbody.add_body(name="horn")
            body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.005, 0, 0], mass=1e-6)
            body.add_joint(name="horn", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1],
                           damping=servo.stall_torque / max(servo.no_load_speed, 1e-9),
                           armature=ARMATURE.get(servo.name, 1e-3))
            a = ms.add_actuator(name="horn", target="horn", trntype=mujoco.mjtTrn.mjTRN_JOINT)
            a.set_to_position(kp=1.0, kv=0.0)
            add_controller(ms, "horn", integral=True, feedforward=True)
            m = cls._templates[servo.name] = ms.compile()
        return m

    def __init__(self, servo: ServoModel):
        import mujoco

        self._mj = mujoco
        self.damping = servo.stall_torque / max(servo.no_load_speed, 1e-9)
        self.m = copy.deepcopy(self.template(servo))  # its own: `set_controller` writes the gains into it
        self.d = mujoco.MjData(self.m)
        self.acts = JointActuators.find(self.m, "horn")
        m = self.m
        self.ctrl = (int(m.actuator_ctrladr[self.acts.position]), int(m.actuator_ctrladr[self.acts.integral]),
                     int(m.actuator_ctrladr[self.acts.feedforward]))
        self.iact = int(m.actuator_actadr[self.acts.integral])
        self.ctl = Controller(0.0)

    def set_controller(self, ctl: Controller) -> None:
        self.ctl = ctl
        configure_joint(self.m, self.acts, ctl)

    def set_reference(self, p: float, v: float, a: float) -> None:
        c, ctl = self.d.ctrl, self.ctl
        c[self.ctrl[0]] = p
        c[self.ctrl[1]] = p
        c[self.ctrl[2]] = (ctl.kd + ctl.kff1) * v + ctl.kff2 * a

    def reset_integral(self) -> None:
        self.d.act[self.iact] = 0.0

    def step(self, theta: float, omega: float, n: int) -> tuple[float, float, float]:
        """``n`` physics steps from (θ, ω); returns (θ, ω, motor torque = actuator force − back-EMF)."""
        d = self.d
        d.qpos[0], d.qvel[0] = theta, omega
        self._mj.mj_step(self.m, d, n)
        w = float(d.qvel[0])
        return float(d.qpos[0]), w, float(d.qfrc_actuator[0]) - self.damping * w


class HornModel:
    """The horn of `VirtualServo` (module doc): its state, the present items it shows, its standalone dynamics
    and the Bus Watchdog. The servo's ``__init__`` and ``_boot`` set these attributes."""

    mem: bytearray
    datasheet: ServoModel
    mount: Mount
    clock: Callable[[], float]
    external: bool
    revision: int
    _theta: float
    _omega: float
    _torque: float
    _t: float
    _t0: float
    _last_rx: float
    _kt: float | None
    _current_unit: float | None

    def _cache_settings(self) -> None:
        """Items the dynamics read on every access, decoded once per change (the hot path)."""
        mem = self.mem
        self._s = -1 if mem[DRIVE_MODE] & 1 else 1
        self._homing = I32.unpack_from(mem, HOMING_OFFSET)[0]
        self._moving_threshold = I32.unpack_from(mem, MOVING_THRESHOLD)[0]


    def use_clock(self, clock: Callable[[], float]) -> None:
        """Run on ``clock`` from now on, e.g. a simulated one the host advances (`felis.calib.sysid.StepClock`):
        the horn is brought up to now on the old clock, then its times (physics, Realtime Tick from 0, Bus
        Watchdog) restart on the new one. The horn keeps its state."""
        self._advance()
        now = clock()
        self.clock = clock
        self._t = self._t0 = self._last_rx = now
        if getattr(self, "torque_on_at", None) is not None:
            self.torque_on_at = now
        st = self.__dict__.get("_standalone")
        if st is not None:
            st.tm = now
        self._refresh()

    # -------------------------------------------------------------- horn and frames
    @property
    def angle(self) -> float:
        """Horn angle θ (rad around the centre tick)."""
        self._advance()
        return self._theta

    @angle.setter
    def angle(self, theta: float) -> None:
        self._advance()
        self._theta = float(theta)
        self._omega = self._torque = 0.0
        self._refresh()

    @property
    def q(self) -> float:
        """The horn angle as a joint position, through the mounting."""
        return self.mount.joint(self.angle)

    def goal_angle(self) -> float:
        """Goal Position as a horn angle (rad)."""
        return self._s * (I32.unpack_from(self.mem, GOAL_POSITION)[0] - CENTRE - self._homing) * RAD_PER_TICK

    def profile_speed(self) -> float:
        """Profile Velocity as horn speed (rad/s); 0 = unlimited."""
        return I32.unpack_from(self.mem, PROFILE_VELOCITY)[0] * RAD_S_PER_VELOCITY_UNIT

    def hold_by_hand(self, q: float | Callable[[float], float] | None) -> None:
        """A hand on the joint (teaching by hand, a leader arm): while torque is off the horn sits where the hand
        puts it, ``q`` in joint units through the mounting, or ``q(t)`` with t in seconds of the servo's clock
        since this call (the hand's speed shows as Present Velocity). ``None`` lets go: the horn stays where the
        hand left it. While torque is on the servo holds its goal and the hand is ignored (a held horn is not
        backdriven here); a simulated horn (``external``) belongs to the physics and refuses a hand."""
        if self.external:
            raise ParameterError(f"servo {self.mem[ID]}: its horn is simulated; move the simulated joint instead")
        self._advance()
        if q is None:
            self.__dict__.pop("_hand", None)
            return
        fn = q if callable(q) else (lambda t, _q=float(q): _q)
        self._hand = (fn, self.clock())
        self._advance()

    def _by_hand(self) -> None:
        """The hand's pose now (`hold_by_hand`), while torque is off."""
        fn, t0 = self._hand
        t = self.clock() - t0
        q, q_before = float(fn(t)), float(fn(max(t - 1e-3, 0.0)))
        if not math.isfinite(q):
            raise ParameterError(f"servo {self.mem[ID]}: the hand's position {q} is not finite")
        theta = self.mount.horn(q)
        self._omega = (theta - self.mount.horn(q_before)) / 1e-3 if t >= 1e-3 else 0.0
        self._theta, self._torque = theta, 0.0

    def set_present(self, theta: float, omega: float, torque: float) -> None:
        """Horn state from outside (simulation): angle (rad), speed (rad/s), torque (N·m)."""
        self._theta, self._omega, self._torque = theta, omega, torque
        self._t = self.clock()
        self._refresh()

    def _refresh(self) -> None:
        """Present items from the horn state."""
        mem, s = self.mem, self._s
        pos = CENTRE + s * round(self._theta / RAD_PER_TICK) + self._homing
        vel = s * round(self._omega / RAD_S_PER_VELOCITY_UNIT)
        if self._kt is not None:
            cur = round(s * self._torque / self._kt / self._current_unit)
        else:
            cur = round(s * 1000.0 * self._torque / self.datasheet.stall_torque)
        _PRESENT.pack_into(mem, PRESENT_CURRENT, max(-32768, min(32767, cur)), vel, max(-2**31, min(2**31 - 1, pos)))
        mem[MOVING] = 1 if abs(vel) > self._moving_threshold else 0
        U16.pack_into(mem, REALTIME_TICK, int((self._t - self._t0) * 1000.0) & 0x7FFF)


    # -------------------------------------------------------------- standalone dynamics
    def _advance(self) -> None:
        """Bring the horn to now and refresh the present items (a simulated horn is published instead)."""
        if self.mem[BUS_WATCHDOG]:
            self.check_watchdog()
        if not self.external:
            self._integrate()
            if "_hand" in self.__dict__ and not self.mem[TORQUE_ENABLE]:
                self._by_hand()
            self._refresh()


    # -------------------------------------------------------------- Bus Watchdog
    def heard(self) -> None:
        """An instruction packet for this servo (its ID or broadcast) arrived: the Bus Watchdog restarts
        (after a trip that was already due, which a late packet does not undo)."""
        if self.mem[BUS_WATCHDOG]:
            self.check_watchdog()
        self._last_rx = self.clock()

    def check_watchdog(self, now: float | None = None) -> float | None:
        """Trip the Bus Watchdog if it is due (module doc). Returns the time from the last packet to the
        trip when it trips now, else None. A standalone horn is integrated up to the trip instant."""
        wd = self.mem[BUS_WATCHDOG]
        if not 1 <= wd <= 127 or not self.mem[TORQUE_ENABLE]:
            return None
        now = self.clock() if now is None else now
        due = self._last_rx + wd * WATCHDOG_UNIT_S
        if now < due:
            return None
        if not self.external:
            self._integrate(due)  # the horn moved under its last goal until the trip
        mem = self.mem
        pos = CENTRE + self._s * round(self._theta / RAD_PER_TICK) + self._homing
        I32.pack_into(mem, GOAL_POSITION, pos)  # stop: hold where it is
        I32.pack_into(mem, GOAL_VELOCITY, 0)
        if not self.external:
            self._theta = self._s * (pos - CENTRE - self._homing) * RAD_PER_TICK
            self._omega = self._torque = 0.0
        mem[BUS_WATCHDOG] = WATCHDOG_ERROR
        self.revision += 1
        return (due if not self.external else now) - self._last_rx

    @property
    def watchdog_tripped(self) -> bool:
        return self.mem[BUS_WATCHDOG] == WATCHDOG_ERROR


    # -------------------------------------------------------------- standalone dynamics
    def _integrate(self, until: float | None = None) -> None:
        """Standalone dynamics (module doc): the one-joint model stepped over the whole physics steps elapsed since
        the last access (or up to ``until``); settings and goals written since are taken up first."""
        now = self.clock() if until is None else until
        if self.external or now <= self._t:
            return
        before, self._t = self._t, now
        mem = self.mem
        mode = mem[OPERATING_MODE]
        st = self.__dict__.get("_standalone")
        if not mem[TORQUE_ENABLE] or mode not in POSITION_MODES and mode != 1:
            self._omega = self._torque = 0.0
            if st is not None:
                st.on = False
                st.tm = now
            return
        if st is None:
            st = self._standalone = _Standalone(self.datasheet, before)
        st.run(self, now)

    def firmware_controller(self) -> Controller:
        """The controller the servo's memory sets now (operating mode, gains, PWM Limit, Goal Current in mode 5);
        made again only when those bytes changed (a goal write changes none of them: the hot path of a bus loop)."""
        mem = self.mem
        key = (mem[OPERATING_MODE], bytes(mem[_CTL_SPAN[0]:_CTL_SPAN[1]]),
               bytes(mem[PWM_LIMIT_ADDR:PWM_LIMIT_ADDR + 2]), bytes(mem[GOAL_CURRENT:GOAL_CURRENT + 2]))
        cached = self.__dict__.get("_ctl_cache")
        if cached is not None and cached[0] == key:
            return cached[1]
        ctl = self._make_controller()
        self._ctl_cache = (key, ctl)
        return ctl

    def _make_controller(self) -> Controller:
        mem, ds = self.mem, self.datasheet
        pwm = U16.unpack_from(mem, PWM_LIMIT_ADDR)[0]
        if mem[OPERATING_MODE] == 1:
            return velocity_controller(ds, U16.unpack_from(mem, VELOCITY_P)[0], U16.unpack_from(mem, VELOCITY_I)[0],
                                       pwm_limit=pwm)
        cap = None
        if mem[OPERATING_MODE] == 5 and self._current_unit is not None:
            cap = abs(I16.unpack_from(mem, GOAL_CURRENT)[0]) * self._current_unit
        return position_controller(ds, Gains(*(U16.unpack_from(mem, a)[0] for a in _GAINS)), pwm_limit=pwm,
                                   current_limit_a=cap)

    def goal_velocity(self) -> float:
        """Goal Velocity as horn speed (rad/s), capped at the no-load speed."""
        v = self._s * I32.unpack_from(self.mem, GOAL_VELOCITY)[0] * RAD_S_PER_VELOCITY_UNIT
        vmax = self.datasheet.no_load_speed
        return max(-vmax, min(vmax, v))


class _Standalone:
    """A `HornModel`'s own physics (`HornSim`) and the firmware state around it: the model time (whole steps), the
    profile in force and the settings it was planned from."""

    CHUNK = 200  # steps between checks for rest on a long catch-up

    def __init__(self, servo: ServoModel, now: float):
        self.sim = HornSim(servo)
        self.tm = now  # model time: the last whole physics step
        self.on = False
        self.revision = -1
        self.key: tuple | None = None
        self.ctl: Controller | None = None
        self.profile = Profile.step(0.0)

    def _plan(self, horn: HornModel) -> None:
        """Take up the servo's memory: controller gains, and a new profile when the goal or its settings changed."""
        mem = horn.mem
        mode = mem[OPERATING_MODE]
        ctl = horn.firmware_controller()
        if ctl != self.ctl:
            self.sim.set_controller(ctl)
            self.ctl = ctl
        goal = horn.goal_velocity() if mode == 1 else horn.goal_angle()
        key = (mode, mem[DRIVE_MODE] & 4, goal, I32.unpack_from(mem, PROFILE_VELOCITY)[0],
               I32.unpack_from(mem, PROFILE_ACCELERATION)[0])
        if key != self.key or not self.on:
            if self.on and self.profile.active(self.tm):
                p0, v0, _ = self.profile.sample(self.tm)
            else:
                p0, v0 = horn._theta, horn._omega if mode == 1 else 0.0
            self.profile = profile_for(mode, mem[DRIVE_MODE], key[3], key[4], self.tm, p0, v0, goal)
            self.key = key
        if not self.on:
            self.sim.reset_integral()  # torque just came on: the integral starts from zero
            self.on = True
        self.revision = horn.revision

    def run(self, horn: HornModel, now: float) -> None:
        if horn.revision != self.revision or not self.on:
            self._plan(horn)
        n = int((now - self.tm) / PHYSICS_DT + 1e-9)
        if n <= 0:
            return
        prof, sim = self.profile, self.sim
        theta, omega = horn._theta, horn._omega
        if not prof.active(self.tm) and theta == prof.goal and omega == 0.0:  # at rest on the goal
            self.tm += n * PHYSICS_DT
            horn._torque = 0.0
            return
        torque = horn._torque
        while n > 0:
            if prof.active(self.tm):  # the profile at the physics rate: one step at a time
                sim.set_reference(*prof.sample(self.tm))
                k = 1
            else:
                sim.set_reference(prof.goal, 0.0, 0.0)
                k = min(n, self.CHUNK)
            theta, omega, torque = sim.step(theta, omega, k)
            self.tm += k * PHYSICS_DT
            n -= k
            if not prof.active(self.tm) and abs(theta - prof.goal) < 1e-9 and abs(omega) < 1e-7:
                theta, omega, torque = prof.goal, 0.0, 0.0  # arrived (far below a tick): rest exactly on the goal
                sim.reset_integral()
                self.tm += n * PHYSICS_DT
                break
        horn._theta, horn._omega, horn._torque = theta, omega, torque
