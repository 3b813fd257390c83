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

**Samples that land, from the motion library** (`library_samples`). Of those 24 samples only the ones within
73° of upright land, and none near the paper's 7 orientations (tilted 90–180°). The shipped motion library
(`felis.learning.landing.library`) holds, on its 3 m shelf, hundreds of motions that land their own attitude (and,
mirrored, the mirror attitude), tilted up to 100°, and two tilted 120° and 122.5° (the hard drops). For each
target orientation in turn (default the paper's `TRAINING_ORIENTATIONS`) the sample is the landing candidate
whose start up-axis is nearest the target's (each used once), dropped from its own attitude and recorded; so
the samples keep the targets' order and indices (orientation 1 and 4 of experiment 1 are samples 0 and 3) and
every one of them lands. ``felis train landing --samples LIBRARY.json`` makes them on the fly (seven 2 s
rollouts, on the described cat); the shipped file, made on the cat as described until 2026-11-29 (the design
``4ms-paw``; ``design=`` picks and records on another cat)::

    python -c "from felis.learning.landing.wholebody import make_library_samples; \\
    make_library_samples('learning/weights/landing_samples_library.json', design='4ms-paw')"
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
PICK_BATCH = 16  # candidates tried at once by `library_picks`
DEFAULT_PATH = Path(__file__).parents[1] / "weights" / "landing_samples_wholebody.json"
COMMAND = ("python -c \"from felis.learning.landing.wholebody import make_wholebody_samples; "
           "make_wholebody_samples('learning/weights/landing_samples_wholebody.json')\"")
LIBRARY_COMMAND = ("python -c \"from felis.learning.landing.wholebody import make_library_samples; "
                   "make_library_samples('learning/weights/{}'{})\"")  # the file's name, the design


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
    _write_samples(out_json, doc, samples)
    return samples


def _write_samples(out_json: Path, doc: dict, samples: list[Sample]) -> None:
    """The samples file: ``doc`` as JSON and the recorded arrays beside it (``doc["arrays"]``), `load_samples`'s
    format."""
    arrays = {"vectors": np.stack([s.vectors for s in samples]),
              "heights_mm": np.stack([s.heights_mm for s in samples]), "up_z": np.stack([s.up_z for s in samples])}
    write_atomic(out_json.with_name(doc["arrays"]), lambda f: np.savez_compressed(f, **arrays), "landing samples",
                 ParameterError)
    write_atomic(out_json, json.dumps(doc, indent=1) + "\n", "landing samples", ParameterError)


# ------------------------------------------------------------------------------------------ from the library


def _up(o) -> np.ndarray:
    from felis.learning.landing.library import up_axis

    return up_axis(math.radians(float(o[0])), math.radians(float(o[1])))


def library_picks(library, height_m: float = TRAIN_HEIGHT_M, targets=None, design: str | None = None) -> list[dict]:
    """For each target (roll, pitch, yaw °; default `TRAINING_ORIENTATIONS`), the library candidate (an entry of
    the shelf for ``height_m``, or its mirror image) that starts nearest the target by up-axis and lands its own
    attitude, each used once (module doc): ``{"target", "orientation", "x", "entry", "mirrored", "angle_deg"}``;
    ``design``: tried on that cat of `felis.learning.landing.designs.DESIGNS` (default the described one).
    Whether a candidate lands is tried here (`felis.learning.landing.optimum.evaluate`, nearest first, a batch
    of `PICK_BATCH` at a time), not read from the file's flags. ``library``: a `MotionLibrary` or a library
    file."""
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.library import MotionLibrary, angles_deg, load_library
    from felis.learning.landing.library_build import candidate_drop
    from felis.learning.landing.optimum import evaluate
    from felis.learning.landing.samples import TRAINING_ORIENTATIONS

    lib = library if isinstance(library, MotionLibrary) else load_library(library)
    shelf = lib.shelf(height_m)
    if abs(shelf.height_m - float(height_m)) > 1e-6:
        raise ParameterError(f"motion library: no shelf for {height_m:g} m "
                             f"(it has {', '.join(f'{h:g}' for h in lib.heights)} m)")
    if not shelf.drops:
        raise ParameterError(f"motion library: the {height_m:g} m shelf does not record its entries' drops")
    cand_up, cand_x, _ = shelf.candidates()
    sim = design_sim(design or "cat")  # "cat": `BatchLandingSim()` itself
    used: set[int] = set()
    out: list[dict] = []
    try:
        for t in (TRAINING_ORIENTATIONS if targets is None else targets):
            a = angles_deg(_up(t), cand_up)
            order = [int(c) for c in np.argsort(a, kind="stable") if int(c) not in used]
            pick = None
            for k in range(0, len(order), PICK_BATCH):
                part = order[k:k + PICK_BATCH]
                res = evaluate(sim, [candidate_drop(shelf, c) for c in part], cand_x[part])
                pick = next((c for c, (_, v) in zip(part, res, strict=True) if v.landed), None)
                if pick is not None:
                    break
            if pick is None:
                raise ParameterError(f"motion library: no motion of the {height_m:g} m shelf lands its own attitude "
                                     f"for target {tuple(t)}")
            used.add(pick)
            d = candidate_drop(shelf, pick)
            out.append({"target": tuple(map(float, t)), "orientation": (d.roll_deg, d.pitch_deg, d.yaw_deg),
                        "x": cand_x[pick], "entry": pick // 2, "mirrored": bool(pick & 1),
                        "angle_deg": float(a[pick])})
    finally:
        sim.close()
    return out


def library_samples(library, height_m: float = TRAIN_HEIGHT_M, targets=None, design: str | None = None
                    ) -> tuple[list[Sample], list[dict]]:
    """(the samples, their picks) of `library_picks`, each dropped from its own attitude and recorded for `STEPS`
    ticks (`felis.learning.landing.samples.rollout`); ``design``: on that cat of
    `felis.learning.landing.designs.DESIGNS` (default the described one)."""
    from felis.learning.landing.evaluate import LandingSim

    picks = library_picks(library, height_m, targets, design)
    sim = LandingSim(design=design)
    samples = []
    try:
        for p in picks:
            rule = MotionRule(p["x"], float(height_m), STEPS)
            r = rollout(sim, p["orientation"], rule, float(height_m), STEPS)
            samples.append(Sample(r.orientation, r.height_m, rule, r.vectors, r.heights_mm, r.final_up_z, r.landed,
                                  r.up_z, None, air_up_z(r)))
            p["rollout"] = r
    finally:
        sim.close()
    return samples, picks


def make_library_samples(out_json: str | Path, library: str | Path | None = None, height_m: float = TRAIN_HEIGHT_M,
                         progress: Callable[[str], None] | None = None, design: str | None = None) -> list[Sample]:
    """`library_samples` for the paper's 7 orientations (on ``design``'s cat, default the described one), written
    as a samples file (.json and .npz, `load_samples`'s format)."""
    from felis.learning.landing.library import DEFAULT_LIBRARY, load_library

    out_json = Path(out_json)
    library = Path(library or DEFAULT_LIBRARY)
    lib = load_library(library)
    t0 = time.perf_counter()
    samples, picks = library_samples(lib, height_m, design=design)
    entries = []
    for s, p in zip(samples, picks, strict=True):
        r = p["rollout"]
        entries.append({"orientation": list(s.orientation), "height_m": s.height_m, "rule": s.rule.as_dict(),
                        "stands_in_for": list(p["target"]), "angle_to_target_deg": round(p["angle_deg"], 2),
                        "library_entry": p["entry"], "mirrored": p["mirrored"], "air_up_z": s.air_up_z,
                        "final_up_z": s.final_up_z, "final_tilt_deg": round(math.degrees(math.acos(max(-1.0, min(
                            1.0, s.final_up_z)))), 2), "landed": s.landed, "outcome": r.outcome.as_dict()})
        if progress:
            progress(f"{p['target']} -> {s.orientation} ({p['angle_deg']:.1f}° away): landed {s.landed}")
    npz = out_json.with_suffix(".npz")
    doc = {"format": FORMAT, "version": VERSION, "kind": "whole-body",
           "command": LIBRARY_COMMAND.format(out_json.name, "" if design is None else f", design='{design}'"),
           **({} if design is None else {"design": design}),
           "source": f"the motion library {library.name}: per target the landing motion nearest by up-axis "
           "(learning/landing/wholebody.py, library_samples)", "library_made_by": lib.meta.get("made_by", ""),
           "train_height_m": float(height_m), "steps": STEPS, "dt": DT, "arrays": npz.name,
           "wall_s": round(time.perf_counter() - t0, 1), "samples": entries}
    _write_samples(out_json, doc, samples)
    return samples
