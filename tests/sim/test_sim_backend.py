"""MujocoRobot, servo model and scenarios against the descriptions and physics."""

import math

import mujoco
import numpy as np
import pytest

from felis.controllers import PoseController
from felis.errors import LifecycleError, ParameterError, SimulationError
from felis.hal import Command, Lifecycle, Robot
from felis.learning.landing.evaluate import standing_waist_height
from felis.loop import run_loop
from felis.rotations import euler_quat, quat_euler
from felis.servos import RAD_PER_TICK, SERVOS
from felis.sim import ModelMismatch, MujocoRobot
from felis.sim.landing import ImpactRecorder, LandingRecorder, assess_landing
from felis.sim.scenarios import drop, lowest_point, push, set_pose
from felis.sim.servo import kp_from_gain, servo_params
from felis.spec import ROBOTS_DIR, load_spec, parse_spec

CAT, ARM = load_spec("cat"), load_spec("arm")
G = 9.81


@pytest.fixture
def cat():
    with MujocoRobot(CAT) as robot:
        yield robot


@pytest.fixture
def arm():
    with MujocoRobot(ARM) as robot:
        yield robot


def test_cat_mass_and_links_match_description(cat):
    assert 0.8 <= cat.mass() <= 1.5
    for body, mass in CAT.links.items():
        assert cat.model.body_mass[cat.body_id(body)] == pytest.approx(mass), body


def test_arm_links_match_description(arm):
    for body, mass in ARM.links.items():
        assert arm.model.body_mass[arm.body_id(body)] == pytest.approx(mass), body


@pytest.mark.parametrize("spec", [CAT, ARM], ids=["cat", "arm"])
def test_joint_ranges_equal_description(spec):
    with MujocoRobot(spec) as robot:
        m = robot.model
        for j in spec.joints:
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j.name)
            assert tuple(m.jnt_range[jid]) == pytest.approx((j.lower, j.upper), abs=1e-12)
            aid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, j.name)
            assert tuple(m.actuator_ctrlrange[aid]) == pytest.approx((j.lower, j.upper), abs=1e-12)


def test_model_mismatch_is_reported():
    text = (ROBOTS_DIR / "cat.toml").read_text().replace(
        "[joint.tail_yaw]\nid = 4\nservo = \"XL330-M288-T\"\nrange_deg = [-60, 60]",
        "[joint.tail_yaw]\nid = 4\nservo = \"XL330-M288-T\"\nrange_deg = [-50, 60]")
    spec = parse_spec(text, "edited.toml")
    with pytest.raises(ModelMismatch, match="joint 'tail_yaw' range .* differs from edited.toml"):
        MujocoRobot(spec).connect()


