"""The replay of system identification: a recording's commands run in MuJoCo with given servo models
(`Replay`, `simulate`), to compare with what the servos did.

Model: the firmware's position controller per joint, P, I and D in control-table units, through the same code
the MuJoCo robots and the virtual bus's servos run (`felis.sim.servo.controller`, `configure_joint`: the
position actuator with kp and kd, MuJoCo's ``pid`` actuator ``<joint>_i`` for the integral, added here to
every joint that lacks it), plus damping, armature and friction on the joint. The setup (`Recording.setup`):
the robot's MuJoCo model (``"robot"``), or one bare horn per joint (``"bench"``, `bench_model`: the virtual
bus's standalone servo exactly, `felis.drivers.virtual.horn.HornSim`, in joint units).

Timing: a servo applies a goal when the packet arrives and reports the latest state it has, so the replay
(`simulate`) applies command k from ``t_write_end,k + latency_s`` and samples state k at ``t_read_start,k``
(the times `record` took, on the recording's time base), with a zero-order hold on the commands in between,
at the model timestep (1 ms) with sub-step timing: a command arriving inside a step weights that step's
control by the time it is in force, a read between two steps interpolates them (so the error is smooth in the
parameters and in the latency, which `fit` fits). On the emulator's time base (a virtual bus on a `StepClock`)
the commands land on the physics grid and the true latency is 0: a replay with the true gains reproduces the
recording to the encoder's resolution.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from felis.calib.sysid.model import default_params
from felis.calib.sysid.recording import Recording
from felis.errors import SysidError
from felis.sim.servo import ServoParams
from felis.spec import RobotSpec

_SCHEDULES = 64  # cached replay schedules (one per segment and latency)


def bench_model(spec: RobotSpec):
    """One bare horn per joint of ``spec``, as the virtual bus's standalone servo (`HornSim`): a hinge with
    the servo's armature and back-EMF damping, no load, no gravity, no contacts, the firmware's controller's
    actuators; in joint units (a prismatic joint's horn seen through its transmission)."""
    import mujoco

    from felis.calib.sysid.model import default_params
    from felis.drivers.virtual.horn import PHYSICS_DT, add_controller

    start = default_params(spec)
    ms = mujoco.MjSpec()
    ms.option.timestep = PHYSICS_DT
    ms.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    ms.option.gravity = [0.0, 0.0, 0.0]
    ms.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    for k, j in enumerate(spec.joints):
        body = ms.worldbody.add_body(name=f"horn_{j.name}", pos=[0.05 * k, 0.0, 0.0])
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.005, 0, 0], mass=1e-6)
        body.add_joint(name=j.name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1],
                       damping=start[j.name].damping, armature=start[j.name].armature)
        a = ms.add_actuator(name=j.name, target=j.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_position(kp=1.0, kv=0.0)
        add_controller(ms, j.name, integral=True, feedforward=False)
    return ms.compile()


def _on_grid(x: np.ndarray) -> np.ndarray:
    """Times in steps, those within float noise of a whole step put on it."""
    n = np.rint(x)
    return np.where(np.abs(x - n) < 1e-6, n, x)


class Replay:
    """The recorded commands replayed in MuJoCo for a segment of ticks, with settable servo models.

    One compiled model is reused across evaluations (`fit` calls `run` hundreds of times).
    """

    def __init__(self, spec: RobotSpec, recording: Recording, params: Mapping[str, ServoParams] | None = None,
                 fixed_base: bool | None = None, latency_s: float | None = None):
        import mujoco  # here, not at module level: MuJoCo is heavy and only the replay needs it

        from felis.sim.servo import JointActuators, add_controller, controller

        if recording.robot != spec.name or tuple(recording.joints) != spec.names:
            raise SysidError(f"the recording is of {recording.robot!r}, not of {spec.name!r}")
        self._mj = mujoco
        self._controller = controller
        self.spec, self.rec = spec, recording
        self.latency_s = recording.latency_s if latency_s is None else float(latency_s)
        if recording.setup == "bench":
            self.model = bench_model(spec)
        else:
            from felis.sim.robot import MujocoRobot

            lacking = [j.name for j in spec.joints if controller(j).ki <= 0]  # MujocoRobot adds the others'

            def edit(ms) -> None:
                for name in lacking:
                    add_controller(ms, name, integral=True, feedforward=False)

            fixed = recording.fixed_base if fixed_base is None else fixed_base
            sim = MujocoRobot(spec, quantize=False, fixed_base=fixed, edit=edit)
            sim.connect()
            sim.arm()
            self.model = sim.model
            self._sim = sim  # keeps the model alive
        m = self.model
        self.data = mujoco.MjData(m)
        if recording.setup != "bench":
            self.data.qpos[:] = self._sim.data.qpos
        O = mujoco.mjtObj
        self.acts = [JointActuators.find(m, n) for n in spec.names]
        if any(a.position < 0 or a.integral < 0 for a in self.acts):
            raise SysidError(f"the {spec.name} model lacks a joint's position or integral actuator")
        jid = [mujoco.mj_name2id(m, O.mjOBJ_JOINT, n) for n in spec.names]
        self.qadr = np.array([m.jnt_qposadr[j] for j in jid])
        self.dadr = np.array([m.jnt_dofadr[j] for j in jid])
        # command k drives each joint's position and integral actuators (same setpoint); feedforward stays 0
        self._ctrl_idx = np.array([m.actuator_ctrladr[a.position] for a in self.acts]
                                  + [m.actuator_ctrladr[a.integral] for a in self.acts])
        self._ctrl_col = np.concatenate([np.arange(spec.n), np.arange(spec.n)])
        self.h = float(m.opt.timestep)
        self.params = default_params(spec)
        self.damping = np.zeros(spec.n)
        for name, p in self.params.items():
            self.set(name, p)
        for name, p in (params or {}).items():
            self.set(name, p)
        self._qpos0 = self.data.qpos.copy()
        self._schedules: dict[tuple, tuple] = {}

    def set(self, joint: str, p: ServoParams) -> None:
        """Joint ``joint`` runs servo model ``p`` (its ``pid``, else the description's gains) from now on."""
        from felis.sim.servo import configure_joint

        i = self.spec.index(joint)
        m, dof = self.model, self.dadr[i]
        configure_joint(m, self.acts[i], self._controller(self.spec.joints[i], p))
        m.dof_damping[dof] = p.damping
        m.dof_armature[dof] = p.armature
        m.dof_frictionloss[dof] = p.frictionloss
        self.damping[i] = p.damping
        self.params[joint] = p

    def _schedule(self, k0: int, k1: int, latency_s: float) -> tuple:
        """Boundary steps, the control for the step after each, and where the reads fall (cached)."""
        key = (k0, k1, latency_s)
        if key in self._schedules:
            return self._schedules[key]
        if len(self._schedules) >= _SCHEDULES:
            self._schedules.clear()
        rec, h = self.rec, self.h
        origin = rec.t_read[k0, 0]
        # command k0+j (j ≥ 1) takes effect at c[j-1] (in steps); before c[0] the command of tick k0 holds
        c = np.maximum.accumulate(np.maximum((rec.t_write[k0 + 1:k1, 1] + latency_s - origin) / h, 0.0))
        r = np.maximum((rec.t_read[k0:k1, 0] - origin) / h, 0.0)
        c, r = _on_grid(c), _on_grid(r)
        r_lo = np.floor(r).astype(np.int64)
        c_lo = np.floor(c).astype(np.int64)
        # a time on the step grid needs no boundary after it (the emulator's time base: all of them)
        bounds = np.unique(np.concatenate([[0], c_lo, c_lo[c > c_lo] + 1, r_lo, r_lo[r > r_lo] + 1]))
        cmds = rec.q_cmd[k0:k1]
        first = np.searchsorted(c, bounds, side="right")  # command in force at the boundary
        last = np.searchsorted(c, bounds + 1, side="left")  # ... and at the end of the step after it
        ctrl = cmds[first].copy()
        for b in np.flatnonzero(last > first):  # the command changes inside this step: time-weighted mean
            t0, acc = float(bounds[b]), np.zeros(cmds.shape[1])
            for j in range(first[b], last[b]):
                acc += (c[j] - t0) * cmds[j]
                t0 = c[j]
            ctrl[b] = acc + (bounds[b] + 1 - t0) * cmds[last[b]]
        lo = np.searchsorted(bounds, r_lo)
        hi = np.where(r > r_lo, lo + 1, lo)
        needed = np.zeros(len(bounds), dtype=bool)
        needed[lo] = needed[hi] = True
        out = (bounds, ctrl, needed, lo, hi, (r - r_lo)[:, None])
        self._schedules[key] = out
        return out

    def run(self, ticks: slice, latency_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Replay ``ticks`` from the measured state at its first tick: (q, effort) at every read.

        Sub-step timing: a command that arrives inside a model step contributes to that step's control
        in proportion to the time it is in force (exact for the linear part of the actuator); a read
        between two steps is interpolated linearly.
        """
        mj, m, d, rec = self._mj, self.model, self.data, self.rec
        k0, k1 = ticks.start or 0, ticks.stop if ticks.stop is not None else len(rec.q)
        lat = self.latency_s if latency_s is None else float(latency_s)
        bounds, ctrl, needed, lo, hi, frac = self._schedule(k0, k1, lat)
        mj.mj_resetData(m, d)
        d.qpos[:] = self._qpos0
        d.qpos[self.qadr] = rec.q[k0]
        d.qvel[self.dadr] = rec.dq[k0]
        d.act[:] = 0.0  # integrals start from zero (the segment starts at rest on its goal)
        cidx, ccol = self._ctrl_idx, self._ctrl_col
        d.ctrl[:] = 0.0
        d.ctrl[cidx] = rec.q_cmd[k0][ccol]
        mj.mj_forward(m, d)
        nb, n = len(bounds), self.spec.n
        qs, es = np.zeros((nb, n)), np.zeros((nb, n))
        qadr, dadr, damping = self.qadr, self.dadr, self.damping
        step = mj.mj_step
        cur = 0
        for b in range(nb):
            s = bounds[b]
            if s > cur:
                step(m, d, int(s - cur))
                cur = s
            if needed[b]:
                qs[b] = d.qpos[qadr]
                es[b] = d.qfrc_actuator[dadr] - damping * d.qvel[dadr]
            d.ctrl[cidx] = ctrl[b][ccol]
        q = qs[lo] + frac * (qs[hi] - qs[lo])
        e = es[lo] + frac * (es[hi] - es[lo])
        return q, e


def simulate(spec: RobotSpec, recording: Recording, params: Mapping[str, ServoParams] | None = None, *,
             fixed_base: bool | None = None, ticks: slice | None = None,
             latency_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Replay ``recording``'s commands in MuJoCo with ``params`` (joint -> ServoParams; others the datasheet
    servo at the description's gains).

    Zero-order hold on the commands at the recorded write times (+ latency), sampled at the recorded
    read times, at the model timestep; the replay starts from the measured state at the first tick
    of ``ticks`` (default: all). Returns (q, effort), ticks × joints.
    """
    return Replay(spec, recording, params, fixed_base=fixed_base, latency_s=latency_s).run(ticks or slice(None))
