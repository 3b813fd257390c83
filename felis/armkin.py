"""Kinematics of the 4-DOF arm: forward kinematics, Jacobian, closed-form IK, DLS refinement.

Geometry (``shared/reference/robots.md``, ``sim/models/arm.xml``): joint1 turns the arm plane about
the base's z axis at x = 0.012 m; joints 2–4 are pitch joints about the plane's normal, positive
tipping the arm forward and down. The shoulder (joint2) sits at S = (0.012, 0, 0.0765) m for every
q1. In the arm plane, with r the horizontal distance from the joint1 axis and h the height above
the shoulder, and angles measured from the vertical (forward positive)::

    α1 = q2 + β,   α2 = q2 + q3 + π/2,   α3 = q2 + q3 + q4 + π/2 = φ + π/2
    (r, h) = L1 (sin α1, cos α1) + L2 (sin α2, cos α2) + L3 (sin α3, cos α3)
    p = S + r (cos q1, sin q1, 0) + (0, 0, h)

with L1 = |(0.024, 0.128)| = 130.23 mm and β = atan2(0.024, 0.128) = 10.62° (the upper link's
built-in offset), L2 = 124 mm (forearm), L3 = 126 mm (wrist → tool point). The tool pitch is
φ = q2 + q3 + q4 (0 = level, positive = pointing down).

A position-only target leaves φ free (the redundant degree of freedom). Given φ, the wrist
W = T − L3 (cos φ, −sin φ) in the plane fixes a two-link problem with the closed form

    cos δ = (|W|² − L1² − L2²) / (2 L1 L2),    δ = α2 − α1 = ±acos(·)
    α1 = atan2(W_r, W_h) − atan2(L2 sin δ, L1 + L2 cos δ)
    q2 = α1 − β,   q3 = β + δ − π/2,   q4 = φ − q2 − q3

δ > 0 is the elbow-up branch (the arm's natural one: at q = 0, δ = π/2 − β); δ < 0 is elbow-down.
The other half-plane solution (q1 + π with the arm reaching back over the top) is not used.

Everything is vectorised: ``q`` is (..., 4) and targets (..., 3). Units are metres and radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

JOINTS = ("joint1", "joint2", "joint3", "joint4")  # the arm's joints these functions take, in order
SHOULDER = np.array([0.012, 0.0, 0.017 + 0.0595])
L1 = float(np.hypot(0.024, 0.128))
BETA = float(np.arctan2(0.024, 0.128))
L2 = 0.124
L3 = 0.126
REACH = L1 + L2 + L3  # 0.3802 m: shoulder → tool at full extension
LOWER = np.array([-np.pi, -1.5, -1.5, -1.7])
UPPER = np.array([np.pi, 1.5, 1.4, 1.97])
HALF_PI = np.pi / 2


def _alphas(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a1 = q[..., 1] + BETA
    a2 = q[..., 1] + q[..., 2] + HALF_PI
    a3 = a2 + q[..., 3]
    return a1, a2, a3


def planar(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r, h) of the tool point in the arm plane, relative to the shoulder."""
    q = np.asarray(q, dtype=float)
    a1, a2, a3 = _alphas(q)
    r = L1 * np.sin(a1) + L2 * np.sin(a2) + L3 * np.sin(a3)
    h = L1 * np.cos(a1) + L2 * np.cos(a2) + L3 * np.cos(a3)
    return r, h


def fk(q: np.ndarray) -> np.ndarray:
    """Tool point (..., 3) in the base frame for joint angles q (..., 4)."""
    q = np.asarray(q, dtype=float)
    r, h = planar(q)
    return SHOULDER + np.stack([r * np.cos(q[..., 0]), r * np.sin(q[..., 0]), h], axis=-1)


def pitch(q: np.ndarray) -> np.ndarray:
    """Tool pitch φ = q2 + q3 + q4 (rad; 0 = level, positive = pointing down)."""
    q = np.asarray(q, dtype=float)
    return q[..., 1] + q[..., 2] + q[..., 3]


