"""``felis train ik`` and ``felis eval ik``: the arm's learned IK (seed 001).

``felis train ik`` builds the demonstration corpus, trains the Motion Predictor and the Posture
Estimator with progress bars and per-epoch checkpoints (``--resume`` continues an interrupted run),
writes the weights (.npz), a results JSON and learning curves. ``felis eval ik`` runs the whole
pipeline on a trajectory file (CSV ``t,x,y,z`` at 100 Hz) or on the held-out test trajectories of
the weights' own corpus (``builtin``) and reports accuracy, limits, smoothness, latency and posture,
beside the closed-form and DLS solvers.
"""

from __future__ import annotations

import sys
from pathlib import Path

from felis.cli import output
from felis.cli.args import check_checkpoints, group, has_checkpoints, restart_option
from felis.errors import ParameterError, TrajectoryError

DEFAULT_OUT = Path("runs/train-ik/ik.npz")


def _defaults():
    from felis.learning.ik.config import IkTrainConfig  # late: its settings only (not torch)

    return IkTrainConfig()


def register(sub) -> None:
    """Add ``felis ik demos``."""
    d = _defaults()
    iksub = group(sub, "ik", "the arm's IK demonstrations: generate, export", "ik_command", "IK_COMMAND")
    dm = iksub.add_parser("demos", help="generate the deterministic demonstration corpus (what `felis train ik` "
                          "trains on) to .npz, and its splits as CSV files for `felis eval ik`")
    dm.add_argument("--out", type=Path, required=True, help="directory to write corpus.npz (and CSVs) into")
    dm.add_argument("--corpus", type=int, default=d.corpus, help=f"trajectories (default {d.corpus})")
    dm.add_argument("--corpus-seed", type=int, default=d.corpus_seed, help=f"seed (default {d.corpus_seed})")
    dm.add_argument("--csv", choices=["none", "test", "all"], default="test",
                    help="also write trajectories as CSV t,x,y,z,q1..q4 (default: the test split)")
    dm.add_argument("--json", action="store_true", help="print a summary as JSON")
    dm.set_defaults(func=cmd_ik_demos)


def register_train(train_sub) -> None:
    """Add ``felis train ik``."""
    d = _defaults()
    t = train_sub.add_parser("ik", help="train the arm's IK nets (Motion Predictor, Posture Estimator) on "
                             "generated demonstrations")
    t.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"weights file (.npz; default {DEFAULT_OUT})")
    t.add_argument("--workdir", type=Path, help="checkpoints (default: <out>.ckpt/ beside the weights)")
    t.add_argument("--resume", action="store_true", help="continue from the checkpoints in --workdir")
    restart_option(t)
    t.add_argument("--corpus", type=int, default=d.corpus, help=f"demonstration trajectories (default {d.corpus})")
    t.add_argument("--corpus-seed", type=int, default=d.corpus_seed, help=f"corpus seed (default {d.corpus_seed})")
    t.add_argument("--seed", type=int, default=d.seed, help=f"training seed (default {d.seed})")
    t.add_argument("--kind", choices=["lstm", "mlp"], default=d.kind, help=f"network type (default {d.kind})")
    t.add_argument("--hidden", type=int, default=d.hidden, help=f"hidden units per layer (default {d.hidden})")
    t.add_argument("--layers", type=int, default=d.layers, help=f"LSTM/MLP layers (default {d.layers})")
    t.add_argument("--pe-frames", type=int, choices=[1, 3, 5], default=d.pe_frames,
                   help="Posture Estimator input frames (default 5, the paper's)")
    t.add_argument("--epochs", type=int, default=d.epochs, help=f"epochs per net (default {d.epochs})")
    t.add_argument("--batch", type=int, default=d.batch, help=f"batch size (default {d.batch})")
    t.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate (default {d.lr})")
    t.add_argument("--stride", type=int, default=d.stride, help=f"training window stride (default {d.stride})")
    t.add_argument("--threads", type=int, default=d.threads, help="torch threads (default: all cores)")
    t.add_argument("--recorded", type=Path, nargs="+", default=[], metavar="LOG",
                   help="run logs of the arm (.mcap) added to the training demonstrations")
    t.add_argument("--mp-from", type=Path, metavar="FILE", help="reuse this weights file's Motion Predictor")
    t.add_argument("--no-eval", action="store_true", help="skip the test-set evaluation")
    t.add_argument("--json", action="store_true", help="print the results as JSON")
    t.set_defaults(func=cmd_train_ik)


