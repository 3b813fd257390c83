"""Training of the deep IK nets (`felis.learning.ik.net`): Adam, gradient clipping, exponential
learning-rate decay, MSE on standardised targets, the best-validation weights kept, a checkpoint every
epoch that a later run resumes bit-identically.

Method (seed 001 §3.1.2 and ch. 4): Adam with lr 1e-4, batch 128, gradient clipping and learning-rate
decay. Our nets are far smaller than the paper's 3 × 512 LSTM, so a larger lr (2e-3) trains them well;
the epoch-e learning rate is ``lr_e = lr · lr_decay^e`` and the loss

    L = mean over batch and outputs of (ŷ − (y − μ_y) / σ_y)²

with μ, σ the training set's per-channel mean and standard deviation (std 0 → 1), stored in the model.

Determinism: the weights are drawn from ``torch.manual_seed(seed)`` (inside ``fork_rng``, so the
caller's global RNG is untouched), batches from a seeded ``torch.Generator``; the run uses
``threads`` intra-op threads and deterministic algorithms. For a given seed and thread count two
runs give bit-identical weights, and a run resumed from its checkpoint gives the same weights as an
uninterrupted one (the checkpoint holds the model, Adam's moments and step counts, the shuffling
generator's state, the best weights so far and the history). Checkpoints are ``.npz`` files (no
pickle) replaced atomically, so a run killed at any instant leaves the previous epoch's checkpoint.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import TypedDict

import numpy as np

from felis.errors import ParameterError, WeightsError
from felis.learning.common.checkpoints import load_checkpoint, save_checkpoint
from felis.learning.common.curves import TorchSettings, fingerprint, run_epochs, stats
from felis.learning.common.torchstate import torch_to_arrays
from felis.learning.ik.infer import NetSpec, check_arrays
from felis.learning.ik.net import model_from_spec

CHECKPOINT_ID = "felis-ik-checkpoint"
CHECKPOINT_SCHEMA = 1
HISTORY_LISTS = ("train", "val", "lr", "seconds")
EVAL_CHUNK = 16384  # rows per forward pass when evaluating (bounds memory, keeps BLAS efficient)

Progress = Callable[[int, int, float, float], None]


@dataclass(frozen=True)
class TrainConfig:
    """Training settings. ``epochs`` passes over the data in batches of ``batch`` (128 as in the
    paper); Adam at ``lr``, times ``lr_decay`` after each epoch; gradients clipped to norm
    ``grad_clip`` (0 = off); ``seed`` for weights and shuffling; ``threads`` torch intra-op threads,
    0 for torch's default (part of the determinism contract: the same seed and thread count give the
    same weights); ``kind``/``hidden``/``layers`` the architecture for `net_spec`: when set,
    `train_net` checks that its spec agrees; None leaves it to the spec."""

    epochs: int = 30
    batch: int = 128
    lr: float = 2e-3
    lr_decay: float = 0.95
    grad_clip: float = 1.0
    seed: int = 0
    threads: int = 2
    kind: str | None = None
    hidden: int | None = None
    layers: int | None = None

    def __post_init__(self):
        for f in ("epochs", "batch", "hidden", "layers"):
            v = getattr(self, f)
            if v is None and f in ("hidden", "layers"):
                continue
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ParameterError(f"training {f} must be a positive integer, got {v!r}")
        if not isinstance(self.threads, int) or self.threads < 0:
            raise ParameterError(f"training threads must be ≥ 0 (0: torch's default), got {self.threads!r}")
        if self.kind not in (None, "lstm", "mlp"):
            raise ParameterError(f"training kind must be lstm or mlp, got {self.kind!r}")
        if not (np.isfinite(self.lr) and self.lr > 0):
            raise ParameterError(f"training lr must be positive, got {self.lr!r}")
        if not (0 < self.lr_decay <= 1):
            raise ParameterError(f"training lr_decay must be in (0, 1], got {self.lr_decay!r}")
        if not (np.isfinite(self.grad_clip) and self.grad_clip >= 0):
            raise ParameterError(f"training grad_clip must be ≥ 0 (0 = off), got {self.grad_clip!r}")

    def net_spec(self, name: str, k: int, n_out: int, n_in: int = 3, in_offsets=(), out_offsets=()) -> NetSpec:
        """The `NetSpec` of a net with this config's kind, hidden size and layers (unset: lstm, 64, 2)."""
        return NetSpec(self.kind or "lstm", k, n_in, self.hidden or 64, self.layers or 2, n_out, name,
                       tuple(in_offsets), tuple(out_offsets))

    def lr_at(self, epoch: int) -> float:
        """Learning rate of 0-based ``epoch``: lr · lr_decay^epoch."""
        return self.lr * self.lr_decay ** epoch


class History(TypedDict):
    """What `train_net` returns beside the model; plain JSON (a results file or weights metadata take
    it as is). Per epoch: ``train`` and ``val`` losses (MSE on standardised targets; without
    validation data ``val`` repeats ``train``), ``lr``, wall ``seconds``; ``best_epoch`` (1-based,
    0 before any epoch) and ``best_val`` (None before any epoch) of the weights returned."""

    train: list[float]
    val: list[float]
    lr: list[float]
    seconds: list[float]
    best_epoch: int
    best_val: float | None


def new_history() -> History:
    return {"train": [], "val": [], "lr": [], "seconds": [], "best_epoch": 0, "best_val": None}


