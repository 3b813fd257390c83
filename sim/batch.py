"""Many drops at once: a batch of cats stepped in lockstep on native threads by `mujoco.batch.Batch` (issue 21).

The sequential path (`felis.learning.landing.evaluate.LandingSim`) runs one cat through `felis.loop.run_loop`:
each 10 ms tick it reads the state, runs the controller, filters the command through the safety layer,
writes it and steps the physics 10 times, with a `felis.sim.landing.LandingRecorder` in the sub-step hook.
`DropBatch` does the same for B cats at once:

    per tick k:  obs (B) ← last step's state and sensors      (q in encoder ticks, IMU quaternion, waist z)
                 q* (B,n) ← controller(t, q, quat, h)          (numpy, the whole batch in one call)
                 q* ← SafetyLayer.filter_many(q*), clipped to the joint ranges (what `MujocoRobot.write` does)
                 Batch.rollout(B cats, 10 physics steps, ctrl = q*)  (threads; per-step state and sensordata back)

so the physics never leaves C between ticks and the policy runs once per tick for the whole batch.

**Bit for bit the sequential path.** `mujoco.batch.Batch` keeps each cat's whole integration state between
calls, the solver's warm start (``qacc_warmstart``) included, and steps it with `mj_step`: a cat's physics is
the loop's, bit for bit, at any thread count or batch order. (`mujoco.rollout` takes a state without the warm
start, so each tick's first step started cold and contact-rich steps differed in the last digits; that was this
module's stated tolerance until MuJoCo 4's `Batch`.) ``tests/sim/test_batch.py`` checks that every figure of a
drop's outcome is the loop's exactly under controllers that compute the same numbers in both paths (the pose
held, the motion library), and within 1e-9 under the evolved nets, whose batched ``einsum`` rounds in another
order than one cat's matrix product (compliant legs included).

**The verdict's truth from sensors.** Everything `LandingRecorder` reads from ``mjData`` at each physics step
comes back as sensor data (`verdict_sensors` adds them to the model; sensors change no dynamics): the
upper body's z-axis (``framezaxis``, its world z = R₂₂), the waist site's position, one ``contact`` sensor per
robot body against the floor (data ``found``) and the net force of all robot–floor contacts (its world z is
Σ normal forces on a flat floor: the peak impact). `truth` builds the same `LandingTruth` and the caller
judges it with the one `felis.scenarios.verdicts.landing_verdict`. The body named in a verdict's reason is the
lowest-numbered body touching the floor at that step (the recorder names the first contact MuJoCo found).

**Divergence.** MuJoCo resets a cat whose state went non-finite or huge (as the loop's `mj_step` does: time goes
back to 0) and raises its warning counter, and `Batch` then stops stepping it, repeating its last records; a
MuJoCo error leaves the cat where it was. Either way its time does not advance a whole tick, and the cat is
reported diverged and stepped no further; the other cats of its batch are untouched (``tests/sim/test_batch.py``).

Threads: ``nthread`` (default: every core); results do not depend on it (each cat is stepped alone).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import mujoco.batch
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
        nthread: threads, the caller's included (default: every core).
        safety: the safety layer's configuration (`felis.loop.run_loop`'s default when None).
        sensors: an `MjSpec` edit adding more sensors for ``record`` (e.g. the landing features' body points).
        timestep: the physics step in s (default the model's, 0.5 ms for the cat): each control tick runs as many
            steps as fit (a whole number; `bench/landing_height.py`: from 3 m the impact's verdict depends on the
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
        self._sims: mujoco.batch.Batch | None = None  # made for the largest batch run so far (`_batch`)
        self._gains: tuple[np.ndarray, np.ndarray] | None = None  # its per-cat actuator gains, once any is soft
        self.nstate = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS)  # ``record``'s state rows
        r = self.robot
        self._qadr = 1 + np.asarray(r._qadr)  # FULLPHYSICS: time, qpos, qvel, …
        self._act = np.asarray(r._act)
        self._kp = m.actuator_gainprm[self._act, 0].copy()  # the armed gains `Command.stiffness` scales
        self._kb = m.actuator_biasprm[self._act, 1].copy()
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
        self._sims = self._gains = None  # the batch's threads end with it
        self.robot.close()

    def __enter__(self) -> DropBatch:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _batch(self, n: int) -> mujoco.batch.Batch:
        """A `mujoco.batch.Batch` of at least ``n`` cats (kept; a larger run makes a larger one), gains as armed."""
        if self._sims is None or self._sims.nsim < n:
            self._sims, self._gains = mujoco.batch.Batch(self.model, n, nthread=self.nthread), None
        elif self._gains is not None:
            self._gains[0][:] = self.model.actuator_gainprm
            self._gains[1][:] = self.model.actuator_biasprm
        return self._sims

    def _set_stiffness(self, rows: np.ndarray | slice, stiffness: np.ndarray | None) -> None:
        """Cats ``rows``' position gains scaled by ``stiffness`` (their rows, per joint, clamped as the safety layer
        does), as `MujocoRobot` applies `felis.hal.Command.stiffness`: kp·s and −kp·s, the same products."""
        if stiffness is None and self._gains is None:
            return
        if self._gains is None:
            self._gains = (self._sims.expand("actuator_gainprm"), self._sims.expand("actuator_biasprm"))
        s = 1.0 if stiffness is None else np.minimum(np.maximum(np.asarray(stiffness, dtype=float), MIN_STIFFNESS), 1.0)
        gain, bias = self._gains
        if isinstance(rows, slice):
            gain[rows, self._act, 0] = self._kp * s
            bias[rows, self._act, 1] = self._kb * s
        else:
            gain[rows[:, None], self._act, 0] = self._kp * s
            bias[rows[:, None], self._act, 1] = self._kb * s

    # ------------------------------------------------------------------ start states
    def _start(self, drops: Sequence[Drop]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(integration rows (B, `mjSTATE_INTEGRATION`), FULLPHYSICS states (B, nstate), sensordata (B, nsens)) of
        the cats released as ``drops`` say: `MujocoRobot.reset`, then `felis.sim.scenarios.apply_drop`."""
        r, m = self.robot, self.model
        ints = np.empty((len(drops), mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_INTEGRATION)))
        states = np.empty((len(drops), self.nstate))
        sens = np.empty((len(drops), m.nsensordata))
        for i, d in enumerate(drops):
            r.reset()
            apply_drop(r, d)
            mujoco.mj_getState(m, r.data, ints[i], mujoco.mjtState.mjSTATE_INTEGRATION)
            mujoco.mj_getState(m, r.data, states[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
            sens[i] = r.data.sensordata
        return ints, states, sens

    def initial(self, drops: Sequence[Drop]) -> tuple[np.ndarray, np.ndarray]:
        """(states (B, nstate), sensordata (B, nsensordata)) of the cats released as ``drops`` say: the model's
        pose, turned and lifted by `felis.sim.scenarios.apply_drop`, at rest, time 0 (FULLPHYSICS states, as
        `mujoco.rollout` takes them)."""
        _, states, sens = self._start(drops)
        return states, sens

    # ------------------------------------------------------------------ the run
    def run(self, drops: Sequence[Drop], controller, standing_waist_m: float, *, rate_hz: float = 100.0,
            margin_s: float = 1.0, ticks: Sequence[int] | None = None,
            record: Callable[[int, np.ndarray, np.ndarray, np.ndarray], None] | None = None) -> list[BatchResult]:
        """Drop every cat of ``drops`` under ``controller`` and return one `BatchResult` per drop, in order.

        ``controller``: ``reset(t (B,), q (B, n))`` then, each tick, ``controller(t, q, quat, h) -> (B, n)``
        position targets (q in encoder ticks, quat (w, x, y, z) from the IMU, h the waist height). Each cat
        runs ``round((fall_time + margin_s) · rate_hz)`` ticks (as `LandingSim`) unless ``ticks`` gives them.
        ``record(k, states (B, S, nstate), sensordata (B, S, nsens), active)`` (S: physics steps a tick, 20 at the
        cat's 0.5 ms; FULLPHYSICS states): called after each tick's physics with the rows of the cats still
        running (``active``: their indices), e.g. to record motion."""
        per = int(round(1.0 / (rate_hz * self.model.opt.timestep)))
        if per < 1 or abs(rate_hz * self.model.opt.timestep * per - 1.0) > 1e-9:
            raise ParameterError(f"the batch runs whole physics steps per tick: rate {rate_hz} Hz does not divide "
                                 f"into {self.model.opt.timestep:g} s steps")
        B = len(drops)
        if B == 0:
            return []
        n_ticks = (np.array([int(round((d.fall_time + margin_s) * rate_hz)) for d in drops]) if ticks is None
                   else np.asarray(ticks, dtype=int).copy())
        m = self.model
        rows0, state, sens = self._start(drops)
        sims = self._batch(B)
        sims.state[:B] = rows0
        FULL, TIME = mujoco.mjtState.mjSTATE_FULLPHYSICS, mujoco.mjtState.mjSTATE_TIME
        qpos = sims.bind("qpos")  # live: the cats' state rows
        qadr = np.asarray(self.robot._qadr)
        t = state[:, 0].copy()
        q = self._quantize(state[:, self._qadr])
        quat = sens[:, self._imu] if self._imu is not None else np.tile([1.0, 0, 0, 0], (B, 1))
        controller.reset(t, q)
        last = np.clip(q, self.safety.lower, self.safety.upper)
        lower, upper = self.spec.lower, self.spec.upper
        # per cat and physics step, what the verdict reads: time; up z, waist z, net floor force; bodies on the floor
        steps = int(n_ticks.max()) * per
        tt = np.full((B, steps), np.nan)
        rec = np.full((B, steps, 3), np.nan)
        found = np.zeros((B, steps, self._floor_adr.size), dtype=bool)
        cols = np.array([self._up, self._waist, self._force])
        dt = m.opt.timestep
        diverged = np.zeros(B, dtype=bool)
        ctrl = np.zeros((B, per, m.nu))
        out_state = np.empty((B, per, self.nstate)) if record is not None else None  # ``record``'s only
        out_sens = np.empty((B, per, m.nsensordata))
        out_time = np.empty((B, per, 1))
        active = np.arange(B)
        h = sens[:, self._waist].copy()
        for k in range(int(n_ticks.max())):
            active = active[n_ticks[active] > k]
            if active.size == 0:
                break
            na = active.size
            a = slice(0, B) if na == B else active  # every cat: slices, not gathers
            ids = None if na == sims.nsim else active.astype(np.int32)
            cmd = controller(t, q, quat, h)
            cmd = self.safety.filter_many(cmd, last)
            last = sent = np.minimum(np.maximum(cmd, lower), upper)  # what MujocoRobot.write sends
            c = ctrl[:na]
            c[:, :, self._act] = sent[a][:, None, :]
            sd, tm = out_sens[:na], out_time[:na]
            out = {"sensordata": sd, TIME: tm}
            if record is not None:
                out[FULL] = st = out_state[:na]
            self.last_ctrl = c
            stiffness = getattr(controller, "stiffness", None)  # `Command.stiffness` per cat, when any is soft
            self._set_stiffness(a, None if stiffness is None else stiffness[a])
            try:
                sims.rollout(per, c, record=tuple(out), ids=ids, out=out)
            except mujoco.batch.SimulationError as e:  # MuJoCo raised: those cats kept their state (module doc)
                failed = np.isin(active, e.ids)
                tm[failed] = t[active[failed], None, None]
                sd[failed] = 0.0
                if record is not None:
                    st[failed] = np.nan
            tnow = tm[:, :, 0]
            # divergence: a cat whose time stopped (warnings rose, or MuJoCo raised), or non-finite sensors
            bad = (tnow[:, -1] < t[a] + (per - 0.5) * dt) | ~np.isfinite(sd[:, -1]).all(axis=1)
            if bad.any():
                diverged[active[bad]] = True
                n_ticks[active[bad]] = k + 1  # stepped no further
            sl = slice(k * per, (k + 1) * per)
            tt[a, sl] = tnow
            rec[a, sl] = sd[:, :, cols]
            found[a, sl] = sd[:, :, self._floor_adr] > 0
            if record is not None:
                record(k, st, sd, active)
            t[a] = tnow[:, -1]
            q[a] = self._quantize(qpos[a][:, qadr])
            if self._imu is not None:
                quat[a] = sd[:, -1][:, self._imu]
            h[a] = sd[:, -1, self._waist]
        return [self._result(tt[i], rec[i], found[i], int(n_ticks[i]) * per, diverged[i], sens[i, self._up],
                             standing_waist_m) for i in range(B)]

    def _result(self, tt: np.ndarray, rec: np.ndarray, found: np.ndarray, n: int, diverged: bool,
                up0: float, standing_waist_m: float) -> BatchResult:
        """A cat's `BatchResult` from its ``n`` recorded steps (time; up z, waist z, floor force; bodies found
        on the floor): the truth is touchdown to touchdown + `WINDOW_S`, what the recorder keeps."""
        on = found[:n].any(axis=1)
        rows = np.flatnonzero(on)
        if rows.size:
            i0 = int(rows[0])
            stop = np.flatnonzero(tt[i0:n] >= tt[i0] + WINDOW_S - 1e-9)
            sel = slice(i0, i0 + (int(stop[0]) + 1 if stop.size else n - i0))
        else:
            sel = slice(0, 0)
        f = found[sel]
        off = f & ~self._is_foot
        floor_body = np.where(on[sel], self._floor_body[np.argmax(f, axis=1)], -1).astype(np.int32)
        off_foot = np.where(off.any(axis=1), self._floor_body[np.argmax(off, axis=1)], -1).astype(np.int32)
        truth = LandingTruth(t=tt[sel], up_z=rec[sel, 0], waist_m=rec[sel, 1], floor_body=floor_body,
                             off_foot_body=off_foot, bodies=self.bodies, standing_waist_m=float(standing_waist_m))
        peak = float(np.abs(rec[:n, 2]).max()) if n else 0.0
        final_up = float(rec[n - 1, 0]) if n else float(up0)
        return BatchResult(truth, peak / self.weight if self.weight > 0 else 0.0, final_up, bool(diverged))

    def _quantize(self, q: np.ndarray) -> np.ndarray:
        """Joint positions as the servo reports them: whole encoder ticks (`MujocoRobot` with ``quantize``)."""
        out = np.rint(q * (1.0 / self._qstep))
        out *= self._qstep
        return out
