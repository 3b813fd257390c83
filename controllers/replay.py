"""Replay controller: a run's logged commands sent again, at a chosen speed, after a minimum-jerk approach.

A replay of the log window [t_a, t_b] (run times of the log, s) at speed ``s`` begins with an approach from
the present pose ``q0`` to the command at ``t_a`` over ``T`` seconds (`felis.controllers.pose.min_jerk`), then
plays the log. At loop time ``t`` (s since the controller's reset)::

    t < T:   q(t) = q0 + w(t / T) · (c(t_a) − q0),        w(s) = 10 s³ − 15 s⁴ + 6 s⁵
    t ≥ T:   q(t) = c(τ),  τ = t_a + s · (t − T)  (the log time being replayed, held at t_b past the end)

where ``c`` interpolates the logged commands piecewise-linearly in time (``c(τ)`` is the command sent at τ
when τ is a logged tick's time). The commands go through the loop's safety layer like any controller's, so
a replay faster than the servos can follow is rate-limited, never sent around it.

`approach_time` picks ``T`` from the distance: the minimum-jerk profile's peak speed is 1.875·|Δq|/T, kept
at or below `APPROACH_FRACTION` of each joint's maximum velocity, and ``T`` at least `APPROACH_MIN_S`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from felis.controllers.pose import min_jerk
from felis.errors import ParameterError
from felis.hal import Command, State
from felis.spec import RobotSpec

APPROACH_FRACTION = 0.25  # of each joint's maximum velocity: the approach's peak speed
APPROACH_MIN_S = 0.5  # s: the shortest approach, even to a pose the robot is already at
MIN_JERK_PEAK = 1.875  # max of dw/ds for w(s) = 10 s³ − 15 s⁴ + 6 s⁵ (at s = ½)


@dataclass(frozen=True)
class Commands:
    """Logged commands: ``t`` (M,) strictly increasing run times (s), ``q`` (M, n) positions (rad; m for
    prismatic joints), finite."""

    t: np.ndarray
    q: np.ndarray

    @staticmethod
    def from_arrays(t: np.ndarray, q: np.ndarray) -> Commands:
        """The usable commands of a log: rows with a non-finite value or a time not after the previous row's
        are dropped (a log's missing values are NaN). ParameterError when none is left."""
        t = np.asarray(t, dtype=float)
        q = np.asarray(q, dtype=float).reshape(len(t), -1)
        keep = np.isfinite(t) & np.isfinite(q).all(axis=1)
        t, q = t[keep], q[keep]
        if len(t):
            later = np.concatenate([[True], t[1:] > np.maximum.accumulate(t)[:-1]])
            t, q = t[later], q[later]
        if not len(t):
            raise ParameterError("no usable commands (every logged command has a missing value)")
        return Commands(t, q)

    def at(self, tau: float | np.ndarray) -> np.ndarray:
        """c(τ): the commands interpolated linearly at log time(s) τ, held at the first and last."""
        tau = np.asarray(tau, dtype=float)
        out = np.stack([np.interp(tau, self.t, self.q[:, j]) for j in range(self.q.shape[1])], axis=-1)
        return out


def approach_time(spec: RobotSpec, q_from: np.ndarray, q_to: np.ndarray, fraction: float = APPROACH_FRACTION,
                  minimum: float = APPROACH_MIN_S) -> float:
    """Seconds for a minimum-jerk move from ``q_from`` to ``q_to`` whose peak speed on every joint is at most
    ``fraction`` of that joint's maximum velocity: T = max(minimum, max_j 1.875·|Δq_j| / (fraction·v_max,j))."""
    dq = np.abs(np.asarray(q_to, dtype=float) - np.asarray(q_from, dtype=float))
    vmax = fraction * spec.max_velocity
    need = np.where(vmax > 0, MIN_JERK_PEAK * dq / np.where(vmax > 0, vmax, 1.0), 0.0)
    return float(max(minimum, float(need.max(initial=0.0))))


class ReplayController:
    """Sends a log's commands again (module doc): approach over ``approach_s``, then the window
    [``t_from``, ``t_to``] of log time at ``speed``.

    ``log_time(t)`` maps loop times (s since reset) to the log times they replay (NaN during the approach), so
    what the robot did can be compared with what it did when the log was recorded.
    """

    name = "replay"

    def __init__(self, commands: Commands, *, t_from: float, t_to: float, speed: float = 1.0,
                 approach_s: float = APPROACH_MIN_S):
        if not (np.isfinite(speed) and speed > 0):
            raise ParameterError(f"replay speed must be a positive number, got {speed}")
        if not (np.isfinite(approach_s) and approach_s > 0):
            raise ParameterError(f"the approach must take a positive number of seconds, got {approach_s}")
        if not (np.isfinite(t_from) and np.isfinite(t_to) and t_from < t_to):
            raise ParameterError(f"replay window {t_from:g}…{t_to:g} s is empty: --from must be before --to")
        self.commands = commands
        self.t_from, self.t_to = float(t_from), float(t_to)
        self.speed = float(speed)
        self.approach_s = float(approach_s)
        self.first = commands.at(self.t_from)
        self._q0: np.ndarray | None = None
        self.t0 = 0.0  # state time at reset: loop time 0

    @property
    def duration(self) -> float:
        """Loop seconds the replay takes: the approach and the window at its speed."""
        return self.approach_s + (self.t_to - self.t_from) / self.speed

    def reset(self, spec: RobotSpec, state: State) -> None:
        if self.first.shape != (spec.n,):
            raise ParameterError(f"the logged commands have {self.first.shape[-1]} joints, {spec.name} has {spec.n}")
        self._q0 = np.asarray(state.q, dtype=float).copy()
        self.t0 = state.t

    def log_time(self, t: float | np.ndarray) -> np.ndarray:
        """τ = t_from + speed·(t − T) for loop time(s) ``t`` (s since reset); NaN outside the window: during the
        approach, and past t_to (a wall-clock loop that overran gets there before its last tick and holds)."""
        t = np.asarray(t, dtype=float)
        tau = self.t_from + self.speed * (t - self.approach_s)
        return np.where((t >= self.approach_s) & (tau <= self.t_to), tau, np.nan)

    def __call__(self, state: State) -> Command:
        if self._q0 is None:
            raise RuntimeError("ReplayController.reset() must run before the first tick")
        t = state.t - self.t0
        if t < self.approach_s:
            return Command(q=self._q0 + min_jerk(t / self.approach_s) * (self.first - self._q0))
        return Command(q=self.commands.at(min(self.t_from + self.speed * (t - self.approach_s), self.t_to)))
