"""The per-drop optimum (issue 21): for each drop, the best open-loop whole-body motion that CMA-ES finds.

This is the ceiling the landing goals refer to: a motion tuned for one known drop, which no policy that
only senses the cat can beat by much. ``felis eval landing --policy optimum`` runs it.

**Motion family**: `felis.learning.landing.motion` (`motion_table`, `MotionRule`).

**Search** (`optimise`). Parameters x ∈ [−1, 1]^55 (48 waypoint angles / their limits, the return time
mapped onto [`RETURN_MIN_S`, `RETURN_MAX_S`], the 6 posture angles / 0.6 rad).
Generation 0 evaluates the `seeds` (the spine's circle both
ways, the legs' loop both ways with the spine's circle both ways, holding still, and four touchdown postures
after holding still); then `cma`'s CMA-ES runs from the best seed (σ₀ = `SIGMA0`), and, with ``restarts``,
again from the next seeds. Every drop is
searched at once: each generation's candidates of every drop are one batch (`felis.sim.batch.DropBatch`).
A drop stops as soon as a candidate lands. Score (maximised, `score`): training's landing fitness plus 3
for a landing. Deterministic per seed.

**Warm start** (``warm``; ``felis eval landing --policy optimum --warm-start``). Searched from these seeds, the
optimum lands almost nothing tilted beyond 100°, where the motion library, grown by continuation from motions
that land a neighbouring attitude, lands most (docs/landing.md): a search from scratch is no ceiling. With
a library, a drop's generation 0 also tries the library's choice for its attitude and every library motion made
within `WARM_RADIUS_DEG` of it (`MotionLibrary.near`), and CMA-ES starts from the best of all. So started, the
optimum lands every drop the library lands (its choice is a seed) and is the ceiling the goals are read against.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.motion import (  # noqa: F401  (the family lives there; re-exported)
    BODY_JOINTS,
    DIMS,
    DT,
    LIMITS,
    N_POSTURE,
    N_WAYPOINTS,
    POSTURE_LIMIT,
    RETURN_MAX_S,
    RETURN_MIN_S,
    MotionRule,
    decode,
    motion_table,
)
from felis.scenarios.drop import Drop
from felis.scenarios.verdicts import landing_verdict

SIGMA0 = 0.3
POPULATION = 12
GENERATIONS = 30
WARM_RADIUS_DEG = 30.0  # a warm start's library candidates: as far as the library tries each (EVAL_RADIUS_DEG)


def _circle(sign: int) -> np.ndarray:
    ring = [(1.0, 0.0), (0.0, sign * 1.0), (-1.0, 0.0), (0.0, -sign * 1.0)]
    return np.array([ring[i % 4] for i in range(N_WAYPOINTS)])


def _leg_loop(sign: int) -> np.ndarray:
    ring = [(0.0, sign * 1.0), (1.0, sign * 1.0), (1.0, 0.0), (0.0, 0.0)]  # in units of the limits
    return np.array([ring[i % 4] for i in range(N_WAYPOINTS)])


def seeds() -> np.ndarray:
    """Generation 0 (module doc): (13, 55) motions in x units: 9 loops (or holding still), 4 postures."""
    out = []
    for sc in (+1, -1):
        x = np.zeros((N_WAYPOINTS, 8))
        x[:, :2] = _circle(sc)
        out.append(x)
        for sl in (+1, -1):
            x = np.zeros((N_WAYPOINTS, 8))
            x[:, :2] = _circle(sc)
            x[:, 4:6] = x[:, 6:8] = _leg_loop(sl)
            out.append(x)
    for sl in (+1, -1):
        x = np.zeros((N_WAYPOINTS, 8))
        x[:, 4:6] = x[:, 6:8] = _leg_loop(sl)
        out.append(x)
    out.append(np.zeros((N_WAYPOINTS, 8)))
    loops = [np.concatenate([x.ravel(), np.zeros(1 + N_POSTURE)]) for x in out]
    postures = []  # hold still, then take a touchdown posture: legs splayed, tucked or reached
    for fp, fs, hp, hs in ((0, 1, 0, 1), (1, 0, -1, 0), (-1, 0, 1, 0), (0.5, 0.5, -0.5, 0.5)):
        p = np.zeros(DIMS)
        p[N_WAYPOINTS * 8 + 1:] = (fp, 0.0, fs, hp, 0.0, hs)
        postures.append(p)
    return np.array(loops + postures)


class OpenLoop:
    """A `LandingBatch` policy: per cat, the velocity table of its motion; ``tables`` (B, n_ticks, 12)."""

    def __init__(self, tables: np.ndarray):
        self.tables = tables

    def __call__(self, it: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
        k = np.clip(np.rint(t / DT).astype(int), 0, self.tables.shape[1] - 1)
        return self.tables[rows, k]


def score(result, standing_waist_m: float) -> tuple[float, object]:
    """(score, verdict) of one `felis.sim.batch.BatchResult`: training's landing fitness
    (`felis.learning.landing.nets.landing_score`: up-axis at touchdown, the clean share of the window, tilt and
    waist after it, landed; 0…5) plus 3 more for a landing, so that any landing beats any near miss."""
    from felis.learning.landing.nets import landing_score
    from felis.scenarios.verdicts import WINDOW_S

    v = landing_verdict(result.truth)
    if result.diverged:
        return -1.0, v
    air = float(result.truth.up_z[0]) if len(result.truth.up_z) else -1.0
    if v.touchdown_t is None:
        clean = 0.0
    else:
        clean = 1.0 if v.foot_only else min(1.0, max(0.0, (v.touch_t - v.touchdown_t) / WINDOW_S))
    waist = None if v.waist_m is None else v.waist_m / standing_waist_m
    f = landing_score(air, clean, v.tilt_deg, waist, v.landed)
    return float(f + 3.0 * v.landed), v


@dataclass
class DropOptimum:
    drop: Drop
    landed: bool
    score: float
    x: list[float]  # the best motion, in x units (`decode`)
    rollouts: int
    why: str
    tilt_deg: float | None
    reasons: tuple[str, ...] = ()  # the verdict's reasons, as kinds fit for counting

    @staticmethod
    def from_dict(d: dict) -> DropOptimum:
        return DropOptimum(Drop(d["roll_deg"], d["pitch_deg"], d["yaw_deg"], d["height_m"]), bool(d["landed"]),
                           float(d["score"]), [float(v) for v in d["motion_x"]], int(d["rollouts"]), d["why"] or "",
                           d["tilt_deg"], tuple(d.get("reasons", ())))

    def as_dict(self) -> dict:
        return {**self.drop.as_dict(), "landed": self.landed, "why": self.why or None,
                "reasons": list(self.reasons),
                "tilt_deg": None if self.tilt_deg is None else round(self.tilt_deg, 2),
                "score": round(self.score, 4), "rollouts": self.rollouts,
                "motion_x": [float(v) for v in self.x]}  # full precision: at 3 m a 1e-4 change can flip a landing


def patch(d: Drop, deg: float) -> list[Drop]:
    """The four drops ``deg`` away from ``d`` in roll and in pitch, each way."""
    return [Drop(d.roll_deg + r, d.pitch_deg + p, d.yaw_deg, d.height_m)
            for r, p in ((deg, 0.0), (-deg, 0.0), (0.0, deg), (0.0, -deg))]


def evaluate(sim, drops: Sequence[Drop], xs: np.ndarray, touchdown_stiffness: float = 1.0,
             outcomes: list | None = None, late_ticks: int = 0, wrap=None,
             patch_deg: float = 0.0, patch_mm: float = 0.0, results: list | None = None) -> list[tuple[float, object]]:
    """Score motions ``xs`` (B, 55) on ``drops`` (B) in one batch of ``sim`` (`BatchLandingSim`), with the legs'
    touchdown compliance (`felis.controllers.landing.LandingController`); ``outcomes``: a list that gets each
    drop's `felis.learning.landing.evaluate.LandingOutcome` too; ``results``: one that gets each drop's
    `felis.sim.batch.BatchResult` (its recorded truth: e.g. the waist's height after touchdown).

    ``late_ticks`` k > 0: each motion is also run started 1…k ticks late (its velocity table shifted, the joints
    held meanwhile), as a servo bus's latency and a wall clock's jitter delay it on hardware; its score and
    verdict are the worst of the k + 1 runs, so it lands only if it lands at every delay (the outcomes: the
    on-time runs').

    ``wrap(policy, rows)``: a policy that runs around the open-loop one (``rows`` cats; e.g. a feedback,
    ``bench/landing_touchdown.py``). ``patch_deg`` d > 0: each motion is also run from the four attitudes d away
    (`patch`), and its score and verdict are the worst of the five (with ``late_ticks``, of every combination).
    ``patch_mm`` m > 0: each (also) from m millimetres lower and higher, the worst of those too: from 3 m whether a
    motion lands can turn on a millimetre of drop height (``bench/landing_height.py``)."""
    from felis.controllers.landing import LandingBatch
    from felis.learning.landing.designs import joint_speeds
    from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ

    if late_ticks < 0:
        raise ParameterError(f"optimum: late ticks must be ≥ 0, got {late_ticks}")
    if not (patch_deg >= 0 and patch_mm >= 0):
        raise ParameterError(f"optimum: a patch must be ≥ 0 degrees and ≥ 0 mm, got {patch_deg} and {patch_mm}")
    n = len(drops)
    if patch_deg > 0:  # blocks of n: the drops, then each of the four offsets
        near = [patch(d, patch_deg) for d in drops]
        drops = list(drops) + [near[i][j] for j in range(4) for i in range(n)]
        xs = np.concatenate([xs] * 5)
    if patch_mm > 0:  # then each of those lower and higher
        drops = list(drops) + [Drop(d.roll_deg, d.pitch_deg, d.yaw_deg, d.height_m + sign * patch_mm / 1000.0)
                               for sign in (-1.0, 1.0) for d in drops]
        xs = np.concatenate([xs] * 3)
    n_ticks = [int(round((d.fall_time + MARGIN_S) * RATE_HZ)) for d in drops]
    T = max(n_ticks)
    speed = joint_speeds(sim.spec)
    tables = np.stack([motion_table(x, d.height_m, speed, T) for x, d in zip(xs, drops, strict=True)])
    k = int(late_ticks)
    if k:
        late = [np.concatenate([np.zeros((len(xs), s, 12)), tables[:, :T - s]], axis=1) for s in range(1, k + 1)]
        tables = np.concatenate([tables, *late])
    every = list(drops) * (k + 1)
    policy = OpenLoop(tables) if wrap is None else wrap(OpenLoop(tables), len(tables))
    ctl = LandingBatch(sim.spec, [policy], touchdown_stiffness=touchdown_stiffness)
    batch = sim.batch.run(every, ctl, sim.standing_waist_m, rate_hz=RATE_HZ, margin_s=MARGIN_S)
    if outcomes is not None:
        from felis.learning.landing.evaluate import outcome_of

        outcomes += [outcome_of(d, "optimum", r, sim.standing_waist_m)
                     for d, r in zip(drops[:n], batch[:n], strict=True)]
    if results is not None:
        results += batch[:n]
    scored = [score(r, sim.standing_waist_m) for r in batch]
    blocks = len(scored) // n
    return [min((scored[i + s * n] for s in range(blocks)), key=lambda sv: sv[0]) for i in range(n)]


def _check_warm_radius(deg: float) -> None:
    if not 0 <= deg <= 180:
        raise ParameterError(f"optimum: the warm start's radius must be within [0, 180] degrees, got {deg:g}")


def optimise(drops: Sequence[Drop], *, generations: int = GENERATIONS, population: int = POPULATION,
             restarts: int = 0, seed: int = 0, workers: int | None = None,
             progress: Callable[[int, int], None] | None = None, sim=None,
             index: Sequence[int] | None = None, late_ticks: int = 0, wrap=None,
             patch_deg: float = 0.0, warm=None, warm_radius_deg: float = WARM_RADIUS_DEG,
             patch_mm: float = 0.0) -> list[DropOptimum]:
    """The per-drop optimum of every drop (module doc); ``progress(generation, drops still searching)``.
    ``index``: each drop's index in the whole list (default 0, 1, …): its CMA-ES is seeded by it, so a drop's
    result does not depend on how the list is cut. ``late_ticks``: a motion must also land started that many
    ticks late (`evaluate`); the rollouts counted include those. ``wrap``, ``patch_deg``, ``patch_mm``: as
    `evaluate`'s, in every rollout (a drop counts as landed only if its motion lands the whole patch). ``warm``: a
    `felis.learning.landing.library.MotionLibrary` whose motions for each drop's attitude (`MotionLibrary.near`:
    its choice, then its candidates within ``warm_radius_deg``) join that drop's seeds (module doc)."""
    from felis.learning.landing.evaluate import BatchLandingSim

    if generations < 0 or population < 2 or restarts < 0:
        raise ParameterError("optimum: generations ≥ 0, population ≥ 2 and restarts ≥ 0 are needed")
    _check_warm_radius(warm_radius_deg)
    ids = list(range(len(drops))) if index is None else [int(i) for i in index]
    if len(ids) != len(drops):
        raise ParameterError(f"optimum: {len(drops)} drops need {len(drops)} indices, got {len(ids)}")
    own = sim is None
    sim = sim or BatchLandingSim(nthread=workers)
    try:
        n = len(drops)
        S = [seeds()] * n
        if warm is not None:
            from felis.learning.landing.library import drop_up

            S = [np.concatenate([S[i], warm.near(drop_up(d), d.height_m, warm_radius_deg)])
                 for i, d in enumerate(drops)]
        best_s = np.full(n, -np.inf)
        best_x = np.zeros((n, DIMS))
        best_v: list = [None] * n
        used = np.zeros(n, dtype=int)
        runs = (late_ticks + 1) * (1 + 4 * (patch_deg > 0)) * (1 + 2 * (patch_mm > 0))  # rollouts per motion tried
        # generation 0: every seed on every drop
        res = evaluate(sim, [d for i, d in enumerate(drops) for _ in S[i]], np.concatenate(S), late_ticks=late_ticks,
                       wrap=wrap, patch_deg=patch_deg, patch_mm=patch_mm)
        order, at = [], 0
        for i in range(n):
            sc = np.array([r[0] for r in res[at:at + len(S[i])]])
            order.append(np.argsort(-sc, kind="stable"))
            j = int(order[i][0])
            best_s[i], best_x[i], best_v[i] = sc[j], S[i][j], res[at + j][1]
            used[i] += len(S[i]) * runs
            at += len(S[i])
        for start in range(restarts + 1 if generations else 0):  # generations 0: the seeds alone
            import cma  # ~2 s to import (it brings scipy.stats): only for a search

            active = [i for i in range(n) if not best_v[i].landed]
            es = {i: cma.CMAEvolutionStrategy(S[i][int(order[i][min(start, len(S[i]) - 1)])], SIGMA0,
                                              {"popsize": population, "bounds": [-1.0, 1.0], "verbose": -9,
                                               "seed": int(seed * 100003 + ids[i] * 101 + start + 1)})
                  for i in active}
            for g in range(generations):
                active = [i for i in active if not best_v[i].landed]
                if progress is not None:
                    progress(start * generations + g, len(active))
                if not active:
                    break
                asks = {i: np.array(es[i].ask()) for i in active}
                batch_drops = [drops[i] for i in active for _ in range(population)]
                res = evaluate(sim, batch_drops, np.concatenate([asks[i] for i in active]), late_ticks=late_ticks,
                               wrap=wrap, patch_deg=patch_deg, patch_mm=patch_mm)
                for a, i in enumerate(active):
                    part = res[a * population:(a + 1) * population]
                    sc = np.array([r[0] for r in part])
                    es[i].tell(list(asks[i]), list(-sc))
                    used[i] += population * runs
                    j = int(np.argmax(sc))
                    if sc[j] > best_s[i]:
                        best_s[i], best_x[i], best_v[i] = sc[j], asks[i][j], part[j][1]
        return [DropOptimum(d, bool(best_v[i].landed), float(best_s[i]), best_x[i].tolist(), int(used[i]),
                            best_v[i].why, best_v[i].tilt_deg, tuple(k for k, _ in best_v[i].reasons))
                for i, d in enumerate(drops)]
    finally:
        if own:
            sim.close()


# ------------------------------------------------------------------------------ long runs: chunks, resume
CHECKPOINT = "optimum.jsonl"
_SIMS: dict = {}  # per evaluator worker: its batch simulation of each design


def _worker_sim(design: str = "cat", timestep: float | None = None):
    import multiprocessing

    from felis.learning.landing.designs import design_sim

    key = (design, timestep)
    if key not in _SIMS:
        _SIMS[key] = design_sim(design, nthread=None if multiprocessing.parent_process() is None else 1,
                                timestep=timestep)
    return _SIMS[key]


def _init_worker() -> None:
    _worker_sim()


def _chunk_job(job) -> list[dict]:
    index, drops, settings = job
    settings = dict(settings)
    ms = settings.pop("timestep_ms", None)
    sim = _worker_sim(settings.pop("design", "cat"), None if ms is None else ms / 1000.0)
    if "warm" in settings:
        from felis.learning.landing.library import load_library

        settings.pop("warm_sha256", None)
        settings["warm"] = load_library(settings.pop("warm"))  # parsed once per worker (`load_library` keeps it)
    return [o.as_dict() for o in optimise(drops, sim=sim, index=index, **settings)]


def optimise_all(drops: Sequence[Drop], *, generations: int = GENERATIONS, population: int = POPULATION,
                 restarts: int = 0, seed: int = 0, workers: int | None = None, ray_address: str | None = None,
                 chunk: int | None = None, workdir: str | None = None, resume: bool = False,
                 progress: Callable[[int], None] | None = None, design: str = "cat",
                 late_ticks: int = 0, patch_deg: float = 0.0, warm: str | None = None,
                 warm_radius_deg: float = WARM_RADIUS_DEG, timestep_ms: float | None = None) -> list[DropOptimum]:
    """`optimise` for a long list: cut into chunks of ``chunk`` drops (default: shared evenly among the
    workers, at most 25 a chunk), one chunk per evaluator worker at a time
    (`felis.learning.common.evaluator`: a process pool of ``workers``, or Ray at ``ray_address``; one worker:
    this process, every core on the chunk's batch), each finished drop appended to ``workdir``/`CHECKPOINT`
    (JSON lines after a header with the settings and the drops); ``resume`` skips the drops already there.
    Results equal one `optimise` over the whole list (each drop is searched alone); ``progress(n)`` after
    each round of chunks, n drops done in it. ``design``: a cat of `felis.learning.landing.designs.DESIGNS`;
    ``late_ticks``, ``patch_deg``: as in `optimise`; ``warm``: a library file (its path, which every worker
    reads; on Ray, the same path on every machine) whose motions join the seeds, as `optimise`'s ``warm``;
    ``timestep_ms``: the physics step (default the design's; it must divide the 10 ms control tick)."""
    import json
    from pathlib import Path

    from felis.learning.common.evaluator import make_evaluator
    from felis.learning.landing.designs import get_design

    get_design(design)  # a bad name is one line before any work
    settings = {"generations": generations, "population": population, "restarts": restarts, "seed": seed}
    if design != "cat":  # the described cat's checkpoints stay as they were
        settings["design"] = design
    if timestep_ms is not None:
        from felis.learning.landing.evaluate import check_timestep_ms

        settings["timestep_ms"] = check_timestep_ms(timestep_ms)  # one line before any work
    if late_ticks:
        settings["late_ticks"] = int(late_ticks)
    if not patch_deg >= 0:
        raise ParameterError(f"optimum: a patch must be ≥ 0 degrees, got {patch_deg}")
    if patch_deg:
        settings["patch_deg"] = float(patch_deg)
    if warm is not None:
        import hashlib

        from felis.learning.landing.library import load_library

        _check_warm_radius(warm_radius_deg)
        load_library(warm)  # a bad file is one line before any work
        settings["warm"] = str(warm)
        settings["warm_radius_deg"] = float(warm_radius_deg)
        settings["warm_sha256"] = hashlib.sha256(Path(warm).read_bytes()).hexdigest()[:16]  # resume: the same file
    header = {"settings": settings, "drops": [d.as_dict() for d in drops]}
    done: dict[int, DropOptimum] = {}
    ckpt = Path(workdir) / CHECKPOINT if workdir else None
    if ckpt is not None:
        ckpt.parent.mkdir(parents=True, exist_ok=True)
        if resume and ckpt.exists():
            lines = ckpt.read_text().splitlines()
            try:
                head = json.loads(lines[0]) if lines else None
                rows = [json.loads(x) for x in lines[1:] if x.strip()]
            except ValueError:  # a line cut by a kill: keep what parses
                head, rows = (json.loads(lines[0]) if lines else None), []
                for x in lines[1:]:
                    try:
                        rows.append(json.loads(x))
                    except ValueError:
                        break
            if head != header:
                raise ParameterError(f"{ckpt}: a checkpoint of other drops or settings; remove it or drop --resume")
            done = {int(r["i"]): DropOptimum.from_dict(r) for r in rows}
            ckpt.write_text("".join(json.dumps(x) + "\n" for x in [header, *rows]))  # without a cut last line
        else:
            ckpt.write_text(json.dumps(header) + "\n")
    todo = [i for i in range(len(drops)) if i not in done]
    ev = make_evaluator(ray_address, workers if ray_address else (workers or 1), initializer=_init_worker)
    n_workers = max(1, int(getattr(ev, "workers", 1) or 1))
    if chunk is None:
        chunk = max(1, min(25, math.ceil(len(todo) / n_workers)))
    chunks = [todo[k:k + chunk] for k in range(0, len(todo), chunk)]
    try:
        for r in range(0, len(chunks), n_workers):
            group = chunks[r:r + n_workers]
            jobs = [(idx, [drops[i] for i in idx], settings) for idx in group]
            for idx, res in zip(group, ev.map(_chunk_job, jobs), strict=True):
                for i, d in zip(idx, res, strict=True):
                    done[i] = DropOptimum.from_dict(d)
                    if ckpt is not None:
                        with ckpt.open("a") as f:
                            f.write(json.dumps({"i": i, **d}) + "\n")
            if progress is not None:
                progress(sum(len(g) for g in group))
    finally:
        ev.close()
    return [done[i] for i in range(len(drops))]
