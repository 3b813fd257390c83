"""`felis.sim.gather.Gather`: one take from MuJoCo's buffer equals reading field by field; `MujocoRobot.read`
built on it reports what the data holds."""

import math

import mujoco
import numpy as np
import pytest

from felis.hal import Command
from felis.sim import MujocoRobot
from felis.sim.gather import Gather
from felis.sim.robot import TOUCH_THRESHOLD_N, collision_points
from felis.sim.scenarios import drop
from felis.spec import load_spec


@pytest.fixture
def moving_cat():
    robot = MujocoRobot(load_spec("cat"))
    robot.connect()
    robot.arm()
    drop(robot, 0.3, roll=150.0)
    rng = np.random.default_rng(3)
    for _ in range(40):  # falling, turning, touching down: every field non-trivial
        robot.write(Command(q=robot.spec.pose("stand") + rng.normal(0.0, 0.2, robot.spec.n)))
        robot.advance(0.01)
    yield robot
    robot.close()


def test_one_take_equals_the_fields_it_names(moving_cat):
    d = moving_cat.data
    parts = [("qpos", [0, 2, 9]), ("sensordata", range(d.sensordata.size)), ("xmat", [8, 17]),
             ("subtree_linvel", [3, 4, 5]), ("xpos", [])]
    g = Gather(d, parts)
    assert g.one_buffer  # MuJoCo keeps them in one buffer
    want = np.concatenate([getattr(d, f).ravel()[list(ix)] for f, ix in parts])
    got = g.take()
    np.testing.assert_array_equal(got, want)
    assert [s.stop - s.start for s in g.slices] == [3, d.sensordata.size, 2, 3, 0]
    got[:] = 0.0  # a copy: the data is untouched
    assert d.qpos[2] == want[1]


def test_order_interleaves_fields(moving_cat):
    d = moving_cat.data
    parts = [("xpos", [3, 4, 5, 6, 7, 8]), ("xquat", [4, 5, 6, 7, 8, 9, 10, 11])]
    order = [0, 1, 2, 6, 7, 8, 9, 3, 4, 5, 10, 11, 12, 13]  # body 1: position, rotation; body 2: the same
    want = np.concatenate([d.xpos[1], d.xquat[1], d.xpos[2], d.xquat[2]])
    np.testing.assert_array_equal(Gather(d, parts, order).take(), want)
    with pytest.raises(ValueError, match="permutation"):
        Gather(d, parts, order[:-1])


def test_arrays_outside_one_buffer_are_read_field_by_field():
    class Apart:  # two separate allocations: no flat view spans them
        a = np.arange(5.0)
        b = np.arange(10.0, 20.0).reshape(2, 5)

    g = Gather(Apart(), [("b", [9, 0]), ("a", [4])])
    assert not g.one_buffer
    np.testing.assert_array_equal(g.take(), [19.0, 10.0, 4.0])
    np.testing.assert_array_equal(Gather(Apart(), [("b", [9, 0]), ("a", [4])], [2, 0, 1]).take(), [4.0, 19.0, 10.0])


def test_bad_fields_are_refused_with_their_name(moving_cat):
    with pytest.raises(IndexError, match="qpos"):
        Gather(moving_cat.data, [("qpos", [moving_cat.data.qpos.size])])
    with pytest.raises(TypeError, match="geom_bodyid|not a contiguous float64"):
        Gather(moving_cat.model, [("geom_bodyid", [0])])


@pytest.mark.parametrize("quantize", [True, False])
def test_read_reports_what_the_data_holds(moving_cat, quantize):
    r = moving_cat
    r.quantize = quantize
    m, d = r.model, r.data
    s = r.read()
    qadr = [m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in r.spec.names]
    dadr = [m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in r.spec.names]
    q, dq = d.qpos[qadr], d.qvel[dadr]
    if quantize:
        q = np.rint(q / r._qstep) * r._qstep
        dq = np.rint(dq / r._vstep) * r._vstep
    np.testing.assert_allclose(s.q, q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.dq, dq, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(s.effort, d.qfrc_actuator[dadr] - r._damping * d.qvel[dadr])
    np.testing.assert_array_equal(s.imu.quat, d.sensor("imu_quat").data)
    np.testing.assert_array_equal(s.imu.gyro, d.sensor("imu_gyro").data)
    np.testing.assert_array_equal(s.imu.accel, d.sensor("imu_accel").data)
    assert s.height == d.site_xpos[r._height_site, 2]
    feet = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f) for f in r.spec.sensors.contacts]
    np.testing.assert_array_equal(s.truth.feet, d.xpos[feet])
    np.testing.assert_array_equal(s.contacts, s.truth.foot_force > TOUCH_THRESHOLD_N)
    root = r._truth_root
    np.testing.assert_array_equal(s.truth.com, d.subtree_com[root])
    np.testing.assert_array_equal(s.truth.com_vel, d.subtree_linvel[root])
    robot = {b for b in range(m.nbody) if m.body_rootid[b] == m.body_rootid[root]}
    bodies, points, radii = collision_points(m, robot - set(feet))  # the lowest point, point by point
    low = min(d.xmat[b].reshape(3, 3)[2] @ p + d.xpos[b, 2] - rad
              for b, p, rad in zip(bodies, points, radii, strict=True))
    assert math.isclose(s.truth.low, low, abs_tol=1e-12)
