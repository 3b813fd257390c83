"""The IK nets' size table and the paper's ablations (seed 001 Fig. 4.7–4.8), trained and measured here.

    python bench/ik_study.py [--epochs 10] [--stride 4] [--seeds 0,1,2] [--out runs/ik-study] [--only NAME,...]

Every variant is trained with the same corpus, seed, epochs and window stride (`felis train ik` with
options; shorter than the shipped run so that the study fits in about half an hour on 2 cores), then
its whole pipeline is evaluated on the held-out test trajectories. Rows:

- size table: LSTM hidden 32 / 64 / 128 (2 layers, 5 input frames): accuracy against file size;
- input length: the Posture Estimator fed 1 frame (v_i), 3 frames (v_{i−10}, v_{i−5}, v_i: no Motion
  Predictor) or the paper's 5 (with the predicted v_{i+5}, v_{i+10}); they share the reference run's
  Motion Predictor;
- network type: LSTM against an MLP of similar parameter count (`ik.infer.mlp_width`).

Each variant is trained once per seed (initialisation and batch order; the corpus is the same); the
table gives mean ± standard deviation over the seeds. Prints a Markdown table (also written to
``<out>/study.md`` with every run's numbers in ``study.json``).
Latency is per single query on this machine; compare rows of one run only.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

VARIANTS = {  # name: (IkTrainConfig overrides, share the reference Motion Predictor)
    "lstm64-5f": ({}, False),
    "lstm64-1f": ({"pe_frames": 1}, True),
    "lstm64-3f": ({"pe_frames": 3}, True),
    "mlp64-5f": ({"kind": "mlp"}, False),
    "lstm32-5f": ({"hidden": 32}, False),
    "lstm128-5f": ({"hidden": 128}, False),
}
REFERENCE = "lstm64-5f"


def main() -> int:
    from felis.learning.ik.data import make_corpus, split
    from felis.learning.ik.evaluate import evaluate
    from felis.learning.ik.run import IkTrainConfig, train_ik
    from felis.learning.ik.solver import IkSolver

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "ik-study")
    ap.add_argument("--only", help="comma-separated variant names")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated training seeds (default 0,1,2)")
    args = ap.parse_args()
    names = list(VARIANTS) if not args.only else args.only.split(",")
    seeds = [int(x) for x in args.seeds.split(",")]
    args.out.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list[dict]] = {}
    for seed in seeds:
        ref_file = args.out / f"{REFERENCE}-s{seed}.npz"
        for name in names:
            over, share = VARIANTS[name]
            cfg = IkTrainConfig(epochs=args.epochs, stride=args.stride, seed=seed, **over)
            out = args.out / f"{name}-s{seed}.npz"
            t0 = time.perf_counter()
            if not out.exists():
                train_ik(cfg, out, args.out / f"{name}-s{seed}.ckpt", evaluate_test=False,
                         mp_from=ref_file if share and ref_file.exists() else None, resume=True)
            train_s = time.perf_counter() - t0
            solver = IkSolver.load(out)
            test = split(make_corpus(cfg.corpus, cfg.corpus_seed), cfg.corpus_seed)[2]
            r = evaluate(solver, test, baselines=False)
            runs.setdefault(name, []).append({"seed": seed, "config": over, "size_kb": out.stat().st_size / 1024,
                                              "train_s": round(train_s, 1), "eval": r})
            print(f"{name} seed {seed}: raw median {r['raw']['median_mm']:.2f} mm, "
                  f"jerk {r.get('jerk_ratio', float('nan')):.2f}x", flush=True)

    def ms(name, get, fmt="{:.2f}"):
        v = np.array([get(x["eval"]) for x in runs[name]], dtype=float)
        return fmt.format(v.mean()) + (f" ± {fmt.format(v.std(ddof=1))}" if len(v) > 1 else "")

    lines = [f"seeds {','.join(map(str, seeds))}; {args.epochs} epochs, window stride {args.stride}; mean ± sd", "",
             "| variant | file KB | raw median mm | raw p95 mm | filtered median mm | refined p99 mm (max) | "
             "jerk × demos | pitch dev ° | single query ms |", "|---|---|---|---|---|---|---|---|---|"]
    for name in names:
        worst = max(x["eval"]["refined"]["p99_mm"] for x in runs[name])
        lines.append(f"| {name} | {runs[name][0]['size_kb']:.0f} | {ms(name, lambda r: r['raw']['median_mm'])} | "
                     f"{ms(name, lambda r: r['raw']['p95_mm'])} | {ms(name, lambda r: r['filtered']['median_mm'])} | "
                     f"{worst:.1e} | {ms(name, lambda r: r.get('jerk_ratio', np.nan))} | "
                     f"{ms(name, lambda r: r['pitch_dev_deg']['median'])} | "
                     f"{ms(name, lambda r: r['latency_ms']['single']['median'], '{:.3f}')} |")
    table = "\n".join(lines)
    print(table)
    (args.out / "study.md").write_text(table + "\n")
    (args.out / "study.json").write_text(json.dumps(runs, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
