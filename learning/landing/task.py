"""One evaluation of the landing evolution: an individual dropped from a training orientation (or a
general-stage drop), rolled out in MuJoCo and scored (f, D, S, up_z, landed); the per-worker simulation
that runs these jobs, and the task (orientations, PCA, the samples' features) built from the motion
samples. Formulas: `felis.learning.landing.train`'s module doc, "One evaluation".
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.config import TrainConfig
from felis.learning.landing.features import (
    Pca,
    flatten_features,
    logical_features,
    motion_distance,
    transition_distance,
    transition_features,
)
from felis.learning.landing.nets import fitness, landing_score
from felis.learning.landing.policy import ComplexBehaviour, SimpleBehaviour
from felis.learning.landing.samples import DT, load_samples, rollout
from felis.scenarios.verdicts import WINDOW_S

DEFAULT_SAMPLES = Path(__file__).parents[1] / "weights" / "landing_samples.json"
DIVERGED = 1e9  # D and S of a rollout whose physics diverged
GENERAL_HEIGHTS_M = (1.0, 3.0)  # the general stage's drops alternate between these heights
GENERAL_STEPS = 150  # 1.5 s: a 3 m fall (0.78 s) and the 0.5 s the landed rule watches, with room


@dataclass(frozen=True)
class Rollout:
    """What one rollout gives the scoring: segment vectors (T, J, 3), waist heights (T,) in mm, the
    upper body's up-axis z at the end, whether the drop met the `landed` rule, its `landing_score`;
    ``complete`` is False when the physics diverged."""

    vectors: np.ndarray
    heights_mm: np.ndarray
    final_up_z: float
    complete: bool = True
    landed: bool = False
    landing: float = 0.0


@dataclass(frozen=True)
class Task:
    """Everything a worker needs to score an individual on training orientation k (identical in every
    worker): orientations (roll, pitch, yaw °) and drop heights (m) per k, the rollout length, the fitness
    variant, the PCA and the samples' SF and TF."""

    orientations: tuple[tuple[float, float, float], ...]
    heights_m: tuple[float, ...]
    steps: int
    smooth_upright: bool
    pca: Pca
    sf: tuple[np.ndarray, ...]
    tf: tuple[np.ndarray, ...]
    robot: str = "cat"
    fitness: str = "eq9"
    design: str = "cat"  # a cat of `felis.learning.landing.designs.DESIGNS`

    @property
    def k(self) -> int:
        return len(self.orientations)


