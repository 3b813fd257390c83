"""How many distinct open-loop motions landing takes: the most drops K of the library's motions can land.

The paper's landing controller (seed 000 §6.2–6.5) is a compose net dispatching a few simple behaviours, each
evolved to imitate one motion sample (seven in the paper). Whatever the nets learn, a dispatcher of K behaviours
that each reproduce one open-loop motion lands no more drops than the best K motions would with a perfect
choice. This bench measures that bound on the shipped library's motions:

1. for each drop of ``random:N`` (``--seed``, at ``--height``), every candidate of the shelf (entry or mirror image)
   whose start attitude is within ``--radius`` of the drop's, and the library's own choice, are run on the drop
   (on its yaw-0 half-sphere image, the attitude the shelf covers; a turn about the vertical changes nothing in
   a fall): a matrix L[drop, candidate] of landings;
2. for each K of ``--k``, the exact maximum coverage (`max_cover`: the K candidates that together land the most
   drops, an integer program solved by `scipy.optimize.milp`), and the fewest candidates that land as many drops
   as all of them (`min_cover`), and that land ``--goal`` drops.

    python bench/landing_cover.py [--height 1] [--seed 0] [--n 100] [--radius 30] [--k 1 3 7 15 30] [--goal 75]
        [--design cat] [--out FILE.json] [--motions-from FILE.json] [--json]

A candidate is a motion in the frame of the half sphere the shelf covers (u_y ≥ 0): a drop of the other half runs
its mirror image, so K motions are K behaviours that each also run mirrored. The bound is in-sample (the K motions
are chosen for these drops), so for held-out drops it is optimistic, and ``--motions-from`` measures it held out;
and it bounds open-loop imitation only: a closed-loop behaviour may turn one motion into several. The library's
own count here is on the yaw-0 images, so it can differ by a drop or two from ``felis eval landing``'s (at 3 m
a millimetre or a rounding can flip a landing). On the described cat, 1 m, 30°: about 10 000 rollouts, 9 minutes
on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from felis.cli.output import progress
from felis.errors import ParameterError
from felis.files import write_atomic
from felis.learning.landing.designs import design_library, design_sim
from felis.learning.landing.library import DEFAULT_LIBRARY, _half, _sha256, angles_deg, drop_up, load_library
from felis.learning.landing.library_build import tilts_deg, up_drop
from felis.learning.landing.optimum import evaluate
from felis.scenarios.drop import random_drops

CHUNK = 256


def _cover_program(lands: np.ndarray):
    """(cols, A, n_c): the candidates that land something, and the rows z_d − Σ_{c lands d} y_c ≤ 0 over the
    variables [y (n_c), z (drops)]."""
    cols = np.flatnonzero(lands.any(axis=0))
    sub = lands[:, cols].astype(float)
    n_d, n_c = sub.shape
    return cols, np.hstack([-sub, np.eye(n_d)]), n_c


def max_cover(lands: np.ndarray, k: int) -> tuple[int, list[int]]:
    """The most drops (rows of the bool matrix ``lands``) that ``k`` candidates (columns) land together, and
    those candidates (column indices), by the integer program max Σ z_d s.t. z_d ≤ Σ_{c lands d} y_c,
    Σ y_c ≤ k, y, z ∈ {0, 1}."""
    from scipy.optimize import Bounds, LinearConstraint, milp

    if k < 0:
        raise ParameterError(f"cover: K must be ≥ 0, got {k}")
    cols, A, n_c = _cover_program(lands)
    n_d = lands.shape[0]
    if n_c == 0 or k == 0:
        return 0, []
    cost = np.concatenate([np.zeros(n_c), -np.ones(n_d)])
    budget = np.concatenate([np.ones(n_c), np.zeros(n_d)])[None]
    res = milp(cost, constraints=[LinearConstraint(A, -np.inf, 0.0), LinearConstraint(budget, 0, k)],
               integrality=np.ones(n_c + n_d), bounds=Bounds(0, 1))
    if not res.success:
        raise RuntimeError(f"cover: the solver failed ({res.message})")
    chosen = [int(cols[i]) for i in np.flatnonzero(res.x[:n_c] > 0.5)]
    return int(lands[:, chosen].any(axis=1).sum()), chosen


def min_cover(lands: np.ndarray, target: int) -> list[int] | None:
    """The fewest candidates (columns) that together land at least ``target`` drops (rows); None if all of them
    land fewer."""
    from scipy.optimize import Bounds, LinearConstraint, milp

    cols, A, n_c = _cover_program(lands)
    n_d = lands.shape[0]
    if target <= 0:
        return []
    if int(lands.any(axis=1).sum()) < target:
        return None
    cost = np.concatenate([np.ones(n_c), np.zeros(n_d)])
    need = np.concatenate([np.zeros(n_c), np.ones(n_d)])[None]
    res = milp(cost, constraints=[LinearConstraint(A, -np.inf, 0.0), LinearConstraint(need, target, np.inf)],
               integrality=np.ones(n_c + n_d), bounds=Bounds(0, 1))
    if not res.success:
        raise RuntimeError(f"cover: the solver failed ({res.message})")
    return [int(cols[i]) for i in np.flatnonzero(res.x[:n_c] > 0.5)]


def load_cover(path) -> tuple[dict, np.ndarray]:
    """(the results, L (drops, candidates) bool) of a run's ``--out`` file."""
    doc = json.loads(Path(path).read_text())
    lands = np.zeros((doc["drops"], doc["candidates"]), bool)
    if doc["landed_pairs"]:
        lands[tuple(np.array(doc["landed_pairs"]).T)] = True
    return doc, lands


