"""`felis.controllers.teleop`: the leader → follower mapping, the engagement ramp, the lag measure and keyboard
jogging (joint and tool space through the shipped IK weights), as pure functions of state."""

from __future__ import annotations

import math

import numpy as np
import pytest

from felis import armkin
from felis.controllers.teleop import (
    JOINT_STEP,
    JogController,
    JointLink,
    TeleopController,
    parse_map,
    resolve_map,
    tracking_lag,
)
from felis.errors import ParameterError
from felis.hal import State
from felis.learning.ik.solver import IkSolver
from felis.spec import load_spec

ARM, LEADER, CAT = load_spec("arm"), load_spec("arm-leader"), load_spec("cat")


def state(t: float, q) -> State:
    q = np.asarray(q, dtype=float)
    return State(t=t, q=q, dq=np.zeros_like(q))


# ------------------------------------------------------------------------------------------- mapping
def test_parse_map_reads_scale_and_offset():
    assert parse_map("joint1=joint1, j4=joint4*-1+0.2,g=gripper*0.5-1e-3") == (
        JointLink("joint1", "joint1"), JointLink("j4", "joint4", -1.0, 0.2), JointLink("g", "gripper", 0.5, -0.001))


@pytest.mark.parametrize("text, fragment", [
    ("joint1", "cannot read 'joint1'"), ("a=b*", "cannot read"), ("a=b,,c=d", "an empty entry"),
    ("a=b*0", "non-zero"), ("a=b*1e999", "finite"),
])
def test_parse_map_refuses_bad_text(text, fragment):
    with pytest.raises(ParameterError, match=fragment):
        parse_map(text)


def test_default_mapping_is_same_names_then_same_order():
    m = resolve_map(None, LEADER, ARM)
    assert [k.leader for k in m.links] == list(ARM.names) and list(m.follower_idx) == list(range(5))
    by_order = resolve_map(None, CAT, ARM)  # no name in common: the first joints in order
    assert [(k.leader, k.follower) for k in by_order.links] == list(zip(CAT.names[:5], ARM.names, strict=True))


@pytest.mark.parametrize("text, fragment", [
    ("joint9=joint1", "leader 'arm-leader' has no joint 'joint9'"),
    ("joint1=wrist", "follower 'arm' has no joint 'wrist'"),
    ("joint1=joint2,joint2=joint2", "'joint2' from more than one"),
])
def test_resolve_map_names_what_is_missing(text, fragment):
    with pytest.raises(ParameterError, match=fragment):
        resolve_map(parse_map(text), LEADER, ARM)


def test_mapping_scales_offsets_and_holds_the_rest():
    m = resolve_map(parse_map("joint4=joint1*-1+0.2,gripper=gripper*0.5"), LEADER, ARM)
    q = m.apply(np.array([0.1, 0.2, 0.3, 0.4, 0.01]), np.array([9.0, 8.0, 7.0, 6.0, 5.0]))
    assert np.allclose(q, [-0.4 + 0.2, 8.0, 7.0, 6.0, 0.005])


# ------------------------------------------------------------------------------------------- following
def test_teleop_ramps_in_then_follows_the_leader():
    leader = {"q": np.array([0.5, -0.2, 0.3, 0.1, 0.01])}
    ctl = TeleopController(resolve_map(None, LEADER, ARM), lambda: leader["q"], ramp=1.0)
    q0 = np.zeros(5)
    ctl.reset(ARM, state(2.0, q0))
    assert np.allclose(ctl(state(2.0, q0)).q, q0)  # no jump at engagement
    mid = ctl(state(2.5, q0)).q
    assert np.allclose(mid, 0.5 * leader["q"])  # min-jerk weight at half time is exactly 1/2
    leader["q"] = np.array([0.6, -0.1, 0.2, 0.0, 0.015])
    assert np.allclose(ctl(state(3.0, q0)).q, leader["q"]) and np.allclose(ctl.leader_q, leader["q"])


def test_a_failing_leader_read_propagates_for_the_loop_to_hold():
    def fail():
        raise ParameterError("no leader")

    ctl = TeleopController(resolve_map(None, LEADER, ARM), fail, ramp=0.0)
    ctl.reset(ARM, state(0.0, np.zeros(5)))
    with pytest.raises(ParameterError):
        ctl(state(0.01, np.zeros(5)))


def test_tracking_lag_recovers_a_known_delay():
    t = np.arange(0.0, 3.0, 0.01)
    ref = np.column_stack([0.3 * np.sin(np.pi * t), 0.2 * np.cos(2.1 * t)])
    delayed = np.column_stack([0.3 * np.sin(np.pi * (t - 0.037)), 0.2 * np.cos(2.1 * (t - 0.037))]) + 0.001
    lag = tracking_lag(t, ref, delayed)
    assert abs(lag.lag_s - 0.037) <= 0.001
    assert abs(lag.rms - 0.001) < 2e-4 and lag.rms_raw > 10 * lag.rms


def test_teleop_summary_measures_a_follower_one_tick_behind():
    # a follower that reads exactly what was commanded one tick earlier: a lag of one tick, no error
    hand = {"q": np.zeros(5)}
    ctl = TeleopController(resolve_map(None, LEADER, ARM), lambda: hand["q"], ramp=0.0)
    dt, q = 0.01, np.zeros(5)
    ctl.reset(ARM, state(0.0, q))
    for k in range(300):
        hand["q"] = np.array([0.3 * math.sin(math.pi * k * dt), 0.1, 0.0, 0.0, 0.01])
        q = ctl(state(k * dt, q)).q
    s = ctl.summary()
    assert s["lag_ms"] == pytest.approx(10.0, abs=0.5) and s["rms_after_lag"] < 1e-9


# ------------------------------------------------------------------------------------------- jogging
def jog(keys: list[list[str]], solver=None, ticks: int = 1, t0: float = 0.0):
    feed = iter(keys)
    ctl = JogController(lambda: next(feed, []), solver)
    q = ARM.pose("stand")
    ctl.reset(ARM, state(t0, q))
    out = None
    for k in range(ticks):
        out = ctl(state(t0 + 0.01 * k, q)).q
    return ctl, out


def test_jog_selects_a_joint_and_steps_it_within_its_limits():
    ctl, q = jog([["2", "+", "+", "up", "-"]])
    assert q[1] == pytest.approx(ARM.pose("stand")[1] + 2 * JOINT_STEP)
    ctl, q = jog([["3"] + ["+"] * 100])
    assert q[2] == pytest.approx(ARM.joints[2].upper)
    ctl, q = jog([["o", "o", "c", "9", "?"]])
    assert q[4] == pytest.approx(ARM.pose("stand")[4] + 0.002) and ctl.ignored == 2  # "9": the arm has 5 joints
    ctl, _ = jog([["esc"]])
    assert ctl.done


def test_jog_in_tool_space_moves_the_tool_point_through_the_learned_ik():
    ctl, q = jog([["z", "up", "up", "x", "-"]], IkSolver.load(), ticks=60)
    start = armkin.fk(ARM.pose("stand")[:4])
    assert ctl.mode == "tool" and np.allclose(ctl.tool - start, [-0.005, 0, 0.01])
    assert np.linalg.norm(armkin.fk(q[:4]) - ctl.tool) < 1e-3
    assert q[4] == ARM.pose("stand")[4]  # the gripper is left alone


def test_tool_space_needs_the_arm_and_the_ik():
    ctl, _ = jog([["x", "+"]], None)
    assert ctl.mode == "joint" and ctl.ignored == 1  # "x" refused without a solver; "+" jogs joint1