def register_eval(eval_sub) -> None:
    """Add ``felis eval ik``."""
    e = eval_sub.add_parser("ik", help="evaluate the IK pipeline on a trajectory: accuracy, limits, jerk, latency")
    e.add_argument("--trajectory", required=True, metavar="FILE.csv|builtin",
                   help="CSV t,x,y,z at 100 Hz (m, the arm's base frame), or builtin: the held-out test "
                   "trajectories of the weights' corpus")
    e.add_argument("--weights", type=Path, metavar="FILE", help="IK weights (default: the shipped ones)")
    e.add_argument("--seed", type=int, default=0, help="seed for the batch-latency windows (default 0)")
    e.add_argument("--no-baselines", action="store_true", help="skip the closed-form and DLS solvers")
    e.add_argument("--json", action="store_true", help="print the results as JSON")
    e.set_defaults(func=cmd_eval_ik)


def cmd_ik_demos(args) -> int:
    from felis.controllers.trajectories import write_trajectory_csv
    from felis.learning.ik.corpus import save_corpus
    from felis.learning.ik.data import make_corpus, split

    if args.corpus < 3:
        raise ParameterError(f"--corpus must be at least 3 trajectories, got {args.corpus}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ParameterError(f"{out} exists and is not a directory")
    corpus = make_corpus(args.corpus, args.corpus_seed)
    parts = dict(zip(("train", "val", "test"), split(corpus, args.corpus_seed), strict=True))
    out.mkdir(parents=True, exist_ok=True)
    files = [str(save_corpus(out / "corpus.npz", corpus))]
    for name, trajs in parts.items():
        if args.csv == "all" or (args.csv == "test" and name == "test"):
            for t in trajs:
                files.append(str(write_trajectory_csv(out / f"{name}_{t.ident:04d}_{t.kind}.csv", t)))
    summary = {"trajectories": len(corpus), "frames": int(sum(len(t.p) for t in corpus)),
               "split": {k: [t.ident for t in v] for k, v in parts.items()}, "files": len(files), "out": str(out)}
    if args.json:
        output.print_json(summary)
    else:
        print(f"{summary['trajectories']} trajectories, {summary['frames']} frames at 100 Hz → {out}/corpus.npz; "
              f"{len(files) - 1} CSV files; split train/val/test {len(parts['train'])}/{len(parts['val'])}/"
              f"{len(parts['test'])} by whole trajectories")
    return 0


def _check_out(path: Path) -> None:
    from felis.files import check_target

    if path.suffix.lower() != ".npz":
        raise ParameterError(f"{path}: IK weights must end in .npz")
    check_target(path, "IK weights", ParameterError)


def cmd_train_ik(args) -> int:
    from felis.learning.ik.run import IkTrainConfig, train_ik

    cfg = IkTrainConfig(corpus=args.corpus, corpus_seed=args.corpus_seed, seed=args.seed, kind=args.kind,
                        hidden=args.hidden, layers=args.layers, pe_frames=args.pe_frames, epochs=args.epochs,
                        batch=args.batch, lr=args.lr, stride=args.stride, threads=args.threads,
                        recorded=tuple(str(p) for p in args.recorded))
    cfg.check()
    _check_out(args.out)
    workdir = args.workdir or args.out.with_suffix(".ckpt")
    check_checkpoints(workdir, args.resume, args.restart, has_checkpoints(workdir))
    quiet = args.json or not sys.stderr.isatty()
    bar = output.bar(quiet=quiet, field="loss", transient=False)
    tasks: dict[str, int] = {}

    def progress(name, epoch, epochs, train_loss, val_loss):
        label = {"mp": "Motion Predictor", "pe": "Posture Estimator"}[name]
        if name not in tasks:
            tasks[name] = bar.add_task(label, total=epochs, loss="")
        bar.update(tasks[name], completed=epoch, loss=f"train {train_loss:.2e} val {val_loss:.2e}")
        if quiet and not args.json:
            print(f"{label}: epoch {epoch}/{epochs} train {train_loss:.3e} val {val_loss:.3e}", flush=True)

    with bar:
        res = train_ik(cfg, args.out, workdir, resume=args.resume, progress=progress, evaluate_test=not args.no_eval,
                       mp_from=args.mp_from)
    if args.json:
        output.print_json(res)
        return 0
    print(f"weights: {res['weights']} ({res['size_bytes'] / 1e6:.2f} MB; params {res['params']}); "
          f"trained in {res['train_s']:.0f} s")
    if "test" in res:
        _print_eval(res["test"])
    stem = Path(res["weights"]).with_suffix("")
    print(f"results: {stem}.results.json; curves: {stem}.curves.png")
    return 0


def cmd_eval_ik(args) -> int:
    from felis.learning.ik.evaluate import evaluate
    from felis.learning.ik.solver import IkSolver

    solver = IkSolver.load(args.weights)
    if args.trajectory == "builtin":
        from felis.learning.ik.data import make_corpus, split

        corpus = solver.meta.get("corpus", {})
        n, seed = int(corpus.get("trajectories", 400)), int(corpus.get("seed", 1))
        trajs = split(make_corpus(n, seed), seed)[2]
    else:
        from felis.controllers.arm_posture import demo_joints
        from felis.controllers.trajectories import read_trajectory_csv

        traj = read_trajectory_csv(args.trajectory)
        try:  # the demonstrator's joints, when the pitch rule can reach every point, for the jerk ratio
            traj.q = demo_joints(traj.p)
        except TrajectoryError:  # some point has no demonstrated pose: no ratio; the rest still runs
            traj.q = None
        trajs = [traj]
    res = evaluate(solver, trajs, seed=args.seed, baselines=not args.no_baselines)
    if args.json:
        output.print_json(res)
    else:
        _print_eval(res)
    return 0


def _fmt(stats: dict) -> str:
    if stats.get("median_mm") is None:
        return "n/a"
    return (f"median {stats['median_mm']:.3g} · p95 {stats['p95_mm']:.3g} · p99 {stats['p99_mm']:.3g} · "
            f"max {stats['max_mm']:.3g} mm")


def _print_eval(r: dict) -> None:
    lat = r["latency_ms"]
    print(f"{r['trajectories']} trajectories, {r['frames']} frames; unreachable {r['unreachable']['count']}")
    print(f"  raw network: {_fmt(r['raw'])}")
    print(f"  filtered:    {_fmt(r['filtered'])}")
    print(f"  refined:     {_fmt(r['refined'])}; limit violations {r['limit_violations']}")
    jr = f"; RMS jerk {r['jerk_ratio']:.2f}× the demonstrations'" if "jerk_ratio" in r else ""
    print(f"  posture: pitch off the demonstrator's by median {r['pitch_dev_deg']['median']:.2f}°{jr}")
    print(f"  latency: single query median {lat['single']['median']:.3f} ms, p99 {lat['single']['p99']:.3f} ms; "
          f"{lat['batch_per_query'] * 1e3:.1f} µs per query in a batch of {lat['batch']}")
    for name, b in r.get("baselines", {}).items():
        jr = f", jerk {b['jerk_ratio']:.2f}×" if "jerk_ratio" in b else ""
        print(f"  {name}: {_fmt(b['refined'])}; pitch off by {b['pitch_dev_deg']['median']:.2f}°{jr}; "
              f"latency median {b['latency_ms']['single']['median']:.3f} ms")
