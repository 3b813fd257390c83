"""Smoke tests of ``bench/landing_limits.py``: short drops at ×1 and ×4 servo speed, spine and whole-body rules
(no search)."""

import numpy as np
import pytest
from conftest import load_bench


@pytest.fixture(scope="module")
def bench():
    return load_bench("landing_limits")


def test_faster_servo_turns_further(bench):
    rows, vmax, damping = {}, {}, {}
    for k in (1.0, 4.0):
        sim = bench.make_sim(k)
        try:
            vmax[k] = sim.spec.max_velocity.copy()
            damping[k] = sim.robot.servo["spine_pitch"].damping
            # upside down from 1.5 m, 0.25 s: still in the air, spine going round the circle
            rows[k] = bench.measure(sim, (180.0, 0.0, 0.0), 1.5, k, bench.circle(+1), duration=0.25)
        finally:
            sim.close()
    np.testing.assert_allclose(vmax[4.0], 4.0 * vmax[1.0])  # the safety layer's step limit follows the servo
    assert damping[4.0] == pytest.approx(damping[1.0])  # k× torque and k× no-load speed: same back-EMF
    for r in rows.values():
        assert r["touchdown_s"] is None and r["landed"] is False
        assert r["start_tilt_deg"] == pytest.approx(180.0, abs=0.5)
        assert 0.0 <= r["rotation_deg"] <= 180.0
        assert {"tilt_at_touchdown_deg", "upper_tilt_deg", "lower_tilt_deg", "waypoints_rad", "fall_s"} <= set(r)
    # measured: ×1 turns 11°, ×4 turns 49° in the same 0.25 s
    assert rows[4.0]["rotation_deg"] > rows[1.0]["rotation_deg"] + 10.0


def test_loop_rule_repeats_the_loop(bench):
    rule = bench.LoopRule(bench.circle(+1), speed=10.0, duration=2.0)
    q = np.cumsum(rule.v[:, :2], axis=0) * bench.DT  # integrated spine targets
    assert np.abs(q).max() <= bench.WAYPOINT_LIMIT + 1e-9
    assert np.count_nonzero(np.abs(rule.v[150:, :2]).max(axis=1)) > 0  # still moving late in the fall
    assert np.all(rule(None, 5.0) == 0.0)


def test_whole_body_rule_moves_leg_pairs_and_returns_to_the_release_pose(bench):
    w = np.zeros((bench.N_WAYPOINTS, 8))
    w[:, 4:] = [[1.5, 0.0, -1.5, 0.0], [1.5, 1.5, -1.5, -1.5], [0.0, 1.5, 0.0, -1.5]] * (bench.N_WAYPOINTS // 3)
    w[:, :2] = bench.circle(+1)
    fall = 0.45
    rule = bench.LoopRule(w, speed=10.0, duration=fall + 0.1, body=True)
    q = np.cumsum(rule.v, axis=0) * bench.DT  # integrated joint targets, from the release pose (0)
    assert np.abs(q[:, :4]).max() <= bench.WAYPOINT_LIMIT + 1e-9
    assert np.abs(q).max() <= max(bench.BODY_LIMITS) + 1e-9
    np.testing.assert_allclose(q[:, 4:6], q[:, 6:8])  # the front legs move together
    np.testing.assert_allclose(q[:, 8:10], q[:, 10:12])  # so do the hind legs
    assert np.abs(q[:, 4:]).max() > 1.0  # the legs do go round their loop
    back = int(round((fall - bench.RETURN_S) / bench.DT))  # from here on every joint heads home
    assert np.allclose(q[back + 16:], 0.0, atol=1e-9)  # 1.5 rad at 10 rad/s: home within 16 ticks
    assert np.all(np.abs(q[back + 1:]).max(axis=1)[1:] <= np.abs(q[back + 1:]).max(axis=1)[:-1] + 1e-12)


def test_legs_alone_turn_further_than_the_spine(bench):
    sim = bench.make_sim(1.0)
    try:
        w = np.zeros((bench.N_WAYPOINTS, 8))
        w[:, :2] = bench.circle(+1)
        spine = bench.measure(sim, (180.0, 0.0, 0.0), 1.5, 1.0, bench.circle(+1), duration=0.3)
        same = bench.measure(sim, (180.0, 0.0, 0.0), 1.5, 1.0, w, duration=0.3, body=True)
        # spine still; every leg swings out across the roll axis (roll), up along it (pitch), back (roll) and
        # down (pitch): only the first stroke turns a leg about the roll axis, so the body keeps its turn
        w[:] = 0.0
        w[:, 4:6] = w[:, 6:8] = bench.leg_loop(+1)
        legs = bench.measure(sim, (180.0, 0.0, 0.0), 1.5, 1.0, w, duration=0.3, body=True)
    finally:
        sim.close()
    assert same["joints"] == legs["joints"] == "whole body" and spine["joints"] == "spine"
    assert same["rotation_deg"] == pytest.approx(spine["rotation_deg"], abs=0.5)  # legs held: the spine rule
    assert np.asarray(legs["waypoints_rad"]).shape == (bench.N_WAYPOINTS, 8)
    # measured: the spine's circle turns 17°, the legs' loop 34° in the same 0.3 s
    assert legs["rotation_deg"] > spine["rotation_deg"] + 10.0
