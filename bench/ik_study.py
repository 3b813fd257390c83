"""The IK nets' size table and the paper's ablations (seed 001 Fig. 4.7–4.8), trained and measured here.

    python bench/ik_study.py [--epochs 10] [--stride 4] [--out runs/ik-study] [--only NAME,...]

Every variant is trained with the same corpus, seed, epochs and window stride (`felis train ik` with
options; shorter than the shipped run so that the study fits in about half an hour on 2 cores), then
its whole pipeline is evaluated on the held-out test trajectories. Rows:

- size table: LSTM hidden 32 / 64 / 128 (2 layers, 5 input frames): accuracy against file size;
- input length: the Posture Estimator fed 1 frame (v_i), 3 frames (v_{i−10}, v_{i−5}, v_i: no Motion
  Predictor) or the paper's 5 (with the predicted v_{i+5}, v_{i+10}); they share the reference run's
  Motion Predictor;
- network type: LSTM against an MLP of similar parameter count (`ik_net.mlp_width`).

Prints a Markdown table (also written to ``<out>/study.md`` with the numbers in ``study.json``).
Latency is per single query on this machine; compare rows of one run only.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

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
    from felis.learning.ik_data import make_corpus, split
    from felis.learning.ik_eval import evaluate
    from felis.learning.ik_run import IkTrainConfig, train_ik
    from felis.learning.ik_solver import IkSolver

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "ik-study")
    ap.add_argument("--only", help="comma-separated variant names")
    args = ap.parse_args()
    names = list(VARIANTS) if not args.only else args.only.split(",")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = {}
    ref_file = args.out / f"{REFERENCE}.npz"
    for name in names:
        over, share = VARIANTS[name]
        cfg = IkTrainConfig(epochs=args.epochs, stride=args.stride, **over)
        out = args.out / f"{name}.npz"
        t0 = time.perf_counter()
        if not out.exists():
            train_ik(cfg, out, args.out / f"{name}.ckpt", evaluate_test=False,
                     mp_from=ref_file if share and ref_file.exists() else None, resume=True)
        train_s = time.perf_counter() - t0
        solver = IkSolver.load(out)
        test = split(make_corpus(cfg.corpus, cfg.corpus_seed), cfg.corpus_seed)[2]
        r = evaluate(solver, test, baselines=False)
        rows[name] = {"config": over, "size_kb": out.stat().st_size / 1024, "params": solver.meta.get("nets", {}),
                      "train_s": round(train_s, 1), "eval": r}
        print(f"{name}: raw median {r['raw']['median_mm']:.2f} mm, jerk {r.get('jerk_ratio', float('nan')):.2f}×",
              flush=True)
    lines = ["| variant | file KB | raw median mm | raw p95 mm | filtered median mm | refined p99 mm | "
             "jerk × demos | pitch dev ° | single query ms |", "|---|---|---|---|---|---|---|---|---|"]
    for name, row in rows.items():
        r = row["eval"]
        lines.append(f"| {name} | {row['size_kb']:.0f} | {r['raw']['median_mm']:.2f} | {r['raw']['p95_mm']:.2f} | "
                     f"{r['filtered']['median_mm']:.2f} | {r['refined']['p99_mm']:.1e} | "
                     f"{r.get('jerk_ratio', float('nan')):.2f} | {r['pitch_dev_deg']['median']:.2f} | "
                     f"{r['latency_ms']['single']['median']:.3f} |")
    table = "\n".join(lines)
    print(table)
    (args.out / "study.md").write_text(table + "\n")
    (args.out / "study.json").write_text(json.dumps(rows, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
