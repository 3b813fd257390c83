"""Checks of the MuJoCo models sim/models/cat.xml and sim/models/arm.xml.

Uses mujoco and numpy directly (felis only for the lowest-point helper), so the models are checked on their own.
"""

from pathlib import Path

import mujoco
import numpy as np
import pytest

MODELS = Path(__file__).resolve().parents[2] / "sim/models"
CAT_XML = MODELS / "cat.xml"
ARM_XML = MODELS / "arm.xml"

CAT_ACTUATORS = [
    "spine_pitch",
    "spine_yaw",
    "tail_pitch",
    "tail_yaw",
    "fl_pitch",
    "fl_roll",
    "fr_pitch",
    "fr_roll",
    "hl_pitch",
    "hl_roll",
    "hr_pitch",
    "hr_roll",
]
ARM_ACTUATORS = ["joint1", "joint2", "joint3", "joint4", "gripper"]

DEG60 = 1.0471975511965976
DEG90 = 1.5707963267948966
CAT_RANGES = {
    "spine_pitch": (-DEG60, DEG60),
    "spine_yaw": (-DEG60, DEG60),
    "tail_pitch": (-DEG60, DEG60),
    "tail_yaw": (-DEG60, DEG60),
    **{f"{leg}_{j}": (-DEG90, DEG90) for leg in ("fl", "fr", "hl", "hr") for j in ("pitch", "roll")},
}
ARM_RANGES = {
    "joint1": (-np.pi, np.pi),
    "joint2": (-1.5, 1.5),
    "joint3": (-1.5, 1.4),
    "joint4": (-1.7, 1.97),
    "gripper": (-0.010, 0.019),
    "gripper_sub": (-0.010, 0.019),
}
CAT_BODIES = [
    "upper_body",
    "lower_body",
    "head",
    "tail",
    "fl_leg",
    "fr_leg",
    "hl_leg",
    "hr_leg",
    "fl_foot",
    "fr_foot",
    "hl_foot",
    "hr_foot",
]
FEET = ["fl", "fr", "hl", "hr"]


@pytest.fixture(scope="module")
def cat():
    return mujoco.MjModel.from_xml_path(str(CAT_XML))


@pytest.fixture(scope="module")
def arm():
    return mujoco.MjModel.from_xml_path(str(ARM_XML))


def _names(model, objtype, n):
    return [mujoco.mj_id2name(model, objtype, i) for i in range(n)]


# --------------------------------------------------------------------------------------------
# structure


@pytest.mark.parametrize(
    "xml,actuators,ranges",
    [(CAT_XML, CAT_ACTUATORS, CAT_RANGES), (ARM_XML, ARM_ACTUATORS, ARM_RANGES)],
    ids=["cat", "arm"],
)
def test_compiles_actuators_and_ranges(xml, actuators, ranges):
    model = mujoco.MjModel.from_xml_path(str(xml))
    assert _names(model, mujoco.mjtObj.mjOBJ_ACTUATOR, model.nu) == actuators
    for i, name in enumerate(actuators):
        # each actuator drives the joint of the same name
        assert model.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT
        assert model.joint(model.actuator_trnid[i, 0]).name == name
    for name, (lo, hi) in ranges.items():
        j = model.joint(name)
        assert model.jnt_limited[j.id] == 1, name
        assert model.jnt_range[j.id, 0] == lo, name
        assert model.jnt_range[j.id, 1] == hi, name
    # one step of the physics from the reference pose works
    data = mujoco.MjData(model)
    mujoco.mj_step(model, data)
    assert np.all(np.isfinite(data.qpos))


