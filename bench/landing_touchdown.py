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


class TouchdownFeedback(LibraryBatch):
    """`LibraryBatch` plus the legs' offsets −k·(pitch, roll) below ``on_m``, held from ``freeze_m`` down (module
    doc). The offsets enter as velocities (their change per tick), as the controller integrates the policy's output."""

    def __init__(self, *args, k: float, on_m: float, freeze_m: float, **kw):
        super().__init__(*args, **kw)
        self.k, self.on_m, self.freeze_m = float(k), float(on_m), float(freeze_m)
        self.offset = np.zeros((len(self.heights), 12))
        self.frozen = np.zeros(len(self.heights), dtype=bool)

    def __call__(self, it: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
        v = np.array(super().__call__(it, t, rows), dtype=float)
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
        policy = LibraryBatch(*args) if k == 0 else TouchdownFeedback(*args, k=k, on_m=on_m, freeze_m=freeze_m)
        return sum(o.landed for o in sim.run(drops, LandingBatch(sim.spec, [policy]), policy="library"))
    finally:
        sim.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=float, default=3.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[2, 3], help="random:100 seeds (default 2 3: the "
                    "validation seeds of docs/landing.md)")
    ap.add_argument("--drops", type=int, default=100)
    ap.add_argument("--gains", type=float, nargs="+", default=[0.0, 0.1, -0.1, 0.3, 1.0])
    ap.add_argument("--on", type=float, default=0.6, help="waist height (m) below which the feedback acts")
    ap.add_argument("--freeze", type=float, default=0.2, help="waist height (m) from which the offsets are held")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
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
