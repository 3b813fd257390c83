"""BNO08x UART-RVC frames: the codec (`encode_frame`, `decode_frame`), the incremental parser (`RvcParser`), and
what a sample of bytes looks like (`looks_like_rvc`, `looks_like_dynamixel`, `frames_between`).

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
as `felis.rotations.euler_quat`. The datasheet gives no sign diagram in that section; we take
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
yaw = 2·atan2(z, w). The conversions are `felis.rotations.quat_from_ypr` and `felis.rotations.ypr_from_quat`.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np

from felis.drivers.framing import skip_to_header
from felis.rotations import quat_from_ypr

HEADER = b"\xaa\xaa"
FRAME_LEN = 19
G = 9.80665  # m/s² per g
BAUD = 115200
RATE_HZ = 100.0
_BODY = struct.Struct("<B6h3s")  # index, yaw, pitch, roll, ax, ay, az, reserved (bytes 2..17)
_INT16 = (-32768, 32767)


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
        return quat_from_ypr(self.yaw, self.pitch, self.roll)


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
            skipped, found = skip_to_header(buf, HEADER)  # a lone trailing AA may start a header: kept
            self.dropped_bytes += skipped
            if not found:
                return out
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

