"""Evolution of the landing controller: simple behaviours per orientation, then the compose net (seed 000 §5–6).

Source: ``seeds/000_d27ba58563dbcb8e.txt`` §5 (gene units, crossover, elimination; "create a population,
compute fitness, crossover and mutate, repeat"), §6.4 (eqs. 9–11), §6.5 (motion samples), §6.6 (the
experiments). Nets, operators and ranking live in `felis.learning.landing.nets`, features and similarity
in `felis.learning.landing.features`; this module is the loop around them.

**Features.** A PCA (`Pca`, ``pca_dims`` components) is fitted on the logical features B of every motion
sample (all orientations in the samples file, eq. 3–4); each training sample k then has SF_k (eq. 4) and
TF_k (eq. 5–6).

**One evaluation** (individual, training orientation k): a rollout of ``steps`` ticks at 100 Hz from the
sample's orientation and height (`landing_samples.rollout`, the recording the samples were made with; any
other length through `_rollout`, the same recording) gives the waist heights (mm), the segment vectors
and the upper body's up-axis z at the end; then

    f = eq. 9 × upright(up_z)    D = eq. 7 (SF, SF_k)    S = eq. 8 (TF, TF_k)

(`landing_nets.fitness`; ``smooth_upright`` uses its ramp), and, for the record only, whether the drop
meets the issue's `landed` rule (`felis.sim.drops`: feet only for 0.5 s after touchdown, tilt ≤ 30°,
waist up). A rollout whose physics diverged gets f = 0 and D = S = `DIVERGED` (worse than any real
motion). The marks of one evaluation are (f, D, S, up_z, landed).

**Simple stage.** One population of simple behaviours per training orientation. Each generation: all
individuals of all orientations are evaluated in one `Evaluator.map` call; each population is ranked by
eq. 10 (`rank_simple`; with ``use_similarity=False`` by f alone, the paper's experiment 1, §6.6.1); the
next population is

    elites (the best ``n_elite``, unchanged, best first)
    + children: parent a by tournament among the survivors of elimination; with probability
      ``p_crossover`` a second parent b and `crossover_simple` (the fitter first), else a copy of a;
      then `mutate_simple`
    + immigrants: `eliminate_and_immigrate` drops the worst ``n_eliminate`` and adds random individuals (§5)

so the population keeps its size and the previous best is always its first member. A generation is a
success for orientation k when its best individual ends upright (up_z ≥ cos 30°) after coming down
(eq. 9's H is not empty, f > 0); "generations to the first success" (1-based) is reported per orientation,
and beside it the generation whose best first meets the stricter `landed` rule. (From 3 m a random net
often ends upright after rolling over on the floor, so the first number is usually 1; the second is the
one that tells a landing.)

**Complex stage.** The best simple behaviour of each orientation is frozen; a population of compose
units evolves. Each complex behaviour (`ComplexBehaviour`) is evaluated on every training orientation,
(N, K, 3) marks ranked by eq. 11 (`rank_complex`); breeding as above with `mutate` / `crossover` /
`random_unit("compose")`. Success: the best ends upright (and, for the landing count, lands) on every
orientation.

**One net** (``one_net=True``, §6.6.2's baseline). One population of simple behaviours, each evaluated on
every training orientation and ranked by eq. 11 like the compose units, for ``generations_simple +
generations_complex`` generations: the same number of rollouts as simple then complex.

**Landing fitness** (``fitness="landing"``, ours). Eq. 9 rewards a steady, high waist and an upright body
at the end, not feet-first contact; nets trained on it learn to hit the floor body first and roll back
up, which the issue's `landed` rule rejects. `landing_nets.landing_score` ∈ [0, 5] gives one point per
clause of that rule, each with partial credit: the mean up-axis z at touchdown (air righting), the share
of the 0.5 s window with only feet on the floor, the tilt at its end against 30°, the waist against half
its standing height, and 1 if it landed. D and S still rank ties (eq. 10).

**General stage** (``generations_general`` > 0, ours). The paper's policy composes behaviours made for 7
orientations; it never sees the rest of the sphere, and from 3 m none of our 7 orientations can be righted
at the XL330's speed (docs/landing.md). So a last stage evolves one simple behaviour on new random drops
every generation (`general_drops`: ``general_drops`` of them, 1 m and 3 m in turn, start tilt at most
``general_max_tilt_deg``), seeded with one that holds still (`still`: the passive baseline, so the stage
starts no worse than doing nothing), the best simple behaviour of each orientation, and random ones. It is
ranked by drops landed first, then mean fitness (`_general_generation`), and its best is the policy.

**Determinism.** All randomness comes from one ``np.random.default_rng(seed)`` in this process, drawn in a
fixed order; workers only run deterministic rollouts, so results are identical whatever the evaluator
(inline, any number of processes, Ray). After every generation a checkpoint ``<workdir>/checkpoint.npz``
(no pickle, replaced atomically) holds the populations still to be evaluated, the frozen behaviours, the
generator's state (``bit_generator.state`` as JSON) and the curves; ``resume=True`` continues from it and
gives bit-identical results to an uninterrupted run.

**Outputs.** ``out_path`` (the complex policy, or the one simple behaviour of the one-net or general
stage, `save_policy`), ``<stem>.results.json`` (config, curves per
generation, generations to the first success, final per-orientation marks) and ``<stem>.curves.png``.
"""

from __future__ import annotations

