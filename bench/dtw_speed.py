"""Cost of the motion similarity (seed 000 §4) against the 200-step rollout it scores, in the same run.

    python bench/dtw_speed.py [--steps 200] [--dims 8] [--repeats 15] [--height 3.0]

Anchor: a rollout of the cat through `MujocoRobot`, ``advance(0.01)`` ``--steps`` times (1 kHz physics),
released upside-down ``--height`` m above the floor as in the paper's task (0: from the standing
start pose). Timed against it, on sequences of ``--steps`` frames and ``--dims`` PCA dims:

- one ``dtw`` (vectorised anti-diagonal fill, with its Euclidean cost matrix);
- ``motion_distance`` D (eq. 7, both DTW directions as the paper writes it);
- the whole scoring of a rollout: recording `body_frame` at each step, logical features, PCA, TF, D, S.

Rounds interleave (rollout, then the similarity timings) so both see the same machine load; each ratio
is the median over rounds of (similarity ÷ rollout). Goal (issue 5): one 200-step DTW ≤ 10% of the
rollout. The plain-Python ``dtw_reference`` is timed once for scale.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    from felis.learning.landing.features import (
        FEATURE_BODIES,
        MotionRecorder,
        Pca,
        dtw,
        dtw_reference,
        flatten_features,
        logical_features,
        motion_distance,
        transition_distance,
        transition_features,
    )
    from felis.sim import MujocoRobot
    from felis.sim.scenarios import drop
    from felis.spec import load_spec

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--dims", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--height", type=float, default=3.0)
    args = ap.parse_args()

    robot = MujocoRobot(load_spec("cat"))
    robot.connect()
    robot.arm()
    rng = np.random.default_rng(0)
    sf_a, sf_b = rng.normal(size=(args.steps, args.dims)), rng.normal(size=(args.steps, args.dims))
    pca = Pca.fit(flatten_features(rng.random((400, len(FEATURE_BODIES), 3)) < 0.5), args.dims)
    sample_sf, sample_tf = sf_b, transition_features(rng.random((args.steps, len(FEATURE_BODIES), 3)) < 0.5)

    def rollout() -> float:
        robot.reset()
        if args.height > 0:
            drop(robot, args.height, roll=180.0)
        t0 = time.perf_counter()
        for _ in range(args.steps):
            robot.advance(0.01)
        return time.perf_counter() - t0

    def timed(fn, n: int = 5) -> float:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        return (time.perf_counter() - t0) / n

    def record() -> MotionRecorder:
        rec = MotionRecorder(robot.model)
        for _ in range(args.steps):
            rec.record(robot.data)
        return rec

    def score(rec: MotionRecorder) -> tuple[float, float]:
        bits = logical_features(rec.vectors())
        sf = pca.transform(flatten_features(bits))
        return motion_distance(sf, sample_sf), transition_distance(transition_features(bits), sample_tf)

    rollout()  # warm-up
    dtw(sf_a, sf_b)
    r_dtw, r_d, r_score, t_roll, t_dtw, t_d, t_score, t_rec = [], [], [], [], [], [], [], []
    for _ in range(args.repeats):
        roll = rollout()
        one, both = timed(lambda: dtw(sf_a, sf_b)), timed(lambda: motion_distance(sf_a, sf_b))
        rec_s = timed(record)
        rec = record()
        scoring = rec_s + timed(lambda rec=rec: score(rec))
        t_roll.append(roll)
        t_dtw.append(one)
        t_d.append(both)
        t_score.append(scoring)
        t_rec.append(rec_s)
        r_dtw.append(one / roll)
        r_d.append(both / roll)
        r_score.append(scoring / roll)
    ref = timed(lambda: dtw_reference(sf_a, sf_b), 1)

    def ms(x: list[float] | float) -> str:
        return f"{1e3 * (statistics.median(x) if isinstance(x, list) else x):8.3f} ms"

    start = f"dropped upside-down from {args.height:g} m" if args.height > 0 else "from the start pose"
    print(f"anchor: {args.steps}-step cat rollout (advance 0.01 s, 1 kHz physics) {start}: {ms(t_roll)}")
    print(f"  {'dtw, one direction':38s} {ms(t_dtw)}  ratio {100 * statistics.median(r_dtw):5.1f}%  (goal ≤ 10%)")
    print(f"  {'motion_distance D (eq. 7, both ways)':38s} {ms(t_d)}  ratio {100 * statistics.median(r_d):5.1f}%")
    print(f"  {'recording body_frame at each step':38s} {ms(t_rec)}  ratio "
          f"{100 * statistics.median(t_rec) / statistics.median(t_roll):5.1f}%")
    print(f"  {'scoring: record + features + D + S':38s} {ms(t_score)}  ratio "
          f"{100 * statistics.median(r_score):5.1f}%")
    print(f"  {'dtw_reference (plain Python, once)':38s} {ms(ref)}  ratio "
          f"{100 * ref / statistics.median(t_roll):5.1f}%")
    print(f"({args.steps}x{args.steps} frames, {args.dims} dims; medians over {args.repeats} interleaved rounds)")
    robot.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
