"""felis.rotations against scipy's Rotation (the reference), over random rotations."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from felis import rotations as R

RNG = np.random.default_rng(7)
QUATS = [q if q[0] >= 0 else -q for q in (Rotation.random(50, random_state=3).as_quat(scalar_first=True))]


def _scipy(q):
    return Rotation.from_quat(q, scalar_first=True)


@pytest.mark.parametrize("i", range(0, 50, 7))
def test_matrix_rotate_and_product_match_scipy(i):
    q, p = QUATS[i], QUATS[(i + 1) % 50]
    v = RNG.normal(size=3)
    np.testing.assert_allclose(R.quat_matrix(q), _scipy(q).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(R.quat_rotate(q, v), _scipy(q).apply(v), atol=1e-12)
    np.testing.assert_allclose(R.quat_matrix(R.quat_mul(q, p)), (_scipy(q) * _scipy(p)).as_matrix(), atol=1e-12)


@pytest.mark.parametrize("i", range(0, 50, 5))
def test_euler_conventions_match_scipy_zyx(i):
    q = QUATS[i]
    yaw, pitch, roll = R.ypr_from_quat(q)
    np.testing.assert_allclose([yaw, pitch, roll], _scipy(q).as_euler("ZYX"), atol=1e-9)
    np.testing.assert_allclose(R.quat_matrix(R.quat_from_ypr(yaw, pitch, roll)), _scipy(q).as_matrix(), atol=1e-12)
    rd, pd, yd = R.quat_euler(q)
    np.testing.assert_allclose(R.quat_matrix(R.euler_quat(rd, pd, yd)), _scipy(q).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(R.roll_pitch(q), [roll, pitch], atol=1e-9)


@pytest.mark.parametrize("i", range(0, 50, 9))
def test_exp_log_and_body_rate(i):
    q = QUATS[i]
    np.testing.assert_allclose(R.quat_log(q), _scipy(q).as_rotvec(), atol=1e-9)
    np.testing.assert_allclose(R.quat_matrix(R.quat_exp(_scipy(q).as_rotvec())), _scipy(q).as_matrix(), atol=1e-12)
    w = RNG.normal(size=3)
    q2 = R.quat_mul(q, R.quat_exp(w * 0.01))
    np.testing.assert_allclose(R.body_rate(q, q2, 0.01), w, atol=1e-9)


def test_tilt_scalar_and_rows_agree_with_the_up_axis():
    qs = np.array(QUATS)
    up = np.array([_scipy(q).as_matrix()[2, 2] for q in qs])
    want = np.degrees(np.arccos(np.clip(up, -1, 1)))
    np.testing.assert_allclose(R.tilt_deg(qs), want, atol=1e-6)
    np.testing.assert_allclose([R.tilt_deg(q) for q in qs], want, atol=1e-6)
    assert math.isnan(R.tilt_deg(np.zeros((1, 4)))[0])
    assert R.tilt_deg([1, 0, 0, 0]) == 0.0 and abs(R.tilt_deg(R.euler_quat(180, 0, 0)) - 180) < 1e-9


def test_bad_quaternions_raise():
    with pytest.raises(ValueError):
        R.ypr_from_quat([0, 0, 0, 0])
    with pytest.raises(ValueError):
        R.roll_pitch([math.nan, 0, 0, 1])
