"""A touchdown closed on the IMU, on top of the motion library: does it land more drops?

The library (`learning.landing.library`) plays an open-loop motion chosen at release. Most of its failures from 3 m
end upright with a leg link on the floor (docs/landing.md), and `bench/landing_roughness.py` shows that a degree of
release attitude decides. The simplest closed loop: below ``--on`` m of waist height, each leg's pitch and roll
targets are offset by −k × the upper body's pitch and roll from its IMU (the legs held vertical in the world, with
gain k; k < 0 turns them the other way), frozen from ``--freeze`` m down (the touchdown), with body tilts beyond
60° left alone. Every variant runs the same `random:100` drops in one batch each (`learning.landing.evaluate.
BatchLandingSim`) against the library alone.

    python bench/landing_touchdown.py [--height 3] [--seeds 2 3] [--gains 0 0.1 -0.1 0.3 1] [--on 0.6]
        [--freeze 0.2] [--json]
    python bench/landing_touchdown.py --search 40 --max-tilt 90 --seeds 4 --gains 0 0.3 1   # … inside the search

``--search N``: the closed loop where it belongs, inside the search: each of N drops gets its own motion searched
with the feedback on (`robustness`), and each motion that lands is tried from attitudes 1° and 2° away (roll,
pitch and the diagonals, each way): does a closed-loop touchdown make a landing hold over a wider patch of
attitudes? ``--patch D``: the search must land the attitudes D away in roll and pitch too (the worst of five).
``--patch-mm M``: the search must land the drop from M mm lower and higher too (the worst of three); each landing
motion is then also run from 1, 2 and 3 mm lower and higher: does a landing hold over a band of drop heights?
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from felis.controllers.landing import LandingBatch
from felis.learning.landing.designs import joint_speeds
from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ, BatchLandingSim
from felis.learning.landing.library import DEFAULT_LIBRARY, LibraryBatch, load_library
from felis.learning.landing.motion import DT
from felis.learning.landing.policy import DROP_HEIGHT_M
from felis.scenarios.drop import drops_from

PITCH, ROLL = [4, 6, 8, 10], [5, 7, 9, 11]  # the legs' joints in the description's order
LIMIT = math.radians(60.0)


class TouchdownFeedback:
    """A `LandingBatch` policy: ``base``'s output (``rows`` cats in all) plus the legs' offsets −k·(pitch, roll)
    below ``on_m``, held from ``freeze_m`` down (module doc). The offsets enter as velocities (their change per
    tick), as the controller integrates the policy's output."""

    def __init__(self, base, rows: int, *, k: float, on_m: float, freeze_m: float):
        self.base = base
        self.k, self.on_m, self.freeze_m = float(k), float(on_m), float(freeze_m)
        self.offset = np.zeros((rows, 12))
        self.frozen = np.zeros(rows, dtype=bool)

    def __call__(self, it: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
        v = np.array(self.base(it, t, rows), dtype=float)
        h = it[:, 6] * DROP_HEIGHT_M
        roll, pitch = it[:, 4] * math.pi, it[:, 5] * math.pi / 2
        new = np.zeros((len(rows), 12))
        new[:, PITCH] = (-self.k * pitch)[:, None]
        new[:, ROLL] = (-self.k * roll)[:, None]
        new[~((h < self.on_m) & (np.abs(roll) < LIMIT) & (np.abs(pitch) < LIMIT))] = 0.0
        self.frozen[rows] |= h < self.freeze_m
        held = self.frozen[rows]
        new[held] = self.offset[rows][held]
        v += (new - self.offset[rows]) / DT
        self.offset[rows] = new
        return v


def landed(drops, k: float, on_m: float, freeze_m: float, library=DEFAULT_LIBRARY, workers=None) -> int:
    """Drops of ``drops`` the library lands with the feedback of gain ``k`` (k = 0: the library alone)."""
    sim = BatchLandingSim("cat", nthread=workers)
    try:
        lib = load_library(library)
        n_ticks = max(int(round((d.fall_time + MARGIN_S) * RATE_HZ)) for d in drops)
        args = (lib, [d.height_m for d in drops], n_ticks, joint_speeds(sim.spec))
        policy = LibraryBatch(*args)
        if k != 0:
            policy = TouchdownFeedback(policy, len(drops), k=k, on_m=on_m, freeze_m=freeze_m)
        return sum(o.landed for o in sim.run(drops, LandingBatch(sim.spec, [policy]), policy="library"))
    finally:
        sim.close()


DIRECTIONS = [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)] + [(a * math.sqrt(0.5), b * math.sqrt(0.5))
                                                                  for a in (1, -1) for b in (1, -1)]


