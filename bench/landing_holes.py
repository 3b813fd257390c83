"""Where the motion library loses held-out drops: beyond its shelf, in its shelf's holes, or in its vote.

For a shelf (drop height H) of the library and the drops of ``random:100`` (``--n``) for each ``--seeds`` at H:

1. **the shelf's holes**: its probes, by start tilt, that no candidate (entry or mirror image) lands in the shelf's
   own results (the vote's data), and the vote's misses (`felis.learning.landing.library_build.misses`);
2. **the drops the library loses** (`felis eval landing`'s drops and verdict), by start tilt, and for each whether
   some candidate within ``--radius`` of its attitude lands it (each tried on the drop's attitude with yaw 0, the
   half-sphere image the shelf covers): a candidate that does is a loss of the vote; none is a loss of the shelf
   (a hole, or a tilt beyond its farthest probe);
3. with ``--fill-sample N``: the first round of ``felis train landing-library --fill`` (`fill`, 8 generations) on N
   of the shelf's holes tilted ``--band`` (drawn with seed 0): how many land their probe, and the seconds a target.

    python bench/landing_holes.py [--height 1] [--seeds 10 11 12] [--radius 15] [--fill-sample 24 --band 60 130] \
        [--design cat] [--lost FILE] [--json]

``--lost FILE`` writes the lost drops as a drops file, for the ceiling of exactly those drops: ``felis eval landing
--policy optimum --warm-start --restarts 1 --drops FILE`` (its seeds include the library's choice, so the ceiling of
the seeds' drops is the library's landings plus what it lands of these).

On the described cat: about 2 minutes for three seeds on 2 cores; the fill sample about 20 s a target.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from felis.learning.landing.designs import design_library, design_sim
from felis.learning.landing.evaluate import run_drops
from felis.learning.landing.library import DEFAULT_LIBRARY, _half, angles_deg, drop_up, load_library
from felis.learning.landing.library_build import fill, misses, tilts_deg, up_drop
from felis.learning.landing.optimum import evaluate
from felis.scenarios.drop import random_drops

BANDS = (0, 60, 90, 110, 130, 150, 180)


def band_counts(tilts: np.ndarray, mask: np.ndarray) -> dict[str, list[int]]:
    """{"a-b": [count where mask, count]} per band of start tilt (degrees)."""
    return {f"{a}-{b}": [int((mask & (tilts >= a) & (tilts < b)).sum()), int(((tilts >= a) & (tilts < b)).sum())]
            for a, b in zip(BANDS, BANDS[1:], strict=False)}


def losses(sim, shelf, library: str, design: str, seed: int, height_m: float, radius_deg: float, n: int = 100
           ) -> dict:
    """The library's lost drops of ``random:n`` seed ``seed``: their tilts, and which a candidate within
    ``radius_deg`` lands."""
    drops = random_drops(n, seed=seed, heights=(height_m,))
    outs = run_drops(drops, library, design=design)
    lost = [i for i, o in enumerate(outs) if not o.landed]
    cand_up, cand_x = shelf.candidates()[:2]
    pairs = []
    for i in lost:
        u = _half(drop_up(drops[i]))[0]
        pairs += [(i, int(c)) for c in np.flatnonzero(angles_deg(u, cand_up) <= radius_deg)]
    ok = []
    for k in range(0, len(pairs), 256):
        part = pairs[k:k + 256]
        ds = [up_drop(_half(drop_up(drops[i]))[0], height_m) for i, _ in part]
        ok += [v.landed for _, v in evaluate(sim, ds, cand_x[[c for _, c in part]])]
    rescued = sorted({i for (i, _), y in zip(pairs, ok, strict=True) if y})
    tilt = {i: float(tilts_deg(drop_up(drops[i])[None])[0]) for i in lost}
    return {"seed": seed, "drops": n, "landed": n - len(lost), "lost": len(lost), "pairs_tried": len(pairs),
            "lost_drops": [drops[i].as_dict() for i in lost],
            "lost_tilts": [round(tilt[i]) for i in lost], "a_candidate_lands": len(rescued),
            "rescued_tilts": [round(tilt[i]) for i in rescued]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=float, default=1.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[10, 11, 12])
    ap.add_argument("--n", type=int, default=100, help="drops per seed (random:N; default 100)")
    ap.add_argument("--radius", type=float, default=15.0, help="candidates this close to a lost drop are tried")
    ap.add_argument("--design", default="cat")
    ap.add_argument("--fill-sample", type=int, default=0, metavar="N", help="fill N holes (default 0: none)")
    ap.add_argument("--band", type=float, nargs=2, default=[60.0, 130.0], metavar=("LO", "HI"))
    ap.add_argument("--lost", type=Path, metavar="FILE", help="write the lost drops (a drops file)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    library = str(design_library(args.design) or DEFAULT_LIBRARY)
    lib = load_library(library)
    shelf = lib.shelf(args.height)
    t = tilts_deg(shelf.probe_up)
    holes = ~shelf.lands.any(axis=1)
    missed = np.zeros(len(t), bool)
    missed[misses(shelf, lib.radius_deg, shelf.sigma_deg or lib.sigma_deg)] = True
    res = {"height_m": args.height, "design": args.design, "probes": len(t), "holes": int(holes.sum()),
           "misses": int(missed.sum()), "holes_by_tilt": band_counts(t, holes),
           "misses_by_tilt": band_counts(t, missed), "seeds": []}
    sim = design_sim(args.design, nthread=None)
    try:
        for s in args.seeds:
            res["seeds"].append(losses(sim, shelf, library, args.design, s, args.height, args.radius, args.n))
            if not args.json:
                r = res["seeds"][-1]
                print(f"seed {s}: landed {r['landed']}; of the {r['lost']} lost, a candidate within {args.radius:g}° "
                      f"lands {r['a_candidate_lands']} ({r['rescued_tilts']}); lost tilts {sorted(r['lost_tilts'])}",
                      flush=True)
        if args.fill_sample > 0:
            lo, hi = args.band
            pool = np.flatnonzero(holes & (t >= lo) & (t < hi))
            pick = np.sort(np.random.default_rng(0).choice(pool, size=min(args.fill_sample, len(pool)),
                                                           replace=False))
            t0 = time.perf_counter()
            _, five, centre = fill(sim, shelf, pick, seed=1)
            dt = time.perf_counter() - t0
            res["fill_sample"] = {"band_deg": [lo, hi], "holes_in_band": int(len(pool)), "targets": int(len(pick)),
                                  "land_their_probe": int(centre.sum()), "land_one_of_five": int((five > 0).sum()),
                                  "s_per_target": round(dt / max(1, len(pick)), 1)}
    finally:
        sim.close()
    if args.lost is not None:
        args.lost.write_text(json.dumps([d for r in res["seeds"] for d in r["lost_drops"]], indent=1))
    if args.json:
        print(json.dumps(res, indent=1))
        return
    print(f"{args.height:g} m shelf ({args.design}): {res['probes']} probes, {res['holes']} holes, "
          f"{res['misses']} misses of the vote")
    print("  holes by tilt:  " + ", ".join(f"{k}° {v[0]}/{v[1]}" for k, v in res["holes_by_tilt"].items()))
    print("  misses by tilt: " + ", ".join(f"{k}° {v[0]}/{v[1]}" for k, v in res["misses_by_tilt"].items()))
    if "fill_sample" in res:
        f = res["fill_sample"]
        print(f"fill sample: {f['targets']} of the {f['holes_in_band']} holes tilted {f['band_deg'][0]:g}–"
              f"{f['band_deg'][1]:g}°: {f['land_their_probe']} land their probe, {f['land_one_of_five']} one of its "
              f"five attitudes; {f['s_per_target']} s a target")


if __name__ == "__main__":
    main()
