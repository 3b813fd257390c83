"""Touchdown compliance (issue 21, item 5): does softening the legs at touchdown land more of the drops?

The legs' Position P gain drops to a fraction s of the described below the landing rule's height
(`felis.controllers.landing`, `felis.hal.Command.stiffness`; I, D, feedforward kept). For each height it replays,
on `random:100 --seed 0`, (a) the shipped per-drop optimum's motions (`learning/weights/landing_optimum-*.json`,
searched with stiff legs: not re-searched here) and (b) the shipped policy, for s = 1, 0.5, 0.25, 0.1, in batches
(`felis.sim.batch.DropBatch`); it counts landings, the failures whose first wrong contact is a leg link, and
the median peak impact (body weights).

    python bench/landing_compliance.py [--json]      (about a minute on 2 cores)
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from felis.controllers.landing import LandingBatch
from felis.learning.landing.evaluate import BatchLandingSim, shipped_policy
from felis.learning.landing.optimum import DropOptimum, evaluate
from felis.learning.landing.policy import load_policy

WEIGHTS = Path(__file__).resolve().parents[1] / "learning" / "weights"
STIFFNESS = (1.0, 0.5, 0.25, 0.1)


def summary(outcomes) -> dict:
    legs = sum(1 for o in outcomes if not o.landed and o.why and "leg" in o.why)
    return {"landed": sum(o.landed for o in outcomes), "failed_on_a_leg_link": legs,
            "median_peak_impact": round(statistics.median(o.peak_impact for o in outcomes), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    behaviour, _ = load_policy(shipped_policy())
    sim = BatchLandingSim()
    out: dict = {}
    t0 = time.perf_counter()
    try:
        for h in ("1m", "3m"):
            optimum = [DropOptimum.from_dict(d) for d in json.loads((WEIGHTS / f"landing_optimum-{h}.json")
                                                                   .read_text())["drops"]]
            drops = [o.drop for o in optimum]
            xs = np.array([o.x for o in optimum])
            for s in STIFFNESS:
                got: list = []
                evaluate(sim, drops, xs, touchdown_stiffness=s, outcomes=got)
                out[f"{h} optimum s={s:g}"] = summary(got)
                pol = sim.run(drops, LandingBatch(sim.spec, [behaviour], touchdown_stiffness=s), policy="shipped")
                out[f"{h} policy s={s:g}"] = summary(pol)
    finally:
        sim.close()
    if args.json:
        print(json.dumps(out, indent=2))
        return
    print(f"touchdown compliance on random:100 (seed 0), {time.perf_counter() - t0:.0f} s")
    print(f"{'case':<24} {'landed':>6} {'leg link':>8} {'median impact (body weights)':>30}")
    for k, v in out.items():
        print(f"{k:<24} {v['landed']:>6} {v['failed_on_a_leg_link']:>8} {v['median_peak_impact']:>30}")


if __name__ == "__main__":
    main()
