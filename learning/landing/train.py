"""Evolution of the landing controller: simple behaviours per orientation, then the compose net (seed 000 §5–6).

Source: ``seeds/000_d27ba58563dbcb8e.txt`` §5 (gene units, crossover, elimination; "create a population,
compute fitness, crossover and mutate, repeat"), §6.4 (eqs. 9–11), §6.5 (motion samples), §6.6 (the
experiments). Nets, operators and ranking live in `felis.learning.landing.nets`, features and similarity
in `felis.learning.landing.features`; this module is the loop around them.

**Features.** A PCA (`Pca`, ``pca_dims`` components) is fitted on the logical features B of every motion
sample (all orientations in the samples file, eq. 3–4); each training sample k then has SF_k (eq. 4) and
TF_k (eq. 5–6).

**One evaluation** (individual, training orientation k): a rollout of ``steps`` ticks at 100 Hz from the
sample's orientation and height (`samples.rollout`, the recording the samples were made with; any
other length through `task._rollout`, the same recording) gives the waist heights (mm), the segment vectors
and the upper body's up-axis z at the end; then

    f = eq. 9 × upright(up_z)    D = eq. 7 (SF, SF_k)    S = eq. 8 (TF, TF_k)

(`nets.fitness`; ``smooth_upright`` uses its ramp), and, for the record only, whether the drop
meets the issue's `landed` rule (`felis.scenarios.verdicts`: feet only for 0.5 s after touchdown, tilt ≤ 30°,
waist up). A rollout whose physics diverged gets f = 0 and D = S = `task.DIVERGED` (worse than any real
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
up, which the issue's `landed` rule rejects. `nets.landing_score` ∈ [0, 5] gives one point per
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
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import ParameterError
from felis.files import check_target, write_atomic
from felis.learning.common.evaluator import Evaluator, make_evaluator
from felis.learning.landing.breeding import breed_compose, breed_simple, rank_marks
from felis.learning.landing.checkpoint import CHECKPOINT, TrainState, load_checkpoint, save_checkpoint
from felis.learning.landing.config import TrainConfig
from felis.learning.landing.nets import (
    LANDING_HEIGHT_MM,
    UPRIGHT_COS,
    fitness,
    random_simple,
    random_unit,
    save_policy,
)
from felis.learning.landing.plot import plot_curves
from felis.learning.landing.policy import DROP_HEIGHT_M, ComplexBehaviour, GeneUnit, SimpleBehaviour
from felis.learning.landing.task import (
    Task,
    evaluate_batch,
    init_batch_worker,
    load_task_samples,
    make_task,
    release_batch_worker,
    samples_fingerprint,
)

RATE_HZ = 100.0  # §6.4: steps of 1/100 s (`STEPS` = 200 of them)
GENERAL_HEIGHTS_M = (1.0, 3.0)  # the general stage's drops alternate between these heights

Progress = Callable[[str, int, int, dict], None]


# ------------------------------------------------------------------------------------------ state


def _is_success(marks: np.ndarray) -> bool:
    """(f, D, S, up_z, landed) of a success: upright at the end (up_z ≥ cos 30°) and f > 0, i.e. the waist came
    below 500 mm and stayed off the floor (eq. 9's H not empty, mean > 0)."""
    return bool(marks[3] >= UPRIGHT_COS and marks[0] > 0.0)


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




# ------------------------------------------------------------------------------------------ outputs


def output_paths(out_path: str | Path) -> tuple[Path, Path, Path]:
    """(policy ``.npz``, ``<stem>.results.json``, ``<stem>.curves.png``)."""
    out = Path(out_path)
    if out.suffix != ".npz":
        raise ParameterError(f"{out}: the landing policy file must end in .npz")
    return out, out.with_name(out.stem + ".results.json"), out.with_name(out.stem + ".curves.png")



def _results(cfg: TrainConfig, task: Task, idx: list[int], samples: Sequence[Any], state: TrainState,
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


def _evaluate(ev: Evaluator, jobs: list) -> np.ndarray:
    """(f, D, S, up_z, landed) of every job, in job order: the jobs cut into one batch per evaluator worker,
    each batch stepped together (`task.evaluate_batch`, `felis.sim.batch.DropBatch`)."""
    n = max(1, min(len(jobs), int(getattr(ev, "workers", 1) or 1)))
    bounds = np.linspace(0, len(jobs), n + 1).round().astype(int)
    parts = ev.map(evaluate_batch, [jobs[a:b] for a, b in zip(bounds, bounds[1:], strict=False)])
    return np.array([m for part in parts for m in part], dtype=float)


def _simple_generation(state: TrainState, cfg: TrainConfig, ev: Evaluator) -> dict:
    pops = state.simple
    k_n, n = len(pops), cfg.population
    jobs = [(b, k) for k in range(k_n) for b in pops[k]]
    marks = _evaluate(ev, jobs).reshape(k_n, n, 5)
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


def _complex_generation(state: TrainState, cfg: TrainConfig, ev: Evaluator, k_n: int) -> dict:
    frozen = tuple(state.frozen)
    jobs = [(ComplexBehaviour(frozen, u), k) for u in state.compose for k in range(k_n)]
    marks = _evaluate(ev, jobs).reshape(len(state.compose), k_n, 5)
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
    """The drops (roll, pitch, yaw °, height m) of general-stage generation ``generation`` (1-based): orientations
    uniform over all rotations as in `random_drops` (drawn from a generator seeded by (seed, generation)),
    keeping those with `start_tilt_deg` ≤ ``general_max_tilt_deg``; heights `GENERAL_HEIGHTS_M` in turn."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng([cfg.seed, generation])
    out: list[tuple[float, float, float, float]] = []
    while len(out) < cfg.general_drops:
        y, p, r = (float(a) for a in Rotation.random(random_state=rng).as_euler("ZYX", degrees=True))
        if start_tilt_deg(r, p) <= cfg.general_max_tilt_deg:
            out.append((r, p, y, GENERAL_HEIGHTS_M[len(out) % len(GENERAL_HEIGHTS_M)]))
    return out


def _general_generation(state: TrainState, cfg: TrainConfig, ev: Evaluator) -> dict:
    """Every individual on this generation's drops, ranked lexicographically by (drops landed, mean f):
    the score is n_landed + mean f / (F_max + 1) (no motion samples here, so no D, S). Landing comes
    first: ranked by mean f alone, a policy that scores partial credit on every drop (turning in the air,
    rolling back up after a body-first touch) beat the passive cat's score while landing less often."""
    pop = state.simple[0]
    gen = state.generation + 1
    drops = general_drops(cfg, gen)
    jobs = [(b, d) for b in pop for d in drops]
    marks = _evaluate(ev, jobs).reshape(len(pop), len(drops), 5)
    f_max = 5.0 if cfg.fitness == "landing" else max(1.0, float(marks[:, :, 0].max()))
    sc = marks[:, :, 4].sum(axis=1) + marks[:, :, 0].mean(axis=1) / (f_max + 1.0)
    order = np.lexsort((np.arange(len(pop)), -sc))  # best first; ties: earlier first (elites stay first)
    hg = state.history["general"]
    _record_complex(hg, gen, marks, order, sc)
    state.simple, state.generation = [breed_simple(pop, order, sc, cfg, state.rng)], gen
    return {"score": hg["best_score"][-1], "landed": hg["best_n_landed"][-1], "orientations": len(drops)}


def _one_generation(state: TrainState, cfg: TrainConfig, ev: Evaluator, k_n: int) -> dict:
    """One-net baseline (§6.6.2): one population of simple behaviours, each on every training orientation,
    ranked by eq. 11 like the compose units."""
    pop = state.simple[0]
    jobs = [(b, k) for b in pop for k in range(k_n)]
    marks = _evaluate(ev, jobs).reshape(len(pop), k_n, 5)
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


def _start_general(state: TrainState, cfg: TrainConfig, seeds: Sequence[SimpleBehaviour]) -> None:
    """The general stage's population: a still behaviour, the previous stages' simple behaviours, then
    random ones."""
    pop = ([still(random_simple(state.rng, cfg.max_hidden))] + list(seeds))[:cfg.population]
    pop += [random_simple(state.rng, cfg.max_hidden) for _ in range(cfg.population - len(pop))]
    state.simple, state.stage, state.generation = [pop], "general", 0


def _start(cfg: TrainConfig, k_n: int) -> TrainState:
    rng = np.random.default_rng(cfg.seed)
    if cfg.one_net:
        return TrainState("one", 0, [[random_simple(rng, cfg.max_hidden) for _ in range(cfg.population)]], None, None,
                      rng, _new_history(k_n))
    simple = [[random_simple(rng, cfg.max_hidden) for _ in range(cfg.population)] for _ in range(k_n)]
    return TrainState("simple", 0, simple, None, None, rng, _new_history(k_n))


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
    check_target(out, "landing policy", ParameterError)
    samples = load_task_samples(cfg, samples)
    task, idx = make_task(cfg, samples)
    fingerprint = samples_fingerprint(samples)
    run_id = {"config": cfg.results_settings(), "samples": fingerprint}
    ckpt = Path(workdir) / CHECKPOINT
    resumed = bool(resume and ckpt.exists())
    state = load_checkpoint(ckpt, run_id) if resumed else _start(cfg, task.k)
    t_start = time.perf_counter()
    ev = make_evaluator(cfg.ray_address, cfg.workers, initializer=init_batch_worker, initargs=(task,))
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
        release_batch_worker()
    run = {"resumed": resumed, "seconds": round(time.perf_counter() - t_start, 3), "evaluator": where}
    return _write_outputs(cfg, task, idx, samples, state, fingerprint, out, run)
