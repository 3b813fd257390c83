"""``felis eval landing``: drop the simulated cat from many orientations and heights and count landings.

``felis eval landing --drops FILE|random:N [--policy passive|stand|FILE]`` releases the cat once per drop
and judges each landing by the issue's rule (`felis.scenarios.verdicts`): only the feet touch the ground from
touchdown to 0.5 s after it, and then the upper body is within 30° of vertical and the waist above half
its standing height. It prints the success rate and the reasons for the failures, or with ``--json`` the
result with one entry per drop (``--out`` also writes it to a file).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from felis.cli import output
from felis.cli.args import check_checkpoints, has_checkpoints, live_option, restart_option
from felis.errors import ParameterError
from felis.learning.landing.designs import DESIGNS, design_library

DEFAULT_TRAIN_OUT = Path("runs/train-landing/landing.npz")
DEFAULT_TRAIN_LIBRARY = Path("runs/train-landing/landing_library.json")


def register_train(train_sub) -> None:
    """Add ``felis train landing``."""
    from felis.learning.landing.config import TrainConfig  # late: its settings only

    d = TrainConfig()
    t = train_sub.add_parser("landing", help="evolve the landing nets (seed 000): the simple stage per training "
                             "orientation, then the complex stage; checkpoints resume")
    t.add_argument("--out", type=Path, default=DEFAULT_TRAIN_OUT,
                   help=f"policy file (.npz; default {DEFAULT_TRAIN_OUT})")
    t.add_argument("--workdir", type=Path, help="checkpoints (default: <out>.ckpt/ beside the policy)")
    t.add_argument("--resume", action="store_true", help="continue from the checkpoint in --workdir")
    restart_option(t)
    t.add_argument("--seed", type=int, default=d.seed, help=f"seed (default {d.seed})")
    t.add_argument("--population", type=int, default=d.population, help=f"individuals per population "
                   f"(default {d.population})")
    t.add_argument("--generations-simple", type=int, default=d.generations_simple,
                   help=f"generations of the simple stage (default {d.generations_simple})")
    t.add_argument("--generations-complex", type=int, default=d.generations_complex,
                   help=f"generations of the complex stage (default {d.generations_complex})")
    t.add_argument("--orientations", type=int, nargs="+", metavar="I",
                   help="training orientations (indices into the motion samples; default all 7)")
    t.add_argument("--f-only", action="store_true", help="rank by the fitness f alone, without the similarity to "
                   "the motion samples (the paper's experiment 1)")
    t.add_argument("--fitness", choices=("eq9", "landing"), default=d.fitness,
                   help="eq9: the paper's eq. 9 x upright (default); landing: ours, partial credit for each clause "
                   "of the landed rule")
    t.add_argument("--one-net", action="store_true", help="one net on every training orientation instead of "
                   "simple then complex (the paper's experiment 2 baseline)")
    t.add_argument("--generations-general", type=int, default=d.generations_general,
                   help="generations of a last stage on random drops from 1 m and 3 m (ours; default 0: none); "
                   "its best is the policy")
    t.add_argument("--general-drops", type=int, default=d.general_drops,
                   help=f"random drops per generation of that stage (default {d.general_drops})")
    t.add_argument("--general-max-tilt", type=float, default=d.general_max_tilt_deg, metavar="DEG",
                   help="that stage draws only drops tilted at most this far from upright (default "
                   f"{d.general_max_tilt_deg:g}: any)")
    t.add_argument("--samples", type=Path, metavar="FILE", help="motion samples (default: the shipped ones), or a "
                   "motion library: its landing motions nearest the 7 orientations")
    t.add_argument("--design", default=d.design, choices=list(DESIGNS),
                   help="evolve on another buildable cat of the design study (its servos, paws and physics step; "
                   "default cat, the described one; the shipped nets were evolved on 4ms-paw)")
    t.add_argument("--workers", type=int, help="local processes (default: every core)")
    t.add_argument("--ray-address", metavar="ADDRESS|auto|local",
                   help="run rollouts on a Ray cluster (needs felis[cluster]); local starts one here")
    t.add_argument("--json", action="store_true", help="print the results as JSON")
    t.set_defaults(func=cmd_train_landing)

    from felis.learning.landing.library import DEFAULT_LIBRARY
    from felis.learning.landing.library_build import FILL_GENERATIONS, FILL_ROUNDS, GRID, MAX_TILT_DEG, PROBES

    b = train_sub.add_parser("landing-library", help="the landing motion library: the per-drop optimum on a grid of "
                             "start attitudes, then which motion lands each probe attitude (docs/landing.md)")
    b.add_argument("--out", type=Path, default=DEFAULT_TRAIN_LIBRARY,
                   help=f"library file (.json; default {DEFAULT_TRAIN_LIBRARY}; the shipped one is "
                   f"learning/weights/{DEFAULT_LIBRARY.name})")
    b.add_argument("--heights", type=float, nargs="+", default=[1.0, 3.0], metavar="M",
                   help="drop heights, one shelf each (default 1 3)")
    b.add_argument("--grid", type=int, default=GRID, help=f"points of the attitudes' Fibonacci sphere (default {GRID})")
    b.add_argument("--probes", type=int, default=PROBES,
                   help=f"points of the probes' Fibonacci sphere (default {PROBES})")
    b.add_argument("--max-tilt", type=float, default=MAX_TILT_DEG, metavar="DEG",
                   help=f"attitudes tilted at most this far from upright (default {MAX_TILT_DEG:g})")
    b.add_argument("--generations", type=int, default=30, help="CMA-ES generations per start (default 30)")
    b.add_argument("--population", type=int, default=12, help="CMA-ES population (default 12)")
    b.add_argument("--restarts", type=int, default=1, help="further CMA-ES starts (default 1)")
    b.add_argument("--fill-generations", type=int, default=FILL_GENERATIONS, metavar="N",
                   help="CMA-ES generations of a new motion for each probe that no motion lands, from the nearest "
                   f"(0: none; default {FILL_GENERATIONS})")
    b.add_argument("--fill-rounds", type=int, default=FILL_ROUNDS, metavar="N",
                   help="rounds of the fill: the first for the probes no motion lands, the next for those where the "
                   f"choice, their own vote left out, picks one that fails (default {FILL_ROUNDS})")
    b.add_argument("--patch", type=float, default=0.0, metavar="DEG",
                   help="each entry's search must also land the four attitudes DEG away in roll and pitch (its score "
                   "the worst of five; 5x the rollouts; default 0)")
    b.add_argument("--seed", type=int, default=0, help="search seed (default 0)")
    b.add_argument("--workdir", type=Path, help="checkpoints (default: <out>.ckpt/ beside the library)")
    b.add_argument("--resume", action="store_true", help="continue from the checkpoints in --workdir")
    restart_option(b)
    b.add_argument("--workers", type=int, help="processes for the search, threads for the probes (default: every "
                   "core)")
    b.add_argument("--ray-address", metavar="ADDRESS|auto|local", help="search on a Ray cluster (felis[cluster])")
    b.add_argument("--add", nargs="+", type=Path, metavar="MOTION.json",
                   help="no search: add these motion files (felis eval landing --policy optimum --motions DIR) to "
                   "the library --base as entries of their drop height's shelf, tried on the probes near them")
    b.add_argument("--base", type=Path, metavar="LIBRARY.json",
                   help="the library --add or --add-probes extends (default: the shipped one, "
                   f"learning/weights/{DEFAULT_LIBRARY.name}); with a search: the library whose --heights shelves "
                   "the search rebuilds, its other shelves kept")
    b.add_argument("--join", type=Path, metavar="LIBRARY.json",
                   help="no search: the --heights shelves of --base also hold this library's motions for those "
                   "heights (the same probes needed), so the vote chooses among both searches' candidates")
    b.add_argument("--add-probes", type=int, metavar="N",
                   help="no search: add the probes of an N-point Fibonacci sphere to the --heights shelves of --base, "
                   "each tried with the motions within --probe-radius of it (a denser grid for a narrower vote)")
    b.add_argument("--near-misses", action="store_true",
                   help="--add-probes: only the sphere's points whose nearest probe is a miss (the vote, that probe "
                   "left out, picks a motion that fails there): a refinement where the vote is wrong")
    b.add_argument("--recheck", action="store_true",
                   help="no search: try every entry of the --heights shelves of --base on its own attitude again and "
                   "record whether it lands (libraries built before robustify's fix carry wrong flags)")
    b.add_argument("--extend", type=float, metavar="DEG",
                   help="no search of the grid: take the --heights shelves of --base out to this tilt: the probes of "
                   "the --probes sphere beyond the shelf's farthest, tried with the motions within --probe-radius, "
                   "then --fill-rounds rounds of fills for those that no motion (or the choice) lands, each searched "
                   "from the nearest motion that lands something (continuation from the shelf's edge)")
    b.add_argument("--fill", type=float, nargs="?", const=180.0, metavar="DEG",
                   help="no search of the grid: --fill-rounds rounds of fills over the --heights shelves' own probes "
                   "(those tilted at most DEG; default all): a motion searched on --design's cat for each probe "
                   "that no motion lands, then where the vote picks one that fails, each from the nearest motion "
                   "that lands it or lands something (a shelf searched on another cat leaves holes on this one)")
    b.add_argument("--probe-radius", type=float, default=30.0, metavar="DEG",
                   help="--add-probes, --extend, --fill: try the motions within this angle of each new probe or "
                   "motion (default 30)")
    b.add_argument("--sigma", type=float, metavar="DEG",
                   help="--add-probes, --join: the vote width of those shelves (default: as it was)")
    b.add_argument("--design", default="cat", choices=list(DESIGNS),
                   help="search and judge every motion on another buildable cat of the design study (its servos, "
                   "paws and physics step; default cat, the described one)")
    b.set_defaults(func=cmd_train_library)


def register_eval(eval_sub) -> None:
    """Add ``felis eval landing``."""
    e = eval_sub.add_parser("landing", help="drop the cat from many orientations and heights: the landing "
                            "success rate of a policy")
    e.add_argument("--drops", required=True, metavar="FILE|random:N|euler:N",
                   help="a JSON list of drops {roll_deg, pitch_deg, yaw_deg, height_m}, random:N (orientations "
                   "uniform over all rotations) or euler:N (roll, pitch and yaw each uniform over the circle)")
    e.add_argument("--policy", metavar="caps+library|library|shipped|caps|passive|stand|rules|optimum|FILE",
                   help="what the cat does while it falls and lands: caps+library (the default: at 1 m and 3 m, "
                   "whichever of the cap policy made for that height and the motion library landed more training "
                   "drops started near the attitude at release; on another --design, library), library (the "
                   "shipped motion library: the "
                   "motion that lands most often near the attitude the IMU gives at release; "
                   "on a --design with its own vote, that one: 4ms-paw's and the study's, taken on the 4 ms-paw cat), "
                   "shipped "
                   "(the evolved nets), caps (the shipped cap policy: closed-loop nets of the paper's size imitated "
                   "from the library's motions, then evolved; built for 1 m), passive (hold the pose at release), "
                   "stand (go to the stand pose), rules (the "
                   "hand-written spine rule of the nearest training orientation), optimum (the best open-loop "
                   "whole-body motion CMA-ES finds for each drop; slow; with --warm-start, searched from the library's "
                   "motions too: the ceiling), a policy file from `felis "
                   "train landing` (.npz), a library from `felis train landing-library` (.json), a cap policy "
                   "from bench/landing_caps.py (.json) or a vote between policies from bench/landing_vote.py (.json)")
    e.add_argument("--generations", type=int, default=30, help="optimum: CMA-ES generations per start (default 30)")
    e.add_argument("--population", type=int, default=12, help="optimum: CMA-ES population (default 12)")
    e.add_argument("--restarts", type=int, default=0, help="optimum: further starts from the next seeds (default 0)")
    e.add_argument("--checkpoint", type=Path, metavar="DIR",
                   help="optimum: append each finished drop to DIR/optimum.jsonl (with --resume: skip those)")
    e.add_argument("--resume", action="store_true", help="optimum: continue from --checkpoint DIR")
    restart_option(e, "--checkpoint DIR")
    e.add_argument("--late-ticks", type=int, default=0, metavar="K",
                   help="optimum: a motion counts only if it also lands started 1..K ticks late (a servo bus's "
                   "latency and jitter; default 0)")
    e.add_argument("--patch", type=float, default=0.0, metavar="DEG",
                   help="optimum: a motion counts only if it also lands the four attitudes DEG away in roll and pitch "
                   "(its score the worst of five: a landing that holds when the release attitude is a little off; "
                   "5x the rollouts; default 0)")
    e.add_argument("--warm-start", nargs="?", const="library", metavar="LIBRARY",
                   help="optimum: each drop's search also starts from a motion library's motions for its attitude "
                   "(its choice and every motion made within 30°; LIBRARY: a file from `felis train "
                   "landing-library`, default the shipped one): the ceiling the library is read against (with "
                   "--design, on that design's cat)")
    e.add_argument("--motions", type=Path, metavar="DIR",
                   help="optimum: write each drop's best motion to DIR/drop-<i>.json, a policy `felis run landing "
                   "--policy` runs (open loop, for that drop)")
    e.add_argument("--ray-address", metavar="ADDRESS|auto|local",
                   help="optimum: search chunks of drops on a Ray cluster (pip install felis[cluster])")
    e.add_argument("--design", default="cat", choices=list(DESIGNS),
                   help="another buildable cat (servos, voltage, paws; docs/landing.md, the design study); "
                   "default cat, the described one")
    e.add_argument("--timestep", type=float, metavar="MS",
                   help="the physics step in ms (default the design's: the described cat's model 0.5, 4ms-paw and "
                   "the study's designs 1; it must divide the 10 ms control tick): "
                   "whether a result holds as the impact is resolved more finely (docs/landing.md, the physics step)")
    e.add_argument("--seed", type=int, default=0, help="seed of random:N (default 0)")
    e.add_argument("--height", type=float, metavar="M", help="drop height for random:N (m, default 1.0)")
    e.add_argument("--workers", type=int, help="rollout threads (default: every core); optimum: processes, one "
                   "thread each (default: this process, every core)")
    e.add_argument("--out", type=Path, metavar="FILE.json", help="also write the JSON result to this file")
    e.add_argument("--json", action="store_true", help="print the result as JSON")
    live_option(e, "one drop only: serve it live to Foxglove over WebSocket, on the wall clock")
    e.set_defaults(func=cmd_eval_landing)


def cmd_train_landing(args) -> int:
    from felis.files import check_target
    from felis.learning.landing.train import TrainConfig, train_landing

    cfg = TrainConfig(seed=args.seed, population=args.population, generations_simple=args.generations_simple,
                      generations_complex=args.generations_complex, orientations=tuple(args.orientations or ()),
                      use_similarity=not args.f_only, samples=str(args.samples or ""), fitness=args.fitness,
                      one_net=args.one_net, generations_general=args.generations_general,
                      general_drops=args.general_drops, general_max_tilt_deg=args.general_max_tilt,
                      design=args.design, workers=args.workers,
                      ray_address=args.ray_address)
    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise ParameterError(f"{out}: a landing policy file must end in .npz")
    check_target(out, "landing policy", ParameterError)
    workdir = args.workdir or out.with_suffix(".ckpt")
    check_checkpoints(workdir, args.resume, args.restart, has_checkpoints(workdir, "checkpoint.npz"))
    quiet = args.json or not sys.stderr.isatty()
    bar = output.bar(quiet=quiet, field="info", transient=False)
    tasks: dict[str, int] = {}

    def progress(stage, generation, generations, info):
        def fmt(v):
            if isinstance(v, list):
                return f"{max(v):.3g}" if v else "-"
            return f"{v:.3g}" if isinstance(v, float) else str(v)

        keys = ("best_f", "score", "mean_f", "successes", "landed", "orientations")
        text = ", ".join(f"{k} {fmt(info[k])}" for k in keys if k in info)
        if stage not in tasks:
            tasks[stage] = bar.add_task(f"{stage} stage", total=generations, info="")
        bar.update(tasks[stage], completed=generation, info=text)
        if quiet and not args.json:
            print(f"{stage} stage: generation {generation}/{generations}: {text}", flush=True)

    with bar:
        res = train_landing(cfg, out, workdir, resume=args.resume, progress=progress)
    if args.json:
        output.print_json(res)
        return 0
    stem = out.with_suffix("")
    print(f"policy: {out}; results: {stem}.results.json; curves: {stem}.curves.png")
    return 0


def _stage_bar():
    """(a progress bar, ``progress(stage, done, total)`` for it): one task per stage; a line per update when
    stderr is not a terminal."""
    quiet = not sys.stderr.isatty()
    bar = output.bar(quiet=quiet, field="info", transient=False)
    tasks: dict[str, int] = {}

    def progress(stage, done, total):
        if stage not in tasks:
            tasks[stage] = bar.add_task(stage, total=total, info="")
        bar.update(tasks[stage], completed=done)
        if quiet:
            print(f"{stage}: {done}/{total}", flush=True)

    return bar, progress


def cmd_train_library(args) -> int:
    import shlex

    from felis.files import check_target
    from felis.learning.landing.library_build import build_library

    out = Path(args.out)
    if out.suffix.lower() != ".json":
        raise ParameterError(f"{out}: a landing motion library file must end in .json")
    if args.workers is not None and args.workers < 1:
        raise ParameterError(f"--workers must be ≥ 1, got {args.workers}")
    if args.fill_generations < 0 or args.fill_rounds < 1:
        raise ParameterError(f"--fill-generations must be ≥ 0 and --fill-rounds ≥ 1, got {args.fill_generations} "
                             f"and {args.fill_rounds}")
    check_target(out, "landing motion library", ParameterError)
    command = "felis " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    if sum(x is not None and x != [] and x is not False for x in (args.add, args.add_probes, args.join,
                                                                  args.recheck, args.extend, args.fill)) > 1:
        raise ParameterError("--add, --add-probes, --join, --recheck, --extend and --fill: one at a time")
    if args.near_misses and args.add_probes is None:
        raise ParameterError("--near-misses refines --add-probes N: give it too")
    if args.extend is not None:
        return _extend_library(args, out, command)
    if args.fill is not None:
        return _fill_library(args, out, command)
    if args.recheck:
        return _recheck_library(args, out, command)
    if args.join is not None:
        return _join_libraries(args, out, command)
    if args.add:
        return _add_to_library(args, out, command)
    if args.add_probes is not None:
        return _add_probes_to_library(args, out, command)
    base = None
    if args.base is not None:  # a rebuild of the --heights shelves; read first, so a bad file costs no search
        from felis.learning.landing.library import load_library

        base = load_library(args.base)
    if not (math.isfinite(args.patch) and args.patch >= 0):
        raise ParameterError(f"--patch must be ≥ 0 degrees, got {args.patch}")
    workdir = args.workdir or out.with_suffix(".ckpt")
    check_checkpoints(workdir, args.resume, args.restart, has_checkpoints(workdir))
    bar, progress = _stage_bar()
    with bar:
        lib = build_library(args.heights, grid=args.grid, probes=args.probes, max_tilt_deg=args.max_tilt,
                            generations=args.generations, population=args.population, restarts=args.restarts,
                            seed=args.seed, workers=args.workers, ray_address=args.ray_address, workdir=workdir,
                            resume=args.resume, command=command, fill_generations=args.fill_generations,
                            fill_rounds=args.fill_rounds, patch_deg=args.patch, design=args.design,
                            progress=progress)
    built = [s.height_m for s in lib.shelves]
    if base is not None:
        from felis.learning.landing.library_build import replace_shelves

        lib = replace_shelves(base, lib, command)
    _write_library(out, lib)
    for s in lib.shelves:
        if s.height_m not in built:
            print(f"{s.height_m:g} m: kept from {args.base}")
            continue
        print(f"{s.height_m:g} m: {int(s.landed.sum())} of {len(s.landed)} entries (the optimum, its robust "
              f"twins, the fills) land their own attitude; "
              f"{int(s.lands.any(axis=1).sum())} of {len(s.probe_up)} probes landed by some motion")
    print(f"library: {out}")
    return 0


def _write_library(out: Path, lib) -> None:
    import json

    from felis.files import write_atomic

    write_atomic(out, json.dumps(lib.as_dict(), separators=(",", ":")) + "\n", "landing motion library")


def _add_to_library(args, out: Path, command: str) -> int:
    """``felis train landing-library --add MOTION.json… [--base LIBRARY]``: `add_motions`, written to ``out``."""

    from felis.learning.landing.library import DEFAULT_LIBRARY, load_library
    from felis.learning.landing.library_build import add_motions
    from felis.learning.landing.motion import load_motion

    base = args.base or DEFAULT_LIBRARY
    lib = load_library(base)
    motions = []
    for path in args.add:
        rule, drop = load_motion(path)
        if drop is None:
            raise ParameterError(f"{path}: a motion file without its 'drop' cannot join a library (the library "
                                 "places a motion by the attitude it was searched for)")
        if not math.isclose(rule.height_m, float(drop["height_m"]), rel_tol=1e-6):
            raise ParameterError(f"{path}: the motion is timed for {rule.height_m:g} m but its drop is from "
                                 f"{float(drop['height_m']):g} m")
        motions.append((rule.x, drop, Path(path).name))
    bar, progress = _stage_bar()
    with bar:
        lib = add_motions(lib, motions, workers=args.workers, command=command, design=args.design, progress=progress)
    _write_library(out, lib)
    for a in lib.meta["added"][-len(motions):]:
        d = a["drop"]
        print(f"{a['motion']}: {a['height_m']:g} m shelf, drop ({d['roll_deg']:g}, {d['pitch_deg']:g}, "
              f"{d['yaw_deg']:g}) {'lands' if a['landed'] else 'does NOT land'} its own attitude; "
              f"{a['probes_landed']} probes landed by it or its mirror image")
    print(f"library: {out} (from {base})")
    return 0


def _join_libraries(args, out: Path, command: str) -> int:
    """``felis train landing-library --join OTHER [--base LIBRARY] [--heights H…]``: `join_shelves`."""
    from felis.learning.landing.library import DEFAULT_LIBRARY, load_library
    from felis.learning.landing.library_build import join_shelves

    base = args.base or DEFAULT_LIBRARY
    lib = join_shelves(load_library(base), load_library(args.join), args.heights, sigma_deg=args.sigma,
                       command=command)
    _write_library(out, lib)
    for a in lib.meta["joined"][-len(args.heights):]:
        s = lib.shelf(a["height_m"])
        print(f"{a['height_m']:g} m: {a['entries']} entries joined from {args.join}, {len(s.up)} in all; "
              f"{int(s.lands.any(axis=1).sum())} of {len(s.probe_up)} probes landed by some motion"
              + (f"; vote σ {a['sigma_deg']:g}°" if "sigma_deg" in a else ""))
    print(f"library: {out} (from {base})")
    return 0


def _recheck_library(args, out: Path, command: str) -> int:
    """``felis train landing-library --recheck [--heights H…] [--base LIBRARY]``: `recheck_entries`."""
    from felis.learning.landing.library import DEFAULT_LIBRARY, load_library
    from felis.learning.landing.library_build import recheck_entries

    base = args.base or DEFAULT_LIBRARY
    lib = recheck_entries(load_library(base), args.heights, workers=args.workers, command=command, design=args.design)
    _write_library(out, lib)
    for a in lib.meta["rechecked"][-len(args.heights):]:
        print(f"{a['height_m']:g} m: {a['landed']} of {a['entries']} entries land their own attitude "
              f"({a['was_landed']} flagged before; {a['changed']} flags changed)")
    print(f"library: {out} (from {base})")
    return 0


def _base_and_workdir(args, out: Path):
    """(the --base path, that library read, the checkpoint folder: --workdir or <out>.ckpt, which --resume needs)."""
    from felis.learning.landing.library import DEFAULT_LIBRARY, load_library

    base = args.base or DEFAULT_LIBRARY
    lib = load_library(base)
    workdir = args.workdir or out.with_suffix(".ckpt")
    check_checkpoints(workdir, args.resume, args.restart, has_checkpoints(workdir))
    return base, lib, workdir


def _add_probes_to_library(args, out: Path, command: str) -> int:
    """``felis train landing-library --add-probes N [--heights H…] [--base LIBRARY]``: `add_probes`."""

    from felis.learning.landing.library_build import add_probes

    base, lib, workdir = _base_and_workdir(args, out)
    bar, progress = _stage_bar()
    with bar:
        lib = add_probes(lib, args.heights, args.add_probes, radius_deg=args.probe_radius,
                         max_tilt_deg=args.max_tilt, sigma_deg=args.sigma, workers=args.workers, command=command,
                         workdir=workdir, resume=args.resume, near_misses=args.near_misses, design=args.design,
                         progress=progress)
    _write_library(out, lib)
    for a in lib.meta["probes_added"][-len(args.heights):]:
        print(f"{a['height_m']:g} m: {a['probes']} probes added ({a['points']}-point sphere, motions within "
              f"{a['radius_deg']:g}°"
              + (f"; only near the {a['near_misses']} probes where the vote missed" if "near_misses" in a else "")
              + f"), {a['landed_by_some']} of them landed by some motion"
              + (f"; vote σ {a['sigma_deg']:g}°" if "sigma_deg" in a else ""))
    print(f"library: {out} (from {base})")
    return 0


def _extend_library(args, out: Path, command: str) -> int:
    """``felis train landing-library --extend DEG [--heights H…] [--base LIBRARY]``: `extend_shelves`."""
    from felis.learning.landing.library_build import extend_shelves

    base, lib, workdir = _base_and_workdir(args, out)
    bar, progress = _stage_bar()
    with bar:
        lib = extend_shelves(lib, args.heights, args.extend, probes=args.probes, radius_deg=args.probe_radius,
                             fill_generations=args.fill_generations, fill_rounds=args.fill_rounds, seed=args.seed,
                             workers=args.workers, command=command, workdir=workdir, resume=args.resume,
                             design=args.design, progress=progress)
    _write_library(out, lib)
    for a in lib.meta["extended"][-len(args.heights):]:
        s = lib.shelf(a["height_m"])
        fills = ", ".join(f"round {k}: {r['entries']} entries of {r['targets']} targets"
                          for k, r in enumerate(a["fill"]["rounds"], 1))
        print(f"{a['height_m']:g} m: {a['probes']} probes added from {a['from_deg']:.0f}° to {a['max_tilt_deg']:g}°, "
              f"{a['landed_by_some_before']} landed by some motion before the fill, {a['landed_by_some']} after"
              + (f" ({fills})" if fills else "") + f"; {len(s.up)} entries in all")
    print(f"library: {out} (from {base})")
    return 0


def _fill_library(args, out: Path, command: str) -> int:
    """``felis train landing-library --fill [DEG] [--heights H…] [--base LIBRARY]``: `fill_shelves`."""
    from felis.learning.landing.library_build import fill_shelves

    base, lib, workdir = _base_and_workdir(args, out)
    bar, progress = _stage_bar()
    with bar:
        lib = fill_shelves(lib, args.heights, max_tilt_deg=args.fill, radius_deg=args.probe_radius,
                           fill_generations=args.fill_generations, fill_rounds=args.fill_rounds, seed=args.seed,
                           workers=args.workers, command=command, workdir=workdir, resume=args.resume,
                           design=args.design, progress=progress)
    _write_library(out, lib)
    for a in lib.meta["filled"][-len(args.heights):]:
        s = lib.shelf(a["height_m"])
        fills = ", ".join(f"round {k}: {r['entries']} entries of {r['targets']} targets, {r['land_their_probe']} "
                          "land their probe" for k, r in enumerate(a["fill"]["rounds"], 1))
        print(f"{a['height_m']:g} m: of {a['probes']} probes tilted at most {a['max_tilt_deg']:g}°, "
              f"{a['landed_by_some_before']} landed by some motion before the fill, {a['landed_by_some']} after "
              f"({fills}; on {a['design']}); {len(s.up)} entries in all")
    print(f"library: {out} (from {base})")
    return 0


def cmd_eval_landing(args) -> int:
    from felis.cli.live import check_one, live_drop
    from felis.learning.landing.evaluate import by_tilt, check_policy, default_policy, run_drops, summarise
    from felis.scenarios.drop import drops_from

    drops = drops_from(args.drops, args.seed, args.height)
    if args.policy is None:  # another design: the library (with that cat's own vote, if any); caps are the cat's
        args.policy = default_policy() if args.design == "cat" else "library"
    if args.policy == "library" and design_library(args.design) is not None:
        args.policy = str(design_library(args.design))  # that cat's own vote of the library's motions
    if args.design != "cat" and args.live is not None:
        raise ParameterError("--live runs the described cat; --design is for batched evaluations")
    if args.timestep is not None:
        from felis.learning.landing.evaluate import check_timestep_ms

        check_timestep_ms(args.timestep)
        if args.live is not None:
            raise ParameterError("--live runs the model's physics step; --timestep is for batched evaluations")
    if args.policy == "optimum":
        if args.live is not None:
            raise ParameterError("--live needs a policy that runs in the loop; optimum searches many rollouts")
        return _eval_optimum(args, drops)
    if args.warm_start is not None:
        raise ParameterError("--warm-start starts the optimum's search (--policy optimum)")
    check_policy(args.policy)
    if args.workers is not None and args.workers < 1:
        raise ParameterError(f"--workers must be ≥ 1, got {args.workers}")
    output.check_json_out(args.out)
    quiet = args.json or not sys.stderr.isatty()
    if check_one(args, len(drops), "drops"):
        outcomes = [live_drop(args.live, drops[0], args.policy)]
    else:
        bar, step = output.progress(len(drops), "drops", quiet)
        with bar:
            outcomes = run_drops(drops, args.policy, workers=args.workers, progress=step, design=args.design,
                                 timestep=None if args.timestep is None else args.timestep / 1000.0)
    summary = summarise(outcomes)
    res = {"success_rate": summary["success_rate"], "policy": args.policy, **summary,
           "by_tilt": by_tilt(drops, [o.landed for o in outcomes]),
           "drops_source": args.drops, "seed": args.seed if ":" in args.drops else None, "design": args.design,
           **_step(args)}
    res["drops"] = res.pop("drops")  # the per-drop list last, after the headline and the counts
    return output.emit(args, res, _print_summary)


def _eval_optimum(args, drops) -> int:
    from felis.learning.landing.evaluate import by_tilt
    from felis.learning.landing.optimum import CHECKPOINT, optimise_all

    if args.workers is not None and args.workers < 1:
        raise ParameterError(f"--workers must be ≥ 1, got {args.workers}")
    if args.resume and not args.checkpoint:
        raise ParameterError("--resume needs --checkpoint DIR (where the finished drops were written)")
    if args.late_ticks < 0:
        raise ParameterError(f"--late-ticks must be ≥ 0 (ticks a motion may start late), got {args.late_ticks}")
    if not (math.isfinite(args.patch) and args.patch >= 0):
        raise ParameterError(f"--patch must be ≥ 0 degrees, got {args.patch}")
    output.check_json_out(args.out)
    if args.motions is not None and args.motions.exists() and not args.motions.is_dir():
        raise ParameterError(f"--motions {args.motions}: not a directory")
    warm = args.warm_start
    if warm == "library":
        from felis.learning.landing.library import DEFAULT_LIBRARY

        warm = str(design_library(args.design) or DEFAULT_LIBRARY)  # the library as that cat votes it
    if args.checkpoint is not None:  # after the inputs' own faults (a bad --warm-start file is its own line)
        if warm is not None:
            from felis.learning.landing.library import load_library

            load_library(warm)  # kept: the search reads it again for free
        check_checkpoints(args.checkpoint, args.resume, args.restart, has_checkpoints(args.checkpoint, CHECKPOINT))
    quiet = args.json or not sys.stderr.isatty()
    bar, step = output.progress(len(drops), "drops", quiet)
    with bar:
        best = optimise_all(drops, generations=args.generations, population=args.population, restarts=args.restarts,
                            seed=args.seed, workers=args.workers, ray_address=args.ray_address,
                            workdir=str(args.checkpoint) if args.checkpoint else None, resume=args.resume,
                            progress=step, design=args.design, late_ticks=args.late_ticks, patch_deg=args.patch,
                            warm=warm, timestep_ms=args.timestep)
    if args.motions is not None:
        _write_motions(args.motions, best)
    landed = [o.landed for o in best]
    reasons: dict[str, int] = {}
    for o in best:
        for k in o.reasons:
            reasons[k] = reasons.get(k, 0) + 1
    res = {"success_rate": round(sum(landed) / len(best), 4) if best else None, "policy": "optimum",
           "landed": sum(landed), "total": len(best),
           "reasons": dict(sorted(reasons.items(), key=lambda kv: (-kv[1], kv[0]))),
           "standing_waist_m": None, "by_tilt": by_tilt(drops, landed),
           "search": {"generations": args.generations, "population": args.population, "restarts": args.restarts,
                      "late_ticks": args.late_ticks, "patch_deg": args.patch,
                      "warm_start": args.warm_start,  # "library": the shipped one
                      "rollouts": int(sum(o.rollouts for o in best))},
           "drops_source": args.drops, "seed": args.seed if ":" in args.drops else None, "design": args.design,
           **_step(args), "drops": [o.as_dict() for o in best]}
    return output.emit(args, res, _print_summary)


def _step(args) -> dict:
    """The result's ``timestep_ms`` when ``--timestep`` set one (results at the model's step carry none, as before)."""
    return {} if args.timestep is None else {"timestep_ms": args.timestep}


def _write_motions(folder: Path, best) -> None:
    """Each drop's best motion as a motion file (`felis.learning.landing.motion`), with the command that made it."""
    import json
    import shlex

    from felis.files import write_atomic
    from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ
    from felis.learning.landing.motion import motion_doc

    folder.mkdir(parents=True, exist_ok=True)
    command = "felis " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    width = len(str(len(best) - 1))
    for i, o in enumerate(best):
        steps = int(round((o.drop.fall_time + MARGIN_S) * RATE_HZ))
        doc = motion_doc(o.x, o.drop.as_dict(), o.landed, command, steps)
        write_atomic(folder / f"drop-{i:0{width}d}.json", json.dumps(doc, indent=1) + "\n", "motion file")


def _print_summary(r: dict) -> None:
    heights = sorted({d["height_m"] for d in r["drops"]})
    hs = f"{heights[0]:g} m" if len(heights) == 1 else f"{heights[0]:g}…{heights[-1]:g} m"
    rate = "n/a" if r["success_rate"] is None else f"{r['success_rate']:.3f}"
    src = r["drops_source"] + (f", seed {r['seed']}" if r["seed"] is not None else "")
    waist = f"; standing waist {r['standing_waist_m']:.3f} m" if r.get("standing_waist_m") else ""
    on = "" if r.get("design", "cat") == "cat" else f" on {r['design']}"
    step = f", physics step {r['timestep_ms']:g} ms" if r.get("timestep_ms") is not None else ""
    print(f"{r['total']} drops from {hs} ({src}){on}{step}, policy {r['policy']}: {r['landed']} landed "
          f"(success rate {rate}){waist}")
    if r.get("by_tilt"):
        print("  by start tilt: " + ", ".join(f"{k}: {v['landed']}/{v['total']}" for k, v in r["by_tilt"].items()))
    if r["reasons"]:
        print("  why not (a drop may have several reasons): "
              + "; ".join(f"{k}: {v}" for k, v in r["reasons"].items()))