def test_cat_names_and_sensors(cat):
    for body in CAT_BODIES:
        assert cat.body(body).id > 0
    assert cat.body("upper_body").parentid == 0
    assert cat.body("head").parentid == cat.body("upper_body").id
    assert cat.body("lower_body").parentid == cat.body("upper_body").id
    assert cat.body("tail").parentid == cat.body("lower_body").id
    for leg, parent in (
        ("fl", "upper_body"),
        ("fr", "upper_body"),
        ("hl", "lower_body"),
        ("hr", "lower_body"),
    ):
        assert cat.body(f"{leg}_leg").parentid == cat.body(parent).id
        assert cat.body(f"{leg}_foot").parentid == cat.body(f"{leg}_leg").id
        assert cat.site(f"{leg}_touch").bodyid == cat.body(f"{leg}_foot").id
        assert cat.sensor(f"{leg}_touch").type == mujoco.mjtSensor.mjSENS_TOUCH
    root = cat.joint("root")
    assert root.type == mujoco.mjtJoint.mjJNT_FREE
    assert cat.jnt_bodyid[root.id] == cat.body("upper_body").id
    assert cat.site("imu").bodyid == cat.body("upper_body").id
    assert cat.site("waist").bodyid == cat.body("upper_body").id
    assert cat.sensor("imu_quat").type == mujoco.mjtSensor.mjSENS_FRAMEQUAT
    assert cat.sensor("imu_gyro").type == mujoco.mjtSensor.mjSENS_GYRO
    assert cat.sensor("imu_accel").type == mujoco.mjtSensor.mjSENS_ACCELEROMETER
    assert cat.camera("track").mode == mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM
    assert cat.geom("floor").type == mujoco.mjtGeom.mjGEOM_PLANE
    # 0.5 ms: a quarter of the paws' 2 ms contact time constant, so a 7.7 m/s impact is resolved (docs/landing.md)
    assert cat.opt.timestep == 0.0005
    feet = [cat.geom(f"{leg}_foot") for leg in ("fl", "fr", "hl", "hr")]
    assert all(list(g.solref) == [0.002, 1.0] and g.priority[0] == 1 for g in feet)
    assert cat.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    # the waist site sits on the spine joints' axis point
    data = mujoco.MjData(cat)
    mujoco.mj_forward(cat, data)
    lower = cat.body("lower_body").id
    for name in ("spine_pitch", "spine_yaw"):
        assert cat.jnt_bodyid[cat.joint(name).id] == lower
        np.testing.assert_allclose(data.xanchor[cat.joint(name).id], data.site("waist").xpos, atol=1e-12)


def test_cat_mass(cat):
    total = sum(cat.body(b).mass[0] for b in CAT_BODIES)
    assert 0.8 <= total <= 1.5
    # nothing else carries mass
    assert total == pytest.approx(cat.body_mass.sum())


def test_cat_reference_pose(cat):
    """At all joints 0: legs straight down, spine straight, tail straight back."""
    data = mujoco.MjData(cat)
    mujoco.mj_forward(cat, data)
    for leg in FEET:
        hip = data.body(f"{leg}_leg").xpos
        foot = data.body(f"{leg}_foot").xpos
        np.testing.assert_allclose(foot[:2], hip[:2], atol=1e-12)
        assert foot[2] < hip[2] - 0.05
    np.testing.assert_allclose(data.body("lower_body").xmat, data.body("upper_body").xmat)
    tail = cat.geom("tail")
    axis = data.geom_xmat[tail.id].reshape(3, 3)[:, 2]  # capsule axis
    np.testing.assert_allclose(np.abs(axis), [1, 0, 0], atol=1e-12)
    assert data.geom_xpos[tail.id][0] < data.body("tail").xpos[0]  # points to -x


# --------------------------------------------------------------------------------------------
# arm kinematics


def _rot(axis, q):
    """Rotation matrix for angle q about a unit axis (Rodrigues)."""
    a = np.asarray(axis, float)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(q) * k + (1 - np.cos(q)) * (k @ k)


def _transform(offset, axis, q):
    t = np.eye(4)
    t[:3, :3] = _rot(axis, q)
    t[:3, 3] = offset
    return t


