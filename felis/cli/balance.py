"""``felis eval balance`` and ``felis train balance``: the XCoM balance monitor, protective reactions and
the strategy selector (seed 004) under simulated pushes.

``felis eval balance --pushes FILE|random:N`` pushes the simulated cat (standing or trotting in place)
once per episode and prints recall, false-alarm rate, median lead time and fall rate, with one entry per
push; ``--reaction none|fixed:NAME|selector`` chooses what the cat does when the monitor warns.
``--backend dxl --port virtual`` runs each push through the whole hardware path (virtual Dynamixel bus
backed by MuJoCo, wall clock). ``felis train balance`` makes the demonstrations (every push that calls
for a reaction, tried with every strategy), fits the denoised kNN selector and an SVM beside it, and
writes the selector (.npz), its demonstrations and a results JSON.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from felis.cli.output import check_json_out, emit
from felis.cli.output import progress as _progress
from felis.errors import ParameterError

DEFAULT_TRAIN_OUT = Path("runs/train-balance/balance_selector.npz")
TOL = 0.05  # selector accuracy: a strategy whose score is within this of the best counts as the best


def register(train_sub, eval_sub, parser_class) -> None:
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
    e.add_argument("--workers", type=int, help="processes for the sim backend (default: every core)")
    e.add_argument("--out", type=Path, metavar="FILE.json", help="also write the JSON result to this file")
    e.add_argument("--json", action="store_true", help="print the result as JSON")
    e.set_defaults(func=cmd_eval_balance)

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
    from felis.learning.balance.evaluate import run_push_virtual, run_pushes, summarise
    from felis.sim.pushes import pushes_from

    pushes = pushes_from(args.pushes, args.seed)
    reaction = _reaction(args.reaction)
    if args.selector is not None and reaction != "selector":
        raise ParameterError("--selector needs --reaction selector")
    if args.workers is not None and args.workers < 1:
        raise ParameterError(f"--workers must be ≥ 1, got {args.workers}")
    check_json_out(args.out)
    quiet = args.json or not sys.stderr.isatty()
    if args.backend == "dxl":
        if args.port != "virtual":
            raise ParameterError("eval balance --backend dxl needs --port virtual: the pushes and the ground truth "
                                 "act on the virtual bus's simulated cat")
        react = reaction
        if reaction == "selector":
            from felis.controllers.reactions import FEATURES
            from felis.learning.balance.selector import load_selector

            react = load_selector(args.selector, feature_names=FEATURES)
        bar, step = _progress(len(pushes), "pushes (virtual bus, wall clock)", quiet)
        with bar:
            outcomes = []
            for p in pushes:
                o = run_push_virtual(p, react)
                o.reaction = reaction
                outcomes.append(o)
                step(1)
    else:
        bar, step = _progress(len(pushes), "pushes", quiet)
        with bar:
            outcomes = run_pushes(pushes, reaction, selector=None if args.selector is None else str(args.selector),
                                  workers=args.workers, progress=step)
    res = {**summarise(outcomes), "reaction": args.reaction, "backend": args.backend,
           "pushes_source": args.pushes, "seed": args.seed, "pushes": [o.as_dict() for o in outcomes]}
    res = {k: res[k] for k in ("recall", "false_alarm_rate", "median_lead_s", "fall_rate", *res)}  # headline first
    return emit(args, res, _print_summary)


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

    import numpy as np

    from felis.controllers.reactions import FEATURES, REACTIONS
    from felis.files import check_target, prepare_parent, write_atomic
    from felis.learning.balance.evaluate import demonstrate
    from felis.learning.balance.selector import (
        CaseBase,
        KnnSelector,
        SvmSelector,
        accuracy,
        exact_accuracy,
        recovery_accuracy,
    )
    from felis.sim.pushes import pushes_from

    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise ParameterError(f"{out}: the selector file must end in .npz")
    if not 0.05 <= args.holdout <= 0.9:
        raise ParameterError(f"--holdout must be within 0.05…0.9, got {args.holdout}")
    check_target(out, "selector", ParameterError)
    demos_out = out.with_suffix(".demos.npz")
    t0 = time.perf_counter()
    if args.demos is not None:
        X, S, source = _read_demos(args.demos)
    else:
        pushes = pushes_from(args.pushes, args.seed)
        quiet = args.json or not sys.stderr.isatty()
        bar, step = _progress(len(pushes) * len(REACTIONS), "demonstration runs (at most)", quiet,
                              lines=quiet and not args.json)
        with bar:
            X, S, used = demonstrate(pushes, workers=args.workers, progress=step)
        source = args.pushes
    cases = CaseBase(X, S, FEATURES, REACTIONS)
    if len(cases) < 20:
        raise ParameterError(f"only {len(cases)} pushes called for a reaction: too few demonstrations "
                             "(use more pushes)")
    train, held = cases.split(1.0 - args.holdout, args.seed)
    knn = KnnSelector(k=args.k, power=2.0, interpolate="scores").fit(train)
    variants = {"knn": knn,
                "knn_no_denoise": KnnSelector(k=args.k, power=2.0, interpolate="scores", denoise=False).fit(train),
                "knn_labels": KnnSelector(k=args.k).fit(train), "svm": SvmSelector().fit(train)}
    labels = cases.labels()
    common = int(np.bincount(train.labels(), minlength=len(REACTIONS)).argmax())
    fixed = {f"always_{name}": i for i, name in enumerate(REACTIONS)}

    def fixed_rates(metric):
        return {k: round(metric(i), 4) for k, i in fixed.items()}

    res = {
        "demonstrations": len(cases), "train": len(train), "held_out": len(held), "pushes": source,
        "seed": args.seed, "tolerance": TOL, "features": list(FEATURES), "strategies": list(REACTIONS),
        "best_strategy_counts": {name: int((labels == i).sum()) for i, name in enumerate(REACTIONS)},
        "most_common_best": REACTIONS[common],
        "kept_after_denoise": int(knn.kept.sum()),
        "held_out_recovery_accuracy": {
            **{k: round(recovery_accuracy(v, held), 4) for k, v in variants.items()},
            **fixed_rates(lambda i: float(np.mean((held.scores[:, i] < 1) | (held.scores.min(axis=1) >= 1))))},
        "held_out_accuracy": {
            **{k: round(accuracy(v, held, TOL), 4) for k, v in variants.items()},
            **fixed_rates(lambda i: float(held.acceptable(TOL)[:, i].mean()))},
        "held_out_accuracy_tol_0.1": {k: round(accuracy(v, held, 0.1), 4) for k, v in variants.items()},
        "held_out_exact_accuracy": {k: round(exact_accuracy(v, held), 4) for k, v in variants.items()},
        "held_out_fall_fraction": {
            **{k: round(float(np.mean(held.scores[np.arange(len(held)), v.predict_index(held.features)] >= 1)), 4)
               for k, v in variants.items()},
            "best_possible": round(float(np.mean(held.scores.min(axis=1) >= 1)), 4),
            **fixed_rates(lambda i: float(np.mean(held.scores[:, i] >= 1)))},
        "selector": str(out), "time_s": round(time.perf_counter() - t0, 1),
    }
    prepare_parent(out, "selector", ParameterError)
    knn.save(out)
    if args.demos is None:
        write_atomic(demos_out, _demos_bytes(X, S, source), "demonstrations", ParameterError)
    res["demonstrations_file"] = str(demos_out if args.demos is None else args.demos)
    write_atomic(out.with_suffix(".results.json"), json.dumps(res, indent=1) + "\n", "results", ParameterError)
    if args.json:
        print(json.dumps(res, indent=1))
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


def _demos_bytes(X, S, source: str) -> bytes:
    import io

    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, features=X, scores=S, source=np.array(source))
    return buf.getvalue()


def _read_demos(path: Path):
    import numpy as np

    from felis.controllers.reactions import FEATURES, REACTIONS
    from felis.files import MAX_ARRAY_BYTES, check_readable

    check_readable(path, "demonstrations file", ParameterError, MAX_ARRAY_BYTES)
    try:
        with np.load(path, allow_pickle=False) as z:
            X, S, source = z["features"], z["scores"], str(z["source"])
    except FileNotFoundError:
        raise ParameterError(f"{path}: no such demonstrations file") from None
    except (OSError, ValueError, KeyError) as e:
        raise ParameterError(f"{path}: not a demonstrations file ({type(e).__name__}: {e})") from None
    if X.ndim != 2 or X.shape[1] != len(FEATURES) or S.shape != (len(X), len(REACTIONS)):
        raise ParameterError(f"{path}: demonstrations have shape {X.shape}/{S.shape}, expected (n, {len(FEATURES)})"
                             f"/(n, {len(REACTIONS)})")
    return X, S, source


DEMO_PUSH = {"body": "upper_body", "direction_deg": 90.0, "impulse_ns": 0.6, "t_s": 0.8, "phase": "stand"}


def push_demo(run_dir: Path, video: bool = True) -> dict:
    """``felis demo`` part 4: the standing cat pushed sideways, once without a reaction and once with the
    shipped strategy selector; the margin of stability with the warning and the alarm, to PNG; the
    selector's run to MP4."""
    from felis.learning.balance.evaluate import PushSim
    from felis.sim.pushes import check_push

    p = check_push(DEMO_PUSH, "demo push")
    sim = PushSim()
    runs = {}
    try:
        runs["none"] = sim.run(p, "none", trace=True)
        recorder = []
        if video:
            from felis.sim.render import VideoRecorder

            recorder = [VideoRecorder(sim.robot, run_dir / "push.mp4", fps=30.0, width=640, height=480)]
        from felis.controllers.reactions import FEATURES
        from felis.learning.balance.selector import load_selector

        try:
            runs["selector"] = sim.run(p, load_selector(feature_names=FEATURES), trace=True, monitors=recorder)
        except BaseException:
            for r in recorder:
                r.abort()
            raise
        files = {"plot": str(plot_margins(runs, p, run_dir / "push_margin.png", sim.monitor_defaults()))}
        for r in recorder:
            files["video"] = str(r.close())
    finally:
        sim.close()
    summary = {"push": p.as_dict(), "files": files,
               "runs": {k: {kk: v for kk, v in o.as_dict().items() if kk in ("fell", "why", "alarm_t_s", "lead_s",
                                                                              "strategy", "max_tilt_deg")}
                        for k, o in runs.items()}}
    (run_dir / "push.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def plot_margins(runs: dict, p, path: Path, monitor: dict) -> Path:
    """Margin of stability over time per run, with the alarm shaded, the push and any fall marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(len(runs), 1, figsize=(8, 2.6 * len(runs)), sharex=True, squeeze=False)
    for ax, (name, o) in zip(axes[:, 0], runs.items(), strict=True):
        tr = o.margins
        t, b, alarm = tr[:, 0], tr[:, 1] * 100, tr[:, 2] > 0
        ax.plot(t, b, color="tab:blue", lw=1.5, label="margin of stability b")
        ax.fill_between(t, np.nanmin(b) - 1, np.nanmax(b) + 1, where=alarm, color="tab:red", alpha=0.15,
                        label="alarm", step="post")
        ax.axhline(0, color="k", lw=0.8)
        ax.axhline(monitor["warn_m"] * 100, color="tab:orange", lw=0.8, ls="--", label="warning level")
        ax.axhline(-monitor["on_m"] * 100, color="tab:red", lw=0.8, ls="--", label="alarm level")
        ax.axvline(p.t_s, color="tab:purple", lw=1, label="push")
        if o.fell:
            ax.axvline(o.fall_t, color="k", lw=1.5, ls=":", label=f"fell ({o.why})")
        verdict = "fell" if o.fell else "stayed up"
        what = "no reaction" if name == "none" else f"selector → {o.strategy}"
        ax.set_title(f"{what}: {verdict}" + (f", alarm {o.lead_s * 1000:.0f} ms before the fall" if o.lead_s else ""),
                     fontsize=10)
        ax.set_ylabel("b (cm)")
        ax.set_ylim(max(np.nanmin(b) - 1, -20), np.nanmax(b) + 1)
        ax.legend(fontsize=7, loc="lower left", ncol=3)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(f"cat pushed: {p.impulse_ns:g} N·s at {p.direction_deg:g}° on the {p.body}", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
