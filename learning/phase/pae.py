"""The periodic autoencoder (PAE) and Fourier latent dynamics (FLD): a gait window → per-channel phase,
frequency, amplitude and offset; the same parameters rolled forward in time to predict the next windows.

Method: seed 003 (``003_1dde03cf3fe89d53.txt``), "PAE" §2–3 and "FLD"; summary in
``shared/reference/methods.md``, "Periodic autoencoder and Fourier latent dynamics".

Input. A window x ∈ R^{J×W}: J joint angles (rad) over W frames at ``rate_hz``. The net sees
x̂_j = (x_j − μ_j) / σ_j with per-joint statistics of the training data (buffers ``mean``, ``std``).
The paper's windows are de-meaned per window and not scaled; here the mean pose is information the
offset b should carry, and joints of very different ranges are put on one scale.

Encoder. z = Conv1d(H→M, K)(ELU(Conv1d(J→H, K)(x̂))) ∈ R^{M×W}, "same" padding (K odd) that repeats the
edge frames: a still window (a standing robot) then gives a constant latent and amplitude A = 0, where zero
padding would make the window's ends look like motion (0.12 of the stepping amplitude when standing). The paper
follows each convolution with batch normalisation; there is none here, so training and inference
compute the same function and `PaeNumpy` is exact (the input standardisation does that job). The
paper's kernel spans the whole window; the default K = 25 (0.25 s at 100 Hz, half a 2 Hz stride) costs
a quarter of that (`PaeNumpy` ≈ 130 µs per window against ≈ 450 µs for K = 101, J = 12, W = 100).

FFT parameterisation (`fft_params`), per latent channel z ∈ R^W, c = rfft(z), c_k = Σ_n z_n e^{−2πikn/W}::

    p_k = |c_k|²,  k = 1 … ⌊W/2⌋          (power; the DC bin k = 0 is left out)
    f_k = k · rate / W                    (Hz; grid step rate / W)
    f   = Σ_k p_k f_k / (Σ_k p_k + ε)     (power-weighted mean frequency)
    A   = 2 √(Σ_k p_k + ε) / W
    b   = Re c_0 / W                      (the window mean)

By Parseval, Σ_{n}(z_n − z̄)² = (2 Σ_{k<W/2} p_k + p_{W/2}) / W, so A = √2 · rms(z − z̄) when W is odd or
the Nyquist bin k = W/2 is empty (that bin would count twice). A pure on-grid sinusoid a·sin(2πk₀n/W + θ)
with 0 < k₀ < W/2 has |c_{k₀}| = aW/2 and nothing else, so A = a, f = k₀·rate/W, b its mean: exact. A sum
of such sinusoids gives A = √(Σ a_i²). Off the grid the window cuts the wave with a jump between its
ends, whose leakage decays only as 1/k²; f is then biased upward: at W = 100 by at most 1.21 grid
steps (worst phase, 2.6 cycles per window), ≤ 1 step from 4 cycles up, far less when the ends meet.
ε = 1e-12 keeps a flat channel (Σp = 0) finite: f = 0, A ≈ 2·10⁻⁶/W.

Phase. Per channel m a linear layer over the window, (s_x, s_y) = z_m · V_m + β_m with V ∈ R^{M×W×2}
(one layer per channel, batched), φ = atan2(s_y, s_x) / 2π wrapped to [0, 1).

Rebuild (`latent_wave`). ẑ_m(t_k) = A_m sin(2π(f_m t_k + φ_m)) + b_m on the centred time axis
t_k = (k − (W−1)/2) / rate, k = 0 … W−1: φ is the phase at the window's centre. With the on-grid wave
z = a sin(2π(f₀t + φ₀)) + b and V_x(t_k) = (2/W) sin 2πf₀t_k, V_y(t_k) = (2/W) cos 2πf₀t_k, β = 0, the
layer gives (s_x, s_y) = a (cos 2πφ₀, sin 2πφ₀), so φ = φ₀ and ẑ = z exactly (the tests use this).

Decoder. ŷ = Conv1d(H→J, K)(ELU(Conv1d(M→H, K)(ẑ))), normalised units; `decode` returns
y = ŷ σ + μ in radians. The reconstruction loss is the MSE on normalised windows, mean (ŷ − x̂)².

Phase manifold (`manifold`). P = (A_1 sin 2πφ_1, A_1 cos 2πφ_1, …, A_M sin 2πφ_M, A_M cos 2πφ_M) ∈ R^{2M}.

FLD (`propagate`, `fld_terms`, `fld_loss`, `predict`, `predict_frames`). f, A, b are held constant over the horizon and
the phase advances: φ_i = φ_0 + i f Δt. A sequence is N+1 windows S_0 … S_N of one trajectory, S_i
starting ``step`` frames after S_{i−1}, so Δt = step / rate (1/rate for consecutive frames). Only S_0 is
encoded; L_i = MSE(dec(φ_0 + i f Δt, f, A, b), S_i) (normalised units) and L_FLD = Σ_{i=0}^{N} α^i L_i.

"Now" is the last frame of the input window (frame W−1). Predicted window i covers the W frames
ending at now + i·step, so its last frame is the prediction of the joint angles i·step frames ahead;
the N-step trajectory prediction is the last frame of each predicted window (`predict(...)[..., -1]`,
`predict_frames` with ``frame=-1``), as in the paper. The decoder's last frames are its weakest (its
convolutions see only the repeated edge frame beyond it), so `predict_frames` can also read an inner frame c of a window
propagated (W−1−c)/rate further, which predicts the same instant while holding f, A, b constant
longer; `felis.learning.phase.train.evaluate_phase` reports both. Which wins depends on the data: on a
tiny net (H = 8) the centre read was 7× better; on the default net trained on a gait with a drifting
frequency the last frame was 1.7× better (FLD's loss trains the edge frames too).

`PaeConfig`, the numpy encoder `PaeNumpy` and reading the weights are `felis.learning.phase.infer` (no
torch import; controllers load it cheaply). The weights file is one ``.npz`` (no pickle): the state-dict
arrays (float32) and a JSON ``__meta__``.
"""