def sample_features(pca: Pca, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(SF, TF) of a motion's segment vectors (T, J, 3): SF = PCA(B) rows (eq. 4), TF (eq. 5–6)."""
    bits = logical_features(vectors)
    return pca.transform(flatten_features(bits)), transition_features(bits)


def fit_features(samples: Sequence[Any], dims: int) -> tuple[Pca, list[np.ndarray], list[np.ndarray]]:
    """PCA fitted on the B rows of every sample stacked (eq. 3–4), and each sample's SF and TF."""
    if not samples:
        raise ParameterError("no motion samples to fit the features on")
    bs = [flatten_features(logical_features(s.vectors)) for s in samples]
    pca = Pca.fit(np.concatenate(bs), dims)
    feats = [sample_features(pca, s.vectors) for s in samples]
    return pca, [f[0] for f in feats], [f[1] for f in feats]


def score(task: Task, k: int | tuple, r: Rollout) -> np.ndarray:
    """(f, D, S, up_z, landed) of rollout ``r`` on training orientation ``k`` (module doc); ``k`` a drop
    (roll, pitch, yaw, height) of the general stage: D = S = 0 (no motion sample to compare with)."""
    if not r.complete or len(r.heights_mm) < 2:
        up = float(r.final_up_z) if math.isfinite(r.final_up_z) else -1.0
        return np.array([0.0, DIVERGED, DIVERGED, up, 0.0])
    f = r.landing if task.fitness == "landing" else fitness(r.heights_mm, r.final_up_z, task.smooth_upright)
    if not isinstance(k, int | np.integer):
        return np.array([f, 0.0, 0.0, r.final_up_z, float(bool(r.landed))])
    sf, tf = sample_features(task.pca, r.vectors)
    return np.array([f, motion_distance(sf, task.sf[k]), transition_distance(tf, task.tf[k]), r.final_up_z,
                     float(bool(r.landed))])


def _landing(r: Any) -> float:
    """`landing_score` of a `samples.Rollout` (its outcome and per-tick up-axes)."""
    return _landing_of(r.outcome, r.up_z, r.lower_up_z)


def _landing_of(o: Any, up_z: np.ndarray, lower_up_z: np.ndarray) -> float:
    """`landing_score` of an outcome (`LandingOutcome`) with the per-tick up-axis z of upper and lower body."""
    n = len(up_z)
    if o.touchdown_s is None:
        i, clean = n - 1, 0.0
    else:
        i = min(n - 1, max(0, int(o.touchdown_s / DT)))
        clean = 1.0 if o.foot_only else min(1.0, float(o.touch_s or 0.0) / WINDOW_S)
    waist = None if o.waist_m is None else float(o.waist_m) / float(o.standing_waist_m)
    air = 0.5 * (float(up_z[i]) + float(lower_up_z[i]))
    return landing_score(air if math.isfinite(air) else -1.0, clean, o.tilt_deg, waist, bool(o.landed))


def _rollout(sim, orientation: Sequence[float], policy, height_m: float, steps: int) -> Rollout:
    """A rollout of ``steps`` ticks of 10 ms (`samples.rollout`) as the scoring needs it."""
    r = rollout(sim, orientation, policy, height_m, steps)
    if r.outcome.why == "physics diverged":
        return Rollout(r.vectors, r.heights_mm, float("nan"), complete=False)
    return Rollout(r.vectors, r.heights_mm, float(r.final_up_z), landed=bool(r.landed), landing=_landing(r))


# ---------------------------------------------------------------------------------- worker functions
# Per worker process (pool initializer, Ray's per-worker initializer, or this process when inline): one
# compiled simulation and the task, built once and reused by every job.
_WORKER: tuple[Any, Task] | None = None


def init_worker(task: Task) -> None:
    """Evaluator initializer: a `LandingSim` for ``task.robot`` and the task, kept for this process's jobs."""
    global _WORKER
    from felis.learning.landing.evaluate import LandingSim

    release_worker()
    _WORKER = (LandingSim(task.robot, design=None if task.design == "cat" else task.design), task)


def release_worker() -> None:
    """Close this process's simulation (the inline evaluator's, at the end of training)."""
    global _WORKER
    if _WORKER is not None:
        _WORKER[0].close()
        _WORKER = None


def evaluate_job(job: tuple[SimpleBehaviour | ComplexBehaviour, int | tuple]) -> np.ndarray:
    """One job (behaviour, orientation index k, or a general-stage drop (roll, pitch, yaw, height)) →
    (f, D, S, up_z, landed); needs `init_worker` in this process."""
    if _WORKER is None:
        raise RuntimeError("evaluate_job needs init_worker(task) in this process first")
    sim, task = _WORKER
    behaviour, k = job
    return score(task, k, run_rollout(sim, task, behaviour, k))


# Batched (issue 21): per worker a `BatchLandingSim` with the motion sensors; a whole list of jobs is one batch.
_BATCH: tuple[Any, Task, Any] | None = None


def init_batch_worker(task: Task) -> None:
    """Evaluator initializer for `evaluate_batch`: a `BatchLandingSim` with the motion sensors
    (`features.motion_sensors`); rollout threads: every core in the main process (the inline evaluator),
    one in a pool's or Ray's worker process (the processes are the parallelism there)."""
    global _BATCH
    import multiprocessing

    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.features import SensorMotion, motion_sensors

    release_batch_worker()
    nthread = None if multiprocessing.parent_process() is None else 1
    if task.design == "cat":
        sim = BatchLandingSim(task.robot, nthread=nthread, sensors=motion_sensors)
    else:  # another cat of the design study: its servos, paws and step, with the motion sensors
        from felis.learning.landing.designs import design_sim

        sim = design_sim(task.design, nthread=nthread, sensors=motion_sensors)
    _BATCH = (sim, task, SensorMotion(sim.batch.model))


def release_batch_worker() -> None:
    global _BATCH
    if _BATCH is not None:
        _BATCH[0].close()
        _BATCH = None


def evaluate_batch(jobs: Sequence[tuple[SimpleBehaviour | ComplexBehaviour, int | tuple]]) -> list[np.ndarray]:
    """`evaluate_job` for a list of jobs at once, as one batch of `felis.sim.batch.DropBatch` (every cat stepped
    together, each job's behaviour evaluated for its rows in one numpy call per tick): the same (f, D, S, up_z,
    landed) per job as the sequential path (its physics bit for bit; the nets' batched rounding ~1e-13).
    Needs `init_batch_worker`."""
    if _BATCH is None:
        raise RuntimeError("evaluate_batch needs init_batch_worker(task) in this process first")
    from felis.controllers.landing import LandingBatch
    from felis.learning.landing.evaluate import outcome_of
    from felis.scenarios.drop import Drop

    sim, task, motion = _BATCH
    if not jobs:
        return []
    drops, steps, policies, index, ids = [], [], [], [], {}
    for behaviour, k in jobs:
        if isinstance(k, int | np.integer):
            drops.append(Drop(*task.orientations[k], task.heights_m[k]))
            steps.append(task.steps)
        else:
            drops.append(Drop(*k[:3], k[3]))
            steps.append(GENERAL_STEPS)
        if id(behaviour) not in ids:
            ids[id(behaviour)] = len(policies)
            policies.append(behaviour)
        index.append(ids[id(behaviour)])
    B, T = len(jobs), max(steps)
    J = len(motion.index.start)
    vec = np.zeros((B, T + 1, J, 3))
    heights = np.zeros((B, T + 1))
    up = np.zeros((B, T + 1))
    lower = np.zeros((B, T + 1))
    a_up, a_waist = sim.batch.adr["up_z"], sim.batch.adr["waist_z"]

    def keep(rows: np.ndarray, sd: np.ndarray, k: int) -> None:  # the state the controller reads at tick k
        vec[rows, k] = motion.vectors(sd)
        heights[rows, k] = 1000.0 * sd[:, a_waist]
        up[rows, k] = sd[:, a_up]
        lower[rows, k] = motion.lower_up_z(sd)

    _, sens0 = sim.batch.initial(drops)
    keep(np.arange(B), sens0, 0)
    results = sim.batch.run(drops, LandingBatch(sim.spec, policies, np.array(index)), sim.standing_waist_m,
                            ticks=steps, record=lambda k, st, sd, rows: keep(rows, sd[:, -1], k + 1))
    out = []
    for i, ((_, k), d, r) in enumerate(zip(jobs, drops, results, strict=True)):
        n = steps[i]
        if r.diverged:
            roll = Rollout(vec[i, :n], heights[i, :n], float("nan"), complete=False)
        else:
            o = outcome_of(d, "", r, sim.standing_waist_m)
            roll = Rollout(vec[i, :n], heights[i, :n], float(r.final_up_z), landed=bool(o.landed),
                           landing=_landing_of(o, up[i, :n], lower[i, :n]))
        out.append(score(task, k, roll))
    return out


def run_rollout(sim, task: Task, policy, k: int | tuple) -> Rollout:
    """The rollout of ``policy`` on training orientation ``k`` of ``task`` (`samples.rollout`, the
    samples' own recording, for ``task.steps`` ticks), or on a general-stage drop ``k`` = (roll, pitch,
    yaw, height) for `GENERAL_STEPS` ticks."""
    if not isinstance(k, int | np.integer):
        return _rollout(sim, k[:3], policy, k[3], GENERAL_STEPS)
    return _rollout(sim, task.orientations[k], policy, task.heights_m[k], task.steps)


# ------------------------------------------------------------------------------------------ samples


def load_task_samples(cfg: TrainConfig, samples: Sequence[Any] | None) -> list[Any]:
    """``samples`` as given, else the samples file ``cfg.samples`` (default `DEFAULT_SAMPLES`); a motion library
    file gives its landing motions nearest the paper's 7 orientations, recorded now
    (`felis.learning.landing.wholebody.library_samples`)."""
    if samples is not None:
        return list(samples)
    from felis.learning.landing.library import is_library_file

    if cfg.samples and is_library_file(cfg.samples):
        from felis.learning.landing.wholebody import library_samples

        return library_samples(cfg.samples)[0]
    return list(load_samples(cfg.samples or DEFAULT_SAMPLES))


def samples_fingerprint(samples: Sequence[Any]) -> str:
    """CRC-32 over every sample's orientation, height and segment vectors: a checkpoint is resumed only
    on the samples it was trained on."""
    crc = 0
    for s in samples:
        head = np.array([*map(float, s.orientation), float(s.height_m)])
        v = np.ascontiguousarray(np.asarray(s.vectors, dtype=np.float64))
        for part in (head, np.array(v.shape, np.int64), v):
            crc = zlib.crc32(part.tobytes(), crc)
    return f"{len(samples)}:{crc:08x}"


def make_task(cfg: TrainConfig, samples: Sequence[Any]) -> tuple[Task, list[int]]:
    """The task of ``cfg`` on ``samples`` and the training orientations (indices into ``samples``)."""
    if not samples:
        raise ParameterError("the motion samples file holds no samples")
    idx = list(cfg.orientations) or list(range(len(samples)))
    bad = [i for i in idx if i >= len(samples)]
    if bad:
        raise ParameterError(f"training orientation {bad[0]} is out of range: the samples hold {len(samples)} "
                             f"orientations (0…{len(samples) - 1})")
    pca, sfs, tfs = fit_features(samples, cfg.pca_dims)
    for i in idx:
        h = float(samples[i].height_m)
        if not (math.isfinite(h) and h > 0):
            raise ParameterError(f"motion sample {i} has drop height {h}; needs a positive number of metres")
    task = Task(orientations=tuple(tuple(float(a) for a in samples[i].orientation) for i in idx),
                heights_m=tuple(float(samples[i].height_m) for i in idx), steps=cfg.steps,
                smooth_upright=cfg.smooth_upright, pca=pca, sf=tuple(sfs[i] for i in idx),
                tf=tuple(tfs[i] for i in idx), fitness=cfg.fitness, design=cfg.design)
    return task, idx
