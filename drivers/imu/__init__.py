"""BNO08x IMU in UART-RVC mode: frame codec, incremental parser, serial reader, mounting and a pty emulator.

    frames.py     the 19-byte RVC frame: constants, codec, incremental parser, port diagnosis (the wire format)
    reader.py     ImuReader: the serial port read by a thread, body rates, mean accelerometer between reads
    mounting.py   apply_mounting (sensor frame -> body frame), SensorMount (body -> a mis-mounted sensor)
    emulator.py   RvcEmulator: a BNO08x on a pseudo-terminal

Quaternion and Euler helpers are `felis.rotations` (the RVC angles are its yaw, pitch, roll:
`felis.rotations.quat_from_ypr`, `felis.rotations.ypr_from_quat`).
"""

from felis.drivers.imu.emulator import RvcEmulator
from felis.drivers.imu.frames import (
    BAUD,
    DYNAMIXEL_HEADER,
    FRAME_LEN,
    HEADER,
    RATE_HZ,
    G,
    RvcFrame,
    RvcParser,
    checksum,
    decode_frame,
    encode_frame,
    frames_between,
    looks_like_dynamixel,
    looks_like_rvc,
)
from felis.drivers.imu.mounting import SensorMount, apply_mounting
from felis.drivers.imu.reader import ImuReader
from felis.errors import ImuProtocolError, ImuSilentError

__all__ = [
    "BAUD", "DYNAMIXEL_HEADER", "FRAME_LEN", "HEADER", "RATE_HZ", "G", "ImuProtocolError", "ImuReader",
    "ImuSilentError", "RvcEmulator", "RvcFrame", "RvcParser", "SensorMount", "apply_mounting", "checksum",
    "decode_frame", "encode_frame", "frames_between", "looks_like_dynamixel", "looks_like_rvc",
]
