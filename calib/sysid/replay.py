"""The replay of system identification: a recording's commands run in MuJoCo with given servo parameters
(`Replay`, `simulate`), to compare with what the servos did.

Timing: a servo applies a goal when the packet arrives and reports the latest state it has, so the replay
(`simulate`) applies command k from ``t_write_end,k + latency_s`` and samples state k at ``t_read_start,k``
(the times `record` took), with a zero-order hold on the commands in between, at the model timestep (1 ms)
with sub-step timing: a command arriving inside a step weights that step's control by the time it is in force,
a read between two steps interpolates them (so the error is smooth in the parameters and timing is not
rounded). ``latency_s`` (default ``LATENCY_S`` for realtime recordings, 0 for simulation) covers the bus
transfer and the servo's (or the virtual bus's 1 kHz physics thread's) next update.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from felis.calib.sysid.model import default_params
from felis.calib.sysid.recording import Recording
from felis.errors import SysidError
from felis.sim.servo import ServoParams
from felis.spec import RobotSpec


class Replay:
    """The recorded commands replayed in MuJoCo for a segment of ticks, with settable servo parameters.

    One compiled model is reused across evaluations (`fit` calls `run` hundreds of times).
    """

    def __init__(self, spec: RobotSpec, recording: Recording, params: Mapping[str, ServoParams] | None = None,
                 fixed_base: bool | None = None, latency_s: float | None = None):
        import mujoco  # here, not at module level: MuJoCo is heavy and only the replay needs it

        from felis.sim.robot import MujocoRobot

        if recording.robot != spec.name or tuple(recording.joints) != spec.names:
            raise SysidError(f"the recording is of {recording.robot!r}, not of {spec.name!r}")
        self._mj = mujoco
        self.spec, self.rec = spec, recording
        self.latency_s = recording.latency_s if latency_s is None else float(latency_s)
        fixed = recording.fixed_base if fixed_base is None else fixed_base
        sim = MujocoRobot(spec, quantize=False, fixed_base=fixed)
        sim.connect()
        sim.arm()  # torque on: gains in place
        self.model, self.data = sim.model, sim.data
        self._sim = sim  # keeps the model alive
        m = self.model
        O = mujoco.mjtObj
        jid = [mujoco.mj_name2id(m, O.mjOBJ_JOINT, n) for n in spec.names]
        self.act = np.array([mujoco.mj_name2id(m, O.mjOBJ_ACTUATOR, n) for n in spec.names])
        self.qadr = np.array([m.jnt_qposadr[j] for j in jid])
        self.dadr = np.array([m.jnt_dofadr[j] for j in jid])
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
        i = self.spec.index(joint)
        m, a, dof = self.model, self.act[i], self.dadr[i]
        m.actuator_gainprm[a, 0] = p.kp
        m.actuator_biasprm[a, 1] = -p.kp
        m.actuator_forcerange[a] = (-p.torque_limit, p.torque_limit)
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
        rec, h = self.rec, self.h
        origin = rec.t_read[k0, 0]
        # command k0+j (j ≥ 1) takes effect at c[j-1] (in steps); before c[0] the command of tick k0 holds
        c = np.maximum.accumulate(np.maximum((rec.t_write[k0 + 1:k1, 1] + latency_s - origin) / h, 0.0))
        r = np.maximum((rec.t_read[k0:k1, 0] - origin) / h, 0.0)
        r_lo = np.floor(r).astype(np.int64)
        c_lo = np.floor(c).astype(np.int64)
        bounds = np.unique(np.concatenate([[0], c_lo, c_lo + 1, r_lo, r_lo + 1]))
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
        needed = np.zeros(len(bounds), dtype=bool)
        needed[lo] = needed[lo + 1] = True
        out = (bounds, ctrl, needed, lo, (r - r_lo)[:, None])
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
        bounds, ctrl, needed, lo, frac = self._schedule(k0, k1, lat)
        mj.mj_resetData(m, d)
        d.qpos[:] = self._qpos0
        d.qpos[self.qadr] = rec.q[k0]
        d.qvel[self.dadr] = rec.dq[k0]
        d.ctrl[self.act] = rec.q_cmd[k0]
        mj.mj_forward(m, d)
        nb, n = len(bounds), self.spec.n
        qs, es = np.zeros((nb, n)), np.zeros((nb, n))
        act, qadr, dadr, damping = self.act, self.qadr, self.dadr, self.damping
        step = mj.mj_step
        cur = 0
        for b in range(nb):
            s = bounds[b]
            if s > cur:
                step(m, d, int(s - cur))
                cur = s
            if needed[b]:
                qs[b] = d.qpos[qadr]
                es[b] = d.actuator_force[act] - damping * d.qvel[dadr]
            d.ctrl[act] = ctrl[b]
        q = qs[lo] + frac * (qs[lo + 1] - qs[lo])
        e = es[lo] + frac * (es[lo + 1] - es[lo])
        return q, e


def simulate(spec: RobotSpec, recording: Recording, params: Mapping[str, ServoParams] | None = None, *,
             fixed_base: bool | None = None, ticks: slice | None = None,
             latency_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Replay ``recording``'s commands in MuJoCo with ``params`` (joint -> ServoParams; others datasheet).

    Zero-order hold on the commands at the recorded write times (+ latency), sampled at the recorded
    read times, at the model timestep; the replay starts from the measured state at the first tick
    of ``ticks`` (default: all). Returns (q, effort), ticks × joints.
    """
    return Replay(spec, recording, params, fixed_base=fixed_base, latency_s=latency_s).run(ticks or slice(None))
