"""The firmware's controller (`felis.drivers.virtual.horn`, used by `felis.sim.servo` and `felis.sim.robot`):
unit scaling against hand-computed values, step responses (P only: first-step torque and steady state; PI: steady
error → 0 under a load), the profile generator's timing (trapezoid d/v + v/a, triangle 2·√(d/a), time-based),
mode 5 holding Goal Current's torque, mode 1 tracking a velocity, and the virtual bus's standalone servo and the
MuJoCo robot giving the same response (one implementation).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from felis.drivers.virtual import VirtualServo
from felis.drivers.virtual.horn import (
    POSITION_LOOP_S,
    RAD_S2_PER_ACCEL_UNIT,
    Gains,
    HornSim,
    Profile,
    position_controller,
    profile_for,
    pwm_scale,
)
from felis.hal import Command
from felis.servos import PWM_LIMIT, RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, TICKS_PER_REV, servo_model
from felis.sim.robot import MujocoRobot
from felis.sim.servo import controller
from felis.spec import load_spec

XM430, XL330 = "XM430-W350-T", "XL330-M288-T"
TORQUE, GOAL_POSITION = 64, 116


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_gain_scaling_is_the_e_manuals():
    s = servo_model(XM430)
    c = s.stall_torque * (TICKS_PER_REV / (2 * math.pi)) / PWM_LIMIT  # N·m/rad per PWM unit per tick
    assert pwm_scale(s) == pytest.approx(c)
    ctl = position_controller(s, Gains(800, 100, 100, 40, 8))
    T = POSITION_LOOP_S
    assert ctl.kp == pytest.approx(c * 800 / 128)  # KPP = P/128
    assert ctl.ki == pytest.approx(c * 100 / 65536 / T)  # KPI = I/65536 per control period
    assert ctl.kd == pytest.approx(c * 100 / 16 * T)  # KPD = D/16
    assert ctl.kff1 == pytest.approx(c * 40 / 4 * T)  # KFF1 = FF1/4
    assert ctl.kff2 == pytest.approx(c * 8 / 4 * T * T)  # KFF2 = FF2/4
    assert ctl.torque_limit == pytest.approx(s.stall_torque)
    assert ctl.imax * ctl.ki == pytest.approx(s.stall_torque)  # anti-windup at the PWM limit
    half = position_controller(s, Gains(800), pwm_limit=PWM_LIMIT / 2)
    assert half.torque_limit == pytest.approx(s.stall_torque / 2)
    # factory gains come from the control table
    assert Gains.factory(XM430) == Gains(800, 0, 0, 0, 0) and Gains.factory(XL330).p == 400


def _horn(gains: Gains, servo: str = XM430, limit: float | None = None) -> HornSim:
    sim = HornSim(servo_model(servo))
    ctl = position_controller(servo_model(servo), gains, current_limit_a=limit)
    sim.set_controller(ctl)
    return sim


def test_p_only_first_step_torque_and_steady_state():
    sim = _horn(Gains(800))
    kp, e = sim.ctl.kp, 0.05  # below saturation: kp·e = 0.94 N·m < 4.1
    sim.set_reference(e, 0.0, 0.0)
    sim.step(0.0, 0.0, 1)
    assert sim.d.qfrc_actuator[0] == pytest.approx(kp * e)  # the first step's torque: the P term alone (ω = 0)
    theta, w = 0.0, 0.0
    theta, w, tau = sim.step(theta, w, 2000)
    assert theta == pytest.approx(e, abs=1e-9) and abs(w) < 1e-6  # no load: P alone reaches the goal
    big = _horn(Gains(800))
    big.set_reference(1.0, 0.0, 0.0)
    big.step(0.0, 0.0, 1)
    assert big.d.qfrc_actuator[0] == pytest.approx(servo_model(XM430).stall_torque)  # saturated: the PWM limit


def test_pi_removes_the_steady_error_under_a_load():
    load = 1.0  # N·m pushing the horn back
    errors = {}
    for gains in (Gains(800), Gains(800, 2000)):
        sim = _horn(gains)
        sim.d.qfrc_applied[0] = -load
        sim.set_reference(0.3, 0.0, 0.0)
        theta, w, _ = sim.step(0.0, 0.0, 20000)  # 20 s
        errors[gains.i] = 0.3 - theta
    assert errors[0] == pytest.approx(load / _horn(Gains(800)).ctl.kp, rel=1e-3)  # P only: e = load / kp
    assert abs(errors[2000]) < 1e-6  # PI: the integral takes the load


@pytest.mark.parametrize("d, v, a", [(1.0, 2.0, 8.0), (0.2, 2.0, 8.0)])
def test_trapezoid_and_triangle_timing(d, v, a):
    p = Profile.move(0.0, 0.0, 0.0, d, v, a)
    expect = d / v + v / a if d >= v * v / a else 2 * math.sqrt(d / a)
    assert p.end == pytest.approx(expect)
    assert p.sample(p.end) == (d, 0.0, 0.0)
    assert p.sample(expect / 2)[0] == pytest.approx(d / 2)  # symmetric
    peak = max(abs(p.sample(t)[1]) for t in np.linspace(0, p.end, 2001))
    assert peak == pytest.approx(min(v, math.sqrt(a * d)), rel=1e-3)
    # the same through the control table's units
    raw_v, raw_a = round(v / RAD_S_PER_VELOCITY_UNIT), round(a / RAD_S2_PER_ACCEL_UNIT)
    q = profile_for(3, 0, raw_v, raw_a, 0.0, 0.0, 0.0, d)
    vv, aa = raw_v * RAD_S_PER_VELOCITY_UNIT, raw_a * RAD_S2_PER_ACCEL_UNIT
    assert q.end == pytest.approx(d / vv + vv / aa if d >= vv * vv / aa else 2 * math.sqrt(d / aa))


def test_time_based_and_rectangular_profiles():
    p = profile_for(3, 4, 800, 200, 1.0, 0.0, 0.0, 0.5)  # time-based: 800 ms in all, 200 ms accelerating
    assert p.end == pytest.approx(1.8)
    assert p.sample(1.0 + 0.2)[1] == pytest.approx(0.5 / 0.6)  # cruise speed d / (T − ta)
    r = profile_for(3, 0, 100, 0, 0.0, 0.0, 0.0, 1.0)  # Profile Acceleration 0: a rectangle
    assert r.end == pytest.approx(1.0 / (100 * RAD_S_PER_VELOCITY_UNIT))
    assert profile_for(3, 0, 0, 50, 0.0, 0.0, 0.0, 1.0).end == -math.inf  # Profile Velocity 0: a step


def test_horn_follows_a_trapezoid_and_arrives_on_time():
    clock = FakeClock()
    s = VirtualServo(XM430, 1, 1_000_000, clock=clock)
    s.set("profile_velocity", 80)  # 1.92 rad/s
    s.set("profile_acceleration", 20)  # 7.5 rad/s²
    s.write(TORQUE, b"\x01")
    goal = 2048 + 1024
    s.write(GOAL_POSITION, goal.to_bytes(4, "little"))
    v, a = 80 * RAD_S_PER_VELOCITY_UNIT, 20 * RAD_S2_PER_ACCEL_UNIT
    t_end = (math.pi / 2) / v + v / a
    clock.t = t_end / 2
    ctl = s.firmware_controller()
    lag = v * (servo_model(XM430).stall_torque / servo_model(XM430).no_load_speed) / ctl.kp  # P only: v·b/kp
    assert s.angle == pytest.approx(math.pi / 4 - lag, abs=0.01)  # follows the profile, a P-only servo's lag behind
    clock.t = t_end + 0.5
    assert s.get("present_position") == goal


def test_mode_5_holds_goal_currents_torque():
    servo = servo_model(XM430)
    kt = servo.stall_torque / servo.stall_current
    cap_a = 0.5
    sim = _horn(Gains(800), limit=cap_a)
    sim.d.qfrc_applied[0] = -3.0  # a load above the cap: the horn is pushed back, the servo holds the cap
    sim.set_reference(0.5, 0.0, 0.0)
    theta, w = 0.0, 0.0
    for _ in range(200):
        theta, w, _ = sim.step(theta, w, 5)
        assert abs(sim.d.qfrc_actuator[0]) <= kt * cap_a + 1e-9
    # through the servo's memory: Goal Current in mode 5
    clock = FakeClock()
    s = VirtualServo(XM430, 1, 1_000_000, clock=clock)
    s.set("operating_mode", 5)
    s.set("goal_current", round(cap_a / 0.00269))
    assert s.firmware_controller().torque_limit == pytest.approx(kt * round(cap_a / 0.00269) * 0.00269)


def test_mode_1_tracks_the_goal_velocity():
    clock = FakeClock()
    s = VirtualServo(XM430, 1, 1_000_000, clock=clock)
    s.set("operating_mode", 1)
    s.write(TORQUE, b"\x01")
    s.set("goal_velocity", 100)  # 2.4 rad/s
    clock.t = 1.0
    assert s.get("present_velocity") == pytest.approx(100, abs=1)
    a0 = s.angle
    clock.t = 2.0
    assert s.angle - a0 == pytest.approx(100 * RAD_S_PER_VELOCITY_UNIT, rel=0.01)


def test_virtual_bus_and_mujoco_give_the_same_response():
    """One implementation: the standalone horn and a MuJoCo robot's joint (the arm's joint1, a vertical axis with
    the link's inertia removed to leave the servo alone) run the same actuators on the same step."""
    spec = load_spec("arm")
    j = spec.joints[0]
    clock = FakeClock()
    s = VirtualServo(j.servo, j.servo_id, 1_000_000, clock=clock)
    for name, v in zip(("position_p_gain", "position_i_gain", "position_d_gain"), j.pid, strict=True):
        s.set(name, v)
    s.write(TORQUE, b"\x01")
    step = 0.3
    s.write(GOAL_POSITION, (2048 + round(step / RAD_PER_TICK)).to_bytes(4, "little"))
    goal = round(step / RAD_PER_TICK) * RAD_PER_TICK

    def edit(ms: mujoco.MjSpec) -> None:  # joint1 alone: the links made weightless, no gravity, like the bare horn
        ms.option.gravity = [0.0, 0.0, 0.0]
        for g in ms.geoms:
            g.mass = 1e-6

    r = MujocoRobot(spec, quantize=False, edit=edit)
    r.connect()
    r.model.dof_frictionloss[:] = 0.0
    r.arm()
    q0 = r.read().q
    horn, robot = [], []
    for k in range(1, 41):
        clock.t = 0.005 * k
        horn.append(s.angle)
        q = q0.copy()
        q[0] = goal
        r.write(Command(q=q))
        r.advance(0.005)
        robot.append(r.read().q[0])
    assert controller(j).ki > 0  # the arm's I term is in both
    np.testing.assert_allclose(horn, robot, atol=2e-3)