def _chain(q):
    """The arm's kinematic chain from robots.md: translate by the offset, then rotate about the axis."""
    def rot(axis, a):
        c, s = math.cos(a), math.sin(a)
        return {"z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
                "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])}[axis]
    R, p = np.eye(3), np.zeros(3)
    for offset, axis, angle in [((0.012, 0, 0.017), "z", q[0]), ((0, 0, 0.0595), "y", q[1]),
                                ((0.024, 0, 0.128), "y", q[2]), ((0.124, 0, 0), "y", q[3])]:
        p = p + R @ np.array(offset)
        R = R @ rot(axis, angle)
    return p + R @ np.array([0.126, 0, 0])


def test_arm_tool_site_equals_kinematic_chain(arm):
    rng = np.random.default_rng(7)
    site = mujoco.mj_name2id(arm.model, mujoco.mjtObj.mjOBJ_SITE, "tool")
    worst = 0.0
    for _ in range(20):
        q = rng.uniform(ARM.lower, ARM.upper)
        set_pose(arm, q)
        worst = max(worst, np.linalg.norm(arm.data.site_xpos[site] - _chain(q)))
    assert worst < 1e-4  # 0.1 mm
    set_pose(arm, np.zeros(5))
    assert arm.data.site_xpos[site] == pytest.approx([0.286, 0, 0.2045], abs=1e-12)


@pytest.mark.parametrize("h", [0.5, 1.0, 3.0])
def test_free_fall_time(cat, h):
    info = drop(cat, h, roll=30, pitch=-20, yaw=45)
    assert lowest_point(cat.model, cat.data, cat.root_body) == pytest.approx(h, abs=1e-9)
    rec = ImpactRecorder(cat).attach()
    run_loop(cat, PoseController("hold"), duration=info.fall_time + 0.1)
    expected = math.sqrt(2 * h / G)
    assert rec.first_contact_t == pytest.approx(expected, rel=0.02)
    assert rec.impact_speed == pytest.approx(G * expected, rel=0.02)


@pytest.fixture(scope="module")
def standing_waist():
    with MujocoRobot(CAT) as robot:
        return standing_waist_height(robot)


def test_hard_landing_from_3m_stays_sane(cat, standing_waist):
    drop(cat, 3.0, roll=180)
    rec = LandingRecorder(cat, tuple(CAT.sensors.contacts)).attach()
    report = run_loop(cat, PoseController("stand"), duration=2.0)
    landing = assess_landing(cat, rec, standing_waist)
    assert report.ok and np.all(np.isfinite(cat.data.qpos))
    assert landing.impact_speed_ms == pytest.approx(7.67, rel=0.02)
    assert landing.torso_contact and not landing.on_feet  # the stand controller cannot right it
    assert lowest_point(cat.model, cat.data, cat.root_body) > -0.02


def test_upright_drop_lands_on_feet(cat, standing_waist):
    drop(cat, 0.3)
    rec = LandingRecorder(cat, tuple(CAT.sensors.contacts)).attach()
    run_loop(cat, PoseController("stand"), duration=1.5)
    landing = assess_landing(cat, rec, standing_waist)
    assert landing.on_feet and landing.why is None and landing.feet_down == 4 and landing.tilt_deg < 10


def test_servo_gain_mapping():
    xl = SERVOS["XL330-M288-T"]
    # P=400: K_PP = 400/128 PWM per tick; 885 PWM = stall torque
    assert kp_from_gain(xl, 400) == pytest.approx(0.52 * 3.125 * 4096 / (2 * math.pi) / 885)
    p = servo_params(xl)
    assert p.torque_limit == 0.52 and p.damping == pytest.approx(0.52 / xl.no_load_speed)
    g = servo_params(SERVOS["XM430-W350-T"], m_per_rad=0.015)
    assert g.torque_limit == pytest.approx(4.1 / 0.015)


def test_servo_step_response_reaches_target_and_saturates(cat):
    """tail_yaw swings in the horizontal plane (no gravity load): a 1 rad step from rest."""
    set_pose(cat, CAT.pose("stand"))
    cat.arm()
    i = CAT.index("tail_yaw")
    act = cat._act[i]
    target = CAT.pose("stand")
    target[i] = 1.0
    forces, q, dq = [], [], []
    for _ in range(60):  # 0.6 s
        cat.write(Command(q=target))
        cat.advance(0.01)
        forces.append(cat.data.actuator_force[act])
        s = cat.read()
        q.append(s.q[i])
        dq.append(s.dq[i])
    limit = cat.servo["tail_yaw"].torque_limit
    assert max(np.abs(forces)) == pytest.approx(limit)  # saturated at the stall torque early on
    assert abs(forces[0]) == pytest.approx(limit)
    assert abs(q[-1] - 1.0) < 0.02  # reached the target
    assert max(np.abs(dq)) <= SERVOS["XL330-M288-T"].no_load_speed * 1.02  # velocity limit
    # reading is quantised to whole ticks
    assert np.allclose(np.array(q) / RAD_PER_TICK, np.round(np.array(q) / RAD_PER_TICK))


def test_stiffness_scales_the_position_gain_and_the_legs_give(cat):
    """`Command.stiffness` in MuJoCo: the position actuators' kp times s (I, D, feedforward kept); the standing
    cat's loaded leg pitch joints sink about 1/s as far from their goal at s = 0.2 as at 1, and come back."""
    set_pose(cat, CAT.pose("stand"))
    cat.arm()
    legs = np.array([CAT.index(n) for n in ("fl_pitch", "fr_pitch", "hl_pitch", "hr_pitch")])
    stand = CAT.pose("stand")
    kp = cat.model.actuator_gainprm[cat._act, 0].copy()

    def sag(stiffness) -> float:
        for _ in range(150):
            cat.write(Command(q=stand, stiffness=stiffness))
            cat.advance(0.01)
        return float(np.abs(cat.read().q[legs] - stand[legs]).max())

    stiff = sag(None)
    soft = np.full(12, 0.2)
    sent = cat.write(Command(q=stand, stiffness=soft))
    assert sent.stiffness is not None
    assert cat.model.actuator_gainprm[cat._act, 0] == pytest.approx(kp * soft)
    assert cat.model.actuator_biasprm[cat._act, 1] == pytest.approx(-kp * soft)
    softer = sag(soft)
    again = sag(None)
    assert cat.model.actuator_gainprm[cat._act, 0] == pytest.approx(kp)
    print(f"\nleg pitch sag under the cat's weight: {stiff:.4f} rad stiff, {softer:.4f} at s = 0.2, {again:.4f} back")
    assert softer > 2 * stiff + RAD_PER_TICK and again < softer / 2


def test_torque_off_goes_limp(cat):
    set_pose(cat, CAT.pose("stand"))
    cat.arm()
    mask = np.ones(12, dtype=bool)
    mask[CAT.index("tail_pitch")] = False
    sent = cat.write(Command(q=CAT.pose("stand"), torque=mask))
    assert sent.torque is not None and not sent.torque[CAT.index("tail_pitch")]
    for _ in range(100):
        cat.advance(0.01)
    s = cat.read()
    # the unpowered tail sinks under gravity, slowed only by back-EMF damping and friction
    assert s.q[CAT.index("tail_pitch")] < CAT.pose("stand")[CAT.index("tail_pitch")] - 0.25
    assert abs(s.q[CAT.index("tail_yaw")] - 0.0) < 0.02  # powered joint holds


def test_state_sensors_standing(cat):
    report = run_loop(cat, PoseController("stand"), duration=1.0, keep_armed=True)
    s = report.final_state
    assert s.contacts.tolist() == [True] * 4
    assert 0.09 < s.height < 0.13
    assert s.imu.quat == pytest.approx([1, 0, 0, 0], abs=0.05)
    assert s.imu.accel == pytest.approx([0, 0, G], abs=0.3)
    assert np.all(np.abs(s.imu.gyro) < 0.05)
    assert s.effort is not None and np.all(np.abs(s.effort) <= 0.52 + 1e-9)


def test_push_changes_momentum_by_the_impulse(cat):
    drop(cat, 1.0)
    m, d = cat.model, cat.data
    mujoco.mj_subtreeVel(m, d)
    v0 = d.subtree_linvel[cat.root_body].copy()
    push(cat, "upper_body", [0.5, -0.2, 0.1])
    mujoco.mj_subtreeVel(m, d)
    dv = d.subtree_linvel[cat.root_body] - v0
    assert dv == pytest.approx(np.array([0.5, -0.2, 0.1]) / cat.mass(), rel=1e-6)


@pytest.mark.parametrize("kw,match", [
    ({"height": -1}, "drop height"), ({"height": 0}, "drop height"), ({"height": 50}, "drop height"),
    ({"height": float("nan")}, "finite"), ({"height": 1, "roll": 400}, "roll"), ({"height": "x"}, "number"),
])
def test_drop_rejects_bad_parameters(cat, kw, match):
    with pytest.raises(ParameterError, match=match):
        drop(cat, **kw)


def test_drop_needs_free_floating_robot(arm):
    with pytest.raises(ParameterError, match="fixed to the world"):
        drop(arm, 1.0)


def test_push_and_pose_reject_bad_input(cat):
    with pytest.raises(ParameterError):
        push(cat, "upper_body", [np.nan, 0, 0])
    with pytest.raises(Exception, match="no body 'wing'"):
        push(cat, "wing", [1, 0, 0])
    with pytest.raises(ParameterError, match="outside its range"):
        set_pose(cat, np.full(12, 2.0))


def test_euler_roundtrip():
    for rpy in [(10, 20, 30), (-170, 45, 90), (0, -80, -120)]:
        assert quat_euler(euler_quat(*rpy)) == pytest.approx(rpy, abs=1e-9)


def test_divergence_raises_simulation_error(cat):
    cat.arm()
    cat.data.qvel[:] = 1e12  # absurd state: MuJoCo flags it
    with pytest.raises(SimulationError, match="diverged"):
        cat.advance(0.01)
    assert cat.lifecycle is Lifecycle.ERROR
    assert np.all(cat.model.actuator_gainprm[:, 0] == 0)  # torque off
    with pytest.raises(LifecycleError):
        cat.write(Command(q=np.zeros(12)))
    cat.close()
    assert cat.lifecycle is Lifecycle.DISCONNECTED


def test_mujoco_robot_is_a_hal_robot(cat):
    assert isinstance(cat, Robot)


def test_reset_restores_initial_state(cat):
    q0 = cat.data.qpos.copy()
    drop(cat, 1.0, roll=90)
    run_loop(cat, PoseController("sit"), duration=0.3, keep_armed=True)
    cat.reset()
    assert cat.data.time == 0 and np.array_equal(cat.data.qpos, q0)


@pytest.mark.parametrize("rate", [100, 300, 64, 1000])
def test_simulated_time_follows_the_loop_at_any_rate(cat, rate):
    report = run_loop(cat, PoseController("hold"), duration=1.0, rate_hz=rate, keep_armed=True)
    assert cat.data.time == pytest.approx(report.sim_time_s, abs=0.6e-3)  # within a physics step
