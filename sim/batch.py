"""Many drops at once: a batch of cats stepped in lockstep by `mujoco.rollout` on native threads (issue 21).

The sequential path (`felis.learning.landing.evaluate.LandingSim`) runs one cat through `felis.loop.run_loop`:
each 10 ms tick it reads the state, runs the controller, filters the command through the safety layer,
writes it and steps the physics 10 times, with a `felis.sim.landing.LandingRecorder` in the sub-step hook.
`DropBatch` does the same for B cats at once:

    per tick k:  obs (B) ← last step's state and sensors      (q in encoder ticks, IMU quaternion, waist z)
                 q* (B,n) ← controller(t, q, quat, h)          (numpy, the whole batch in one call)
                 q* ← SafetyLayer.filter_many(q*), clipped to the joint ranges (what `MujocoRobot.write` does)
                 rollout(B cats, 10 physics steps, ctrl = q*)  (threads; per-step state and sensordata back)

so the physics never leaves C between ticks and the policy runs once per tick for the whole batch.

**The verdict's truth from sensors.** Everything `LandingRecorder` reads from ``mjData`` at each physics step
comes back as sensor data (`verdict_sensors` adds them to the model; sensors change no dynamics): the
upper body's z-axis (``framezaxis``, its world z = R₂₂), the waist site's position, one ``contact`` sensor per
robot body against the floor (data ``found``) and the net force of all robot–floor contacts (its world z is
Σ normal forces on a flat floor: the peak impact). `truth` builds the same `LandingTruth` and the caller
judges it with the one `felis.scenarios.verdicts.landing_verdict`.

**Equal to the sequential path, within a stated tolerance.** `mj_step` starts its constraint solver from the
last step's accelerations (the warm start); `mujoco.rollout` takes a state without them, so each tick's
first step starts cold. With MuJoCo's Newton solver both converge to the same answer to ~1e-10, which
leaves free flight identical and makes contact-rich steps differ in the last digits; chaotic impacts can
grow that. ``tests/sim/test_batch.py`` states and checks the tolerance: joint angles and attitude before
touchdown within 1e-6, and the same verdict on the test drops. The body named in a verdict's reason is the
lowest-numbered body touching the floor at that step (the recorder names the first contact MuJoCo found).

Threads: ``nthread`` (default: every core); results do not depend on it (each cat is stepped alone).
"""

from __future__ import annotations

import copy
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import mujoco.rollout
import numpy as np

from felis.errors import ParameterError
from felis.hal import MIN_STIFFNESS
from felis.safety import SafetyConfig, SafetyLayer
from felis.scenarios.drop import Drop
from felis.scenarios.verdicts import WINDOW_S, LandingTruth
from felis.sim.robot import MujocoRobot
from felis.sim.scenarios import apply_drop
from felis.sim.servo import ServoParams, quantization_steps
from felis.spec import RobotSpec

PHYSICS_PER_TICK = 10  # 100 Hz control over 1 kHz physics
PREFIX = "felis_verdict_"
FLOOR = "floor"


def verdict_sensors(spec: RobotSpec) -> Callable[[mujoco.MjSpec], None]:
    """An `MjSpec` edit (``MujocoRobot(edit=…)``) adding the sensors the landing verdict is taken on (module
    doc): ``felis_verdict_up`` (root body z-axis), ``…waist`` (waist site position), ``…floor_<body>`` per body
    of the robot, ``…force`` (net robot–floor contact force)."""
    waist = spec.sensors.height
    if waist is None:
        raise ParameterError(f"{spec.name} has no waist height site (sensors.height): drops cannot be judged")

    def edit(ms: mujoco.MjSpec) -> None:
        m = ms.compile()  # names and the tree, before anything is added
        if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, FLOOR) < 0:
            raise ParameterError(f"{spec.name}'s model has no {FLOOR!r} geom: drops cannot be judged")
        roots = np.flatnonzero(m.body_parentid[1:] == 0) + 1
        root = m.body(int(roots[0])).name
        robot = [b for b in range(1, m.nbody) if m.body_rootid[b] == roots[0]]
        O, S = mujoco.mjtObj, mujoco.mjtSensor
        ms.add_sensor(name=PREFIX + "up", type=S.mjSENS_FRAMEZAXIS, objtype=O.mjOBJ_XBODY, objname=root)
        ms.add_sensor(name=PREFIX + "waist", type=S.mjSENS_FRAMEPOS, objtype=O.mjOBJ_SITE, objname=waist)
        for b in robot:
            s = ms.add_sensor(name=PREFIX + "floor_" + m.body(b).name, type=S.mjSENS_CONTACT, objtype=O.mjOBJ_BODY,
                              objname=m.body(b).name, reftype=O.mjOBJ_GEOM, refname=FLOOR)
            s.intprm[0], s.intprm[1], s.intprm[2] = 1 << int(mujoco.mjtConDataField.mjCONDATA_FOUND), 0, 1
        s = ms.add_sensor(name=PREFIX + "force", type=S.mjSENS_CONTACT, objtype=O.mjOBJ_XBODY, objname=root,
                          reftype=O.mjOBJ_GEOM, refname=FLOOR)
        s.intprm[0], s.intprm[1], s.intprm[2] = 1 << int(mujoco.mjtConDataField.mjCONDATA_FORCE), 3, 1  # netforce

    return edit


