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

import time
import zlib
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TypedDict

import numpy as np

from felis.errors import ParameterError, WeightsError
from felis.learning.common.checkpoints import load_checkpoint, save_checkpoint
from felis.learning.ik.net import NetSpec, check_arrays, model_from_spec, torch_to_arrays

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


def _stats(a: np.ndarray, axes: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std over ``axes`` in float64; a (near-)constant channel gets std 1 so it passes unscaled."""
    mean = a.mean(axis=axes, dtype=np.float64)
    std = a.std(axis=axes, dtype=np.float64)
    std = np.where(std > 1e-8 * np.maximum(1.0, np.abs(mean)), std, 1.0)
    return mean, std


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


def _fingerprint(*arrays: np.ndarray) -> str:
    """Shapes and CRC-32 of the data, so a checkpoint is not resumed on other data."""
    crc = 0
    for a in arrays:
        crc = zlib.crc32(np.ascontiguousarray(a).view(np.uint8).ravel(), crc)
    return f"{'/'.join('x'.join(map(str, a.shape)) for a in arrays)}:{crc:08x}"


class _TorchSettings:
    """Set torch's thread count and deterministic mode for a training run; restore them afterwards
    (the caller's process keeps its own settings: no global state leaks out of `train_net`)."""

    def __init__(self, threads: int):
        self.threads = threads

    def __enter__(self):
        import torch

        self._saved = (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled(),
                       torch.is_deterministic_algorithms_warn_only_enabled())
        if self.threads > 0:
            torch.set_num_threads(self.threads)
        torch.use_deterministic_algorithms(True, warn_only=True)
        return self

    def __exit__(self, *exc):
        import torch

        threads, det, warn_only = self._saved
        torch.set_num_threads(threads)
        torch.use_deterministic_algorithms(det, warn_only=warn_only)
        return False


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
    x_mean, x_std = _stats(X, (0, 1))
    y_mean, y_std = _stats(Y, (0,))
    fingerprint = _fingerprint(X, Y, *((Xval, Yval) if has_val else ()))
    run_id = {"spec": spec.to_json(), "config": {k: v for k, v in asdict(cfg).items() if k != "epochs"},
              "data": fingerprint}

    with _TorchSettings(cfg.threads):
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
        opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, fused=True)  # one kernel per step; deterministic on CPU
        gen = torch.Generator().manual_seed(cfg.seed)
        hist = new_history()
        best = {k: v.detach().clone() for k, v in model.state_dict().items()}
        start = 0
        if resume and checkpoint is not None and Path(checkpoint).exists():
            start, hist, best = _load_checkpoint(Path(checkpoint), run_id, spec, model, opt, gen)

        params = list(model.parameters())
        n = xs.shape[0]
        for epoch in range(start, cfg.epochs):
            t0 = time.perf_counter()
            lr = cfg.lr_at(epoch)
            for group in opt.param_groups:
                group["lr"] = lr
            model.train()
            perm = torch.randperm(n, generator=gen)
            total = torch.zeros((), dtype=torch.float64)
            for i in range(0, n, cfg.batch):
                idx = perm[i:i + cfg.batch]
                loss = torch.nn.functional.mse_loss(model.core(xs[idx]), ys[idx])
                opt.zero_grad(set_to_none=True)
                loss.backward()
                if cfg.grad_clip > 0:
                    torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip, foreach=True)
                opt.step()
                total += loss.detach().double() * idx.numel()
            train_loss = float(total) / n
            val_loss = _evaluate(model, xv, yv) if has_val else train_loss
            if not np.isfinite(train_loss) or not np.isfinite(val_loss):
                raise ParameterError(f"training of net {spec.name!r} diverged at epoch {epoch + 1} (loss "
                                     f"{train_loss:.3g}); lower the lr (now {cfg.lr:g}) or grad_clip")
            hist["train"].append(train_loss)
            hist["val"].append(val_loss)
            hist["lr"].append(lr)
            hist["seconds"].append(round(time.perf_counter() - t0, 3))
            if hist["best_val"] is None or val_loss < hist["best_val"]:
                hist["best_val"], hist["best_epoch"] = val_loss, epoch + 1
                best = {k: v.detach().clone() for k, v in model.state_dict().items()}
            if checkpoint is not None:
                _save_checkpoint(Path(checkpoint), run_id, epoch + 1, model, opt, gen, hist, best)
            if progress is not None:
                progress(epoch + 1, cfg.epochs, train_loss, val_loss)
        model.load_state_dict(best)
        model.eval()
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


def _save_checkpoint(path: Path, run_id: dict, epoch: int, model, opt, gen, hist: History, best: dict) -> None:
    save_checkpoint(path, (CHECKPOINT_ID, CHECKPOINT_SCHEMA), run_id, epoch, torch_to_arrays(model), opt, gen, hist,
                    HISTORY_LISTS, best, "training checkpoint", WeightsError)


def _load_checkpoint(path: Path, run_id: dict, spec: NetSpec, model, opt, gen):
    """Restore model, optimiser, generator from ``path`` (`felis.learning.common.checkpoints`); returns (next
    epoch, history, best state). WeightsError (one line) for a corrupt checkpoint or one from another run."""
    return load_checkpoint(path, (CHECKPOINT_ID, CHECKPOINT_SCHEMA), run_id,
                           (("spec", "net spec"), ("config", "training config"), ("data", "training data")),
                           lambda arrays, where: check_arrays(spec, arrays, where), model, opt, gen, new_history,
                           HISTORY_LISTS, "IK training checkpoint", WeightsError)
