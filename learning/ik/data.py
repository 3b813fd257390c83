"""Demonstration data for the arm's IK LSTM (seed 001 §3.1): tool-point trajectories, the joint angles a
demonstrator would use for them, and the network's input/output windows.

**Demonstrator.** A tool point alone leaves the tool pitch φ free (`felis.armkin`); the demonstrator fixes it
by a posture rule (`felis.controllers.arm_posture.posture_pitch`), a smooth function of the target and of
its vertical velocity (a person leads with the tool), and solves the closed form on the elbow-up branch
(`arm_posture.demo_joints`). The network thus learns one smooth, human-like posture per moment of a
motion rather than an arbitrary member of the redundant family; the velocity term makes it depend on
more than the current frame.

**Workspace** of the demonstrations (`arm_posture.in_workspace`): d = |p − S| / REACH ≤ 0.92, horizontal distance
from the joint1 axis r ≥ 0.08 m, z ≥ 0.03 m, and the rule's pose within the joint limits by 0.05 rad
with the elbow at least 0.15 rad from stretched (δ ≥ 0.15, away from the singular straight arm).

**Trajectories** (`felis.controllers.trajectories.Trajectory`, 100 Hz): minimum-jerk reaches with pauses,
back-and-forth lines, circles in various planes, pick-and-place (lift, arc, lower) and random splines, 4–12 s each, tool
speed ≤ 0.35 m/s, acceleration ≤ 2.5 m/s², every joint ≤ 4.5 rad/s, C² in time. A candidate with any
frame outside these bounds is rejected and drawn again from the same generator (deterministic).
`make_corpus` draws trajectory i from ``default_rng([seed, i])``, so a corpus is bit-identical for a
seed and a longer corpus extends a shorter one.

**Network data** (seed 001 §3.1.1–3.1.2): inputs are v = (p − S) / REACH, the shoulder → tool vector
over the limb length; joint angles are encoded as (sin q, cos q) pairs (no wrap jumps) and decoded
by atan2. `windows` cuts (input frames, output frames) at fixed frame offsets around every frame,
clamping indices to the trajectory (a stream that starts and ends at rest).

Files: corpora as ``.npz`` (no pickle, `felis.learning.ik.corpus`), trajectories as CSV ``t,x,y,z`` at 100 Hz
(`felis.controllers.trajectories`), recorded demonstrations from run logs (`corpus.recorded_demos`).
Units: metres, seconds, radians.
"""


from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from scipy.interpolate import CubicSpline

from felis.armkin import SHOULDER
from felis.controllers.arm_posture import DT, R_MIN, Z_MIN, demo_joints, in_workspace, smootherstep
from felis.controllers.trajectories import Trajectory, ease_progress, frame_times
from felis.errors import ParameterError, TrajectoryError
from felis.learning.ik.infer import encode_angles, normalise

V_MAX = 0.35  # m/s tool speed
A_MAX = 2.5  # m/s² tool acceleration
QD_MAX = 4.5  # rad/s per joint (XM430-W350 no-load speed ≈ 4.8 rad/s); also rejects q1 crossing ±π

KINDS = ("reach", "line", "circle", "pick_place", "spline")
_MIX = ("reach", "spline", "circle", "line", "pick_place", "reach", "spline", "circle")  # kind of id i: _MIX[i % 8]
MIN_LEN, MAX_LEN = 4.0, 12.0  # s



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
    return path(frame_times(length)) if path.items else None


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
    return path(frame_times(length)) if path.items else None


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
    t = frame_times(length)
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
    return path(frame_times(length)) if path.items else None


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
    t = frame_times(length)
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
            return Trajectory(t=frame_times(length), p=p, q=q, kind=kind, ident=ident)
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