import json
import math
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import CheckpointError, ParameterError
from felis.learning.common.evaluator import Evaluator, make_evaluator
from felis.learning.landing.features import (
    Pca,
    flatten_features,
    logical_features,
    motion_distance,
    transition_distance,
    transition_features,
)
from felis.learning.landing.nets import (
    DROP_HEIGHT_M,
    LANDING_HEIGHT_MM,
    MAX_HIDDEN,
    PARTS,
    UPRIGHT_COS,
    ComplexBehaviour,
    GeneUnit,
    SimpleBehaviour,
    crossover,
    crossover_simple,
    eliminate_and_immigrate,
    fitness,
    landing_score,
    mutate,
    mutate_simple,
    random_simple,
    random_unit,
    rank_complex,
    rank_simple,
    save_policy,
)
from felis.learning.landing.samples import DT, STEPS, load_samples, rollout
from felis.sim.drops import WINDOW_S

RATE_HZ = 100.0  # §6.4: steps of 1/100 s (`STEPS` = 200 of them)
DEFAULT_SAMPLES = Path(__file__).parents[1] / "weights" / "landing_samples.json"
DIVERGED = 1e9  # D and S of a rollout whose physics diverged
CHECKPOINT = "checkpoint.npz"
CHECKPOINT_FORMAT = "felis-landing-checkpoint"
CHECKPOINT_VERSION = 2
META_KEY = "__meta__"
RUNTIME_FIELDS = ("workers", "ray_address")  # settings that never change the numbers
FITNESSES = ("eq9", "landing")
GENERAL_HEIGHTS_M = (1.0, 3.0)  # the general stage's drops alternate between these heights
GENERAL_STEPS = 150  # 1.5 s: a 3 m fall (0.78 s) and the 0.5 s the landed rule watches, with room

Progress = Callable[[str, int, int, dict], None]



# ------------------------------------------------------------------------------------------- config


@dataclass(frozen=True)
class TrainConfig:
    """Settings of `train_landing`.

    ``population``: individuals per population (one population per training orientation in the simple
    stage; compose units in the complex stage). ``generations_simple`` / ``generations_complex``: the
    length of each stage. ``elite_frac``: the best floor(frac·N) (at least 1) pass unchanged;
    ``elimination_frac``: the worst floor(frac·N) are replaced by random immigrants (§5). ``tournament``:
    tournament size for picking parents among the survivors; ``p_crossover``: chance a child has two
    parents. ``p_weight``, ``sigma``, ``p_structure``, ``max_hidden``: `landing_nets.mutate`'s settings
    (``max_hidden`` also bounds random units). ``pca_dims``: components of the PCA (eq. 4).
    ``orientations``: indices into the samples file (empty: all of them). ``use_similarity``: rank by
    (f, D, S) (eq. 10); False ranks by f alone (§6.6.1, experiment 1). ``smooth_upright``: f uses the
    upright ramp instead of the 0/1 test. ``steps``: rollout length in 10 ms ticks (§6.4: 200).
    ``samples``: motion samples file (`landing_samples.load_samples`; "" = `DEFAULT_SAMPLES`).
    ``fitness``: "eq9" (the paper's eq. 9 × upright, `landing_nets.fitness`) or "landing" (our
    `landing_nets.landing_score`, partial credit for each clause of the `landed` rule). ``one_net``: instead
    of simple then complex, one simple behaviour evolves on every training orientation at once for
    ``generations_simple + generations_complex`` generations, ranked by eq. 11 (§6.6.2's baseline).
    ``generations_general`` (0 = none): a last stage, ours, that evolves one simple behaviour on
    ``general_drops`` random drops per generation (new ones each generation, from 1 m and 3 m in turn,
    start tilt at most ``general_max_tilt_deg``), seeded with the previous stages' simple behaviours and
    one that holds still (passive); its best is then the policy.
    ``workers``/``ray_address``: where rollouts run (`make_evaluator`); they never change the results.
    """

    seed: int = 0
    population: int = 24
    generations_simple: int = 200
    generations_complex: int = 100
    elite_frac: float = 0.1
    elimination_frac: float = 0.2
    tournament: int = 2
    p_crossover: float = 0.5
    p_weight: float = 0.1
    sigma: float = 0.1
    p_structure: float = 0.05
    max_hidden: int = MAX_HIDDEN
    pca_dims: int = 8
    orientations: tuple[int, ...] = ()
    use_similarity: bool = True
    smooth_upright: bool = False
    steps: int = STEPS
    samples: str = ""
    fitness: str = "eq9"
    one_net: bool = False
    generations_general: int = 0
    general_drops: int = 16
    general_max_tilt_deg: float = 180.0
    workers: int | None = None
    ray_address: str | None = None

    def __post_init__(self):
        object.__setattr__(self, "orientations", tuple(self.orientations) if isinstance(
            self.orientations, list | tuple) else self.orientations)
        self.check()

    @property
    def n_elite(self) -> int:
        return max(1, int(math.floor(self.elite_frac * self.population + 1e-9)))

    @property
    def n_eliminate(self) -> int:
        return int(math.floor(self.elimination_frac * self.population + 1e-9))  # as eliminate_and_immigrate

    def check(self) -> TrainConfig:
        """One-line `ParameterError` for the first bad setting; returns the config."""
        def integer(name: str, lo: int, none_ok: bool = False) -> None:
            v = getattr(self, name)
            if v is None and none_ok:
                return
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < lo:
                raise ParameterError(f"training {name} must be an integer ≥ {lo}, got {v!r}")

        def fraction(name: str) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0.0 <= v <= 1.0:
                raise ParameterError(f"training {name} must be a number in [0, 1], got {v!r}")

        integer("seed", 0)
        integer("population", 2)
        integer("generations_simple", 1)
        integer("generations_complex", 1)
        integer("generations_general", 0)
        integer("general_drops", 1)
        t = self.general_max_tilt_deg
        if isinstance(t, bool) or not isinstance(t, int | float) or not 0.0 < t <= 180.0:
            raise ParameterError(f"training general_max_tilt_deg must be a number in (0, 180], got {t!r}")
        integer("tournament", 1)
        integer("max_hidden", 1)
        integer("pca_dims", 1)
        integer("steps", 2)
        integer("workers", 1, none_ok=True)
        for name in ("elite_frac", "elimination_frac", "p_crossover", "p_weight", "p_structure"):
            fraction(name)
        if isinstance(self.sigma, bool) or not isinstance(self.sigma, int | float) or not (
                math.isfinite(self.sigma) and self.sigma >= 0):
            raise ParameterError(f"training sigma must be a finite number ≥ 0, got {self.sigma!r}")
        if self.n_elite + self.n_eliminate > self.population - 1:
            raise ParameterError(f"training keeps {self.n_elite} elites and replaces {self.n_eliminate} of "
                                 f"{self.population} individuals: leave room for at least one child (lower "
                                 "elite_frac or elimination_frac)")
        o = self.orientations
        if not isinstance(o, tuple) or any(isinstance(i, bool) or not isinstance(i, int | np.integer) or i < 0
                                           for i in o):
            raise ParameterError(f"training orientations must be sample indices (integers ≥ 0), got {o!r}")
        if len(set(o)) != len(o):
            raise ParameterError(f"training orientations {list(o)} name a sample twice")
        if self.fitness not in FITNESSES:
            raise ParameterError(f"training fitness must be one of {', '.join(FITNESSES)}, got {self.fitness!r}")
        for name in ("use_similarity", "smooth_upright", "one_net"):
            if not isinstance(getattr(self, name), bool):
                raise ParameterError(f"training {name} must be true or false, got {getattr(self, name)!r}")
        if not isinstance(self.samples, str):
            raise ParameterError(f"training samples must be a file path (text), got {self.samples!r}")
        if self.ray_address is not None and (not isinstance(self.ray_address, str) or not self.ray_address.strip()):
            raise ParameterError(f"training ray_address must be 'local' or a cluster address, got {self.ray_address!r}")
        return self

    def as_dict(self) -> dict:
        d = asdict(self)
        d["orientations"] = [int(i) for i in self.orientations]
        return d

    def results_settings(self) -> dict:
        """The settings that decide the numbers (all but `RUNTIME_FIELDS`)."""
        return {k: v for k, v in self.as_dict().items() if k not in RUNTIME_FIELDS}


