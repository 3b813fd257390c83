"""The MJCF model → `felis.bodymodel.BodyModel` (geometry from the model, masses from the description).

The MJCF is the one source of the robot's geometry; this reads it once (compiled by MuJoCo, so
defaults, ``fromto`` capsules and inertia inference are resolved) and hands the monitor plain arrays,
so the balance monitor estimates the CoM on hardware with exactly the simulated robot's geometry.
"""

from __future__ import annotations

import mujoco
import numpy as np

from felis.bodymodel import BodyModel
from felis.rotations import quat_matrix
from felis.sim.robot import ModelMismatch, collision_points, load_model, model_path
from felis.spec import RobotSpec


def load_body_model(spec: RobotSpec) -> BodyModel:
    """The floating-base tree of ``spec``'s model; link masses from ``spec.links`` where given."""
    path = model_path(spec)
    m = load_model(path)
    free = np.flatnonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    if free.size == 0:
        raise ModelMismatch(f"{path.name}: no floating base: a body model is for free-standing robots")
    root = int(m.jnt_bodyid[free[0]])
    bodies = [b for b in range(m.nbody) if b == root or _under(m, b, root)]
    index = {b: i for i, b in enumerate(bodies)}
    jindex = {}
    for i, j in enumerate(spec.joints):
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j.name)
        if jid < 0 or m.jnt_type[jid] != mujoco.mjtJoint.mjJNT_HINGE:
            raise ModelMismatch(f"{path.name}: body model: joint {j.name!r} is not a hinge of the model")
        if np.any(m.jnt_pos[jid] != 0):
            raise ModelMismatch(f"{path.name}: body model: joint {j.name!r} is off its body's origin")
        jindex[jid] = i
    n = len(bodies)
    joints = -np.ones((n, 2), dtype=int)
    axis = np.zeros((spec.n, 3))
    for b in bodies:
        hinges = [j for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
                  if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
        if len(hinges) > 2:
            raise ModelMismatch(f"{path.name}: body model: body {m.body(b).name!r} has more than 2 hinges")
        for k, j in enumerate(hinges):
            if j not in jindex:
                raise ModelMismatch(f"{path.name}: hinge {m.joint(j).name!r} is not in {spec.source}")
            joints[index[b], k] = jindex[j]
            axis[jindex[j]] = m.jnt_axis[j]
    mass = np.array([spec.links.get(m.body(b).name, float(m.body_mass[b])) for b in bodies])
    feet = []
    for foot in spec.sensors.contacts:
        bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, foot)
        if bid not in index:
            raise ModelMismatch(f"{path.name}: body model: no foot body {foot!r}")
        feet.append(index[bid])
    radius = 0.0
    if feet:
        g = [g for g in range(m.ngeom) if m.geom_bodyid[g] == bodies[feet[0]] and m.geom_contype[g]]
        radius = float(m.geom_size[g[0], 0]) if g and m.geom_type[g[0]] == mujoco.mjtGeom.mjGEOM_SPHERE else 0.0
    imu_rot = np.eye(3)
    if spec.sensors.imu is not None:
        sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, spec.sensors.imu)
        if sid < 0 or m.site_bodyid[sid] != root:
            raise ModelMismatch(f"{path.name}: body model: the IMU site must be on the root body")
        imu_rot = quat_matrix(m.site_quat[sid])
    lb, lp, lr = collision_points(m, set(bodies) - {bodies[f] for f in feet})
    return BodyModel(
        names=tuple(m.body(b).name for b in bodies),
        parent=np.array([index.get(int(m.body_parentid[b]), -1) if b != root else -1 for b in bodies]),
        pos=np.array([m.body_pos[b] for b in bodies]),
        rot=np.array([quat_matrix(m.body_quat[b]) for b in bodies]),
        com=np.array([m.body_ipos[b] for b in bodies]), mass=mass, joints=joints, axis=axis,
        feet=np.array(feet, dtype=int), foot_radius=radius, imu_rot=imu_rot,
        low_body=np.array([index[b] for b in lb], dtype=int), low_point=lp, low_radius=lr)


def _under(m: mujoco.MjModel, b: int, root: int) -> bool:
    while b > 0:
        b = int(m.body_parentid[b])
        if b == root:
            return True
    return False
