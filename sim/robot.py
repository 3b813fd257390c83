"""`MujocoRobot`: the HAL's `Robot` on a MuJoCo model.

Physics runs at the model's timestep (2 kHz for the cat, 1 kHz for the arm); ``advance(dt)`` steps
``round(dt / timestep)`` times in one native call. Each actuated joint of the description is a
position actuator of the same name in the MJCF (its P term and D gain); the rest of the servo's firmware
controller (`felis.sim.servo.controller`: the description's operating mode and gains) is added at load
where the joint needs it: ``<joint>_i`` (MuJoCo's ``pid`` actuator, the integral, when I > 0) and
``<joint>_ff`` (the feedforward torque, when D or a feedforward gain > 0), the joint's total actuator force
clamped at the PWM limit's torque (mode 5: Goal Current's). All of it runs inside the physics step.
Velocity limits (``Command.dq_max``) start the firmware's profile generator (a rectangular velocity
profile at dq_max, `felis.sim.servo.Profile`); while a profile runs, the physics is stepped one step at a
time with the desired position, velocity and acceleration at the physics rate.

Torque off (connected, or ``Command.torque`` False) zeroes every gain: the joint
is then moved only by gravity, contacts, back-EMF damping and friction, like an unpowered servo; the
integral restarts from zero when torque comes back.
A tick's readings are one gather from MuJoCo's data (`felis.sim.gather`; the `State`'s arrays are views of that
one copy). They are quantised like the servo's (4096 ticks per turn, 0.229 rpm), ``effort`` is the motor
torque (the actuators' force on the joint minus back-EMF), ``height`` is the waist site's height above the floor.
``fixed_base=True`` hangs a floating-base robot on a stand (free joint removed, body lifted), as for
system identification (`felis.calib.sysid`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from importlib import resources
from pathlib import Path

import mujoco
import numpy as np

from felis.bodymodel import low_matrix
from felis.errors import FelisError, ModelMismatch, SimulationError
from felis.hal import Command, Faults, Imu, Lifecycle, RobotBase, State, Truth
from felis.servos import servo_model
from felis.sim.gather import Gather
from felis.sim.servo import (
    Controller,
    JointActuators,
    Profile,
    ServoParams,
    add_controller,
    configure_joint,
    controller,
    quantization_steps,
    servo_params,
)
from felis.spec import RobotSpec

MODELS_DIR = resources.files("felis.sim") / "models"
TOUCH_THRESHOLD_N = 1e-3
_min = np.minimum.reduce  # without ndarray.min's Python wrapper
STAND_LIFT_M = 0.25  # fixed base: the root body is lifted this much above its MJCF pose (the stand)


def collision_points(m: mujoco.MjModel, bodies) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points bounding the collision geometry of ``bodies`` from below, in their body frames.

    Returns (body (P,), point (P, 3), radius (P,)): the lowest point of the geometry is
    min over P of (p_body + R_body · point)_z − radius, exactly for boxes (8 corners, radius 0),
    spheres (the centre, r) and capsules (the two end centres, r); cylinders count as capsules and
    ellipsoids and meshes as spheres of their bounding radius (lower than the true point: on the safe
    side for a clearance check).
    """
    T = mujoco.mjtGeom
    out_b, out_p, out_r = [], [], []
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        if b not in bodies or not (m.geom_contype[g] or m.geom_conaffinity[g]):
            continue
        s, t = m.geom_size[g], int(m.geom_type[g])
        if t == int(T.mjGEOM_BOX):
            local = np.array([[x, y, z] for x in (-s[0], s[0]) for y in (-s[1], s[1]) for z in (-s[2], s[2])])
            r = np.zeros(8)
        elif t in (int(T.mjGEOM_CAPSULE), int(T.mjGEOM_CYLINDER)):
            local, r = np.array([[0.0, 0.0, -s[1]], [0.0, 0.0, s[1]]]), np.full(2, s[0])
        elif t == int(T.mjGEOM_SPHERE):
            local, r = np.zeros((1, 3)), np.array([s[0]])
        elif t == int(T.mjGEOM_PLANE):
            continue
        else:
            local, r = np.zeros((1, 3)), np.array([m.geom_rbound[g]])
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, m.geom_quat[g])
        out_b += [b] * len(local)
        out_p.append(m.geom_pos[g] + local @ rot.reshape(3, 3).T)
        out_r.append(r)
    if not out_b:
        return np.zeros(0, dtype=int), np.zeros((0, 3)), np.zeros(0)
    return np.array(out_b, dtype=int), np.concatenate(out_p), np.concatenate(out_r)