# ------------------------------------------------------------------------------------------ the task


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
    """`landing_score` of a `landing_samples.Rollout` (its outcome and per-tick up-axes)."""
    o = r.outcome
    n = len(r.up_z)
    if o.touchdown_s is None:
        i, clean = n - 1, 0.0
    else:
        i = min(n - 1, max(0, int(o.touchdown_s / DT)))
        clean = 1.0 if o.foot_only else min(1.0, float(o.touch_s or 0.0) / WINDOW_S)
    waist = None if o.waist_m is None else float(o.waist_m) / float(o.standing_waist_m)
    air = 0.5 * (float(r.up_z[i]) + float(r.lower_up_z[i]))
    return landing_score(air if math.isfinite(air) else -1.0, clean, o.tilt_deg, waist, bool(o.landed))


def _rollout(sim, orientation: Sequence[float], policy, height_m: float, steps: int) -> Rollout:
    """A rollout of ``steps`` ticks of 10 ms (`landing_samples.rollout`) as the scoring needs it."""
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
    _WORKER = (LandingSim(task.robot), task)


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


def run_rollout(sim, task: Task, policy, k: int | tuple) -> Rollout:
    """The rollout of ``policy`` on training orientation ``k`` of ``task`` (`landing_samples.rollout`, the
    samples' own recording, for ``task.steps`` ticks), or on a general-stage drop ``k`` = (roll, pitch,
    yaw, height) for `GENERAL_STEPS` ticks."""
    if not isinstance(k, int | np.integer):
        return _rollout(sim, k[:3], policy, k[3], GENERAL_STEPS)
    return _rollout(sim, task.orientations[k], policy, task.heights_m[k], task.steps)


# ------------------------------------------------------------------------------------------ samples


def _load_samples(cfg: TrainConfig, samples: Sequence[Any] | None) -> list[Any]:
    if samples is not None:
        return list(samples)
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
                tf=tuple(tfs[i] for i in idx), fitness=cfg.fitness)
    return task, idx


# ---------------------------------------------------------------------------------------- breeding


def _tournament(kept: Sequence[int], pos: np.ndarray, size: int, rng: np.random.Generator) -> int:
    """The best (lowest rank position) of ``size`` survivors drawn uniformly with replacement."""
    picks = [kept[int(rng.integers(len(kept)))] for _ in range(size)]
    return min(picks, key=lambda i: pos[i])