def cover_of(lands: np.ndarray, motions) -> int:
    """How many drops (rows) some candidate of ``motions`` (column indices) lands."""
    return int(lands[:, list(motions)].any(axis=1).sum()) if len(motions) else 0


def nearest_choice(ups: np.ndarray, cand_up: np.ndarray, motions) -> np.ndarray:
    """For each drop's half-sphere up axis (rows of ``ups``), the one of ``motions`` (candidate ids) whose start is
    nearest: the simplest dispatcher a net could learn."""
    m = np.asarray(list(motions), dtype=int)
    return m[np.argmin(angles_deg(ups, cand_up[m]), axis=1)]


def pairs_to_try(shelf, drops, radius_deg: float, choose) -> tuple[list[tuple[int, int]], np.ndarray]:
    """((drop, candidate) pairs, chosen (drops,)): each candidate within ``radius_deg`` of a drop, and the one
    ``choose(u)`` (the library's vote) picks for it, from the drop's half-sphere up axis u."""
    cand_up = shelf.candidates()[0]
    chosen = np.empty(len(drops), int)
    pairs = []
    for i, d in enumerate(drops):
        u = _half(drop_up(d))[0]
        chosen[i] = choose(u)
        near = set(np.flatnonzero(angles_deg(u, cand_up) <= radius_deg).tolist()) | {int(chosen[i])}
        pairs += [(i, c) for c in sorted(near)]
    return pairs, chosen


