"""Training and evaluation of the periodic autoencoder with Fourier latent dynamics (`felis.learning.phase.pae`)
on joint trajectories: windows and sequences from trajectories, Adam, a checkpoint every epoch that a
later run resumes bit-identically, the best-validation weights kept, and an N-step prediction benchmark.

Method: seed 003 (``003_1dde03cf3fe89d53.txt``), "PAE" §4 and "FLD"; summary in
``shared/reference/methods.md``, "Periodic autoencoder and Fourier latent dynamics".

Data. A trajectory is an array q (T, J) of joint angles (rad) at ``rate_hz``; the functions take plain
arrays, not a recording class. A training sample is a *sequence*: N+1 windows of W frames, window i
starting i·``fld_step`` frames after window 0 (`make_sequences`); sequences start every ``stride`` frames.
They are stored as segments of W + N·fld_step frames and cut into windows per batch.

Loss per batch (normalised units; L_i as in `felis.learning.phase.pae.fld_terms`, Δt = fld_step / rate)::

    L = L_0 + w_FLD · Σ_{i=0}^{N} α^i L_i

L_0 is the reconstruction MSE of window 0 (the PAE loss); the sum is the FLD loss, which holds L_0 as
its first term, as in the paper. Adam at ``lr · lr_decay^epoch``, gradients clipped to ``grad_clip``.

Determinism (as `felis.learning.ik.train`): weights from ``torch.manual_seed(seed)`` inside
``fork_rng``, batches from a seeded ``torch.Generator``, ``threads`` intra-op threads and deterministic
algorithms, restored afterwards. Same data, config and thread count → bit-identical weights; a run
resumed from its checkpoint ends with the same weights as an uninterrupted one.

Evaluation (`evaluate_phase`). Reconstruction MSE in rad² and the error of predicting the joint angles
1 … N frames after a window's last frame ("now"), by FLD read two ways (`felis.learning.phase.pae.predict_frames`):
the last frame of each predicted window (the paper's reading, ``fld``) and the centre frame of a window
propagated W/2 frames further (``fld_centre``; the decoder is most accurate away from the window's
zero-padded ends), and by two baselines: constant velocity, q̂(now + i) = q(now) + i (q(now) − q(now − 1));
and last-cycle repeat, q̂(now + i) = q(now − P + 1 + (i − 1) mod P) with the period P found in the window itself by
YIN's difference function (`cycle_period`; it needs no model, so the baseline does not borrow FLD's
frequency, and unlike the power-weighted FFT frequency it is not pulled up by harmonics).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any, TypedDict

import numpy as np

from felis.errors import ParameterError, PhaseError
from felis.learning.common.checkpoints import load_checkpoint, save_checkpoint
from felis.learning.common.curves import TorchSettings, fingerprint, run_epochs, stats
from felis.learning.common.torchstate import torch_to_arrays
from felis.learning.phase.infer import PaeConfig, check_arrays
from felis.learning.phase.pae import fld_terms, model_from_config, predict_frames

CHECKPOINT_ID = "felis-pae-checkpoint"
CHECKPOINT_SCHEMA = 1
HISTORY_LISTS = ("train", "val", "train_recon", "train_fld", "val_recon", "val_fld", "lr", "seconds")
EVAL_CHUNK = 256  # sequences per forward pass when evaluating
PREDICTORS = ("fld", "fld_centre", "const_vel", "last_cycle")

Progress = Callable[[int, int, float, float], None]


@dataclass(frozen=True)
class PhaseTrainConfig:
    """Training settings. Model: ``window`` W frames at ``rate_hz``, ``n_phases`` M, ``hidden``, ``kernel``
    (`felis.learning.phase.pae.PaeConfig`). Data: a sequence starts every ``stride`` frames; it holds
    ``fld_steps`` N + 1 windows ``fld_step`` frames apart (Δt = fld_step / rate_hz). Loss: FLD decay
    ``alpha`` α, weight ``fld_weight`` (0: the plain PAE). Optimiser: ``epochs`` passes in batches of
    ``batch`` sequences, Adam at ``lr`` times ``lr_decay`` per epoch, gradient norm clipped to
    ``grad_clip`` (0 = off). ``seed`` for weights and shuffling; ``threads`` torch intra-op threads (0:
    torch's default), part of the determinism contract."""

    window: int = 100
    n_phases: int = 5
    hidden: int = 32
    kernel: int = 25
    rate_hz: float = 100.0
    epochs: int = 60
    batch: int = 32
    lr: float = 1e-3
    lr_decay: float = 0.98
    grad_clip: float = 1.0
    stride: int = 5
    fld_steps: int = 10
    fld_step: int = 1
    alpha: float = 0.9
    fld_weight: float = 1.0
    seed: int = 0
    threads: int = 1

    def __post_init__(self):
        for f in ("window", "n_phases", "hidden", "kernel", "epochs", "batch", "stride", "fld_step"):
            v = getattr(self, f)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ParameterError(f"phase training {f} must be a positive integer, got {v!r}")
        for f in ("fld_steps", "threads", "seed"):
            v = getattr(self, f)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ParameterError(f"phase training {f} must be an integer ≥ 0, got {v!r}")
        for f, lo, hi, lo_open in (("lr", 0, math.inf, True), ("lr_decay", 0, 1, True),
                                   ("grad_clip", 0, math.inf, False), ("alpha", 0, 1, True),
                                   ("fld_weight", 0, math.inf, False), ("rate_hz", 0, math.inf, True)):
            v = getattr(self, f)
            ok = (not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
                  and (v > lo if lo_open else v >= lo) and v <= hi)
            if not ok:
                rng = f"{'(' if lo_open else '['}{lo}, {hi if hi < math.inf else '∞'}{']' if hi < math.inf else ')'}"
                raise ParameterError(f"phase training {f} must be in {rng}, got {v!r}")
        self.pae_config(1)  # the model part: window ≥ 4, odd kernel ≤ 2W − 1

    @property
    def dt(self) -> float:
        """Δt between consecutive windows of a sequence (s): fld_step / rate_hz."""
        return self.fld_step / self.rate_hz

    @property
    def span(self) -> int:
        """Frames of one sequence: W + N · fld_step."""
        return self.window + self.fld_steps * self.fld_step

    def lr_at(self, epoch: int) -> float:
        """Learning rate of 0-based ``epoch``: lr · lr_decay^epoch."""
        return self.lr * self.lr_decay ** epoch

    def pae_config(self, n_joints: int, joints: Sequence[str] | None = None) -> PaeConfig:
        return PaeConfig(n_joints, self.window, self.n_phases, self.hidden, self.kernel, self.rate_hz,
                         None if joints is None else tuple(joints))


class PhaseHistory(TypedDict):
    """Per epoch: total ``train`` / ``val`` loss and their reconstruction (L_0) and FLD parts (without
    validation data the val lists repeat the train ones), ``lr``, wall ``seconds``; ``best_epoch``
    (1-based, 0 before any) and ``best_val`` of the weights returned. Plain JSON."""

    train: list[float]
    val: list[float]
    train_recon: list[float]
    train_fld: list[float]
    val_recon: list[float]
    val_fld: list[float]
    lr: list[float]
    seconds: list[float]
    best_epoch: int
    best_val: float | None


def new_history() -> PhaseHistory:
    return {**{k: [] for k in HISTORY_LISTS}, "best_epoch": 0, "best_val": None}  # type: ignore[typeddict-item]


# ----------------------------------------------------------------------------------------------- data


def check_trajectories(trajs, min_frames: int, what: str = "training", need: str = "") -> list[np.ndarray]:
    """``trajs`` as float32 arrays (T, J) with one J, T ≥ ``min_frames``, all finite; a one-line PhaseError
    naming the trajectory (and the frame and joint of a NaN) otherwise. ``need`` explains min_frames."""
    if isinstance(trajs, np.ndarray) or not isinstance(trajs, Sequence) or len(trajs) == 0:
        raise PhaseError(f"{what} trajectories: expected a non-empty list of (T, J) arrays")
    out = []
    for i, q in enumerate(trajs):
        q = np.asarray(q, dtype=np.float32)
        if q.ndim != 2 or q.shape[1] == 0:
            raise PhaseError(f"{what} trajectory {i} has shape {q.shape}, not (frames, joints)")
        if out and q.shape[1] != out[0].shape[1]:
            raise PhaseError(f"{what} trajectory {i} has {q.shape[1]} joints, trajectory 0 has {out[0].shape[1]}")
        if q.shape[0] < min_frames:
            raise PhaseError(f"{what} trajectory {i} has {q.shape[0]} frames, fewer than the {min_frames}"
                             f"{need or ' of a window'}")
        bad = ~np.isfinite(q)
        if bad.any():
            t, j = np.argwhere(bad)[0]
            raise PhaseError(f"{what} trajectory {i} holds {q[t, j]} at frame {t}, joint {j}")
        out.append(q)
    return out


def make_windows(trajs, window: int, stride: int, what: str = "training") -> np.ndarray:
    """Windows (K, J, W) float32 of trajectories q (T, J), starting at frames 0, stride, 2·stride, … ≤ T − W
    of each (all trajectories at the same rate). Too short or non-finite: PhaseError (`check_trajectories`)."""
    if not (isinstance(window, int) and isinstance(stride, int) and window >= 1 and stride >= 1):
        raise ParameterError(f"window and stride must be positive integers, got {window!r}, {stride!r}")
    qs = check_trajectories(trajs, window, what)
    parts = [np.lib.stride_tricks.sliding_window_view(q, window, axis=0)[::stride] for q in qs]
    return np.ascontiguousarray(np.concatenate(parts))


def make_sequences(trajs, window: int, n_steps: int, stride: int, step: int = 1,
                   what: str = "training") -> np.ndarray:
    """FLD sequences (K, N+1, J, W): sequence k holds the windows starting at s_k + i·step, i = 0 … N,
    with s_k = 0, stride, … (a read-only view over (K, J, W + N·step) segments, no copy per window)."""
    return sequence_view(_segments(trajs, window, n_steps, stride, step, what), window, step)


def _segments(trajs, window: int, n_steps: int, stride: int, step: int, what: str) -> np.ndarray:
    span = window + n_steps * step
    qs = check_trajectories(trajs, span, what, f" of a sequence ({window}-frame window + {n_steps} steps × {step})")
    return make_windows(qs, span, stride, what)


def sequence_view(segments: np.ndarray, window: int, step: int) -> np.ndarray:
    """(K, J, L) segments → (K, N+1, J, W) windows ``step`` frames apart, N = (L − W) / step (a view)."""
    v = np.lib.stride_tricks.sliding_window_view(segments, window, axis=2)[:, :, ::step]
    return v.transpose(0, 2, 1, 3)


def _unfold(seg, window: int, step: int):
    """torch twin of `sequence_view`: (B, J, L) → (B, N+1, J, W)."""
    return seg.unfold(2, window, step).permute(0, 2, 1, 3)


# ------------------------------------------------------------------------------------------- training


def train_phase(train_trajs, val_trajs, cfg: PhaseTrainConfig, checkpoint: Path | None = None,
                progress: Progress | None = None, *, resume: bool = False, joints: Sequence[str] | None = None):
    """Train a PAE with FLD; returns (model with the best-validation weights, `PhaseHistory`).

    ``train_trajs``, ``val_trajs``: lists of (T, J) joint-angle arrays at ``cfg.rate_hz`` (``val_trajs``
    None: the training loss picks the best epoch). The per-joint normalisation comes from the training
    frames. ``checkpoint``: written after every epoch (atomically). ``resume``: continue from
    ``checkpoint`` if it exists — it must come from the same config (apart from ``epochs``, so a run can
    be extended), joints and data, else PhaseError. ``progress(epoch, epochs, train_loss, val_loss)``
    after each epoch; an exception it raises stops training after that epoch's checkpoint.
    """
    import torch

    need = f" of a sequence ({cfg.window}-frame window + {cfg.fld_steps} steps × {cfg.fld_step})"
    qs = check_trajectories(train_trajs, cfg.span, "training", need)
    n_joints = qs[0].shape[1]
    pcfg = cfg.pae_config(n_joints, joints)
    seg = make_windows(qs, cfg.span, cfg.stride, "training")
    has_val = val_trajs is not None
    if has_val:
        seg_val = _segments(val_trajs, cfg.window, cfg.fld_steps, cfg.stride, cfg.fld_step, "validation")
        if seg_val.shape[1] != n_joints:
            raise PhaseError(f"validation trajectories have {seg_val.shape[1]} joints, training ones {n_joints}")
    mean, std = stats(np.concatenate(qs), (0,))
    run_id = {"config": {k: v for k, v in asdict(cfg).items() if k != "epochs"}, "pae": pcfg.to_json(),
              "data": fingerprint(seg, *((seg_val,) if has_val else ()))}

    with TorchSettings(cfg.threads):
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            model = model_from_config(pcfg)
        model.set_stats(mean, std)
        segs = torch.from_numpy(seg)
        segv = torch.from_numpy(seg_val) if has_val else None
        weights = cfg.alpha ** torch.arange(cfg.fld_steps + 1, dtype=torch.float32)

        n = segs.shape[0]

        def batch_loss(idx):
            terms = fld_terms(model, _unfold(segs[idx], cfg.window, cfg.fld_step), cfg.dt)
            recon, fld = terms[0], (weights * terms).sum()
            return recon + cfg.fld_weight * fld, torch.stack((recon.detach(), fld.detach()))

        def finish(sums):
            tr_recon, tr_fld = (float(v) / n for v in sums)
            va_recon, va_fld = _losses(model, segv, cfg, weights) if has_val else (tr_recon, tr_fld)
            return (tr_recon + cfg.fld_weight * tr_fld, va_recon + cfg.fld_weight * va_fld,
                    (("train_recon", tr_recon), ("train_fld", tr_fld), ("val_recon", va_recon), ("val_fld", va_fld)))

        def diverged(epoch: int, train_loss: float) -> Exception:
            return PhaseError(f"phase training diverged at epoch {epoch} (loss {train_loss:.3g}); lower the "
                              f"lr (now {cfg.lr:g}) or grad_clip")

        hist = run_epochs(model, n, cfg, new_history, batch_loss, finish, diverged, progress, checkpoint, resume,
                          partial(_save_checkpoint, run_id, model), partial(_load_checkpoint, run_id, pcfg, model),
                          terms_shape=(2,))
    return model, hist


def _losses(model, segs, cfg: PhaseTrainConfig, weights) -> tuple[float, float]:
    """(L_0, Σ α^i L_i) over all sequences, in chunks, without gradients."""
    import torch

    model.eval()
    sums = torch.zeros(2, dtype=torch.float64)
    with torch.no_grad():
        for i in range(0, segs.shape[0], EVAL_CHUNK):
            chunk = segs[i:i + EVAL_CHUNK]
            terms = fld_terms(model, _unfold(chunk, cfg.window, cfg.fld_step), cfg.dt)
            sums += torch.stack((terms[0], (weights * terms).sum())).double() * chunk.shape[0]
    n = segs.shape[0]
    return float(sums[0]) / n, float(sums[1]) / n


# ----------------------------------------------------------------------------------------- checkpoint


def _save_checkpoint(run_id: dict, model, path: Path, epoch: int, opt, gen, hist: PhaseHistory, best: dict) -> None:
    save_checkpoint(path, (CHECKPOINT_ID, CHECKPOINT_SCHEMA), run_id, epoch, torch_to_arrays(model), opt, gen, hist,
                    HISTORY_LISTS, best, "PAE training checkpoint", PhaseError)


def _load_checkpoint(run_id: dict, pcfg: PaeConfig, model, path: Path, opt, gen):
    """Restore model, optimiser and generator from ``path`` (`felis.learning.common.checkpoints`); returns
    (next epoch, history, best state). PhaseError (one line) for a corrupt checkpoint or one from another run."""
    return load_checkpoint(path, (CHECKPOINT_ID, CHECKPOINT_SCHEMA), run_id,
                           (("config", "training config"), ("pae", "model config or joints"),
                            ("data", "training data")),
                           lambda arrays, where: check_arrays(pcfg, arrays, where), model, opt, gen, new_history,
                           HISTORY_LISTS, "PAE training checkpoint", PhaseError)


# ----------------------------------------------------------------------------------------- evaluation


def cycle_period(x: np.ndarray, min_lag: int = 2, threshold: float = 0.1) -> np.ndarray:
    """Period in frames of each window x (B, J, W), by YIN (de Cheveigné & Kawahara 2002) on all joints:
    the difference function d(τ) = Σ_j Σ_{t<W−τ} (x_j(t+τ) − x_j(t))² / (W − τ), zero at the period of an
    exactly periodic window, normalised as d′(τ) = d(τ) τ / Σ_{u=1}^{τ} d(u) (d′ ≈ 1 where nothing repeats).
    Among lags τ ∈ [min_lag, ⌊3W/4⌋]: the first τ with d′(τ) < ``threshold``, moved on to the bottom of
    its dip (so the fundamental wins over 2P, 3P, which fit as well); the smallest d′ if none is under
    it. A period longer than 3W/4 cannot be seen in one window."""
    B, J, W = x.shape
    x = x.astype(np.float64)
    spec = np.fft.rfft(x, n=2 * W, axis=-1)
    ac = np.fft.irfft((spec.real ** 2 + spec.imag ** 2).sum(axis=1), n=2 * W, axis=-1)[:, :W]   # Σ x(t) x(t+τ)
    cs = np.concatenate((np.zeros((B, 1)), np.cumsum((x ** 2).sum(axis=1), axis=-1)), axis=-1)   # (B, W+1)
    tau = np.arange(W)
    d = (cs[:, W - tau] + cs[:, W:] - cs[:, tau] - 2 * ac) / (W - tau)
    d[:, 0] = 0.0
    cum = np.cumsum(d, axis=-1)
    dn = np.where(cum > 0, d * tau / np.maximum(cum, 1e-300), 1.0)
    dn[:, 0] = 1.0
    hi = min(max(3 * W // 4, min_lag + 1), W - 1)
    lags = np.arange(min_lag, hi + 1)
    cand = dn[:, lags]
    under = cand < threshold
    first = np.where(under.any(axis=1), under.argmax(axis=1), cand.argmin(axis=1))
    out = lags[first]
    for b in np.flatnonzero(under.any(axis=1)):                    # walk to the bottom of the dip
        t = out[b]
        while t < hi and dn[b, t + 1] < dn[b, t]:
            t += 1
        out[b] = t
    return out


def evaluate_phase(model, trajs, n_steps: int, stride: int = 5) -> dict[str, Any]:
    """Reconstruction and N-step prediction errors of ``model`` on trajectories q (T, J) (rad).

    Windows of W frames start every ``stride`` frames; "now" is a window's last frame, and the targets
    are the N frames after it (so each trajectory needs W + N frames). Returns plain JSON:
    ``windows``; ``recon_mse`` (rad², decoded vs raw windows); ``horizon_s`` (i / rate, i = 1 … N);
    ``pred_mse`` {``fld``, ``fld_centre``, ``const_vel``, ``last_cycle``} (module docstring) → a list over
    i of the MSE (rad², mean over windows and joints); ``pred_mse_mean`` and ``pred_mse_final`` (at
    i = N) per predictor; and ``period_frames_median`` of the last-cycle baseline.
    """
    import torch

    cfg = model.config
    if not isinstance(n_steps, int) or isinstance(n_steps, bool) or n_steps < 1:
        raise ParameterError(f"n_steps must be a positive integer, got {n_steps!r}")
    seg = _segments(trajs, cfg.window, n_steps, stride, 1, "evaluation")
    if seg.shape[1] != cfg.n_joints:
        raise PhaseError(f"evaluation trajectories have {seg.shape[1]} joints, the PAE takes {cfg.n_joints}")
    W, N, K = cfg.window, n_steps, seg.shape[0]
    steps = np.arange(1, N + 1)
    sq = {k: np.zeros(N) for k in PREDICTORS}
    recon, periods = 0.0, []
    model.eval()
    with torch.no_grad():
        for i in range(0, K, EVAL_CHUNK):
            chunk = seg[i:i + EVAL_CHUNK]
            x, truth = chunk[..., :W], chunk[..., W:].transpose(0, 2, 1)            # (b, J, W), (b, N, J)
            xt = torch.from_numpy(np.ascontiguousarray(x))
            y, _ = model(xt)
            recon += float((y.double() - xt.double()).square().sum())
            fld = predict_frames(model, xt, N, 1.0 / cfg.rate_hz).double().numpy()
            fld_c = predict_frames(model, xt, N, 1.0 / cfg.rate_hz, frame=W // 2).double().numpy()
            now, vel = x[:, None, :, -1], (x[:, :, -1] - x[:, :, -2])[:, None, :]
            cv = now + steps[None, :, None] * vel
            P = cycle_period(x)
            periods.append(P)
            idx = W - P[:, None] + (steps[None, :] - 1) % P[:, None]                # (b, N) frame indices in x
            lc = np.take_along_axis(x, idx[:, None, :], axis=2).transpose(0, 2, 1)
            for name, pred in zip(PREDICTORS, (fld, fld_c, cv, lc), strict=True):
                sq[name] += ((pred - truth) ** 2).sum(axis=(0, 2))
    mse = {k: (v / (K * cfg.n_joints)).tolist() for k, v in sq.items()}
    return {"windows": K, "recon_mse": recon / (K * cfg.n_joints * W),
            "horizon_s": (steps / cfg.rate_hz).tolist(), "pred_mse": mse,
            "pred_mse_mean": {k: float(np.mean(v)) for k, v in mse.items()},
            "pred_mse_final": {k: v[-1] for k, v in mse.items()},
            "period_frames_median": float(np.median(np.concatenate(periods)))}
