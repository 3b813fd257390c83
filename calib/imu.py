"""IMU mounting calibration: the sensor's tilt in the body and its gyro bias, from a still, level robot.

The IMU (a BNO08x in UART-RVC mode, `felis.drivers.imu`) reports its own frame s: orientation q_ws,
rate ω_s (derived from consecutive orientations), specific force a_s. The controllers want the body
frame b of the upper body (x forward, y left, z up, as in the MJCF model). The sensor sits in the body
at a fixed rotation q_bs (R_bs = R(q_bs) maps sensor-frame vectors into the body frame) and, at rest,
reports a constant rate b_s (the bias; on a BNO in RVC mode, the drift of its fused orientation).

Estimate (`estimate_mounting`)
------------------------------
With the robot still on a level surface the body's specific force is the reaction to gravity,
a_b = (0, 0, g), so the sensor reads a_s = R_bsᵀ·(0, 0, g): the mean accelerometer direction
u = ā_s/|ā_s| is the body's up axis seen from the sensor. Writing R_bs = Ry(θ)·Rx(φ) (yaw 0)::

    u = (−sin θ,  sin φ cos θ,  cos φ cos θ)
    φ = atan2(u_y, u_z)     θ = atan2(−u_x, √(u_y² + u_z²))     q_bs = qy(θ) ⊗ qx(φ)
    tilt = acos(u_z)        (the angle between the sensor's z and the body's z)

φ and θ are the sensor's roll and pitch in the body (positive by the right-hand rule about the body's
x and y): a sensor rolled by +φ reads +g·sin φ on its y axis. ▸ The rotation about gravity (the
mount's yaw) does not change what a level, still sensor reads, so it is not observable here: it is
kept 0 (`ImuMounting.yaw_observable` is False). A yaw error ψ of the mount leaves the corrected body
level but turned by ψ about z, its gyro and accelerometer axes turned by ψ about z too. Finding it
needs a known rotation (a turn about the body's x or y), not done here.

The bias is the mean rate over the window, taken as the chord of the orientation: b_s =
log(q_ws(0)⁻¹ ⊗ q_ws(T))/T with T on the sensor's sample clock (exact for a constant drift, and free
of the 0.01° quantisation of the per-sample rates except at the two ends). The robot must be still:
the RMS spread of the per-sample rates about b_s (``still_rad_s``) and of the accelerometer about ā_s
(``still_accel``) are bounded, as are |ā_s| − g (``g_tol``), |b_s| (``max_bias``) and the tilt
(``level_tol``: a larger one means the robot is not on a level surface or the IMU is on its side).

Correction (`apply_mounting`, re-exported from `felis.drivers.imu`, where `DynamixelRobot` applies it)::

    q_wb = q_ws ⊗ q_bs⁻¹        ω_b = R_bs·(ω_s − b_s)        a_b = R_bs·a_s

The world frame stays the sensor's reference (z up, yaw 0 at power-up): a level body reports the
sensor's yaw. A bias cannot undo orientation drift that the sensor's output has already integrated.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from felis.drivers.imu import G, ImuReader, apply_mounting, frames_between
from felis.errors import CalibrationError, ParameterError
from felis.hal import Imu
from felis.rotations import body_rate, quat_conj, quat_from_ypr, quat_log, quat_mul, ypr_from_quat

__all__ = ["ImuMounting", "apply_mounting", "estimate_mounting"]

UNIT_TOL = 1e-3  # |‖q‖ − 1| accepted for a stored rotation
_KEYS = ("rotation", "gyro_bias", "tilt_deg", "samples", "duration_s", "gravity_residual", "yaw_observable")


def _vector(where: str, value, n: int) -> np.ndarray:
    """n finite numbers (a list, tuple or array) or CalibrationError naming ``where``."""
    try:
        if isinstance(value, (str, bytes, Mapping)) or any(isinstance(v, bool) for v in value):
            raise TypeError
        v = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: expected {n} numbers, got {value!r}") from None
    if v.shape != (n,):
        raise CalibrationError(f"{where}: expected {n} numbers, got {len(v.ravel())}")
    if not np.all(np.isfinite(v)):
        raise CalibrationError(f"{where}: values must be finite, got {v.tolist()}")
    return v


def _rotation(where: str, value) -> np.ndarray:
    q = _vector(where, value, 4)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > UNIT_TOL:
        raise CalibrationError(f"{where}: not a unit quaternion (w, x, y, z): norm {norm:.6g}")
    q = q / norm
    return -q if q[0] < 0 else q  # q and −q are one rotation: keep w ≥ 0


def _number(where: str, value, *, integer: bool = False, minimum: float | None = None) -> float:
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if not ok or isinstance(value, bool) or not math.isfinite(value) or (minimum is not None and value < minimum):
        kind = "an integer" if integer else "a finite number"
        bound = f" ≥ {minimum:g}" if minimum is not None else ""
        raise CalibrationError(f"{where}: expected {kind}{bound}, got {value!r}")
    return value


@dataclass(frozen=True, eq=False)
class ImuMounting:
    """The IMU's mounting in the body and its gyro bias (module docstring).

    rotation: q_bs, the sensor's orientation in the body frame, unit quaternion (w, x, y, z), w ≥ 0,
    yaw 0 (not observable from a level pose); gyro_bias: the sensor-frame rate at rest (rad/s);
    samples: frames averaged; duration_s: the sample-clock span they cover; gravity_residual: |ā| − g
    (m/s², the accelerometer's scale error as seen at rest). Invalid values raise `CalibrationError`.
    """

    rotation: np.ndarray
    gyro_bias: np.ndarray
    samples: int = 0
    duration_s: float = 0.0
    gravity_residual: float = 0.0

    yaw_observable = False  # the mount's rotation about gravity is not estimated (kept 0)

    def __post_init__(self):
        rotation = _rotation("imu.rotation", self.rotation)
        bias = _vector("imu.gyro_bias", self.gyro_bias, 3)
        for a in (rotation, bias):
            a.flags.writeable = False
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "gyro_bias", bias)

    @property
    def tilt_deg(self) -> float:
        """Angle (°) between the sensor's z axis and the body's: how far the mount is from level."""
        w, x, y, _ = self.rotation
        return math.degrees(math.acos(min(1.0, max(-1.0, 1 - 2 * (x * x + y * y)))))

    @property
    def roll_deg(self) -> float:
        """The sensor's roll in the body (°, about the body's x)."""
        return math.degrees(ypr_from_quat(self.rotation)[2])

    @property
    def pitch_deg(self) -> float:
        """The sensor's pitch in the body (°, about the body's y)."""
        return math.degrees(ypr_from_quat(self.rotation)[1])

    def summary(self) -> str:
        """One line for the operator."""
        b = self.gyro_bias
        return (f"IMU tilted {self.tilt_deg:.2f}° in the body (roll {self.roll_deg:+.2f}°, "
                f"pitch {self.pitch_deg:+.2f}°; yaw not observable from a level pose, kept 0), "
                f"gyro bias ({b[0]:+.4f}, {b[1]:+.4f}, {b[2]:+.4f}) rad/s, |a| − g = {self.gravity_residual:+.3f} "
                f"m/s², {self.samples} samples over {self.duration_s:.2f} s")

    def apply(self, imu: Imu) -> Imu:
        """`apply_mounting` with this rotation and bias: a sensor-frame `felis.hal.Imu` in the body frame."""
        return apply_mounting(imu, self.rotation, self.gyro_bias)

    def to_dict(self) -> dict:
        """Plain numbers (TOML/JSON ready): rotation, gyro_bias, and the estimate's record."""
        return {"rotation": [float(v) for v in self.rotation], "gyro_bias": [float(v) for v in self.gyro_bias],
                "tilt_deg": round(self.tilt_deg, 4), "samples": int(self.samples),
                "duration_s": float(self.duration_s), "gravity_residual": float(self.gravity_residual),
                "yaw_observable": False}

    @classmethod
    def from_dict(cls, data: Mapping, where: str = "imu") -> ImuMounting:
        """Inverse of `to_dict`. ``rotation`` (unit quaternion within 1e-3, renormalised) and ``gyro_bias``
        (3 finite rad/s) are required; the record is optional; ``tilt_deg`` is derived (recomputed from the
        rotation). Unknown keys and bad values raise `CalibrationError` naming ``where.key``."""
        if not isinstance(data, Mapping):
            raise CalibrationError(f"{where}: expected a table with rotation and gyro_bias, got {type(data).__name__}")
        unknown = sorted(set(data) - set(_KEYS))
        if unknown:
            raise CalibrationError(f"{where}: unknown key {unknown[0]!r}; keys: {', '.join(_KEYS)}")
        for key in ("rotation", "gyro_bias"):
            if key not in data:
                raise CalibrationError(f"{where}: missing {key!r}")
        if data.get("yaw_observable", False) is not False:
            raise CalibrationError(f"{where}.yaw_observable: must be false (the mount's yaw is not estimated)")
        return cls(rotation=_rotation(f"{where}.rotation", data["rotation"]),
                   gyro_bias=_vector(f"{where}.gyro_bias", data["gyro_bias"], 3),
                   samples=int(_number(f"{where}.samples", data.get("samples", 0), integer=True, minimum=0)),
                   duration_s=float(_number(f"{where}.duration_s", data.get("duration_s", 0.0), minimum=0)),
                   gravity_residual=float(_number(f"{where}.gravity_residual", data.get("gravity_residual", 0.0))))


