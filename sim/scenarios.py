"""Scenarios applied to MuJoCo: put a simulated robot into a situation (drop, push, pose) before or during a run.

The tasks themselves (`felis.scenarios.Drop`, `felis.scenarios.Push`, their limits and draws) are
backend-free; this module is the physics that applies them.

* `apply_drop` (`drop` from numbers): release the floating base at rest with its lowest point ``height``
  metres above the floor and the body turned by roll, pitch, yaw (degrees; R = Rz(yaw)·Ry(pitch)·Rx(roll),
  x forward, y left, z up). Free fall to first contact then takes t = √(2h/g).
* `push`: an instantaneous impulse p (N·s, world frame) at a body's centre of mass; the velocity
  change is Δv = M⁻¹ Jᵀ p with J the body-CoM Jacobian (exact for an impulse, no force duration).
* `set_pose`: place the joints (and the actuator goals) at q, at rest.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from felis.errors import ParameterError
from felis.rotations import euler_quat
from felis.scenarios.drop import Drop, make_drop
from felis.scenarios.push import MAX_IMPULSE
from felis.sim.robot import MujocoRobot


def lowest_point(m: mujoco.MjModel, d: mujoco.MjData, root: int) -> float:
    """Lowest z of the collision geometry of the robot's bodies (exact for primitives)."""
    low = math.inf
    robot_bodies = _subtree(m, root)
    for g in range(m.ngeom):
        if m.geom_bodyid[g] not in robot_bodies or (m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0):
            continue
        t, size, pos, R = m.geom_type[g], m.geom_size[g], d.geom_xpos[g], d.geom_xmat[g].reshape(3, 3)
        if t == mujoco.mjtGeom.mjGEOM_SPHERE:
            z = pos[2] - size[0]
        elif t == mujoco.mjtGeom.mjGEOM_CAPSULE:
            z = pos[2] - abs(R[2, 2]) * size[1] - size[0]
        elif t == mujoco.mjtGeom.mjGEOM_BOX:
            z = pos[2] - np.abs(R[2, :]) @ size[:3]
        elif t == mujoco.mjtGeom.mjGEOM_CYLINDER:
            z = pos[2] - abs(R[2, 2]) * size[1] - size[0] * math.sqrt(max(0.0, 1 - R[2, 2] ** 2))
        elif t == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            z = pos[2] - math.sqrt(float((R[2, :] * size[:3]) @ (R[2, :] * size[:3])))
        else:  # meshes etc.: bounding sphere, conservative
            z = pos[2] - m.geom_rbound[g]
        low = min(low, z)
    return low


def _subtree(m: mujoco.MjModel, root: int) -> set[int]:
    out = {root}
    for b in range(root + 1, m.nbody):
        if m.body_parentid[b] in out:
            out.add(b)
    return out


def drop(robot: MujocoRobot, height: float, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> Drop:
    """Place the robot at rest, turned by (roll, pitch, yaw) degrees, lowest point ``height`` m up
    (checked by `felis.scenarios.make_drop`); returns the `Drop`."""
    return apply_drop(robot, Drop(roll, pitch, yaw, height))


def apply_drop(robot: MujocoRobot, d: Drop) -> Drop:
    """Place the robot at rest as the drop ``d`` says (checked first: `felis.scenarios.make_drop`), turned,
    its lowest point ``d.height_m`` up; returns the checked drop."""
    d = make_drop(d.height_m, d.roll_deg, d.pitch_deg, d.yaw_deg)
    m, data = robot.model, robot.data
    adr = robot.free_joint
    if adr is None:
        raise ParameterError(f"{robot.spec.name} is fixed to the world: only a free-floating robot can be dropped")
    data.qpos[adr:adr + 3] = 0.0
    data.qpos[adr + 3:adr + 7] = euler_quat(d.roll_deg, d.pitch_deg, d.yaw_deg)
    data.qvel[:] = 0.0
    mujoco.mj_forward(m, data)
    data.qpos[adr + 2] = d.height_m - lowest_point(m, data, robot.root_body)
    mujoco.mj_forward(m, data)
    return d


def push(robot: MujocoRobot, body: str, impulse: np.ndarray | list[float]) -> np.ndarray:
    """Apply an impulse (N·s, world frame) at ``body``'s centre of mass; returns the Δqvel."""
    p = np.asarray(impulse, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ParameterError(f"impulse must be 3 finite numbers (N·s), got {impulse!r}")
    if np.linalg.norm(p) > MAX_IMPULSE:
        raise ParameterError(f"impulse {np.linalg.norm(p):.3g} N·s exceeds {MAX_IMPULSE} N·s")
    m, d = robot.model, robot.data
    bid = robot.body_id(body)
    jacp = np.zeros((3, m.nv))
    mujoco.mj_forward(m, d)
    mujoco.mj_jacBodyCom(m, d, jacp, None, bid)
    dv = np.zeros(m.nv)
    mujoco.mj_solveM(m, d, dv.reshape(1, -1), (jacp.T @ p).reshape(1, -1))
    d.qvel[:] += dv
    mujoco.mj_forward(m, d)
    return dv


def set_pose(robot: MujocoRobot, q: np.ndarray) -> None:
    """Put the joints at ``q`` (rad/m, description order) at rest, with goals equal to ``q``."""
    q = np.asarray(q, dtype=float)
    spec = robot.spec
    if q.shape != (spec.n,) or not np.all(np.isfinite(q)):
        raise ParameterError(f"pose must be {spec.n} finite numbers, got shape {q.shape}")
    bad = np.flatnonzero((q < spec.lower - 1e-9) | (q > spec.upper + 1e-9))
    if bad.size:
        j = spec.joints[bad[0]]
        raise ParameterError(f"pose for {j.name} ({q[bad[0]]:.4g}) outside its range {j.lower:.4g}…{j.upper:.4g}")
    m, d = robot.model, robot.data
    d.qpos[robot._qadr] = q
    d.qvel[robot._dadr] = 0.0
    d.ctrl[robot._act] = q
    robot._goal = q.copy()
    mujoco.mj_forward(m, d)