# robots.md: joint axis, offset from parent (m); tool point in link4's frame
ARM_CHAIN = [
    ((0.012, 0.0, 0.017), (0, 0, 1)),
    ((0.0, 0.0, 0.0595), (0, 1, 0)),
    ((0.024, 0.0, 0.128), (0, 1, 0)),
    ((0.124, 0.0, 0.0), (0, 1, 0)),
]
ARM_TOOL = (0.126, 0.0, 0.0)


def arm_fk(q):
    """Tool position of the arm (base frame) from the table in robots.md: translate, then rotate."""
    t = np.eye(4)
    for (offset, axis), qi in zip(ARM_CHAIN, q, strict=True):
        t = t @ _transform(offset, axis, qi)
    return (t @ np.array([*ARM_TOOL, 1.0]))[:3]


def test_arm_fk_matches_table(arm):
    data = mujoco.MjData(arm)
    mujoco.mj_forward(arm, data)
    np.testing.assert_allclose(data.site("tool").xpos, [0.286, 0.0, 0.2045], atol=1e-12)

    rng = np.random.default_rng(1234)
    joints = ["joint1", "joint2", "joint3", "joint4"]
    adr = [arm.joint(j).qposadr[0] for j in joints]
    lo = np.array([ARM_RANGES[j][0] for j in joints])
    hi = np.array([ARM_RANGES[j][1] for j in joints])
    for _ in range(20):
        q = rng.uniform(lo, hi)
        data.qpos[:] = 0
        data.qpos[adr] = q
        mujoco.mj_kinematics(arm, data)
        err = np.linalg.norm(data.site("tool").xpos - arm_fk(q))
        assert err < 1e-4, (q, err)
        assert err < 1e-9  # the two should agree to rounding


def test_arm_gripper_mirrors(arm):
    """The right finger follows the left one through the equality, mirrored about the xz plane."""
    data = mujoco.MjData(arm)
    act = arm.actuator("gripper").id
    left, right = arm.body("gripper_left").id, arm.body("gripper_right").id
    mujoco.mj_forward(arm, data)
    width0 = data.xpos[left][1] - data.xpos[right][1]
    for target in (0.015, -0.008):
        data.ctrl[act] = target
        for _ in range(1500):
            mujoco.mj_step(arm, data)
        g = data.joint("gripper").qpos[0]
        gs = data.joint("gripper_sub").qpos[0]
        assert g == pytest.approx(target, abs=1e-3)
        assert gs == pytest.approx(g, abs=1e-4)
        width = data.xpos[left][1] - data.xpos[right][1]
        assert width - width0 == pytest.approx(2 * g, abs=3e-4)
        # the fingers stay symmetric about the tool axis
        assert data.xpos[left][1] + data.xpos[right][1] == pytest.approx(0, abs=1e-4)


def test_arm_holds_pose_against_gravity(arm):
    data = mujoco.MjData(arm)
    q = np.array([0.3, 0.5, -0.4, 0.6])
    joints = ["joint1", "joint2", "joint3", "joint4"]
    for j, qi in zip(joints, q, strict=True):
        data.joint(j).qpos[0] = qi
        data.ctrl[arm.actuator(j).id] = qi
    for _ in range(1000):
        mujoco.mj_step(arm, data)
    got = np.array([data.joint(j).qpos[0] for j in joints])
    assert np.all(np.isfinite(data.qpos))
    np.testing.assert_allclose(got, q, atol=0.05)  # P-only servo: small gravity sag


# --------------------------------------------------------------------------------------------
# cat dynamics


def _lowest(model, data):
    """Lowest point of the cat's collision geometry (the same function the drop scenario uses)."""
    from felis.sim.scenarios import lowest_point

    return lowest_point(model, data, root=1)  # body 1 = upper_body, the cat's root


def _quat(axis, angle):
    q = np.zeros(4)
    mujoco.mju_axisAngle2Quat(q, np.asarray(axis, float), angle)
    return q


