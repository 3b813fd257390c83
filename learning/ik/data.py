"""Demonstration data for the arm's IK LSTM (seed 001 §3.1): tool-point trajectories, the joint angles a
demonstrator would use for them, and the network's input/output windows.

**Demonstrator.** A tool point alone leaves the tool pitch φ free (`armkin`); the demonstrator fixes it
by a posture rule (`posture_pitch`), a smooth function of the target and of its vertical velocity (a
person leads with the tool), and solves the closed form on the elbow-up branch (`demo_joints`). The
network thus learns one smooth, human-like posture per moment of a motion rather than an arbitrary
member of the redundant family; the velocity term makes it depend on more than the current frame.

**Workspace** of the demonstrations (`in_workspace`): d = |p − S| / REACH ≤ 0.92, horizontal distance
from the joint1 axis r ≥ 0.08 m, z ≥ 0.03 m, and the rule's pose within the joint limits by 0.05 rad
with the elbow at least 0.15 rad from stretched (δ ≥ 0.15, away from the singular straight arm).

**Trajectories** (`Trajectory`, 100 Hz): minimum-jerk reaches with pauses, back-and-forth lines,
circles in various planes, pick-and-place (lift, arc, lower) and random splines, 4–12 s each, tool
speed ≤ 0.35 m/s, acceleration ≤ 2.5 m/s², every joint ≤ 4.5 rad/s, C² in time. A candidate with any
frame outside these bounds is rejected and drawn again from the same generator (deterministic).
`make_corpus` draws trajectory i from ``default_rng([seed, i])``, so a corpus is bit-identical for a
seed and a longer corpus extends a shorter one.

**Network data** (seed 001 §3.1.1–3.1.2): inputs are v = (p − S) / REACH, the shoulder → tool vector
over the limb length; joint angles are encoded as (sin q, cos q) pairs (no wrap jumps) and decoded
by atan2. `windows` cuts (input frames, output frames) at fixed frame offsets around every frame,
clamping indices to the trajectory (a stream that starts and ends at rest).

Files: corpora as ``.npz`` (no pickle), trajectories as CSV ``t,x,y,z`` at 100 Hz, recorded
demonstrations from run logs (`recorded_demos`). Units: metres, seconds, radians.
"""

from __future__ import annotations

import csv
import io
import json
import math
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline

from felis.controllers import armkin
from felis.controllers.armkin import REACH, SHOULDER
from felis.errors import ParameterError, TrajectoryError
from felis.files import check_readable, write_atomic

DT = 0.01  # s: demonstrations are sampled at 100 Hz

# --- the posture rule (see posture_pitch)
PHI_DOWN = 1.2  # rad (68.8°): tool pitch for a close target at shoulder height
K_HEIGHT = 2.0  # rad per REACH of height: close targets tip the tool up as they rise
K_LEAD, V_LEAD = 0.3, 0.15  # rad, m/s: the tool leads vertical motion by up to K_LEAD (tanh(−v_z/V_LEAD))
D_NEAR, D_FAR = 0.25, 1.0  # blend from "pointing down" (d ≤ D_NEAR) to "along the reach" (d ≥ D_FAR)

# --- the demonstration workspace and motion bounds
D_MAX = 0.92  # max |p − S| / REACH
R_MIN = 0.08  # m: min horizontal distance from the joint1 axis
Z_MIN = 0.03  # m: min height above the base plate
LIMIT_MARGIN = 0.05  # rad inside the joint limits
DELTA_MIN = 0.15  # rad: min elbow angle δ (the straight arm, δ = 0, is singular)
V_MAX = 0.35  # m/s tool speed
A_MAX = 2.5  # m/s² tool acceleration
QD_MAX = 4.5  # rad/s per joint (XM430-W350 no-load speed ≈ 4.8 rad/s); also rejects q1 crossing ±π

KINDS = ("reach", "line", "circle", "pick_place", "spline")
_MIX = ("reach", "spline", "circle", "line", "pick_place", "reach", "spline", "circle")  # kind of id i: _MIX[i % 8]
MIN_LEN, MAX_LEN = 4.0, 12.0  # s

# --- network windows (frame offsets at 100 Hz; seed 001 §3.1.2)
MP_IN = (-10, -5, 0)
MP_OUT = (5, 10)
PE_IN = (-10, -5, 0, 5, 10)
PE_OUT = (0, 1, 2, 3, 4, 5)

BUILTINS = ("circle", "figure8")
ARM_JOINTS = ("joint1", "joint2", "joint3", "joint4")


# ---------------------------------------------------------------------------------------------
# the demonstrator


