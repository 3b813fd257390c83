"""``felis eval balance`` and ``felis train balance``: the XCoM balance monitor, protective reactions and
the strategy selector (seed 004) under simulated pushes.

``felis eval balance --pushes FILE|random:N`` pushes the simulated cat (standing or trotting in place)
once per episode and prints recall, false-alarm rate, median lead time and fall rate, with one entry per
push; ``--reaction none|fixed:NAME|selector`` chooses what the cat does when the monitor warns.
``--backend dxl --port virtual`` runs each push through the whole hardware path (virtual Dynamixel bus
backed by MuJoCo, wall clock; with ``--lockstep`` the simulation steps with the host's ticks, so a loaded machine
costs no simulated time). With one push, ``--live [HOST:]PORT`` serves it to Foxglove while it runs, with the
monitor's ``/balance`` channel (`felis.cli.live`). ``felis train balance`` makes the demonstrations (every push
that calls for a reaction, tried with every strategy), fits the denoised kNN selector and an SVM beside it, and
writes the selector (.npz), its demonstrations and a results JSON (`felis.learning.balance.train`).
"""

from __future__ import annotations

import sys
from pathlib import Path

from felis.cli import output
from felis.cli.args import live_option
from felis.errors import ParameterError

DEFAULT_TRAIN_OUT = Path("runs/train-balance/balance_selector.npz")


def register_eval(eval_sub) -> None:
    """Add ``felis eval balance``."""
    e = eval_sub.add_parser("balance", help="push the cat: the balance monitor's recall, false alarms and lead "
                            "time, and the fall rate with a protective reaction")
    e.add_argument("--pushes", required=True, metavar="FILE|random:N",
                   help="a JSON list of pushes {body, direction_deg, impulse_ns, t_s, phase}, or random:N")
    e.add_argument("--seed", type=int, default=0, help="seed of random:N (default 0)")
    e.add_argument("--reaction", default="none", metavar="none|fixed:NAME|selector",
                   help="what the cat does on a warning: none, fixed:brace|crouch|step, or selector "
                   "(the shipped strategy selector; default none)")
    e.add_argument("--selector", type=Path, metavar="FILE", help="a selector file for --reaction selector "
                   "(default: the shipped one)")
    e.add_argument("--backend", choices=["sim", "dxl"], default="sim",
                   help="sim: MuJoCo directly (default); dxl: through the virtual Dynamixel bus (needs --port virtual)")
    e.add_argument("--port", help="dxl: 'virtual' (the pushes act on the bus's simulated cat)")
    e.add_argument("--lockstep", action="store_true",
                   help="dxl: the simulated cat steps with the host loop's ticks instead of the wall clock (the "
                   "loop's clock is the simulation's; a slow host costs no simulated time)")
    e.add_argument("--workers", type=int, help="processes for the sim backend (default: every core)")
    e.add_argument("--out", type=Path, metavar="FILE.json", help="also write the JSON result to this file")
    e.add_argument("--json", action="store_true", help="print the result as JSON")
    live_option(e, "one push only: serve it live to Foxglove over WebSocket, on the wall clock")
    e.set_defaults(func=cmd_eval_balance)


def register_train(train_sub) -> None:
    """Add ``felis train balance``."""
    t = train_sub.add_parser("balance", help="make push demonstrations and fit the reactive-strategy selector "
                             "(denoised kNN; SVM beside it)")
    t.add_argument("--pushes", default="random:1200", metavar="FILE|random:N",
                   help="pushes to demonstrate (default random:1200)")
    t.add_argument("--seed", type=int, default=1, help="seed of random:N and of the held-out split (default 1)")
    t.add_argument("--holdout", type=float, default=0.3, help="fraction of demonstrations held out (default 0.3)")
    t.add_argument("--k", type=int, default=7, help="kNN neighbours (default 7)")
    t.add_argument("--demos", type=Path, metavar="FILE.npz", help="reuse demonstrations written by an earlier run "
                   "instead of simulating them")
    t.add_argument("--out", type=Path, default=DEFAULT_TRAIN_OUT, help=f"selector file (default {DEFAULT_TRAIN_OUT})")
    t.add_argument("--workers", type=int, help="processes (default: every core)")
    t.add_argument("--json", action="store_true", help="print the results as JSON")
    t.set_defaults(func=cmd_train_balance)


def _reaction(text: str) -> str:
    from felis.controllers.reactions import REACTIONS

    if text in ("none", "selector"):
        return text
    if text.startswith("fixed:") and text[6:] in REACTIONS:
        return text[6:]
    raise ParameterError(f"--reaction {text!r}: use none, fixed:NAME (NAME one of {', '.join(REACTIONS[1:])}) "
                         "or selector")