def next_generation(pop: Sequence[Any], order: np.ndarray, score_: np.ndarray, cfg: TrainConfig,
                    rng: np.random.Generator, make_random: Callable[[np.random.Generator], Any],
                    cross: Callable[[Any, Any, np.random.Generator], Any],
                    mut: Callable[[Any, np.random.Generator], Any]) -> list[Any]:
    """Elites (best first) + children + immigrants (module doc); the size stays len(pop)."""
    n = len(pop)
    pos = np.empty(n, dtype=int)
    pos[order] = np.arange(n)
    elites = [pop[i] for i in order[:cfg.n_elite]]
    rest = eliminate_and_immigrate(list(range(n)), score_, cfg.elimination_frac, rng, make_random)
    kept = list(rest[:n - cfg.n_eliminate])  # survivors' indices, then the immigrants
    immigrants = rest[n - cfg.n_eliminate:]
    children = []
    for _ in range(n - len(elites) - len(immigrants)):
        a = _tournament(kept, pos, cfg.tournament, rng)
        if rng.random() < cfg.p_crossover:
            b = _tournament(kept, pos, cfg.tournament, rng)
            if pos[b] < pos[a]:
                a, b = b, a
            child = cross(pop[a], pop[b], rng)
        else:
            child = pop[a]
        children.append(mut(child, rng))
    return elites + children + list(immigrants)


def _mutation_kw(cfg: TrainConfig) -> dict:
    return {"p_weight": cfg.p_weight, "sigma": cfg.sigma, "p_structure": cfg.p_structure,
            "max_hidden": cfg.max_hidden}


def breed_simple(pop, order, score_, cfg, rng):
    kw = _mutation_kw(cfg)
    return next_generation(pop, order, score_, cfg, rng, lambda r: random_simple(r, cfg.max_hidden),
                           crossover_simple, lambda b, r: mutate_simple(b, r, **kw))


def breed_compose(pop, order, score_, cfg, rng):
    kw = _mutation_kw(cfg)
    return next_generation(pop, order, score_, cfg, rng, lambda r: random_unit("compose", r, cfg.max_hidden),
                           crossover, lambda u, r: mutate(u, r, **kw))


def rank_marks(marks: np.ndarray, use_similarity: bool) -> tuple[np.ndarray, np.ndarray]:
    """`rank_simple` (N, 3+) or `rank_complex` (N, K, 3+) on (f, D, S); by f alone (D = S = 0) when
    ``use_similarity`` is False."""
    m = np.array(marks[..., :3], dtype=float)
    if not use_similarity:
        m[..., 1:] = 0.0
    return rank_simple(m) if m.ndim == 2 else rank_complex(m)


# ------------------------------------------------------------------------------------------ state


def _is_success(marks: np.ndarray) -> bool:
    """(f, D, S, up_z, landed) of a success: upright at the end (up_z ≥ cos 30°) and f > 0, i.e. the waist came
    below 500 mm and stayed off the floor (eq. 9's H not empty, mean > 0)."""
    return bool(marks[3] >= UPRIGHT_COS and marks[0] > 0.0)


@dataclass
class _State:
    stage: str  # "simple", "complex", "one" (one-net), "general" or "done"
    generation: int  # generations done in this stage
    simple: list[list[SimpleBehaviour]]  # per orientation: the population to evaluate next (elites first);
    # in the "one" and "general" stages a single population
    frozen: list[SimpleBehaviour] | None  # the complex stage's simple behaviours
    compose: list[GeneUnit] | None  # the compose population to evaluate next (elites first)
    rng: np.random.Generator
    history: dict


def _new_history(k: int) -> dict:
    cols = ("best_f", "best_D", "best_S", "best_up_z", "median_f", "median_D", "median_S", "best_success",
            "best_landed", "n_upright", "n_landed")
    def joint() -> dict:  # a stage whose individuals are scored on several drops (complex, one-net, general)
        return {"best_score": [], "best_mean_f": [], "best_mean_D": [], "best_mean_S": [], "best_n_success": [],
                "best_n_landed": [], "median_mean_f": [], "first_success": None, "first_landed": None, "best": []}

    return {"simple": [{c: [] for c in cols} | {"first_success": None, "first_landed": None} for _ in range(k)],
            "complex": joint(), "general": joint()}


def _f(x) -> float:
    return float(x)


def _record_simple(hist: dict, gen: int, marks: np.ndarray, order: np.ndarray) -> None:
    """Curves for one orientation's generation ``gen`` (1-based): marks (N, 5)."""
    b = marks[order[0]]
    up = marks[:, 3] >= UPRIGHT_COS
    hist["best_f"].append(_f(b[0]))
    hist["best_D"].append(_f(b[1]))
    hist["best_S"].append(_f(b[2]))
    hist["best_up_z"].append(_f(b[3]))
    for i, c in enumerate("fDS"):
        hist[f"median_{c}"].append(_f(np.median(marks[:, i])))
    ok = _is_success(b)
    hist["best_success"].append(ok)
    hist["n_upright"].append(int(up.sum()))
    landed = bool(b[4])
    hist["best_landed"].append(landed)
    hist["n_landed"].append(int(marks[:, 4].sum()))
    if ok and hist["first_success"] is None:
        hist["first_success"] = gen
    if landed and hist["first_landed"] is None:
        hist["first_landed"] = gen


