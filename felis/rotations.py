"""Rotations: unit quaternions (w, x, y, z), Euler angles and tilt — the one home for them in felis.

Conventions (the same everywhere in felis, the IMU's and MuJoCo's):

- A quaternion is ``(w, x, y, z)``, scalar first, Hamilton product; it rotates body-frame vectors into
  the world frame: ``v_world = R(q) · v_body``.
- Euler angles are intrinsic Z-Y-X: ``R = Rz(yaw) · Ry(pitch) · Rx(roll)`` (the BNO08x UART-RVC report's
  and the drop scenarios' convention).
- Tilt is the angle between the body's up axis and world up: ``cos(tilt) = R₂₂ = 1 − 2(x² + y²)``.
- Gravity is ``G`` = 9.81 m/s², MuJoCo's default and the models'.

These run on the control loop's hot path (one quaternion per tick, a few µs budget), so they are
written on Python floats and numpy; ``scipy.spatial.transform.Rotation`` (their reference in
``tests/core/test_rotations.py``) costs ~20 µs a call to build, which is for off-line work.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

G = 9.81  # m/s², standard gravity; MuJoCo's default ``gravity="0 0 -9.81"`` in sim/models/*.xml

Quat = Sequence[float] | np.ndarray


def quat_mul(a: Quat, b: Quat) -> np.ndarray:
    """Hamilton product a ⊗ b of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw])


def quat_conj(q: Quat) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion)."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_rotate(q: Quat, v: Sequence[float] | np.ndarray) -> np.ndarray:
    """R(q)·v: a vector given in the rotated (body) frame, expressed in the reference (world) frame."""
    return quat_mul(quat_mul(q, np.array([0.0, *v])), quat_conj(q))[1:]