def smootherstep(x: np.ndarray) -> np.ndarray:
    """s(x) = x³ (10 − 15 x + 6 x²) on x clipped to [0, 1]: 0 → 1 with s' = s'' = 0 at both ends (C²).

    Also the minimum-jerk progress profile of a rest-to-rest move."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


def posture_pitch(target: np.ndarray, velocity: np.ndarray | None = None) -> np.ndarray:
    """The demonstrator's tool pitch φ (rad; 0 = level, positive = down) for targets (..., 3) moving at
    ``velocity`` (..., 3) m/s (None: at rest).

    With rel = target − S, r = |rel_xy| (horizontal distance from the joint1 axis), h = rel_z, v_z the
    vertical velocity::

        d = |rel| / REACH,   ε = atan2(h, r)   (elevation of the shoulder → target line)
        w = smootherstep((d − 0.25) / 0.75)
        φ = (1 − w) (1.2 − 2.0 h / REACH + 0.3 tanh(−v_z / 0.15)) + w (−ε)

    What a person does: a far reach points the tool along the reach direction (φ → −ε as d → 1); a
    close target is approached from above with the tool pointing down (φ ≈ 1.2 rad at shoulder
    height, ≈ 1.45 rad at table height), tipping up as the close target rises (the height term).
    The blend is C² (smootherstep) and ε is smooth away from the joint1 axis, so φ has no kinks in
    the workspace (r ≥ 0.08 m). The constants were chosen on a grid over the workspace (`in_workspace`)
    to maximise the smallest distance of φ to the infeasible pitches: ≥ 0.34 rad everywhere (5 mm grid)
    at rest. The lead term: moving down, a person points the tool further down, moving up tips it up,
    by up to 0.3 rad (17°; 0.17 rad at 0.1 m/s), smoothly saturating, fading out at full reach where the
    pitch has no freedom left. It makes the posture depend on the motion, not only on the current
    target: a solver that sees one frame cannot know it (the input-length ablation).
    """
    rel = np.asarray(target, dtype=float) - SHOULDER
    r = np.hypot(rel[..., 0], rel[..., 1])
    h = rel[..., 2]
    d = np.sqrt(r * r + h * h) / REACH
    w = smootherstep((d - D_NEAR) / (D_FAR - D_NEAR))
    near = PHI_DOWN - K_HEIGHT * h / REACH
    if velocity is not None:
        near = near + K_LEAD * np.tanh(-np.asarray(velocity, dtype=float)[..., 2] / V_LEAD)
    return (1.0 - w) * near - w * np.arctan2(h, r)


def path_velocity(points: np.ndarray) -> np.ndarray:
    """Velocity (n, 3) m/s of a 100 Hz path (n, 3) by central differences (one-sided at the ends)."""
    points = np.asarray(points, dtype=float)
    return np.gradient(points, DT, axis=0) if len(points) > 1 else np.zeros_like(points)


def _rule_ik(points: np.ndarray, velocity: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Closed form with the posture rule, elbow up: (q (..., 4), reachable (...))."""
    return armkin.ik_closed(points, posture_pitch(points, velocity), True)


def in_workspace(points: np.ndarray) -> np.ndarray:
    """True where a point (..., 3) is in the demonstration workspace (see the module docstring): inside
    the reach, height and axis bounds, and the rule's elbow-up pose within the joint limits by
    `LIMIT_MARGIN` with the elbow bent by at least `DELTA_MIN`. (The margin on joint1, ±π, leaves out a
    0.05 rad wedge straight behind the base.)"""
    points = np.asarray(points, dtype=float)
    rel = points - SHOULDER
    r = np.hypot(rel[..., 0], rel[..., 1])
    geo = (np.linalg.norm(rel, axis=-1) <= D_MAX * REACH) & (r >= R_MIN) & (points[..., 2] >= Z_MIN)
    q, ok = _rule_ik(points)
    inside = np.all((q >= armkin.LOWER + LIMIT_MARGIN) & (q <= armkin.UPPER - LIMIT_MARGIN), axis=-1)
    bent = q[..., 2] + armkin.HALF_PI - armkin.BETA >= DELTA_MIN
    return geo & ok & inside & bent


