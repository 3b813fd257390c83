"""Can one simple behaviour of the paper's nets reproduce a motion of the library? Regression, not evolution.

The paper's simple behaviours (seed 000 §6.3–6.5, `felis.learning.landing.policy.SimpleBehaviour`: spine, tail and
legs gene units, joint velocities from the 15 inputs IT) are evolved to imitate one motion sample. Evolution is a
search; this bench asks what the best search could give. For each of ``--n`` motions of the shipped shelf that land
their own start when tried (drawn with ``--seed`` among the entries tilted ``--tilt`` flagged landed; a flag is the
build's, so those that do not land on the described cat are skipped), the behaviour's three units (every
input, ``--hidden`` neurons) are fitted by gradient descent (torch, Adam, ``--steps``) to the motion's velocities
at each tick of its fall (outputs against ``v / max speed``, the units' tanh range), then run closed loop from the
motion's start: does it land as the motion does?

- ``--rounds R``: R rounds of DAgger: the states the fitted behaviour visits, labelled with the motion's velocity at
  that tick, join the data and the units are fitted again;
- ``--clock``: time since release as one more input (not in the paper's Table 1, which gives the nets no clock; the
  waist height Sh is their only one, and it barely moves in the first ticks of a fall): whether a clock is what a
  reactive net misses;
- ``--evolve G``: the fitted behaviour is then evolved G generations by CMA-ES (``--popsize``, ``--sigma``) on
  ``--train`` starts of the cap of ``--patch`` degrees round the motion's start (that start one of them), and the
  motion, the fitted and the evolved behaviour are run on ``--test`` other starts of the cap (held out), on time and
  started 1…``--late`` ticks late (`felis.learning.landing.caps`).

    python bench/landing_clone.py [--height 1] [--n 8] [--tilt 50 120] [--hidden 8] [--steps 1500] [--rounds 0] \\
        [--clock] [--seed 0] [--evolve G [--patch 15] [--train 8] [--test 16] [--popsize 16] [--sigma 0.1] \\
        [--late K]] [--json]

About 6 s a motion at the defaults (2 cores; ``--hidden 64`` about 20 s; ``--evolve 30``: about 100 s at 15°, 190 s
with ``--patch 30 --train 16 --test 24``).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from felis.learning.landing.caps import Late, cap_drops, evolve, fit, record, run_population
from felis.learning.landing.designs import design_sim
from felis.learning.landing.library import load_library
from felis.learning.landing.library_build import tilts_deg, up_drop
from felis.learning.landing.motion import DT  # the control tick (s): a motion's table has one row a tick
from felis.learning.landing.optimum import evaluate
from felis.learning.landing.policy import SimpleBehaviour


def closed_loop(sim, drop, policy, clock: bool):
    """(verdict, [(IT, t)] per tick) of ``policy`` driving the cat from ``drop`` (the landing controller's batch)."""
    from felis.controllers.landing import LandingBatch
    from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ
    from felis.scenarios.verdicts import landing_verdict

    seen = []

    def run(it, t, rows):
        seen.append((it.copy(), t.copy()))
        return policy(np.hstack([it, t[:, None]]) if clock else it)

    (r,) = sim.batch.run([drop], LandingBatch(sim.spec, [run]), sim.standing_waist_m, rate_hz=RATE_HZ,
                         margin_s=MARGIN_S)
    return landing_verdict(r.truth), seen


def clone(sim, drop, x: np.ndarray, hidden: int, steps: int, rounds: int = 0, clock: bool = False,
          seed: int = 0) -> dict:
    """One motion: recorded, fitted, run closed loop (with ``rounds`` of DAgger). The row's ``behaviour`` is the
    fitted `SimpleBehaviour` (None with a clock, which the paper's units do not read)."""
    it, v, landed = record(sim, drop, x)
    t = np.arange(len(it)) * DT
    data_x = np.hstack([it, t[:, None]]) if clock else it
    data_y = v
    for r in range(rounds + 1):
        policy, rms, behaviour = fit(data_x, data_y, hidden, steps, seed)
        verdict, seen = closed_loop(sim, drop, policy, clock)
        if r < rounds:  # DAgger: the visited states, labelled with the motion's velocity at their tick
            its = np.concatenate([a for a, _ in seen])
            ts = np.concatenate([b for _, b in seen])
            k = np.clip(np.rint(ts / DT).astype(int), 0, len(v) - 1)
            data_x = np.concatenate([data_x, np.hstack([its, ts[:, None]]) if clock else its])
            data_y = np.concatenate([data_y, v[k]])
    return {"open_loop_landed": landed, "ticks": len(it), "rms_rad_s": round(rms, 3),
            "clone_landed": bool(verdict.landed), "why": verdict.why or "", "behaviour": behaviour}


def patch_study(sim, shelf, e: int, height_m: float, args, b: SimpleBehaviour) -> dict:
    """Motion ``e``'s start and the cap of ``args.patch`` degrees round it: the open-loop motion, the fitted
    behaviour and that behaviour evolved on ``args.train`` drops of the cap (its start among them) against
    ``args.test`` other drops of the cap (held out)."""
    rng = np.random.default_rng([args.seed, e])
    own = up_drop(shelf.up[e], height_m)
    train = [own] + cap_drops(shelf.up[e], args.patch, args.train - 1, height_m, rng)
    test = cap_drops(shelf.up[e], args.patch, args.test, height_m, rng)
    motion = [bool(v.landed) for _, v in evaluate(sim, test, np.repeat(shelf.x[e][None], len(test), 0))]
    motion_train = [bool(v.landed) for _, v in evaluate(sim, train, np.repeat(shelf.x[e][None], len(train), 0))]
    fitted_train = run_population(sim, [b], train)[1][0]
    fitted_test = run_population(sim, [b], test)[1][0]
    best, f, rollouts, history = evolve(sim, b, train, args.evolve, args.popsize, args.sigma, args.seed)
    ev_train = run_population(sim, [best], train)[1][0]
    ev_test = run_population(sim, [best], test)[1][0]
    late = {}
    for k in range(1, args.late + 1):  # the held-out drops started k ticks late
        m = evaluate(sim, test, np.repeat(shelf.x[e][None], len(test), 0), wrap=lambda pol, n, k=k: Late(pol, k))
        late[str(k)] = {"motion": sum(bool(v.landed) for _, v in m),
                        "fitted": int(run_population(sim, [b], test, k)[1].sum()),
                        "evolved": int(run_population(sim, [best], test, k)[1].sum())}
    return {"late_test": late, "patch_deg": args.patch, "train": len(train), "test": len(test),
            "motion_lands_train": int(sum(motion_train)), "motion_lands_test": int(sum(motion)),
            "fitted_lands_train": int(fitted_train.sum()), "fitted_lands_test": int(fitted_test.sum()),
            "evolved_lands_train": int(ev_train.sum()), "evolved_lands_test": int(ev_test.sum()),
            "evolved_lands_own": bool(ev_train[0]), "evolved_score": round(f, 4), "evolution_rollouts": rollouts,
            "best_after_generation": history}


PATCH_COUNTS = ("motion_lands_train", "motion_lands_test", "fitted_lands_train", "fitted_lands_test",
                "evolved_lands_train", "evolved_lands_test", "evolved_lands_own")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=float, default=1.0)
    ap.add_argument("--n", type=int, default=8, help="motions to clone (default 8)")
    ap.add_argument("--tilt", type=float, nargs=2, default=[50.0, 120.0], metavar=("LO", "HI"))
    ap.add_argument("--hidden", type=int, default=8, help="hidden neurons per unit (the paper's nets: 8 at most)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--rounds", type=int, default=0, help="DAgger rounds (default 0)")
    ap.add_argument("--clock", action="store_true", help="time since release as one more input")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--evolve", type=int, default=0, metavar="G",
                    help="evolve each fitted behaviour G generations (CMA-ES) on drops round its start (default 0)")
    ap.add_argument("--patch", type=float, default=15.0, metavar="DEG",
                    help="with --evolve: the radius of the cap of starts round the motion's (default 15)")
    ap.add_argument("--train", type=int, default=8, help="with --evolve: drops it is evolved on, its start one")
    ap.add_argument("--test", type=int, default=16, help="with --evolve: held-out drops of the cap")
    ap.add_argument("--popsize", type=int, default=16)
    ap.add_argument("--sigma", type=float, default=0.1, help="CMA-ES's initial step on the weights (default 0.1)")
    ap.add_argument("--late", type=int, default=0, metavar="K",
                    help="with --evolve: the held-out drops also started 1…K ticks late (default 0)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.n < 1 or args.rounds < 0 or args.hidden < 1 or args.steps < 0:
        ap.error("--n and --hidden must be ≥ 1, --rounds and --steps ≥ 0")
    if args.evolve < 0 or (args.evolve and (args.clock or not 0 < args.patch <= 90 or args.train < 1 or args.late < 0
                                            or args.test < 1 or args.popsize < 2 or not args.sigma > 0)):
        ap.error("--evolve must be ≥ 0, and with it: no --clock (the paper's units read no clock), 0 < --patch ≤ 90, "
                 "--train and --test ≥ 1, --popsize ≥ 2, --sigma > 0, --late ≥ 0")
    import torch

    torch.set_num_threads(1)  # small nets: threads cost more than they give
    shelf = load_library().shelf(args.height)
    t = tilts_deg(shelf.up)
    pool = np.flatnonzero(shelf.landed & (t >= args.tilt[0]) & (t < args.tilt[1]))
    if len(pool) < args.n:
        ap.error(f"only {len(pool)} motions of the {args.height:g} m shelf are flagged landed tilted {args.tilt}")
    order = np.random.default_rng(args.seed).permutation(pool)
    sim = design_sim("cat", nthread=None if args.evolve else 1)  # a population's batch: every core
    rows, skipped = [], []
    t0 = time.perf_counter()
    try:
        for e in order:
            if len(rows) == args.n:
                break
            row = {"entry": int(e), "tilt_deg": round(float(t[e]), 1),
                   **clone(sim, up_drop(shelf.up[e], args.height), shelf.x[e], args.hidden, args.steps, args.rounds,
                           args.clock, args.seed)}
            behaviour = row.pop("behaviour")
            if not row["open_loop_landed"]:  # its flag is the build's; on this cat it does not land: not a sample
                skipped.append(int(e))
                continue
            if args.evolve:
                row["patch"] = patch_study(sim, shelf, e, args.height, args, behaviour)
            rows.append(row)
            if not args.json:
                print(f"entry {row['entry']} tilted {row['tilt_deg']:.0f}°: fitted to {row['rms_rad_s']:.2f} rad/s "
                      f"RMS, closed loop landed {row['clone_landed']} {row['why']}", flush=True)
                if args.evolve:
                    p = row["patch"]
                    print(f"  cap of {p['patch_deg']:g}°, held out {p['test']}: motion lands {p['motion_lands_test']}"
                          f", fitted {p['fitted_lands_test']}, evolved {p['evolved_lands_test']} (on its "
                          f"{p['train']} training drops {p['motion_lands_train']}, {p['fitted_lands_train']}, "
                          f"{p['evolved_lands_train']}; {p['evolution_rollouts']} rollouts)", flush=True)
                    for k, c in p["late_test"].items():
                        print(f"  started {k} tick{'s' * (k != '1')} late: motion {c['motion']}, fitted "
                              f"{c['fitted']}, evolved {c['evolved']}", flush=True)
    finally:
        sim.close()
    res = {"height_m": args.height, "hidden": args.hidden, "steps": args.steps, "rounds": args.rounds,
           "clock": args.clock, "seed": args.seed, "seconds": round(time.perf_counter() - t0),
           "motions_tried": len(rows) + len(skipped), "skipped_not_landing": skipped,
           "clone_landed": sum(r["clone_landed"] for r in rows), "motions": rows}
    if args.evolve:
        res["evolution"] = {"generations": args.evolve, "patch_deg": args.patch, "train": args.train,
                            "test": args.test, "popsize": args.popsize, "sigma": args.sigma,
                            "late": args.late, **{k: sum(r["patch"][k] for r in rows) for k in PATCH_COUNTS},
                            "late_test": {str(k): {w: sum(r["patch"]["late_test"][str(k)][w] for r in rows)
                                                   for w in ("motion", "fitted", "evolved")}
                                          for k in range(1, args.late + 1)}}
    if args.json:
        print(json.dumps(res, indent=1))
        return
    print(f"{len(rows)} motions, h={args.hidden}, {args.steps} steps, {args.rounds} DAgger rounds"
          f"{', with a clock' if args.clock else ''}: the fitted behaviour lands {res['clone_landed']} of the "
          f"{len(rows)} drops its motion lands ({len(skipped)} motions skipped: they do not land their start; "
          f"{res['seconds']} s)")
    if args.evolve:
        v = res["evolution"]
        n = len(rows)
        print(f"held-out starts within {args.patch:g}° ({n} × {args.test}): the open-loop motion lands "
              f"{v['motion_lands_test']}, the fitted behaviour {v['fitted_lands_test']}, evolved {args.evolve} "
              f"generations {v['evolved_lands_test']}; the evolved behaviour lands its own start in "
              f"{v['evolved_lands_own']} of {n}")
        for k, c in v["late_test"].items():
            print(f"  started {k} tick{'s' * (k != '1')} late: the motion lands {c['motion']}, fitted {c['fitted']}, "
                  f"evolved {c['evolved']}")


if __name__ == "__main__":
    main()
