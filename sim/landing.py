"""Measuring a drop in MuJoCo: first contact, impact speed, peak ground force, and the truth the landing
verdict is taken on.

`ImpactRecorder` and `LandingRecorder` are physics sub-step hooks (``MujocoRobot.substep_hook``) so they
measure at the physics rate (2 kHz for the cat), not the control rate: impacts last a few milliseconds.
Ground force = Σ normal forces of the contacts between the floor and the robot. `LandingRecorder` records,
each step, what `felis.scenarios.verdicts.landing_verdict` judges (`LandingTruth`), and runs an
`ImpactRecorder` in the same hook (the robot holds one hook).

`assess_landing` reports a drop (``felis sim drop``): the verdict — *on its feet* is the landing rule
(`felis.scenarios.verdicts`: feet only for 0.5 s after touchdown, then tilt ≤ 30° and the waist above half
its standing height), the same as ``felis eval landing`` — with the final pose and the impact figures.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import mujoco
import numpy as np

from felis.errors import ParameterError
from felis.rotations import quat_euler, tilt_from_up
from felis.scenarios.verdicts import WINDOW_S, LandingTruth, LandingVerdict, landing_verdict
from felis.sim.robot import MujocoRobot

TORSO = ("upper_body", "lower_body", "head")
UPRIGHT_TILT_DEG = 45.0  # the summary's words: past this it lies on its side, past 135° on its back


class ImpactRecorder:
    """Records the first floor contact and the peak ground reaction force during a run."""

    def __init__(self, robot: MujocoRobot, floor: str = "floor"):
        m = robot.model
        self.robot = robot
        self.floor = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, floor)
        if self.floor < 0:
            raise ValueError(f"model has no floor geom {floor!r}")
        self.first_contact_t: float | None = None
        self.impact_speed: float | None = None
        self.peak_force = 0.0
        self.peak_t: float | None = None
        self._f6 = np.zeros(6)
        free = np.flatnonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
        self._dof = int(m.jnt_dofadr[free[0]]) if free.size else None
        self._speed = 0.0  # root speed at the previous sub-step

    def __call__(self, m: mujoco.MjModel, d: mujoco.MjData) -> None:
        total = 0.0
        for i in range(d.ncon):
            c = d.contact[i]
            if c.geom1 == self.floor or c.geom2 == self.floor:
                mujoco.mj_contactForce(m, d, i, self._f6)
                total += self._f6[0]
        if self.first_contact_t is None:
            if total > 0:  # the contact step already decelerates: report the speed just before it
                self.first_contact_t = float(d.time)
                self.impact_speed = self._speed if self._dof is not None else None
            elif self._dof is not None:
                self._speed = float(np.linalg.norm(d.qvel[self._dof:self._dof + 3]))
        if total > self.peak_force:
            self.peak_force, self.peak_t = total, float(d.time)

    def attach(self) -> ImpactRecorder:
        self.robot.substep_hook = self
        return self

    def detach(self) -> None:
        if self.robot.substep_hook is self:
            self.robot.substep_hook = None


class LandingRecorder:
    """Physics sub-step hook recording a drop's `LandingTruth`, one entry per step: time, the upper body's
    up-axis z, the waist height, a body on the floor, a body other than a foot (``feet``:
    `RobotSpec.sensors.contacts`) on the floor. Runs an `ImpactRecorder` too (``impact``).

    It records from touchdown (the first step with a floor contact) to the step that reaches touchdown +
    `WINDOW_S`, what the verdict looks at: recording every step of a 2 s rollout made training's rollouts
    ~13 % slower (``bench/landing_speed.py``); no rows at all means it never touched down."""

    def __init__(self, robot: MujocoRobot, feet: tuple[str, ...], floor: str = "floor"):
        m = robot.model
        self.robot = robot
        self.impact = ImpactRecorder(robot, floor)
        self.floor = self.impact.floor
        foot_ids = {robot.body_id(f) for f in feet}
        self.foot_geom = np.array([m.geom_bodyid[g] in foot_ids for g in range(m.ngeom)])
        site = robot.spec.sensors.height
        self.waist_site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site) if site else -1
        if self.waist_site < 0:
            raise ParameterError(f"{robot.spec.name} has no waist height site (sensors.height)")
        self._root = robot.root_body
        self._rows: list[tuple[float, float, float, int, int]] = []
        self._end: float | None = None  # touchdown + WINDOW_S
        self._done = False

    def __call__(self, m: mujoco.MjModel, d: mujoco.MjData) -> None:
        self.impact(m, d)
        if self._done:
            return
        t = float(d.time)
        floor_body = off_foot = -1
        if d.ncon:
            g1, g2 = d.contact.geom1, d.contact.geom2
            on_floor = (g1 == self.floor) | (g2 == self.floor)
            if on_floor.any():
                other = np.where(g1 == self.floor, g2, g1)[on_floor]
                floor_body = int(m.geom_bodyid[other[0]])
                bad = other[~self.foot_geom[other]]
                if bad.size:
                    off_foot = int(m.geom_bodyid[bad[0]])
        if self._end is None:
            if floor_body < 0:
                return  # still falling: the verdict starts at touchdown
            self._end = t + WINDOW_S
        self._rows.append((t, float(d.xmat[self._root, 8]), float(d.site_xpos[self.waist_site, 2]),
                           floor_body, off_foot))
        self._done = self._end is not None and t >= self._end - 1e-9

    def attach(self) -> LandingRecorder:
        self.robot.substep_hook = self
        return self

    def detach(self) -> None:
        if self.robot.substep_hook is self:
            self.robot.substep_hook = None

    def truth(self, standing_waist_m: float) -> LandingTruth:
        """What was recorded so far, with the robot's standing waist height (m) for the verdict."""
        m = self.robot.model
        rows = np.array(self._rows, dtype=float).reshape(-1, 5)
        return LandingTruth(t=rows[:, 0], up_z=rows[:, 1], waist_m=rows[:, 2], floor_body=rows[:, 3].astype(int),
                            off_foot_body=rows[:, 4].astype(int),
                            bodies=tuple(m.body(b).name for b in range(m.nbody)),
                            standing_waist_m=float(standing_waist_m))

    @property
    def peak_impact(self) -> float:
        """Peak ground reaction force in body weights."""
        weight = self.robot.mass() * float(np.linalg.norm(self.robot.model.opt.gravity))
        return self.impact.peak_force / weight if weight > 0 else 0.0


