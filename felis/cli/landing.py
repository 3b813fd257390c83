"""``felis eval landing``: drop the simulated cat from many orientations and heights and count landings.

``felis eval landing --drops FILE|random:N [--policy passive|stand|FILE]`` releases the cat once per drop
and judges each landing by the issue's rule (`felis.sim.drops`): only the feet touch the ground from
touchdown to 0.5 s after it, and then the upper body is within 30° of vertical and the waist above half
its standing height. It prints the success rate and the reasons for the failures, or with ``--json`` the
result with one entry per drop (``--out`` also writes it to a file).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from felis.errors import ParameterError

DEFAULT_POLICY = "passive"  # becomes the shipped trained policy once `felis train landing` exists


def register(train_sub, eval_sub, parser_class) -> None:
    """Add ``eval landing`` (no ``train landing`` yet)."""
    e = eval_sub.add_parser("landing", help="drop the cat from many orientations and heights: the landing "
                            "success rate of a policy")
    e.add_argument("--drops", required=True, metavar="FILE|random:N",
                   help="a JSON list of drops {roll_deg, pitch_deg, yaw_deg, height_m}, or random:N (roll, pitch "
                   "and yaw uniform over the full circle)")
    e.add_argument("--policy", default=DEFAULT_POLICY, metavar="passive|stand|FILE",
                   help="what the cat does while it falls and lands: passive (hold the pose at release), stand "
                   "(go to the stand pose) or a trained policy file; default passive for now: the shipped trained "
                   "policy becomes the default once `felis train landing` exists")
    e.add_argument("--seed", type=int, default=0, help="seed of random:N (default 0)")
    e.add_argument("--height", type=float, metavar="M", help="drop height for random:N (m, default 1.0)")
    e.add_argument("--workers", type=int, help="processes (default: every core)")
    e.add_argument("--out", type=Path, metavar="FILE.json", help="also write the JSON result to this file")
    e.add_argument("--json", action="store_true", help="print the result as JSON")
    e.set_defaults(func=cmd_eval_landing)


def cmd_eval_landing(args) -> int:
    from felis.cli.balance import _progress
    from felis.learning.landing_eval import check_policy, run_drops, summarise
    from felis.sim.drops import drops_from

    drops = drops_from(args.drops, args.seed, args.height)
    check_policy(args.policy)
    if args.workers is not None and args.workers < 1:
        raise ParameterError(f"--workers must be ≥ 1, got {args.workers}")
    if args.out is not None:
        from felis.files import check_target

        if args.out.suffix.lower() != ".json":
            raise ParameterError(f"{args.out}: the result file must end in .json")
        check_target(args.out, "result", ParameterError)
    quiet = args.json or not sys.stderr.isatty()
    bar, step = _progress(len(drops), "drops", quiet)
    with bar:
        outcomes = run_drops(drops, args.policy, workers=args.workers, progress=step)
    summary = summarise(outcomes)
    res = {"success_rate": summary["success_rate"], "policy": args.policy, **summary,
           "drops_source": args.drops, "seed": args.seed if args.drops.startswith("random:") else None}
    res["drops"] = res.pop("drops")  # the per-drop list last, after the headline and the counts
    if args.out is not None:
        from felis.files import write_atomic

        write_atomic(args.out, json.dumps(res, indent=1) + "\n", "result", ParameterError)
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    _print_summary(res)
    return 0


def _print_summary(r: dict) -> None:
    heights = sorted({d["height_m"] for d in r["drops"]})
    hs = f"{heights[0]:g} m" if len(heights) == 1 else f"{heights[0]:g}…{heights[-1]:g} m"
    rate = "n/a" if r["success_rate"] is None else f"{r['success_rate']:.3f}"
    src = r["drops_source"] + (f", seed {r['seed']}" if r["seed"] is not None else "")
    print(f"{r['total']} drops from {hs} ({src}), policy {r['policy']}: {r['landed']} landed "
          f"(success rate {rate}); standing waist {r['standing_waist_m']:.3f} m")
    if r["reasons"]:
        print("  why not (a drop may have several reasons): "
              + "; ".join(f"{k}: {v}" for k, v in r["reasons"].items()))
