"""Making a landing motion library (`felis.learning.landing.library`): ``felis train landing-library``.

Per drop height: (1) the per-drop optimum (`felis.learning.landing.optimum.optimise_all`, the shipped results'
budget by default) for the attitudes of a Fibonacci grid of up axes (`fibonacci_ups`: ``grid`` points on the
sphere, kept where the tilt is at most ``max_tilt_deg`` and u_y ≥ 0, the mirror images covering the rest);
(2) a robust twin of each entry that landed (`robustify`); (3) every candidate (entries and their mirror images)
tried on the probes, a denser Fibonacci grid (``probes`` points on the sphere, kept likewise), within
`EVAL_RADIUS_DEG` of the candidate's attitude, batched; (4) the fill: a new entry at each probe that no candidate
lands, searched from the nearest candidate (`fill`, `fill_targets`), then its tries on the probes; further rounds
(``fill_rounds``) do the same for the probes where the choice, their own vote left out, picks a motion that fails.
Checkpoints per height in ``WORKDIR/<h>m/``: ``optimum.jsonl`` (per drop), ``robust.npz``, ``probes.npy``,
``fill.npz`` (``fill2.npz``…); ``resume`` goes on from them. Deterministic for a seed. `replace_shelves` puts
the shelves built into another library (``--base``: one shelf rebuilt, the others kept); `join_shelves` puts two
libraries' motions for a height on one shelf (``--join``); `extend_shelves` takes a shelf beyond its maximum tilt
by continuation from the motions at its edge (``--extend``). Every search and try runs on the described cat, or on
``design`` (a cat of `felis.learning.landing.designs.DESIGNS`: its servos, paws and physics step; ``--design``),
whose name a built library records (``design``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.library import EVAL_RADIUS_DEG, RADIUS_DEG, SIGMA_DEG, MotionLibrary, Shelf, angles_deg
from felis.scenarios.drop import Drop

GRID = 240
PROBES = 1440
MAX_TILT_DEG = 100.0  # the optimum from scratch lands almost nothing further; --extend goes on from the edge
CHUNK = 256  # rollouts per batch when trying the probes
ROBUST_OFFSET_DEG = 6.0
ROBUST_GENERATIONS = 8
ROBUST_POPULATION = 8
FILL_GENERATIONS = ROBUST_GENERATIONS
FILL_ROUNDS = 2
FILL_OFFSET_DEG = 3.0  # a hole's neighbours (the probes are ~5° apart at the default density)


def tilts_deg(u: np.ndarray) -> np.ndarray:
    """The tilt from upright (deg) of up axes (…, 3)."""
    return np.degrees(np.arccos(np.clip(np.asarray(u)[..., 2], -1.0, 1.0)))


def fibonacci_ups(n: int, max_tilt_deg: float = 180.0) -> np.ndarray:
    """Up axes (K, 3) of an ``n``-point Fibonacci sphere with tilt ≤ ``max_tilt_deg`` and u_y ≥ 0."""
    if n < 1:
        raise ParameterError(f"library: a grid needs at least 1 point, got {n}")
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (1.0 + math.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    u = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    keep = (tilts_deg(u) <= max_tilt_deg + 1e-9) & (u[:, 1] >= 0)
    return u[keep]


def up_drop(u: np.ndarray, height_m: float) -> Drop:
    """The drop (yaw 0) whose up axis in the body frame is ``u``: roll = atan2(u_y, u_z), pitch = −asin(u_x)."""
    return Drop(round(math.degrees(math.atan2(u[1], u[2])), 4), round(-math.degrees(math.asin(max(-1, min(1, u[0])))),
                4), 0.0, float(height_m))


def neighbours(u: np.ndarray, offset_deg: float) -> np.ndarray:
    """``u`` and four attitudes ``offset_deg`` away from it, at right angles round it: (5, 3)."""
    u = np.asarray(u, dtype=float)
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    t = math.radians(offset_deg)
    return np.array([u] + [math.cos(t) * u + math.sin(t) * e for e in (e1, -e1, e2, -e2)])


def robustify(sim, ups: np.ndarray, xs: np.ndarray, height_m: float, *, offset_deg: float = ROBUST_OFFSET_DEG,
              generations: int = ROBUST_GENERATIONS, population: int = ROBUST_POPULATION, sigma: float = 0.15,
              seed: int = 0, progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For each motion ``xs[i]`` searched for attitude ``ups[i]``: the motion near it that lands best over the
    attitude and four neighbours ``offset_deg`` round it (`neighbours`): CMA-ES from ``xs[i]`` (σ ``sigma``), the
    score the mean of the optimum's score (`felis.learning.landing.optimum.score`) over the five drops, every
    entry's candidates in one batch per generation. Returns (motions (E, 55), how many of the five each lands, whether
    each lands its own attitude)."""
    import cma

    from felis.learning.landing.optimum import evaluate

    E = len(xs)
    drops = [[up_drop(v, height_m) for v in neighbours(u, offset_deg)] for u in ups]
    K = len(drops[0]) if drops else 0

    def judge(ids: list[int], cands: list[np.ndarray]) -> tuple:  # entry ids[a]'s cands[a] (n, 55) → mean
        # scores, landings, centre landed; each entry's candidates on that entry's own five drops
        flat_d = [d for i, c in zip(ids, cands, strict=True) for _ in range(len(c)) for d in drops[i]]
        flat_x = np.concatenate([np.repeat(c, K, axis=0) for c in cands])
        res = evaluate(sim, flat_d, flat_x)
        sc = np.array([r[0] for r in res]).reshape(-1, K)
        ld = np.array([r[1].landed for r in res]).reshape(-1, K)
        return sc.mean(axis=1), ld.sum(axis=1), ld[:, 0]

    best_x = np.array(xs, dtype=float)
    best_s, best_n, best_c = (judge(list(range(E)), [x[None] for x in best_x]) if E
                              else (np.zeros(0), np.zeros(0, int), np.zeros(0, bool)))
    es = [cma.CMAEvolutionStrategy(best_x[i], sigma, {"popsize": population, "bounds": [-1.0, 1.0], "verbose": -9,
                                                      "seed": int(seed * 100003 + i * 101 + 7)}) for i in range(E)]
    for g in range(generations):
        active = [i for i in range(E) if best_n[i] < K]
        if progress is not None:
            progress(g, generations)
        if not active:
            break
        asks = [np.array(es[i].ask()) for i in active]
        sc, ld, lc = judge(active, asks)
        for a, i in enumerate(active):
            part = slice(a * population, (a + 1) * population)
            es[i].tell(list(asks[a]), list(-sc[part]))
            j = int(np.argmax(sc[part]))
            if sc[part][j] > best_s[i]:
                best_s[i], best_n[i], best_c[i], best_x[i] = sc[part][j], ld[part][j], lc[part][j], asks[a][j]
    if progress is not None:
        progress(generations, generations)
    return best_x, best_n, best_c