def quat_matrix(q: Quat) -> np.ndarray:
    """3×3 rotation matrix R(q) of a (w, x, y, z) quaternion, normalised here: R·v = `quat_rotate`(q, v)."""
    w, x, y, z = np.asarray(q, dtype=float).tolist()  # Python floats: numpy scalars are slow here
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_from_ypr(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of R = Rz(yaw)·Ry(pitch)·Rx(roll); angles in radians."""
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return np.array([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])


def wrap_pi(a: float) -> float:
    """Angle wrapped to [−π, π)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def ypr_from_quat(q: Quat) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in radians of a (w, x, y, z) quaternion; inverse of `quat_from_ypr`.

    yaw and roll in [−π, π), pitch in [−π/2, π/2]. The quaternion is normalised first; a zero or
    non-finite one raises ValueError. At gimbal lock (|pitch| = 90°) roll is reported as 0.
    """
    q = np.asarray(q, dtype=float)
    norm = float(np.linalg.norm(q))
    if q.shape != (4,) or not math.isfinite(norm) or norm == 0.0:
        raise ValueError(f"not a valid quaternion: {q!r}")
    w, x, y, z = q / norm
    # Bernardes & Viollet (2022), "Quaternion to Euler angles conversion: a direct, general and
    # computationally efficient method", for R = Rz(yaw)·Ry(pitch)·Rx(roll): no asin (full precision at
    # |pitch| → 90°), and near gimbal lock the ill-defined difference angle only moves the rotation by
    # as little as the term that defines it, so the round trip stays exact to rounding.
    a, b, c, d = w - y, x + z, y + w, z - x
    pitch = 2 * math.atan2(math.hypot(c, d), math.hypot(a, b)) - math.pi / 2
    plus, minus = math.atan2(b, a), math.atan2(d, c)
    # At gimbal lock (|pitch| within ~1e-12 rad of 90°) only yaw ± roll is defined: roll is reported as 0,
    # which moves the rotation by at most ~1e-11 rad.
    if math.hypot(c, d) < 1e-12:  # pitch = −90°: yaw + roll
        minus = plus
    elif math.hypot(a, b) < 1e-12:  # pitch = +90°: yaw − roll
        plus = minus
    roll, yaw = plus - minus, plus + minus
    return wrap_pi(yaw), pitch, wrap_pi(roll)


def euler_quat(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """Quaternion (w, x, y, z) of R = Rz(yaw)·Ry(pitch)·Rx(roll), angles in degrees (the drops' convention)."""
    return quat_from_ypr(math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg))


def quat_euler(q: Quat) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in degrees of a unit quaternion; inverse of `euler_quat` away from gimbal lock
    (pitch = asin(2(wy − zx)); use `ypr_from_quat` near ±90° of pitch)."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)


def quat_exp(rotvec: Sequence[float] | np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation vector (axis × angle, rad)."""
    v = np.asarray(rotvec, dtype=float)
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.array([1.0, *(v / 2)])
    return np.array([math.cos(angle / 2), *(v * (math.sin(angle / 2) / angle))])


def quat_log(q: Quat) -> np.ndarray:
    """Rotation vector (axis × angle, rad, angle ≤ π) of a unit quaternion; inverse of `quat_exp`."""
    q = np.asarray(q, dtype=float)
    if q[0] < 0:
        q = -q
    v = q[1:]
    sin_half = float(np.linalg.norm(v))
    if sin_half < 1e-12:
        return 2 * v
    return v * (2 * math.atan2(sin_half, q[0]) / sin_half)


def body_rate(q_prev: Quat, q_cur: Quat, dt: float) -> np.ndarray:
    """Mean body rate (rad/s, body frame) turning q_prev into q_cur over dt seconds.

    Δq = q_prev⁻¹ ⊗ q_cur (sign chosen so Δq_w ≥ 0, the shorter way round); ω = rotvec(Δq) / dt.
    """
    dq = quat_mul(quat_conj(q_prev), q_cur)
    if dq[0] < 0:
        dq = -dq
    v = dq[1:]
    sin_half = float(np.linalg.norm(v))
    if sin_half < 1e-12:
        return 2 * v / dt
    return v * (2 * math.atan2(sin_half, dq[0]) / sin_half / dt)


def up_z(quat: Quat) -> float:
    """World-z component of the body's up axis: R₂₂ = 1 − 2(x² + y²)/|q|², the cosine of the tilt."""
    w, x, y, z = (float(v) for v in quat)
    return 1.0 - 2.0 * (x * x + y * y) / (w * w + x * x + y * y + z * z)


def tilt_from_up(up: float | np.ndarray) -> float | np.ndarray:
    """Tilt (degrees) from the world-z component of the body's up axis (R₂₂, e.g. MuJoCo's ``xmat[8]``)."""
    if np.ndim(up) == 0:
        return math.degrees(math.acos(max(-1.0, min(1.0, float(up)))))
    return np.degrees(np.arccos(np.clip(up, -1.0, 1.0)))


def tilt_deg(quat: Quat) -> float | np.ndarray:
    """Tilt (degrees) of the body's up axis from world up, of one (w, x, y, z) quaternion (a float) or of
    each row of an (…, 4) array (an array; a zero row gives NaN). Quaternions are normalised here."""
    q = np.asarray(quat, dtype=float)
    if q.ndim == 1:
        return tilt_from_up(up_z(q))
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = q / np.where(norm > 0, norm, np.nan)
    return tilt_from_up(1.0 - 2.0 * (q[..., 1] ** 2 + q[..., 2] ** 2))


def roll_pitch(quat: Quat) -> tuple[float, float]:
    """Roll and pitch (rad) of a (w, x, y, z) quaternion, R = Rz(yaw)·Ry(pitch)·Rx(roll):
    roll = atan2(R₂₁, R₂₂) ∈ (−π, π], pitch = asin(−R₂₀) ∈ [−π/2, π/2]. A zero or non-finite quaternion
    raises ValueError."""
    w, x, y, z = (float(v) for v in quat)
    n = w * w + x * x + y * y + z * z
    if not (n > 0 and math.isfinite(n)):
        raise ValueError(f"orientation quaternion {tuple(quat)} is zero or not finite")
    s = 2.0 / n
    r20, r21, r22 = s * (x * z - w * y), s * (y * z + w * x), 1.0 - s * (x * x + y * y)
    return math.atan2(r21, r22), math.asin(max(-1.0, min(1.0, -r20)))


def roll_pitch_many(quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`roll_pitch` of (B, 4) quaternions: two (B,) arrays. Any zero or non-finite row raises ValueError."""
    q = np.asarray(quat, dtype=float)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    n = w * w + x * x + y * y + z * z
    if not np.all((n > 0) & np.isfinite(n)):
        raise ValueError("an orientation quaternion is zero or not finite")
    s = 2.0 / n
    r20, r21, r22 = s * (x * z - w * y), s * (y * z + w * x), 1.0 - s * (x * x + y * y)
    return np.arctan2(r21, r22), np.arcsin(np.clip(-r20, -1.0, 1.0))


def matrix_quats(R: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions (w, x, y, z) of (n, 3, 3) rotation matrices, vectorised (the inverse of
    `quat_matrix`). Each row takes the largest of 1 + tr R, 1 + 2R₀₀ − tr R, … as its pivot (Shepperd's
    method), so no division is by a small number; the sign makes w ≥ 0."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    r00, r11, r22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = r00 + r11 + r22
    piv = np.stack([1 + tr, 1 + 2 * r00 - tr, 1 + 2 * r11 - tr, 1 + 2 * r22 - tr], axis=1)
    k = piv.argmax(axis=1)
    s = np.sqrt(np.maximum(piv[np.arange(len(R)), k], 1e-300))  # = 4·|component k| / 2 … (2·|q_k|)
    d21, d02, d10 = R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]
    s21, s02, s10 = R[:, 2, 1] + R[:, 1, 2], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 0] + R[:, 0, 1]
    q = np.empty((len(R), 4))
    cand = [np.stack([s * s, d21, d02, d10], 1), np.stack([d21, s * s, s10, s02], 1),
            np.stack([d02, s10, s * s, s21], 1), np.stack([d10, s02, s21, s * s], 1)]
    for i in range(4):
        m = k == i
        q[m] = cand[i][m] / (2 * s[m, None])
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q