def model_path(spec: RobotSpec) -> Path:
    path = Path(str(MODELS_DIR / spec.model))
    if not path.is_file():
        raise ModelMismatch(f"{spec.source}: model: no MJCF file {spec.model!r} in {MODELS_DIR}")
    return path


def load_model(path: str | Path, fixed_base: bool = False,
               edit: Callable[[mujoco.MjSpec], None] | None = None) -> mujoco.MjModel:
    """Compile an MJCF file; ``fixed_base`` removes free joints and lifts their bodies by ``STAND_LIFT_M``;
    ``edit`` changes the `mujoco.MjSpec` before it is compiled (e.g. `felis.sim.batch` adds sensors).

    Keyframes lose the removed joints' 7 qpos / 6 qvel entries (the body stays where the MJCF puts it,
    lifted). Errors are `ModelMismatch` with MuJoCo's first line.
    """
    path = Path(path)
    try:
        if not fixed_base and edit is None:
            return mujoco.MjModel.from_xml_path(str(path))
        spec = mujoco.MjSpec.from_file(str(path))
        if edit is not None:
            edit(spec)
        free = [j for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_FREE] if fixed_base else []
        if free:
            before = spec.compile()
            drop_q, drop_v = [], []
            for j in free:
                jid = mujoco.mj_name2id(before, mujoco.mjtObj.mjOBJ_JOINT, j.name) if j.name else -1
                if jid >= 0:
                    drop_q += range(before.jnt_qposadr[jid], before.jnt_qposadr[jid] + 7)
                    drop_v += range(before.jnt_dofadr[jid], before.jnt_dofadr[jid] + 6)
            for k in spec.keys:
                if len(k.qpos) == before.nq:
                    k.qpos = np.delete(np.asarray(k.qpos), drop_q)
                if len(k.qvel) == before.nv:
                    k.qvel = np.delete(np.asarray(k.qvel), drop_v)
            for j in free:
                body = j.parent
                spec.delete(j)
                body.pos = np.asarray(body.pos) + (0.0, 0.0, STAND_LIFT_M)
        return spec.compile()
    except ValueError as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else "cannot load"
        raise ModelMismatch(f"{path}: {first}") from None


