"""Landing controller: a falling cat's policy (evolved nets, or a hand-written spine rule) through the HAL.

Each tick (seed 000 §6.2): the inputs IT (joint angles, the upper body's roll and pitch from the IMU,
the waist height; `felis.learning.landing.policy.normalise_inputs`) go to the policy, which returns joint
velocities v (rad/s). They are integrated into position targets, q* ← clip(q* + v·Δt, limits), with
Δt the time since the last tick; below `LANDING_HEIGHT_M` the spine targets are held straight (the
paper's landing rule). A non-finite velocity holds the last targets.

A policy is anything with ``velocities(it) -> (12,)`` (`SimpleBehaviour`, `ComplexBehaviour`) or a
callable ``(it, t) -> (12,)`` with t the time since the controller's reset (a hand-written rule).

Height: ``State.height`` where the backend knows it (simulation). On hardware the waist height is not
measured, so it is predicted from the drop: h(t) = h0 − ½ g (t − t0)² from the reset (the release) with
h0 = ``drop_height`` (m), floored at 0: free fall is exact until the first touch.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from felis.errors import ParameterError
from felis.hal import Command, State
from felis.learning.landing.policy import JOINTS, LANDING_HEIGHT_M, landing_rule, normalise_inputs
from felis.rotations import G
from felis.spec import RobotSpec


class LandingController:
    """Runs a landing policy (module doc).

    Args:
        policy: `SimpleBehaviour` / `ComplexBehaviour` (``velocities(it)``) or a callable (it, t) → (12,).
        drop_height: release height (m) for the free-fall height estimate where the state has none.
    """

    name = "landing"
    needs_imu = True  # the nets' inputs are the body's orientation: no IMU, no landing (the loop stops)

    def __init__(self, policy, drop_height: float | None = None):
        if drop_height is not None and not (np.isfinite(drop_height) and drop_height > 0):
            raise ParameterError(f"landing: drop height must be a positive number of metres, got {drop_height}")
        if callable(getattr(policy, "velocities", None)):
            self._policy: Callable = lambda it, t: policy.velocities(it)
        elif callable(policy):
            self._policy = policy
        else:
            raise ParameterError("landing: a policy needs velocities(it) or to be callable, got "
                                 f"{type(policy).__name__}")
        self.policy = policy
        self.drop_height = drop_height
        self.held = 0  # ticks whose velocities were not finite

    def reset(self, spec: RobotSpec, state: State) -> None:
        if tuple(spec.names) != JOINTS:
            raise ParameterError(f"landing: the policy drives the cat's joints, not {spec.name}'s")
        self.spec = spec
        self._q = np.clip(np.asarray(state.q, dtype=float), spec.lower, spec.upper)
        self._t0 = self._t = float(state.t)
        self._spine = np.array([spec.index("spine_pitch"), spec.index("spine_yaw")])

    def height(self, state: State) -> float:
        """Waist height (m): measured, else the free-fall prediction from the drop height."""
        if state.height is not None and np.isfinite(state.height):
            return float(state.height)
        if self.drop_height is None:
            raise ParameterError("landing: this robot reports no height: give the drop height (drop_height)")
        return max(0.0, self.drop_height - 0.5 * G * (state.t - self._t0) ** 2)

    def __call__(self, state: State) -> Command:
        dt = max(0.0, float(state.t) - self._t)
        self._t = float(state.t)
        h = self.height(state)
        if state.imu is not None and np.all(np.isfinite(state.q)):
            it = normalise_inputs(state.q, state.imu.quat, h)
            v = np.asarray(self._policy(it, self._t - self._t0), dtype=float)
            if v.shape == (len(JOINTS),) and np.all(np.isfinite(v)):
                self._q = np.clip(self._q + v * dt, self.spec.lower, self.spec.upper)
            else:
                self.held += 1
        else:
            self.held += 1
        if h < LANDING_HEIGHT_M:
            self._q[self._spine] = landing_rule(h, self._q[self._spine])
        return Command(q=self._q.copy())

    def summary(self) -> dict:
        return {"held_ticks": self.held}
