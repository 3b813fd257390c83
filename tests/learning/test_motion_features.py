"""Motion features and similarity (seed 000 §3–4): hand-computed cases, the vectorised DTW against the
plain loop, and the segment vectors on the real cat model."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from felis.errors import ParameterError
from felis.learning.landing.features import (
    FEATURE_BODIES,
    MotionRecorder,
    Pca,
    body_frame,
    dtw,
    dtw_reference,
    flatten_features,
    heading_rotation,
    joint_states,
    logical_features,
    motion_distance,
    segment_index,
    transition_distance,
    transition_features,
)
from felis.sim.robot import load_model, model_path
from felis.spec import load_spec

J = len(FEATURE_BODIES)


# ------------------------------------------------------------------------------------ logical features
def test_logical_features_by_sign():
    v = np.array([[[1.0, -2.0, 0.0], [-1e-9, 3.0, 5.0]]])
    b = logical_features(v)
    assert b.dtype == bool
    np.testing.assert_array_equal(b, [[[True, False, False], [False, True, True]]])  # 0 is not > 0


def test_flatten_order_body_then_front_left_above():
    bits = np.zeros((2, 3, 3), dtype=bool)
    bits[0, 1, 2] = True  # frame 0, body 1, above
    bits[1, 2, 0] = True  # frame 1, body 2, front
    b = flatten_features(bits)
    assert b.shape == (2, 9) and b.dtype == float
    expect = np.zeros((2, 9))
    expect[0, 3 * 1 + 2] = 1.0
    expect[1, 3 * 2 + 0] = 1.0
    np.testing.assert_array_equal(b, expect)


def test_joint_states_follow_paper_row_order():
    # (front, left, above) as a binary number, front most significant: (0,0,1) = 1, (1,0,0) = 4
    combos = np.array([[[f, l, a] for f in (0, 1) for l in (0, 1) for a in (0, 1)]], dtype=bool)
    np.testing.assert_array_equal(joint_states(combos), [list(range(8))])


# ------------------------------------------------------------------------------------ transition features
def _states_to_bits(states):
    s = np.asarray(states)
    return np.stack([(s >> 2) & 1, (s >> 1) & 1, s & 1], axis=-1).astype(bool)


def test_transition_features_hand_case():
    bits = _states_to_bits([[0], [0], [1], [1], [0]])  # one joint, T = 5: 0→0, 0→1, 1→1, 1→0
    tf = transition_features(bits)
    assert tf.shape == (1, 8, 8)
    expect = np.zeros((1, 8, 8))
    for s, s2 in ((0, 0), (0, 1), (1, 1), (1, 0)):
        expect[0, s, s2] = 1 / 5  # count / number of frames (eq. 6), not / transitions
    np.testing.assert_allclose(tf, expect)
    assert tf.sum() == pytest.approx(4 / 5)


def test_transition_features_row_is_first_frame_and_joints_apart():
    bits = _states_to_bits([[7, 2], [3, 2]])  # joint 0: 7→3, joint 1: 2→2
    tf = transition_features(bits)
    assert tf[0, 7, 3] == 0.5 and tf[0, 3, 7] == 0.0
    assert tf[1, 2, 2] == 0.5 and tf.sum() == 1.0
    assert not transition_features(bits[:1]).any()  # one frame: no transitions


def test_transition_distance_hand_case():
    a = np.zeros((2, 8, 8))
    b = np.zeros((2, 8, 8))
    a[0, 0, 0], b[0, 0, 0] = 0.5, 0.25
    a[1, 3, 4], b[1, 4, 3] = 0.1, 0.2
    assert transition_distance(a, b) == pytest.approx(0.25 + 0.1 + 0.2)
    assert transition_distance(a, a) == 0.0
    assert transition_distance(a, b) == transition_distance(b, a)


# ------------------------------------------------------------------------------------ DTW
@pytest.mark.parametrize("a, b, expect", [
    ([0, 1, 2], [0, 1, 1, 2], 0.0),   # repeated frame is warped away
    ([0, 0], [1], 2.0),               # both frames must match the single one
    ([0], [3], 3.0),
    ([0, 2], [0, 1, 2], 1.0),         # 1 pairs with 0 or 2 at cost 1
    ([[0, 0], [3, 4]], [[0, 0]], 5.0),  # Euclidean local cost
])
def test_dtw_hand_cases(a, b, expect):
    assert dtw(a, b) == pytest.approx(expect)
    assert dtw_reference(a, b) == pytest.approx(expect)
    assert motion_distance(a, b) == pytest.approx(expect)


@pytest.mark.parametrize("n, m", [(1, 1), (1, 2), (2, 1), (2, 2), (37, 200), (200, 37), (200, 200)])
def test_dtw_vectorised_equals_reference(n, m):
    rng = np.random.default_rng(n * 1000 + m)
    a, b = rng.normal(size=(n, 8)), rng.normal(size=(m, 8))
    assert dtw(a, b) == pytest.approx(dtw_reference(a, b), rel=1e-12)


def test_motion_distance_symmetric_nonnegative_zero_on_self():
    rng = np.random.default_rng(3)
    for n, m in ((5, 9), (40, 31)):
        a, b = rng.normal(size=(n, 4)), rng.normal(size=(m, 4))
        d = motion_distance(a, b)
        assert d > 0.0
        assert d == motion_distance(b, a)
        assert dtw(a, b) == dtw(b, a)  # this DTW is symmetric: eq. 7's two terms agree
        assert motion_distance(a, a) == 0.0


# ------------------------------------------------------------------------------------ PCA
def _random_bits(seed, t=60):
    rng = np.random.default_rng(seed)
    return flatten_features(rng.random((t, J, 3)) < 0.3)


def test_pca_full_dims_reconstructs_exactly():
    b = _random_bits(0)
    pca = Pca.fit(b, b.shape[1])
    l = pca.transform(b)  # noqa: E741
    assert l.shape == (60, 3 * J)
    np.testing.assert_allclose(pca.inverse_transform(l), b, atol=1e-12)
    np.testing.assert_allclose(pca.components @ pca.components.T, np.eye(3 * J), atol=1e-12)
    assert np.all(np.diff(pca.variance) <= 1e-12)


def test_pca_shape_and_deterministic_signs():
    b = _random_bits(1)
    pca = Pca.fit(b, 4)
    assert pca.transform(b[:7]).shape == (7, 4) and pca.dims == 4
    big = np.abs(pca.components).argmax(axis=1)
    assert np.all(pca.components[np.arange(4), big] > 0)
    again = Pca.fit(b.copy(), 4)
    np.testing.assert_array_equal(again.components, pca.components)
    # negating the centred data flips every SVD vector; the sign rule undoes it
    flipped = Pca.fit(2 * b.mean(axis=0) - b, 4)
    np.testing.assert_allclose(flipped.components, pca.components, atol=1e-10)


def test_pca_round_trips_through_npz(tmp_path):
    pca = Pca.fit(_random_bits(2), 5)
    np.savez(tmp_path / "f.npz", **pca.to_arrays(), other=np.ones(3))
    with np.load(tmp_path / "f.npz") as z:
        back = Pca.from_arrays(z)
    for k in ("mean", "components", "variance"):
        np.testing.assert_array_equal(getattr(back, k), getattr(pca, k))


# ------------------------------------------------------------------------------------ the real cat
@pytest.fixture(scope="module")
def cat():
    m = load_model(model_path(load_spec("cat")))
    return m, mujoco.MjData(m)


def _bits_now(m, d):
    mujoco.mj_forward(m, d)
    return dict(zip(FEATURE_BODIES, logical_features(body_frame(m, d)[None])[0], strict=True))


def _reset(m, d, **joints):
    mujoco.mj_resetData(m, d)
    for name, q in joints.items():
        d.qpos[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)]] = q
    mujoco.mj_forward(m, d)


LEGS = [b for b in FEATURE_BODIES if b.endswith(("_leg", "_foot"))]


def test_body_frame_initial_pose(cat):
    m, d = cat
    _reset(m, d)
    b = _bits_now(m, d)
    for leg in LEGS:
        assert not b[leg][2], leg  # legs point down (hip → foot)
    assert b["head"][0] and not b["head"][2]  # head in front (3 mm below the torso centre)
    assert not b["tail"][0] and not b["lower_body"][0]  # tail and rear half behind
    vec = body_frame(m, d)
    np.testing.assert_allclose(vec[FEATURE_BODIES.index("fl_leg")], [0, 0, -0.085], atol=1e-12)
    np.testing.assert_allclose(vec[FEATURE_BODIES.index("fl_foot")], vec[FEATURE_BODIES.index("fl_leg")])


def test_body_frame_upside_down_flips_above_for_legs(cat):
    m, d = cat
    _reset(m, d)
    d.qpos[3:7] = [0.0, 1.0, 0.0, 0.0]  # 180° about x: on its back, still facing +x
    b = _bits_now(m, d)
    for leg in LEGS:
        assert b[leg][2], leg
    assert b["head"][0] and b["head"][2]  # still in front; now above (the 3 mm offset flipped)
    assert not b["tail"][0]


def test_body_frame_heading_follows_root_yaw(cat):
    m, d = cat
    _reset(m, d)
    base = body_frame(m, d)
    d.qpos[3:7] = [np.cos(1.0), 0.0, 0.0, np.sin(1.0)]  # yaw 2 rad: the heading frame turns with it
    mujoco.mj_forward(m, d)
    np.testing.assert_allclose(body_frame(m, d), base, atol=1e-12)


def test_body_frame_joint_signs(cat):
    m, d = cat
    _reset(m, d, fl_pitch=0.5, fr_pitch=-0.5, hl_roll=0.4, tail_pitch=0.5, spine_yaw=-0.3, spine_pitch=0.2)
    b = _bits_now(m, d)
    assert not b["fl_leg"][0] and b["fr_leg"][0]  # pitch + swings the foot backward
    assert b["hl_leg"][1] and b["hl_foot"][1]     # roll + swings the foot to the left
    assert b["tail"][2]                            # tail pitch + raises the tail
    assert b["lower_body"][1] and b["lower_body"][2]  # spine yaw − swings the rear left; pitch + raises it


def test_heading_fallback_nose_down():
    # pitch +90° about y: x axis straight down, y axis still world +y → heading = world x
    r = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    np.testing.assert_allclose(heading_rotation(r), np.eye(3), atol=1e-12)


def test_recorder_collects_frames(cat):
    m, d = cat
    _reset(m, d)
    rec = MotionRecorder(m)
    for _ in range(3):
        mujoco.mj_step(m, d)
        rec.record(d)
    v = rec.vectors()
    assert v.shape == (3, J, 3) and len(rec) == 3
    np.testing.assert_allclose(v[-1], body_frame(m, d, segment_index(m)))


# ------------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize("call", [
    lambda: logical_features(np.zeros((4, 3))),
    lambda: logical_features(np.zeros((0, J, 3))),
    lambda: logical_features(np.full((2, J, 3), np.nan)),
    lambda: flatten_features(np.full((2, J, 3), 2)),
    lambda: transition_features(np.zeros((3, J, 2), dtype=bool)),
    lambda: transition_distance(np.zeros((2, 8, 8)), np.zeros((3, 8, 8))),
    lambda: dtw(np.zeros((3, 2)), np.zeros((3, 3))),
    lambda: dtw(np.zeros((0, 2)), np.zeros((3, 2))),
    lambda: dtw([0.0, np.nan], [1.0]),
    lambda: motion_distance([[np.inf]], [[1.0]]),
    lambda: Pca.fit(np.zeros((5, 4)), 5),
    lambda: Pca.fit(np.zeros((5, 4)), 0),
    lambda: Pca.fit(np.array([[np.nan, 1.0]]), 1),
    lambda: Pca.fit(np.zeros((5, 4)), 2).transform(np.zeros((2, 3))),
    lambda: Pca.from_arrays({"pca_mean": np.zeros(3)}),
    lambda: heading_rotation(np.zeros(9)),
])
def test_bad_input_is_one_line_parameter_error(call):
    with pytest.raises(ParameterError) as e:
        call()
    assert "\n" not in str(e.value) and str(e.value)


def test_missing_body_is_parameter_error():
    m = mujoco.MjModel.from_xml_string("<mujoco><worldbody><body name='a'><geom size='1'/></body>"
                                       "</worldbody></mujoco>")
    with pytest.raises(ParameterError, match="upper_body|head"):
        segment_index(m)