def try_probes(sim, shelf_up: np.ndarray, shelf_x: np.ndarray, probe_up: np.ndarray, height_m: float,
               progress: Callable[[int, int], None] | None = None, done: np.ndarray | None = None,
               save: Callable[[np.ndarray], None] | None = None, radius_deg: float = EVAL_RADIUS_DEG) -> np.ndarray:
    """(P, 2E) bool: candidate c lands probe p, tried where they are within ``radius_deg`` (`EVAL_RADIUS_DEG`,
    module doc). ``done``: (P, C ≤ 2E) results so far (1 lands, 0 not, −1 not yet tried: a checkpoint, perhaps of
    fewer entries); ``save(results)`` after each batch."""
    from felis.learning.landing.optimum import evaluate

    cand_up, cand_x, _ = Shelf(height_m, shelf_up, shelf_x, np.ones(len(shelf_up), bool), probe_up,
                               np.zeros((len(probe_up), 2 * len(shelf_up)), bool)).candidates()
    res = np.full((len(probe_up), len(cand_up)), -1, dtype=np.int8)
    if done is not None and done.ndim == 2 and done.shape[0] == len(probe_up):
        c = min(done.shape[1], len(cand_up))  # a checkpoint of more candidates: the fill stage's (same order)
        res[:, :c] = done[:, :c]
    near = angles_deg(probe_up, cand_up) <= radius_deg
    pairs = np.argwhere(near & (res < 0))  # (probe, candidate) still to try
    drops = [up_drop(u, height_m) for u in probe_up]
    total = int(np.count_nonzero(near))
    for k in range(0, len(pairs), CHUNK):
        part = pairs[k:k + CHUNK]
        out = evaluate(sim, [drops[p] for p in part[:, 0]], cand_x[part[:, 1]])
        res[part[:, 0], part[:, 1]] = [int(v.landed) for _, v in out]
        if save is not None:
            save(res)
        if progress is not None:
            progress(total - len(pairs) + k + len(part), total)
    return res == 1


def misses(shelf: Shelf, radius_deg: float = RADIUS_DEG, sigma_deg: float = SIGMA_DEG,
           among: np.ndarray | None = None) -> np.ndarray:
    """The probes (of ``among``, in its order; default all, ascending) where the vote is wrong: some candidate
    lands the probe, but the choice there with the probe left out of the vote does not (its neighbours point to a
    motion that fails on it)."""
    from scipy.sparse import csr_matrix

    some = shelf.lands.any(axis=1)
    ps = np.flatnonzero(some) if among is None else np.asarray(among, dtype=int)[some[among]]
    cand_up = shelf.candidates()[0]
    # sparse: a probe has a few hundred voters of thousands of probes, a candidate lands ~0.5 % of them (the 3 m
    # shelf's misses in 3 s, 18 s with dense products; the same weights and sums, in another order)
    lands = csr_matrix(shelf.lands.astype(float))
    near_cos = math.cos(math.radians(min(radius_deg + 0.01, 180.0)))
    wrong = []
    for k in range(0, len(ps), 256):  # `Shelf.choose` for 256 probes at once: one product of weights and verdicts
        rows = ps[k:k + 256]
        u = shelf.probe_up[rows] / np.linalg.norm(shelf.probe_up[rows], axis=1, keepdims=True)
        dots = np.clip(u @ shelf.probe_up.T, -1.0, 1.0)
        i, j = np.nonzero(dots >= near_cos)
        a = np.degrees(np.arccos(dots[i, j]))  # `angles_deg` where it may be within the radius
        keep = (a <= radius_deg) & (j != rows[i])  # the probe's own vote left out
        i, j, a = i[keep], j[keep], a[keep]
        w = csr_matrix((np.exp(-0.5 * (a / sigma_deg) ** 2), (i, j)), shape=(len(rows), len(shelf.probe_up)))
        score = (w @ lands).toarray()
        top = score.max(axis=1)
        tied = score >= top[:, None] * (1.0 - 1e-9)
        pick = np.argmin(np.where(tied, angles_deg(u, cand_up), np.inf), axis=1)  # ties to the nearest
        for p, c, t, y in zip(rows, pick, top, u[:, 1], strict=True):
            if t <= 0 or y < 0:  # no vote (choose falls back on the nearest landed entry) or a mirrored attitude
                c = shelf.choose(shelf.probe_up[p], radius_deg, sigma_deg, exclude=p)[1]
            if not shelf.lands[p, c]:
                wrong.append(p)
    return np.array(wrong, dtype=int)