def _record_complex(hist: dict, gen: int, marks: np.ndarray, order: np.ndarray, score_: np.ndarray) -> None:
    """marks (N, K, 5)."""
    b = marks[order[0]]
    hist["best_score"].append(_f(score_[order[0]]))
    hist["best_mean_f"].append(_f(b[:, 0].mean()))
    hist["best_mean_D"].append(_f(b[:, 1].mean()))
    hist["best_mean_S"].append(_f(b[:, 2].mean()))
    ok = [_is_success(row) for row in b]
    hist["best_n_success"].append(int(sum(ok)))
    hist["median_mean_f"].append(_f(np.median(marks[:, :, 0].mean(axis=1))))
    hist["best_n_landed"].append(int(b[:, 4].sum()))
    hist["best"] = [{"f": _f(r[0]), "D": _f(r[1]), "S": _f(r[2]), "up_z": _f(r[3]), "success": s,
                     "landed": bool(r[4])} for r, s in zip(b, ok, strict=True)]
    if all(ok) and hist["first_success"] is None:
        hist["first_success"] = gen
    if b[:, 4].all() and hist["first_landed"] is None:
        hist["first_landed"] = gen


# ------------------------------------------------------------------------------------ checkpoints


def _pack_unit(prefix: str, u: GeneUnit, arrays: dict[str, np.ndarray]) -> None:
    arrays[f"{prefix}/inputs"] = np.array(u.inputs, dtype=np.int64)
    arrays[f"{prefix}/W1"] = u.W1
    arrays[f"{prefix}/W2"] = u.W2
    arrays[f"{prefix}/scale"] = np.array(u.scale)


def _unpack_unit(prefix: str, kind: str, data: dict[str, np.ndarray]) -> GeneUnit:
    from felis.learning.landing.nets import PolicyError

    try:
        w1 = data[f"{prefix}/W1"]
        u = GeneUnit(kind, tuple(int(i) for i in data[f"{prefix}/inputs"]), int(w1.shape[0]) if w1.ndim == 2 else 0,
                     w1, data[f"{prefix}/W2"], float(data[f"{prefix}/scale"]))
        return u.check()
    except KeyError as e:
        raise CheckpointError(f"checkpoint lacks array {e.args[0]!r}") from None
    except (PolicyError, ValueError, TypeError) as e:
        raise CheckpointError(f"checkpoint unit {prefix!r} is corrupt: {e}") from None


def _pack_simple(prefix: str, b: SimpleBehaviour, arrays: dict[str, np.ndarray]) -> None:
    for p in PARTS:
        _pack_unit(f"{prefix}/{p}", getattr(b, p), arrays)


def _unpack_simple(prefix: str, data: dict[str, np.ndarray]) -> SimpleBehaviour:
    return SimpleBehaviour(*(_unpack_unit(f"{prefix}/{p}", p, data) for p in PARTS))


def save_checkpoint(path: Path, state: _State, run_id: dict) -> None:
    """Write ``state`` (module doc) atomically to ``path``."""
    from felis.files import write_atomic

    arrays: dict[str, np.ndarray] = {}
    for k, pop in enumerate(state.simple):
        for i, b in enumerate(pop):
            _pack_simple(f"simple/{k}/{i}", b, arrays)
    for k, b in enumerate(state.frozen or ()):
        _pack_simple(f"frozen/{k}", b, arrays)
    for i, u in enumerate(state.compose or ()):
        _pack_unit(f"compose/{i}", u, arrays)
    doc = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **run_id, "stage": state.stage,
           "generation": state.generation, "n_simple": [len(p) for p in state.simple],
           "n_frozen": len(state.frozen or ()), "n_compose": len(state.compose or ()),
           "rng": state.rng.bit_generator.state, "history": state.history}
    arrays[META_KEY] = np.array(json.dumps(doc, allow_nan=False))
    write_atomic(path, lambda f: np.savez(f, **arrays), "training checkpoint", CheckpointError)


def _difference(saved: dict, now: dict) -> str | None:
    for key in sorted(set(saved) | set(now)):
        if saved.get(key) != now.get(key):
            return f"{key}={saved.get(key)!r} there, {now.get(key)!r} here"
    return None