DROPS = {
    "upright": _quat([1, 0, 0], 0.0),
    "upside_down": _quat([1, 0, 0], np.pi),
    "on_side": _quat([1, 0, 0], np.pi / 2),
    "nose_down": _quat([0, 1, 0], np.pi / 2),
    "tilted": _quat(np.array([1, 1, 0.3]) / np.linalg.norm([1, 1, 0.3]), 2.2),
}


@pytest.mark.parametrize("orientation", list(DROPS))
def test_cat_hard_landing(cat, orientation):
    """Dropped from 3 m (7.7 m/s impact) with the servos holding 0: the simulation stays sane."""
    data = mujoco.MjData(cat)
    data.qpos[3:7] = DROPS[orientation]
    mujoco.mj_kinematics(cat, data)
    data.qpos[2] += 3.0 - _lowest(cat, data)
    mujoco.mj_forward(cat, data)
    assert _lowest(cat, data) == pytest.approx(3.0)
    data.ctrl[:] = 0.0

    lowest, max_qvel, max_pen, landed = np.inf, 0.0, 0.0, False
    for _ in range(int(round(2.0 / cat.opt.timestep))):  # 2 s
        mujoco.mj_step(cat, data)
        assert np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))
        lowest = min(lowest, _lowest(cat, data))
        max_qvel = max(max_qvel, np.abs(data.qvel).max())
        if data.ncon:
            landed = True
            max_pen = max(max_pen, -data.contact.dist.min())
    for w in (
        mujoco.mjtWarning.mjWARN_BADQACC,
        mujoco.mjtWarning.mjWARN_BADQPOS,
        mujoco.mjtWarning.mjWARN_BADQVEL,
        mujoco.mjtWarning.mjWARN_CONTACTFULL,
        mujoco.mjtWarning.mjWARN_CNSTRFULL,
    ):
        assert data.warning[w].number == 0, w
    assert landed
    assert lowest > -0.03, lowest
    assert max_pen < 0.03, max_pen
    assert max_qvel < 100, max_qvel
    # it has come to rest on the floor
    assert data.qpos[2] < 0.2
    assert np.abs(data.qvel).max() < 5.0
    touching = {cat.geom(data.contact.geom[k, j]).name for k in range(data.ncon) for j in (0, 1)}
    if orientation == "upright":
        assert touching == {"floor", "fl_foot", "fr_foot", "hl_foot", "hr_foot"}
    if orientation == "upside_down":
        # lying on its back: both torso halves touch the floor
        assert {"upper_body", "lower_body"} <= touching


def test_cat_stands(cat):
    data = mujoco.MjData(cat)
    mujoco.mj_forward(cat, data)
    data.qpos[2] += 0.002 - _lowest(cat, data)  # feet 2 mm above the floor
    data.ctrl[:] = 0.0
    for _ in range(int(round(2.0 / cat.opt.timestep))):  # 2 s
        mujoco.mj_step(cat, data)
    up = data.body("upper_body").xmat.reshape(3, 3)[:, 2]
    assert up[2] > 0.9
    for foot in FEET:
        assert data.sensor(f"{foot}_touch").data[0] > 0, foot
    # the four feet carry the weight
    total = sum(data.sensor(f"{f}_touch").data[0] for f in FEET)
    weight = cat.body_mass.sum() * -cat.opt.gravity[2]
    assert total == pytest.approx(weight, rel=0.1)
    assert 0.08 <= data.site("waist").xpos[2] <= 0.14
    assert np.abs(data.qvel).max() < 0.05
    # the IMU sensors read a standing robot
    quat = data.sensor("imu_quat").data
    assert abs(quat[0]) > 0.95
    accel = data.sensor("imu_accel").data  # gravity reaction; the P-only spine sags a few degrees
    assert np.linalg.norm(accel) == pytest.approx(9.81, abs=0.05)
    assert accel[2] > 9.6
    np.testing.assert_allclose(data.sensor("imu_gyro").data, 0, atol=0.05)
