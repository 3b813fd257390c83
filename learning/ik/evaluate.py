"""Evaluation of the arm's IK pipeline on trajectories: accuracy, limits, smoothness, latency, posture.

For every frame the pipeline (`IkSolver`) is streamed as in the controller, and we report:

- position error |fk(q) − T| in mm for the raw network (the Posture Estimator's pose for frame i),
  after the mean filter, and after refinement (``raw``, ``filtered``, ``refined``);
- ``limit_violations``: refined poses outside the joint limits before the final clamp (and the raw
  network's, for information);
- smoothness: RMS jerk per joint, the third difference d³q/dt³ at 100 Hz, against the demonstrated
  joint trajectories where they exist (the pitch rule of `arm_posture.posture_pitch`), and the largest
  step per tick;
- posture: |φ − φ_demo|, how far the chosen tool pitch is from the demonstrator's (`posture_pitch`
  with the path's velocity);
- latency: one query at a time (median, p99) and per query in a batch of 1000 windows, 5% of them
  out of reach (failures included);
- ``unreachable``: targets outside the workspace, projected to the nearest reachable point.

Side by side, the same figures for two classical solvers: the closed form with the demonstrations'
pitch rule (the demonstrator itself) and pure damped least squares warm-started from the previous
frame (position only, the pitch left to drift).
"""

from __future__ import annotations

import time

import numpy as np

from felis import armkin
from felis.controllers.arm_posture import DT, path_velocity, posture_pitch
from felis.controllers.arm_track import error_stats
from felis.controllers.trajectories import Trajectory
from felis.learning.ik.solver import HISTORY, IkSolver

JOINTS = armkin.JOINTS


def jerk(q: np.ndarray, dt: float = DT) -> np.ndarray:
    """Third finite difference of (unwrapped) joint angles (n, 4) → (n − 3, 4) in rad/s³."""
    q = np.unwrap(np.asarray(q, dtype=float), axis=0)
    return np.diff(q, n=3, axis=0) / dt**3 if len(q) > 3 else np.zeros((0, q.shape[-1]))


def _per_joint(values: np.ndarray) -> dict:
    return {j: float(v) for j, v in zip(JOINTS, values, strict=True)}


def _rms(chunks: list[np.ndarray]) -> np.ndarray:
    x = np.concatenate(chunks) if chunks else np.zeros((0, 4))
    return np.sqrt((x**2).mean(axis=0)) if len(x) else np.zeros(4)