def demo_joints(points: np.ndarray) -> np.ndarray:
    """Demonstrated joint angles q (n, 4) for a 100 Hz path of tool points (n, 3): `posture_pitch` with
    the path's velocity (`path_velocity`), elbow up, closed form.

    Raises TrajectoryError naming the first frame whose target has no such pose within the joint limits.
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise TrajectoryError(f"demo_joints needs points of shape (n, 3), got {points.shape}")
    vel = path_velocity(points)
    q, ok = _rule_ik(points, vel)
    good = ok & armkin.within_limits(q) & np.all(np.isfinite(points), axis=-1)
    if not good.all():
        i = int(np.argmin(good))
        x, y, z = points[i]
        raise TrajectoryError(f"frame {i}: target ({x:.4f}, {y:.4f}, {z:.4f}) m has no elbow-up pose within the "
                              f"joint limits at the demonstrator's pitch "
                              f"{float(posture_pitch(points[i], vel[i])):.3f} rad")
    return q


# ---------------------------------------------------------------------------------------------
# trajectories


@dataclass
class Trajectory:
    """A tool-point trajectory at 100 Hz in the arm's base frame.

    t (n,) s; p (n, 3) m; q (n, 4) rad demonstrated joint angles or None; kind (``reach``, ``line``,
    ``circle``, ``pick_place``, ``spline``, ``file``, ``recorded``, a builtin's name); ident: its id in
    a corpus (−1 when not from one).
    """

    t: np.ndarray
    p: np.ndarray
    q: np.ndarray | None
    kind: str
    ident: int

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=float)
        self.p = np.asarray(self.p, dtype=float)
        n = len(self.t)
        if self.t.ndim != 1 or self.p.shape != (n, 3):
            raise TrajectoryError(f"trajectory {self.ident} ({self.kind}): t must be (n,) and p (n, 3), "
                                  f"got {self.t.shape} and {self.p.shape}")
        if self.q is not None:
            self.q = np.asarray(self.q, dtype=float)
            if self.q.shape != (n, 4):
                raise TrajectoryError(f"trajectory {self.ident} ({self.kind}): q must be ({n}, 4), got {self.q.shape}")

    def __len__(self) -> int:
        return len(self.t)


def ease_progress(t: np.ndarray, duration: float, ramp: float) -> np.ndarray:
    """Progress u(t) from 0 to 1 over ``duration`` at a speed that ramps up from rest over ``ramp`` s
    (smootherstep), holds, and ramps down to rest: u' ∝ s(t/ramp) + s((T − t)/ramp) − 1.

    Closed form with F(x) = ∫₀ˣ s = x⁶ − 3x⁵ + 5x⁴/2 (x ≤ 1), F(x) = x − 1/2 (x > 1), ramp τ ≤ T/2::

        u(t) = (τ F(t/τ) + τ F(T/τ) − τ F((T − t)/τ) − t) / (T − τ)

    u, u' and u'' are continuous and u'(0) = u''(0) = u'(T) = u''(T) = 0.
    """
    t = np.asarray(t, dtype=float)
    tau = min(ramp, duration / 2)

    def F(x):
        x = np.clip(x, 0.0, None)
        xi = np.minimum(x, 1.0)
        return np.where(x <= 1.0, xi**4 * (2.5 + xi * (-3.0 + xi)), x - 0.5)

    u = (tau * F(t / tau) + tau * F(duration / tau) - tau * F((duration - t) / tau) - t) / (duration - tau)
    return np.clip(u, 0.0, 1.0)


def _times(length: float) -> np.ndarray:
    return np.arange(int(round(length / DT)) + 1) * DT


def _azimuth(rng: np.random.Generator) -> float:
    """A trajectory's central direction: mostly in front (3 in 4), else anywhere around the base."""
    if rng.random() < 0.75:
        return float(np.clip(rng.normal(0.0, 0.6), -2.6, 2.6))
    return float(rng.uniform(-np.pi, np.pi))


def _cyl(r: np.ndarray, theta: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Points from (r about the joint1 axis, azimuth, z)."""
    return np.stack([SHOULDER[0] + r * np.cos(theta), r * np.sin(theta), z], axis=-1)


def _sample_point(rng: np.random.Generator, theta0: float, spread: float, r_range=(R_MIN, 0.36),
                  z_range=(Z_MIN, 0.42)) -> np.ndarray:
    """One workspace point with azimuth θ0 ± spread (uniform), r and z uniform in their ranges."""
    for _ in range(100):
        k = 32
        pts = _cyl(rng.uniform(*r_range, k), theta0 + rng.uniform(-spread, spread, k), rng.uniform(*z_range, k))
        good = np.flatnonzero(in_workspace(pts))
        if len(good):
            return pts[good[0]]
    raise TrajectoryError(f"no workspace point found near azimuth {theta0:.2f} rad (r {r_range}, z {z_range})")


def _path_ok(fn: Callable[[np.ndarray], np.ndarray], k: int = 24) -> bool:
    """Whether a path piece fn(s), s ∈ [0, 1], stays in the workspace (checked at k points)."""
    return bool(in_workspace(fn(np.linspace(0.0, 1.0, k))).all())


def _line(a: np.ndarray, b: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    return lambda s: a + np.multiply.outer(s, b - a)


def _move_time(dist: float, speed: float) -> float:
    """Duration of a minimum-jerk move of ``dist`` m: peak speed 1.875 D/T ≤ speed, peak acceleration
    5.77 D/T² ≤ 0.6 A_MAX, and at least 0.5 s."""
    return max(1.875 * dist / speed, math.sqrt(5.77 * dist / (0.6 * A_MAX)), 0.5)


class _Pieces:
    """A path built from rest-to-rest pieces: p(t) = p0 + Σ_k [f_k(s((t − t_k)/T_k)) − f_k(0)], s the
    minimum-jerk profile; each piece starts where the previous one ended, so p is C²."""

    def __init__(self, start: np.ndarray, t0: float):
        self.start, self.end, self.time = start, start, t0
        self.items: list[tuple[float, float, Callable]] = []

    def add(self, fn: Callable[[np.ndarray], np.ndarray], duration: float, pause: float = 0.0) -> None:
        self.items.append((self.time, duration, fn))
        self.end = fn(np.array(1.0))
        self.time += duration + pause

    def __call__(self, t: np.ndarray) -> np.ndarray:
        p = np.broadcast_to(self.start, t.shape + (3,)).copy()
        for t0, T, fn in self.items:
            s = smootherstep((t - t0) / T)
            p += fn(s) - fn(np.array(0.0))
        return p


def _gen_reach(rng: np.random.Generator, length: float) -> np.ndarray | None:
    """Minimum-jerk point-to-point reaches between random targets, with pauses."""
    theta0 = _azimuth(rng)
    path = _Pieces(_sample_point(rng, theta0, 0.5), rng.uniform(0.2, 0.8))
    for _ in range(40):
        b = _sample_point(rng, theta0, 0.7)
        dist = float(np.linalg.norm(b - path.end))
        if dist < 0.03 or dist > 0.3 or not _path_ok(_line(path.end, b)):
            continue
        T = _move_time(dist, rng.uniform(0.1, 0.3))
        if path.time + T > length - 0.1:
            continue  # does not fit in what is left: try a nearer target
        path.add(_line(path.end, b), T, rng.uniform(0.1, 1.0))
    return path(_times(length)) if path.items else None


def _gen_line(rng: np.random.Generator, length: float) -> np.ndarray | None:
    """Back and forth along one straight segment (horizontal, vertical or oblique)."""
    theta0 = _azimuth(rng)
    for _ in range(20):
        c = _sample_point(rng, theta0, 0.4)
        th = math.atan2(c[1], c[0] - SHOULDER[0])
        choice = rng.integers(4)
        if choice == 0:
            u = np.array([math.cos(th), math.sin(th), 0.0])  # radial
        elif choice == 1:
            u = np.array([-math.sin(th), math.cos(th), 0.0])  # sideways
        elif choice == 2:
            u = np.array([0.0, 0.0, 1.0])  # vertical
        else:
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
        half = rng.uniform(0.03, 0.12)
        a, b = c - half * u, c + half * u
        if _path_ok(_line(a, b)):
            break
    else:
        return None
    T = _move_time(2 * half, rng.uniform(0.08, 0.3))
    path = _Pieces(a, rng.uniform(0.0, 0.5))
    ends = (b, a)
    while path.time + T <= length - 0.05:
        path.add(_line(path.end, ends[len(path.items) % 2]), T, rng.uniform(0.0, 0.4))
    return path(_times(length)) if path.items else None


def _plane(rng: np.random.Generator, theta: float) -> tuple[np.ndarray, np.ndarray]:
    """An orthonormal pair spanning a circle's plane: horizontal, vertical facing the arm, vertical
    through the joint1 axis, or tilted at random."""
    radial = np.array([math.cos(theta), math.sin(theta), 0.0])
    side = np.array([-math.sin(theta), math.cos(theta), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    choice = rng.integers(4)
    if choice == 0:
        return radial, side
    if choice == 1:
        return side, up
    if choice == 2:
        return radial, up
    e1 = rng.normal(size=3)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e1, rng.normal(size=3))
    return e1, e2 / np.linalg.norm(e2)


def _gen_circle(rng: np.random.Generator, length: float) -> np.ndarray | None:
    """Circles (radius 3–10 cm, period 2–6 s) in various planes, eased in from and out to rest."""
    theta0 = _azimuth(rng)
    for _ in range(20):
        c = _sample_point(rng, theta0, 0.4)
        rho = rng.uniform(0.03, 0.10)
        e1, e2 = _plane(rng, math.atan2(c[1], c[0] - SHOULDER[0]))
        a = np.linspace(0, 2 * np.pi, 48)[:, None]
        ring = c + rho * (np.cos(a) * e1 + np.sin(a) * e2)
        if in_workspace(ring).all():
            break
    else:
        return None
    period = rng.uniform(max(2.0, 2 * np.pi * rho / 0.28), 6.0)
    ramp = rng.uniform(0.5, 1.5)
    t = _times(length)
    angle = rng.uniform(0, 2 * np.pi) + rng.choice((-1.0, 1.0)) * 2 * np.pi / period * (length - ramp) \
        * ease_progress(t, length, ramp)
    return c + rho * (np.cos(angle)[:, None] * e1 + np.sin(angle)[:, None] * e2)


def _gen_pick_place(rng: np.random.Generator, length: float) -> np.ndarray | None:
    """Pick and place: lift, arc over to the next low point (cylindrical path with a raised middle),
    lower, pause; repeated."""
    theta0 = _azimuth(rng)
    lift = rng.uniform(0.04, 0.10)
    low = {"r_range": (0.12, 0.30), "z_range": (Z_MIN, 0.10)}
    up = np.array([0.0, 0.0, lift])
    path = _Pieces(_sample_point(rng, theta0, 0.6, **low), rng.uniform(0.2, 0.8))
    for _ in range(40):
        a = path.end
        b = _sample_point(rng, theta0, 1.0, **low)
        ra, ta = math.hypot(a[0] - SHOULDER[0], a[1]), math.atan2(a[1], a[0] - SHOULDER[0])
        rb, tb = math.hypot(b[0] - SHOULDER[0], b[1]), math.atan2(b[1], b[0] - SHOULDER[0])
        if abs(tb - ta) > np.pi:  # the short way round, without crossing ±π in q1
            continue
        bump = rng.uniform(0.0, 0.06)
        za, zb = a[2] + lift, b[2] + lift

        def arc(s, ra=ra, rb=rb, ta=ta, tb=tb, za=za, zb=zb, bump=bump):
            s = np.asarray(s)
            return _cyl(ra + (rb - ra) * s, ta + (tb - ta) * s, za + (zb - za) * s + 4 * bump * s * (1 - s))

        dist = math.hypot(math.hypot(rb - ra, 0.5 * (ra + rb) * (tb - ta)), zb - za) + 2 * bump
        if dist < 0.05 or not (_path_ok(_line(a, a + up), 8) and _path_ok(arc) and _path_ok(_line(b + up, b), 8)):
            continue
        speed = rng.uniform(0.12, 0.28)
        t_lift, t_arc = _move_time(lift, 0.6 * speed), _move_time(1.2 * dist, speed)
        if path.time + 2 * t_lift + t_arc > length - 0.1:
            break
        path.add(_line(a, a + up), t_lift, rng.uniform(0.0, 0.2))
        path.add(arc, t_arc, rng.uniform(0.0, 0.2))
        path.add(_line(b + up, b), t_lift, rng.uniform(0.3, 1.0))
    return path(_times(length)) if path.items else None


def _gen_spline(rng: np.random.Generator, length: float) -> np.ndarray | None:
    """A cubic spline (chord-length parameter) through a persistent random walk of waypoints,
    traversed with a smooth start and stop (`ease_progress`)."""
    theta0 = _azimuth(rng)
    ramp = rng.uniform(0.5, 1.2)
    want = rng.uniform(0.06, 0.2) * (length - ramp)  # path length for the plateau speed
    pts = [_sample_point(rng, theta0, 0.4)]
    heading = rng.normal(size=3)
    total = 0.0
    for _ in range(200):
        if total >= want or len(pts) > 40:
            break
        heading = heading / np.linalg.norm(heading) + 0.9 * rng.normal(size=3)
        step = rng.uniform(0.05, 0.12)
        nxt = pts[-1] + step * heading / np.linalg.norm(heading)
        if in_workspace(nxt):
            pts.append(nxt)
            total += step
        else:
            heading = -heading
    if len(pts) < 3:
        return None
    w = np.array(pts)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(w, axis=0), axis=1))])
    spline = CubicSpline(s, w, bc_type="natural")
    t = _times(length)
    return spline(s[-1] * ease_progress(t, length, ramp))


GENERATORS: dict[str, Callable[[np.random.Generator, float], np.ndarray | None]] = {
    "reach": _gen_reach, "line": _gen_line, "circle": _gen_circle, "pick_place": _gen_pick_place,
    "spline": _gen_spline,
}


def check_motion(p: np.ndarray) -> np.ndarray | None:
    """Demonstrated joint angles q (n, 4) if the path p (n, 3) is an acceptable demonstration (every
    frame `in_workspace`, tool speed ≤ V_MAX, acceleration ≤ A_MAX, joint speed ≤ QD_MAX by finite
    differences at 100 Hz); None otherwise."""
    if not in_workspace(p).all():
        return None
    if np.linalg.norm(np.diff(p, axis=0), axis=1).max(initial=0.0) > V_MAX * DT:
        return None
    if len(p) > 2 and np.linalg.norm(np.diff(p, 2, axis=0), axis=1).max() > A_MAX * DT * DT:
        return None
    q = demo_joints(p)
    if np.abs(np.diff(q, axis=0)).max(initial=0.0) > QD_MAX * DT:
        return None
    return q


def generate(kind: str, rng: np.random.Generator, ident: int = 0, length: float | None = None,
             max_tries: int = 500) -> Trajectory:
    """One demonstration of ``kind`` (`KINDS`), deterministic from ``rng``: a length in 4–12 s (unless
    given), then candidates from the kind's generator until one passes `check_motion`."""
    if kind not in GENERATORS:
        raise ParameterError(f"unknown trajectory kind {kind!r}; kinds: {', '.join(KINDS)}")
    if length is None:
        length = float(rng.uniform(MIN_LEN, MAX_LEN))
    for _ in range(max_tries):
        p = GENERATORS[kind](rng, length)
        if p is None:
            continue
        q = check_motion(p)
        if q is not None:
            return Trajectory(t=_times(length), p=p, q=q, kind=kind, ident=ident)
    raise TrajectoryError(f"no acceptable {kind} trajectory of {length:.2f} s in {max_tries} tries")


def make_corpus(n_traj: int, seed: int) -> list[Trajectory]:
    """``n_traj`` demonstrations with ids 0 … n−1; id i is of kind ``_MIX[i % 8]`` (reach and spline
    and circle 2 in 8 each, line and pick_place 1 in 8) drawn from ``default_rng([seed, i])``:
    bit-identical for a seed, and a prefix of any longer corpus with the same seed."""
    if n_traj < 0:
        raise ParameterError(f"number of trajectories must be ≥ 0, got {n_traj}")
    return [generate(_MIX[i % len(_MIX)], np.random.default_rng([seed, i]), ident=i) for i in range(n_traj)]


def split(corpus: Sequence[Trajectory], seed: int, fractions: Sequence[float] = (0.8, 0.1, 0.1),
          ) -> tuple[list[Trajectory], list[Trajectory], list[Trajectory]]:
    """(train, val, test) by whole trajectories, from a permutation by ``default_rng(seed)``.

    Sizes: val = round(f_val · n), test = round(f_test · n), each at least 1 when n ≥ 3, train the rest
    (≥ 1). Each split keeps the corpus order.
    """
    f = np.asarray(fractions, dtype=float)
    if f.shape != (3,) or not np.all(np.isfinite(f)) or np.any(f < 0) or f.sum() <= 0:
        raise ParameterError(f"split fractions must be 3 non-negative numbers (train, val, test), got {fractions}")
    f = f / f.sum()
    n = len(corpus)
    n_val, n_test = int(round(f[1] * n)), int(round(f[2] * n))
    if n >= 3:
        n_val, n_test = max(n_val, 1), max(n_test, 1)
    while n_val + n_test > max(n - 1, 0):
        if n_val >= n_test:
            n_val -= 1
        else:
            n_test -= 1
    order = np.random.default_rng(seed).permutation(n)
    parts = (order[n_val + n_test:], order[:n_val], order[n_val:n_val + n_test])
    return tuple([corpus[i] for i in np.sort(part)] for part in parts)  # type: ignore[return-value]


# ---------------------------------------------------------------------------------------------
# network data


def normalise(p: np.ndarray) -> np.ndarray:
    """v = (p − S) / REACH (..., 3): the shoulder → tool vector over the limb length (seed 001 §3.1.1)."""
    return (np.asarray(p, dtype=float) - SHOULDER) / REACH


def encode_angles(q: np.ndarray) -> np.ndarray:
    """(..., 4) angles → (..., 8) as (sin q1, cos q1, sin q2, cos q2, …): continuous across ±π."""
    q = np.asarray(q, dtype=float)
    return np.stack([np.sin(q), np.cos(q)], axis=-1).reshape(q.shape[:-1] + (2 * q.shape[-1],))


def decode_angles(x: np.ndarray) -> np.ndarray:
    """(..., 8) (sin, cos) pairs → (..., 4) angles in [−π, π] by atan2(s, c) (scale-free, so a pair
    need not have norm 1)."""
    x = np.asarray(x, dtype=float)
    pairs = x.reshape(x.shape[:-1] + (x.shape[-1] // 2, 2))
    return np.arctan2(pairs[..., 0], pairs[..., 1])


def windows(trajs: Sequence[Trajectory], offsets_in: Sequence[int], offsets_out: Sequence[int],
            target: str = "points") -> tuple[np.ndarray, np.ndarray]:
    """Training pairs at every frame i of every trajectory.

    X (N, len(in), 3) float32: v = `normalise`(p) at frames i + offsets_in. Y float32: with
    ``target="points"`` v at i + offsets_out, (N, 3·len(out)); with ``"angles"`` `encode_angles`(q) at
    i + offsets_out, (N, 8·len(out)); both flattened frame-major. Frame indices are clamped to
    [0, n − 1] (edge padding: a stream that starts from, and ends at, rest).
    """
    if target not in ("points", "angles"):
        raise ParameterError(f"windows target must be 'points' or 'angles', got {target!r}")
    oin = np.asarray(offsets_in, dtype=int)
    oout = np.asarray(offsets_out, dtype=int)
    width = 3 if target == "points" else 8
    xs, ys = [], []
    for tr in trajs:
        n = len(tr.t)
        i = np.arange(n)[:, None]
        v = normalise(tr.p)
        xs.append(v[np.clip(i + oin, 0, n - 1)])
        iy = np.clip(i + oout, 0, n - 1)
        if target == "points":
            ys.append(v[iy].reshape(n, -1))
        else:
            if tr.q is None:
                raise TrajectoryError(f"trajectory {tr.ident} ({tr.kind}) has no joint angles for angle targets")
            ys.append(encode_angles(tr.q[iy]).reshape(n, -1))
    if not xs:
        return np.zeros((0, len(oin), 3), np.float32), np.zeros((0, width * len(oout)), np.float32)
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# files

_FORMAT = "felis-ik-corpus"


def save_corpus(path: str | Path, corpus: Sequence[Trajectory]) -> Path:
    """Write a corpus as ``.npz`` (atomically, no pickle): arrays ``t`` (N,), ``p`` (N, 3), ``q`` (N, 4)
    (NaN for a trajectory without angles), ``start`` (n + 1,) frame offsets, and ``meta``, a JSON
    string {format, version, kinds, ids, has_q}."""
    path = Path(path)
    start = np.concatenate([[0], np.cumsum([len(tr.t) for tr in corpus])]).astype(np.int64)
    q_rows = [tr.q if tr.q is not None else np.full((len(tr.t), 4), np.nan) for tr in corpus]
    meta = {"format": _FORMAT, "version": 1, "kinds": [tr.kind for tr in corpus],
            "ids": [int(tr.ident) for tr in corpus], "has_q": [tr.q is not None for tr in corpus]}
    buf = io.BytesIO()
    np.savez(buf, t=np.concatenate([tr.t for tr in corpus]) if corpus else np.zeros(0),
             p=np.concatenate([tr.p for tr in corpus]) if corpus else np.zeros((0, 3)),
             q=np.concatenate(q_rows) if corpus else np.zeros((0, 4)), start=start, meta=np.array(json.dumps(meta)))
    return write_atomic(path, buf.getvalue(), "IK corpus", TrajectoryError)


def load_corpus(path: str | Path) -> list[Trajectory]:
    """Read a corpus written by `save_corpus`; TrajectoryError (one line) for a missing, corrupt or
    foreign file."""
    path = Path(path)
    if not path.exists():
        raise TrajectoryError(f"{path}: no such corpus file")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("t", "p", "q", "start", "meta") if k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise TrajectoryError(f"{path}: not a corpus .npz file ({e})") from None
    missing = [k for k in ("t", "p", "q", "start", "meta") if k not in arrays]
    if missing:
        raise TrajectoryError(f"{path}: not an IK corpus: missing array(s) {', '.join(missing)}")
    try:
        meta = json.loads(str(arrays["meta"]))
        kinds, ids, has_q = meta["kinds"], meta["ids"], meta["has_q"]
        if meta.get("format") != _FORMAT:
            raise ValueError(f"format {meta.get('format')!r}")
    except (ValueError, KeyError, TypeError) as e:
        raise TrajectoryError(f"{path}: not an IK corpus: bad meta ({e})") from None
    t, p, q, start = arrays["t"], arrays["p"], arrays["q"], arrays["start"]
    n_all = len(t)
    ok = (t.ndim == 1 and p.shape == (n_all, 3) and q.shape == (n_all, 4) and start.ndim == 1
          and len(start) == len(kinds) + 1 == len(ids) + 1 == len(has_q) + 1
          and start[0] == 0 and start[-1] == n_all and np.all(np.diff(start) >= 0))
    if not ok:
        raise TrajectoryError(f"{path}: IK corpus arrays have inconsistent shapes (t {t.shape}, p {p.shape}, "
                              f"q {q.shape}, start {start.shape}, {len(kinds)} trajectories)")
    return [Trajectory(t=t[a:b].copy(), p=p[a:b].copy(), q=q[a:b].copy() if hq else None, kind=str(k), ident=int(i))
            for a, b, k, i, hq in zip(start[:-1], start[1:], kinds, ids, has_q, strict=True)]


def read_trajectory_csv(path: str | Path) -> Trajectory:
    """A tool-point trajectory from CSV: a header with columns ``t,x,y,z`` (any order, extra columns
    ignored), then one row per 100 Hz frame (t in s, x y z in m in the arm's base frame).

    TrajectoryError (``<file>:<line>: column <c>: …``) for: a missing file, a missing column, a value
    that is not a number or not finite, fewer than 2 rows, t not strictly increasing, or a step that
    is not 0.01 s ± 10%. Returns kind ``file``, ident −1, q None.
    """
    path = Path(path)
    check_readable(path, "trajectory file", TrajectoryError)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise TrajectoryError(f"{path}: no such trajectory file") from None
    except IsADirectoryError:
        raise TrajectoryError(f"{path}: is a directory, not a trajectory file") from None
    except UnicodeDecodeError:
        raise TrajectoryError(f"{path}: not a text CSV file") from None
    except OSError as e:
        raise TrajectoryError(f"{path}: cannot read trajectory file: {e.strerror or e}") from None
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    if not header or not any(h.strip() for h in header):
        raise TrajectoryError(f"{path}:1: empty; expected a header line with columns t,x,y,z")
    names = [h.strip().lower() for h in header]
    cols = {}
    for c in ("t", "x", "y", "z"):
        if c not in names:
            raise TrajectoryError(f"{path}:1: missing column {c!r} (header: {','.join(names)}; needs t,x,y,z)")
        if names.count(c) > 1:
            raise TrajectoryError(f"{path}:1: column {c!r} appears {names.count(c)} times")
        cols[c] = names.index(c)
    rows, lines = [], []
    for row in reader:
        line = reader.line_num
        if not row or all(not f.strip() for f in row):
            continue
        if len(row) < len(names):
            raise TrajectoryError(f"{path}:{line}: {len(row)} fields, the header has {len(names)}")
        values = []
        for c, j in cols.items():
            try:
                v = float(row[j])
            except ValueError:
                raise TrajectoryError(f"{path}:{line}: column {c}: {row[j].strip()!r} is not a number") from None
            if not math.isfinite(v):
                raise TrajectoryError(f"{path}:{line}: column {c}: {row[j].strip()!r} is not finite")
            values.append(v)
        rows.append(values)
        lines.append(line)
    if len(rows) < 2:
        raise TrajectoryError(f"{path}: {len(rows)} data row(s); a trajectory needs at least 2")
    data = np.array(rows)
    t = data[:, 0]
    dt = np.diff(t)
    for k in range(len(dt)):
        if dt[k] <= 0:
            raise TrajectoryError(f"{path}:{lines[k + 1]}: column t: {t[k + 1]:g} s is not after {t[k]:g} s "
                                  f"(line {lines[k]}); time must increase strictly")
        if abs(dt[k] - DT) > 0.1 * DT:
            raise TrajectoryError(f"{path}:{lines[k + 1]}: column t: step {dt[k]:.6g} s from line {lines[k]}; "
                                  f"trajectories are sampled at 100 Hz (0.01 s ± 10%)")
    return Trajectory(t=t, p=data[:, 1:], q=None, kind="file", ident=-1)


def write_trajectory_csv(path: str | Path, traj: Trajectory) -> Path:
    """Write ``t,x,y,z`` (and ``q1…q4`` when the trajectory has angles), floats in shortest round-trip
    form, atomically."""
    path = Path(path)
    cols = [traj.t[:, None], traj.p] + ([traj.q] if traj.q is not None else [])
    data = np.concatenate(cols, axis=1)
    head = "t,x,y,z" + (",q1,q2,q3,q4" if traj.q is not None else "")
    body = "\n".join(",".join(repr(float(v)) for v in row) for row in data)
    return write_atomic(path, head + "\n" + body + "\n", "trajectory file", TrajectoryError)


# ---------------------------------------------------------------------------------------------
# builtin and recorded trajectories

CIRCLE_CENTRE = {"vertical": np.array([0.22, 0.0, 0.16]), "horizontal": np.array([0.22, 0.0, 0.10])}
CIRCLE_RADIUS, CIRCLE_PERIOD = 0.06, 4.0
FIGURE8_CENTRE = np.array([0.22, 0.0, 0.16])
FIGURE8_SIZE, FIGURE8_PERIOD = (0.12, 0.06), 6.0
RAMP = 1.0  # s: ease in from rest and out to rest


def builtin_trajectory(name: str, duration: float | None = None, *, plane: str = "vertical") -> Trajectory:
    """A builtin tracking target in front of the arm, eased in from rest and out to rest over 1 s.

    ``circle``: radius 6 cm, period 4 s, in the vertical plane facing the arm (x = 0.22 m, centre
    z = 0.16 m) or, with ``plane="horizontal"``, at z = 0.10 m; default 9 s (two laps). ``figure8``:
    a lemniscate of Gerono 12 cm wide (y) × 6 cm high (z) in the vertical plane x = 0.22 m,
    (y, z) = c + (0.06 sin θ, 0.03 sin 2θ), period 6 s, starting at its crossing; default 7 s (one lap).
    With θ = 2π/period · (T − 1 s) · `ease_progress`, a duration of k periods + 1 s closes the curve.
    Every frame is in the demonstration workspace; q is filled by `demo_joints`.
    """
    if name not in BUILTINS:
        raise ParameterError(f"unknown builtin trajectory {name!r}; builtins: {', '.join(BUILTINS)}")
    if name == "circle" and plane not in CIRCLE_CENTRE:
        raise ParameterError(f"circle plane must be 'vertical' or 'horizontal', got {plane!r}")
    period = CIRCLE_PERIOD if name == "circle" else FIGURE8_PERIOD
    if duration is None:
        duration = 2 * period + RAMP if name == "circle" else period + RAMP
    if not (math.isfinite(duration) and duration >= 2 * DT):
        raise ParameterError(f"trajectory duration must be at least {2 * DT} s, got {duration}")
    t = _times(duration)
    ramp = min(RAMP, duration / 2)
    theta = 2 * np.pi / period * (duration - ramp) * ease_progress(t, duration, ramp)
    if name == "circle":
        c = CIRCLE_CENTRE[plane]
        e1 = np.array([0.0, 1.0, 0.0])
        e2 = np.array([0.0, 0.0, 1.0]) if plane == "vertical" else np.array([1.0, 0.0, 0.0])
        # starts at the bottom (vertical) or the point nearest the base (horizontal), heading +y
        p = c + CIRCLE_RADIUS * (np.sin(theta)[:, None] * e1 - np.cos(theta)[:, None] * e2)
    else:
        w, h = FIGURE8_SIZE
        p = FIGURE8_CENTRE + np.stack([0 * theta, w / 2 * np.sin(theta), h / 2 * np.sin(2 * theta)], -1)
    return Trajectory(t=t, p=p, q=demo_joints(p), kind=name, ident=-1)


def recorded_demos(log_path: str | Path) -> Trajectory:
    """A demonstration from a run log of the arm: the measured joint angles q (joint1–4) and the tool
    points fk(q); kind ``recorded``, t the log's state times.

    TrajectoryError when the log is not of the arm (no joint1–4), was not recorded at 100 Hz, has
    fewer than 2 states, or has a non-finite angle; LogError when it cannot be read at all.
    """
    from felis.logs.runlog import read_log

    data = read_log(log_path)
    missing = [j for j in ARM_JOINTS if j not in data.joints]
    if missing:
        raise TrajectoryError(f"{data.path}: not a run log of the arm (robot {data.robot!r}, no joint(s) "
                              f"{', '.join(missing)})")
    rate = data.meta.get("rate_hz")
    if isinstance(rate, int | float) and abs(rate * DT - 1.0) > 0.1:
        raise TrajectoryError(f"{data.path}: recorded at {rate:g} Hz; IK demonstrations are 100 Hz")
    if len(data.t) < 2:
        raise TrajectoryError(f"{data.path}: {len(data.t)} state(s); a demonstration needs at least 2")
    q = data.q[:, [data.joints.index(j) for j in ARM_JOINTS]]
    bad = ~(np.all(np.isfinite(q), axis=1) & np.isfinite(data.t))
    if bad.any():
        i = int(np.argmax(bad))
        raise TrajectoryError(f"{data.path}: state {i} (t = {data.t[i]:g} s) has a missing or non-finite joint angle")
    return Trajectory(t=data.t.copy(), p=armkin.fk(q), q=q.copy(), kind="recorded", ident=-1)
