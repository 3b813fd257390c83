"""How much of a landing holds when the drop height moves by a millimetre or two: the ceiling against the library.

The per-drop optimum (the ceiling of issue 21's goals, `felis eval landing --policy optimum --warm-start`) searches
each drop at its exact height and stops at the first motion that lands it. The motion library chooses from what
landed neighbouring attitudes. At 3 m the impact is at the edge of what the leg links' clearance allows, and
whether a motion lands can turn on where the cat's lowest point was at release to the millimetre. This runs
each drop's motion — the ceiling's (from its results file) and the library's choice — from the drop height and
from ``--mm`` millimetres above and below it, and prints how many land at the exact height, how many land on
average over the heights tried, and how many land at every one of them.

    python bench/landing_height.py [--height 3] [--ceiling RESULTS.json] [--mm 3] [--drops N] [--on 4ms-paw] [--json]
    python bench/landing_height.py --design soft-rubber-paw [--height 3]   # the design study's optimum, per design
    python bench/landing_height.py --band [--height 3] [--ceiling RESULTS.json]   # the ceiling over the band
    python bench/landing_height.py --scan 4 [--height 3] [--on 4ms-paw]   # why: the library's choice over ±12 mm
    python bench/landing_height.py --penetration [--height 3] [--on 4ms-paw]   # the paw's penetration, by step
    python bench/landing_height.py --timesteps 1 0.5 0.25 [--height 3] [--ceiling FILE] [--on 4ms-paw]

``--on DESIGN`` (default ``cat``, the described cat): the cat every run goes on, with its own vote of the library
(`felis.learning.landing.designs.design_library`) and its shipped ceiling
(``learning/weights/landing_optimum_warm[_<design>]-<h>m.json``) unless ``--library`` and ``--ceiling`` name others,
at its own physics step (``4ms-paw``, the cat as described until 2026-11-29: 1 ms; the described cat: 0.5 ms).

``--design NAME``: instead, the design study's per-drop optimum (searched from scratch, on the same drops) for that
design (`learning/weights/landing_design.jsonl`, `bench/landing_design.py`), run on that design's cat: how much a
paw or servo change makes a landing hold over the millimetres (the library is the described cat's only).

``--band``: the ceiling read over the band of heights. The file's ceiling is the best motion for each drop at its
exact height, picked from hundreds that the search tries there; where a landing turns on a millimetre, picking the
one that happens to land is luck that no choice made before the drop can share. This reads the ceiling as what a
motion can be relied on to land: for each drop, of every motion the warm-started search starts from (the library's
choice and its motions within 30°, `MotionLibrary.near`) and the file's own motion, the one that lands the most of
the heights h − MM … h + MM, and its share of them (`band_ceiling`; exact: a branch and bound on the heights tried
so far, first h and ±⌈MM/2⌉ mm, never skips a motion that could be the best). It prints that ceiling's landings
on average over the heights against the library's, and how many drops some of those motions lands at the exact
height (the file's own among them). About 20 min on 2 cores for 100 drops from 3 m (17 000 motions from 3 heights
each, then the other heights for those that can still win), 12 min from 1 m.

``--scan N``: why a millimetre decides. The library's choice for each of the first N drops, run from every 0.5 mm
of h − 12 … h + 12 mm: on ``4ms-paw`` from 3 m the landings come and go with a period of about √(2gh)·Δt, the
distance the cat falls in one physics step (7.7 mm at 3 m and Δt = 1 ms; `period_mm` finds it). A physical landing
has no such period: it is the step's phase at the first contact, how deep the foot is in the floor when the contact
is first seen. ``--penetration``: the cat dropped level with its joints held, from h and every 1 mm up to the next
step's fall, at its Δt and at a quarter of it (plain `mujoco.mj_step`): the foot's deepest penetration into the
floor and whether a leg link (its capsule ends 11 mm above the bottom of the foot) touches the floor.

``--timesteps MS …``: the library's choice and the ceiling file's motions run at each physics step (ms; a control
tick is 10 ms and runs as many steps as fit) on the described cat or ``--on DESIGN``: which landings are the cat's
and which the step's. A result that holds as the step shrinks is converged; one that goes is numerical.

The default ceiling is the shipped results file for ``random:100 --seed 0`` at that height on that cat; its
``seed`` and heights say which drops to run. Nothing
is random: each (drop, motion, height) is simulated once, by `felis.learning.landing.optimum.evaluate`.
About 30 s on 2 cores for 100 drops at ±3 mm.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.library import DEFAULT_LIBRARY, drop_up, load_library
from felis.scenarios.drop import Drop, random_drops

WEIGHTS = Path(__file__).resolve().parents[1] / "learning" / "weights"


def ceiling_file(height_m: float, on: str = "cat") -> Path:
    """The shipped ceiling of ``random:100 --seed 0`` from ``height_m`` on design ``on`` at its own step."""
    return WEIGHTS / f"landing_optimum_warm{'' if on == 'cat' else '_' + on}-{height_m:g}m.json"


def read_ceiling(path: Path, height_m: float) -> tuple[list[Drop], np.ndarray, np.ndarray]:
    """(the drops, each drop's motion (N, 55), whether the file says it landed (N,)) of a ``--policy optimum``
    results file for ``random:N`` at ``height_m``."""
    doc = json.loads(Path(path).read_text())
    rows = doc.get("drops")
    if not isinstance(rows, list) or not rows or "motion_x" not in rows[0]:
        raise ParameterError(f"{path}: not a per-drop optimum's results (felis eval landing --policy optimum --json)")
    if not all(math.isclose(r["height_m"], height_m) for r in rows):
        raise ParameterError(f"{path}: its drops are not from {height_m:g} m")
    seed = doc.get("seed")
    if not isinstance(seed, int):
        raise ParameterError(f"{path}: no seed (the drops must be random:N --seed S)")
    drops = random_drops(len(rows), seed=seed, heights=height_m)
    for d, r in zip(drops, rows, strict=True):
        if abs(d.roll_deg - r["roll_deg"]) > 1e-3 or abs(d.pitch_deg - r["pitch_deg"]) > 1e-3:
            raise ParameterError(f"{path}: its drops are not random:{len(rows)} --seed {seed}")
    return drops, np.array([r["motion_x"] for r in rows], dtype=float), np.array([bool(r["landed"]) for r in rows])


def read_design(path: Path, design: str, height_m: float) -> tuple[list[Drop], np.ndarray, np.ndarray]:
    """(drops, motions, landed) of the design study's rows for ``design`` from ``height_m``, in drop order."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    mine = sorted((r for r in rows if r.get("design") == design and math.isclose(r["height_m"], height_m)),
                  key=lambda r: r["i"])
    if not mine:
        names = sorted({r.get("design") for r in rows})
        raise ParameterError(f"{path}: no rows for design {design!r} from {height_m:g} m (designs: {', '.join(names)})")
    drops = [Drop(r["roll_deg"], r["pitch_deg"], r["yaw_deg"], r["height_m"]) for r in mine]
    return drops, np.array([r["motion_x"] for r in mine], dtype=float), np.array([bool(r["landed"]) for r in mine])