def cmd_eval_balance(args) -> int:
    from felis.cli.live import check_one, live_push
    from felis.drivers import ports
    from felis.learning.balance.evaluate import run_push_virtual, run_pushes, summarise
    from felis.scenarios.push import pushes_from

    pushes = pushes_from(args.pushes, args.seed)
    reaction = _reaction(args.reaction)
    if args.selector is not None and reaction != "selector":
        raise ParameterError("--selector needs --reaction selector")
    if args.workers is not None and args.workers < 1:
        raise ParameterError(f"--workers must be ≥ 1, got {args.workers}")
    output.check_json_out(args.out)
    quiet = args.json or not sys.stderr.isatty()
    if args.backend == "dxl" and not ports.is_virtual(args.port):
        raise ParameterError("eval balance --backend dxl needs --port virtual: the pushes and the ground truth "
                             "act on the virtual bus's simulated cat")
    if args.lockstep and (args.backend != "dxl" or args.live is not None):
        raise ParameterError("--lockstep steps the virtual bus's simulation with the host: it needs --backend dxl "
                             "--port virtual, without --live")
    if check_one(args, len(pushes), "pushes"):
        outcomes = [live_push(args.live, pushes[0], reaction, args.selector, args.backend)]
    elif args.backend == "dxl":
        react = reaction
        if reaction == "selector":
            from felis.controllers.reactions import FEATURES
            from felis.learning.balance.selector import load_selector

            react = load_selector(args.selector, feature_names=FEATURES)
        clock = "lockstep" if args.lockstep else "wall clock"
        bar, step = output.progress(len(pushes), f"pushes (virtual bus, {clock})", quiet)
        with bar:
            outcomes = []
            for p in pushes:
                o = run_push_virtual(p, react, lockstep=args.lockstep)
                o.reaction = reaction
                outcomes.append(o)
                step(1)
    else:
        bar, step = output.progress(len(pushes), "pushes", quiet)
        with bar:
            outcomes = run_pushes(pushes, reaction, selector=None if args.selector is None else str(args.selector),
                                  workers=args.workers, progress=step)
    res = {**summarise(outcomes), "reaction": args.reaction, "backend": args.backend, "lockstep": args.lockstep,
           "pushes_source": args.pushes, "seed": args.seed, "pushes": [o.as_dict() for o in outcomes]}
    res = {k: res[k] for k in ("recall", "false_alarm_rate", "median_lead_s", "fall_rate", *res)}  # headline first
    return output.emit(args, res, _print_summary)


def _print_summary(r: dict) -> None:
    fmt = lambda v, spec: "n/a" if v is None else format(v, spec)  # noqa: E731
    print(f"{len(r['pushes'])} pushes ({r['backend']}), reaction {r['reaction']}: {r['falls']} fell")
    print(f"  recall {fmt(r['recall'], '.3f')} · false alarms {fmt(r['false_alarm_rate'], '.3f')} of the pushes "
          f"that did not fall · median lead {fmt(r['median_lead_s'], '.3f')} s · "
          f"fall rate {fmt(r['fall_rate'], '.3f')}")
    strategies: dict[str, int] = {}
    for p in r["pushes"]:
        if p["strategy"]:
            strategies[p["strategy"]] = strategies.get(p["strategy"], 0) + 1
    if strategies:
        print("  reactions: " + ", ".join(f"{k} {v}" for k, v in sorted(strategies.items())))


def cmd_train_balance(args) -> int:
    import time

    from felis.controllers.reactions import REACTIONS
    from felis.learning.balance.evaluate import demonstrate  # late: MuJoCo rollouts
    from felis.learning.balance.train import TOL, check_outputs, fit_selector, read_demos
    from felis.scenarios.push import pushes_from

    out = Path(args.out)
    check_outputs(out, args.holdout)
    t0 = time.perf_counter()
    if args.demos is not None:
        X, S, source = read_demos(args.demos)
    else:
        pushes = pushes_from(args.pushes, args.seed)
        quiet = args.json or not sys.stderr.isatty()
        bar, step = output.progress(len(pushes) * len(REACTIONS), "demonstration runs (at most)", quiet,
                                    lines=quiet and not args.json)
        with bar:
            X, S, used = demonstrate(pushes, workers=args.workers, progress=step)
        source = args.pushes
    res = fit_selector(X, S, source, out, seed=args.seed, holdout=args.holdout, k=args.k, demos=args.demos, t0=t0)
    if args.json:
        output.print_json(res)
        return 0
    rec, acc, falls = res["held_out_recovery_accuracy"], res["held_out_accuracy"], res["held_out_fall_fraction"]
    print(f"{res['demonstrations']} demonstrations (best strategy: "
          + ", ".join(f"{k} {v}" for k, v in res["best_strategy_counts"].items())
          + f"); {res['kept_after_denoise']} of {res['train']} training cases kept by eq. 5")
    print(f"  held out ({res['held_out']}): picks a strategy that recovers whenever one does: kNN {rec['knn']:.3f}, "
          f"SVM {rec['svm']:.3f}, always brace {rec['always_brace']:.3f}")
    print(f"  picks within {TOL} of the best outcome: kNN {acc['knn']:.3f}, SVM {acc['svm']:.3f}; "
          f"falls: kNN {falls['knn']:.3f}, SVM {falls['svm']:.3f}, best possible {falls['best_possible']:.3f}")
    print(f"selector: {out}; results: {out.with_suffix('.results.json')}")
    return 0