def fill_targets(shelf: Shelf, round_: int) -> np.ndarray:
    """The probes a fill round searches a motion for: round 1 the holes (no candidate lands them); later rounds the
    `misses` (with the library's default vote)."""
    if round_ <= 1:
        return np.flatnonzero(~shelf.lands.any(axis=1))
    return misses(shelf)


def fill(sim, shelf: Shelf, targets: np.ndarray, *, generations: int = ROBUST_GENERATIONS,
         offset_deg: float = FILL_OFFSET_DEG, seed: int = 0,
         progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """New entries for the probes ``targets`` of ``shelf``: for each, `robustify` over the probe and four attitudes
    ``offset_deg`` round it, from the nearest candidate (an entry or a mirror image) that lands the probe, or, where
    none does, the nearest that lands something (some probe, or its own drop; else the nearest of all): a
    continuation from motions that work, which reaches holes far from every entry (`extend_shelves`). Returns
    (motions (T, 55), how many of the five each lands, whether each lands its probe); the caller keeps those that
    land something."""
    if not len(targets):
        return np.zeros((0, shelf.x.shape[1])), np.zeros(0, int), np.zeros(0, bool)
    cand_up, cand_x, cand_landed = shelf.candidates()
    useful = shelf.lands.any(axis=0) | cand_landed
    if not useful.any():
        useful[:] = True
    mine = shelf.lands[targets]
    a = angles_deg(shelf.probe_up[targets], cand_up)
    a = np.where(np.where(mine.any(axis=1, keepdims=True), mine, useful[None, :]), a, np.inf)
    return robustify(sim, shelf.probe_up[targets], cand_x[np.argmin(a, axis=1)], shelf.height_m,
                     offset_deg=offset_deg, generations=generations, seed=seed, progress=progress)


def build_library(heights: Sequence[float] = (1.0, 3.0), *, grid: int = GRID, probes: int = PROBES,
                  max_tilt_deg: float = MAX_TILT_DEG, generations: int = 30, population: int = 12,
                  restarts: int = 1, seed: int = 0, workers: int | None = None, ray_address: str | None = None,
                  workdir: str | Path | None = None, resume: bool = False, command: str = "",
                  robust_generations: int = ROBUST_GENERATIONS, fill_generations: int = FILL_GENERATIONS,
                  fill_rounds: int = FILL_ROUNDS, patch_deg: float = 0.0, design: str = "cat",
                  progress: Callable[[str, int, int], None] | None = None) -> MotionLibrary:
    """The library (module doc); ``progress(stage, done, total)`` with stage ``"<h> m optimum"``, ``"<h> m
    robust"``, ``"<h> m probes"`` or ``"<h> m fill <round>"``. ``robust_generations`` 0: no robust stage;
    ``fill_generations`` > 0: ``fill_rounds`` rounds of `fill` on `fill_targets`, each followed by the new
    entries' tries on the probes. ``patch_deg`` > 0: each entry's search must land the four attitudes that far
    away too (`felis.learning.landing.optimum.evaluate`; an entry then counts as landed only if it lands all five),
    for motions whose landing holds when the release attitude is a little off (docs/landing.md)."""
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.optimum import optimise_all

    if not heights or any(not (isinstance(h, int | float) and math.isfinite(h) and h > 0) for h in heights):
        raise ParameterError(f"library: heights must be positive numbers of metres, got {list(heights)}")
    if probes < 1 or not 0 < max_tilt_deg <= 180:
        raise ParameterError("library: probes ≥ 1 and a maximum tilt within (0, 180] degrees are needed")
    ups = fibonacci_ups(grid, max_tilt_deg)
    probe_up = fibonacci_ups(probes, max_tilt_deg)
    shelves = []
    for h in heights:
        where = None if workdir is None else Path(workdir) / f"{h:g}m"
        drops = [up_drop(u, h) for u in ups]
        stage = f"{h:g} m optimum"
        count, total = [0], len(drops)

        def step(n, stage=stage, count=count, total=total):
            count[0] += n
            if progress is not None:
                progress(stage, count[0], total)

        best = optimise_all(drops, generations=generations, population=population, restarts=restarts, seed=seed,
                            workers=workers, ray_address=ray_address, workdir=None if where is None else str(where),
                            resume=resume, progress=step, patch_deg=patch_deg, design=design)
        x = np.array([o.x for o in best])
        landed = np.array([o.landed for o in best])
        entry_up, entry_drops = ups, [o.drop.as_dict() for o in best]
        sim = design_sim(design, nthread=workers)
        try:
            if robust_generations > 0 and landed.any():  # a robust twin of every entry that landed, beside it
                rows = np.flatnonzero(landed)
                ck = None if where is None else where / "robust.npz"
                if resume and ck is not None and ck.is_file():
                    with np.load(ck) as f:
                        rx, rn, rc = f["x"], f["landed"], f["centre"]
                else:
                    rx, rn, rc = robustify(sim, ups[rows], x[rows], h, generations=robust_generations, seed=seed,
                                       progress=None if progress is None else
                                       (lambda d, t, h=h: progress(f"{h:g} m robust", d, t)))
                    if ck is not None:
                        np.savez(ck, x=rx, landed=rn, centre=rc)
                new = np.flatnonzero(np.any(rx != x[rows], axis=1))  # a motion robust already has no twin
                rows = rows[new]
                entry_up = np.concatenate([ups, ups[rows]])
                entry_drops = entry_drops + [entry_drops[i] for i in rows]
                x = np.concatenate([x, rx[new]])
                landed = np.concatenate([landed, rc[new]])
            done, save = None, None
            if where is not None:
                ck = where / "probes.npy"
                if resume and ck.is_file():
                    done = np.load(ck)

                def save(res, ck=ck):
                    np.save(ck, res)
            lands = try_probes(sim, entry_up, x, probe_up, h, done=done, save=save,
                               progress=None if progress is None else
                               (lambda d, t, h=h: progress(f"{h:g} m probes", d, t)))
            for k in range(1, fill_rounds + 1) if fill_generations > 0 else ():  # new entries, then their probes
                ck = None if where is None else where / ("fill.npz" if k == 1 else f"fill{k}.npz")
                if resume and ck is not None and ck.is_file():
                    with np.load(ck) as f:
                        at, fx, fn, fc = f["holes"], f["x"], f["landed"], f["centre"]
                else:
                    shelf = Shelf(float(h), entry_up, x, landed, probe_up, lands)
                    at = fill_targets(shelf, k)
                    fx, fn, fc = fill(sim, shelf, at, generations=fill_generations, seed=seed + k,
                                      progress=None if progress is None else
                                      (lambda d, t, h=h, k=k: progress(f"{h:g} m fill {k}", d, t)))
                    if ck is not None:
                        np.savez(ck, holes=at, x=fx, landed=fn, centre=fc)  # "holes": the round's target probes
                keep = fn > 0
                entry_up = np.concatenate([entry_up, probe_up[at[keep]]])
                entry_drops = entry_drops + [up_drop(u, h).as_dict() for u in probe_up[at[keep]]]
                x = np.concatenate([x, fx[keep]])
                landed = np.concatenate([landed, fc[keep]])
                again = done if done is not None and done.shape[1] > lands.shape[1] else lands.astype(np.int8)
                lands = try_probes(sim, entry_up, x, probe_up, h, done=again, save=save,
                                   progress=None if progress is None else
                                   (lambda d, t, h=h: progress(f"{h:g} m probes", d, t)))
        finally:
            sim.close()
        shelves.append(Shelf(float(h), entry_up, x, landed, probe_up, lands, entry_drops))
    meta = {"made_by": command,
            "grid": {"sphere_points": grid, "probe_points": probes, "max_tilt_deg": max_tilt_deg},
            "search": {"generations": generations, "population": population, "restarts": restarts, "seed": seed,
                       **({"patch_deg": float(patch_deg)} if patch_deg else {}),
                       "robust": {"generations": robust_generations, "population": ROBUST_POPULATION,
                                  "offset_deg": ROBUST_OFFSET_DEG},
                       **({"fill": {"generations": fill_generations, "rounds": fill_rounds,
                                    "population": ROBUST_POPULATION,
                                    "offset_deg": FILL_OFFSET_DEG,
                                    "vote_sigma_deg": SIGMA_DEG}} if fill_generations > 0 else {})}}
    if design != "cat":
        meta["design"] = design
    return MotionLibrary(shelves, meta=meta)


def _check_sigma(sigma_deg: float | None) -> None:
    if sigma_deg is not None and not (math.isfinite(sigma_deg) and sigma_deg > 0):
        raise ParameterError(f"--sigma must be a positive number of degrees, got {sigma_deg}")


def _shelf_at(shelves, height_m: float) -> Shelf | None:
    """The shelf of exactly that drop height (None if there is none)."""
    return next((s for s in shelves if math.isclose(s.height_m, float(height_m), rel_tol=1e-6)), None)


def _shelves_for(lib: MotionLibrary, heights: Sequence[float]) -> tuple[dict, list[Shelf]]:
    """``lib``'s shelves by height, and those of ``heights`` (each must exist: one line naming those there are)."""
    shelves = {s.height_m: s for s in lib.shelves}
    picked = []
    for h in heights:
        shelf = _shelf_at(shelves.values(), h)
        if shelf is None:
            raise ParameterError(f"--heights {h:g}: the library has shelves at "
                                 f"{', '.join(f'{s:g}' for s in shelves)} m only")
        picked.append(shelf)
    return shelves, picked


def add_motions(lib: MotionLibrary, motions: Sequence[tuple[np.ndarray, dict, str]], *, workers: int | None = None,
                command: str = "", design: str = "cat",
                progress: Callable[[str, int, int], None] | None = None) -> MotionLibrary:
    """``lib`` with more entries: each motion (x (55,), the drop it was searched for, its name), for example one
    the optimum found for a hard drop (`felis eval landing --policy optimum --motions DIR`), joins the shelf of its
    drop's height (mirrored to u_y ≥ 0 when its drop is not), is tried on that drop with yaw 0 (``landed``) and,
    with its mirror image, on the probes within `EVAL_RADIUS_DEG` (the shelf's other results are kept). A start
    beyond the probes' tilt that no probe votes for then gets the nearest entry that landed: the added one near its
    drop. The meta records each addition (``added``) and the command."""
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.library import drop_up, mirror_motion, mirror_up
    from felis.learning.landing.optimum import evaluate

    shelves = {s.height_m: s for s in lib.shelves}
    added = []
    sim = design_sim(design, nthread=workers)
    try:
        for x, drop, name in motions:
            h = float(drop["height_m"])
            shelf = _shelf_at(shelves.values(), h)
            if shelf is None:
                raise ParameterError(f"{name}: a motion for a {h:g} m drop; the library has shelves at "
                                     f"{', '.join(f'{s:g}' for s in shelves)} m only (a motion is timed for its fall)")
            u = drop_up(Drop(**{k: float(drop[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg", "height_m")}))
            x = np.asarray(x, dtype=float)
            entry_drop = dict(drop)
            if u[1] < 0:  # the entry is the mirror image, and its drop the mirrored one (``added`` keeps the file's)
                u, x = mirror_up(u), mirror_motion(x)
                entry_drop.update(roll_deg=-float(drop["roll_deg"]), yaw_deg=-float(drop["yaw_deg"]))
            (_, verdict), = evaluate(sim, [up_drop(u, h)], x[None])
            up = np.concatenate([shelf.up, u[None]])
            xs = np.concatenate([shelf.x, x[None]])
            lands = try_probes(sim, up, xs, shelf.probe_up, h, done=shelf.lands.astype(np.int8),
                               progress=None if progress is None else
                               (lambda d, t, h=h: progress(f"{h:g} m probes", d, t)))
            drops = (list(shelf.drops) if shelf.drops else [up_drop(v, h).as_dict() for v in shelf.up]) + [entry_drop]
            shelves[shelf.height_m] = Shelf(shelf.height_m, up, xs, np.append(shelf.landed, bool(verdict.landed)),
                                            shelf.probe_up, lands, drops)
            added.append({"motion": name, "drop": dict(drop), "height_m": shelf.height_m,
                          "landed": bool(verdict.landed), "probes_landed": int(lands[:, -2:].any(axis=1).sum())})
    finally:
        sim.close()
    return _extended(lib, shelves, "added", added, command)


def _nearest(a: np.ndarray, b: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """For each unit vector of ``a`` (N, 3): the index of the nearest of ``b`` (M, 3) and the cosine to it, in
    chunks of ``a`` (a 368 640-point sphere against 11 000 probes is 30 GB as one matrix)."""
    idx, cos = np.empty(len(a), dtype=int), np.empty(len(a))
    for k in range(0, len(a), chunk):
        d = a[k:k + chunk] @ b.T
        idx[k:k + chunk] = np.argmax(d, axis=1)
        cos[k:k + chunk] = d[np.arange(len(d)), idx[k:k + chunk]]
    return idx, cos


def add_probes(lib: MotionLibrary, heights: Sequence[float], points: int, *, radius_deg: float = EVAL_RADIUS_DEG,
               max_tilt_deg: float = MAX_TILT_DEG, sigma_deg: float | None = None, workers: int | None = None,
               command: str = "", workdir: str | Path | None = None, resume: bool = False,
               near_misses: bool = False, design: str = "cat",
               progress: Callable[[str, int, int], None] | None = None) -> MotionLibrary:
    """``lib`` with more probes on the shelves of ``heights``: the attitudes of a ``points``-point Fibonacci sphere
    (tilt ≤ ``max_tilt_deg``, u_y ≥ 0; those already probed are skipped), each tried with the candidates within
    ``radius_deg`` of it; the shelf's other results are kept. A denser grid lets a narrower vote (``sigma_deg``,
    the shelf's own; None: the library's) tell neighbouring attitudes apart: at 3 m the choice is limited by the
    probes' spacing (docs/landing.md). ``near_misses``: only the points whose nearest probe is one of the shelf's
    `misses` (under its own vote), a refinement where the vote is wrong (at 3 m it gave most of what the whole
    grid gives, at a fifth of the points; docs/landing.md). Checkpoint per height in
    ``workdir/<h>m/probes_added.npy`` (``resume``). The meta records each addition (``probes_added``) and the
    command."""
    from felis.learning.landing.designs import design_sim

    if points < 1 or not 0 < radius_deg <= 180 or not 0 < max_tilt_deg <= 180:
        raise ParameterError(f"--add-probes needs points ≥ 1, and --probe-radius and --max-tilt within (0, 180] "
                             f"degrees; got {points} points, radius {radius_deg:g}°, maximum tilt {max_tilt_deg:g}°")
    _check_sigma(sigma_deg)
    shelves, targets = _shelves_for(lib, heights)
    added = []
    sim = design_sim(design, nthread=workers)
    try:
        for shelf in targets:
            h = shelf.height_m
            new = fibonacci_ups(points, max_tilt_deg)
            wrong = None
            if len(shelf.probe_up):
                nearest, cos = _nearest(new, shelf.probe_up)
                keep = cos < math.cos(math.radians(1e-3))  # not probed already
                if near_misses:
                    wrong = misses(shelf, lib.radius_deg, shelf.sigma_deg or lib.sigma_deg)
                    is_wrong = np.zeros(len(shelf.probe_up), dtype=bool)
                    is_wrong[wrong] = True
                    keep &= is_wrong[nearest]
                new = new[keep]
            ck = None if workdir is None else Path(workdir) / f"{h:g}m" / "probes_added.npy"
            done = None
            if ck is not None:
                ck.parent.mkdir(parents=True, exist_ok=True)
                if resume and ck.exists():
                    done = np.load(ck)
            lands = try_probes(sim, shelf.up, shelf.x, new, h, done=done, radius_deg=radius_deg,
                               save=None if ck is None else (lambda r, ck=ck: np.save(ck, r)),
                               progress=None if progress is None else
                               (lambda d, t, h=h: progress(f"{h:g} m new probes", d, t)))
            shelves[h] = Shelf(h, shelf.up, shelf.x, shelf.landed, np.concatenate([shelf.probe_up, new]),
                               np.concatenate([shelf.lands, lands]), shelf.drops,
                               sigma_deg if sigma_deg is not None else shelf.sigma_deg)
            added.append({"height_m": h, "points": int(points), "radius_deg": float(radius_deg),
                          "max_tilt_deg": float(max_tilt_deg), "probes": int(len(new)),
                          "landed_by_some": int(lands.any(axis=1).sum()),
                          **({} if wrong is None else {"near_misses": int(len(wrong))}),
                          **({} if sigma_deg is None else {"sigma_deg": float(sigma_deg)})})
    finally:
        sim.close()
    return _extended(lib, shelves, "probes_added", added, command)


def extend_shelves(lib: MotionLibrary, heights: Sequence[float], max_tilt_deg: float, *, probes: int = PROBES,
                   radius_deg: float = EVAL_RADIUS_DEG, fill_generations: int = FILL_GENERATIONS,
                   fill_rounds: int = FILL_ROUNDS, seed: int = 0, workers: int | None = None, command: str = "",
                   workdir: str | Path | None = None, resume: bool = False, design: str = "cat",
                   progress: Callable[[str, int, int], None] | None = None) -> MotionLibrary:
    """``lib`` whose shelves of ``heights`` reach further from upright, by continuation from the motions that land
    at their edge (the grid's optimum, searched from scratch, lands almost nothing tilted beyond 100°;
    docs/landing.md). Per shelf: (1) the attitudes of a ``probes``-point Fibonacci sphere tilted beyond the
    shelf's farthest probe and at most ``max_tilt_deg`` (u_y ≥ 0) become probes, each tried with the candidates
    within ``radius_deg``; (2) ``fill_rounds`` rounds of `fill` aimed at those new probes only: each round at the
    new probes no candidate lands and those where the choice, their own vote left out, picks a motion that fails
    there, each searched from the nearest candidate that lands it, else the nearest that lands something (so a
    round starts from what the last one found, further out); the new motions that land any of their five attitudes
    become entries and are tried on every probe within ``radius_deg``. The shelf's other results are kept.
    Checkpoints per height in ``workdir/<h>m/``: ``extend_probes.npy``, ``extend_fill<k>.npz``,
    ``extend_probes<k>.npy`` (``resume``). The meta records each extension (``extended``) and the command."""
    from felis.learning.landing.designs import design_sim

    if probes < 1 or not 0 < radius_deg <= 180 or not 0 < max_tilt_deg <= 180:
        raise ParameterError(f"--extend needs a maximum tilt and --probe-radius within (0, 180] degrees and --probes "
                             f"≥ 1; got {max_tilt_deg:g}°, {radius_deg:g}°, {probes} points")
    if fill_generations < 0 or fill_rounds < 0:
        raise ParameterError(f"--extend needs --fill-generations and --fill-rounds ≥ 0, got {fill_generations} and "
                             f"{fill_rounds}")
    shelves, picked = _shelves_for(lib, heights)
    targets = []
    for shelf in picked:
        reach = float(tilts_deg(shelf.probe_up).max()) if len(shelf.probe_up) else 0.0
        if max_tilt_deg <= reach + 1e-6:
            raise ParameterError(f"--extend {max_tilt_deg:g}: the {shelf.height_m:g} m shelf's probes reach "
                                 f"{reach:.1f}° already")
        targets.append((shelf, reach))
    extended = []
    sim = design_sim(design, nthread=workers)
    try:
        for shelf, reach in targets:
            h = shelf.height_m
            where = None if workdir is None else Path(workdir) / f"{h:g}m"
            if where is not None:
                where.mkdir(parents=True, exist_ok=True)

            def checkpoint(name: str, where=where):
                ck = None if where is None else where / name
                done = np.load(ck) if resume and ck is not None and ck.exists() else None
                return done, None if ck is None else (lambda r, ck=ck: np.save(ck, r))

            def bar(stage: str, h=h):
                return None if progress is None else (lambda d, t: progress(f"{h:g} m {stage}", d, t))

            new = fibonacci_ups(probes, max_tilt_deg)
            new = new[tilts_deg(new) > reach + 1e-6]
            done, save = checkpoint("extend_probes.npy")
            new_lands = try_probes(sim, shelf.up, shelf.x, new, h, done=done, save=save, radius_deg=radius_deg,
                                   progress=bar("new probes"))
            before = int(new_lands.any(axis=1).sum())
            grown = Shelf(h, shelf.up, shelf.x, shelf.landed, np.concatenate([shelf.probe_up, new]),
                          np.concatenate([shelf.lands, new_lands]), shelf.drops, shelf.sigma_deg)
            mine = np.arange(len(shelf.probe_up), len(grown.probe_up))
            shelves[h], rounds = _fill_rounds(sim, grown, mine, lib, "extend", fill_generations=fill_generations,
                                              fill_rounds=fill_rounds, seed=seed, radius_deg=radius_deg,
                                              where=where, resume=resume, bar=bar)
            lands = shelves[h].lands
            extended.append({"height_m": h, "from_deg": round(reach, 3), "max_tilt_deg": float(max_tilt_deg),
                             "points": int(probes), "radius_deg": float(radius_deg), "probes": int(len(new)),
                             "landed_by_some_before": before, "landed_by_some": int(lands[mine].any(axis=1).sum()),
                             "fill": {"generations": fill_generations, "population": ROBUST_POPULATION,
                                      "offset_deg": FILL_OFFSET_DEG, "seed": seed, "rounds": rounds}})
    finally:
        sim.close()
    return _extended(lib, shelves, "extended", extended, command)


def _fill_rounds(sim, shelf: Shelf, mine: np.ndarray, lib: MotionLibrary, name: str, *, fill_generations: int,
                 fill_rounds: int, seed: int, radius_deg: float, where: Path | None, resume: bool, bar):
    """``fill_rounds`` rounds of `fill` aimed at the probes ``mine`` of ``shelf``: each round at those that no
    candidate lands and those where the choice, their own vote left out, picks a motion that fails there; the new
    motions that land any of their five attitudes become entries, tried on every probe within ``radius_deg``.
    Checkpoints ``<name>_fill<k>.npz`` and ``<name>_probes<k>.npy`` in ``where`` (``resume``). Returns (the shelf,
    one record per round)."""
    h = shelf.height_m
    up, x, landed, probe_up, lands = shelf.up, shelf.x, shelf.landed, shelf.probe_up, shelf.lands
    drops = list(shelf.drops) if shelf.drops else [up_drop(v, h).as_dict() for v in shelf.up]
    sigma = shelf.sigma_deg or lib.sigma_deg
    rounds = []
    for k in range(1, fill_rounds + 1) if fill_generations > 0 else ():
        ck = None if where is None else where / f"{name}_fill{k}.npz"
        if resume and ck is not None and ck.is_file():
            with np.load(ck) as f:
                at, fx, fn, fc = f["targets"], f["x"], f["landed"], f["centre"]
        else:
            cur = Shelf(h, up, x, landed, probe_up, lands, drops, shelf.sigma_deg)
            at = np.union1d(mine[~lands[mine].any(axis=1)], misses(cur, lib.radius_deg, sigma, among=mine))
            fx, fn, fc = fill(sim, cur, at, generations=fill_generations, seed=seed + k, progress=bar(f"fill {k}"))
            if ck is not None:
                np.savez(ck, targets=at, x=fx, landed=fn, centre=fc)
        keep = fn > 0
        up = np.concatenate([up, probe_up[at[keep]]])
        x = np.concatenate([x, fx[keep]])
        landed = np.concatenate([landed, fc[keep]])
        drops += [up_drop(v, h).as_dict() for v in probe_up[at[keep]]]
        ck = None if where is None else where / f"{name}_probes{k}.npy"
        done = np.load(ck) if resume and ck is not None and ck.exists() else None
        lands = try_probes(sim, up, x, probe_up, h, done=lands.astype(np.int8) if done is None else done,
                           save=None if ck is None else (lambda r, ck=ck: np.save(ck, r)), radius_deg=radius_deg,
                           progress=bar("probes"))
        rounds.append({"targets": len(at), "entries": int(keep.sum()), "land_their_probe": int(fc.sum())})
    return Shelf(h, up, x, landed, probe_up, lands, drops, shelf.sigma_deg), rounds


def fill_shelves(lib: MotionLibrary, heights: Sequence[float], *, max_tilt_deg: float = 180.0,
                 radius_deg: float = EVAL_RADIUS_DEG, fill_generations: int = FILL_GENERATIONS,
                 fill_rounds: int = 1, seed: int = 0, workers: int | None = None, command: str = "",
                 workdir: str | Path | None = None, resume: bool = False, design: str = "cat",
                 progress: Callable[[str, int, int], None] | None = None) -> MotionLibrary:
    """``lib`` whose shelves of ``heights`` get new motions, searched on ``design``'s cat, where their probes (those
    tilted at most ``max_tilt_deg``) are not landed: the fill rounds of `extend_shelves` over the shelf's own probes
    (`_fill_rounds`: the holes no candidate lands, then the misses of the vote), each motion searched from the nearest
    that lands the probe or lands something. For a shelf whose motions were searched on another cat (the shipped
    ones, on `4ms-paw`): on this one they leave holes. Checkpoints per height in ``workdir/<h>m/``
    (``fill_fill<k>.npz``, ``fill_probes<k>.npy``; ``resume``). The meta records each fill (``filled``) and the
    command."""
    from felis.learning.landing.designs import design_sim

    if not 0 < radius_deg <= 180 or not 0 < max_tilt_deg <= 180:
        raise ParameterError(f"--fill DEG and --probe-radius must be within (0, 180] degrees; got "
                             f"{max_tilt_deg:g}° and {radius_deg:g}°")
    if fill_generations < 1 or fill_rounds < 1:
        raise ParameterError(f"--fill needs --fill-generations and --fill-rounds ≥ 1, got {fill_generations} and "
                             f"{fill_rounds}")
    shelves, picked = _shelves_for(lib, heights)
    filled = []
    sim = design_sim(design, nthread=workers)
    try:
        for shelf in picked:
            h = shelf.height_m
            where = None if workdir is None else Path(workdir) / f"{h:g}m"
            if where is not None:
                where.mkdir(parents=True, exist_ok=True)
            mine = np.flatnonzero(tilts_deg(shelf.probe_up) <= max_tilt_deg + 1e-6)
            before = int(shelf.lands[mine].any(axis=1).sum())

            def bar(stage: str, h=h):
                return None if progress is None else (lambda d, t: progress(f"{h:g} m {stage}", d, t))

            shelves[h], rounds = _fill_rounds(sim, shelf, mine, lib, "fill", fill_generations=fill_generations,
                                              fill_rounds=fill_rounds, seed=seed, radius_deg=radius_deg,
                                              where=where, resume=resume, bar=bar)
            filled.append({"height_m": h, "design": design, "max_tilt_deg": float(max_tilt_deg),
                           "radius_deg": float(radius_deg), "probes": int(len(mine)),
                           "landed_by_some_before": before,
                           "landed_by_some": int(shelves[h].lands[mine].any(axis=1).sum()),
                           "fill": {"generations": fill_generations, "population": ROBUST_POPULATION,
                                    "offset_deg": FILL_OFFSET_DEG, "seed": seed, "rounds": rounds}})
    finally:
        sim.close()
    return _extended(lib, shelves, "filled", filled, command)


def candidate_drop(shelf: Shelf, c: int) -> Drop:
    """The start candidate ``c`` (2·entry + 1 if mirrored) was made for: its entry's recorded drop (else the entry's
    attitude with yaw 0), mirrored (roll and yaw negated) for a mirror image."""
    if shelf.drops:
        d = shelf.drops[c // 2]
        roll, pitch, yaw = (float(d[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg"))
    else:
        e = up_drop(shelf.up[c // 2], shelf.height_m)
        roll, pitch, yaw = e.roll_deg, e.pitch_deg, e.yaw_deg
    if c & 1:
        roll, yaw = 0.0 - roll, 0.0 - yaw
    return Drop(roll, pitch, yaw, shelf.height_m)


def recheck_entries(lib: MotionLibrary, heights: Sequence[float], *, workers: int | None = None,
                    command: str = "", design: str = "cat") -> MotionLibrary:
    """``lib`` with each entry of the shelves of ``heights`` tried again on its own drop (its recorded drop, else
    its attitude with yaw 0) and its ``landed`` set to what it does: what a start that no probe votes for falls
    back on. Libraries built before `robustify`
    judged each entry on its own attitudes carry twins and fills flagged for another attitude. The probes'
    verdicts are kept; the meta records the recheck (``rechecked``) and the command."""
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.optimum import evaluate

    shelves, picked = _shelves_for(lib, heights)
    done = []
    sim = design_sim(design, nthread=workers)
    try:
        for shelf in picked:
            drops = [candidate_drop(shelf, 2 * i) for i in range(len(shelf.up))]
            landed = np.array([v.landed for _, v in evaluate(sim, drops, shelf.x)], dtype=bool)
            shelves[shelf.height_m] = Shelf(shelf.height_m, shelf.up, shelf.x, landed, shelf.probe_up, shelf.lands,
                                            shelf.drops, shelf.sigma_deg)
            done.append({"height_m": shelf.height_m, "entries": len(landed), "landed": int(landed.sum()),
                         "was_landed": int(shelf.landed.sum()), "changed": int((landed != shelf.landed).sum())})
    finally:
        sim.close()
    return _extended(lib, shelves, "rechecked", done, command)


def replace_shelves(base: MotionLibrary, built: MotionLibrary, command: str = "") -> MotionLibrary:
    """``base`` with ``built``'s shelves in place of those of the same heights (a height ``base`` lacks is added):
    one shelf rebuilt, say with another search, the others kept. ``base``'s vote (radius, σ) is kept; the
    records of what was added to the replaced shelves (``added``, ``probes_added``) go with them, and the meta
    records the rebuild (``rebuilt``: the heights, ``built``'s grid and search) and the command (``extended_by``)."""
    def replaced(h: float) -> bool:
        return _shelf_at(built.shelves, h) is not None

    shelves = {s.height_m: s for s in base.shelves if not replaced(s.height_m)}
    shelves.update({s.height_m: s for s in built.shelves})
    meta = dict(base.meta)
    for key in ("added", "probes_added"):
        if key in meta:
            meta[key] = [a for a in meta[key] if not replaced(a["height_m"])]
    rebuilt = [{"heights": built.heights, **{k: built.meta[k] for k in ("grid", "search") if k in built.meta}}]
    return _extended(MotionLibrary(list(shelves.values()), base.radius_deg, base.sigma_deg, meta=meta), shelves,
                     "rebuilt", rebuilt, command)


def join_shelves(base: MotionLibrary, other: MotionLibrary, heights: Sequence[float], *,
                 sigma_deg: float | None = None, command: str = "") -> MotionLibrary:
    """``base`` whose shelves of ``heights`` also hold ``other``'s motions for those heights: the entries (those not
    in ``base`` already) appended and their verdicts on the probes kept, so the vote chooses among both searches'
    candidates. Both shelves must have the same probes (build both the same way, or give both the same
    ``--add-probes``): a verdict is only comparable on the same attitude. ``sigma_deg``: those shelves' vote
    width (None: as it was); ``base``'s other shelves are kept; the meta records the join (``joined``) and the
    command."""
    _check_sigma(sigma_deg)
    shelves = {s.height_m: s for s in base.shelves}
    joined = []
    for h in heights:
        mine = _shelf_at(shelves.values(), h)
        theirs = _shelf_at(other.shelves, h)
        if mine is None or theirs is None:
            lacks = "--base" if mine is None else "--join"
            raise ParameterError(f"--heights {h:g}: the {lacks} library has no shelf for that height")
        if mine.probe_up.shape != theirs.probe_up.shape or not np.allclose(mine.probe_up, theirs.probe_up,
                                                                          atol=1e-6):
            raise ParameterError(f"{h:g} m: the two shelves have different probes ({len(mine.probe_up)} and "
                                 f"{len(theirs.probe_up)}); give both the same --add-probes first")
        new = [i for i in range(len(theirs.x)) if not np.any(np.all(mine.x == theirs.x[i], axis=1))]
        cols = np.array([2 * i + k for i in new for k in (0, 1)], dtype=int)
        drops = None
        if mine.drops is not None and theirs.drops is not None:
            drops = list(mine.drops) + [theirs.drops[i] for i in new]
        shelves[mine.height_m] = Shelf(mine.height_m, np.concatenate([mine.up, theirs.up[new]]),
                                       np.concatenate([mine.x, theirs.x[new]]),
                                       np.concatenate([mine.landed, theirs.landed[new]]), mine.probe_up,
                                       np.concatenate([mine.lands, theirs.lands[:, cols]], axis=1), drops,
                                       mine.sigma_deg if sigma_deg is None else float(sigma_deg))
        joined.append({"height_m": mine.height_m, "entries": len(new), "made_by": other.meta.get("made_by", ""),
                       **({} if sigma_deg is None else {"sigma_deg": float(sigma_deg)}),
                       **({"extended_by": other.meta["extended_by"]} if other.meta.get("extended_by") else {})})
    return _extended(base, shelves, "joined", joined, command)


def _extended(lib: MotionLibrary, shelves: dict, key: str, added: list, command: str) -> MotionLibrary:
    """``lib`` with ``shelves`` (by height) and the record of what was added (``meta[key]``, ``extended_by``)."""
    meta = dict(lib.meta)
    meta[key] = list(meta.get(key, [])) + added
    if command:
        meta["extended_by"] = list(meta.get("extended_by", [])) + [command]
    return MotionLibrary(list(shelves.values()), lib.radius_deg, lib.sigma_deg, meta=meta)