def landed_at(sim, drops: list[Drop], xs: np.ndarray, offsets_mm: list[int]) -> np.ndarray:
    """(N, len(offsets_mm)) bool: motion ``xs[i]`` lands drop i dropped from its height + each offset."""
    from felis.learning.landing.optimum import evaluate

    every = [Drop(d.roll_deg, d.pitch_deg, d.yaw_deg, d.height_m + mm / 1000.0) for d in drops for mm in offsets_mm]
    out = evaluate(sim, every, np.repeat(xs, len(offsets_mm), axis=0))
    return np.array([v.landed for _, v in out], dtype=bool).reshape(len(drops), len(offsets_mm))


def band_ceiling(sim, drops: list[Drop], cands: list[np.ndarray], offsets_mm: list[int], *, chunk: int = 2048,
                 progress=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each drop i, the motion of ``cands[i]`` (K_i, 55) that lands the most of the heights ``offsets_mm``:
    (its share of them (N,), its index (N,), whether any candidate lands at offset 0 (N,)).

    Exact, with fewer rollouts than every candidate at every height: all candidates first at offset 0 and
    ±⌈M/2⌉ mm (M the largest offset), then, best count first, the rest of the heights only for candidates whose
    count could still beat the best one fully tried (a candidate with k of the s first heights lands at most
    k + (n − s) of n). Of equal counts the first found is kept. ``progress(done, total)`` after each chunk of
    rollouts."""
    n_off = len(offsets_mm)
    if 0 not in offsets_mm:
        raise ParameterError("band ceiling: the heights must include the drop height (offset 0)")
    half = -(-max(abs(m) for m in offsets_mm) // 2)
    first = [k for k, m in enumerate(offsets_mm) if m in (0, -half, half)]
    rest = [k for k in range(n_off) if k not in first]
    R = [np.full((len(c), n_off), -1, dtype=np.int8) for c in cands]
    done = total = 0

    def run(jobs: list[tuple[int, int, int]]) -> None:  # (drop, candidate, offset index)
        nonlocal done, total
        total += len(jobs)
        for a in range(0, len(jobs), chunk):
            part = jobs[a:a + chunk]
            got = landed_at(sim, [_offset(drops[i], offsets_mm[k]) for i, _, k in part],
                            np.array([cands[i][c] for i, c, _ in part]), [0])[:, 0]
            for (i, c, k), ok in zip(part, got, strict=True):
                R[i][c, k] = ok
            done += len(part)
            if progress is not None:
                progress(done, total)

    run([(i, c, k) for i in range(len(drops)) for c in range(len(cands[i])) for k in first])
    best = np.full(len(drops), -1)
    best_count = np.full(len(drops), -1)
    count1 = [r[:, first].sum(axis=1) for r in R]
    for k in range(len(first), -1, -1):  # candidates with k of the first heights, while they can still win
        level = [(i, np.flatnonzero(count1[i] == k)) for i in range(len(drops))
                 if best_count[i] < k + len(rest)]
        run([(i, int(c), j) for i, cs in level for c in cs for j in rest])
        for i, cs in level:
            for c in cs:
                lands = int(R[i][c].sum())
                if lands > best_count[i]:
                    best_count[i], best[i] = lands, int(c)
    at_h = np.array([bool((r[:, offsets_mm.index(0)] == 1).any()) for r in R])
    return best_count / n_off, best, at_h


def _offset(d: Drop, mm: int) -> Drop:
    return Drop(d.roll_deg, d.pitch_deg, d.yaw_deg, d.height_m + mm / 1000.0)


def period_mm(pattern: np.ndarray, step_mm: float, min_mm: float = 3.0) -> float | None:
    """The period of a landed/not-landed ``pattern`` sampled every ``step_mm`` (mm): the shift (≥ ``min_mm``, at most
    half the pattern) at which it agrees with itself most; None where it never changes."""
    p = np.asarray(pattern, dtype=bool)
    if p.all() or not p.any():
        return None
    shifts = range(max(1, math.ceil(min_mm / step_mm - 1e-9)), len(p) // 2 + 1)
    agree = [float(np.mean(p[k:] == p[:-k])) for k in shifts]
    return float(list(shifts)[int(np.argmax(agree))] * step_mm)


def penetration(height_m: float, offsets_mm, timestep: float, design: str = "cat"
                ) -> list[tuple[float, float, float | None]]:
    """The described cat (or ``design``'s: its paw) dropped level (its lowest point at ``height_m`` + each offset),
    joints held at the release pose, plain `mujoco.mj_step` at ``timestep`` s: (offset mm, the feet's deepest
    penetration into the floor in mm, ms from the first foot contact to a leg link's first contact, or None) over
    the 50 ms after touchdown."""
    import mujoco

    from felis.learning.landing.designs import design_robot, get_design
    from felis.sim.robot import load_model, model_path
    from felis.spec import load_spec

    m = load_model(model_path(load_spec("cat")), edit=design_robot(get_design(design))[2])
    m.opt.timestep = float(timestep)
    d = mujoco.MjData(m)
    gid = {n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("floor", *(
        f"{leg}_{part}" for leg in ("fl", "fr", "hl", "hr") for part in ("foot", "leg")))}
    feet = {gid[n] for n in gid if n.endswith("_foot")}
    links = {gid[n] for n in gid if n.endswith("_leg")}
    out = []
    for mm in offsets_mm:
        mujoco.mj_resetData(m, d)
        mujoco.mj_forward(m, d)
        low = min(float(d.geom_xpos[g][2] - m.geom_size[g][0]) for g in feet)
        d.qpos[2] += height_m + mm / 1000.0 - low
        mujoco.mj_forward(m, d)
        deepest, t_foot, t_link = 0.0, None, None
        while d.time < 2.0 and (t_foot is None or d.time < t_foot + 0.05):
            mujoco.mj_step(m, d)
            for c in d.contact[:d.ncon]:
                g = c.geom2 if c.geom1 == gid["floor"] else c.geom1
                if g in feet and c.dist < 0:
                    deepest = min(deepest, float(c.dist))
                    t_foot = d.time if t_foot is None else t_foot
                elif g in links and c.dist < 0 and t_link is None:
                    t_link = d.time
        lag = None if t_link is None or t_foot is None else (t_link - t_foot) * 1000.0
        out.append((float(mm), -deepest * 1000.0, lag))
    return out


def summary(R: np.ndarray, offsets_mm: list[int]) -> dict:
    at = R[:, offsets_mm.index(0)]
    return {"landed_at_height": int(at.sum()), "mean_over_heights": round(float(R.mean(axis=1).sum()), 1),
            "landed_at_every_height": int(R.all(axis=1).sum()),
            "by_offset_mm": {str(mm): int(R[:, k].sum()) for k, mm in enumerate(offsets_mm)}}


def main() -> None:
    from felis.learning.landing.optimum import _worker_sim

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=float, default=3.0)
    ap.add_argument("--ceiling", type=Path, help="a --policy optimum --json results file (default: the shipped "
                    "seed-0 file for --height)")
    ap.add_argument("--library", type=Path, help="a motion library (default: the --on cat's vote of the shipped one)")
    ap.add_argument("--design", help="instead: the design study's optimum for this design, on its own cat")
    ap.add_argument("--mm", type=int, default=3, help="heights from −MM to +MM mm in 1 mm steps (default 3)")
    ap.add_argument("--drops", type=int, help="only the first N drops")
    ap.add_argument("--band", action="store_true", help="also the ceiling read over the band of heights (module doc)")
    ap.add_argument("--scan", type=int, metavar="N", help="instead: the library's choice for the first N drops from "
                    "every 0.5 mm of ±12 mm, and the period of its landings (module doc)")
    ap.add_argument("--timesteps", type=float, nargs="+", metavar="MS", help="instead: the library's choice and "
                    "the ceiling's motions at each physics step (ms), on the described cat or --on DESIGN")
    ap.add_argument("--on", default="cat", metavar="DESIGN", help="the cat every run goes on, with its vote and its "
                    "ceiling (default cat, the described one; 4ms-paw: the cat as described until 2026-11-29)")
    ap.add_argument("--penetration", action="store_true", help="instead: a level drop's paw penetration and leg-link "
                    "contact by the height's phase in a physics step, at the model's step and a quarter of it")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.band and args.design:
        raise SystemExit("landing_height: --band reads the library's motions, on the described cat: not with --design")
    if args.mm < 1:
        raise SystemExit("landing_height: --mm must be ≥ 1")
    if args.penetration:
        return _penetration(args)
    if args.timesteps is not None and (args.design or args.band or args.scan is not None):
        raise SystemExit("landing_height: --timesteps is a study of its own: not with --design, --band or --scan")
    if args.scan is not None:
        if args.scan < 1:
            raise SystemExit("landing_height: --scan needs at least 1 drop")
        args.drops = args.scan
    try:
        from felis.learning.landing.designs import design_library, get_design

        get_design(args.on)
        args.library = args.library or design_library(args.on) or DEFAULT_LIBRARY
        if args.design:
            get_design(args.design)
            drops, ceil_x, ceil_landed = read_design(WEIGHTS / "landing_design.jsonl", args.design, args.height)
        else:
            drops, ceil_x, ceil_landed = read_ceiling(args.ceiling or ceiling_file(args.height, args.on), args.height)
            lib = load_library(args.library)
    except (OSError, ValueError, ParameterError) as e:
        raise SystemExit(f"landing_height: {e}") from None
    n = len(drops) if args.drops is None else max(1, min(args.drops, len(drops)))
    drops, ceil_x, ceil_landed = drops[:n], ceil_x[:n], ceil_landed[:n]
    offsets = list(range(-args.mm, args.mm + 1))
    if args.timesteps is not None:
        return _timesteps(args, drops, ceil_x, ceil_landed, lib)
    sim = _worker_sim(args.design or args.on)
    if args.scan is not None:
        return _scan(args, sim, drops, lib)
    first = "optimum" if args.design else "ceiling"  # the design study's, from scratch; or the warm-started one
    policies = [(first, ceil_x)]
    if not args.design:
        policies.append(("library", np.array([lib.choose(drop_up(d), d.height_m) for d in drops])))
    rows = {name: summary(landed_at(sim, drops, xs, offsets), offsets) for name, xs in policies}
    rows[first]["file_says_landed"] = int(ceil_landed.sum())
    out = {"height_m": args.height, "drops": n, "offsets_mm": offsets, **({"design": args.design} if args.design
                                                                          else {}), **rows}
    if not args.design:
        c, b = rows["ceiling"], rows["library"]
        out["library_over_ceiling"] = {
            "at_height": round(b["landed_at_height"] / max(c["landed_at_height"], 1), 3),
            "mean_over_heights": round(b["mean_over_heights"] / max(c["mean_over_heights"], 1e-9), 3)}
    if args.band:
        t0 = time.monotonic()
        shown = not args.json or sys.stderr.isatty()

        def progress(done: int, total: int) -> None:
            if shown:
                print(f"\rband ceiling: {done}/{total} rollouts, {time.monotonic() - t0:.0f} s", end="",
                      file=sys.stderr, flush=True)

        cands = [np.concatenate([lib.near(drop_up(d), d.height_m), ceil_x[i:i + 1]]) for i, d in enumerate(drops)]
        share, _, at_h = band_ceiling(sim, drops, cands, offsets, progress=progress)
        if shown:
            print(file=sys.stderr)
        mean = round(float(share.sum()), 1)
        out["band_ceiling"] = {"candidates": int(sum(len(c) for c in cands)), "mean_over_heights": mean,
                               "landed_at_every_height": int((share == 1.0).sum()),
                               "some_candidate_lands_at_height": int(at_h.sum()),
                               "seconds": round(time.monotonic() - t0)}
        out["library_over_band_ceiling"] = round(rows["library"]["mean_over_heights"] / max(mean, 1e-9), 3)
    if args.json:
        print(json.dumps(out, indent=1))
        return
    what = f"design {args.design}: the design study's optimum" if args.design else "the ceiling and the library"
    print(f"{n} drops from {args.height:g} m, each also from ±1…{args.mm} mm; {what}")
    print(f"{'':10} {'at h':>6} {'mean over heights':>18} {'at every height':>16}  by offset (mm)")
    for name, _ in policies:
        r = rows[name]
        print(f"{name:10} {r['landed_at_height']:>6} {r['mean_over_heights']:>18} {r['landed_at_every_height']:>16}  "
              + " ".join(f"{k}:{v}" for k, v in r["by_offset_mm"].items()))
    if not args.design:
        ratios = out["library_over_ceiling"]
        print(f"library / ceiling: {ratios['at_height']} at h, {ratios['mean_over_heights']} on average over the "
              "heights")
    if args.band:
        b = out["band_ceiling"]
        print(f"band ceiling (of {b['candidates']} motions, each drop's that lands the most heights): "
              f"{b['mean_over_heights']} on average over the heights, {b['landed_at_every_height']} at every height; "
              f"some motion lands {b['some_candidate_lands_at_height']} at h")
        print(f"library / band ceiling: {out['library_over_band_ceiling']} on average over the heights")


def _timesteps(args, drops: list[Drop], ceil_x: np.ndarray, ceil_landed: np.ndarray, lib) -> None:
    from felis.learning.landing.designs import design_sim, get_design
    from felis.learning.landing.evaluate import check_timestep_ms

    try:
        get_design(args.on)
        for ms in args.timesteps:
            check_timestep_ms(ms)
    except ParameterError as e:
        raise SystemExit(f"landing_height: {e}") from None
    from felis.learning.landing.optimum import evaluate

    lib_x = np.array([lib.choose(drop_up(d), d.height_m) for d in drops])
    rows = []
    for ms in args.timesteps:
        sim = design_sim(args.on, timestep=ms / 1000.0)
        try:
            got = [int(sum(v.landed for _, v in evaluate(sim, drops, xs))) for xs in (lib_x, ceil_x)]
        finally:
            sim.close()
        rows.append({"timestep_ms": ms, "library": got[0], "ceiling": got[1]})
    out = {"height_m": args.height, "drops": len(drops), "on": args.on, "file_says_landed": int(ceil_landed.sum()),
           "by_timestep": rows}
    if args.json:
        print(json.dumps(out, indent=1))
        return
    print(f"{len(drops)} drops from {args.height:g} m on {args.on}; the ceiling's file says {out['file_says_landed']}")
    for r in rows:
        print(f"physics step {r['timestep_ms']:g} ms: library {r['library']}, the ceiling's motions {r['ceiling']}")


SCAN_STEP_MM, SCAN_MM = 0.5, 12.0


def _model_step(height_m: float, on: str = "cat") -> tuple[float, float]:
    """(design ``on``'s physics step in s, how far a cat dropped from ``height_m`` falls in it at touchdown, mm)."""
    from felis.learning.landing.designs import design_timestep
    from felis.rotations import G

    dt = design_timestep(on)
    return dt, math.sqrt(2.0 * G * height_m) * dt * 1000.0


def _scan(args, sim, drops: list[Drop], lib) -> None:
    offsets = np.round(np.arange(-SCAN_MM, SCAN_MM + 1e-9, SCAN_STEP_MM), 3)
    xs = np.array([lib.choose(drop_up(d), d.height_m) for d in drops])
    _, fall_mm = _model_step(args.height, args.on)
    rows = []
    for d, x in zip(drops, xs, strict=True):
        R = landed_at(sim, [d], x[None], list(offsets))[0]
        rows.append({"drop": asdict(d), "landed": R.astype(int).tolist(),
                     "period_mm": period_mm(R, SCAN_STEP_MM)})
    if args.json:
        print(json.dumps({"height_m": args.height, "offsets_mm": offsets.tolist(), "fall_per_step_mm": fall_mm,
                          "drops": rows}, indent=1))
        return
    print(f"the library's choice from h {-SCAN_MM:+g} … {SCAN_MM:+g} mm every {SCAN_STEP_MM:g} mm ('#' landed, "
          f"'|' at h); one physics step's fall at touchdown: {fall_mm:.1f} mm")
    centre = int(np.flatnonzero(offsets == 0)[0])
    for i, r in enumerate(rows):
        line = "".join("#" if v else "." for v in r["landed"])
        period = "none" if r["period_mm"] is None else f"{r['period_mm']:g} mm"
        print(f"drop {i:3d} {line[:centre]}|{line[centre]}|{line[centre + 1:]}  period {period}")


def _penetration(args) -> None:
    from felis.learning.landing.designs import get_design

    try:
        get_design(args.on)
    except ParameterError as e:
        raise SystemExit(f"landing_height: {e}") from None
    dt, fall_mm = _model_step(args.height, args.on)
    offsets = list(range(0, math.ceil(fall_mm) + 1))
    res = {f"{step * 1000:g}": penetration(args.height, offsets, step, args.on) for step in (dt, dt / 4)}
    if args.json:
        print(json.dumps({"height_m": args.height, "fall_per_step_mm": fall_mm, "on": args.on,
                          "by_timestep_ms": {k: [{"offset_mm": o, "deepest_mm": round(p, 2), "link_after_ms": lag}
                                                 for o, p, lag in v] for k, v in res.items()}}, indent=1))
        return
    print(f"{args.on}: a level drop from {args.height:g} m + offset, joints held; one physics step's fall: "
          f"{fall_mm:.1f} mm")
    for k, v in res.items():
        print(f"Δt {k} ms: " + ", ".join(f"+{o:g} mm {p:.1f}" + ("" if lag is None else f" (link {lag:.1f} ms)")
                                          for o, p, lag in v))


if __name__ == "__main__":
    main()