@dataclass
class BatchResult:
    """One cat's drop: the verdict's truth, the peak ground force (body weights), the upper body's up-axis z
    at the end of its run, and whether the physics diverged (MuJoCo reset the cat: nothing after is the drop's)."""

    truth: LandingTruth
    peak_impact: float
    final_up_z: float
    diverged: bool


class DropBatch:
    """B drops of one robot stepped together (module doc). One compiled model, reused for every batch.

    Args:
        spec: the robot (floating base, waist site, foot contacts).
        servo: per-joint servo parameters, as `MujocoRobot` takes them (a design study's servos).
        nthread: rollout threads (default: every core).
        safety: the safety layer's configuration (`felis.loop.run_loop`'s default when None).
        sensors: an `MjSpec` edit adding more sensors for ``record`` (e.g. the landing features' body points).
        timestep: the physics step in s (default the model's, 1 ms): each control tick runs as many steps as
            fit (a whole number; `bench/landing_height.py`: from 3 m the impact's verdict depends on the
            step's phase at the first contact, and a finer step shows by how much).
    """

    def __init__(self, spec: RobotSpec, *, servo: dict[str, ServoParams] | None = None, nthread: int | None = None,
                 safety: SafetyConfig | None = None, sensors: Callable[[mujoco.MjSpec], None] | None = None,
                 timestep: float | None = None):
        self.spec = spec
        verdict = verdict_sensors(spec)

        def edit(ms: mujoco.MjSpec) -> None:
            verdict(ms)
            if sensors is not None:
                sensors(ms)

        self.robot = MujocoRobot(spec, servo=servo, edit=edit)
        self.robot.connect()
        self.robot.arm()  # gains on, as in every episode
        m = self.model = self.robot.model
        if timestep is not None:
            if not (math.isfinite(timestep) and 0 < timestep <= 0.01):
                raise ParameterError(f"a physics step must be within (0, 0.01] s, got {timestep}")
            m.opt.timestep = float(timestep)
        if self.robot.free_joint is None:
            raise ParameterError(f"{spec.name} is fixed to the world: only a free-floating robot can be dropped")
        self.nthread = max(1, int(nthread or os.cpu_count() or 1))
        self._pool = mujoco.rollout.Rollout(nthread=self.nthread)
        self._datas = [mujoco.MjData(m) for _ in range(self.nthread)]
        self._models: list[mujoco.MjModel] = []  # the model once per cat of a tick (rollout's unchecked call)
        self._stiff: dict[bytes, mujoco.MjModel] = {}  # compliant copies of the model (`_stiff_model`)
        self.nstate = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        r = self.robot
        self._qadr = 1 + np.asarray(r._qadr)  # FULLPHYSICS: time, qpos, qvel, …
        self._act = np.asarray(r._act)
        self._qstep, _ = quantization_steps(np.array([j.m_per_rad for j in spec.joints]))
        self._imu = np.asarray(r._imu[:4]) if r._imu is not None else None
        adr = lambda name: int(m.sensor_adr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SENSOR, PREFIX + name)])  # noqa: E731
        self._up = adr("up") + 2
        self._waist = adr("waist") + 2
        self.adr = {"up_z": self._up, "waist_z": self._waist}  # sensor data addresses, for ``record``
        self._force = adr("force") + 2
        floor = [s for s in range(m.nsensor) if m.sensor(s).name.startswith(PREFIX + "floor_")]
        self._floor_adr = np.array([m.sensor_adr[s] for s in floor])
        self._floor_body = np.array([m.sensor_objid[s] for s in floor])
        feet = {r.body_id(f) for f in spec.sensors.contacts}
        self._is_foot = np.array([b in feet for b in self._floor_body])
        self.bodies = tuple(m.body(b).name for b in range(m.nbody))
        self.weight = r.mass() * float(np.linalg.norm(m.opt.gravity))
        self.safety = SafetyLayer(spec, 1.0 / 100.0, safety)
        self.last_ctrl: np.ndarray | None = None  # (active, 10, nu): the controls of the last tick (benchmarks)

    def close(self) -> None:
        self._pool.close()
        self.robot.close()

    def __enter__(self) -> DropBatch:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _stiff_model(self, stiffness: np.ndarray) -> mujoco.MjModel:
        """The model with its position actuators' kp scaled by ``stiffness`` (per joint, clamped as the safety
        layer does), as `MujocoRobot` applies `felis.hal.Command.stiffness`; one copy per distinct value."""
        s = np.minimum(np.maximum(np.asarray(stiffness, dtype=float), MIN_STIFFNESS), 1.0)
        if np.all(s == 1.0):
            return self.model
        key = s.tobytes()
        m = self._stiff.get(key)
        if m is None:
            m = self._stiff[key] = copy.deepcopy(self.model)
            for i in np.flatnonzero(s != 1.0):
                a = self._act[i]
                m.actuator_gainprm[a, 0] *= s[i]
                m.actuator_biasprm[a, 1] *= s[i]
        return m

    # ------------------------------------------------------------------ start states
    def initial(self, drops: Sequence[Drop]) -> tuple[np.ndarray, np.ndarray]:
        """(states (B, nstate), sensordata (B, nsensordata)) of the cats released as ``drops`` say: the model's
        pose, turned and lifted by `felis.sim.scenarios.apply_drop`, at rest, time 0."""
        r, m = self.robot, self.model
        states = np.empty((len(drops), self.nstate))
        sens = np.empty((len(drops), m.nsensordata))
        for i, d in enumerate(drops):
            r.reset()
            apply_drop(r, d)
            mujoco.mj_getState(m, r.data, states[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
            sens[i] = r.data.sensordata
        return states, sens

    # ------------------------------------------------------------------ the run
    def run(self, drops: Sequence[Drop], controller, standing_waist_m: float, *, rate_hz: float = 100.0,
            margin_s: float = 1.0, ticks: Sequence[int] | None = None,
            record: Callable[[int, np.ndarray, np.ndarray, np.ndarray], None] | None = None) -> list[BatchResult]:
        """Drop every cat of ``drops`` under ``controller`` and return one `BatchResult` per drop, in order.

        ``controller``: ``reset(t (B,), q (B, n))`` then, each tick, ``controller(t, q, quat, h) -> (B, n)``
        position targets (q in encoder ticks, quat (w, x, y, z) from the IMU, h the waist height). Each cat
        runs ``round((fall_time + margin_s) · rate_hz)`` ticks (as `LandingSim`) unless ``ticks`` gives them.
        ``record(k, states (B, S, nstate), sensordata (B, S, nsens), active)`` (S: physics steps a tick, 10 at the
        model's 1 ms): called after each tick's physics with the rows of the cats still running (``active``: their
        indices), e.g. to record motion."""
        per = int(round(1.0 / (rate_hz * self.model.opt.timestep)))
        if per < 1 or abs(rate_hz * self.model.opt.timestep * per - 1.0) > 1e-9:
            raise ParameterError(f"the batch runs whole physics steps per tick: rate {rate_hz} Hz does not divide "
                                 f"into {self.model.opt.timestep:g} s steps")
        B = len(drops)
        if B == 0:
            return []
        n_ticks = (np.array([int(round((d.fall_time + margin_s) * rate_hz)) for d in drops]) if ticks is None
                   else np.asarray(ticks, dtype=int))
        m = self.model
        state, sens = self.initial(drops)
        t = state[:, 0].copy()
        q = self._quantize(state[:, self._qadr])
        quat = sens[:, self._imu] if self._imu is not None else np.tile([1.0, 0, 0, 0], (B, 1))
        controller.reset(t, q)
        last = np.clip(q, self.safety.lower, self.safety.upper)
        lower, upper = self.spec.lower, self.spec.upper
        # the verdict's rows, per cat: touchdown step index into the recorded arrays, and the arrays
        steps = int(n_ticks.max()) * per
        up = np.full((B, steps), np.nan)
        waist = np.full((B, steps), np.nan)
        tt = np.full((B, steps), np.nan)
        floor_body = np.full((B, steps), -1, dtype=np.int32)
        off_foot = np.full((B, steps), -1, dtype=np.int32)
        peak = np.zeros(B)
        final_up = sens[:, self._up].copy()
        diverged = np.zeros(B, dtype=bool)
        ctrl = np.zeros((B, per, m.nu))
        out_state = np.empty((B, per, self.nstate))
        out_sens = np.empty((B, per, m.nsensordata))
        active = np.arange(B)
        h = sens[:, self._waist].copy()
        for k in range(int(n_ticks.max())):
            active = active[n_ticks[active] > k]
            if active.size == 0:
                break
            a = active
            cmd = controller(t, q, quat, h)
            cmd = self.safety.filter_many(cmd, last)
            last = sent = np.minimum(np.maximum(cmd, lower), upper)  # what MujocoRobot.write sends
            na = a.size
            c = ctrl[:na]
            c[:, :, self._act] = sent[a][:, None, :]
            st, sd = out_state[:na], out_sens[:na]
            self.last_ctrl = c
            stiffness = getattr(controller, "stiffness", None)  # `Command.stiffness` per cat, when any is soft
            if stiffness is not None:
                models = [self._stiff_model(stiffness[i]) for i in a]
                self._models = []
            else:
                if len(self._models) != na:
                    self._models = [m] * na
                models = self._models
            self._pool.rollout(models, self._datas, np.ascontiguousarray(state[a]), c, nstep=per,
                               state=st, sensordata=sd, skip_checks=True,
                               chunk_size=max(1, na // (self.nthread * 16)))  # a thread waits ≤ 1/16 at the end
            # divergence: MuJoCo resets a cat whose state went non-finite (its time goes back)
            tnow = st[:, :, 0]
            bad = (np.diff(np.concatenate([t[a, None], tnow], axis=1), axis=1) <= 0).any(axis=1)
            bad |= ~np.isfinite(st[:, -1, :]).all(axis=1)
            diverged[a[bad]] = True
            lo = k * per
            sl = slice(lo, lo + per)
            tt[a, sl] = tnow
            up[a, sl] = sd[:, :, self._up]
            waist[a, sl] = sd[:, :, self._waist]
            found = sd[:, :, self._floor_adr] > 0  # (na, 10, bodies)
            anyb = found.any(axis=2)
            floor_body[a, sl] = np.where(anyb, self._floor_body[np.argmax(found, axis=2)], -1)
            off = found & ~self._is_foot
            anyo = off.any(axis=2)
            off_foot[a, sl] = np.where(anyo, self._floor_body[np.argmax(off, axis=2)], -1)
            peak[a] = np.maximum(peak[a], np.abs(sd[:, :, self._force]).max(axis=1))
            final_up[a] = sd[:, -1, self._up]
            if record is not None:
                record(k, st, sd, a)
            state[a] = st[:, -1]
            t[a] = tnow[:, -1]
            q[a] = self._quantize(st[:, -1, self._qadr])
            if self._imu is not None:
                quat[a] = sd[:, -1][:, self._imu]
            h[a] = sd[:, -1, self._waist]
        out = []
        for i in range(B):
            rows = np.flatnonzero(floor_body[i] >= 0)
            if rows.size:  # touchdown to touchdown + WINDOW_S, what the recorder keeps
                i0 = int(rows[0])
                stop = np.flatnonzero(tt[i, i0:] >= tt[i, i0] + WINDOW_S - 1e-9)
                i1 = i0 + (int(stop[0]) + 1 if stop.size else int(np.count_nonzero(np.isfinite(tt[i, i0:]))))
                sel = slice(i0, i1)
            else:
                sel = slice(0, 0)
            truth = LandingTruth(t=tt[i, sel], up_z=up[i, sel], waist_m=waist[i, sel], floor_body=floor_body[i, sel],
                                 off_foot_body=off_foot[i, sel], bodies=self.bodies,
                                 standing_waist_m=float(standing_waist_m))
            out.append(BatchResult(truth, float(peak[i] / self.weight) if self.weight > 0 else 0.0,
                                   float(final_up[i]), bool(diverged[i])))
        return out

    def _quantize(self, q: np.ndarray) -> np.ndarray:
        """Joint positions as the servo reports them: whole encoder ticks (`MujocoRobot` with ``quantize``)."""
        out = np.rint(q * (1.0 / self._qstep))
        out *= self._qstep
        return out
