"""The landing design study (issue 21, item 6): the per-drop optimum for other buildable cats.

For each design of `felis.learning.landing.designs.DESIGNS` (other servos of the XL330/XC330 family on legs,
tail or spine, the XL330 at its 6 V maximum, softer paws) and each height, the per-drop optimum
(`felis.learning.landing.optimum.optimise`, the shipped results' budget: population 12, 30 generations, one
restart; every drop seeded by its index as in the shipped run) on the first ``--drops`` drops of
`random:100 --seed 0`, the drops of the shipped optimum (`learning/weights/landing_optimum_4ms-paw-*.json`). The
study's base, the 4 ms-paw cat at 1 ms (``4ms-paw``: the cat as described until 2026-11-29, on which the study was
measured), runs in the same run: the anchor every design is read against (same drops, same machine); the shipped
results for those drops are printed beside it as a check. ``cat`` (the cat as described now: 2 ms paws at 0.5 ms)
is the base of the ``cat+…`` designs, the same servo changes made to it; its
shipped ceiling (the optimum warm-started from the library) on those drops is printed beside it. Each design named
with its base (`Design.base`) is read against it drop by drop: the drops it lands and the base does not (+), the
other way (−), and a two-sided sign test of those (`against`), with how many of the lost drops it loses after
touching down on its feet (`late`); ``--sag`` also replays both cats' motions and measures how far the waist sinks
after touchdown (`sag`).

Each ``--chunk`` of drops of a design and height is one job in a process pool of ``--workers`` (one thread
each), searched as one batch; jobs are ordered chunk by chunk so a run cut short still compares every design on
the same drops; every finished drop is appended to ``--out`` (JSON lines), and ``--resume`` skips those (with
nothing left to search it prints the table of the file).

    python bench/landing_design.py [--drops 30] [--designs 4ms-paw,6V] [--heights 1,3] [--workers N] \\
        [--chunk 4] [--out FILE.jsonl [--resume]] [--json]
    python bench/landing_design.py --drops 100 --out learning/weights/landing_design.jsonl --resume \\
        --designs 4ms-paw,fast-limbs,strong-spine,fast-limbs+strong-spine,6V,soft-rubber-paw  # the table shipped
    python bench/landing_design.py --drops 100 --out learning/weights/landing_design.jsonl --resume \\
        --designs cat,cat+fast-limbs,cat+strong-spine,cat+fast-limbs+strong-spine,cat+6V  # on the described cat
    python bench/landing_design.py --drops 100 --out learning/weights/landing_design.jsonl --resume \\
        --designs cat,cat+fast-limbs --sag  # why faster legs lose from 3 m (the docs' sag table)

A drop that does not land uses the whole budget, 733 rollouts: about 50 s of one core of the 2-core machine
searched alone, less in a chunk. The default, 30 drops × every design × 2 heights, takes hours on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import re
import sys
import time
from pathlib import Path

WEIGHTS = Path(__file__).resolve().parents[1] / "learning" / "weights"
ANCHOR = "4ms-paw"  # the study's base (module doc)
LATE_S = 0.05  # a failure this long after touchdown or later is not the impact's (`late`)
_TOUCH = re.compile(r"touched the ground (\d+\.\d+) s after touchdown")  # the verdict's detail (`late`)
SETTINGS = {"generations": 30, "population": 12, "restarts": 1, "seed": 0}  # the shipped optimum's


def shipped(height: str) -> list[dict]:
    return json.loads((WEIGHTS / f"landing_optimum_{ANCHOR}-{height}.json").read_text())["drops"]


def ceiling(height: str) -> list[dict]:
    """The described cat's shipped ceiling on the same drops (the optimum warm-started from the library as well as
    searched from scratch: docs/landing.md): what ``cat``'s search from scratch here is read against."""
    return json.loads((WEIGHTS / f"landing_optimum_warm-{height}.json").read_text())["drops"]


def late(row: dict) -> bool:
    """Whether a drop that did not land failed after touching down on its feet: no body but a foot on the floor in
    the first `LATE_S` after touchdown (the impact), so what failed is holding the landing, not the turn or the
    posture at touchdown. Read from the verdict's detail (`felis.scenarios.verdicts.landing_verdict`: "BODY touched
    the ground T s after touchdown"); a drop that never touched down is not late."""
    if row["landed"]:
        return False
    why = row["why"] or ""
    if "never touched down" in why:
        return False
    m = _TOUCH.search(why)
    return m is None or float(m.group(1)) >= LATE_S