def robustness(drops, k: float, on_m: float, freeze_m: float, *, generations: int, population: int,
               offsets_deg=(1.0, 2.0), patch_deg: float = 0.0, patch_mm: float = 0.0,
               offsets_mm=(1, 2, 3), workers=None) -> dict:
    """The closed loop inside the search: each drop's motion searched (`felis.learning.landing.optimum.optimise`,
    no restart) with the feedback of gain ``k`` on in every rollout (k = 0: open loop, as the library's), and with
    ``patch_deg`` > 0 required to land the four attitudes that far away in roll and pitch too (its worst); then
    each motion that lands its drop run, with the same feedback, from the attitudes ``offsets_deg`` away in eight
    directions (roll, pitch and the diagonals, each way): how far a landing carries; and from ``offsets_mm``
    millimetres lower and higher (``patch_mm`` > 0: the search must land ±``patch_mm`` too)."""
    from felis.learning.landing.optimum import evaluate, optimise
    from felis.scenarios.drop import Drop

    wrap = None if k == 0 else (lambda p, n: TouchdownFeedback(p, n, k=k, on_m=on_m, freeze_m=freeze_m))
    sim = BatchLandingSim("cat", nthread=workers)
    try:
        found = optimise(drops, generations=generations, population=population, restarts=0, sim=sim, wrap=wrap,
                         patch_deg=patch_deg, patch_mm=patch_mm)
        ok = [r for r in found if r.landed]
        near, xs, up_down = [], [], []
        for r in ok:
            d = r.drop
            for off in offsets_deg:
                for dr, dp in DIRECTIONS:
                    near.append(Drop(d.roll_deg + off * dr, d.pitch_deg + off * dp, d.yaw_deg, d.height_m))
                    xs.append(r.x)
            up_down += [Drop(d.roll_deg, d.pitch_deg, d.yaw_deg, d.height_m + sign * mm / 1000.0)
                        for mm in offsets_mm for sign in (-1, 1)]
        verdicts = evaluate(sim, near, np.array(xs), wrap=wrap) if near else []
        heights = (evaluate(sim, up_down, np.repeat([r.x for r in ok], 2 * len(offsets_mm), axis=0), wrap=wrap)
                   if ok else [])
    finally:
        sim.close()
    m = len(DIRECTIONS)
    per = len(offsets_deg) * m
    by_offset = {f"{off:g}": sum(v.landed for i, (_, v) in enumerate(verdicts) if (i % per) // m == j)
                 for j, off in enumerate(offsets_deg)}
    per_mm = 2 * len(offsets_mm)
    by_mm = {f"{mm:g}": sum(v.landed for i, (_, v) in enumerate(heights) if (i % per_mm) // 2 == j)
             for j, mm in enumerate(offsets_mm)}
    return {"k": k, "patch_deg": patch_deg, "patch_mm": patch_mm, "drops": len(drops), "landed": len(ok),
            "rollouts": int(sum(r.rollouts for r in found)), "near_tried_per_offset": m * len(ok),
            "near_landed": by_offset, "heights_tried_per_offset": 2 * len(ok), "heights_landed": by_mm}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=float, default=3.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[2, 3], help="random:100 seeds (default 2 3: the "
                    "validation seeds of docs/landing.md)")
    ap.add_argument("--drops", type=int, default=100)
    ap.add_argument("--gains", type=float, nargs="+", default=[0.0, 0.1, -0.1, 0.3, 1.0])
    ap.add_argument("--on", type=float, default=0.6, help="waist height (m) below which the feedback acts")
    ap.add_argument("--freeze", type=float, default=0.2, help="waist height (m) from which the offsets are held")
    ap.add_argument("--search", type=int, metavar="N", help="instead: search the first N drops of the first seed "
                    "with each gain on, then try each landing motion from attitudes 1° and 2° away (`robustness`)")
    ap.add_argument("--max-tilt", type=float, default=180.0, help="with --search: only drops whose start tilt is at "
                    "most this (deg; default 180: all)")
    ap.add_argument("--patch", type=float, nargs="+", default=[0.0], help="with --search: each search must land "
                    "the attitudes this far away in roll and pitch too (deg; several: one search each; default 0)")
    ap.add_argument("--patch-mm", type=float, nargs="+", default=[0.0], help="with --search: each search must "
                    "land the drop from this many mm lower and higher too (several: one search each; default 0)")
    ap.add_argument("--generations", type=int, default=30, help="with --search: CMA-ES generations (default 30)")
    ap.add_argument("--population", type=int, default=12, help="with --search: CMA-ES population (default 12)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.search:
        from felis.rotations import euler_quat, tilt_deg

        drops = [d for d in drops_from(f"random:{args.drops}", seed=args.seeds[0], height=args.height)
                 if float(tilt_deg(euler_quat(d.roll_deg, d.pitch_deg, d.yaw_deg))) <= args.max_tilt][:args.search]
        res = [robustness(drops, k, args.on, args.freeze, generations=args.generations, population=args.population,
                          patch_deg=p, patch_mm=mm) for mm in args.patch_mm for p in args.patch for k in args.gains]
        if args.json:
            print(json.dumps({"height_m": args.height, "seed": args.seeds[0], "rows": res}, indent=2))
            return
        print(f"landing_touchdown --search: the first {len(drops)} drops of random:{args.drops} seed "
              f"{args.seeds[0]} tilted at most {args.max_tilt:g}° from {args.height:g} m, each searched "
              f"({args.generations} × {args.population}) with the feedback on")
        for r in res:
            name = ("open loop" if r["k"] == 0 else f"k = {r['k']:+g}") + (
                f", patch {r['patch_deg']:g}°" if r["patch_deg"] else "") + (
                f", ±{r['patch_mm']:g} mm" if r["patch_mm"] else "")
            near = ", ".join(f"{o}°: {n}/{r['near_tried_per_offset']}" for o, n in r["near_landed"].items())
            mm = ", ".join(f"±{o} mm: {n}/{r['heights_tried_per_offset']}" for o, n in r["heights_landed"].items())
            print(f"  {name:28s} landed {r['landed']}/{r['drops']} ({r['rollouts']} rollouts); "
                  f"from attitudes away: {near}; from heights away: {mm}")
        return
    rows = []
    for k in args.gains:
        per = [landed(drops_from(f"random:{args.drops}", seed=s, height=args.height), k, args.on, args.freeze)
               for s in args.seeds]
        rows.append({"k": k, "landed": per, "total": sum(per)})
    if args.json:
        print(json.dumps({"height_m": args.height, "seeds": args.seeds, "drops": args.drops, "on_m": args.on,
                          "freeze_m": args.freeze, "rows": rows}, indent=2))
        return
    print(f"landing_touchdown: random:{args.drops} seeds {args.seeds} from {args.height:g} m; legs offset by −k × "
          f"the body's pitch and roll below {args.on:g} m, held from {args.freeze:g} m")
    for r in rows:
        name = "library alone" if r["k"] == 0 else f"k = {r['k']:+g}"
        print(f"  {name:14s} landed {' + '.join(map(str, r['landed']))} = {r['total']}")


if __name__ == "__main__":
    main()