from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from felis.errors import PhaseError
from felis.learning.common.torchstate import lazy_attribute, model_with_arrays, torch_to_arrays
from felis.learning.common.weights import weights_target, write_weights
from felis.learning.phase.infer import (
    EPS,
    MODEL_ID,
    SCHEMA,
    TWO_PI,
    PaeConfig,
    check_arrays,
    read_pae,
    window_time,
)

if TYPE_CHECKING:  # torch is imported lazily: inference with PaeNumpy must not pay for it
    import torch

RESERVED_META = ("model", "schema", "config")


# --------------------------------------------------------------------------------------------- torch


def fft_params(z: torch.Tensor, rate_hz: float, eps: float = EPS):
    """(freq Hz, amp, offset), each (…, M), of latent curves z (…, M, W); formulas in the module docstring."""
    import torch

    W = z.shape[-1]
    c = torch.fft.rfft(z, dim=-1)
    p = c[..., 1:].real.square() + c[..., 1:].imag.square()
    fk = torch.arange(1, W // 2 + 1, dtype=z.dtype, device=z.device) * (rate_hz / W)
    total = p.sum(-1)
    freq = (p * fk).sum(-1) / (total + eps)
    amp = 2.0 * torch.sqrt(total + eps) / W
    offset = c[..., 0].real / W
    return freq, amp, offset


def latent_wave(phase, freq, amp, offset, t):
    """ẑ(t) = A sin(2π(f t + φ)) + b: parameters (…, M), time axis t (W,) → (…, M, W)."""
    return amp[..., None] * (TWO_PI * (freq[..., None] * t + phase[..., None])).sin() + offset[..., None]


def manifold(phase, amp):
    """The phase manifold P (…, 2M): (A_m sin 2πφ_m, A_m cos 2πφ_m) per channel, interleaved.
    numpy arrays in, numpy out (for `PaeNumpy` results); torch tensors in, tensors out."""
    if isinstance(phase, np.ndarray):
        a = TWO_PI * phase
        return np.stack((amp * np.sin(a), amp * np.cos(a)), axis=-1).reshape(*phase.shape[:-1], -1)
    import torch

    a = TWO_PI * phase
    return torch.stack((amp * a.sin(), amp * a.cos()), dim=-1).flatten(-2)


def propagate(params: Mapping[str, torch.Tensor], i, dt: float) -> dict[str, torch.Tensor]:
    """FLD step: φ ← (φ + i f Δt) mod 1; f, A, b unchanged. ``i`` a number (shapes stay (B, M)) or a 1-D
    tensor of N step counts (every output then (B, N, M))."""
    import torch

    phase, freq, amp, offset = (params[k] for k in ("phase", "freq", "amp", "offset"))
    i = torch.as_tensor(i, dtype=phase.dtype)
    if i.ndim == 1:
        phase, freq, amp, offset = (v[:, None, :] for v in (phase, freq, amp, offset))
        i = i[None, :, None]
        shape = (phase.shape[0], i.shape[1], phase.shape[2])
        freq, amp, offset = (v.expand(shape) for v in (freq, amp, offset))
    return {"phase": torch.remainder(phase + i * freq * dt, 1.0), "freq": freq, "amp": amp, "offset": offset}


@functools.cache
def _pae_class():
    """The torch ``PAE`` class (see its docstring); defined on first use to keep torch lazy."""
    import torch
    from torch import nn
    from torch.nn import functional as F

    class PAE(nn.Module):
        """The periodic autoencoder (module docstring); arguments as in `PaeConfig`, held in ``config``.

        ``encode(x)``: raw windows (B, J, W) in rad → dict of ``phase``, ``freq``, ``amp``, ``offset``
        (each (B, M)) and the latent ``z`` (B, M, W). ``decode(phase, freq, amp, offset)`` → (B, J, W)
        in rad (``decode_normalised``: in normalised units). ``forward(x)`` → (decode(encode(x)), params).
        """

        def __init__(self, n_joints: int, window: int, n_phases: int = 5, hidden: int = 32, kernel: int = 25,
                     rate_hz: float = 100.0, joints: Sequence[str] | None = None):
            super().__init__()
            cfg = PaeConfig(n_joints, window, n_phases, hidden, kernel, rate_hz,
                            None if joints is None else tuple(joints))
            self.config = cfg
            J, W, M, H, K = cfg.n_joints, cfg.window, cfg.n_phases, cfg.hidden, cfg.kernel
            self.enc1 = nn.Conv1d(J, H, K, padding=K // 2, padding_mode="replicate")
            self.enc2 = nn.Conv1d(H, M, K, padding=K // 2, padding_mode="replicate")
            bound = 1.0 / math.sqrt(W)                     # nn.Linear's default init, per channel
            self.phase_weight = nn.Parameter(torch.empty(M, W, 2).uniform_(-bound, bound))
            self.phase_bias = nn.Parameter(torch.empty(M, 2).uniform_(-bound, bound))
            self.dec1 = nn.Conv1d(M, H, K, padding=K // 2, padding_mode="replicate")
            self.dec2 = nn.Conv1d(H, J, K, padding=K // 2, padding_mode="replicate")
            self.register_buffer("mean", torch.zeros(J))
            self.register_buffer("std", torch.ones(J))
            self.register_buffer("t", torch.as_tensor(window_time(W, cfg.rate_hz), dtype=torch.float32),
                                 persistent=False)

        def set_stats(self, mean, std) -> None:
            """Copy the per-joint normalisation statistics in (array-likes of shape (J,))."""
            self.mean.copy_(torch.as_tensor(np.asarray(mean), dtype=self.mean.dtype))
            self.std.copy_(torch.as_tensor(np.asarray(std), dtype=self.std.dtype))

        def normalise(self, x: torch.Tensor) -> torch.Tensor:
            return (x - self.mean[:, None]) / self.std[:, None]

        def denormalise(self, xn: torch.Tensor) -> torch.Tensor:
            return xn * self.std[:, None] + self.mean[:, None]

        def latent(self, x: torch.Tensor) -> torch.Tensor:
            """Raw windows (B, J, W) → latent curves z (B, M, W)."""
            return self.enc2(F.elu(self.enc1(self.normalise(x))))

        def phase_of(self, z: torch.Tensor) -> torch.Tensor:
            """The phase layer: latent (B, M, W) → φ (B, M) in [0, 1)."""
            s = torch.einsum("bmw,mwk->bmk", z, self.phase_weight) + self.phase_bias
            return torch.remainder(torch.atan2(s[..., 1], s[..., 0]) / TWO_PI, 1.0)

        def encode(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
            z = self.latent(x)
            freq, amp, offset = fft_params(z, self.config.rate_hz)
            return {"phase": self.phase_of(z), "freq": freq, "amp": amp, "offset": offset, "z": z}

        def decode_normalised(self, phase, freq, amp, offset) -> torch.Tensor:
            zhat = latent_wave(phase, freq, amp, offset, self.t.to(phase.dtype))
            return self.dec2(F.elu(self.dec1(zhat)))

        def decode(self, phase, freq, amp, offset) -> torch.Tensor:
            return self.denormalise(self.decode_normalised(phase, freq, amp, offset))

        def forward(self, x: torch.Tensor):
            params = self.encode(x)
            return self.decode(params["phase"], params["freq"], params["amp"], params["offset"]), params

    return PAE


# ``PAE`` is built on first access, so importing this module does not import torch.
__getattr__ = lazy_attribute(__name__, "PAE", _pae_class)


def model_from_config(cfg: PaeConfig):
    """A freshly initialised `PAE` for ``cfg`` (draws from torch's global RNG, like any nn.Module)."""
    return _pae_class()(cfg.n_joints, cfg.window, cfg.n_phases, cfg.hidden, cfg.kernel, cfg.rate_hz, cfg.joints)


def recon_loss(model, x: torch.Tensor) -> torch.Tensor:
    """Reconstruction loss: MSE between decoded and input windows (B, J, W), in normalised units."""
    import torch

    p = model.encode(x)
    y = model.decode_normalised(p["phase"], p["freq"], p["amp"], p["offset"])
    return torch.nn.functional.mse_loss(y, model.normalise(x))


def fld_terms(model, seq: torch.Tensor, dt: float) -> torch.Tensor:
    """L_i for i = 0 … N (a (N+1,) tensor): seq (B, N+1, J, W) raw windows, window i ``i·Δt`` after
    window 0; window 0 is encoded, propagated i steps and decoded, compared in normalised units."""
    import torch

    B, n1, J, W = seq.shape
    p = propagate(model.encode(seq[:, 0]), torch.arange(n1), dt)              # each (B, N+1, M)
    flat = [p[k].reshape(B * n1, -1) for k in ("phase", "freq", "amp", "offset")]
    y = model.decode_normalised(*flat).reshape(B, n1, J, W)
    target = (seq - model.mean[:, None]) / model.std[:, None]
    return (y - target).square().mean(dim=(0, 2, 3))


def fld_loss(model, seq: torch.Tensor, alpha: float, dt: float) -> torch.Tensor:
    """L_FLD = Σ_{i=0}^{N} α^i L_i (`fld_terms`); not divided by Σ α^i, as in the paper."""
    import torch

    terms = fld_terms(model, seq, dt)
    return (alpha ** torch.arange(terms.shape[0], dtype=terms.dtype) * terms).sum()


def predict(model, x: torch.Tensor, n: int, dt: float) -> torch.Tensor:
    """The n windows after x (B, J, W) by FLD, (B, n, J, W) in rad; window i (1-based) is x shifted
    i·Δt later, so ``predict(...)[:, i − 1, :, -1]`` is the joint angles i·Δt after x's last frame."""
    import torch

    B, J, W = x.shape
    p = propagate(model.encode(x), torch.arange(1, n + 1), dt)
    flat = [p[k].reshape(B * n, -1) for k in ("phase", "freq", "amp", "offset")]
    return model.decode(*flat).reshape(B, n, J, W)


def predict_frames(model, x: torch.Tensor, n: int, dt: float, frame: int = -1) -> torch.Tensor:
    """The joint angles i·Δt after x's last frame, i = 1 … n, by FLD: (B, n, J) in rad.

    ``frame`` -1 (the paper's reading): the last frame of predicted window i, i.e. ``predict(...)[..., -1]``.
    Another frame c (0 … W−1, or negative from the end): window 0 is propagated by i·Δt plus the
    (W−1−c)/rate that frame c lags the last one, and frame c is read. The decoder's convolutions see
    repeated edge frames near the window's ends, so an inner frame (c ≈ W/2) is decoded better; the latent waves are
    held constant over (W−1−c)/rate longer.
    """
    import torch

    B, J, W = x.shape
    c = frame % W
    i = torch.arange(1, n + 1, dtype=torch.float64) + (W - 1 - c) / (model.config.rate_hz * dt)
    p = propagate(model.encode(x), i, dt)
    flat = [p[k].reshape(B * n, -1) for k in ("phase", "freq", "amp", "offset")]
    return model.decode(*flat).reshape(B, n, J, W)[..., c]


def arrays_to_torch(cfg: PaeConfig, arrays: Mapping[str, np.ndarray], where: str = "PAE"):
    """A `PAE` for ``cfg`` holding ``arrays`` (in eval mode); PhaseError (one line) if they do not fit."""
    check_arrays(cfg, arrays, where)
    return model_with_arrays(lambda: model_from_config(cfg), cfg.shapes(), arrays).eval()


# --------------------------------------------------------------------------------------- weights file


def save_pae(path: str | Path, model, meta: Mapping[str, Any] | None = None) -> Path:
    """Write ``model`` to one ``.npz`` atomically: its state-dict arrays (float32) and ``__meta__``::

        {"model": "felis-pae", "schema": 1, "config": {n_joints, window, n_phases, hidden, kernel,
         rate_hz, joints}, "params": P, ...meta}

    ``meta`` (JSON-serialisable: e.g. the training config, history, data description) may not use the
    keys "model", "schema", "config". The arrays are checked first, so a bad model is never written.
    """
    path, meta = weights_target(path, meta, RESERVED_META, "PAE weights", "PAE", PhaseError)
    cfg: PaeConfig = model.config
    arrays = torch_to_arrays(model)
    check_arrays(cfg, arrays, f"{path}: model")
    doc = {"model": MODEL_ID, "schema": SCHEMA, "config": cfg.to_json(), "params": cfg.param_count, **meta}
    return write_weights(path, arrays, doc, "PAE", "PAE weights", PhaseError)


def load_pae(path: str | Path, expect_joints: int | Sequence[str] | None = None):
    """(torch `PAE` in eval mode, metadata) from a file written by `save_pae`; checks as `read_pae`."""
    cfg, arrays, doc = read_pae(path, expect_joints)
    return arrays_to_torch(cfg, arrays, str(path)), doc
