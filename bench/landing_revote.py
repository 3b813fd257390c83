"""Bench: the motion library's vote taken again on another paw and physics step (issue 21: "a library voted on that
paw and step").

A library's shelf for one height voted on one cat and step: which of its candidates (entries and their mirror
images) lands each probe. On another paw, or at a step that resolves the impact differently, the same motions land
other attitudes (the library was voted on the 4 ms-paw cat at 1 ms, the cat as described until 2026-11-29, and
then, by this bench, on the described cat's rubber paws at 0.5 ms, then the design ``rubber-paw``). This
re-tries, for each probe, the candidates the vote would weigh there: the ``--top`` best by the shipped vote at the
probe's attitude and the ``--nearest`` nearest by attitude (the union), on DESIGN at STEP; a shelf whose ``lands``
are those results (the pairs not re-tried count as not landing) is then the re-voted library, written to
``--out``, and evaluated beside the shipped one on ``random:100`` of each ``--seeds`` (`felis eval landing`'s drops
and verdict) at the same design and step.

Which probes: all of the shelf's (``--near-deg 0``, the whole re-vote: ~11 000 at 3 m, hours of 2 cores), or
those within ``--near-deg`` of the evaluated drops' attitudes. The vote at an attitude weighs probes by
exp(−½(angle/σ)²) with σ the shelf's (0.75° at 3 m), so probes 3° away weigh exp(−8) of those on top of it: the
choice at the evaluated drops then is the whole re-vote's, except where no re-tried candidate lands any probe
within ``--near-deg`` (the fallback, the nearest entry that landed its own drop, then decides; counted). The
candidates and the vote's σ and radius are the shipped library's: nothing here is chosen on the evaluated drops'
outcomes. Checkpoints (``--out`` + ``.npz``) after every batch; ``--resume`` goes on from them.

    python bench/landing_revote.py [--design cat] [--timestep MS] --height 3 --seeds 0 1 --near-deg 3 \
        --out /tmp/revote.json [--resume] [--workers N] [--json]

``--out`` is a votes file (`felis.learning.landing.library`, "Votes file"): the re-voted shelves' lands over the
library ``--library`` names (a votes file given as ``--library`` adds its shelves), with each shelf's options and
results under ``revoted``. The shipped library's own vote was made as ``--library
learning/weights/landing_library_4ms-paw.json --height 3 --near-deg 0 --out V3.json`` (73 min on 2 cores) then
``--library V3.json --height 1 --near-deg 0 --out V.json`` (13 min), and written into ``landing_library.json``
(then a file of its own, for the design ``rubber-paw``; the candidates ranked by the 4 ms-paw cat's vote).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from felis.learning.landing.library import (
    DEFAULT_LIBRARY,
    MotionLibrary,
    Shelf,
    _half,
    angles_deg,
    drop_up,
    load_library,
    votes_dict,
)
from felis.learning.landing.library_build import CHUNK, up_drop
from felis.scenarios.drop import random_drops


def candidates_to_try(shelf: Shelf, probes: np.ndarray, top: int, nearest: int, radius_deg: float,
                      sigma_deg: float) -> list[np.ndarray]:
    """For each probe index in ``probes``: the candidate ids to re-try (the ``top`` best-voted at its attitude, with
    the shelf's lands and vote; then the ``nearest`` nearest by attitude), unique, in that order."""
    cand_up = shelf.candidates()[0]
    out = []
    for p in probes:
        u = shelf.probe_up[p]
        a = angles_deg(u, shelf.probe_up)
        voters = np.flatnonzero(a <= radius_deg)
        score = np.exp(-0.5 * (a[voters] / sigma_deg) ** 2) @ shelf.lands[voters]
        near = angles_deg(u, cand_up)
        by_vote = [int(c) for c in np.lexsort((near, -score))[:top] if score[c] > 0]
        by_angle = [int(c) for c in np.argsort(near, kind="stable")[:nearest]]
        out.append(np.array(list(dict.fromkeys(by_vote + by_angle)), dtype=int))
    return out


def revote(lib: MotionLibrary, height_m: float, probes: np.ndarray, tries: list[np.ndarray], sim, *,
           state: Path | None = None, resume: bool = False, progress=None) -> np.ndarray:
    """(P, 2E) bool: the re-tried pairs' results on ``sim`` (pairs not tried: False). Checkpointed in ``state``."""
    from felis.learning.landing.optimum import evaluate

    shelf = lib.shelf(height_m)
    _, cand_x, _ = shelf.candidates()
    pairs = np.array([(p, c) for p, cs in zip(probes, tries, strict=True) for c in cs], dtype=int).reshape(-1, 2)
    res = np.full(len(pairs), -1, dtype=np.int8)
    if resume and state is not None and state.exists():
        with np.load(state) as f:
            if np.array_equal(f["pairs"], pairs):
                res = f["res"].copy()
            else:
                sys.exit(f"{state}: a checkpoint of other pairs (other options or library); remove it or drop --resume")
    todo = np.flatnonzero(res < 0)
    for k in range(0, len(todo), CHUNK):
        part = todo[k:k + CHUNK]
        drops = [up_drop(shelf.probe_up[p], height_m) for p in pairs[part, 0]]
        out = evaluate(sim, drops, cand_x[pairs[part, 1]])
        res[part] = [int(v.landed) for _, v in out]
        if state is not None:
            np.savez(state, pairs=pairs, res=res)
        if progress is not None:
            progress(len(pairs) - len(todo) + k + len(part), len(pairs))
    lands = np.zeros_like(shelf.lands)
    ok = res == 1
    lands[pairs[ok, 0], pairs[ok, 1]] = True
    return lands


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--library", type=Path, default=DEFAULT_LIBRARY)
    ap.add_argument("--design", default="cat")
    ap.add_argument("--timestep", type=float, metavar="MS", help="physics step (ms; default the design's)")
    ap.add_argument("--height", type=float, default=3.0, help="the shelf (drop height, m)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="random:100 seeds evaluated")
    ap.add_argument("--near-deg", type=float, default=3.0, help="probes this close to an evaluated drop (0: all)")
    ap.add_argument("--top", type=int, default=4, help="candidates re-tried per probe, best-voted first")
    ap.add_argument("--nearest", type=int, default=4, help="and the nearest by attitude")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--out", type=Path, required=True, help="the re-voted library (JSON); checkpoint beside it")
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.evaluate import run_drops

    lib = load_library(args.library)
    shelf = lib.shelf(args.height)
    sigma = shelf.sigma_deg or lib.sigma_deg
    if args.timestep is None:
        from felis.learning.landing.designs import design_timestep

        args.timestep = design_timestep(args.design) * 1000.0
    step = args.timestep / 1000.0
    drops = {s: random_drops(100, seed=s, heights=(args.height,)) for s in args.seeds}
    if args.near_deg > 0:
        ups = np.array([_half(drop_up(d))[0] for ds in drops.values() for d in ds])
        probes = np.flatnonzero((angles_deg(ups, shelf.probe_up) <= args.near_deg).any(axis=0))
    else:
        probes = np.arange(len(shelf.probe_up))
    tries = candidates_to_try(shelf, probes, args.top, args.nearest, lib.radius_deg, sigma)
    n_pairs = sum(len(t) for t in tries)
    print(f"{args.height:g} m shelf: {len(probes)} of {len(shelf.probe_up)} probes, {n_pairs} pairs to try on "
          f"{args.design} at {args.timestep:g} ms", file=sys.stderr)
    sim = design_sim(args.design, nthread=args.workers, timestep=step)
    t0 = time.perf_counter()

    def progress(done: int, total: int) -> None:
        el = time.perf_counter() - t0
        print(f"\r  {done}/{total} rollouts, {el:.0f} s", end="", file=sys.stderr, flush=True)

    try:
        lands = revote(lib, args.height, probes, tries, sim, state=args.out.with_suffix(".npz"), resume=args.resume,
                       progress=progress)
    finally:
        sim.close()
    print(file=sys.stderr)
    shelf.lands = lands
    revoted = {**lib.meta.get("revoted", {}), f"{args.height:g}m": {
        "design": args.design, "timestep_ms": args.timestep, "near_deg": args.near_deg, "seeds": args.seeds,
        "top": args.top, "nearest": args.nearest, "pairs": n_pairs}}
    base = args.library.parent / lib.meta["votes_of"]["file"] if "votes_of" in lib.meta else args.library
    heights = [float(k.removesuffix("m")) for k in revoted]
    args.out.write_text(json.dumps(votes_dict(lib, base, args.out, heights, {
        "made_by": "bench/landing_revote.py", "revoted": revoted})))
    rows = {}
    for s, ds in drops.items():
        row = {}
        for name, path in (("shipped", args.library), ("revoted", args.out)):
            out = run_drops(ds, str(path), workers=args.workers, design=args.design, timestep=step)
            row[name] = sum(o.landed for o in out)
        fallback = 0
        for d in ds:
            u = _half(drop_up(d))[0]
            a = angles_deg(u, shelf.probe_up)
            v = np.flatnonzero(a <= lib.radius_deg)
            fallback += not (np.exp(-0.5 * (a[v] / sigma) ** 2) @ shelf.lands[v]).any()
        row["fallback"] = fallback
        rows[s] = row
    res = {"height_m": args.height, "design": args.design, "timestep_ms": args.timestep, "probes": int(len(probes)),
           "pairs": n_pairs, "seconds": round(time.perf_counter() - t0), "landed": rows}
    doc = json.loads(args.out.read_text())  # the results beside the vote they are of
    doc["revoted"][f"{args.height:g}m"].update(probes=res["probes"], seconds=res["seconds"], landed=rows)
    args.out.write_text(json.dumps(doc))
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        for s, r in rows.items():
            print(f"random:100 --seed {s} at {args.height:g} m on {args.design} at {args.timestep:g} ms: shipped "
                  f"library {r['shipped']}, re-voted {r['revoted']} ({r['fallback']} drops chose by the fallback)")


if __name__ == "__main__":
    main()