def load_checkpoint(path: Path, run_id: dict) -> _State:
    """The state in ``path``; `CheckpointError` (one line) if it is corrupt or from another run."""
    from felis.files import MAX_ARRAY_BYTES, check_readable

    check_readable(path, "checkpoint", CheckpointError, MAX_ARRAY_BYTES)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - any unreadable file is one line for the operator
        raise CheckpointError(f"{path}: unreadable training checkpoint ({type(e).__name__}); delete it or "
                              "start afresh without resume") from None
    try:
        doc = json.loads(str(data[META_KEY]))
    except (KeyError, ValueError):
        raise CheckpointError(f"{path}: not a landing training checkpoint (no metadata)") from None
    if doc.get("format") != CHECKPOINT_FORMAT or doc.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: not a landing training checkpoint of version {CHECKPOINT_VERSION}")
    for key in run_id:
        diff = _difference(doc.get(key) or {}, run_id[key]) if isinstance(run_id[key], dict) else (
            None if doc.get(key) == run_id[key] else f"{doc.get(key)!r} there, {run_id[key]!r} here")
        if diff:
            raise CheckpointError(f"{path}: written by a run with other {key} ({diff}); use the same "
                                  "settings to resume, or start afresh without resume")
    try:
        simple = [[_unpack_simple(f"simple/{k}/{i}", data) for i in range(n)] for k, n in enumerate(doc["n_simple"])]
        frozen = [_unpack_simple(f"frozen/{k}", data) for k in range(doc["n_frozen"])] or None
        compose = [_unpack_unit(f"compose/{i}", "compose", data) for i in range(doc["n_compose"])] or None
        rng = np.random.default_rng()
        rng.bit_generator.state = doc["rng"]
        return _State(doc["stage"], int(doc["generation"]), simple, frozen, compose, rng, doc["history"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: corrupt training checkpoint ({type(e).__name__}: {e})") from None


# ------------------------------------------------------------------------------------------ outputs


def output_paths(out_path: str | Path) -> tuple[Path, Path, Path]:
    """(policy ``.npz``, ``<stem>.results.json``, ``<stem>.curves.png``)."""
    out = Path(out_path)
    if out.suffix != ".npz":
        raise ParameterError(f"{out}: the landing policy file must end in .npz")
    return out, out.with_name(out.stem + ".results.json"), out.with_name(out.stem + ".curves.png")


def plot_curves(path: Path, results: dict) -> Path:
    """Best f and D per generation per orientation (simple stage); the complex stage's best mean f and
    how many orientations it lands upright on. Agg canvas, no pyplot state."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    from felis.files import write_atomic

    fig = Figure(figsize=(11, 7.5))
    FigureCanvasAgg(fig)
    ax = fig.subplots(2, 2)
    for c in results["simple"]:
        g = np.arange(1, len(c["best_f"]) + 1)
        label = "k{index} ({r:g}, {p:g}, {y:g})".format(index=c["sample"], r=c["orientation"][0],
                                                       p=c["orientation"][1], y=c["orientation"][2])
        ax[0, 0].plot(g, c["best_f"], label=label)
        ax[0, 1].plot(g, c["best_D"], label=label)
    ax[0, 0].set(title="simple stage: best f (eq. 9 × upright)", xlabel="generation", ylabel="f")
    ax[0, 1].set(title="simple stage: D of the best (eq. 7)", xlabel="generation", ylabel="D")
    ax[0, 0].legend(fontsize=7)
    cx = results["complex"]
    g = np.arange(1, len(cx["best_mean_f"]) + 1)
    ax[1, 0].plot(g, cx["best_mean_f"], label="best: mean f")
    ax[1, 0].plot(g, cx["median_mean_f"], label="median: mean f")
    gx = results.get("general") or {}
    if gx.get("best_mean_f"):
        gg = np.arange(1, len(gx["best_mean_f"]) + 1)
        ax[1, 0].plot(gg, gx["best_mean_f"], label="general stage, best: mean f over its drops")
        ax[1, 0].plot(gg, gx["median_mean_f"], label="general stage, median")
    ax[1, 0].set(title="complex stage: f over the orientations", xlabel="generation", ylabel="mean f")
    ax[1, 0].legend(fontsize=7)
    ax[1, 1].plot(g, cx["best_n_success"], drawstyle="steps-mid", label="upright at the end, f > 0")
    ax[1, 1].plot(g, cx["best_n_landed"], drawstyle="steps-mid", label="landed (feet first, 0.5 s)")
    ax[1, 1].legend(fontsize=7)
    ax[1, 1].set(title="complex stage: orientations the best lands on", xlabel="generation",
                 ylabel="orientations", ylim=(-0.2, len(results["simple"]) + 0.2))
    for a in ax.flat:
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax[1, 1].yaxis.set_major_locator(MaxNLocator(integer=True))
    fig.tight_layout()
    return write_atomic(path, lambda f: fig.savefig(f, format="png", dpi=90), "training curves", ParameterError)


def _results(cfg: TrainConfig, task: Task, idx: list[int], samples: Sequence[Any], state: _State,
             fingerprint: str, run: dict) -> dict:
    h = state.history
    simple = []
    for k, c in enumerate(h["simple"]):
        ref = samples[idx[k]]
        ref_f = None
        if getattr(ref, "heights_mm", None) is not None and getattr(ref, "final_up_z", None) is not None:
            ref_f = _f(fitness(np.asarray(ref.heights_mm, dtype=float), float(ref.final_up_z), cfg.smooth_upright))
        simple.append({"sample": idx[k], "orientation": list(task.orientations[k]), "height_m": task.heights_m[k],
                       "sample_f": ref_f, **c})
    final = [{"sample": idx[k], "orientation": list(task.orientations[k]), **r}
             for k, r in enumerate(h["complex"]["best"])]
    return {
        "format": "felis-landing-training", "version": 1, "config": cfg.results_settings(),
        "samples": {"path": cfg.samples, "fingerprint": fingerprint, "count": len(samples)},
        "drop_height_norm_m": DROP_HEIGHT_M, "landing_height_mm": LANDING_HEIGHT_MM, "upright_cos": UPRIGHT_COS,
        "generations_to_first_success": {"simple": [c["first_success"] for c in h["simple"]],
                                         "complex": h["complex"]["first_success"]},
        "generations_to_first_landing": {"simple": [c["first_landed"] for c in h["simple"]],
                                         "complex": h["complex"]["first_landed"]},
        "simple": simple,
        "complex": {k: v for k, v in h["complex"].items() if k != "best"},
        "general": {k: v for k, v in h["general"].items() if k != "best"},
        "final": final,
        "final_success_rate": (sum(r["success"] for r in final) / len(final)) if final else None,
        "final_landed_rate": (sum(r["landed"] for r in final) / len(final)) if final else None,
        "run": run,
    }


def _write_outputs(cfg, task, idx, samples, state, fingerprint, out_path, run) -> dict:
    from felis.files import write_atomic

    out, res_path, png = output_paths(out_path)
    if cfg.generations_general or cfg.one_net:  # the population's first member is its last best (an elite)
        policy = state.simple[0][0]
    else:
        policy = ComplexBehaviour(tuple(state.frozen), state.compose[0])
    results = _results(cfg, task, idx, samples, state, fingerprint, run)
    meta = {"trained_by": "felis.learning.landing.train", "seed": cfg.seed, "samples": fingerprint,
            "orientations": [list(o) for o in task.orientations], "heights_m": list(task.heights_m),
            "steps": cfg.steps, "use_similarity": cfg.use_similarity, "fitness": cfg.fitness,
            "one_net": cfg.one_net, "generations": [cfg.generations_simple, cfg.generations_complex,
                                                    cfg.generations_general],
            "final": results["final"]}
    save_policy(out, policy, meta)
    write_atomic(res_path, json.dumps(results, indent=1, allow_nan=False) + "\n", "training results",
                 ParameterError)
    plot_curves(png, results)
    return results


# ------------------------------------------------------------------------------------------ training


def _simple_generation(state: _State, cfg: TrainConfig, ev: Evaluator) -> dict:
    pops = state.simple
    k_n, n = len(pops), cfg.population
    jobs = [(b, k) for k in range(k_n) for b in pops[k]]
    marks = np.array(ev.map(evaluate_job, jobs), dtype=float).reshape(k_n, n, 5)
    gen = state.generation + 1
    new = []
    for k in range(k_n):
        order, sc = rank_marks(marks[k], cfg.use_similarity)
        _record_simple(state.history["simple"][k], gen, marks[k], order)
        new.append(breed_simple(pops[k], order, sc, cfg, state.rng))
    state.simple, state.generation = new, gen
    hs = state.history["simple"]
    return {"best_f": [c["best_f"][-1] for c in hs], "best_D": [c["best_D"][-1] for c in hs],
            "successes": sum(c["best_success"][-1] for c in hs), "landed": sum(c["best_landed"][-1] for c in hs),
            "orientations": k_n}


def _complex_generation(state: _State, cfg: TrainConfig, ev: Evaluator, k_n: int) -> dict:
    frozen = tuple(state.frozen)
    jobs = [(ComplexBehaviour(frozen, u), k) for u in state.compose for k in range(k_n)]
    marks = np.array(ev.map(evaluate_job, jobs), dtype=float).reshape(len(state.compose), k_n, 5)
    order, sc = rank_marks(marks, cfg.use_similarity)
    gen = state.generation + 1
    hc = state.history["complex"]
    _record_complex(hc, gen, marks, order, sc)
    state.compose, state.generation = breed_compose(state.compose, order, sc, cfg, state.rng), gen
    return {"score": hc["best_score"][-1], "mean_f": hc["best_mean_f"][-1], "successes": hc["best_n_success"][-1],
            "landed": hc["best_n_landed"][-1], "orientations": k_n}


def start_tilt_deg(roll_deg: float, pitch_deg: float) -> float:
    """Tilt of the up-axis from vertical for R = Rz(yaw)·Ry(pitch)·Rx(roll): acos(cos roll · cos pitch)."""
    c = math.cos(math.radians(roll_deg)) * math.cos(math.radians(pitch_deg))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def general_drops(cfg: TrainConfig, generation: int) -> list[tuple[float, float, float, float]]:
    """The drops (roll, pitch, yaw °, height m) of general-stage generation ``generation`` (1-based): roll,
    pitch and yaw uniform over the full circle as in `random_drops`, from a generator seeded by (seed,
    generation), keeping those with `start_tilt_deg` ≤ ``general_max_tilt_deg``; heights
    `GENERAL_HEIGHTS_M` in turn."""
    rng = np.random.default_rng([cfg.seed, generation])
    out: list[tuple[float, float, float, float]] = []
    while len(out) < cfg.general_drops:
        r, p, y = (float(a) for a in rng.uniform(-180.0, 180.0, size=3))
        if start_tilt_deg(r, p) <= cfg.general_max_tilt_deg:
            out.append((r, p, y, GENERAL_HEIGHTS_M[len(out) % len(GENERAL_HEIGHTS_M)]))
    return out


def _general_generation(state: _State, cfg: TrainConfig, ev: Evaluator) -> dict:
    """Every individual on this generation's drops, ranked lexicographically by (drops landed, mean f):
    the score is n_landed + mean f / (F_max + 1) (no motion samples here, so no D, S). Landing comes
    first: ranked by mean f alone, a policy that scores partial credit on every drop (turning in the air,
    rolling back up after a body-first touch) beat the passive cat's score while landing less often."""
    pop = state.simple[0]
    gen = state.generation + 1
    drops = general_drops(cfg, gen)
    jobs = [(b, d) for b in pop for d in drops]
    marks = np.array(ev.map(evaluate_job, jobs), dtype=float).reshape(len(pop), len(drops), 5)
    f_max = 5.0 if cfg.fitness == "landing" else max(1.0, float(marks[:, :, 0].max()))
    sc = marks[:, :, 4].sum(axis=1) + marks[:, :, 0].mean(axis=1) / (f_max + 1.0)
    order = np.lexsort((np.arange(len(pop)), -sc))  # best first; ties: earlier first (elites stay first)
    hg = state.history["general"]
    _record_complex(hg, gen, marks, order, sc)
    state.simple, state.generation = [breed_simple(pop, order, sc, cfg, state.rng)], gen
    return {"score": hg["best_score"][-1], "landed": hg["best_n_landed"][-1], "orientations": len(drops)}


def _one_generation(state: _State, cfg: TrainConfig, ev: Evaluator, k_n: int) -> dict:
    """One-net baseline (§6.6.2): one population of simple behaviours, each on every training orientation,
    ranked by eq. 11 like the compose units."""
    pop = state.simple[0]
    jobs = [(b, k) for b in pop for k in range(k_n)]
    marks = np.array(ev.map(evaluate_job, jobs), dtype=float).reshape(len(pop), k_n, 5)
    order, sc = rank_marks(marks, cfg.use_similarity)
    gen = state.generation + 1
    hc = state.history["complex"]
    _record_complex(hc, gen, marks, order, sc)
    state.simple, state.generation = [breed_simple(pop, order, sc, cfg, state.rng)], gen
    return {"score": hc["best_score"][-1], "mean_f": hc["best_mean_f"][-1], "successes": hc["best_n_success"][-1],
            "landed": hc["best_n_landed"][-1], "orientations": k_n}


def still(b: SimpleBehaviour) -> SimpleBehaviour:
    """``b`` with every output weight and bias 0: it holds the release pose (passive), and mutation
    starts from there."""
    return SimpleBehaviour(*(GeneUnit(u.kind, u.inputs, u.hidden, u.W1, np.zeros_like(u.W2), u.scale)
                             for u in (b.spine, b.tail, b.legs)))


def _start_general(state: _State, cfg: TrainConfig, seeds: Sequence[SimpleBehaviour]) -> None:
    """The general stage's population: a still behaviour, the previous stages' simple behaviours, then
    random ones."""
    pop = ([still(random_simple(state.rng, cfg.max_hidden))] + list(seeds))[:cfg.population]
    pop += [random_simple(state.rng, cfg.max_hidden) for _ in range(cfg.population - len(pop))]
    state.simple, state.stage, state.generation = [pop], "general", 0


def _start(cfg: TrainConfig, k_n: int) -> _State:
    rng = np.random.default_rng(cfg.seed)
    if cfg.one_net:
        return _State("one", 0, [[random_simple(rng, cfg.max_hidden) for _ in range(cfg.population)]], None, None,
                      rng, _new_history(k_n))
    simple = [[random_simple(rng, cfg.max_hidden) for _ in range(cfg.population)] for _ in range(k_n)]
    return _State("simple", 0, simple, None, None, rng, _new_history(k_n))


def train_landing(cfg: TrainConfig, out_path: str | Path, workdir: str | Path, resume: bool = False,
                  progress: Progress | None = None, samples: Sequence[Any] | None = None) -> dict:
    """Evolve a landing policy (module doc) and write it to ``out_path`` with its results and curves.

    ``workdir`` holds the checkpoint (`CHECKPOINT`); ``resume`` continues from it when it exists (a
    checkpoint from other settings or samples is a `CheckpointError`), else training starts afresh.
    ``progress(stage, generation, generations, info)`` is called after every generation, once its
    checkpoint is written (``info``: the generation's best marks and ``seconds``). ``samples``: motion
    samples to use instead of ``cfg.samples`` (objects with ``orientation``, ``height_m``, ``vectors``,
    ``heights_mm``, ``final_up_z``). Rollouts run where ``cfg.workers`` / ``cfg.ray_address`` say
    (`make_evaluator`). Returns the results (as written)."""
    cfg.check()
    out, _, _ = output_paths(out_path)
    from felis.files import check_target

    check_target(out, "landing policy", ParameterError)
    samples = _load_samples(cfg, samples)
    task, idx = make_task(cfg, samples)
    fingerprint = samples_fingerprint(samples)
    run_id = {"config": cfg.results_settings(), "samples": fingerprint}
    ckpt = Path(workdir) / CHECKPOINT
    resumed = bool(resume and ckpt.exists())
    state = load_checkpoint(ckpt, run_id) if resumed else _start(cfg, task.k)
    t_start = time.perf_counter()
    ev = make_evaluator(cfg.ray_address, cfg.workers, initializer=init_worker, initargs=(task,))
    where = ev.describe()
    try:
        while state.stage != "done":
            t0 = time.perf_counter()
            if state.stage == "simple":
                info = _simple_generation(state, cfg, ev)
                stage, total = "simple", cfg.generations_simple
                if state.generation >= cfg.generations_simple:
                    # the previous best of each orientation is its population's first member (an elite)
                    state.frozen = [pop[0] for pop in state.simple]
                    state.compose = [random_unit("compose", state.rng, cfg.max_hidden) for _ in range(cfg.population)]
                    state.stage, state.generation = "complex", 0
                    info["generation"] = cfg.generations_simple
            elif state.stage == "complex":
                info = _complex_generation(state, cfg, ev, task.k)
                stage, total = "complex", cfg.generations_complex
                if state.generation >= cfg.generations_complex:
                    state.stage = "done"
                    info["generation"] = state.generation
                    if cfg.generations_general:
                        _start_general(state, cfg, state.frozen)
            elif state.stage == "one":
                info = _one_generation(state, cfg, ev, task.k)
                stage, total = "one-net", cfg.generations_simple + cfg.generations_complex
                if state.generation >= total:
                    state.stage = "done"
                    info["generation"] = state.generation
                    if cfg.generations_general:
                        _start_general(state, cfg, state.simple[0])
            else:
                info = _general_generation(state, cfg, ev)
                stage, total = "general", cfg.generations_general
                if state.generation >= cfg.generations_general:
                    state.stage = "done"
            gen = info.pop("generation", state.generation)
            save_checkpoint(ckpt, state, run_id)
            if progress is not None:
                progress(stage, gen, total, info | {"seconds": time.perf_counter() - t0})
    finally:
        ev.close()
        release_worker()
    run = {"resumed": resumed, "seconds": round(time.perf_counter() - t_start, 3), "evaluator": where}
    return _write_outputs(cfg, task, idx, samples, state, fingerprint, out, run)
