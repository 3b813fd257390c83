"""The MJCF model → `felis.scene.RobotScene` (the robot's shapes for a 3D viewer) and MuJoCo's body poses.

`model_scene` reads the compiled model's geoms: those in MuJoCo's visible groups (0–2) with some opacity, on the
robot's bodies (attached to the body's frame) and on the world body (the floor, a thin box of the plane's size);
colours from the geom's material where it has one. Meshes are left out (the models have none). `MujocoPoses`
reads ``xpos``/``xquat`` of every body after the physics step: the simulation's truth. `hardware_view` gives what
a robot on servos can know: the same shapes on the body model's bodies, posed by `felis.scene.BodyModelPoses`.
"""

from __future__ import annotations

import mujoco
import numpy as np

from felis.scene import BodyModelPoses, Geom, RobotScene
from felis.sim.gather import Gather
from felis.sim.robot import load_model, model_path
from felis.spec import RobotSpec

_SHAPES = {int(mujoco.mjtGeom.mjGEOM_BOX): "box", int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
           int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid", int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder",
           int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule", int(mujoco.mjtGeom.mjGEOM_PLANE): "plane"}


def model_scene(m: mujoco.MjModel, bodies: list[int] | None = None, path: np.ndarray | None = None) -> RobotScene:
    """The shapes of ``bodies`` (MuJoCo body ids; default: every body but the world) and of the world body."""
    if bodies is None:
        bodies = list(range(1, m.nbody))
    index = {b: i for i, b in enumerate(bodies)}
    index[0] = -1
    # the model's arrays read once, as Python lists (an MjModel attribute is a new numpy view at each access)
    bodyid, gtype, group, matid = (getattr(m, f).tolist() for f in ("geom_bodyid", "geom_type", "geom_group",
                                                                      "geom_matid"))
    size, pos, quat, grgba, mrgba = (getattr(m, f).tolist() for f in ("geom_size", "geom_pos", "geom_quat",
                                                                        "geom_rgba", "mat_rgba"))
    geoms = []
    for g in range(m.ngeom):
        b = bodyid[g]
        shape = _SHAPES.get(gtype[g])
        if b not in index or shape is None or group[g] > 2:
            continue
        rgba = mrgba[matid[g]] if matid[g] >= 0 else grgba[g]
        if rgba[3] <= 0:
            continue
        geoms.append(Geom(body=index[b], shape=shape, size=tuple(size[g]), pos=tuple(pos[g]), quat=tuple(quat[g]),
                          rgba=tuple(rgba)))
    names = tuple(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in bodies)
    return RobotScene(bodies=names, geoms=tuple(geoms),
                      path=None if path is None else np.asarray(path, dtype=float).reshape(-1, 3))


class MujocoPoses:
    """`felis.scene.BodyPoses` of a `felis.sim.MujocoRobot`: every body but the world, from MuJoCo's data (the
    state just read: the loop logs before it advances the physics), in one gather (`felis.sim.gather`)."""

    def __init__(self, robot):
        self.robot = robot
        m = robot.model
        self.bodies = tuple(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(1, m.nbody))
        self._gather = self._layout()

    def _layout(self) -> Gather:
        b = np.arange(1, self.robot.model.nbody)[:, None]
        n = len(b)  # per body: x y z from xpos, then the rotation x y z w from xquat (w first there)
        parts = [("xpos", (3 * b + np.arange(3)).ravel()), ("xquat", (4 * b + np.array([1, 2, 3, 0])).ravel())]
        order = np.hstack([np.arange(3 * n).reshape(n, 3), 3 * n + np.arange(4 * n).reshape(n, 4)]).ravel()
        return Gather(self.robot.data, parts, order)

    def __call__(self, state) -> np.ndarray:
        if self._gather.data is not self.robot.data:  # reconnected: a new MjData
            self._gather = self._layout()
        return self._gather.take().reshape(-1, 7)


def hardware_view(spec: RobotSpec) -> tuple[RobotScene, BodyModelPoses] | None:
    """The scene and poses of a robot on servos: the body model (floating-base robots; None for a fixed base,
    whose model has no body model) and the MJCF's shapes on its bodies."""
    from felis.errors import FelisError
    from felis.sim.bodymodel import load_body_model

    try:
        body = load_body_model(spec)
    except FelisError:
        return None
    m = load_model(model_path(spec))
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in body.names]
    return model_scene(m, ids), BodyModelPoses(body)
