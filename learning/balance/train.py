"""Training the reactive-strategy selector (seed 004) and the balance part of ``felis demo``.

`fit_selector` takes push demonstrations (features of every push that called for a reaction, and the
score of every strategy tried on it: `felis.learning.balance.evaluate.demonstrate`), splits off a
held-out part, fits the denoised kNN selector (and, beside it, variants and an SVM), measures them on
the held-out part against fixed strategies, and writes the selector (.npz), its demonstrations
(``.demos.npz``, reusable with ``felis train balance --demos``) and a results JSON. `push_demo` and
`plot_margins` are ``felis demo``'s part 4: the standing cat pushed, with and without the selector.
"""

from __future__ import annotations

import io
import json
import time
from pathlib import Path

import numpy as np

from felis.controllers.reactions import FEATURES, REACTIONS
from felis.errors import ParameterError
from felis.files import MAX_ARRAY_BYTES, check_readable, check_target, prepare_parent, write_atomic
from felis.learning.balance.compare import SvmSelector, accuracy, exact_accuracy, recovery_accuracy
from felis.learning.balance.selector import CaseBase, KnnSelector

TOL = 0.05  # selector accuracy: a strategy whose score is within this of the best counts as the best
DEMO_PUSH = {"body": "upper_body", "direction_deg": 90.0, "impulse_ns": 0.6, "t_s": 0.8, "phase": "stand"}


def check_outputs(out: Path, holdout: float) -> None:
    """Refuse a selector file that is not ``.npz`` or cannot be written, and a held-out fraction outside
    0.05…0.9, before any work."""
    if out.suffix.lower() != ".npz":
        raise ParameterError(f"{out}: the selector file must end in .npz")
    if not 0.05 <= holdout <= 0.9:
        raise ParameterError(f"--holdout must be within 0.05…0.9, got {holdout}")
    check_target(out, "selector", ParameterError)


def demos_bytes(X, S, source: str) -> bytes:
    """A demonstrations file's content: features ``X``, scores ``S`` and where the pushes came from."""
    buf = io.BytesIO()
    np.savez(buf, features=X, scores=S, source=np.array(source))
    return buf.getvalue()


def read_demos(path: Path):
    """(features, scores, source) of a demonstrations file written by `fit_selector`."""
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


def fit_selector(X, S, source: str, out: Path, *, seed: int, holdout: float, k: int, demos: Path | None,
                 t0: float) -> dict:
    """Fit and measure the selectors on demonstrations ``X``/``S``; write the selector to ``out``, the
    demonstrations beside it (unless they came from the file ``demos``) and ``<out>.results.json``.
    Returns the results (``time_s`` counted from ``t0``, a `time.perf_counter` reading)."""
    demos_out = out.with_suffix(".demos.npz")
    cases = CaseBase(X, S, FEATURES, REACTIONS)
    if len(cases) < 20:
        raise ParameterError(f"only {len(cases)} pushes called for a reaction: too few demonstrations "
                             "(use more pushes)")
    train, held = cases.split(1.0 - holdout, seed)
    knn = KnnSelector(k=k, power=2.0, interpolate="scores").fit(train)
    variants = {"knn": knn,
                "knn_no_denoise": KnnSelector(k=k, power=2.0, interpolate="scores", denoise=False).fit(train),
                "knn_labels": KnnSelector(k=k).fit(train), "svm": SvmSelector().fit(train)}
    labels = cases.labels()
    common = int(np.bincount(train.labels(), minlength=len(REACTIONS)).argmax())
    fixed = {f"always_{name}": i for i, name in enumerate(REACTIONS)}

    def fixed_rates(metric):
        return {k: round(metric(i), 4) for k, i in fixed.items()}

    res = {
        "demonstrations": len(cases), "train": len(train), "held_out": len(held), "pushes": source,
        "seed": seed, "tolerance": TOL, "features": list(FEATURES), "strategies": list(REACTIONS),
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
    if demos is None:
        write_atomic(demos_out, demos_bytes(X, S, source), "demonstrations", ParameterError)
    res["demonstrations_file"] = str(demos_out if demos is None else demos)
    write_atomic(out.with_suffix(".results.json"), json.dumps(res, indent=1) + "\n", "results", ParameterError)
    return res


# ------------------------------------------------------------------------------ felis demo, part 4
def push_demo(run_dir: Path, video: bool = True) -> dict:
    """``felis demo`` part 4: the standing cat pushed sideways, once without a reaction and once with the
    shipped strategy selector; the margin of stability with the warning and the alarm, to PNG; the
    selector's run to MP4."""
    from felis.learning.balance.evaluate import PushSim
    from felis.learning.balance.selector import load_selector
    from felis.scenarios.push import check_push

    p = check_push(DEMO_PUSH, "demo push")
    sim = PushSim()
    runs = {}
    try:
        runs["none"] = sim.run(p, "none", trace=True)
        recorder = []
        if video:
            from felis.sim.render import VideoRecorder  # late: MuJoCo rendering, only with video

            recorder = [VideoRecorder(sim.robot, run_dir / "push.mp4", fps=30.0, width=640, height=480)]
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
    import matplotlib  # late: matplotlib only for the demo's plot

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
