"""Learning curves of the gradient-trained nets (the IK nets, the PAE): the epoch loop that trains a torch
model and records its curves (`run_epochs`), the per-run torch settings and data statistics it needs,
and the plot of the curves (`plot_loss_curves`).

One epoch: the learning rate of the schedule (``cfg.lr_at(epoch)``), a permutation of the training rows
from the run's own generator, Adam steps over mini-batches of ``cfg.batch`` rows (gradient norm clipped
at ``cfg.grad_clip`` when > 0), then the training and validation losses; the weights with the lowest
validation loss are kept. The order of the random draws is fixed, so a checkpointed run resumes
bit-identically. torch is imported inside the functions that need it (it is heavy; importing this module
must not load it).
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np


class TorchSettings:
    """Set torch's thread count and deterministic mode for a training run; restore them afterwards
    (the caller's process keeps its own settings: no global state leaks out of a training run)."""

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


def stats(a: np.ndarray, axes: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std over ``axes`` in float64; a (near-)constant channel gets std 1 so it passes unscaled."""
    mean = a.mean(axis=axes, dtype=np.float64)
    std = a.std(axis=axes, dtype=np.float64)
    std = np.where(std > 1e-8 * np.maximum(1.0, np.abs(mean)), std, 1.0)
    return mean, std


def fingerprint(*arrays: np.ndarray) -> str:
    """Shapes and CRC-32 of the data, so a checkpoint is not resumed on other data."""
    crc = 0
    for a in arrays:
        crc = zlib.crc32(np.ascontiguousarray(a).view(np.uint8).ravel(), crc)
    return f"{'/'.join('x'.join(map(str, a.shape)) for a in arrays)}:{crc:08x}"


def run_epochs(model, n: int, cfg: Any, new_history: Callable[[], dict],
               batch_loss: Callable[[Any], tuple[Any, Any]], finish: Callable[[Any], tuple[float, float, Sequence]],
               diverged: Callable[[int, float], Exception], progress: Callable[[int, int, float, float], None] | None,
               checkpoint: str | Path | None, resume: bool, save: Callable[[Path, int, Any, Any, dict, dict], None],
               load: Callable[[Path, Any, Any], tuple[int, dict, dict]], terms_shape: tuple[int, ...] = ()) -> dict:
    """Train ``model`` on ``n`` training rows for epochs … ``cfg.epochs − 1`` (module doc); returns the history,
    with the model holding the best weights, in eval mode.

    The run's Adam optimiser (fused: one kernel per step, deterministic on CPU) and generator (seeded with
    ``cfg.seed``) are made here, the history by ``new_history()``. With ``resume`` and an existing
    ``checkpoint``, ``load(checkpoint, opt, gen)`` restores them and returns (next epoch, history, best
    state); a missing one starts afresh. ``batch_loss(idx)`` → (loss to minimise, the detached terms to sum,
    of shape ``terms_shape``) for the rows ``idx``; the sums, weighted by batch size, go to ``finish(sums)`` →
    (training loss, validation loss, further (history key, value) pairs). A non-finite loss raises
    ``diverged(epoch, train_loss)``. The history gets ``train``, ``val``, the further pairs, ``lr`` and
    ``seconds`` appended, ``best_val`` and ``best_epoch`` updated. After every epoch (1-based), ``save(checkpoint,
    epoch, opt, gen, hist, best)`` when there is a ``checkpoint``, then ``progress(epoch, epochs, train_loss,
    val_loss)``."""
    import torch

    checkpoint = None if checkpoint is None else Path(checkpoint)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, fused=True)
    gen = torch.Generator().manual_seed(cfg.seed)
    hist = new_history()
    best = {k: v.detach().clone() for k, v in model.state_dict().items()}
    start = 0
    if resume and checkpoint is not None and checkpoint.exists():
        start, hist, best = load(checkpoint, opt, gen)
    params = list(model.parameters())
    for epoch in range(start, cfg.epochs):
        t0 = time.perf_counter()
        lr = cfg.lr_at(epoch)
        for group in opt.param_groups:
            group["lr"] = lr
        model.train()
        perm = torch.randperm(n, generator=gen)
        sums = torch.zeros(terms_shape, dtype=torch.float64)
        for i in range(0, n, cfg.batch):
            idx = perm[i:i + cfg.batch]
            loss, terms = batch_loss(idx)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip, foreach=True)
            opt.step()
            sums += terms.double() * idx.numel()
        train_loss, val_loss, more = finish(sums)
        if not (np.isfinite(train_loss) and np.isfinite(val_loss)):
            raise diverged(epoch + 1, train_loss)
        for k, v in (("train", train_loss), ("val", val_loss), *more, ("lr", lr),
                     ("seconds", round(time.perf_counter() - t0, 3))):
            hist[k].append(v)
        if hist["best_val"] is None or val_loss < hist["best_val"]:
            hist["best_val"], hist["best_epoch"] = val_loss, epoch + 1
            best = {k: v.detach().clone() for k, v in model.state_dict().items()}
        if checkpoint is not None:
            save(checkpoint, epoch + 1, opt, gen, hist, best)
        if progress is not None:
            progress(epoch + 1, cfg.epochs, train_loss, val_loss)
    model.load_state_dict(best)
    model.eval()
    return hist


def plot_loss_curves(history: Mapping[str, Mapping[str, Sequence[float]]], path: Path,
                     titles: Mapping[str, str] | None = None) -> Path:
    """Training and validation loss per epoch of each net in ``history`` (name → {"train", "val"}), one
    panel each, log scale; ``titles`` maps a net's name to its panel's title (default: the name)."""
    import matplotlib  # heavy: only the plot needs it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(history), figsize=(5 * len(history), 3.5), squeeze=False)
    for ax, (name, h) in zip(axes[0], history.items(), strict=True):
        ax.semilogy(np.arange(1, len(h["train"]) + 1), h["train"], label="train")
        ax.semilogy(np.arange(1, len(h["val"]) + 1), h["val"], label="validation")
        ax.set_title((titles or {}).get(name, name))
        ax.set_xlabel("epoch")
        ax.set_ylabel("MSE (standardised)")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
