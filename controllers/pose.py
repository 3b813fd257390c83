"""Pose controller: hold, stand, sit, or go to any pose with time-based interpolation.

From the start pose ``q0`` (the commanded pose when the move begins, or the present position at
reset) to the target ``q1`` over ``T`` seconds with the minimum-jerk profile

    s = clip((t - t0) / T, 0, 1),   w(s) = 10 s³ − 15 s⁴ + 6 s⁵,   q(t) = q0 + w(s) · (q1 − q0)

which starts and ends at rest (zero velocity and acceleration). Named poses come from the robot's
description (``[poses.NAME]``), so the same controller object runs on the cat and the arm; a dict
pose names some joints and holds the others where they are.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from felis.errors import ParameterError
from felis.hal import Command, State
from felis.spec import RobotSpec

HOLD = "hold"


def min_jerk(s: float) -> float:
    """Minimum-jerk blend weight for normalised time s ∈ [0, 1]."""
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


class PoseController:
    """Moves to a pose and holds it.

    Args:
        pose: ``"hold"`` (the present pose), a pose name of the description (``"stand"``,
            ``"sit"``, …), or a mapping joint name → position (rad; m for prismatic).
        duration: seconds for the move (0 = jump, which the safety layer still rate-limits).
    """

    def __init__(self, pose: str | Mapping[str, float] = HOLD, duration: float = 1.0):
        if not (np.isfinite(duration) and duration >= 0):
            raise ParameterError(f"pose duration must be ≥ 0 s, got {duration}")
        self.pose = pose
        self.duration = float(duration)
        self.name = pose if isinstance(pose, str) else "pose"
        self.spec: RobotSpec | None = None
        self._q0 = self._q1 = None
        self._t0 = 0.0

    def target(self, spec: RobotSpec, present: np.ndarray, pose: str | Mapping[str, float]) -> np.ndarray:
        """Resolve ``pose`` to a full joint vector for ``spec``."""
        if isinstance(pose, str):
            if pose == HOLD:
                return present.copy()
            if pose not in spec.poses:
                raise ParameterError(f"robot {spec.name!r} has no pose {pose!r}; poses: "
                                     f"{', '.join([HOLD, *spec.poses])}")
            return spec.pose(pose)
        q = present.copy()
        for joint, value in pose.items():
            if joint not in spec.names:
                raise ParameterError(f"robot {spec.name!r} has no joint {joint!r}")
            if not np.isfinite(value):
                raise ParameterError(f"pose value for {joint!r} is not finite: {value}")
            q[spec.index(joint)] = float(value)
        return q

    def reset(self, spec: RobotSpec, state: State) -> None:
        self.spec = spec
        self._q0 = np.asarray(state.q, dtype=float).copy()
        self._q1 = self.target(spec, self._q0, self.pose)
        self._t0 = state.t

    def go_to(self, pose: str | Mapping[str, float], state: State, duration: float | None = None) -> None:
        """Start a new move from the pose commanded now toward ``pose``."""
        if self.spec is None:
            raise RuntimeError("PoseController.reset() must run before go_to()")
        current = self._command(state.t)
        self.pose = pose
        self.name = pose if isinstance(pose, str) else "pose"
        if duration is not None:
            self.duration = float(duration)
        self._q0 = current
        self._q1 = self.target(self.spec, current, pose)
        self._t0 = state.t

    def _command(self, t: float) -> np.ndarray:
        if self.duration <= 0:
            return self._q1.copy()
        return self._q0 + min_jerk((t - self._t0) / self.duration) * (self._q1 - self._q0)

    def __call__(self, state: State) -> Command:
        if self._q1 is None:
            raise RuntimeError("PoseController.reset() must run before the first tick")
        return Command(q=self._command(state.t))
