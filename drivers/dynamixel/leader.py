"""`LeaderArm`: a torque-off Dynamixel chain read as joint positions, the input of teleoperation.

A leader arm is a chain of servos that an operator's hand moves (`felis teleop`). It is a `DynamixelRobot` that
is connected and never armed: connecting checks every servo answers with the model its description names (a
missing servo is one line naming it), installs the one-sync-read-per-tick map, and then Torque Enable is written
0 and read back, so the hand can move every joint. Each ``read()`` is one sync read; positions come through the
description's direction, zero and transmission and the calibration (`felis.drivers.dynamixel.robot`), so they are
in the follower's joint units.

Losing it: a read in which some servo did not answer (stale) or no servo did is a failure. Up to ``tolerance``
failures in a row raise a plain `CommError` (the control loop holds the follower's last command); one more, or
a port that vanished, raises a *fatal* `CommError` whose text starts ``leader arm lost``: the loop then stops
and disarms the follower at once (torque off, read back). So a leader that vanishes holds the follower for
``tolerance`` ticks, then stops it. A tick's read is not retried within the tick (``retries=0``: the next tick
is the retry), so a silent leader costs each tick one reply timeout, not several, and the follower's goals keep
coming well inside its servos' Bus Watchdog time.
"""

from __future__ import annotations

import numpy as np

from felis.drivers.dynamixel.controltable import address
from felis.drivers.dynamixel.robot import Calibration, DynamixelRobot
from felis.errors import CommError
from felis.spec import RobotSpec

_TORQUE_ENABLE = address("torque_enable")
TOLERANCE = 3  # failed reads in a row held through; one more stops (the loop watchdog's default)


class LeaderArm:
    """The leader on ``port`` (module doc). Use as a context manager, or ``open()`` / ``close()``."""

    def __init__(self, spec: RobotSpec, port: str, baud: int = 1_000_000, *, calibration: Calibration | None = None,
                 tolerance: int = TOLERANCE, retries: int = 0):
        if tolerance < 0:
            raise ValueError(f"tolerance must be ≥ 0, got {tolerance}")
        self.spec = spec
        self.port = port
        self.tolerance = int(tolerance)
        self.robot = DynamixelRobot(spec, port, baud, calibration=calibration, retries=retries, bus_watchdog_s=None)
        self.failures = 0  # in a row
        self.failed = 0  # in all
        self.reads = 0
        self.q: np.ndarray | None = None  # the last good reading

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> LeaderArm:
        """Connect, then torque off on every servo and read it back (CommError naming the leader otherwise)."""
        try:
            self.robot.connect()
            self._torque_off()
        except BaseException as e:
            self.close()
            if isinstance(e, CommError):
                raise CommError(f"leader arm {self.spec.name!r} on {self.port}: {e}") from None
            raise
        return self

    def _torque_off(self) -> None:
        bus, ids = self.robot.bus, self.robot.ids
        bus.sync_write(_TORQUE_ENABLE, 1, {i: b"\x00" for i in ids})
        res = bus.sync_read(ids, _TORQUE_ENABLE, 1, fast=False, retries=2)
        on = [f"{j.name} (ID {j.servo_id})" for j in self.spec.joints
              if res.data[j.servo_id] is None or res.data[j.servo_id][0] != 0]
        if on:
            raise CommError(f"torque could not be switched off (read back) on {', '.join(on)}: a leader moves by hand")

    def close(self) -> None:
        """Release the port (torque is written off once more on the way, where the port still works)."""
        self.robot.close()

    def __enter__(self) -> LeaderArm:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ reading
    def read(self) -> np.ndarray:
        """The leader's joint positions (its description's order, rad or m); raises as the module doc says."""
        self.reads += 1
        try:
            state = self.robot.read()
            stale = state.faults.stale
            if stale is not None and stale.any():
                names = [f"{j.name} (ID {j.servo_id})" for j, s in zip(self.spec.joints, stale, strict=True) if s]
                raise CommError(f"no reply from {', '.join(names)}")
        except CommError as e:
            self.failures += 1
            self.failed += 1
            if e.fatal or self.failures > self.tolerance:
                why = "its port vanished" if e.fatal else f"{self.failures} reads in a row failed"
                lost = CommError(f"leader arm lost on {self.port}: {why} (last: {e}); the follower held its last "
                                 "command, then stopped")
                lost.fatal = True
                raise lost from None
            raise CommError(f"leader arm: {e} (holding, {self.failures} of {self.tolerance} tolerated)") from None
        self.failures = 0
        self.q = state.q
        return state.q