@dataclass(frozen=True)
class Landing:
    on_feet: bool  # the landing verdict (module doc)
    why: str | None  # why not (None when it landed)
    tilt_deg: float  # at the end: angle between the upper body's up-axis and world up
    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    feet_down: int
    torso_contact: bool
    first_contact_s: float | None
    impact_speed_ms: float | None
    peak_force_n: float
    peak_force_bw: float  # in body weights

    def as_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}

    def summary(self) -> str:
        if self.on_feet:
            verdict = "on its feet"
        elif self.tilt_deg > 135:
            verdict = "on its back"
        elif self.tilt_deg > UPRIGHT_TILT_DEG:
            verdict = "on its side"
        else:
            verdict = "upright but not on its feet"
        why = f" ({self.why})" if self.why else ""
        impact = (f"impact {self.impact_speed_ms:.2f} m/s at t={self.first_contact_s:.3f} s, "
                  if self.impact_speed_ms is not None else "")
        return (f"landed {verdict}{why}: tilt {self.tilt_deg:.0f}°, roll {self.roll_deg:.0f}° pitch "
                f"{self.pitch_deg:.0f}° yaw {self.yaw_deg:.0f}°, {self.feet_down} feet down; {impact}"
                f"peak ground force {self.peak_force_n:.1f} N ({self.peak_force_bw:.1f}× body weight)")


def assess_landing(robot: MujocoRobot, recorder: LandingRecorder, standing_waist_m: float) -> Landing:
    """Report a drop at the end of its run: the landing verdict on what ``recorder`` saw (the standing waist
    height from `felis.learning.landing.evaluate.standing_waist_height`), how the robot lies now, the impact."""
    verdict: LandingVerdict = landing_verdict(recorder.truth(standing_waist_m))
    m, d = robot.model, robot.data
    root = robot.root_body
    tilt = tilt_from_up(float(d.xmat[root].reshape(3, 3)[2, 2]))
    roll, pitch, yaw = quat_euler(d.xquat[root])
    state = robot.read()
    feet = int(state.contacts.sum()) if state.contacts is not None else 0
    floor = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    torso_ids = {mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in TORSO} - {-1}
    torso = False
    for i in range(d.ncon):
        c = d.contact[i]
        other = c.geom2 if c.geom1 == floor else c.geom1 if c.geom2 == floor else None
        if other is not None and m.geom_bodyid[other] in torso_ids:
            torso = True
    weight = robot.mass() * float(np.linalg.norm(m.opt.gravity))
    impact = recorder.impact
    peak = impact.peak_force
    return Landing(
        on_feet=verdict.landed, why=verdict.why or None, tilt_deg=tilt, roll_deg=roll,
        pitch_deg=pitch, yaw_deg=yaw, feet_down=feet, torso_contact=torso,
        first_contact_s=impact.first_contact_t, impact_speed_ms=impact.impact_speed,
        peak_force_n=peak, peak_force_bw=peak / weight if weight > 0 else 0.0,
    )