def against(done: dict, design: str, base: str, height: str, drops: int) -> dict:
    """``design`` read against ``base`` on the drops of the first ``drops`` that both have: drops it lands and the
    base does not (gained), the other way (lost), and the two-sided sign test of those (scipy's exact binomial
    test, p = 1 with none either way); ``lost_late``: of the lost drops, those it fails after touching down on its
    feet (`late`)."""
    from scipy.stats import binomtest

    both = [i for i in range(drops) if (design, height, i) in done and (base, height, i) in done]
    gained = sum(done[(design, height, i)]["landed"] and not done[(base, height, i)]["landed"] for i in both)
    lost = [i for i in both if done[(base, height, i)]["landed"] and not done[(design, height, i)]["landed"]]
    p = binomtest(gained, gained + len(lost)).pvalue if gained + len(lost) else 1.0
    return {"of": len(both), "gained": int(gained), "lost": len(lost), "p": float(p),
            "lost_late": sum(late(done[(design, height, i)]) for i in lost)}


def sag(done: dict, design: str, base: str, height: str, drops: int) -> dict:
    """How far the cat sinks after touchdown, ``design`` against ``base``: each one's searched motion replayed on
    its own cat, on the drops the base lands and the design loses after touching down on its feet (``lost_late``)
    and on those both land (``both``); per set the median over its drops of the waist's lowest height from
    touchdown to touchdown + 0.5 s (the verdict's window), as a share of the standing waist height (None for an
    empty set). About a second of one core a drop."""
    import numpy as np

    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.optimum import evaluate
    from felis.scenarios.drop import Drop
    from felis.scenarios.verdicts import WINDOW_S

    both = [i for i in range(drops) if (design, height, i) in done and (base, height, i) in done]
    sets = {"lost_late": [i for i in both if done[(base, height, i)]["landed"] and late(done[(design, height, i)])],
            "both": [i for i in both if done[(base, height, i)]["landed"] and done[(design, height, i)]["landed"]]}
    out: dict = {k: {"drops": len(v)} for k, v in sets.items()}
    for who in (base, design):
        sim = design_sim(who, nthread=1)
        try:
            for k, idx in sets.items():
                rows = [done[(who, height, i)] for i in idx]
                got: list = []
                if rows:
                    evaluate(sim, [Drop(r["roll_deg"], r["pitch_deg"], r["yaw_deg"], r["height_m"]) for r in rows],
                             np.array([r["motion_x"] for r in rows]), results=got)
                low = []
                for r in got:
                    t, floor = np.asarray(r.truth.t), np.flatnonzero(np.asarray(r.truth.floor_body) >= 0)
                    t0 = t[floor[0]]
                    window = (t >= t0) & (t <= t0 + WINDOW_S)
                    low.append(float(np.min(np.asarray(r.truth.waist_m)[window])) / sim.standing_waist_m)
                out[k][who] = round(float(np.median(low)), 3) if low else None
        finally:
            sim.close()
    return out


def _job(job: tuple[str, str, list[int]]) -> list[dict]:
    from felis.learning.landing.optimum import _worker_sim, optimise
    from felis.scenarios.drop import Drop

    design, height, idx = job
    rows = shipped(height)
    drops = [Drop(rows[i]["roll_deg"], rows[i]["pitch_deg"], rows[i]["yaw_deg"], rows[i]["height_m"]) for i in idx]
    t0 = time.perf_counter()
    best = optimise(drops, sim=_worker_sim(design), index=idx, **SETTINGS)
    s = round((time.perf_counter() - t0) / len(idx), 1)
    return [{"design": design, "height": height, "i": i, "seconds": s, **o.as_dict()} for i, o in zip(idx, best,
                                                                                                     strict=True)]


