"""A closed-loop landing policy of the paper's shape, made from the library: K simple behaviours, each imitating the
library's motion for its centre and evolved over its cell of starts, dispatched by the start's up axis (issue 21).

Build (``--out FILE``): the centres are a Fibonacci grid of ``--centres N`` points on the sphere, those tilted at most
``--max-tilt`` with u_y ≥ 0 (the other half runs mirrored). For each centre, `felis.learning.landing.caps`:

1. the library's choice for the centre's start is run open loop and a simple behaviour of the paper's nets (``--hidden``
   neurons, every input) is fitted to its velocities (``--steps`` of Adam);
2. it is evolved by CMA-ES (``--generations``, ``--popsize``, ``--sigma``) on ``--train`` starts of its cell (the
   starts nearest that centre, within ``--radius`` of it; the centre one of them), maximising the mean of the
   optimum's score. With ``--neighbours N`` it starts from whichever scores best on those starts: the fit or one of
   the N nearest centres' evolved behaviours (the grid runs from upright down, so a centre continues from the ones
   above it).

With ``--shift-from FILE`` (a cap policy built for a lower height h₁) there is no fit: each centre starts from the best
of FILE's N nearest behaviours (at least one) and the N nearest built centres', and every behaviour runs shifted, as
if released from h₁ (`felis.learning.landing.cap_policy`, "Shifted"; the file records ``shift_from_m``).

The file is written after each centre; ``--resume`` keeps the centres a file of the same settings holds. ``--more G``
(same settings) evolves G more generations for each centre landing fewer than ``--below N`` of its training starts,
from its genome on the same starts (with ``--neighbours N``: from the best there of it and the N nearest other
centres' behaviours, on either side), and keeps the result where it scores higher (the file records each round).

Evaluate (``--policy FILE``): on ``--drops`` (``random:100`` by default) for each ``--seeds`` S at the file's height
(or ``--height``), the cap policy and the shipped library (``--policy library``), each started
0…``--late`` ticks late (the joints held meanwhile), landed of the drops by the one verdict; ``--record NAME`` keeps
it in the file.

    python bench/landing_caps.py --out FILE [--height 1] [--centres 24] [--max-tilt 130] [--radius 42] [--train 16] \\
        [--generations 30] [--popsize 16] [--sigma 0.1] [--hidden 8] [--steps 1500] [--seed 0] [--neighbours N] \\
        [--shift-from FILE] [--resume] [--more G [--below N]]
    python bench/landing_caps.py --policy FILE [--drops random:100] [--seeds 0 1] [--late 2] [--height H] [--json] \\
        [--record NAME]

The build takes about 3 min a centre on 2 cores at the defaults (7 696 rollouts); the evaluation about 1 min.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.cap_policy import FORMAT, CapPolicy, file_shift, genome, load_caps, template, with_genome
from felis.learning.landing.caps import Late, cell_drops, evolve, fit, record, run_population
from felis.learning.landing.designs import design_sim
from felis.learning.landing.library import load_library
from felis.learning.landing.library_build import fibonacci_ups, tilts_deg, up_drop


def build(args) -> None:
    settings = {"height_m": args.height, "centres": args.centres, "max_tilt_deg": args.max_tilt,
                "radius_deg": args.radius, "train": args.train, "generations": args.generations,
                "popsize": args.popsize, "sigma": args.sigma, "hidden": args.hidden, "steps": args.steps,
                "seed": args.seed, **({"neighbours": args.neighbours} if args.neighbours else {})}
    base = None  # --shift-from FILE: its behaviours, run shifted, start each centre's evolution (no fit)
    if args.shift_from:
        base, base_centres, base_behaviours = load_caps(args.shift_from)
        bs = base["settings"]
        if file_shift(base) is not None or bs["hidden"] != args.hidden or not bs["height_m"] < args.height:
            raise ParameterError(f"caps: --shift-from {args.shift_from}: needs unshifted behaviours of "
                                 f"{args.hidden} hidden neurons made for a lower height than {args.height:g} m")
        settings.update(shift_from=Path(args.shift_from).name, shift_from_m=float(bs["height_m"]))
    shift = file_shift({"settings": settings})
    out = Path(args.out)
    done, d = [], {}
    if args.more and not out.exists():
        raise ParameterError(f"caps: --more continues a built file; {out} does not exist")
    if (args.resume or args.more) and out.exists():
        d, _, _ = load_caps(out)
        if d["settings"] != settings:
            raise ParameterError(f"caps: {out} was built with other settings: {d['settings']}")
        done = d["caps"]
    centres = fibonacci_ups(args.centres, args.max_tilt)
    lib = load_library()
    sim = design_sim("cat")
    t0 = time.perf_counter()

    def training(k: int) -> list:  # centre k's training starts: the same for every round
        rng = np.random.default_rng([args.seed, k])
        start = up_drop(centres[k], args.height)
        return [start] + cell_drops(centres, k, args.radius, args.train - 1, args.height, rng)

    def save() -> None:
        doc = {"format": FORMAT, "version": 1, "made_by": made_by, "settings": settings, "caps": done}
        if more_by:
            doc["more_by"] = more_by
        if d.get("evaluated"):  # evaluations recorded before (--record NAME): kept, named for what they measured
            doc["evaluated"] = d["evaluated"]
        tmp = out.with_suffix(out.suffix + ".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(out)

    made_by = d.get("made_by") if done else "python bench/landing_caps.py " + " ".join(args.argv)
    more_by = list(d.get("more_by", [])) if done else []
    try:
        if args.more:  # each centre landing fewer than --below of its training starts: evolved --more generations on
            if len(done) < len(centres):  # from its genome, kept where it scores higher
                raise ParameterError(f"caps: {out} holds {len(done)} of {len(centres)} centres; finish it first")
            t = template(args.hidden)
            for k, cap in enumerate(done):
                if cap["evolved_lands_train"] >= args.below:
                    continue
                tk = time.perf_counter()
                train = training(k)
                # from its own genome or, with --neighbours N, the best on its starts of it and the N nearest
                # other centres' behaviours (on both sides now: the whole grid is built)
                others = [j for j in np.argsort(-(centres @ centres[k])) if j != k][:args.neighbours]
                cands = [with_genome(t, np.array(done[j]["genome"], dtype=float)) for j in [k, *others]]
                i, started = 0, {}
                if len(cands) > 1:
                    scores, lands = run_population(sim, cands, train, shift=shift)
                    i = int(np.argmax(scores.mean(axis=1)))
                    started = {"start": "own" if i == 0 else f"centre {int(others[i - 1]) + 1}",
                               "start_lands_train": int(lands[i].sum())}
                best, f, rollouts, history = evolve(sim, cands[i], train, args.more, args.popsize, args.sigma,
                                                    args.seed + 1 + len(cap.get("more", [])), shift)
                evolved = run_population(sim, [best], train, shift=shift)[1][0]
                cap.setdefault("more", []).append({"generations": args.more, "score_before": cap["score"],
                                                   "lands_train_before": cap["evolved_lands_train"], **started,
                                                   "score": round(f, 4),
                                                   "evolved_lands_train": int(evolved.sum()),
                                                   "rollouts": rollouts + len(train) * (len(cands) - 1),
                                                   "best_after_generation": history,
                                                   "seconds": round(time.perf_counter() - tk)})
                frm = f" (from {started['start']}, which lands {started['start_lands_train']})" if started else ""
                print(f"centre {k + 1}/{len(centres)}: {cap['evolved_lands_train']} → {int(evolved.sum())} of its "
                      f"{args.train} training starts after {args.more} more generations{frm}", flush=True)
                cap.update(evolved_lands_train=int(evolved.sum()), score=round(f, 4),
                           genome=[float(x) for x in genome(best)])
                if not more_by or more_by[-1] != " ".join(args.argv):
                    more_by.append(" ".join(args.argv))
                save()
            return
        for k in range(len(done), len(centres)):
            tk = time.perf_counter()
            c = centres[k]
            train = training(k)
            near = np.argsort(-(np.array([x["centre"] for x in done]).reshape(-1, 3) @ c))[:args.neighbours]
            cands = [with_genome(template(args.hidden), np.array(done[j]["genome"], dtype=float)) for j in near]
            names = [f"centre {int(j) + 1}" for j in near]
            fitted = {}
            if base is None:  # the fit to the library's motion for the centre, then the N nearest built centres'
                start = up_drop(c, args.height)
                it, v, landed = record(sim, start, lib.choose(c, args.height))
                cands.insert(0, fit(it, v, args.hidden, args.steps, args.seed)[2])
                names.insert(0, "fit")
            else:  # --shift-from: the N nearest of its behaviours (at least one), then the N nearest built centres'
                own = np.argsort(-(base_centres @ c))[:max(1, args.neighbours)]
                cands[:0] = [base_behaviours[j] for j in own]
                names[:0] = [f"{settings['shift_from']} centre {int(j) + 1}" for j in own]
            # the evolution starts from the best of them on these starts (a continuation over the sphere: the grid
            # runs from upright down)
            scores, lands = run_population(sim, cands, train, shift=shift)
            if base is None:
                fitted = {"motion_lands_centre": landed, "fitted_lands_train": int(lands[0].sum())}
            i = int(np.argmax(scores.mean(axis=1)))
            best, f, rollouts, history = evolve(sim, cands[i], train, args.generations, args.popsize, args.sigma,
                                                args.seed, shift)
            evolved = run_population(sim, [best], train, shift=shift)[1][0]
            started = ({"start": names[i], "start_lands_train": int(lands[i].sum())}
                       if len(cands) > 1 or base is not None else {})
            done.append({"centre": [round(float(x), 9) for x in c], "tilt_deg": round(float(tilts_deg(c)), 1),
                         **fitted, **started,
                         "evolved_lands_train": int(evolved.sum()), "score": round(f, 4),
                         "rollouts": rollouts + len(train) * (len(cands) - 1),
                         "best_after_generation": history, "seconds": round(time.perf_counter() - tk),
                         "genome": [float(x) for x in genome(best)]})
            save()
            frm = f" (from {started['start']}, which lands {started['start_lands_train']})" if started else ""
            fit_says = f"the fitted behaviour lands {fitted['fitted_lands_train']}, " if fitted else ""
            print(f"centre {k + 1}/{len(centres)} tilted {done[-1]['tilt_deg']:.0f}°: of its {args.train} training "
                  f"starts {fit_says}evolved{frm} {done[-1]['evolved_lands_train']} ({done[-1]['seconds']} s)",
                  flush=True)
    finally:
        sim.close()
    print(f"{out}: {len(done)} behaviours ({time.perf_counter() - t0:.0f} s this run)")


def evaluate_caps(args) -> dict:
    from felis.controllers.landing import LandingBatch
    from felis.learning.landing.designs import joint_speeds
    from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ, by_tilt
    from felis.learning.landing.library import LibraryBatch
    from felis.scenarios.drop import drops_from

    d, centres, behaviours = load_caps(args.policy)
    h = float(d["settings"]["height_m"]) if args.height is None else args.height  # --height: from another height
    lib = load_library()
    sim = design_sim("cat")
    res = {"policy": str(args.policy), "height_m": h, "drops": args.drops, "behaviours": len(behaviours), "seeds": {}}
    try:
        for s in args.seeds:
            drops = drops_from(args.drops, s, h)
            n_ticks = max(int(round((x.fall_time + MARGIN_S) * RATE_HZ)) for x in drops)
            row = {}
            heights = [x.height_m for x in drops]
            for name, make in (("caps", lambda: CapPolicy(centres, behaviours, file_shift(d))),
                               ("library", lambda hs=heights, n=n_ticks: LibraryBatch(lib, hs, n,
                                                                                      joint_speeds(sim.spec)))):
                landed = []
                for k in range(args.late + 1):
                    pol = make() if k == 0 else Late(make(), k)
                    out = sim.run(drops, LandingBatch(sim.spec, [pol]))
                    landed.append([bool(o.landed) for o in out])
                row[name] = {"landed": [sum(x) for x in landed], "by_tilt": by_tilt(drops, landed[0])}
            res["seeds"][str(s)] = row
    finally:
        sim.close()
    return res


def record_evaluation(path: str, name: str, res: dict, argv: str) -> None:
    """Keep an evaluation in the caps file it evaluated, under ``evaluated[name]`` with the command that made it
    (the file written whole, atomically; its behaviours untouched)."""
    p = Path(path)
    d = json.loads(p.read_text())
    d.setdefault("evaluated", {})[name] = {"command": "python bench/landing_caps.py " + argv,
                                            **{k: v for k, v in res.items() if k != "policy"}}
    tmp = p.with_suffix(p.suffix + ".tmp")
    tmp.write_text(json.dumps(d, indent=1))
    tmp.replace(p)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="build a cap policy into this file")
    ap.add_argument("--policy", help="evaluate the cap policy of this file")
    ap.add_argument("--height", type=float, help="build: the drop height (m, default 1); evaluate: drops from this "
                    "height instead of the file's")
    ap.add_argument("--centres", type=int, default=24, help="Fibonacci points on the sphere (default 24: 9 kept)")
    ap.add_argument("--max-tilt", type=float, default=130.0)
    ap.add_argument("--radius", type=float, default=42.0, help="the training starts lie this close to the centre")
    ap.add_argument("--train", type=int, default=16)
    ap.add_argument("--generations", type=int, default=30)
    ap.add_argument("--popsize", type=int, default=16)
    ap.add_argument("--sigma", type=float, default=0.1)
    ap.add_argument("--hidden", type=int, default=8)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--neighbours", type=int, default=0, metavar="N",
                    help="start each centre's evolution from the best of its fit and the N nearest built centres' "
                    "behaviours on its training starts (default 0: from the fit)")
    ap.add_argument("--shift-from", metavar="FILE",
                    help="build: start each centre's evolution from the best of FILE's N nearest behaviours (made for "
                    "a lower height, at least one) and the N nearest built centres', every behaviour run shifted as "
                    "if released from FILE's height (felis.learning.landing.cap_policy, \"Shifted\"); no fit")
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--more", type=int, default=0, metavar="G",
                    help="with --out FILE (built): evolve G more generations for each centre below --below")
    ap.add_argument("--below", type=int, default=10 ** 9, metavar="N",
                    help="with --more: only centres landing fewer than N of their training starts (default all)")
    ap.add_argument("--drops", default="random:100")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--late", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--record", metavar="NAME", help="with --policy FILE: keep the evaluation in FILE as "
                    "evaluated.NAME (with this command)")
    args = ap.parse_args()
    args.argv = sys.argv[1:]
    if (args.out is None) == (args.policy is None):
        ap.error("give --out FILE (build) or --policy FILE (evaluate)")
    if args.height is not None and not 0 < args.height <= 20:
        ap.error("--height must be in (0, 20] m")
    if args.out and args.height is None:
        args.height = 1.0
    if args.out and not (args.centres >= 1 and 0 < args.max_tilt <= 180 and 0 < args.radius <= 90
                         and args.train >= 1 and args.generations >= 1 and args.popsize >= 2 and args.sigma > 0
                         and args.hidden >= 1 and args.steps >= 0):
        ap.error("needs --centres, --train, --generations, --hidden ≥ 1, --popsize ≥ 2, --steps ≥ 0, --sigma > 0, "
                 "0 < --max-tilt ≤ 180, 0 < --radius ≤ 90, 0 < --height ≤ 20")
    if args.record is not None and args.policy is None:
        ap.error("--record keeps an evaluation: give --policy FILE")
    if args.late < 0 or args.more < 0 or args.neighbours < 0:
        ap.error("--late, --more and --neighbours must be ≥ 0")
    import torch

    torch.set_num_threads(1)  # small nets: threads cost more than they give
    try:
        if args.out:
            build(args)
            return
        res = evaluate_caps(args)
        if args.record:
            record_evaluation(args.policy, args.record, res, " ".join(args.argv))
    except ParameterError as e:
        raise SystemExit(str(e)) from None
    if args.json:
        print(json.dumps(res, indent=1))
        return
    print(f"{res['policy']}: {res['behaviours']} behaviours; {args.drops} from {res['height_m']:g} m, landed "
          f"started 0…{args.late} ticks late")
    for s, row in res["seeds"].items():
        for name, r in row.items():
            print(f"  seed {s} {name:8s} " + "  ".join(f"{k} late: {n}" for k, n in enumerate(r["landed"])))


if __name__ == "__main__":
    main()
