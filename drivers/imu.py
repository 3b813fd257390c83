"""BNO08x IMU in UART-RVC mode: frame codec, incremental parser, serial reader and a pty emulator.

Wire format
-----------
In UART-RVC ("robot vacuum cleaner") mode the BNO08x sends, unprompted, at 115200 baud 8N1 and
100 Hz, one 19-byte frame per sample (BNO080 datasheet 1000-3927, §1.3.5.2 "UART-RVC protocol")::

    offset  0    1    2      3-4   5-6    7-8   9-10  11-12 13-14 15-17     18
            AA   AA   index  yaw   pitch  roll  ax    ay    az    reserved  csum

- ``index``: uint8 sample counter, +1 per sample, wraps 255 -> 0 (a gap means lost frames).
- ``yaw``, ``pitch``, ``roll``: int16 little-endian in 0.01° (8734 = 87.34°). The sensor reports
  yaw in ±180°, pitch in ±90°, roll in ±180°; the int16 field itself holds ±327.67°.
- ``ax``, ``ay``, ``az``: int16 little-endian in mg (milli-g, g = 9.80665 m/s²). The datasheet's
  example frame reads +977 mg on z for a sensor lying roughly level, so this is the accelerometer's
  specific force (gravity included), the same convention as a MuJoCo ``accelerometer`` sensor and
  `felis.hal.Imu.accel` (+9.81 m/s² on z when level and still).
- ``reserved``: 3 bytes, zero in the datasheet (later BNO08x firmware documents the first two as
  "motion intent" / "motion request"); they are decoded as raw bytes and never interpreted.
- ``csum``: sum of bytes 2..17 (index through reserved) mod 256. The datasheet's example
  ``AA AA DE 01 00 92 FF 25 08 8D FE EC FF D1 03 00 00 00 E7`` checks out (see the tests).

Euler convention
----------------
The datasheet says yaw is the rotation about Z, pitch about Y, roll about X, and that "to determine
the actual orientation of the module, the rotations should be applied in the order yaw, pitch then
roll". That is the intrinsic Z-Y'-X'' (Tait-Bryan, aerospace) sequence, which we rely on::

    R = Rz(yaw) · Ry(pitch) · Rx(roll)          q = qz(yaw) ⊗ qy(pitch) ⊗ qx(roll)

R maps IMU-frame vectors into the world (reference) frame, i.e. ``q`` is the orientation of the IMU
in the world in (w, x, y, z) order — MuJoCo's convention, `felis.hal.Imu.quat`, and the same formula
as `felis.sim.scenarios.euler_quat`. The datasheet gives no sign diagram in that section; we take
the right-hand rule about each axis (positive yaw turns x towards y). The reference frame is the
sensor's own: z up (it reads +1 g on z when level), yaw zero at power-up / reset ("rotation around
the Z-axis since reset"). With half angles (c = cos(·/2), s = sin(·/2)) of roll r, pitch p, yaw y::

    w = cr cp cy + sr sp sy        x = sr cp cy − cr sp sy
    y = cr sp cy + sr cp sy        z = cr cp sy − sr sp cy

and back::

    roll  = atan2(2(w x + y z), 1 − 2(x² + y²))
    pitch = asin(2(w y − z x))                       (clipped to [−1, 1])
    yaw   = atan2(2(w z + x y), 1 − 2(y² + z²))      (wrapped to [−π, π))

At pitch = ±90° (gimbal lock) only yaw ∓ roll is defined; we then report roll = 0 and
yaw = 2·atan2(z, w).

Body rates
----------
RVC mode has no gyro output. `ImuReader` estimates the body rate from two consecutive orientations:
with q_cur = q_prev ⊗ Δq, the increment Δq = q_prev⁻¹ ⊗ q_cur is expressed in the IMU frame, and

    ω = θ·n / Δt,   θ = 2·atan2(|Δq_xyz|, Δq_w) (Δq_w ≥ 0 chosen),  n = Δq_xyz / |Δq_xyz|

Δt is taken from the sensor's sample clock, (index difference) / rate_hz, not from receive times:
USB-serial adapters deliver bytes in bursts (an FTDI latency timer is 16 ms by default), so receive
times jitter by more than the 10 ms between samples. The 0.01° quantisation of the angles gives a
rate noise of roughly 0.01°·√2 / 10 ms ≈ 0.025 rad/s.

Accelerometer between control ticks
-----------------------------------
A control loop at the sensor's rate still sees two frames arrive between some ticks and none between
others (receive-time jitter, above). `ImuReader.read` therefore reports the mean accelerometer of
every frame received since the previous ``read()``, with the latest orientation and rate: a short
impact (a landing's lasts less than one 10 ms sample) is kept, since the mean preserves the velocity
change Σ a·Δt over the frames, where taking only the latest frame would drop it. `latest` peeks at
the latest frame alone.

Mounting
--------
The sensor sits in the robot's body at a rotation q_bs and its orientation drifts, so a still sensor
reports a constant rate (the bias). `apply_mounting` turns a sensor-frame reading into the body frame
and removes the bias (`DynamixelRobot` applies the calibration's values to every reading; they are
estimated by `felis.calib.imu.estimate_mounting`); `SensorMount` does the opposite for emulators.
"""