def mounting_from_gravity(accel: np.ndarray) -> np.ndarray:
    """q_bs (yaw 0) that makes the mean sensor-frame specific force ``accel`` of a level body point up."""
    u = np.asarray(accel, dtype=float)
    u = u / np.linalg.norm(u)
    roll = math.atan2(u[1], u[2])
    pitch = math.atan2(-u[0], math.hypot(u[1], u[2]))
    return quat_from_ypr(0.0, pitch, roll)


def estimate_mounting(reader: ImuReader, seconds: float = 2.0, *, min_samples: int = 50, still_rad_s: float = 0.05,
                      still_accel: float = 0.3, g_tol: float = 0.1, max_bias: float = 0.2, level_tol: float = 30.0,
                      first_frame_s: float = 1.0) -> ImuMounting:
    """The IMU's mounting tilt and gyro bias from ``seconds`` of frames of a still robot on a level surface.

    Uses only frames received after the call. Limits: at least ``min_samples`` frames; RMS spread of the
    per-sample rates about the bias ≤ ``still_rad_s`` (rad/s; the RVC angles' 0.01° steps alone give
    ≈ 0.02) and of the accelerometer about its mean ≤ ``still_accel`` (m/s²); |ā| within ``g_tol`` × g
    of g; |bias| ≤ ``max_bias`` (rad/s; a larger steady rate is the robot turning); tilt ≤ ``level_tol``
    (degrees). A port that sends nothing for ``first_frame_s`` s fails early. Each failure is a
    `CalibrationError` with a one-line message (what was seen, what to do).
    """
    if not (math.isfinite(seconds) and seconds > 0):
        raise ParameterError(f"IMU calibration time must be positive seconds, got {seconds!r}")
    port, rate = reader.port, reader.rate_hz
    quats: list[np.ndarray] = []
    accels: list[np.ndarray] = []
    rates: list[np.ndarray] = []
    ticks = 0  # sample-clock periods from the first frame to the last
    t_start = time.monotonic()
    deadline, first_deadline = t_start + seconds, t_start + min(seconds, first_frame_s)
    seen = reader.frames
    prev, prev_t = None, 0.0
    while True:
        limit = deadline if prev is not None else first_deadline
        left = limit - time.monotonic()
        if left <= 0:
            break
        arrived = reader.wait(seen + 1, timeout=left)
        if reader.error is not None:
            raise CalibrationError(f"{reader.error}; IMU calibration stopped after {len(quats)} frames")
        if not arrived:
            if limit - time.monotonic() > 0.005:  # wait() gave up early: the reader has stopped
                raise CalibrationError(f"IMU port {port}: the reader stopped (closed?) during the calibration")
            continue
        seen = reader.frames
        f, t = reader.latest_frame(), time.monotonic()
        if prev is not None:
            n = frames_between(prev.index, f.index, t - prev_t, rate)
            if n == 0:  # the same sample again
                continue
            rates.append(body_rate(prev.quat, f.quat, n / rate))
            ticks += n
        quats.append(f.quat)
        accels.append(np.asarray(f.accel, dtype=float))
        prev, prev_t = f, t
    if not quats:
        raise CalibrationError(f"no IMU frames on {port} in {min(seconds, first_frame_s):g} s: check that the BNO08x "
                               "is powered, in UART-RVC mode (PS0 high, PS1 low) and its TX wired to the adapter's RX")
    if len(quats) < max(2, min_samples):
        raise CalibrationError(f"only {len(quats)} IMU frames on {port} in {seconds:g} s (need {max(2, min_samples)}): "
                               "frames lost (bad checksums, wrong baud rate?) or the calibration time is too short")
    duration = ticks / rate
    bias = quat_log(quat_mul(quat_conj(quats[0]), quats[-1])) / duration
    a = np.array(accels)
    a_mean = a.mean(axis=0)
    a_spread = float(np.sqrt(np.mean(np.sum((a - a_mean) ** 2, axis=1))))
    w_spread = float(np.sqrt(np.mean(np.sum((np.array(rates) - bias) ** 2, axis=1))))
    if w_spread > still_rad_s or a_spread > still_accel:
        raise CalibrationError(f"the robot moved during the IMU calibration (rate spread {w_spread:.3f} rad/s, limit "
                               f"{still_rad_s:g}; accel spread {a_spread:.3f} m/s², limit {still_accel:g}): keep it "
                               "still on a level surface, torque off or holding, and retry")
    norm = float(np.linalg.norm(a_mean))
    if abs(norm - G) > g_tol * G:
        raise CalibrationError(f"the IMU reads {norm:.2f} m/s² at rest, expected g = {G:.2f} ± {g_tol * G:.2f}: the "
                               "robot is not resting on a surface (falling, held and bouncing) or the sensor is faulty")
    w_bias = float(np.linalg.norm(bias))
    if w_bias > max_bias:
        raise CalibrationError(f"the IMU turned steadily at {w_bias:.3f} rad/s (limit {max_bias:g}) during the "
                               "calibration: the robot was turning; keep it still and retry")
    mounting = ImuMounting(rotation=mounting_from_gravity(a_mean), gyro_bias=bias, samples=len(quats),
                           duration_s=duration, gravity_residual=norm - G)
    if mounting.tilt_deg > level_tol:
        raise CalibrationError(f"the IMU is tilted {mounting.tilt_deg:.1f}° from the body's vertical (limit "
                               f"{level_tol:g}°): not on a level surface or the IMU is mounted on its side")
    return mounting
