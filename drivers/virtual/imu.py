"""The IMU of a virtual bus: a BNO08x in UART-RVC mode (`felis.drivers.imu.RvcEmulator`, 100 Hz) on its own
pseudo-terminal, reporting what a `HornBackend` says the body does, as a real sensor would.

Each sample takes the body's orientation q_wb and specific force accel_b from the backend, passes them
through the sensor's mounting (`felis.drivers.imu.SensorMount`: q_ws = q_wb ⊗ q_bs ⊗ exp(ω_d·t),
accel_s = R(q_bs)ᵀ·accel_b, t on the sample clock) and saturates each accelerometer axis at ±8 g
(``ACCEL_RANGE_G``, the BNO08x accelerometer's full scale). `check_imu_mount` is the one validator of a
mount and drift given by an operator or a test.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from felis.drivers.imu import G, RvcEmulator, SensorMount
from felis.errors import ParameterError

ACCEL_RANGE_G = 8.0  # the IMU's accelerometer saturates here (per axis)


class VirtualImu:
    """An emulated BNO08x on ``.port`` fed by ``source() -> (q_wb, accel_b)`` through ``mount`` (module doc).

    ``emulator`` is the `RvcEmulator` (its ``error`` holds what stopped it)."""

    def __init__(self, source: Callable[[], tuple[np.ndarray, np.ndarray]], mount: SensorMount | None = None):
        self.source = source
        self.mount = mount or SensorMount()
        self.emulator = RvcEmulator(self.sample)
        self.port = self.emulator.port

    def sample(self) -> tuple[np.ndarray, np.ndarray]:
        """One sensor sample: the source's reading, mounted, drifting, saturated."""
        quat, accel = self.mount.sample(*self.source())
        limit = ACCEL_RANGE_G * G
        return quat, np.clip(accel, -limit, limit)

    def start(self) -> None:
        self.emulator.start()

    def stop(self) -> None:
        """Stop the thread and close the pty (idempotent)."""
        self.emulator.stop()


def check_imu_mount(rotation: Sequence[float] | None, drift: Sequence[float] | None) -> SensorMount | None:
    """The `SensorMount` of a mount (unit quaternion w, x, y, z) and drift (rad/s, 3-vector); None when both are
    None. ParameterError, one line, when either is malformed."""
    if rotation is None and drift is None:
        return None
    try:
        return SensorMount(rotation, drift)
    except ValueError as e:
        raise ParameterError(str(e)) from None
