"""`ImuReader`: a BNO08x in UART-RVC mode on a serial port, read by a thread.

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
"""

from __future__ import annotations

import errno
import math
import threading
import time

import numpy as np
import serial

from felis.drivers.imu.frames import BAUD, RATE_HZ, RvcFrame, RvcParser, frames_between, looks_like_dynamixel
from felis.errors import CommError, ImuProtocolError, ImuSilentError
from felis.hal import Imu
from felis.rotations import body_rate


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
