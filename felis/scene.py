"""What a viewer needs to draw the robot: its bodies' shapes (`RobotScene`) and, every tick, where each body is
(`BodyPoses`), backend-free.

A `RobotScene` lists the robot's bodies by name and its geoms as primitives attached to them (MuJoCo's shape
names and sizes: half sizes for a box, radius for a sphere, (radius, half length) along z for a cylinder or
capsule); geoms with ``body = -1`` sit in the world (the floor). The run log (`felis.logs.runlog`) turns it into
a ``foxglove.SceneUpdate`` once and writes the poses as ``foxglove.FrameTransforms`` each tick, so a 3D viewer
shows the robot moving. The scene comes from the MJCF (`felis.sim.scene`), the one source of geometry.

Poses: in simulation MuJoCo's (`felis.sim.scene.MujocoPoses`); on hardware `BodyModelPoses`: the body model
(`felis.bodymodel`) from the joint angles and the IMU's attitude, with the lowest foot set on the floor (z = its
radius) since a robot on servos does not know where it stands.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from felis.bodymodel import BodyModel
from felis.hal import State
from felis.rotations import matrix_quats, quat_matrix


@dataclass(frozen=True)
class Geom:
    """One shape: ``shape`` is box | sphere | ellipsoid | cylinder | capsule | plane; ``size`` MuJoCo's;
    ``pos`` and ``quat`` (w, x, y, z) in the body frame; ``rgba`` 0…1; ``body`` an index into
    `RobotScene.bodies`, −1 for the world."""

    body: int
    shape: str
    size: tuple[float, float, float]
    pos: tuple[float, float, float]
    quat: tuple[float, float, float, float]
    rgba: tuple[float, float, float, float]


@dataclass(frozen=True)
class RobotScene:
    """The robot's bodies (frame names), its geoms, and optionally a path of world points to draw (the arm's
    target), all in metres."""

    bodies: tuple[str, ...]
    geoms: tuple[Geom, ...]
    path: np.ndarray | None = None  # (n, 3)


class BodyPoses(Protocol):
    """Every body's pose in the world at a state: ``bodies`` names them (the scene's order); calling returns
    (len(bodies), 7): x, y, z and the rotation x, y, z, w (Foxglove's order), a new array each call (a log
    keeps it until its chunk is written), or None when not known."""

    bodies: tuple[str, ...]

    def __call__(self, state: State) -> np.ndarray | None: ...


class BodyModelPoses:
    """Body poses on hardware: `BodyModel.forward` from the joint angles and the IMU's orientation (identity
    without an IMU reading), the root placed above the world origin so that the lowest foot touches the
    floor. About 30 µs a tick for the cat."""

    def __init__(self, model: BodyModel):
        self.model = model
        self.bodies = tuple(model.names)
        self._imu_t = model.imu_rot.T
        self._turned = not np.allclose(model.imu_rot, np.eye(3))
        self._out = np.zeros((len(self.bodies), 7))

    def __call__(self, state: State) -> np.ndarray | None:
        m = self.model
        imu = state.imu
        root = np.eye(3)
        if imu is not None and np.all(np.isfinite(imu.quat)):
            root = quat_matrix(imu.quat)
            if self._turned:
                root = root @ self._imu_t
        q = np.asarray(state.q, dtype=float)
        if not np.all(np.isfinite(q)):
            return None
        p, R, _ = m.forward(q, root)
        out = np.empty_like(self._out)
        out[:, :3] = p
        if m.feet.size:
            out[:, 2] += m.foot_radius - p[m.feet, 2].min()
        out[:, 3:] = matrix_quats(R)[:, [1, 2, 3, 0]]
        return out
