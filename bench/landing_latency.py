"""How much a late start costs the motion library: its landings when each motion starts k ticks after release.

The library (`learning.landing.library`) is open loop: at release it picks a motion from the IMU's attitude and plays
it against the fall. On servos a bus's latency and a loaded host's late ticks delay it. For each drop this runs the
motion the library chooses started on time and 1…K ticks late (`felis.learning.landing.optimum.evaluate` with
``late_ticks``: the velocity table shifted, the joints held meanwhile), and counts the drops it lands at every delay
from 0 to k, for k = 0…K. On the described cat at its 1 ms step, deterministic.

    python bench/landing_latency.py [--drops random:100] [--seeds 0 1] [--heights 1 3] [--ticks 3] [--json]

About 2 minutes on 2 cores for the defaults (docs/landing.md, "The demo's hard drop"; issue 21).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from felis.errors import FelisError
from felis.learning.landing.evaluate import BatchLandingSim
from felis.learning.landing.library import DEFAULT_LIBRARY, drop_up, load_library
from felis.learning.landing.optimum import evaluate
from felis.scenarios.drop import drops_from


def landed_by_delay(sim, library, drops, height_m: float, ticks: int) -> list[int]:
    """Drops (of ``drops``, all from ``height_m``) the library's choices land at every delay 0…k, k = 0…``ticks``."""
    xs = np.stack([library.choose(drop_up(d), height_m) for d in drops])
    return [sum(v.landed for _, v in evaluate(sim, drops, xs, late_ticks=k)) for k in range(ticks + 1)]


def _groups(args) -> list[tuple[float, int | None, list]]:
    """(height, seed, drops) per row: random:N / euler:N for each height and seed; a drops file by its heights (the
    seeds and --heights do not apply to it)."""
    if args.drops.split(":")[0] in ("random", "euler"):
        return [(h, seed, drops_from(args.drops, seed=seed, height=h)) for h in args.heights for seed in args.seeds]
    drops = drops_from(args.drops)
    return [(h, None, [d for d in drops if d.height_m == h]) for h in sorted({d.height_m for d in drops})]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("library", nargs="?", default=str(DEFAULT_LIBRARY), help="library file (default: the shipped one)")
    ap.add_argument("--drops", default="random:100", help="drops (as `felis eval landing --drops`)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--heights", type=float, nargs="+", default=[1.0, 3.0])
    ap.add_argument("--ticks", type=int, default=3, help="the longest delay, in 10 ms ticks (default 3)")
    ap.add_argument("--workers", type=int, default=None, help="simulation threads (default: every core)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.ticks < 0:
        ap.error("--ticks must be ≥ 0")
    try:
        library = load_library(args.library)
        groups = _groups(args)
    except FelisError as e:
        ap.error(str(e))
    sim = BatchLandingSim(nthread=args.workers)
    rows = []
    t0 = time.perf_counter()
    try:
        for h, seed, drops in groups:
            rows.append({"height_m": h, "seed": seed, "total": len(drops),
                         "landed_by_delay": landed_by_delay(sim, library, drops, h, args.ticks)})
    finally:
        sim.close()
    out = {"library": args.library, "drops": args.drops, "rows": rows, "seconds": round(time.perf_counter() - t0, 1)}
    if args.json:
        print(json.dumps(out, indent=1))
        return
    print(f"landing_latency: {args.library}, {args.drops}; drops the library lands at every start delay 0…k ticks")
    print("  height  seed  " + "  ".join(f"k={k:<3d}" for k in range(args.ticks + 1)))
    for r in rows:
        seed = "file" if r["seed"] is None else r["seed"]
        print(f"  {r['height_m']:4g} m  {seed:>4}  " + "  ".join(f"{n:5d}" for n in r["landed_by_delay"])
              + f"   of {r['total']}")
    print(f"  ({out['seconds']} s)")


if __name__ == "__main__":
    main()
