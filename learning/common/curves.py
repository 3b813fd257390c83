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


def run_epochs(model, opt, gen, n: int, cfg: Any, start: int, hist: dict, best: dict,
               batch_loss: Callable[[Any], tuple[Any, Any]], finish: Callable[[Any], tuple[float, float, Sequence]],
               diverged: Callable[[int, float], Exception], save: Callable[[int, dict, dict], None] | None,
               progress: Callable[[int, int, float, float], None] | None, terms_shape: tuple[int, ...] = ()) -> dict:
    """Epochs ``start`` … ``cfg.epochs − 1`` of ``model`` on ``n`` training rows (module doc); returns the
    best state (the caller loads it).

    ``batch_loss(idx)`` → (loss to minimise, the detached terms to sum, of shape ``terms_shape``) for the
    rows ``idx``; the sums, weighted by batch size, go to ``finish(sums)`` → (training loss, validation
    loss, further (history key, value) pairs). A non-finite loss raises ``diverged(epoch, train_loss)``.
    ``hist`` gets ``train``, ``val``, the further pairs, ``lr`` and ``seconds`` appended, ``best_val`` and
    ``best_epoch`` updated. ``save(epoch, hist, best)`` (the checkpoint) and then ``progress(epoch,
    epochs, train_loss, val_loss)`` after every epoch (1-based)."""
    import torch

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
        if save is not None:
            save(epoch + 1, hist, best)
        if progress is not None:
            progress(epoch + 1, cfg.epochs, train_loss, val_loss)
    return best


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