def _smoothness(qs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    rms = _rms([jerk(q) for q in qs])
    steps = [np.abs(np.diff(np.unwrap(q, axis=0), axis=0)) for q in qs if len(q) > 1]
    max_step = np.max(np.concatenate(steps), axis=0) if steps else np.zeros(4)
    return rms, max_step


def _summary(qs: list[np.ndarray], trajs: list[Trajectory], demo_jerk: np.ndarray | None,
             mask: np.ndarray | None = None) -> dict:
    """Error (over the frames in ``mask``: the reachable ones), smoothness, limits and posture of a solver."""
    err = np.concatenate([np.linalg.norm(armkin.fk(q) - t.p, axis=-1) for q, t in zip(qs, trajs, strict=True)])
    rms, max_step = _smoothness(qs)
    out = {"refined": error_stats(err if mask is None else err[mask]), "rms_jerk": _per_joint(rms),
           "max_step_rad": _per_joint(max_step),
           "limit_violations": int(sum((~armkin.within_limits(q)).sum() for q in qs))}
    if demo_jerk is not None and np.all(demo_jerk > 0):
        out["jerk_ratio"] = float(np.sqrt((rms**2).mean() / (demo_jerk**2).mean()))
    rule = (posture_pitch(t.p, path_velocity(t.p)) for t in trajs)
    dev = [np.abs(armkin.pitch(q) - t_phi) for q, t_phi in zip(qs, rule, strict=True)]
    out["pitch_dev_deg"] = {"median": float(np.degrees(np.median(np.concatenate(dev)))),
                            "p95": float(np.degrees(np.percentile(np.concatenate(dev), 95)))}
    return out


def _latency(times_s: list[float]) -> dict:
    t = np.asarray(times_s) * 1e3
    return {"median": float(np.median(t)), "p99": float(np.percentile(t, 99))}


def closed_form_rule(p: np.ndarray, velocity: np.ndarray | None = None) -> np.ndarray:
    """The demonstrator: the closed form with the pitch rule at ``velocity``, elbow up; DLS where that
    fails. (In `evaluate` the velocity is the path's central difference: it knows the next frame.)"""
    q, ok = armkin.ik_closed(p, posture_pitch(p, velocity), True)
    bad = ~(ok & armkin.within_limits(q))
    if bad.any():
        q = np.array(q, copy=True)
        q[bad] = armkin.dls(p[bad], np.tile([0.0, 0.0, 0.0, 0.6], (int(bad.sum()), 1)))
    return q


def dls_tracker(p: np.ndarray, q0: np.ndarray | None = None) -> tuple[np.ndarray, list[float]]:
    """Pure DLS, position only, warm-started from the previous frame's solution (from the arm's
    ``stand`` pose at the start). Returns the joint angles and the time of each query."""
    q = np.array([0.0, 0.0, 0.0, 0.6]) if q0 is None else np.asarray(q0, dtype=float)
    out, times = [], []
    for target in p:
        t0 = time.perf_counter()
        q = armkin.dls(target[None], q[None])[0]
        times.append(time.perf_counter() - t0)
        out.append(q)
    return np.array(out), times


def _batch_windows(trajs: list[Trajectory], refined: list[np.ndarray], n: int, rng: np.random.Generator,
                   past: int) -> tuple[np.ndarray, np.ndarray]:
    hist, prev = [], []
    for _ in range(n):
        k = int(rng.integers(len(trajs)))
        p, q = trajs[k].p, refined[k]
        i = int(rng.integers(len(p)))
        idx = np.clip(np.arange(i - HISTORY + 1, i + 1), 0, len(p) - 1)
        h = p[idx].copy()
        if rng.random() < 0.05:  # out of reach: 1.2–1.6 × the reach from the shoulder
            d = h[-1] - armkin.SHOULDER
            h[-1] = armkin.SHOULDER + d / np.linalg.norm(d) * armkin.REACH * rng.uniform(1.2, 1.6)
        hist.append(h)
        prev.append(q[np.clip(np.arange(i - past, i), 0, len(q) - 1)])
    return np.array(hist), np.array(prev)


def evaluate(solver: IkSolver, trajs: list[Trajectory], *, seed: int = 0, batch: int = 1000,
             baselines: bool = True) -> dict:
    """The figures above for ``solver`` on ``trajs`` (each streamed from a reset)."""
    raw, filt, ref, times, unreach = [], [], [], [], []
    raw_violations = 0
    for k, traj in enumerate(trajs):
        solver.reset()
        qn, qf, qr = [], [], []
        for i, target in enumerate(traj.p):
            t0 = time.perf_counter()
            s = solver.step(target)
            times.append(time.perf_counter() - t0)
            qn.append(s.q_net)
            qf.append(s.q_filtered)
            qr.append(s.q)
            if not s.reachable:
                unreach.append((k, i))
        raw.append(np.array(qn))
        filt.append(np.array(qf))
        ref.append(np.array(qr))
        raw_violations += int((~armkin.within_limits(raw[-1])).sum())

    def err(qs):
        return np.concatenate([np.linalg.norm(armkin.fk(q) - t.p, axis=-1) for q, t in zip(qs, trajs, strict=True)])

    reach_mask = np.ones(sum(len(t.p) for t in trajs), dtype=bool)
    offsets = np.cumsum([0] + [len(t.p) for t in trajs])
    for k, i in unreach:
        reach_mask[offsets[k] + i] = False
    demos = [t.q for t in trajs if t.q is not None]
    demo_jerk = _rms([jerk(q) for q in demos]) if len(demos) == len(trajs) else None
    out = {"trajectories": len(trajs), "frames": int(offsets[-1]),
           "raw": error_stats(err(raw)[reach_mask]), "filtered": error_stats(err(filt)[reach_mask])}
    out.update(_summary(ref, trajs, demo_jerk, reach_mask))  # reachable targets; the others are flagged
    out["raw_limit_violations"] = raw_violations
    if demo_jerk is not None:
        out["demo_rms_jerk"] = _per_joint(demo_jerk)
    rng = np.random.default_rng(seed)
    hist, prev = _batch_windows(trajs, ref, batch, rng, max(solver.filter_past, 2))
    per_query = []
    for _ in range(3):
        t0 = time.perf_counter()
        solver.predict(hist, prev)
        per_query.append((time.perf_counter() - t0) / batch)
    out["latency_ms"] = {"single": _latency(times), "batch_per_query": float(np.median(per_query) * 1e3),
                         "batch": batch}
    out["unreachable"] = {"count": len(unreach), "frames": [{"trajectory": k, "frame": i} for k, i in unreach[:20]]}
    if baselines:
        out["baselines"] = {}
        cf_q, cf_t = [], []
        for t in trajs:
            for target, vel in zip(t.p, path_velocity(t.p), strict=True):
                t0 = time.perf_counter()
                cf_q.append(closed_form_rule(target[None], vel[None])[0])
                cf_t.append(time.perf_counter() - t0)
        cf = np.array(cf_q)
        cf_split = np.split(cf, offsets[1:-1])
        b = _summary(cf_split, trajs, demo_jerk, reach_mask)
        b["latency_ms"] = {"single": _latency(cf_t)}
        out["baselines"]["closed_form_rule"] = b
        dq, dt_ = [], []
        for t in trajs:
            q, tt = dls_tracker(t.p)
            dq.append(q)
            dt_ += tt
        b = _summary(dq, trajs, demo_jerk, reach_mask)
        b["latency_ms"] = {"single": _latency(dt_)}
        out["baselines"]["dls"] = b
    return out
