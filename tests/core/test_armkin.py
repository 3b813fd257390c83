"""Arm kinematics (felis.armkin) against the MuJoCo model and in round trips."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from felis import armkin as K
from felis.sim.robot import MODELS_DIR


@pytest.fixture(scope="module")
def arm_model():
    m = mujoco.MjModel.from_xml_path(str(MODELS_DIR / "arm.xml"))
    return m, mujoco.MjData(m)


def _random_q(n: int, seed: int = 0, margin: float = 0.97) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(K.LOWER * margin, K.UPPER * margin, (n, 4))


def test_fk_matches_the_mujoco_tool_site(arm_model):
    m, d = arm_model
    site = m.site("tool").id
    for q in _random_q(300):
        d.qpos[:4] = q
        mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(K.fk(q), d.site_xpos[site], atol=1e-12)


def test_geometry_constants_match_the_reference():
    # robots.md: upper link 130.23 mm with a 10.62° offset; shoulder→wrist 254.2 mm, →tool 380.2 mm
    assert K.L1 == pytest.approx(0.13023, abs=1e-5)
    assert np.degrees(K.BETA) == pytest.approx(10.62, abs=0.01)
    assert K.L1 + K.L2 == pytest.approx(0.2542, abs=1e-4)
    assert K.REACH == pytest.approx(0.3802, abs=1e-4)
    np.testing.assert_allclose(K.fk(np.zeros(4)), [0.286, 0.0, 0.2045], atol=1e-12)


def test_jacobian_matches_finite_differences(arm_model):
    m, d = arm_model
    q = _random_q(200, seed=1)
    eps = 1e-6
    num = np.stack([(K.fk(q + eps * e) - K.fk(q - eps * e)) / (2 * eps) for e in np.eye(4)], axis=-1)
    np.testing.assert_allclose(K.jacobian(q), num, atol=1e-9)
    # and against MuJoCo's own site Jacobian
    site = m.site("tool").id
    jacp = np.zeros((3, m.nv))
    for qi in q[:20]:
        d.qpos[:4] = qi
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_jacSite(m, d, jacp, None, site)
        np.testing.assert_allclose(K.jacobian(qi), jacp[:, :4], atol=1e-12)


def test_closed_form_round_trips_both_elbow_branches():
    q = _random_q(5000, seed=2, margin=1.0)
    r, _ = K.planar(q)
    q = q[r > 0.01]  # the other half-plane (reaching back over the top) maps to q1 + π
    p = K.fk(q)
    up = K.elbow_up(q)
    assert up.any() and (~up).any()
    qc, ok = K.ik_closed(p, K.pitch(q), up, q[:, 0])
    assert ok.all()
    np.testing.assert_allclose(np.angle(np.exp(1j * (qc - q))), 0.0, atol=1e-9)
    np.testing.assert_allclose(K.fk(qc), p, atol=1e-12)


def test_closed_form_reports_targets_beyond_the_two_link_reach():
    q, ok = K.ik_closed(np.array([0.6, 0.0, 0.1]), 0.0)
    assert not ok


def test_refine_is_exact_with_the_seed_pitch_and_branch():
    q = _random_q(2000, seed=3, margin=0.9)
    r, _ = K.planar(q)
    q = q[r > 0.05]
    p = K.fk(q)
    seed = q + np.random.default_rng(4).normal(0.0, 0.02, q.shape)
    res = K.refine(p, seed)
    assert res.reachable.all() and K.within_limits(res.q).all()
    assert res.error.max() < 1e-12
    kept = res.exact
    assert kept.mean() > 0.9
    np.testing.assert_allclose(K.pitch(res.q[kept]), K.pitch(seed[kept]), atol=1e-12)
    np.testing.assert_array_equal(K.elbow_up(res.q[kept]), K.elbow_up(seed[kept]))


def test_refine_moves_an_infeasible_pitch_to_the_nearest_feasible_one():
    target = K.fk(np.array([0.0, 0.9, 0.6, 0.0]))  # far forward and low: pointing up is impossible
    res = K.refine(target, np.array([0.0, 0.9, 0.6, -2.5 - 0.9 - 0.6 + 0.9 + 0.6]))
    assert res.reachable and not res.exact
    assert res.error < 1e-12 and K.within_limits(res.q)


def test_refine_projects_unreachable_targets_and_flags_them():
    target = np.array([0.6, 0.0, 0.1])
    res = K.refine(target, np.zeros(4))
    assert not res.reachable and K.within_limits(res.q)
    direction = (target - K.SHOULDER) / np.linalg.norm(target - K.SHOULDER)
    nearest = K.SHOULDER + K.REACH * direction
    assert np.linalg.norm(K.fk(res.q) - nearest) < 2e-3


def test_dls_converges_from_a_nearby_seed():
    q = _random_q(500, seed=5, margin=0.8)
    p = K.fk(q)
    qd = K.dls(p, q + 0.1)
    assert np.percentile(np.linalg.norm(K.fk(qd) - p, axis=-1), 95) < 1e-8
