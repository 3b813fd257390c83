"""``felis phase``: gait data for phase learning (`felis.learning.phase.data`) and a look at what a phase
model reads from a gait (`felis.learning.phase.plot`).

::

    felis phase record --out FILE.npz [--set train|heldout|all] [--rate HZ] [--scale F] [--json]
    felis phase record --from-log RUN.mcap [--from-log RUN2.mcap …] --out FILE.npz [--rate HZ] [--json]

The first form records the default schedules in MuJoCo (deterministic; each recording keeps its set,
train or heldout, so a loader can pick one); ``--scale`` multiplies every segment's duration (e.g.
0.1 for a quick check). The second takes the joint trajectories of run logs, e.g. from
``felis run step-in-place --robot cat --backend dxl --port virtual --log run.mcap``, resampled onto a
uniform grid at the run's rate (or ``--rate``). Prints the recordings, their seconds and rate.
Nothing is written on an error (one line).

::

    felis phase plot SOURCE --out FILE.png [--weights W.npz] [--recording NAME]

draws a phase model's (default: the shipped ``phase.npz``) channels, the gait channel's frequency and
amplitude and the phase manifold over a run log (.mcap) or one recording of a gait-data file (.npz);
prints the written path.

::

    felis train phase [--data GAIT.npz] [--out W.npz] [--epochs N] [--resume] [--json]
    felis eval phase [--weights W.npz] [--data GAIT.npz] [--pushes random:N|FILE|none] [--json] [--out R.json]

train the PAE with FLD on the train recordings (the held-out ones pick the best epoch), calibrate the
phase estimator, and report on the held-out recordings (`felis.learning.phase.run`); evaluate a phase
model: the held-out phase figures, reconstruction and prediction against the baselines, and the balance
monitor's false alarms with its gait gate fed by the clock, by the estimator, and without a gate, on the
same pushes (`felis.learning.phase.evaluate`).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from felis.cli import output
from felis.cli.args import check_checkpoints, group, has_checkpoints, restart_option
from felis.errors import ParameterError


def cmd_phase_record(args) -> int:
    from felis.files import check_target
    from felis.learning.phase import data as gait_data

    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise ParameterError(f"{out}: the gait-data file must end in .npz")
    check_target(out, "gait-data file", ParameterError)
    if args.rate is not None and not 1 <= args.rate <= 1000:
        raise ParameterError(f"--rate must be within 1…1000 Hz, got {args.rate:g}")
    t0 = time.perf_counter()
    if args.from_log:
        if args.set is not None or args.scale is not None:
            raise ParameterError("--set and --scale choose simulated recordings: leave them out with --from-log")
        recs = [gait_data.from_log(p, rate_hz=args.rate) for p in args.from_log]
        set_name = "log"
    else:
        scale = 1.0 if args.scale is None else args.scale
        if not 0 < scale <= 10:
            raise ParameterError(f"--scale must be within 0…10, got {scale:g}")
        set_name = args.set or "all"
        which = ["train", "heldout"] if set_name == "all" else [set_name]
        rate = 100.0 if args.rate is None else args.rate
        recs = [r for w in which for r in gait_data.record_set(w, rate_hz=rate, scale=scale)]
    path = gait_data.save_recordings(out, recs, set_name=set_name)
    wall = time.perf_counter() - t0
    rows = [{"name": r.name, "split": r.split, "source": r.source, "seconds": round(r.duration_s, 3),
             "samples": len(r.t), "rate_hz": r.rate_hz, "contacts": r.contacts is not None} for r in recs]
    total = sum(r.duration_s for r in recs)
    if args.json:
        output.print_json({"out": str(path), "set": set_name, "recordings": rows, "seconds": round(total, 3),
                           "wall_s": round(wall, 2)})
        return 0
    for row in rows:
        print(f"{row['name']} ({row['split']}): {row['seconds']:.1f} s, {row['samples']} samples at "
              f"{row['rate_hz']:g} Hz{'' if row['contacts'] else ', no contacts'}")
    print(f"{len(recs)} recording(s), {total:.1f} s in all, recorded in {wall:.1f} s → {path}")
    return 0


def cmd_phase_plot(args) -> int:
    from felis.learning.phase.plot import plot_phase

    out = plot_phase(args.source, args.out, weights=args.weights, recording=args.recording)
    print(f"plot: {out}")
    return 0


def register(sub) -> None:
    """Add ``felis phase record`` and ``felis phase plot`` to the ``felis`` sub-commands."""
    phasesub = group(sub, "phase", "gait data for phase learning: record, plot", "phase_command", "PHASE_COMMAND")
    rec = phasesub.add_parser("record", help="record joint trajectories of the trotting cat (MuJoCo, the default "
                              "train/heldout schedules) or take them from run logs (--from-log)",
                              description="Record the cat stepping in place at several frequencies and lifts, "
                              "with transitions and standing (MuJoCo, deterministic), or take the joint "
                              "trajectories of run logs; write them to one .npz.")
    rec.add_argument("--out", type=Path, required=True, help="gait-data file to write (.npz)")
    rec.add_argument("--set", choices=["train", "heldout", "all"],
                     help="simulation: which default schedules (default all)")
    rec.add_argument("--from-log", type=Path, action="append", metavar="RUN.mcap",
                     help="take a run log instead of simulating (repeat for several)")
    rec.add_argument("--rate", type=float, help="samples per second (default: 100 in simulation, a log's run rate)")
    rec.add_argument("--scale", type=float, help="simulation: multiply every segment's duration (quick checks; "
                     "default 1)")
    rec.add_argument("--json", action="store_true", help="print the summary as JSON")
    rec.set_defaults(func=cmd_phase_record)
    plot = phasesub.add_parser("plot", help="plot a phase model's channels, gait frequency and amplitude and phase "
                               "manifold over a run log or a gait-data recording (PNG)",
                               description="Run a trained phase model over the joint trajectory of a run log "
                               "(.mcap) or of one recording of a gait-data file (.npz) and draw, per channel, "
                               "the phase as A·sin 2πφ, the gait channel's frequency (with the gait clock's "
                               "when known) and amplitude (with the stepping threshold), and the phase "
                               "manifold coloured by time.")
    plot.add_argument("source", type=Path, help="run log (.mcap) or gait-data file (.npz)")
    plot.add_argument("--out", type=Path, required=True, help="PNG file to write")
    plot.add_argument("--weights", type=Path, help="phase model from `felis train phase` (default: the shipped "
                      "learning/weights/phase.npz)")
    plot.add_argument("--recording", metavar="NAME", help="gait-data file: which recording (default the first)")
    plot.set_defaults(func=cmd_phase_plot)


# ------------------------------------------------------------------------------ train / eval phase
DEFAULT_TRAIN_OUT = Path("runs/train-phase/phase.npz")


def register_train(train_sub) -> None:
    """Add ``felis train phase``."""
    from felis.learning.phase.train import PhaseTrainConfig  # late: the training package (torch), for its defaults

    d = PhaseTrainConfig()
    t = train_sub.add_parser("phase", help="train the periodic autoencoder with FLD (seed 003) on gait recordings; "
                             "checkpoints resume", description="Train the PAE with Fourier latent dynamics on the "
                             "cat's gait recordings, calibrate the phase estimator, evaluate on the held-out "
                             "recordings; writes the weights and <name>.results.json.")
    t.add_argument("--out", type=Path, default=DEFAULT_TRAIN_OUT, help=f"weights (.npz; default {DEFAULT_TRAIN_OUT})")
    t.add_argument("--data", type=Path, metavar="GAIT.npz", help="gait data from `felis phase record --set all` "
                   "(default: record the default schedules now, ≈ 10 s)")
    t.add_argument("--workdir", type=Path, help="checkpoints (default: <out>.ckpt/ beside the weights)")
    t.add_argument("--resume", action="store_true", help="continue from the checkpoint in --workdir")
    restart_option(t)
    t.add_argument("--epochs", type=int, default=d.epochs, help=f"epochs (default {d.epochs})")
    t.add_argument("--window", type=int, default=d.window, help=f"frames per window (default {d.window})")
    t.add_argument("--phases", type=int, default=d.n_phases, help=f"phase channels M (default {d.n_phases})")
    t.add_argument("--hidden", type=int, default=d.hidden, help=f"hidden channels (default {d.hidden})")
    t.add_argument("--fld-steps", type=int, default=d.fld_steps, help=f"FLD steps N (default {d.fld_steps})")
    t.add_argument("--seed", type=int, default=d.seed, help=f"seed (default {d.seed})")
    t.add_argument("--scale", type=float, default=1.0, help="without --data: multiply every recorded segment's "
                   "duration (quick checks; default 1)")
    t.add_argument("--json", action="store_true", help="print the results as JSON")
    t.set_defaults(func=cmd_train_phase)


def register_eval(eval_sub) -> None:
    """Add ``felis eval phase``."""
    e = eval_sub.add_parser("phase", help="the phase estimator on held-out gait recordings, and the balance "
                            "monitor's false alarms with and without it as its gait gate")
    e.add_argument("--weights", type=Path, help="PAE weights (default: the shipped ones)")
    e.add_argument("--data", type=Path, metavar="GAIT.npz", help="held-out gait recordings (default: record the "
                   "held-out schedules now)")
    e.add_argument("--pushes", metavar="FILE|random:N", default="random:200",
                   help="pushes for the gate comparison (default random:200; 'none' skips it)")
    e.add_argument("--seed", type=int, default=0, help="seed of random:N (default 0)")
    e.add_argument("--workers", type=int, help="processes (default: every core)")
    e.add_argument("--out", type=Path, metavar="FILE.json", help="also write the JSON result to this file")
    e.add_argument("--json", action="store_true", help="print the result as JSON")
    e.set_defaults(func=cmd_eval_phase)


def cmd_train_phase(args) -> int:
    from felis.files import check_target
    from felis.learning.phase.run import results_path, train_phase_run
    from felis.learning.phase.train import PhaseTrainConfig

    cfg = PhaseTrainConfig(epochs=args.epochs, window=args.window, n_phases=args.phases, hidden=args.hidden,
                           fld_steps=args.fld_steps, seed=args.seed)
    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise ParameterError(f"{out}: the phase weights file must end in .npz")
    check_target(out, "phase weights", ParameterError)
    if not 0 < args.scale <= 10:
        raise ParameterError(f"--scale must be within 0…10, got {args.scale:g}")
    workdir = Path(args.workdir or out.with_suffix(".ckpt"))
    check_checkpoints(workdir, args.resume, args.restart, has_checkpoints(workdir, "checkpoint.npz"))
    quiet = args.json or not sys.stderr.isatty()
    bar, step = output.progress(cfg.epochs, "epochs", quiet, lines=not args.json)
    last = [0]

    def progress(epoch, epochs, train_loss, val_loss):
        step(epoch - last[0])
        last[0] = epoch

    with bar:
        res = train_phase_run(cfg, out, workdir, data=args.data, scale=args.scale, resume=args.resume,
                              progress=progress)
    if args.json:
        output.print_json(res, default=float)
        return 0
    _print_phase(res["heldout_phase"], res["heldout_prediction"])
    print(f"weights: {out} ({res['params']} parameters, best epoch {res['best_epoch']}); "
          f"results: {results_path(out)}")
    return 0


def cmd_eval_phase(args) -> int:
    from felis.learning.phase.data import load_recordings, record_set
    from felis.learning.phase.estimator import DEFAULT_WEIGHTS
    from felis.learning.phase.evaluate import gate_comparison, phase_metrics
    from felis.learning.phase.infer import load_pae_numpy
    from felis.learning.phase.pae import load_pae
    from felis.learning.phase.train import evaluate_phase

    weights = Path(args.weights or DEFAULT_WEIGHTS)
    if not weights.is_file():
        raise ParameterError(f"{weights}: no phase weights (run `felis train phase` first)")
    pae, meta = load_pae_numpy(weights)
    cal = meta.get("phase_estimator")
    if not isinstance(cal, dict) or "channel" not in cal:
        from felis.errors import PhaseError

        raise PhaseError(f"{weights}: no phase-estimator calibration in the weights (made by `felis train phase`)")
    if args.workers is not None and args.workers < 1:
        raise ParameterError(f"--workers must be ≥ 1, got {args.workers}")
    pushes = None
    if args.pushes != "none":
        from felis.scenarios.push import pushes_from

        pushes = pushes_from(args.pushes, args.seed)
    output.check_json_out(args.out)
    held = load_recordings(args.data, split="heldout") if args.data else record_set("heldout")
    model, _ = load_pae(weights)
    steps = int(meta.get("training", {}).get("config", {}).get("fld_steps", 10))  # the horizon it was trained for
    res = {"weights": str(weights), "gait_channel": cal["channel"],
           "heldout_phase": phase_metrics(pae, cal["channel"], held, cal["stepping_amp"]),
           "heldout_prediction": evaluate_phase(model, [r.q for r in held], steps)}
    if pushes is not None:
        quiet = args.json or not sys.stderr.isatty()
        bar, step = output.progress(len(pushes), "pushes", quiet)
        with bar:
            res["gate"] = gate_comparison(pushes, weights, workers=args.workers, progress=step)
        res["pushes_source"], res["seed"] = args.pushes, args.seed
    return output.emit(args, res, _print_eval)


def _print_phase(ph: dict, pred: dict) -> None:
    print(f"held-out phase: rate within {ph['phase_error_max']:.2%} of the contact-timing step frequency (allowing "
          f"multiples) over {len(ph['segments'])} steady segments; frequency output within "
          f"{ph['frequency_error_max']:.1%} (median {ph['frequency_error_median']:.1%}); standing amplitude "
          f"{ph['amp_standing_ratio']:.1%} of stepping; largest phase jump at gait changes "
          f"{ph['phase_jump_at_changes_max']:.3f} cycles (steady {ph['phase_jump_steady_max']:.3f})")
    m = pred["pred_mse_mean"]
    print(f"held-out reconstruction MSE {pred['recon_mse']:.3g} rad²; {len(pred['horizon_s'])}-step prediction MSE: "
          + ", ".join(f"{k} {v:.3g}" for k, v in m.items()))


def _print_eval(r: dict) -> None:
    _print_phase(r["heldout_phase"], r["heldout_prediction"])
    g = r.get("gate")
    if g:
        for phase in ("step", "stand"):
            row = g[phase]
            print(f"{phase} pushes ({row['pushes']}, {row['falls']} fell): " + "; ".join(
                f"{name} gate recall {row[name]['recall']} false alarms {row[name]['false_alarm_rate']}"
                for name in ("clock", "phase", "none")))