from __future__ import annotations

import errno
import math
import os
import struct
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import serial

from felis.errors import CommError, ImuProtocolError, ImuSilentError
from felis.hal import Imu

HEADER = b"\xaa\xaa"
FRAME_LEN = 19
G = 9.80665  # m/s² per g
BAUD = 115200
RATE_HZ = 100.0
_BODY = struct.Struct("<B6h3s")  # index, yaw, pitch, roll, ax, ay, az, reserved (bytes 2..17)
_INT16 = (-32768, 32767)


# --- quaternions -----------------------------------------------------------------------------------


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw])


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion)."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q)·v: a vector given in the rotated (IMU) frame, expressed in the reference (world) frame."""
    return quat_mul(quat_mul(q, np.array([0.0, *v])), quat_conj(q))[1:]


def quat_from_rvc(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of R = Rz(yaw)·Ry(pitch)·Rx(roll); angles in radians."""
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return np.array([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])


def _wrap_pi(a: float) -> float:
    """Angle wrapped to [−π, π)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def rvc_from_quat(q: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in radians of a (w, x, y, z) quaternion; inverse of `quat_from_rvc`.

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
    return _wrap_pi(yaw), pitch, _wrap_pi(roll)


def body_rate(q_prev: np.ndarray, q_cur: np.ndarray, dt: float) -> np.ndarray:
    """Mean body rate (rad/s, IMU frame) turning q_prev into q_cur over dt seconds.

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


def quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation vector (axis × angle, rad)."""
    v = np.asarray(rotvec, dtype=float)
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.array([1.0, *(v / 2)])
    return np.array([math.cos(angle / 2), *(v * (math.sin(angle / 2) / angle))])


def quat_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector (axis × angle, rad, angle ≤ π) of a unit quaternion; inverse of `quat_exp`."""
    q = np.asarray(q, dtype=float)
    if q[0] < 0:
        q = -q
    v = q[1:]
    sin_half = float(np.linalg.norm(v))
    if sin_half < 1e-12:
        return 2 * v
    return v * (2 * math.atan2(sin_half, q[0]) / sin_half)


def quat_matrix(q: np.ndarray) -> np.ndarray:
    """3×3 rotation matrix R(q) of a (w, x, y, z) quaternion (normalised first): R·v = `quat_rotate`(q, v)."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# --- mounting --------------------------------------------------------------------------------------


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


# --- frames ----------------------------------------------------------------------------------------


def checksum(body: bytes) -> int:
    """RVC checksum: sum of the bytes (frame bytes 2..17: index through reserved) mod 256."""
    return sum(body) & 0xFF


def _int16(name: str, value: float) -> int:
    if not math.isfinite(value):
        raise ValueError(f"RVC {name} must be finite, got {value}")
    n = round(value)
    if not _INT16[0] <= n <= _INT16[1]:
        raise ValueError(f"RVC {name} {value} does not fit an int16 field")
    return n


def encode_frame(index: int, yaw_deg: float, pitch_deg: float, roll_deg: float,
                 accel_mps2: np.ndarray | tuple[float, float, float], reserved: bytes = b"\0\0\0") -> bytes:
    """One 19-byte RVC frame.

    Angles are rounded to 0.01°, accelerations (m/s²) to 1 mg. Yaw is wrapped to [−180°, 180°) in
    centidegrees (the same angle, as the sensor reports it); any value that does not fit its int16
    field raises ValueError (nothing is clamped). ``index`` is taken mod 256.
    """
    if len(reserved) != 3:
        raise ValueError(f"RVC reserved field is 3 bytes, got {len(reserved)}")
    yaw = _int16("yaw (0.01°)", yaw_deg * 100)
    yaw = (yaw + 18000) % 36000 - 18000
    pitch = _int16("pitch (0.01°)", pitch_deg * 100)
    roll = _int16("roll (0.01°)", roll_deg * 100)
    a = [_int16(f"accel {axis} (mg)", float(v) / G * 1000) for axis, v in zip("xyz", accel_mps2, strict=True)]
    body = _BODY.pack(int(index) & 0xFF, yaw, pitch, roll, *a, bytes(reserved))
    return HEADER + body + bytes([checksum(body)])


@dataclass(frozen=True, eq=False)
class RvcFrame:
    """A decoded RVC frame, values exactly as on the wire (converted to SI, nothing clamped).

    index: sample counter (0..255); yaw, pitch, roll: rad (intrinsic Z-Y'-X'', see the module
    docstring); accel: specific force in the IMU frame, m/s², shape (3,); reserved: the 3 raw
    reserved bytes; raw: the 19 frame bytes.
    """

    index: int
    yaw: float
    pitch: float
    roll: float
    accel: np.ndarray
    reserved: bytes = b"\0\0\0"
    raw: bytes = field(default=b"", repr=False)

    @property
    def quat(self) -> np.ndarray:
        """Orientation of the IMU in the sensor's reference frame, (w, x, y, z)."""
        return quat_from_rvc(self.yaw, self.pitch, self.roll)


def decode_frame(frame: bytes) -> RvcFrame:
    """Decode exactly one 19-byte frame; ValueError on a wrong length, header or checksum."""
    frame = bytes(frame)
    if len(frame) != FRAME_LEN or frame[:2] != HEADER:
        raise ValueError(f"not an RVC frame: {frame.hex(' ')}")
    if checksum(frame[2:18]) != frame[18]:
        raise ValueError(f"RVC checksum mismatch: computed {checksum(frame[2:18]):#04x}, got {frame[18]:#04x}")
    index, yaw, pitch, roll, ax, ay, az, reserved = _BODY.unpack(frame[2:18])
    rad = math.pi / 18000  # 0.01° in rad
    accel = np.array([ax, ay, az], dtype=float) * (G / 1000)
    accel.flags.writeable = False
    return RvcFrame(index, yaw * rad, pitch * rad, roll * rad, accel, reserved, frame)


class RvcParser:
    """Incremental RVC stream parser: bytes in, whole frames out; never raises on any input.

    Search for ``AA AA``; once 19 bytes from it are buffered, check the checksum. A match yields a
    frame and consumes all 19 bytes (so ``AA AA`` inside a payload is never looked at while in
    sync). A mismatch — a corrupted frame or a false header found in garbage or mid-frame — counts
    in ``bad_checksums`` and drops only the first byte, so a real header starting one byte later
    (``AA AA AA …``) is still found. Every byte not returned inside a frame counts in
    ``dropped_bytes``. At most 18 bytes are held between calls.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.frames = 0
        self.bad_checksums = 0
        self.dropped_bytes = 0

    def feed(self, data: bytes) -> list[RvcFrame]:
        """Add received bytes; return the frames completed by them, in order."""
        buf = self._buf
        buf += data
        out: list[RvcFrame] = []
        while True:
            start = buf.find(HEADER)
            if start < 0:
                keep = 1 if buf[-1:] == HEADER[:1] else 0  # a lone trailing AA may start a header
                self._drop(len(buf) - keep)
                return out
            self._drop(start)
            if len(buf) < FRAME_LEN:
                return out
            if checksum(buf[2:18]) != buf[18]:
                self.bad_checksums += 1
                self._drop(1)
                continue
            out.append(decode_frame(bytes(buf[:FRAME_LEN])))
            del buf[:FRAME_LEN]
            self.frames += 1

    def _drop(self, n: int) -> None:
        if n > 0:
            del self._buf[:n]
            self.dropped_bytes += n


# --- reader ----------------------------------------------------------------------------------------


def _open_error(port: str, e: Exception) -> CommError:
    code = getattr(e, "errno", None)
    if code == errno.ENOENT:
        why = "no such device (is the IMU adapter plugged in?)"
    elif code == errno.EACCES:
        why = "permission denied (add your user to the 'dialout' group)"
    elif code == errno.EBUSY:
        why = "device busy (another program has it open)"
    elif "ioctl" in str(e) or code == errno.ENOTTY:
        why = "not a serial device"
    else:
        why = "cannot open"
    detail = " ".join(str(e).split())
    return CommError(f"IMU port {port}: {why} ({detail})")




DYNAMIXEL_HEADER = b"\xff\xff\xfd\x00"


def looks_like_rvc(data: bytes) -> bool:
    """Whether a sample of received bytes holds UART-RVC frames (two or more with valid checksums):
    the diagnosis of an IMU's port given where a Dynamixel bus was expected."""
    parser = RvcParser()
    parser.feed(bytes(data))
    return parser.frames >= 2


def looks_like_dynamixel(data: bytes) -> bool:
    """Whether a sample of received bytes holds Dynamixel Protocol 2.0 packets (their FF FF FD 00 header)."""
    return DYNAMIXEL_HEADER in bytes(data)


def frames_between(prev_index: int, index: int, dt_rx: float, rate_hz: float) -> int:
    """Samples elapsed between two frames: the index difference mod 256, plus 256 per wrap that
    the receive-time difference ``dt_rx`` (s) shows (a silence longer than ~1.28 s at 100 Hz).
    0 means a repeated frame."""
    d = (index - prev_index) % 256
    return d + 256 * max(0, round((dt_rx * rate_hz - d) / 256))


class ImuReader:
    """Reads a BNO08x in UART-RVC mode on a serial port in a background thread.

    Keeps the latest frame, its receive time (``time.monotonic``), a body-rate estimate from the
    last two frames and the accelerometer's sum since the previous `read` (see the module docstring).
    Counters: ``frames``, ``bad_checksums``, ``dropped_bytes``, ``lost_frames`` (index gaps),
    ``bytes_received``. If the port fails while running (or anything in the thread raises), the thread
    stops, ``error`` holds a one-line message, ``latest()`` keeps returning the last reading and
    ``stale()`` is true. `wait_first` tells a silent port from one that speaks another protocol.

    ``rate_hz`` is the sensor's sample rate (100 Hz in RVC mode), used as the Δt of the body rate.
    Raises `CommError` naming the port if it cannot be opened.
    """

    def __init__(self, port: str, baud: int = BAUD, *, rate_hz: float = RATE_HZ):
        self.port = port
        self.rate_hz = rate_hz
        self.error: str | None = None
        self.lost_frames = 0
        self._parser = RvcParser()
        self._lock = threading.Condition()
        self._frame: RvcFrame | None = None
        self._t_rx = -math.inf
        self._gyro: np.ndarray | None = None
        self._accel_sum, self._accel_n = np.zeros(3), 0  # frames since the previous read()
        self.bytes_received = 0
        self._sample = bytearray()  # the first bytes received (diagnosis of a port that is not an IMU)
        self._stop = threading.Event()
        try:
            self._ser = serial.Serial(port, baud, timeout=0.05)
        except (serial.SerialException, OSError, ValueError) as e:
            raise _open_error(port, e) from None
        self._thread = threading.Thread(target=self._run, name=f"imu-reader {port}", daemon=True)
        self._thread.start()

    # counters -------------------------------------------------------------------------------------
    @property
    def frames(self) -> int:
        return self._parser.frames

    @property
    def bad_checksums(self) -> int:
        return self._parser.bad_checksums

    @property
    def dropped_bytes(self) -> int:
        return self._parser.dropped_bytes

    # thread ---------------------------------------------------------------------------------------
    def _run(self) -> None:
        ser = self._ser
        while not self._stop.is_set():
            try:
                data = ser.read(ser.in_waiting or 1)
                if data:
                    self.bytes_received += len(data)
                    if len(self._sample) < 512:
                        self._sample += data[: 512 - len(self._sample)]
                    self._receive(data, time.monotonic())
            except Exception as e:  # noqa: BLE001 - the thread never dies silently: kept for stale()/check()
                if not self._stop.is_set():
                    kind = "lost" if isinstance(e, serial.SerialException | OSError) else type(e).__name__
                    self.error = f"IMU port {self.port}: {kind} ({' '.join(str(e).split())})"
                with self._lock:
                    self._lock.notify_all()
                return

    def _receive(self, data: bytes, t: float) -> None:
        frames = self._parser.feed(data)
        if not frames:
            return
        with self._lock:
            for f in frames:
                prev = self._frame
                n = 1
                if prev is not None:
                    n = frames_between(prev.index, f.index, t - self._t_rx, self.rate_hz)
                    if n > 0:  # n == 0: a repeated frame carries no new rate information
                        self._gyro = body_rate(prev.quat, f.quat, n / self.rate_hz)
                        self.lost_frames += n - 1
                if n > 0:
                    self._accel_sum += f.accel
                    self._accel_n += 1
                self._frame, self._t_rx = f, t
            self._lock.notify_all()

    # readings -------------------------------------------------------------------------------------
    def latest(self) -> Imu | None:
        """The latest reading (quat, gyro estimate, accel), or None until two frames gave a rate."""
        with self._lock:
            f, gyro = self._frame, self._gyro
        if f is None or gyro is None:
            return None
        return Imu(quat=f.quat, gyro=gyro.copy(), accel=f.accel.copy())

    def read(self) -> Imu | None:
        """The reading for one control tick: the latest orientation and rate, and the mean accelerometer
        of the frames received since the previous ``read()`` (the latest frame's when none arrived; see
        the module docstring). None until two frames gave a rate."""
        with self._lock:
            f, gyro = self._frame, self._gyro
            if f is None or gyro is None:
                return None
            accel = self._accel_sum / self._accel_n if self._accel_n else f.accel.copy()
            self._accel_sum, self._accel_n = np.zeros(3), 0
        return Imu(quat=f.quat, gyro=gyro.copy(), accel=accel)

    def latest_frame(self) -> RvcFrame | None:
        """The latest decoded frame, or None before the first."""
        with self._lock:
            return self._frame

    def age(self) -> float:
        """Seconds since the latest frame was received (inf before the first)."""
        return time.monotonic() - self._t_rx

    def stale(self, max_age: float = 0.05) -> bool:
        """True when the latest frame is older than ``max_age`` s, or the reader has stopped."""
        return self.error is not None or not self._thread.is_alive() or self.age() > max_age

    def wait(self, frames: int = 1, timeout: float = 1.0) -> bool:
        """Block until ``frames`` frames have been received in all (or the reader stopped, or
        ``timeout`` s passed); True if they were."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while self.frames < frames and self.error is None and self._thread.is_alive():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._lock.wait(left)
            return self.frames >= frames

    def wait_first(self, timeout_s: float = 0.5) -> None:
        """Block until the first reading (two frames: orientation and a rate) has arrived.

        Raises `ImuSilentError` when the port delivered nothing in ``timeout_s`` (unpowered, not in RVC
        mode, another baud rate, or the bus's port, which is silent until asked), `ImuProtocolError` when
        bytes arrived but no RVC frame (a Dynamixel bus is named as such), `CommError` when the port failed.
        """
        if self.wait(2, timeout_s):
            return
        if self.error is not None:
            raise CommError(self.error)
        if self.bytes_received == 0:
            raise ImuSilentError(f"IMU on {self.port} sent nothing in {timeout_s:g} s: is it powered and in UART-RVC "
                                 "mode (P0 high) at 115200 bps? (or are --port and --imu-port swapped?)")
        sample = bytes(self._sample)
        what = ("Dynamixel packets: this is the servo bus; are --port and --imu-port swapped?"
                if looks_like_dynamixel(sample) else "no 0xAA 0xAA header with a valid checksum")
        raise ImuProtocolError(f"{self.port} answers, but not with BNO08x UART-RVC frames ({self.bytes_received} "
                               f"bytes, {what})")

    def close(self) -> None:
        """Stop the thread and close the port (idempotent)."""
        self._stop.set()
        try:
            self._ser.cancel_read()
        except Exception:  # port already gone: the thread is stopping anyway
            pass
        self._thread.join(timeout=2.0)
        self._ser.close()

    def __enter__(self) -> ImuReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --- emulator --------------------------------------------------------------------------------------


class RvcEmulator:
    """A BNO08x in UART-RVC mode on a pseudo-terminal: any serial client can open ``.port``.

    Every 1/rate_hz s the thread calls ``source() -> (quat wxyz, accel m/s² in the IMU frame)``,
    encodes a frame (index +1 per sample) and writes it to the pty master. Faults, drawn from a
    seeded RNG: ``drop_rate`` — probability a sample is not sent (its index is still used, so the
    reader sees a gap); ``corrupt_rate`` — probability one byte of a frame is XOR-ed with a random
    non-zero mask. Writes are non-blocking: when nobody reads and the pty buffer is full, frames are
    dropped (``overflows``) instead of blocking. An exception from ``source`` or the encoder stops
    the thread and is kept in ``error``.

    The slave fd stays open in the emulator (raw mode), so clients may open and close the port
    freely. ``stop()`` closes the pty: to a client the port vanishes, as when a USB adapter is
    unplugged.
    """

    def __init__(self, source: Callable[[], tuple[np.ndarray, np.ndarray]], rate_hz: float = RATE_HZ, *,
                 corrupt_rate: float = 0.0, drop_rate: float = 0.0, seed: int = 0):
        self.source = source
        self.rate_hz = rate_hz
        self.corrupt_rate = corrupt_rate
        self.drop_rate = drop_rate
        self._rng = np.random.default_rng(seed)
        self.sent = self.dropped = self.corrupted = self.overflows = 0
        self.error: Exception | None = None
        self._index = 0
        self._pending = b""
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False

    def start(self) -> RvcEmulator:
        if self._closed:
            raise RuntimeError("RvcEmulator: stopped emulators cannot be restarted")
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"rvc-emulator {self.port}", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the pty (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if not self._closed:
            self._closed = True
            os.close(self._master)
            os.close(self._slave)

    def __enter__(self) -> RvcEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def frame(self) -> bytes | None:
        """Sample the source once and return the frame to send (None when dropped); index +1."""
        quat, accel = self.source()
        yaw, pitch, roll = rvc_from_quat(quat)
        data = encode_frame(self._index, math.degrees(yaw), math.degrees(pitch), math.degrees(roll), accel)
        self._index = (self._index + 1) & 0xFF
        if self.drop_rate and self._rng.random() < self.drop_rate:
            self.dropped += 1
            return None
        if self.corrupt_rate and self._rng.random() < self.corrupt_rate:
            b = bytearray(data)
            b[int(self._rng.integers(len(b)))] ^= int(self._rng.integers(1, 256))
            data = bytes(b)
            self.corrupted += 1
        return data

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                data = self.frame()
                if data is not None:
                    self._write(data)
                next_t += period
                now = time.monotonic()
                if now - next_t > 5 * period:  # fell far behind (paused process): resume, no burst
                    next_t = now
                self._stop.wait(max(0.0, next_t - now))
        except Exception as e:  # keep it for the test / operator; the port simply goes quiet
            self.error = e

    def _write(self, data: bytes) -> None:
        """Write a frame without blocking; finish a partly written one first, else drop the new one."""
        if self._pending:
            self._pending = self._pending[self._try_write(self._pending):]
            if self._pending:
                self.overflows += 1
                return
        n = self._try_write(data)
        if n == 0:
            self.overflows += 1
        else:
            self.sent += 1
            self._pending = data[n:]

    def _try_write(self, data: bytes) -> int:
        try:
            return os.write(self._master, data)
        except BlockingIOError:
            return 0
