"""Teaching by hand: torque off (read back), the operator poses the robot, its calibrated joint positions are read.

`capture` works on a connected `felis.drivers.dynamixel.robot.DynamixelRobot` (never armed here), so the reading
goes through the same conversion as every control tick, calibration included::

    q = (a − b) / k,   a = (Present Position − 2048) · 2π/4096   (`DynamixelRobot`'s module doc)

and the pose is exact to the encoder: played back, each servo's goal is the tick it read (`DynamixelRobot.q_to_ticks`
inverts the conversion). Torque goes off first on every servo of the description and is read back; a servo that
still holds torque, or does not answer, stops the capture before the operator is asked to move anything. Torque is
left off afterwards; the robot's ``close()`` turns it off again and reads it back on every way out.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from felis.calib.operator import Operator
from felis.drivers.dynamixel.controltable import address
from felis.errors import CommError

_TORQUE_ENABLE = address("torque_enable")


@dataclass
class Captured:
    """What a capture read: the joint positions (description order, rad/m) and the present ticks behind them."""

    q: np.ndarray
    ticks: dict[str, int]


def torque_off(bus, ids: list[int], names: list[str]) -> None:
    """Torque off on ``ids`` and read it back (a lost write is sent again once); `CommError` naming the joints
    whose torque is still on or unknown."""
    wrong: list[int] = []
    silent: list[int] = []
    for _ in range(2):
        bus.torque(ids, False)
        back = bus.sync_read(ids, _TORQUE_ENABLE, 1, fast=False, retries=3)
        wrong = [i for i in ids if back.data[i] is not None and back.data[i][0] != 0]
        silent = [i for i in ids if back.data[i] is None]
        if not wrong and not silent:
            return
    who = dict(zip(ids, names, strict=True))
    parts = []
    if wrong:
        parts.append(f"torque is still ON on {', '.join(f'{who[i]} (ID {i})' for i in wrong)}")
    if silent:
        parts.append(f"no reply from {', '.join(f'{who[i]} (ID {i})' for i in silent)}: torque state unknown")
    raise CommError("; ".join(parts) + "; nothing was captured (check with `felis torque off`)")


def capture(robot, operator: Operator, name: str, *, after_s: float | None = None) -> Captured:
    """Torque off (read back), let the operator pose the robot (``operator.wait``, or ``after_s`` seconds), then
    read its calibrated joint positions. ``robot``: a connected `DynamixelRobot`."""
    spec = robot.spec
    torque_off(robot.bus, list(robot.ids), list(spec.names))
    instruction = f"Torque is off: pose the {spec.name} by hand for {name!r} and hold it still"
    if after_s is not None:
        operator.say(f"{instruction}; reading in {after_s:g} s")
        time.sleep(after_s)
    else:
        operator.wait(instruction)
    state = robot.read()
    stale = state.faults.stale if state.faults is not None else None
    if stale is not None and stale.any():
        lost = ", ".join(spec.names[i] for i in np.flatnonzero(stale))
        raise CommError(f"no valid reply from {lost} while reading the pose; nothing was captured, try again")
    ticks = {j.name: int(t) for j, t in zip(spec.joints, robot.q_to_ticks(state.q), strict=True)}
    return Captured(q=np.asarray(state.q, float).copy(), ticks=ticks)


__all__ = ["Captured", "capture", "torque_off"]
