"""Latency of the arm's IK pipeline against the closed-form solver measured in the same run.

    python bench/ik_latency.py [--frames 2000]

Streams held-out demonstration trajectories through the shipped pipeline (MP → PE → mean filter →
pitch smoothing → exact refinement), one query at a time, and times the same targets through the
closed form with the demonstrations' pitch rule (the anchor) and pure damped least squares. Prints
median and p99 per single query, the batch-of-1000 cost per query, and ratios to the anchor.
Goal (issue 6): single-query median and p99 ≤ 2 ms on this CPU.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    from felis import armkin
    from felis.learning.ik.data import make_corpus, split
    from felis.learning.ik.evaluate import _batch_windows, closed_form_rule
    from felis.learning.ik.solver import IkSolver

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2000)
    args = ap.parse_args()
    solver = IkSolver.load()
    trajs, n = [], 0
    for t in split(make_corpus(400, 1), 1)[2]:
        trajs.append(t)
        n += len(t.p)
        if n >= args.frames:
            break

    def timed(fn, points):
        out = []
        for p in points:
            t0 = time.perf_counter()
            fn(p)
            out.append(time.perf_counter() - t0)
        return np.array(out) * 1e3

    pipe, refined = [], []
    for t in trajs:
        solver.reset()
        qs = []

        def step(p, qs=qs):
            qs.append(solver.step(p).q)

        pipe.append(timed(step, t.p))
        refined.append(np.array(qs))
    pipe = np.concatenate(pipe)
    pts = np.concatenate([t.p for t in trajs])
    anchor = timed(lambda p: closed_form_rule(p[None], np.zeros((1, 3))), pts)
    q = np.array([0.0, 0.0, 0.0, 0.6])

    def dls(p):
        nonlocal q
        q = armkin.dls(p[None], q[None])[0]

    dls_t = timed(dls, pts)
    hist, prev = _batch_windows(trajs, refined, 1000, np.random.default_rng(0), max(solver.filter_past, 2))
    batch = []
    for _ in range(5):
        t0 = time.perf_counter()
        solver.predict(hist, prev)
        batch.append((time.perf_counter() - t0) / 1000 * 1e3)
    a = float(np.median(anchor))
    print(f"{len(pts)} queries on held-out trajectories; anchor: closed form + pitch rule, median {a:.4f} ms")
    for name, t in (("pipeline (single query)", pipe), ("pure DLS (single query)", dls_t), ("closed form (anchor)",
                                                                                           anchor)):
        print(f"  {name:26s} median {np.median(t):.4f} ms  p99 {np.percentile(t, 99):.4f} ms  "
              f"ratio {np.median(t) / a:.1f}x")
    print(f"  {'pipeline (batch of 1000)':26s} per query {np.median(batch):.4f} ms  ratio {np.median(batch) / a:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
