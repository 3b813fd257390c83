"""Whole-body motion samples (seed 000 §6.5 done for this robot, issue 21).

The paper's samples move the spine only (`felis.learning.landing.samples`), which turns this cat at most
~30° in a 1 m fall. These samples are the per-drop optimum (`felis.learning.landing.optimum`: loops of
spine, tail and legs, and a touchdown posture, found by CMA-ES) for orientations that cover the sphere,
dropped from the paper's 3 m and recorded for its 200 ticks, in the samples' own format (`load_samples`
reads them; each sample's ``rule`` is a `MotionRule`), so training can imitate them (``felis train
landing --samples FILE``).

**Orientations** (`sphere_orientations`): `N_ORIENTATIONS` up-axis directions on a Fibonacci lattice of the
sphere (every start tilt from near upright to upside down, evenly by area), each as (roll, pitch, 0): with
R = Ry(pitch)·Rx(roll) the body's up-axis is (cos r·sin p, −sin r, cos r·cos p), so roll = asin(−u_y) and
pitch = atan2(u_x, u_z). Yaw turns only the heading, which a fall does not feel.

**Regenerate** (deterministic per seed), one line::

    python -c "from felis.learning.landing.wholebody import make_wholebody_samples; \\
    make_wholebody_samples('learning/weights/landing_samples_wholebody.json')"
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.files import write_atomic
from felis.learning.landing.optimum import GENERATIONS, POPULATION, MotionRule, optimise
from felis.learning.landing.samples import (
    DT,
    FORMAT,
    STEPS,
    TRAIN_HEIGHT_M,
    VERSION,
    Sample,
    air_up_z,
    rollout,
)
from felis.scenarios.drop import Drop

N_ORIENTATIONS = 24
DEFAULT_PATH = Path(__file__).parents[1] / "weights" / "landing_samples_wholebody.json"
COMMAND = ("python -c \"from felis.learning.landing.wholebody import make_wholebody_samples; "
           "make_wholebody_samples('learning/weights/landing_samples_wholebody.json')\"")


def sphere_orientations(n: int = N_ORIENTATIONS) -> list[tuple[float, float, float]]:
    """(roll, pitch, 0) degrees for ``n`` up-axes on a Fibonacci lattice of the sphere (module doc)."""
    out = []
    golden = math.pi * (3.0 - math.sqrt(5.0))
    for i in range(n):
        z = 1.0 - 2.0 * (i + 0.5) / n
        r = math.sqrt(max(0.0, 1.0 - z * z))
        ux, uy = r * math.cos(golden * i), r * math.sin(golden * i)
        roll = math.degrees(math.asin(max(-1.0, min(1.0, -uy))))
        pitch = math.degrees(math.atan2(ux, z))
        out.append((round(roll, 2), round(pitch, 2), 0.0))
    return out


def make_wholebody_samples(out_json: str | Path = DEFAULT_PATH, seed: int = 0, n: int = N_ORIENTATIONS,
                           generations: int = GENERATIONS, population: int = POPULATION, restarts: int = 1,
                           workers: int | None = None, progress: Callable[[str], None] | None = None
                           ) -> list[Sample]:
    """Optimise one whole-body motion per `sphere_orientations` entry from `TRAIN_HEIGHT_M` (all at once,
    batched), record each for `STEPS` ticks, write the samples (.json and .npz, `load_samples`'s format)."""
    from felis.learning.landing.evaluate import LandingSim

    out_json = Path(out_json)
    t0 = time.perf_counter()
    orientations = sphere_orientations(n)
    drops = [Drop(r, p, y, TRAIN_HEIGHT_M) for r, p, y in orientations]
    best = optimise(drops, generations=generations, population=population, restarts=restarts, seed=seed,
                    workers=workers, progress=(lambda g, k: progress(f"generation {g}: {k} orientations searching"))
                    if progress else None)
    sim = LandingSim()
    samples, entries = [], []
    try:
        for o, b in zip(orientations, best, strict=True):
            rule = MotionRule(np.array(b.x), TRAIN_HEIGHT_M, STEPS)
            r = rollout(sim, o, rule, TRAIN_HEIGHT_M, STEPS)
            s = Sample(r.orientation, r.height_m, rule, r.vectors, r.heights_mm, r.final_up_z, r.landed, r.up_z,
                       b.score, air_up_z(r))
            samples.append(s)
            entries.append({"orientation": list(r.orientation), "height_m": r.height_m, "rule": rule.as_dict(),
                            "score": round(b.score, 4), "air_up_z": s.air_up_z, "final_up_z": r.final_up_z,
                            "final_tilt_deg": round(math.degrees(math.acos(max(-1.0, min(1.0, r.final_up_z)))), 2),
                            "landed": r.landed, "optimum_landed": b.landed, "rollouts": b.rollouts,
                            "outcome": r.outcome.as_dict()})
            if progress:
                progress(f"{o}: landed {r.landed}, air up_z {s.air_up_z:.2f}")
    finally:
        sim.close()
    npz = out_json.with_suffix(".npz")
    doc = {"format": FORMAT, "version": VERSION, "kind": "whole-body", "command": COMMAND,
           "source": "seed 000 §6.5 with whole-body motions (issue 21): learning/landing/optimum.py",
           "seed": int(seed), "generations": generations, "population": population, "restarts": restarts,
           "train_height_m": TRAIN_HEIGHT_M, "steps": STEPS, "dt": DT, "objective": "optimum.score (3*landed + "
           "0.5*feet only + (1 - tilt at touchdown/180) + (1 - tilt 0.5 s later/180))", "arrays": npz.name,
           "wall_s": round(time.perf_counter() - t0, 1), "samples": entries}
    arrays = {"vectors": np.stack([s.vectors for s in samples]),
              "heights_mm": np.stack([s.heights_mm for s in samples]), "up_z": np.stack([s.up_z for s in samples])}
    write_atomic(npz, lambda f: np.savez_compressed(f, **arrays), "landing samples", ParameterError)
    write_atomic(out_json, json.dumps(doc, indent=1) + "\n", "landing samples", ParameterError)
    return samples
