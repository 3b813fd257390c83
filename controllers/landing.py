"""Landing controller: a falling cat's policy (evolved nets, or a hand-written spine rule) through the HAL.

Each tick (seed 000 §6.2): the inputs IT (joint angles, the upper body's roll and pitch from the IMU,
the waist height; `felis.learning.landing.policy.normalise_inputs`) go to the policy, which returns joint
velocities v (rad/s). They are integrated into position targets, q* ← clip(q* + v·Δt, limits), with
Δt the time since the last tick; below `LANDING_HEIGHT_M` the spine targets are held straight (the
paper's landing rule). A non-finite velocity holds the last targets.

Touchdown compliance (issue 21, item 5): with ``touchdown_stiffness`` s < 1, below the same height the legs'
Position P gain drops to s of the described (`felis.hal.Command.stiffness`; I, D and feedforward kept), so the
legs give at impact instead of folding a rigid link onto the floor; s = 1 (the default) changes nothing.

A policy is anything with ``velocities(it) -> (12,)`` (`SimpleBehaviour`, `ComplexBehaviour`) or a
callable ``(it, t) -> (12,)`` with t the time since the controller's reset (a hand-written rule).

Height: ``State.height`` where the backend knows it (simulation). On hardware the waist height is not
measured, so it is predicted from the drop: h(t) = h0 − ½ g (t − t0)² from the reset (the release) with
h0 = ``drop_height`` (m), floored at 0: free fall is exact until the first touch.

`LandingBatch` is the same controller for a batch of simulated cats (`felis.sim.batch.DropBatch`): one
numpy call per tick for every cat, each row driven by its own policy (``policies[index[row]]``), with the
height measured. `PerCat` runs any HAL controller once per cat (the baselines ``passive`` and ``stand``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from felis.errors import ParameterError
from felis.hal import MIN_STIFFNESS, Command, Imu, State
from felis.learning.landing.policy import (
    JOINTS,
    LANDING_HEIGHT_M,
    landing_rule,
    normalise_inputs,
    normalise_inputs_many,
)
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

    def __init__(self, policy, drop_height: float | None = None, touchdown_stiffness: float = 1.0):
        if drop_height is not None and not (np.isfinite(drop_height) and drop_height > 0):
            raise ParameterError(f"landing: drop height must be a positive number of metres, got {drop_height}")
        self.touchdown_stiffness = check_stiffness(touchdown_stiffness)
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
        self._soft = leg_stiffness(spec, self.touchdown_stiffness)

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
            if self._soft is not None:
                return Command(q=self._q.copy(), stiffness=self._soft)
        return Command(q=self._q.copy())

    def summary(self) -> dict:
        return {"held_ticks": self.held}


def check_stiffness(s: float) -> float:
    """A touchdown stiffness (fraction of the legs' P gain): within [MIN_STIFFNESS, 1], else one line."""
    if not (isinstance(s, int | float) and math.isfinite(s) and MIN_STIFFNESS <= s <= 1.0):
        raise ParameterError(f"landing: touchdown stiffness must be within {MIN_STIFFNESS:g}…1 (a fraction of the "
                             f"legs' P gain), got {s!r}")
    return float(s)


def leg_stiffness(spec: RobotSpec, s: float) -> np.ndarray | None:
    """Per-joint stiffness with the legs at ``s`` and the rest at 1; None when s = 1 (nothing to change)."""
    if s >= 1.0:
        return None
    out = np.ones(spec.n)
    out[spec.indices("legs")] = s
    return out


class LandingBatch:
    """`LandingController` for B simulated cats at once (module doc): ``policies[index[b]]`` drives cat b.

    A policy is a behaviour (``velocities_many(IT (G, 15)) -> (G, 12)``) or a callable ``(IT (G, 15), t (G,),
    rows (G,)) -> (G, 12)`` with t the time since the reset and rows the cats' indices in the batch (an
    open-loop motion per cat). The rows of each policy are evaluated together.
    """

    def __init__(self, spec: RobotSpec, policies, index=None, touchdown_stiffness: float = 1.0):
        if tuple(spec.names) != JOINTS:
            raise ParameterError(f"landing: the policy drives the cat's joints, not {spec.name}'s")
        self.spec = spec
        self._soft = leg_stiffness(spec, check_stiffness(touchdown_stiffness))
        self.stiffness: np.ndarray | None = None  # (B, n) after each tick when a row is compliant (DropBatch reads)
        self.policies = list(policies)
        self.index = None if index is None else np.asarray(index, dtype=int)
        self._spine = np.array([spec.index("spine_pitch"), spec.index("spine_yaw")])
        self.held = 0

    def reset(self, t: np.ndarray, q: np.ndarray) -> None:
        B = len(t)
        index = np.zeros(B, dtype=int) if self.index is None else self.index
        if index.shape != (B,) or (B and (index.min() < 0 or index.max() >= len(self.policies))):
            raise ParameterError(f"landing: {B} cats need {B} policy indices into {len(self.policies)} policies")
        from felis.learning.landing.policy import SimpleBehaviour, StackedSimple

        if len(self.policies) > 1 and all(isinstance(p, SimpleBehaviour) for p in self.policies):
            self._groups = [(StackedSimple(self.policies, index), np.arange(B))]  # a population: one stack
        else:
            self._groups = [(p, np.flatnonzero(index == i)) for i, p in enumerate(self.policies)]
        self._q = np.clip(np.asarray(q, dtype=float), self.spec.lower, self.spec.upper)
        self._t0 = np.array(t, dtype=float)
        self._t = np.array(t, dtype=float)

    def __call__(self, t: np.ndarray, q: np.ndarray, quat: np.ndarray, h: np.ndarray) -> np.ndarray:
        dt = np.maximum(0.0, t - self._t)
        self._t = np.array(t, dtype=float)
        it = normalise_inputs_many(q, quat, h)
        v = np.empty_like(self._q)
        since = self._t - self._t0
        for policy, rows in self._groups:
            if rows.size == 0:
                continue
            if callable(getattr(policy, "velocities_many", None)):
                v[rows] = policy.velocities_many(it[rows])
            else:
                v[rows] = policy(it[rows], since[rows], rows)
        ok = np.isfinite(v).all(axis=1)
        self.held += int(np.count_nonzero(~ok))
        self._q[ok] = np.clip(self._q[ok] + v[ok] * dt[ok, None], self.spec.lower, self.spec.upper)
        low = np.flatnonzero(np.asarray(h) < LANDING_HEIGHT_M)
        if low.size:
            self._q[np.ix_(low, self._spine)] = 0.0
        self.stiffness = None
        if low.size and self._soft is not None:
            self.stiffness = np.ones_like(self._q)
            self.stiffness[low] = self._soft
        return self._q.copy()


class PerCat:
    """Any HAL controller run once per cat of a batch (`felis.sim.batch.DropBatch`): ``make(b)`` gives a fresh
    one for cat b; each sees a `State` of the time, joint angles, IMU attitude and waist height."""

    def __init__(self, spec: RobotSpec, make: Callable[[int], object]):
        self.spec, self.make = spec, make
        self.stiffness: np.ndarray | None = None  # (B, n) when a cat's command softens joints (DropBatch reads)

    def _state(self, t, q, quat, h) -> State:
        z = np.zeros(3)
        return State(t=float(t), q=np.array(q), dq=np.zeros(len(q)), imu=Imu(quat=np.array(quat), gyro=z, accel=z),
                     height=float(h))

    def reset(self, t: np.ndarray, q: np.ndarray) -> None:
        self._cats = [self.make(b) for b in range(len(t))]
        quat = np.array([1.0, 0.0, 0.0, 0.0])
        for i, c in enumerate(self._cats):
            c.reset(self.spec, self._state(t[i], q[i], quat, np.inf))

    def __call__(self, t: np.ndarray, q: np.ndarray, quat: np.ndarray, h: np.ndarray) -> np.ndarray:
        cmds = [c(self._state(t[i], q[i], quat[i], h[i])) for i, c in enumerate(self._cats)]
        soft = [c.stiffness for c in cmds]
        self.stiffness = None if all(x is None for x in soft) else np.array(
            [np.ones(len(q[i])) if x is None else np.asarray(x, dtype=float) for i, x in enumerate(soft)])
        return np.array([np.asarray(c.q, dtype=float) for c in cmds])