def main() -> int:
    from felis.learning.landing.designs import DESIGNS, get_design

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drops", type=int, default=30, help="the first N drops of random:100 --seed 0 (default 30)")
    ap.add_argument("--designs", default=",".join(DESIGNS), help="comma-separated (default: all)")
    ap.add_argument("--heights", default="1,3", help="comma-separated, of 1 and 3 m (default 1,3)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes, one thread each")
    ap.add_argument("--chunk", type=int, default=4, help="drops searched together in one batch (default 4; "
                    "larger batches cost less Python per physics step)")
    ap.add_argument("--out", type=Path, metavar="FILE.jsonl", help="append each finished drop to this file")
    ap.add_argument("--resume", action="store_true", help="skip the drops already in --out")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--sag", action="store_true", help="also replay the motions of each design and its base to "
                    "measure how far the cat sinks after touchdown (`sag`; about a second of one core a drop)")
    args = ap.parse_args()
    from felis.errors import ParameterError

    try:
        designs = [get_design(n.strip()).name for n in args.designs.split(",") if n.strip()]
    except ParameterError as e:
        ap.error(str(e))
    designs.sort(key=lambda d: DESIGNS[d].base != d)  # the bases first (stable: otherwise as named)
    heights = [f"{float(h):g}m" for h in args.heights.split(",")]
    if not set(heights) <= {"1m", "3m"} or not 1 <= args.drops <= 100 or args.workers < 1 or args.chunk < 1:
        ap.error("--heights of 1 and 3, --drops within 1..100, --workers ≥ 1, --chunk ≥ 1")
    done: dict[tuple, dict] = {}
    log = None
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        path = args.out
        if args.resume and path.exists():
            for line in path.read_text().splitlines():
                try:
                    r = json.loads(line)
                except ValueError:
                    continue  # a line cut by a kill
                done[(r["design"], r["height"], r["i"])] = r
        log = path.open("a" if args.resume else "w")
    jobs = []
    for c in range(0, args.drops, args.chunk):
        for h in heights:
            for d in designs:
                idx = [i for i in range(c, min(args.drops, c + args.chunk)) if (d, h, i) not in done]
                if idx:
                    jobs.append((d, h, idx))
    t0 = time.perf_counter()
    n, k = sum(len(j[2]) for j in jobs), 0
    with multiprocessing.get_context("spawn").Pool(min(args.workers, max(1, len(jobs)))) as pool:
        for got in pool.imap_unordered(_job, jobs):
            for r in got:
                k += 1
                done[(r["design"], r["height"], r["i"])] = r
                if log is not None:
                    log.write(json.dumps(r) + "\n")
                    log.flush()
                if not args.json:
                    print(f"[{k}/{n} {time.perf_counter() - t0:.0f} s] {r['design']} {r['height']} drop {r['i']}: "
                          f"{'landed' if r['landed'] else 'no'} ({r['seconds']} s a drop)", file=sys.stderr,
                          flush=True)
    if log is not None:
        log.close()
    table: dict = {"settings": SETTINGS, "drops": args.drops, "seconds": round(time.perf_counter() - t0, 1),
                   "designs": {}}
    for d in designs:
        row = {"summary": DESIGNS[d].summary}
        for h in heights:
            got = [done[(d, h, i)] for i in range(args.drops) if (d, h, i) in done]
            row[h] = {"landed": sum(r["landed"] for r in got), "of": len(got)}
            base = DESIGNS[d].base
            if base != d and base in designs:
                row[h]["vs"] = against(done, d, base, h, args.drops)
                if args.sag:
                    row[h]["sag"] = sag(done, d, base, h, args.drops)
        table["designs"][d] = row
    table["shipped_anchor"] = {h: sum(r["landed"] for r in shipped(h)[:args.drops]) for h in heights}
    table["ceiling_cat"] = {h: sum(r["landed"] for r in ceiling(h)[:args.drops]) for h in heights}
    if args.json:
        print(json.dumps(table, indent=2))
        return 0
    print(f"per-drop optimum, first {args.drops} drops of random:100 --seed 0, {table['seconds']:.0f} s")
    print(f"{'design':<26}" + "".join(f"{h:>12}" for h in heights) + "   what")
    for d, row in table["designs"].items():
        counts = "".join(f"{row[h]['landed']:>7}/{row[h]['of']:<4}" for h in heights)
        print(f"{d:<26}{counts}   {row['summary']}")
        for h in heights:
            if "vs" in row[h]:
                v = row[h]["vs"]
                print(f"{'':<26}{h} against {DESIGNS[d].base} on the {v['of']} drops both have: +{v['gained']} "
                      f"-{v['lost']} (two-sided sign test p = {v['p']:.2g}); {v['lost_late']} of the lost fail "
                      f"after touching down on its feet")
            if "sag" in row[h]:
                for k, what in (("lost_late", "those late losses"), ("both", "the drops both land")):
                    g = row[h]["sag"][k]
                    if g["drops"]:
                        print(f"{'':<26}{h} lowest waist after touchdown, median share of standing, on {what} "
                              f"({g['drops']}): {DESIGNS[d].base} {g[DESIGNS[d].base]:.2f}, {d} {g[d]:.2f}")
    for key, design, what in (("shipped_anchor", ANCHOR, f"(shipped results, {ANCHOR})"),
                              ("ceiling_cat", "cat", "(cat's ceiling, warm)")):
        if design in designs:  # a check beside the design it belongs to
            counts = "".join(f"{table[key][h]:>7}/{args.drops:<4}" for h in heights)
            print(f"{what:<26}{counts}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
