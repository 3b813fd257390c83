"""Smoke test of ``bench/landing_limits.py``: one short drop at ×1 and ×4 servo speed (no search)."""

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
