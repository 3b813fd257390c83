"""Where the IMU sits in the body.

The sensor sits in the robot's body at a rotation q_bs and its orientation drifts, so a still sensor
reports a constant rate (the bias). `apply_mounting` turns a sensor-frame reading into the body frame
and removes the bias (`DynamixelRobot` applies the calibration's values to every reading; they are
estimated by `felis.calib.imu.estimate_mounting`); `SensorMount` does the opposite for emulators.
"""

from __future__ import annotations

import math

import numpy as np

from felis.drivers.imu.frames import RATE_HZ
from felis.hal import Imu
from felis.rotations import quat_conj, quat_exp, quat_matrix, quat_mul


def apply_mounting(imu: Imu, rotation: np.ndarray | None = None, bias: np.ndarray | None = None) -> Imu:
    """A sensor-frame reading expressed in the body frame, gyro bias removed (a pure function).

    ``rotation`` q_bs is the sensor's orientation in the body frame (w, x, y, z; None = identity),
    ``bias`` b the rate the sensor reports at rest (rad/s, sensor frame; None = zero), as estimated by
    `felis.calib.imu.estimate_mounting`::

        q_wb = q_ws ⊗ q_bs⁻¹        gyro_b = R(q_bs)·(gyro_s − b)        accel_b = R(q_bs)·accel_s

    The world frame stays the sensor's own reference (z up, yaw zero at power-up); only the body is
    swapped for the sensor. With a yaw-free q_bs (what a level-pose estimate gives) a level body
    reports exactly the sensor's yaw: q_ws = qz(ψ) ⊗ q_bs gives q_wb = qz(ψ).
    """
    gyro = np.asarray(imu.gyro, dtype=float)
    if bias is not None:
        gyro = gyro - np.asarray(bias, dtype=float)
    if rotation is None:
        return Imu(quat=np.asarray(imu.quat, dtype=float).copy(), gyro=gyro.copy(),
                   accel=np.asarray(imu.accel, dtype=float).copy())
    q_bs = np.asarray(rotation, dtype=float)
    q_bs = q_bs / np.linalg.norm(q_bs)
    r = quat_matrix(q_bs)
    q_wb = quat_mul(np.asarray(imu.quat, dtype=float), quat_conj(q_bs))
    return Imu(quat=q_wb / np.linalg.norm(q_wb), gyro=r @ gyro, accel=r @ np.asarray(imu.accel, dtype=float))


class SensorMount:
    """What a sensor mounted at q_bs in a body reports, its orientation drifting at a constant rate (emulators).

    Each `sample` call is one sensor sample, 1/rate_hz s after the previous one (the sample clock, as
    `ImuReader` counts it)::

        q_ws(k) = q_wb ⊗ q_bs ⊗ exp(ω_d·k/rate_hz)          accel_s = R(q_bs)ᵀ·accel_b

    ``rotation``: q_bs (w, x, y, z), None = identity; ``drift``: ω_d, a constant sensor-frame rate
    (rad/s, 3-vector) integrated into the reported orientation, None = none. A still body then shows
    ω_d as a constant gyro offset in `ImuReader` (its rate is derived from consecutive orientations).
    The accelerometer does not drift. ▸ All three axes drift: a real BNO08x holds roll and pitch to
    gravity and drifts in heading, so this is the worse case for anything that trusts the orientation.
    Raises ValueError on a rotation that is not a unit quaternion (±1e-3) or a non-finite drift.
    """

    def __init__(self, rotation: np.ndarray | None = None, drift: np.ndarray | None = None, *,
                 rate_hz: float = RATE_HZ):
        self.rotation = np.array([1.0, 0.0, 0.0, 0.0]) if rotation is None else np.asarray(rotation, dtype=float)
        norm = float(np.linalg.norm(self.rotation)) if self.rotation.shape == (4,) else math.nan
        if not math.isfinite(norm) or abs(norm - 1.0) > 1e-3:
            raise ValueError(f"IMU mount must be a unit quaternion (w, x, y, z), got {self.rotation.tolist()}")
        self.rotation = self.rotation / norm
        self.drift = np.zeros(3) if drift is None else np.asarray(drift, dtype=float)
        if self.drift.shape != (3,) or not np.all(np.isfinite(self.drift)):
            raise ValueError(f"IMU drift must be 3 finite rates (rad/s), got {self.drift.tolist()}")
        self.rate_hz = rate_hz
        self.samples = 0
        self._r_sb = quat_matrix(self.rotation).T
        self.identity = bool(np.array_equal(self.rotation, [1.0, 0.0, 0.0, 0.0]) and not self.drift.any())

    def sample(self, q_wb: np.ndarray, accel_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q_ws, accel_s) for the body's orientation and specific force; advances the drift one sample."""
        k, self.samples = self.samples, self.samples + 1
        if self.identity:
            return q_wb, accel_b
        q = quat_mul(quat_mul(q_wb, self.rotation), quat_exp(self.drift * (k / self.rate_hz)))
        return q / np.linalg.norm(q), self._r_sb @ np.asarray(accel_b, dtype=float)
