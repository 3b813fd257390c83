"""Keyframe player: a minimum-jerk move from the present pose to the first keyframe, then from each keyframe to
the next, then holding the last (`felis pose play`).

Keyframes ``q_1 … q_K`` (full joint vectors, rad/m) with durations ``T_1 … T_K``; ``q_0`` is the present pose when
the run starts (t₀) and segment k starts at ``t_k = t₀ + T_1 + … + T_(k−1)``. During segment k

    s = (t − t_k) / T_k,   q(t) = q_(k−1) + w(s) · (q_k − q_(k−1)),   w(s) = 10 s³ − 15 s⁴ + 6 s⁵

(`felis.controllers.pose.min_jerk`), so every keyframe is reached at rest (zero velocity and acceleration) and the
path between two keyframes is a straight line in joint space. After the last segment the last keyframe is held.
The peak speed of a segment is ``w'(½) · |Δq| / T = 1.875 · |Δq| / T`` (`peak_speed`); the safety layer
rate-limits anything faster, which only delays the move.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Sequence

import numpy as np

from felis.controllers.pose import min_jerk
from felis.errors import ParameterError
from felis.hal import Command, State
from felis.spec import RobotSpec

PEAK = 1.875  # max of w'(s) = 30 s²(1 − s)², at s = ½


def peak_speed(dq: np.ndarray, duration: float) -> np.ndarray:
    """Peak joint speed of a minimum-jerk move by ``dq`` over ``duration`` s: 1.875·|dq|/T."""
    return PEAK * np.abs(np.asarray(dq, float)) / duration


class KeyframeController:
    """Plays keyframes (module doc).

    Args:
        keyframes: (name, q) pairs, q a full joint vector in the description's order.
        durations: seconds of each move (the first is the approach from the present pose), each > 0.
    """

    name = "keyframes"

    def __init__(self, keyframes: Sequence[tuple[str, np.ndarray]], durations: Sequence[float]):
        if not keyframes:
            raise ParameterError("controller 'keyframes' plays poses: use `felis pose play NAME… --durations …`")
        if len(durations) != len(keyframes):
            raise ParameterError(f"{len(keyframes)} keyframe(s) need {len(keyframes)} duration(s), got "
                                 f"{len(durations)}")
        bad = [d for d in durations if not (np.isfinite(d) and d > 0)]
        if bad:
            raise ParameterError(f"keyframe durations must be > 0 s, got {bad[0]}")
        self.names = [n for n, _ in keyframes]
        self.targets = [np.asarray(q, float).copy() for _, q in keyframes]
        self.durations = [float(d) for d in durations]
        self.starts = np.concatenate([[0.0], np.cumsum(self.durations)])  # segment k runs starts[k]…starts[k+1]
        self.spec: RobotSpec | None = None
        self._points: list[np.ndarray] = []
        self._t0 = 0.0
        self._last_q: np.ndarray | None = None

    @property
    def length(self) -> float:
        """Seconds from the start to the last keyframe."""
        return float(self.starts[-1])

    def reset(self, spec: RobotSpec, state: State) -> None:
        shapes = {q.shape for q in self.targets}
        if shapes != {(spec.n,)}:
            raise ParameterError(f"keyframes must give all {spec.n} joints of the {spec.name}")
        self.spec = spec
        self._points = [np.asarray(state.q, float).copy(), *self.targets]
        self._t0 = state.t
        self._last_q = None

    def target(self, t: float) -> np.ndarray:
        """The commanded pose ``t`` seconds after the start."""
        k = min(bisect_right(self.starts, t), len(self.durations))  # segment 1…K (K: held after the end)
        k = max(k, 1)
        s = (t - self.starts[k - 1]) / self.durations[k - 1]
        q0, q1 = self._points[k - 1], self._points[k]
        return q0 + min_jerk(s) * (q1 - q0)

    def __call__(self, state: State) -> Command:
        if not self._points:
            raise RuntimeError("KeyframeController.reset() must run before the first tick")
        self._last_q = state.q
        return Command(q=self.target(state.t - self._t0))

    def summary(self) -> dict:
        """The keyframes played and how far the last reading was from the last keyframe (per joint, rad/m)."""
        out = {"keyframes": self.names, "durations_s": self.durations}
        if self._last_q is not None and self.spec is not None:
            err = np.asarray(self._last_q, float) - self.targets[-1]
            worst = int(np.argmax(np.abs(err)))
            out["final_error"] = {"max_abs": float(abs(err[worst])), "joint": self.spec.names[worst],
                                  "per_joint": {n: float(e) for n, e in zip(self.spec.names, err, strict=True)}}
        return out


def keyframes(poses: Sequence[tuple[str, np.ndarray]] = (), durations: Sequence[float] = ()) -> KeyframeController:
    """`KeyframeController` by name for `felis.controllers.make_controller` (``felis pose play`` gives the poses)."""
    return KeyframeController(poses, durations)


__all__ = ["KeyframeController", "keyframes", "peak_speed"]