def _check_data(X, Y, spec: NetSpec, what: str) -> tuple[np.ndarray, np.ndarray]:
    X = np.asarray(X, dtype=np.float32)
    Y = np.asarray(Y, dtype=np.float32)
    if X.ndim != 3 or X.shape[1:] != (spec.k, spec.n_in):
        raise ParameterError(f"{what} inputs have shape {X.shape}, net {spec.name!r} needs (N, {spec.k}, {spec.n_in})")
    if Y.shape != (X.shape[0], spec.n_out):
        raise ParameterError(f"{what} targets have shape {Y.shape}, net {spec.name!r} needs ({X.shape[0]}, "
                             f"{spec.n_out})")
    if X.shape[0] == 0:
        raise ParameterError(f"{what} set is empty")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Y))):
        raise ParameterError(f"{what} set holds non-finite values")
    return X, Y


def train_net(X, Y, Xval, Yval, spec: NetSpec, cfg: TrainConfig, checkpoint: Path | None = None,
              resume: bool = False, progress: Progress | None = None):
    """Train one IK net; returns (model, `History`) with the model holding the best-validation weights.

    X (N, k, n_in), Y (N, n_out) float arrays; Xval, Yval the validation set (None: the training loss
    picks the best epoch). ``spec`` gives the architecture; ``cfg``'s kind, hidden and layers, where
    set, must agree with it. ``checkpoint``: written after every epoch (atomically). ``resume``:
    continue from ``checkpoint`` if it exists (a missing one starts afresh) — it must come from the
    same spec, config (apart from ``epochs``, so a finished run can be extended) and data, else
    `WeightsError`. ``progress(epoch, epochs, train_loss, val_loss)`` is called after each epoch
    (1-based epoch); an exception it raises stops training after that epoch's checkpoint. The
    `History` returned is a plain-JSON dict.
    """
    import torch

    for f in ("kind", "hidden", "layers"):
        if getattr(cfg, f) is not None and getattr(cfg, f) != getattr(spec, f):
            raise ParameterError(f"net {spec.name!r} has {f} {getattr(spec, f)!r} but the training config says "
                                 f"{getattr(cfg, f)!r}")
    X, Y = _check_data(X, Y, spec, "training")
    has_val = Xval is not None
    if has_val:
        Xval, Yval = _check_data(Xval, Yval, spec, "validation")
    x_mean, x_std = stats(X, (0, 1))
    y_mean, y_std = stats(Y, (0,))
    data_id = fingerprint(X, Y, *((Xval, Yval) if has_val else ()))
    run_id = {"spec": spec.to_json(), "config": {k: v for k, v in asdict(cfg).items() if k != "epochs"},
              "data": data_id}

    with TorchSettings(cfg.threads):
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            model = model_from_spec(spec)
        model.set_stats(x_mean, x_std, y_mean, y_std)
        # standardise once; the model's core works on standardised data (forward adds the affine maps)
        xs = torch.from_numpy(((X - x_mean) / x_std).astype(np.float32))
        ys = torch.from_numpy(((Y - y_mean) / y_std).astype(np.float32))
        if has_val:
            xv = torch.from_numpy(((Xval - x_mean) / x_std).astype(np.float32))
            yv = torch.from_numpy(((Yval - y_mean) / y_std).astype(np.float32))
        n = xs.shape[0]

        def batch_loss(idx):
            loss = torch.nn.functional.mse_loss(model.core(xs[idx]), ys[idx])
            return loss, loss.detach()

        def finish(total):
            train_loss = float(total) / n
            return train_loss, _evaluate(model, xv, yv) if has_val else train_loss, ()

        def diverged(epoch: int, train_loss: float) -> Exception:
            return ParameterError(f"training of net {spec.name!r} diverged at epoch {epoch} (loss "
                                  f"{train_loss:.3g}); lower the lr (now {cfg.lr:g}) or grad_clip")

        hist = run_epochs(model, n, cfg, new_history, batch_loss, finish, diverged, progress, checkpoint, resume,
                          partial(_save_checkpoint, run_id, model), partial(_load_checkpoint, run_id, spec, model))
    return model, hist


def _evaluate(model, xs, ys) -> float:
    """MSE on standardised data, in chunks."""
    import torch

    model.eval()
    total = 0.0
    with torch.no_grad():
        for i in range(0, xs.shape[0], EVAL_CHUNK):
            err = model.core(xs[i:i + EVAL_CHUNK]) - ys[i:i + EVAL_CHUNK]
            total += float(err.double().square().sum())
    return total / (xs.shape[0] * ys.shape[1])


# ----------------------------------------------------------------------------------------- checkpoint


def _save_checkpoint(run_id: dict, model, path: Path, epoch: int, opt, gen, hist: History, best: dict) -> None:
    save_checkpoint(path, (CHECKPOINT_ID, CHECKPOINT_SCHEMA), run_id, epoch, torch_to_arrays(model), opt, gen, hist,
                    HISTORY_LISTS, best, "training checkpoint", WeightsError)


def _load_checkpoint(run_id: dict, spec: NetSpec, model, path: Path, opt, gen):
    """Restore model, optimiser, generator from ``path`` (`felis.learning.common.checkpoints`); returns (next
    epoch, history, best state). WeightsError (one line) for a corrupt checkpoint or one from another run."""
    return load_checkpoint(path, (CHECKPOINT_ID, CHECKPOINT_SCHEMA), run_id,
                           (("spec", "net spec"), ("config", "training config"), ("data", "training data")),
                           lambda arrays, where: check_arrays(spec, arrays, where), model, opt, gen, new_history,
                           HISTORY_LISTS, "IK training checkpoint", WeightsError)