def jacobian(q: np.ndarray) -> np.ndarray:
    """∂p/∂q (..., 3, 4) of the tool point."""
    q = np.asarray(q, dtype=float)
    a1, a2, a3 = _alphas(q)
    c1, c2, c3 = L1 * np.cos(a1), L2 * np.cos(a2), L3 * np.cos(a3)
    s1, s2, s3 = L1 * np.sin(a1), L2 * np.sin(a2), L3 * np.sin(a3)
    r = s1 + s2 + s3
    cq, sq = np.cos(q[..., 0]), np.sin(q[..., 0])
    dr = np.stack([c1 + c2 + c3, c2 + c3, c3], axis=-1)  # ∂r/∂(q2, q3, q4)
    dh = -np.stack([s1 + s2 + s3, s2 + s3, s3], axis=-1)
    J = np.zeros(q.shape[:-1] + (3, 4))
    J[..., 0, 0] = -r * sq
    J[..., 1, 0] = r * cq
    J[..., 0, 1:] = dr * cq[..., None]
    J[..., 1, 1:] = dr * sq[..., None]
    J[..., 2, 1:] = dh
    return J


def within_limits(q: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """True where every joint of q (..., 4) is within the arm's limits."""
    q = np.asarray(q, dtype=float)
    return np.all((q >= LOWER - tol) & (q <= UPPER + tol), axis=-1)


def ik_closed(target: np.ndarray, phi: np.ndarray, elbow_up: np.ndarray | bool = True,
              q1_hint: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Exact IK for tool position + pitch: returns (q (..., 4), ok (...)).

    ``ok`` is False where the wrist is out of the two-link reach (|cos δ| > 1); q is then the
    nearest stretched/folded configuration and must not be used as a solution. Joint limits are not
    checked here (see `within_limits`). On the joint1 axis (r ≈ 0) q1 is free and ``q1_hint`` is kept.
    """
    target = np.asarray(target, dtype=float)
    phi = np.asarray(phi, dtype=float)
    rel = target - SHOULDER
    r = np.hypot(rel[..., 0], rel[..., 1])
    on_axis = r < 1e-9
    q1 = np.where(on_axis, q1_hint, np.arctan2(rel[..., 1], rel[..., 0]))
    wr = r - L3 * np.cos(phi)
    wh = rel[..., 2] + L3 * np.sin(phi)
    c = (wr * wr + wh * wh - L1 * L1 - L2 * L2) / (2 * L1 * L2)
    ok = np.abs(c) <= 1.0 + 1e-12
    delta = np.arccos(np.clip(c, -1.0, 1.0))
    delta = np.where(np.asarray(elbow_up), delta, -delta)
    a1 = np.arctan2(wr, wh) - np.arctan2(L2 * np.sin(delta), L1 + L2 * np.cos(delta))
    q2 = a1 - BETA
    q3 = BETA + delta - HALF_PI
    q4 = phi - q2 - q3
    q = np.stack(np.broadcast_arrays(q1, q2, q3, q4), axis=-1)
    return q, np.broadcast_to(ok, q.shape[:-1]).copy()


def elbow_up(q: np.ndarray) -> np.ndarray:
    """True where q is on the elbow-up branch (δ = q3 + π/2 − β > 0)."""
    q = np.asarray(q, dtype=float)
    return q[..., 2] + HALF_PI - BETA > 0


@dataclass(frozen=True)
class Refined:
    """Result of `refine`: joint angles, position error (m), and how it was found."""

    q: np.ndarray
    error: np.ndarray  # |fk(q) − target| (m)
    exact: np.ndarray  # closed form with the seed's pitch and branch, within limits
    reachable: np.ndarray  # error ≤ tol after refinement


def dls(target: np.ndarray, q0: np.ndarray, *, phi: np.ndarray | None = None, pitch_weight: float = 0.0,
        damping: float = 1e-2, max_step: float = 0.2, iters: int = 100, tol: float = 1e-8) -> np.ndarray:
    """Damped least squares toward ``target`` (..., 3) from ``q0`` (..., 4), within the joint limits.

    Each step solves (JᵀJ + w² gᵀg + λ² I) Δq = Jᵀ e + w² g (φ* − φ) with g = ∂φ/∂q = (0, 1, 1, 1),
    with λ = ``damping`` · clip(|e| / 0.01 m, 10⁻³, 1) (Levenberg–Marquardt style: near Gauss–Newton steps near
    the solution), scales Δq down to at most ``max_step`` rad per joint, and clips q to the limits (a
    projected step). With ``pitch_weight`` w > 0 the pitch is kept near ``phi`` as a soft secondary
    task; with w = 0 only the position counts. Returns the last iterate: a local nearest reachable
    point when the target is out of reach.
    """
    target = np.asarray(target, dtype=float)
    q = np.clip(np.array(q0, dtype=float, copy=True), LOWER, UPPER)
    g = np.array([0.0, 1.0, 1.0, 1.0])
    eye = np.eye(4)
    for _ in range(iters):
        e = target - fk(q)
        en = np.linalg.norm(e, axis=-1)
        if np.all(en < tol):
            break
        J = jacobian(q)
        JT = np.swapaxes(J, -1, -2)
        lam = damping * np.clip(en / 0.01, 1e-3, 1.0)
        A = JT @ J + (lam**2)[..., None, None] * eye
        b = (JT @ e[..., None])[..., 0]
        if phi is not None and pitch_weight > 0:
            A = A + pitch_weight**2 * np.outer(g, g)
            b = b + pitch_weight**2 * (np.asarray(phi) - pitch(q))[..., None] * g
        dq = np.linalg.solve(A, b[..., None])[..., 0]
        scale = np.minimum(1.0, max_step / np.maximum(np.abs(dq).max(axis=-1), 1e-300))
        q = np.clip(q + dq * scale[..., None], LOWER, UPPER)
    return q


# Pitch offsets tried, nearest first, when the seed's own pitch cannot reach a target within limits.
_OFFSETS = np.concatenate([[0.0], np.stack([s := np.arange(1, 629) * 0.005, -s], axis=-1).ravel()])


def nearest_feasible_pitch(target: np.ndarray, phi: np.ndarray, up: np.ndarray, q1_hint: np.ndarray,
                           ) -> tuple[np.ndarray, np.ndarray]:
    """For targets (n, 3): the closed-form solution whose pitch is nearest ``phi`` (5 mrad grid) on
    branch ``up`` and within the joint limits; (q (n, 4), found (n,))."""
    n = len(target)
    qs, ok = ik_closed(target[:, None, :], phi[:, None] + _OFFSETS, up[:, None], q1_hint[:, None])
    ok &= within_limits(qs)
    first = np.argmax(ok, axis=1)
    found = ok[np.arange(n), first]
    return qs[np.arange(n), first], found


def refine(target: np.ndarray, seed: np.ndarray, *, tol: float = 1e-4) -> Refined:
    """Exact refinement seeded by a network's pose, keeping its branch and pitch.

    1. The closed form with the seed's pitch φ = q2 + q3 + q4 and elbow branch: exact to machine
       precision whenever that pitch reaches the target within the joint limits (``exact``).
    2. Otherwise the closed form with the feasible pitch nearest φ (same branch, then the other).
    3. Otherwise the target is out of the workspace: damped least squares from the seed, within the
       limits, gives the nearest reachable point found; such targets are flagged (``reachable`` False
       when the error exceeds ``tol`` m).
    """
    target = np.asarray(target, dtype=float)
    seed = np.asarray(seed, dtype=float)
    single = target.ndim == 1
    t2, s2 = np.atleast_2d(target), np.atleast_2d(seed)
    phi = pitch(s2)
    up = elbow_up(s2)
    q, ok = ik_closed(t2, phi, up, s2[:, 0])
    exact = ok & within_limits(q)
    if not exact.all():
        q = np.array(q, copy=True)
        todo = np.flatnonzero(~exact)
        for flip in (False, True):
            branch = up[todo] ^ flip
            qn, found = nearest_feasible_pitch(t2[todo], phi[todo], branch, s2[todo, 0])
            q[todo[found]] = qn[found]
            todo = todo[~found]
            if len(todo) == 0:
                break
        if len(todo):
            q[todo] = dls(t2[todo], s2[todo], phi=phi[todo], pitch_weight=0.05)
    err = np.linalg.norm(fk(q) - t2, axis=-1)
    res = Refined(q=q, error=err, exact=exact, reachable=err <= tol)
    if single:
        return Refined(q=res.q[0], error=res.error[0], exact=res.exact[0], reachable=res.reachable[0])
    return res
