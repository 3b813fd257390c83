"""Touchdown compliance (issue 21, item 5): does softening the legs at touchdown land more of the drops?

The legs' Position P gain drops to a fraction s of the described below the landing rule's height
(`felis.controllers.landing`, `felis.hal.Command.stiffness`; I, D, feedforward kept). For each height it replays,
on `random:100 --seed 0`, (a) the shipped per-drop optimum's motions (`learning/weights/landing_optimum-*.json`,
searched with stiff legs: not re-searched here) and (b) the evolved nets (``--policy shipped``), for s = 1, 0.5,
0.25, 0.1, in batches
(`felis.sim.batch.DropBatch`); it counts landings, the failures whose first wrong contact is a leg link, and
the median peak impact (body weights).

Then the paw: the feet's contact is a model parameter (`sim/models/cat.xml`: a 12 mm sphere with MuJoCo's
``solref = (τ, 1)``, τ = 4 ms). With ζ = 1 and solimp's d ≈ 1, a contact behaves as a spring of k ≈ m/τ² per
unit of the mass m it stops, so a paw carrying a quarter of the cat has k ≈ (M/4)/τ²; a rubber pad of thickness
t and contact area A of that stiffness has Young's modulus E = k·t/A. The table replays the same motions, the
nets and the motion library (the shipped policy, `--policy library`; searched on the 4 ms paw) with stiff legs on paws
of τ = 4 (the model's), 2, 3, 8 and 16 ms (the contact's τ: `felis.learning.landing.designs.paw_edit`), and prints k
and E (t = 5 mm, A = π·(6 mm)²)
for each, to read against rubber (Shore 40–60A: E ≈ 1.5–4 MPa) and soft silicone or foam pads (0.1–1 MPa).

    python bench/landing_compliance.py [--json]      (about 130 s on 2 cores)
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from felis.controllers.landing import LandingBatch
from felis.learning.landing.designs import paw_edit
from felis.learning.landing.evaluate import BatchLandingSim, batch_controller, shipped_policy
from felis.learning.landing.optimum import DropOptimum, evaluate
from felis.learning.landing.policy import load_policy

WEIGHTS = Path(__file__).resolve().parents[1] / "learning" / "weights"
STIFFNESS = (1.0, 0.5, 0.25, 0.1)
PAW_TAU_S = (0.004, 0.002, 0.003, 0.008, 0.016)  # the model's first
PAD_T_M, PAD_A_M2 = 0.005, np.pi * 0.006**2  # a 5 mm pad, 6 mm contact radius


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
    mass = sim.batch.robot.mass()
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
            out[f"{h} library paw 4 ms"] = summary(sim.run(drops, batch_controller(sim.spec, "library", drops),
                                                           policy="library"))
    finally:
        sim.close()
    for tau in PAW_TAU_S[1:]:
        paw = BatchLandingSim(sensors=paw_edit(tau))
        try:
            for h in ("1m", "3m"):
                optimum = [DropOptimum.from_dict(d) for d in json.loads((WEIGHTS / f"landing_optimum-{h}.json")
                                                                       .read_text())["drops"]]
                drops = [o.drop for o in optimum]
                got: list = []
                evaluate(paw, drops, np.array([o.x for o in optimum]), outcomes=got)
                out[f"{h} optimum paw {tau * 1e3:g} ms"] = summary(got)
                out[f"{h} policy paw {tau * 1e3:g} ms"] = summary(
                    paw.run(drops, LandingBatch(paw.spec, [behaviour]), policy="shipped"))
                out[f"{h} library paw {tau * 1e3:g} ms"] = summary(
                    paw.run(drops, batch_controller(paw.spec, "library", drops), policy="library"))
        finally:
            paw.close()
    for tau in PAW_TAU_S:
        k = mass / 4.0 / tau**2
        out[f"paw {tau * 1e3:g} ms"] = {"k_N_per_m": round(k), "pad_E_MPa": round(k * PAD_T_M / PAD_A_M2 / 1e6, 2)}
    if args.json:
        print(json.dumps(out, indent=2))
        return
    print(f"touchdown compliance on random:100 (seed 0), {time.perf_counter() - t0:.0f} s")
    print(f"{'case':<24} {'landed':>6} {'leg link':>8} {'median impact (body weights)':>30}")
    for k, v in out.items():
        if "landed" in v:
            print(f"{k:<24} {v['landed']:>6} {v['failed_on_a_leg_link']:>8} {v['median_peak_impact']:>30}")
    for k, v in out.items():
        if "k_N_per_m" in v:
            print(f"{k}: a paw carrying a quarter of the cat ≈ {v['k_N_per_m']} N/m; as a 5 mm pad, E ≈ "
                  f"{v['pad_E_MPa']} MPa")


if __name__ == "__main__":
    main()
