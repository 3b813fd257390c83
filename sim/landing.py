"""Measuring a drop: first contact, impact speed, peak ground force, and how the robot landed.

`ImpactRecorder` is a physics sub-step hook (``MujocoRobot.substep_hook``) so the peak force is
taken at the physics rate (1 kHz), not the control rate: impacts last a few milliseconds.
Ground force = Σ normal forces of the contacts between the floor and the robot.

`assess_landing` judges the final state: *on its feet* means the upper body's up-axis points up
(tilt < 45°), at least three feet touch the floor, and no torso part (upper body, lower body,
head) does.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import mujoco
import numpy as np

from felis.sim.robot import MujocoRobot
from felis.sim.scenarios import quat_euler

TORSO = ("upper_body", "lower_body", "head")
UPRIGHT_TILT_DEG = 45.0


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


@dataclass(frozen=True)
class Landing:
    on_feet: bool
    tilt_deg: float  # angle between the upper body's up-axis and world up
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
        impact = (f"impact {self.impact_speed_ms:.2f} m/s at t={self.first_contact_s:.3f} s, "
                  if self.impact_speed_ms is not None else "")
        return (f"landed {verdict}: tilt {self.tilt_deg:.0f}°, roll {self.roll_deg:.0f}° pitch "
                f"{self.pitch_deg:.0f}° yaw {self.yaw_deg:.0f}°, {self.feet_down} feet down; {impact}"
                f"peak ground force {self.peak_force_n:.1f} N ({self.peak_force_bw:.1f}× body weight)")


def assess_landing(robot: MujocoRobot, recorder: ImpactRecorder | None = None) -> Landing:
    """Judge how the robot lies now (call at the end of a drop run)."""
    m, d = robot.model, robot.data
    root = robot.root_body
    up_z = float(d.xmat[root].reshape(3, 3)[2, 2])
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, up_z))))
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
    peak = recorder.peak_force if recorder else 0.0
    return Landing(
        on_feet=tilt < UPRIGHT_TILT_DEG and feet >= 3 and not torso, tilt_deg=tilt, roll_deg=roll,
        pitch_deg=pitch, yaw_deg=yaw, feet_down=feet, torso_contact=torso,
        first_contact_s=recorder.first_contact_t if recorder else None,
        impact_speed_ms=recorder.impact_speed if recorder else None,
        peak_force_n=peak, peak_force_bw=peak / weight if weight > 0 else 0.0,
    )