class MujocoRobot(RobotBase):
    """Simulated robot.

    Args:
        spec: the robot description.
        model: path to an MJCF file (default: ``felis/sim/models/<spec.model>``).
        servo: per-joint `ServoParams` overriding the datasheet model (e.g. from system
            identification); joints not named keep the datasheet values.
        quantize: report positions/velocities in encoder resolution, as a real servo does.
        fixed_base: weld a floating-base robot to the world (its free joint removed at load), with
            its root body lifted by ``STAND_LIFT_M``: the robot hangs on a stand, legs clear of the
            floor, as for system identification. No effect on a fixed-base model.
        edit: a function changing the model's `mujoco.MjSpec` before it compiles (`load_model`).
    """

    def __init__(self, spec: RobotSpec, model: str | Path | None = None,
                 servo: dict[str, ServoParams] | None = None, quantize: bool = True, fixed_base: bool = False,
                 edit: Callable[[mujoco.MjSpec], None] | None = None, full_controller: bool = False):
        super().__init__(spec)
        self.full_controller = full_controller
        self.fixed_base = fixed_base
        self._edit = edit
        self._model_file = Path(model) if model is not None else model_path(spec)
        self._servo_override = dict(servo or {})
        unknown = set(self._servo_override) - set(spec.names)
        if unknown:
            raise ModelMismatch(f"servo parameters for unknown joints: {', '.join(sorted(unknown))}")
        self.quantize = quantize
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self.substep_hook: Callable[[mujoco.MjModel, mujoco.MjData], None] | None = None
        self._goal = np.zeros(spec.n)
        self._dq_max: np.ndarray | None = None
        self._torque = np.zeros(spec.n, dtype=bool)
        self._all_on = False  # self._torque.all(), kept by _set_torque
        self._stiffness: np.ndarray | None = None  # `Command.stiffness` in force (None: every joint as described)

    # ------------------------------------------------------------------ connect / model checks
    def _connect(self) -> None:
        spec = self.spec
        self._ctl = [controller(j, self._servo_override.get(j.name)) for j in spec.joints]
        full = self.full_controller
        needs = [(j.name, full or c.ki > 0, full or c.kd > 0 or c.kff1 > 0 or c.kff2 > 0)
                 for j, c in zip(spec.joints, self._ctl, strict=True)]
        user_edit = self._edit

        def edit(ms: mujoco.MjSpec) -> None:
            if user_edit is not None:
                user_edit(ms)
            for name, integral, ff in needs:
                if integral or ff:
                    add_controller(ms, name, integral=integral, feedforward=ff)

        extra = any(i or f for _, i, f in needs)
        m = load_model(self._model_file, fixed_base=self.fixed_base, edit=edit if extra else user_edit)
        self.model, self.data = m, mujoco.MjData(m)
        n = spec.n
        self._qadr = np.zeros(n, dtype=int)
        self._dadr = np.zeros(n, dtype=int)
        self._act = np.zeros(n, dtype=int)
        for i, j in enumerate(spec.joints):
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j.name)
            if jid < 0:
                raise ModelMismatch(f"{self._model_file.name}: no joint {j.name!r} (from {spec.source})")
            want = mujoco.mjtJoint.mjJNT_SLIDE if j.kind == "prismatic" else mujoco.mjtJoint.mjJNT_HINGE
            if m.jnt_type[jid] != want:
                raise ModelMismatch(f"{self._model_file.name}: joint {j.name!r} is not {j.kind}")
            lo, hi = m.jnt_range[jid]
            if not (m.jnt_limited[jid] and abs(lo - j.lower) < 1e-6 and abs(hi - j.upper) < 1e-6):
                raise ModelMismatch(
                    f"{self._model_file.name}: joint {j.name!r} range {lo:.6g}…{hi:.6g} differs from "
                    f"{spec.source} ({j.lower:.6g}…{j.upper:.6g})")
            aid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, j.name)
            if aid < 0 or m.actuator_trnid[aid, 0] != jid:
                raise ModelMismatch(f"{self._model_file.name}: no actuator {j.name!r} driving joint {j.name!r}")
            self._act[i] = aid
            self._qadr[i], self._dadr[i] = m.jnt_qposadr[jid], m.jnt_dofadr[jid]
        self._m_per_rad = np.array([j.m_per_rad for j in spec.joints])
        self._lower, self._upper = spec.lower, spec.upper
        self._qstep, self._vstep = quantization_steps(self._m_per_rad)
        self._inv_qstep, self._inv_vstep = 1.0 / self._qstep, 1.0 / self._vstep
        self.servo = {j.name: self._servo_override.get(j.name) or servo_params(servo_model(j.servo),
                                                                               m_per_rad=j.m_per_rad)
                      for j in spec.joints}
        self._kp = np.array([self.servo[j.name].kp for j in spec.joints])
        self._damping = np.array([self.servo[j.name].damping for j in spec.joints])
        self._acts = [JointActuators.find(m, j.name) for j in spec.joints]
        for i, j in enumerate(spec.joints):
            p, aid, dof = self.servo[j.name], self._act[i], self._dadr[i]
            m.actuator_ctrlrange[aid] = (j.lower, j.upper)
            m.actuator_ctrllimited[aid] = 1
            m.dof_damping[dof] = p.damping
            m.dof_armature[dof] = p.armature
            m.dof_frictionloss[dof] = p.frictionloss
        # the integral's setpoint follows the position actuator's; the feedforward torque is set per step
        self._ictrl = np.array([m.actuator_ctrladr[a.integral] for a in self._acts if a.integral >= 0], dtype=int)
        self._ipos = np.array([i for i, a in enumerate(self._acts) if a.integral >= 0], dtype=int)
        self._iact = np.array([m.actuator_actadr[a.integral] for a in self._acts if a.integral >= 0], dtype=int)
        self._fctrl = np.array([m.actuator_ctrladr[a.feedforward] for a in self._acts if a.feedforward >= 0], dtype=int)
        self._fpos = np.array([i for i, a in enumerate(self._acts) if a.feedforward >= 0], dtype=int)
        self._set_fgain()
        self._profiles: list[Profile] | None = None
        self._sensors(m)
        W = mujoco.mjtWarning
        self._divergence = [self.data.warning[w] for w in (W.mjWARN_BADQPOS, W.mjWARN_BADQVEL, W.mjWARN_BADQACC)]
        self._faults = Faults.none(n)
        self._set_torque(np.zeros(n, dtype=bool))
        self._reset_data()

    def _set_fgain(self) -> None:
        self._fgain = np.array([(c.kd + c.kff1, c.kff2) for c, a in zip(self._ctl, self._acts, strict=True)
                                if a.feedforward >= 0]).reshape(-1, 2)

    def set_controller(self, joint: int, ctl: Controller) -> None:
        """Joint ``joint``'s firmware controller (joint units, `felis.sim.servo.controller`) from now on, e.g.
        gains written to a servo-in-the-loop servo. Its integral state is kept. An I, D or feedforward gain the
        model has no actuator for is a `ModelMismatch` (build with ``full_controller=True`` to allow any)."""
        acts = self._acts[joint]
        if (ctl.ki > 0 and acts.integral < 0) or ((ctl.kd > 0 or ctl.kff1 > 0 or ctl.kff2 > 0)
                                                 and acts.feedforward < 0):
            raise ModelMismatch(f"joint {self.spec.names[joint]!r}: the model was built without the actuators for "
                                f"I, D or feedforward gains (MujocoRobot(..., full_controller=True))")
        self._ctl[joint] = ctl
        configure_joint(self.model, acts, self._joint_ctl(joint), bool(self._torque[joint]))
        self._set_fgain()

    def _joint_ctl(self, joint: int) -> Controller:
        """Joint ``joint``'s controller with its `felis.hal.Command.stiffness` (P gain scaled) applied."""
        ctl = self._ctl[joint]
        s = 1.0 if self._stiffness is None else float(self._stiffness[joint])
        return ctl if s == 1.0 else replace(ctl, kp=ctl.kp * s)

    def _set_stiffness(self, stiffness: np.ndarray | None) -> None:
        """`felis.hal.Command.stiffness` (None: as described) into the joints whose value changed."""
        ones = np.ones(self.spec.n)
        new = ones if stiffness is None else np.asarray(stiffness, dtype=float)
        if new.shape != (self.spec.n,):
            raise ValueError(f"stiffness has {new.size} entries, robot has {self.spec.n} joints")
        changed = np.flatnonzero(new != (ones if self._stiffness is None else self._stiffness))
        self._stiffness = None if stiffness is None else new.copy()
        for i in changed:
            configure_joint(self.model, self._acts[i], self._joint_ctl(int(i)), bool(self._torque[i]))

    def _reset_data(self) -> None:
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        if m.nkey > 0:
            mujoco.mj_resetDataKeyframe(m, d, 0)
        self._goal = d.qpos[self._qadr].copy()
        self._dq_max = None
        self._profiles = None
        self._t_target = d.time
        self._set_ctrl(self._goal)
        mujoco.mj_forward(m, d)

    def _set_ctrl(self, q: np.ndarray, v: np.ndarray | None = None, a: np.ndarray | None = None) -> None:
        """The controller's references: the position setpoint (position and integral actuators) and the
        feedforward torque (kd + kff1)·v_d + kff2·a_d."""
        c = self.data.ctrl
        c[self._act] = q
        if self._ictrl.size:
            c[self._ictrl] = q[self._ipos]
        if self._fctrl.size:
            if v is None:
                c[self._fctrl] = 0.0
            else:
                c[self._fctrl] = self._fgain[:, 0] * v[self._fpos] + self._fgain[:, 1] * a[self._fpos]

    def _sensor_for(self, m, stype, objtype, objid) -> int | None:
        for s in range(m.nsensor):
            if m.sensor_type[s] == stype and m.sensor_objtype[s] == objtype and m.sensor_objid[s] == objid:
                return int(m.sensor_adr[s])
        return None

    def _sensors(self, m: mujoco.MjModel) -> None:
        sens = self.spec.sensors
        S, O = mujoco.mjtSensor, mujoco.mjtObj
        self._imu = None
        if sens.imu is not None:
            sid = mujoco.mj_name2id(m, O.mjOBJ_SITE, sens.imu)
            if sid < 0:
                raise ModelMismatch(f"{self._model_file.name}: no IMU site {sens.imu!r}")
            adr = [self._sensor_for(m, t, O.mjOBJ_SITE, sid)
                   for t in (S.mjSENS_FRAMEQUAT, S.mjSENS_GYRO, S.mjSENS_ACCELEROMETER)]
            if None in adr:
                raise ModelMismatch(f"{self._model_file.name}: IMU site {sens.imu!r} needs framequat, gyro "
                                    "and accelerometer sensors")
            self._imu = np.concatenate([np.arange(a, a + k) for a, k in zip(adr, (4, 3, 3), strict=True)])
        self._touch = None
        if sens.contacts:
            adrs = []
            for foot in sens.contacts:
                bid = mujoco.mj_name2id(m, O.mjOBJ_BODY, foot)
                found = None
                for s in range(m.nsensor):
                    if (m.sensor_type[s] == S.mjSENS_TOUCH and bid >= 0
                            and m.site_bodyid[m.sensor_objid[s]] == bid):
                        found = int(m.sensor_adr[s])
                if found is None:
                    raise ModelMismatch(f"{self._model_file.name}: foot {foot!r} has no touch sensor")
                adrs.append(found)
            self._touch = np.array(adrs)
        self._height_site = None
        if sens.height is not None:
            sid = mujoco.mj_name2id(m, O.mjOBJ_SITE, sens.height)
            if sid < 0:
                raise ModelMismatch(f"{self._model_file.name}: no height site {sens.height!r}")
            self._height_site = sid
        # ground truth for monitors (`felis.hal.Truth`): a floating robot with feet
        self._truth_root = None
        free = np.flatnonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
        if free.size and self._touch is not None:
            self._truth_root = int(m.jnt_bodyid[free[0]])
            self._feet = np.array([mujoco.mj_name2id(m, O.mjOBJ_BODY, f) for f in sens.contacts])
            feet = set(self._feet.tolist())
            robot = {b for b in range(m.nbody) if m.body_rootid[b] == m.body_rootid[self._truth_root]}
            lb, lp, self._low_r = collision_points(m, robot - feet)
            self._low_M = low_matrix(lb, lp, m.nbody) if lb.size else None
        self._gather_layout(m)

    def _gather_layout(self, m: mujoco.MjModel) -> None:
        """What `_read` takes from the data in one gather (`felis.sim.gather`), and where each piece lands."""
        n = self.spec.n
        parts = [("qpos", self._qadr), ("qvel", self._dadr), ("qfrc_actuator", self._dadr)]
        if self._imu is not None:
            parts.append(("sensordata", self._imu))
        if self._touch is not None:
            parts.append(("sensordata", self._touch))
        if self._height_site is not None:
            parts.append(("site_xpos", [3 * self._height_site + 2]))
        if self._truth_root is not None:
            b = self._truth_root
            parts += [("subtree_com", range(3 * b, 3 * b + 3)), ("subtree_linvel", range(3 * b, 3 * b + 3)),
                      ("xpos", (3 * self._feet[:, None] + np.arange(3)).ravel())]
            if self._low_M is not None:  # z − r = M · (row 3 of R_b and p_b,z of the bodies with points, 1)
                P = len(self._low_r)
                M = self._low_M.reshape(P, m.nbody, 4)
                low_bodies = np.flatnonzero(np.abs(M).sum(axis=(0, 2)) > 0)
                M = M[:, low_bodies]
                self._low_M = np.hstack([M[:, :, :3].reshape(P, -1), M[:, :, 3], -self._low_r[:, None]])
                parts += [("xmat", (9 * low_bodies[:, None] + np.arange(6, 9)).ravel()),
                          ("xpos", 3 * low_bodies + 2),
                          ("xmat", [8])]  # the world body's R[2, 2]: always 1, the constant for −r
        self._gather = Gather(self.data, parts)
        sl = iter(self._gather.slices)
        self._sl_q, self._sl_dq, self._sl_frc = next(sl), next(sl), next(sl)
        self._sl_qdq = slice(0, 2 * n)
        self._n = n
        self._qdq_inv = np.concatenate([self._inv_qstep, self._inv_vstep])
        self._qdq_step = np.concatenate([self._qstep, self._vstep])
        self._sl_imu = next(sl) if self._imu is not None else None
        self._sl_touch = next(sl) if self._touch is not None else None
        self._sl_height = next(sl).start if self._height_site is not None else None
        if self._truth_root is not None:
            self._sl_com, self._sl_comvel, self._sl_feet = next(sl), next(sl), next(sl)
            self._nfeet = len(self._feet)
            if self._low_M is not None:
                a, _, b = next(sl), next(sl), next(sl)
                self._sl_low = slice(a.start, b.stop)

    # ------------------------------------------------------------------ torque
    def _set_torque(self, mask: np.ndarray) -> None:
        """Torque on: the servo's controller; off: every gain zero (only damping and friction remain). A joint
        whose torque comes on starts its integral from zero, as the firmware does."""
        new = np.array(mask, dtype=bool)
        was = getattr(self, "_torque", np.zeros_like(new))
        self._torque = new
        self._all_on = bool(new.all())
        for i, acts in enumerate(self._acts):
            configure_joint(self.model, acts, self._joint_ctl(i), bool(new[i]))
        if self._iact.size and self.data is not None:
            turned_on = (new & ~was)[self._ipos] | ~new[self._ipos]
            self.data.act[self._iact[turned_on]] = 0.0

    def _arm(self) -> None:
        d = self.data
        self._goal = d.qpos[self._qadr].copy()  # goal = present: no jump
        self._set_ctrl(self._goal)
        self._dq_max = None
        self._profiles = None
        self._set_torque(np.ones(self.spec.n, dtype=bool))

    def _disarm(self) -> None:
        if self.model is not None:
            self._set_torque(np.zeros(self.spec.n, dtype=bool))

    # ------------------------------------------------------------------ I/O
    def _read(self) -> State:
        d = self.data
        if self._truth_root is not None:
            mujoco.mj_subtreeVel(self.model, d)
        v = self._gather.take()  # every reading of the tick in one copy; the fields below are views of it
        qvel = v[self._sl_dq]
        effort = v[self._sl_frc] - self._damping * qvel
        if self.quantize:  # whole encoder ticks and velocity units, as the servo reports them
            qdq = v[self._sl_qdq] * self._qdq_inv
            np.rint(qdq, out=qdq)
            qdq *= self._qdq_step
            q, dq = qdq[:self._n], qdq[self._n:]
        else:
            q, dq = v[self._sl_q], qvel
        imu = None
        if self._sl_imu is not None:
            a = self._sl_imu.start
            imu = Imu(quat=v[a:a + 4], gyro=v[a + 4:a + 7], accel=v[a + 7:a + 10])
        touch = None if self._sl_touch is None else v[self._sl_touch]
        contacts = None if touch is None else touch > TOUCH_THRESHOLD_N
        height = None if self._sl_height is None else float(v[self._sl_height])
        truth = None
        if self._truth_root is not None:
            low = math.nan
            if self._low_M is not None:  # z of the lowest point: R_b[2] · point + p_b,z − r (`low_matrix`)
                low = float(_min(self._low_M @ v[self._sl_low]))
            truth = Truth(com=v[self._sl_com], com_vel=v[self._sl_comvel],
                          feet=v[self._sl_feet].reshape(self._nfeet, 3), foot_force=touch, low=low)
        return State(t=float(d.time), q=q, dq=dq, effort=effort, imu=imu, contacts=contacts,
                     height=height, faults=self._faults, truth=truth)

    def _write(self, command: Command) -> Command:
        q = np.minimum(np.maximum(command.q, self._lower), self._upper)
        torque = command.torque
        if torque is not None:
            torque = np.asarray(torque, dtype=bool)
            if torque.shape != (self.spec.n,):
                raise ValueError(f"torque mask has {torque.size} entries, robot has {self.spec.n} joints")
            if not np.array_equal(torque, self._torque):
                self._set_torque(torque)
        elif not self._all_on:
            self._set_torque(np.ones(self.spec.n, dtype=bool))
        if command.stiffness is not None or self._stiffness is not None:
            self._set_stiffness(command.stiffness)
        self._goal = q
        self._dq_max = None if command.dq_max is None else np.abs(np.asarray(command.dq_max, dtype=float))
        if self._dq_max is None:
            self._profiles = None
            self._set_ctrl(q)
        else:  # the profile generator: a new profile from the desired state of the last one
            t = float(self.data.time)
            prev = self._profiles
            profiles = []
            for i in range(self.spec.n):
                if prev is not None and prev[i].active(t):
                    p0, v0, _ = prev[i].sample(t)
                else:
                    p0, v0 = float(self.data.ctrl[self._act[i]]), 0.0
                vmax = float(self._dq_max[i])
                profiles.append(Profile.move(t, p0, v0, float(q[i]), vmax if math.isfinite(vmax) and vmax > 0
                                             else math.inf, math.inf))
            self._profiles = profiles
        return Command(q=q, dq_max=command.dq_max, torque=torque, stiffness=command.stiffness)

    def _advance(self, dt: float) -> None:
        m, d = self.model, self.data
        # whole physics steps that keep simulated time on the loop's clock, whatever the rate
        self._t_target += dt
        nstep = int(round((self._t_target - d.time) / m.opt.timestep))
        if nstep <= 0:
            return
        profiles = self._profiles
        if profiles is not None and not any(p.active(d.time) for p in profiles):
            self._profiles = profiles = None
            self._set_ctrl(self._goal)
        if profiles is not None:  # the profile generator at the physics rate (module doc)
            n = self.spec.n
            ref = np.empty((3, n))
            for _ in range(nstep):
                for i, p in enumerate(profiles):
                    ref[:, i] = p.sample(d.time)
                self._set_ctrl(ref[0], ref[1], ref[2])
                mujoco.mj_step(m, d)
                if self.substep_hook is not None:
                    self.substep_hook(m, d)
        elif self.substep_hook is None:
            mujoco.mj_step(m, d, nstep)
        else:
            for _ in range(nstep):
                mujoco.mj_step(m, d)
                self.substep_hook(m, d)
        # On a non-finite or huge state MuJoCo counts a warning and resets the data.
        w0, w1, w2 = self._divergence
        if w0.number or w1.number or w2.number:
            raise SimulationError(f"{self.spec.name}: physics diverged (MuJoCo flagged non-finite or huge "
                                  "state and reset); the episode cannot continue")

    def _close(self) -> None:
        self.model = self.data = None

    # ------------------------------------------------------------------ sim-only helpers
    def reset(self) -> None:
        """Back to the model's initial state (keyframe 0 if any), time 0, goals at the present pose.

        Keeps the lifecycle state, so episodes can reuse one compiled model.
        """
        self._require(Lifecycle.CONNECTED, Lifecycle.ARMED, action="reset")
        if self._stiffness is not None:  # every joint as described again
            self._set_stiffness(None)
        self._reset_data()

    def body_id(self, name: str) -> int:
        bid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            names = [self.model.body(i).name for i in range(1, self.model.nbody)]
            raise FelisError(f"{self.spec.name} has no body {name!r}; bodies: {', '.join(names)}")
        return bid

    @property
    def root_body(self) -> int:
        """The robot's root body (child of the world); its subtree is the whole robot."""
        roots = np.flatnonzero(self.model.body_parentid[1:] == 0) + 1
        return int(roots[0]) if roots.size else 0

    @property
    def free_joint(self) -> int | None:
        """Address in qpos of the free (floating-base) joint, or None for a fixed-base robot."""
        free = np.flatnonzero(self.model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
        return int(self.model.jnt_qposadr[free[0]]) if free.size else None

    def mass(self) -> float:
        """Total mass of the robot (kg): the subtree of its root body."""
        return float(self.model.body_subtreemass[self.root_body])
