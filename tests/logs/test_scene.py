"""The robot's look and body poses for viewers (`felis.scene`, `felis.sim.scene`): the body model's poses on
servos agree with MuJoCo's, and `felis.rotations.matrix_quats` inverts `quat_matrix`."""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from felis.hal import Imu, State
from felis.rotations import matrix_quats
from felis.sim import MujocoRobot
from felis.sim.scene import MujocoPoses, hardware_view, model_scene
from felis.spec import load_spec


def test_matrix_quats_against_scipy():
    r = Rotation.random(500, random_state=7)
    q = matrix_quats(r.as_matrix())
    ref = r.as_quat()[:, [3, 0, 1, 2]]
    ref *= np.where(ref[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(q, ref, atol=1e-12)


def test_body_model_poses_match_mujoco():
    """Hardware's view of a tilted, bent cat: the same body rotations as MuJoCo and the same positions
    relative to the root (the root's own position is placed by the lowest foot, not known on servos)."""
    spec = load_spec("cat")
    scene, poses = hardware_view(spec)
    with MujocoRobot(spec, quantize=False) as robot:
        d = robot.data
        d.qpos[3:7] = Rotation.from_euler("xyz", [0.3, -0.2, 0.5]).as_quat()[[3, 0, 1, 2]]
        q = 0.3 * np.sin(np.arange(spec.n))
        for i, j in enumerate(spec.joints):
            d.qpos[robot.model.joint(j.name).qposadr[0]] = q[i]
        mujoco.mj_forward(robot.model, d)
        state = robot.read()
        truth = MujocoPoses(robot)(state)
        assert MujocoPoses(robot).bodies == scene.bodies == poses.bodies
    hw = poses(State(t=0.0, q=q, dq=np.zeros(spec.n), imu=Imu(quat=state.imu.quat, gyro=np.zeros(3),
                                                               accel=np.zeros(3))))
    sign = np.sign(np.sum(hw[:, 3:] * truth[:, 3:], axis=1))
    np.testing.assert_allclose(hw[:, 3:] * sign[:, None], truth[:, 3:], atol=1e-6)  # q and −q: one rotation
    np.testing.assert_allclose(hw[:, :3] - hw[0, :3], truth[:, :3] - truth[0, :3], atol=1e-6)
    feet = [scene.bodies.index(f) for f in spec.sensors.contacts]
    assert abs(hw[feet, 2].min() - 0.012) < 1e-9  # the lowest foot sphere rests on the floor


def test_model_scene_has_the_floor_and_every_body():
    spec = load_spec("arm")
    with MujocoRobot(spec) as robot:
        scene = model_scene(robot.model, path=np.zeros((3, 3)))
    assert any(g.body == -1 and g.shape == "plane" for g in scene.geoms)
    assert {g.body for g in scene.geoms if g.body >= 0} <= set(range(len(scene.bodies)))
    assert scene.path.shape == (3, 3)
