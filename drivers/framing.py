"""Byte streams cut into frames at a fixed header: the resynchronising step that the Dynamixel packet reader
(`felis.drivers.dynamixel.protocol.PacketReader`) and the IMU's RVC parser (`felis.drivers.imu.frames.RvcParser`)
share, so that garbage, a cut-off frame or a lost byte costs only the bytes before the next header.
"""

from __future__ import annotations


def skip_to_header(buf: bytearray, header: bytes) -> tuple[int, bool]:
    """Delete from ``buf`` the bytes before the first ``header``; without one, every byte but a trailing
    part that may be the start of a header (its first 1 … len − 1 bytes), kept for the next bytes to
    complete. Returns (bytes deleted, whether ``buf`` now starts with ``header``)."""
    i = buf.find(header)
    if i < 0:
        keep = next((k for k in range(len(header) - 1, 0, -1) if buf.endswith(header[:k])), 0)
        n = len(buf) - keep
        del buf[:n]
        return n, False
    del buf[:i]
    return i, True