def landing_matrix(sim, shelf, drops, pairs, step=None) -> np.ndarray:
    """L (drops, 2E) bool: L[d, c] whether candidate c lands d's yaw-0 half-sphere image, for the ``pairs`` (d, c)
    (False elsewhere). ``step(n)``: called after each batch of n rollouts (a progress bar)."""
    cand_x = shelf.candidates()[1]
    lands = np.zeros((len(drops), len(cand_x)), bool)
    for k in range(0, len(pairs), CHUNK):
        part = pairs[k:k + CHUNK]
        ds = [up_drop(_half(drop_up(drops[i]))[0], drops[i].height_m) for i, _ in part]
        for (i, c), (_, v) in zip(part, evaluate(sim, ds, cand_x[[c for _, c in part]]), strict=True):
            lands[i, c] = v.landed
        if step is not None:
            step(len(part))
    return lands


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n", type=int, default=100, help="drops (random:N; default 100)")
    ap.add_argument("--radius", type=float, default=30.0, help="candidates this close to a drop are tried (deg)")
    ap.add_argument("--k", type=int, nargs="+", default=[1, 3, 7, 15, 30])
    ap.add_argument("--goal", type=int, default=75, help="the fewest motions that land this many drops")
    ap.add_argument("--design", default="cat")
    ap.add_argument("--motions-from", type=Path, metavar="FILE.json",
                    help="another run's --out: how many of these drops its K motions land (held out)")
    ap.add_argument("--out", type=Path, metavar="FILE.json", help="also write the results with the landing matrix")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if not 0 < args.radius <= 180:
        ap.error(f"--radius must be in (0, 180], got {args.radius:g}")
    if args.n < 1 or min(args.k) < 0:
        ap.error(f"--n must be ≥ 1 and every --k ≥ 0, got --n {args.n} and --k {' '.join(map(str, args.k))}")

    library_file = design_library(args.design) or DEFAULT_LIBRARY
    lib = load_library(library_file)
    shelf = lib.shelf(args.height)
    sigma = shelf.sigma_deg or lib.sigma_deg
    if args.motions_from is not None:  # checked before the rollouts
        if not args.motions_from.is_file():
            ap.error(f"--motions-from {args.motions_from}: no such file")
        try:
            other = load_cover(args.motions_from)[0]
        except (OSError, ValueError, KeyError, IndexError) as e:
            ap.error(f"--motions-from {args.motions_from}: not a cover results file written by --out "
                     f"({type(e).__name__}: {e})")
        if other.get("library_sha256") != _sha256(Path(library_file)) or other.get("height_m") != args.height:
            ap.error(f"--motions-from {args.motions_from}: made on another library or height")
    drops = random_drops(args.n, seed=args.seed, heights=(args.height,))
    pairs, chosen = pairs_to_try(shelf, drops, args.radius, lambda u: shelf.choose(u, lib.radius_deg, sigma)[1])
    tried = len(pairs)
    sim = design_sim(args.design, nthread=None)
    t0 = time.perf_counter()
    bar, step = progress(tried, "rollouts", quiet=args.json or not sys.stderr.isatty())
    try:
        with bar:
            lands = landing_matrix(sim, shelf, drops, pairs, step)
    finally:
        sim.close()
    secs = time.perf_counter() - t0
    tilt = tilts_deg(np.stack([drop_up(d) for d in drops]))
    library = lands[np.arange(len(drops)), chosen]
    some = lands.any(axis=1)
    every = min_cover(lands, int(some.sum()))
    goal = min_cover(lands, args.goal)
    res = {"height_m": args.height, "seed": args.seed, "drops": len(drops), "design": args.design,
           "radius_deg": args.radius, "candidates": int(lands.shape[1]), "rollouts": tried, "seconds": round(secs),
           "library_lands": int(library.sum()), "library_motions_used": int(len(set(chosen.tolist()))),
           "some_candidate_lands": int(some.sum()), "fewest_for_all_of_them": len(every),
           "goal": args.goal, "fewest_for_goal": None if goal is None else len(goal),
           "max_cover": {}, "max_cover_motions": {},
           "unlanded_tilts": sorted(round(float(t)) for t in tilt[~some])}
    for k in args.k:
        res["max_cover"][str(k)], res["max_cover_motions"][str(k)] = max_cover(lands, k)
    if args.motions_from is not None:
        ups = np.stack([_half(drop_up(d))[0] for d in drops])
        cand_up = shelf.candidates()[0]
        res["held_out"] = {"motions_from_seed": other["seed"],
                           "cover": {k: cover_of(lands, m) for k, m in other["max_cover_motions"].items()},
                           "nearest": {k: int(lands[np.arange(len(drops)), nearest_choice(ups, cand_up, m)].sum())
                                       for k, m in other["max_cover_motions"].items()}}
    if args.out is not None:  # the whole matrix: the covers can be recomputed, and any pair run again
        write_atomic(args.out, json.dumps({**res, "library": Path(library_file).name,
                                           "library_sha256": _sha256(Path(library_file)), "chosen": chosen.tolist(),
                                           "landed_pairs": np.argwhere(lands).tolist()}).encode(),
                     "cover results", ParameterError)
    if args.json:
        print(json.dumps(res, indent=1))
        return
    print(f"{args.height:g} m, random:{args.n} seed {args.seed} ({args.design}), candidates within {args.radius:g}°: "
          f"{tried} rollouts in {secs:.0f} s")
    print(f"  the library lands {res['library_lands']} with {res['library_motions_used']} distinct motions; some "
          f"candidate lands {res['some_candidate_lands']}; the fewest that land those: {res['fewest_for_all_of_them']}")
    print(f"  the fewest that land {args.goal}: {res['fewest_for_goal'] if goal is not None else 'none do'}")
    print("  the most K motions land: " + ", ".join(f"K={k} {v}" for k, v in res["max_cover"].items()))
    if "held_out" in res:
        held = res["held_out"]
        print(f"  the K motions chosen on seed {held['motions_from_seed']} land (perfect choice / nearest start): "
              + ", ".join(f"K={k} {v}/{held['nearest'][k]}" for k, v in held["cover"].items()))


if __name__ == "__main__":
    main()
