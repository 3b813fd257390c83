"""Comparing what a robot did in two runs: per-joint position error between measured joint trajectories.

A replay (``felis replay``) measures ``q(t)`` at its own ticks; each tick replays a time τ of the original
log. The original's measured positions are interpolated linearly at those τ (within the original's
measured span, at its finite values) and, per joint j over the N ticks that have one,

    e_j,k = q_j(t_k) − q_orig,j(τ_k),   RMS_j = √(Σ_k e_j,k² / N),   max_j = max_k |e_j,k|

in the joint's unit (rad; m for prismatic joints). A replay of a hardware log in simulation is then a
regression test: the simulation should do what the servos did, within a bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Comparison:
    """Position error of a run against a reference run, per joint (``joints`` order), over ``samples`` ticks
    that replay reference times ``span`` (s). ``rms``/``max`` are NaN for a joint without a sample."""

    joints: list[str]
    kinds: list[str]  # "revolute" (rad) or "prismatic" (m), per joint
    rms: np.ndarray
    max: np.ndarray
    samples: int
    span: tuple[float, float]

    def as_dict(self) -> dict:
        def num(v: float) -> float | None:
            return round(float(v), 6) if math.isfinite(v) else None

        return {"samples": self.samples, "span_s": [num(self.span[0]), num(self.span[1])],
                "joints": {j: {"unit": "m" if k == "prismatic" else "rad", "rms": num(r), "max": num(m)}
                           for j, k, r, m in zip(self.joints, self.kinds, self.rms, self.max, strict=True)}}


def position_error(ref_t: np.ndarray, ref_q: np.ndarray, tau: np.ndarray, q: np.ndarray, joints: list[str],
                   kinds: list[str] | None = None) -> Comparison:
    """Per-joint RMS and max of ``q`` (K, n) against the reference ``ref_q`` (N, n) at times ``ref_t`` (N,)
    interpolated at ``tau`` (K,) (module doc). Ticks with a non-finite τ (e.g. a replay's approach) or a τ
    outside the reference's span are left out, as are missing (NaN) values on either side."""
    ref_t = np.asarray(ref_t, dtype=float)
    ref_q = np.asarray(ref_q, dtype=float).reshape(len(ref_t), -1)
    tau = np.asarray(tau, dtype=float)
    q = np.asarray(q, dtype=float).reshape(len(tau), -1)
    n = q.shape[1]
    if ref_q.shape[1] != n or len(joints) != n:
        raise ValueError(f"joint counts differ: reference {ref_q.shape[1]}, run {n}, names {len(joints)}")
    kinds = list(kinds) if kinds is not None else ["revolute"] * n
    ok_t = np.isfinite(ref_t)
    inside = np.isfinite(tau)
    if ok_t.any():
        inside &= (tau >= ref_t[ok_t].min()) & (tau <= ref_t[ok_t].max())
    else:
        inside[:] = False
    rms, peak = np.full(n, np.nan), np.full(n, np.nan)
    for j in range(n):
        have = ok_t & np.isfinite(ref_q[:, j])
        use = inside & np.isfinite(q[:, j])
        if have.sum() < 1 or not use.any():
            continue
        e = q[use, j] - np.interp(tau[use], ref_t[have], ref_q[have, j])
        rms[j] = float(np.sqrt(np.mean(e * e)))
        peak[j] = float(np.abs(e).max())
    used = tau[inside]
    span = (float(used.min()), float(used.max())) if used.size else (math.nan, math.nan)
    return Comparison(joints=list(joints), kinds=kinds, rms=rms, max=peak, samples=int(inside.sum()), span=span)

