"""`felis train ik`: demonstrations → Motion Predictor and Posture Estimator → weights and results.

One run (seed 001 §3.1): generate the deterministic demonstration corpus (`data.make_corpus`),
split it by whole trajectories into train / validation / test, cut every frame into windows, train
the Motion Predictor (v_{i−10}, v_{i−5}, v_i → v_{i+5}, v_{i+10}) and the Posture Estimator (the
five frames → joint angles of frames i … i+5, as sin/cos), save both in one ``.npz`` weights file,
then evaluate the whole pipeline on the held-out test trajectories (`evaluate.evaluate`). Writes
beside the weights: ``<name>.results.json`` and ``<name>.curves.png`` (learning curves).

Variants for the paper's ablations: ``pe_frames`` 1 (v_i), 3 (v_{i−10}, v_{i−5}, v_i: no Motion
Predictor needed) or 5 (the paper's), and ``kind`` "lstm" or "mlp" (a multilayer perceptron of
similar size, `net.SeqNet`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from felis.errors import ParameterError
from felis.files import write_atomic
from felis.learning.common.curves import plot_loss_curves
from felis.learning.common.torchstate import torch_to_arrays
from felis.learning.ik.config import PE_VARIANTS, IkTrainConfig
from felis.learning.ik.corpus import recorded_demos
from felis.learning.ik.data import make_corpus, split, windows
from felis.learning.ik.evaluate import evaluate
from felis.learning.ik.infer import MP_IN, MP_OUT, PE_OUT, NetSpec, load_arrays
from felis.learning.ik.net import save_weights
from felis.learning.ik.solver import IkSolver
from felis.learning.ik.train import TrainConfig, train_net

NET_TITLES = {"mp": "Motion Predictor", "pe": "Posture Estimator"}  # panels of the learning curves
def data(cfg: IkTrainConfig):
    """The corpus split and every window set the run needs."""
    corpus = make_corpus(cfg.corpus, cfg.corpus_seed)
    train, val, test = split(corpus, cfg.corpus_seed)
    if cfg.recorded:  # recorded runs of the arm (`felis run … --log`): demonstrations too, for training only
        train = train + [recorded_demos(Path(p)) for p in cfg.recorded]
    pe_in = PE_VARIANTS[cfg.pe_frames]
    sets = {}
    for name, trajs in (("train", train), ("val", val)):
        mp = windows(trajs, MP_IN, MP_OUT, target="points")
        pe = windows(trajs, pe_in, PE_OUT, target="angles")
        if name == "train" and cfg.stride > 1:
            mp = tuple(a[:: cfg.stride] for a in mp)
            pe = tuple(a[:: cfg.stride] for a in pe)
        sets[name] = {"mp": mp, "pe": pe}
    return (train, val, test), sets, pe_in


def train_ik(cfg: IkTrainConfig, out: Path, workdir: Path, *, resume: bool = False,
             progress: Callable[[str, int, int, float, float], None] | None = None,
             evaluate_test: bool = True, baselines: bool = True, mp_from: Path | None = None) -> dict:
    """Train both nets, write ``out`` (weights) and its results JSON and learning curves; return the results.

    ``mp_from``: take the Motion Predictor from this weights file instead of training one (the
    ablations vary only the Posture Estimator)."""
    cfg.check()
    out, workdir = Path(out), Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    (train, val, test), sets, pe_in = data(cfg)
    tcfg = TrainConfig(epochs=cfg.epochs, batch=cfg.batch, lr=cfg.lr, lr_decay=cfg.lr_decay,
                       grad_clip=cfg.grad_clip, seed=cfg.seed, threads=cfg.threads)
    nets, history = {}, {}
    for name, k, n_out in (("mp", len(MP_IN), 3 * len(MP_OUT)), ("pe", len(pe_in), 8 * len(PE_OUT))):
        if name == "mp" and mp_from is not None:  # ablations share one Motion Predictor
            arrs, old = load_arrays(mp_from, expect={"nets": ["mp"]})
            nets[name] = arrs["mp"]
            history[name] = old.get("history", {}).get("mp", {"train": [], "val": []})
            continue
        spec = NetSpec(kind=cfg.kind, k=k, n_in=3, hidden=cfg.hidden, layers=cfg.layers, n_out=n_out, name=name)
        X, Y = sets["train"][name]
        Xv, Yv = sets["val"][name]
        cb = None if progress is None else (lambda e, n, tr, va, _name=name: progress(_name, e, n, tr, va))
        model, hist = train_net(X, Y, Xv, Yv, spec, tcfg, checkpoint=workdir / f"{name}.ckpt.npz", resume=resume,
                                progress=cb)
        nets[name] = (spec, torch_to_arrays(model))
        history[name] = hist
    train_s = time.perf_counter() - t0
    meta = {"pe_in": list(pe_in), "config": asdict(cfg),
            "corpus": {"trajectories": cfg.corpus, "seed": cfg.corpus_seed, "train": len(train), "val": len(val),
                       "test": len(test), "train_windows": int(len(sets["train"]["pe"][0]))},
            "history": history, "train_s": round(train_s, 1)}
    save_weights(out, nets, meta)
    results = {"weights": str(out), "size_bytes": out.stat().st_size, "config": asdict(cfg),
               "params": {n: int(s.param_count) for n, (s, _) in nets.items()}, "corpus": meta["corpus"],
               "history": history, "train_s": round(train_s, 1)}
    if evaluate_test:
        results["test"] = evaluate(IkSolver.load(out), test, baselines=baselines)
    stem = out.with_suffix("")
    write_atomic(Path(f"{stem}.results.json"), json.dumps(results, indent=2), "IK results", ParameterError)
    plot_loss_curves(history, Path(f"{stem}.curves.png"), NET_TITLES)
    return results
