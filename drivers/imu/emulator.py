"""`RvcEmulator`: a BNO08x in UART-RVC mode on a pseudo-terminal, for tests and the virtual bus."""

from __future__ import annotations

import math
import os
import threading
import time
import tty
from collections.abc import Callable

import numpy as np

from felis.drivers.imu.frames import RATE_HZ, encode_frame
from felis.rotations import ypr_from_quat


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
        yaw, pitch, roll = ypr_from_quat(quat)
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
