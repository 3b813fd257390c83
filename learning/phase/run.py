"""`felis train phase`: gait recordings → PAE with FLD → calibrated weights, held-out figures.

One run: the gait data (a file from ``felis phase record``, or the default schedules recorded now in
MuJoCo, `felis.learning.phase.data`); the ``train`` recordings train the PAE with FLD
(`felis.learning.phase.train.train_phase`, a checkpoint per epoch in the work folder), the ``heldout``
ones pick the best epoch and are the evaluation set; `felis.learning.phase.estimator.calibrate` finds the
gait channel and the stepping threshold on the training recordings, stored in the weights' metadata
(``phase_estimator``). Then, on the held-out recordings: the phase figures
(`felis.learning.phase.evaluate.phase_metrics`) and the reconstruction and N-step prediction errors of FLD
against the constant-velocity and last-cycle baselines (`felis.learning.phase.train.evaluate_phase`).
Writes the weights (``.npz``) and ``<name>.results.json`` beside them.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from felis.errors import PhaseError
from felis.files import write_atomic
from felis.learning.phase.data import load_recordings, record_set
from felis.learning.phase.estimator import calibrate
from felis.learning.phase.evaluate import phase_metrics
from felis.learning.phase.infer import load_pae_numpy
from felis.learning.phase.pae import save_pae
from felis.learning.phase.train import PhaseTrainConfig, evaluate_phase, train_phase


def gait_data(path: Path | None, scale: float = 1.0):
    """(train, heldout) recordings: from a gait-data file, or recorded now (the default schedules)."""
    if path is None:
        return record_set("train", scale=scale), record_set("heldout", scale=scale)
    train, held = load_recordings(path, split="train"), load_recordings(path, split="heldout")
    if not train or not held:
        raise PhaseError(f"{path}: needs recordings of both sets, train and heldout (felis phase record --set all)")
    return train, held


def results_path(out: Path) -> Path:
    return out.with_name(out.stem + ".results.json")


def train_phase_run(cfg: PhaseTrainConfig, out: Path, workdir: Path, *, data: Path | None = None,
                    scale: float = 1.0, resume: bool = False,
                    progress: Callable[[int, int, float, float], None] | None = None) -> dict:
    """Train, calibrate, evaluate, save (module doc); returns the results written beside ``out``."""
    t0 = time.perf_counter()
    train, held = gait_data(data, scale)
    joints = train[0].joints
    for r in train + held:
        if r.rate_hz != cfg.rate_hz:
            raise PhaseError(f"recording {r.name} is at {r.rate_hz:g} Hz, the model at {cfg.rate_hz:g} Hz")
    workdir.mkdir(parents=True, exist_ok=True)
    model, hist = train_phase([r.q for r in train], [r.q for r in held], cfg, checkpoint=workdir / "checkpoint.npz",
                              progress=progress, resume=resume, joints=joints)
    t_train = time.perf_counter() - t0
    tmp = workdir / "uncalibrated.npz"
    save_pae(tmp, model)
    pae, _ = load_pae_numpy(tmp)
    cal = calibrate(pae, [r.q for r in train], [r.stepping for r in train])
    phase = phase_metrics(pae, cal["channel"], held, cal["stepping_amp"])
    pred = evaluate_phase(model, [r.q for r in held], cfg.fld_steps)
    results = {
        "config": asdict(cfg), "data": str(data) if data else f"recorded now (scale {scale:g})",
        "train_recordings": [r.name for r in train], "heldout_recordings": [r.name for r in held],
        "train_seconds": round(sum(r.duration_s for r in train), 1),
        "heldout_seconds": round(sum(r.duration_s for r in held), 1),
        "params": pae.config.param_count, "best_epoch": hist["best_epoch"], "best_val": hist["best_val"],
        "phase_estimator": cal, "heldout_phase": phase, "heldout_prediction": pred,
        "history": {k: v for k, v in hist.items() if isinstance(v, list)},
        "train_wall_s": round(t_train, 1), "wall_s": round(time.perf_counter() - t0, 1),
    }
    save_pae(out, model, {"phase_estimator": cal, "training": {"config": asdict(cfg), "best_epoch": hist["best_epoch"],
                                                               "data": results["data"]}})
    write_atomic(results_path(out), json.dumps(results, indent=1, default=float) + "\n", "phase results", PhaseError)
    tmp.unlink(missing_ok=True)
    return results
