"""What drives the servos' horns from outside: the `HornBackend` protocol.

A virtual bus's servos either run their own standalone dynamics or have their horns driven by a
backend: a physics simulation that reads the servos' goals and writes back where the horns are
(servo-in-the-loop). The drivers define the seam and never import a simulation; `felis.sim.servo_in_loop`
implements it on MuJoCo and hands it to `felis.drivers.virtual.server.VirtualBus.for_robot` as a factory.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from felis.drivers.virtual.server import VirtualBus


class HornBackend(Protocol):
    """Drives the horns of a `VirtualBus`'s servos (``bus.servos``, ``bus.spec``).

    Built by a `BackendFactory` once the servos are on the bus. It marks the servos it drives
    ``external`` and, with ``bus.lock`` held, reads their goals (`VirtualServo.goal_angle`,
    ``torque_enabled``, `VirtualServo.profile_speed`), publishes their horns (`VirtualServo.set_present`) and
    calls ``bus.housekeeping()`` on its own clock. ``imu_sample`` is None when there is no IMU to emulate, else
    it returns the body's IMU orientation (w, x, y, z) and specific force (m/s², body frame); the bus's
    `felis.drivers.virtual.imu.VirtualImu` calls it from its own thread at the sensor's rate.
    """

    imu_sample: Callable[[], tuple[np.ndarray, np.ndarray]] | None

    def start(self) -> None:
        """Begin driving the horns (the bus's server thread is already running)."""

    def stop(self) -> None:
        """Stop and release everything (idempotent; also when never started)."""


BackendFactory = Callable[["VirtualBus"], HornBackend]
