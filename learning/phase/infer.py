"""Numpy inference of the periodic autoencoder (PAE, seed 003): its shape (`PaeConfig`), the encoder
(`PaeNumpy`: a gait window → per-channel phase, frequency, amplitude, offset) and reading the weights
file (`read_pae`, `load_pae_numpy`). No torch: the phase estimator (`felis.learning.phase.estimator`)
and so the controllers load the shipped weights cheaply. The method, the torch model, FLD and saving
are `felis.learning.phase.pae`; its module doc gives the formulas `PaeNumpy` computes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import ParameterError, PhaseError
from felis.files import META_KEY, check_float_arrays, dataclass_from_json, read_meta, read_npz

MODEL_ID = "felis-pae"
SCHEMA = 1
EPS = 1e-12
TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class PaeConfig:
    """The shape of a PAE: ``n_joints`` J inputs, ``window`` W frames at ``rate_hz``, ``n_phases`` M latent
    channels, ``hidden`` H convolution channels, ``kernel`` K (odd, ≤ 2W−1) frames per convolution;
    ``joints`` the joint names in input order (optional, stored in the weights file)."""

    n_joints: int
    window: int
    n_phases: int = 5
    hidden: int = 32
    kernel: int = 25
    rate_hz: float = 100.0
    joints: tuple[str, ...] | None = None

    def __post_init__(self):
        for f in ("n_joints", "window", "n_phases", "hidden", "kernel"):
            v = getattr(self, f)
            if not isinstance(v, int | np.integer) or isinstance(v, bool) or v < 1:
                raise ParameterError(f"PAE {f} must be a positive integer, got {v!r}")
            object.__setattr__(self, f, int(v))
        if self.window < 4:
            raise ParameterError(f"PAE window must be at least 4 frames, got {self.window}")
        if self.kernel % 2 == 0 or self.kernel > 2 * self.window - 1:
            raise ParameterError(f"PAE kernel must be odd and at most 2·window − 1 = {2 * self.window - 1}, "
                                 f"got {self.kernel}")
        r = self.rate_hz
        if isinstance(r, bool) or not isinstance(r, int | float) or not (math.isfinite(r) and r > 0):
            raise ParameterError(f"PAE rate_hz must be a positive number, got {r!r}")
        object.__setattr__(self, "rate_hz", float(r))
        if self.joints is not None:
            names = tuple(self.joints)
            if len(names) != self.n_joints or not all(isinstance(n, str) and n for n in names):
                raise ParameterError(f"PAE joints must be {self.n_joints} non-empty names, got {list(names)!r}")
            object.__setattr__(self, "joints", names)

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """State-dict key → shape of every array of the model (normalisation buffers included)."""
        J, W, M, H, K = self.n_joints, self.window, self.n_phases, self.hidden, self.kernel
        return {"mean": (J,), "std": (J,),
                "enc1.weight": (H, J, K), "enc1.bias": (H,), "enc2.weight": (M, H, K), "enc2.bias": (M,),
                "phase_weight": (M, W, 2), "phase_bias": (M, 2),
                "dec1.weight": (H, M, K), "dec1.bias": (H,), "dec2.weight": (J, H, K), "dec2.bias": (J,)}

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["joints"] = None if self.joints is None else list(self.joints)
        return d

    @classmethod
    def from_json(cls, d: Any) -> PaeConfig:
        """Inverse of `to_json`; ParameterError for a non-object, unknown or missing keys, bad values."""
        if not isinstance(d, Mapping):
            raise ParameterError(f"PAE config must be an object, got {type(d).__name__}")
        return dataclass_from_json(cls, d, "PAE config", ParameterError)

    @property
    def param_count(self) -> int:
        """Trainable parameters (not the normalisation statistics)."""
        return sum(math.prod(s) for k, s in self.shapes().items() if k not in ("mean", "std"))


def window_time(window: int, rate_hz: float) -> np.ndarray:
    """The centred time axis t_k = (k − (W−1)/2) / rate (s), k = 0 … W−1 (float64)."""
    return (np.arange(window) - (window - 1) / 2) / rate_hz


def check_arrays(cfg: PaeConfig, arrays: Mapping[str, np.ndarray], where: str) -> None:
    """PhaseError (one line starting with ``where``) unless ``arrays`` holds exactly the arrays of ``cfg``
    with the right shapes, a float dtype, finite values and positive standard deviations."""
    shapes = cfg.shapes()
    extra = sorted(set(arrays) - set(shapes))
    if extra:
        raise PhaseError(f"{where}: unexpected array {extra[0]!r}; not a PAE of this config")
    check_float_arrays(arrays, shapes, f"{where}:", PhaseError, "the config needs")
    if not np.all(np.asarray(arrays["std"]) > 0):
        raise PhaseError(f"{where}: array 'std' holds a non-positive standard deviation")


# --------------------------------------------------------------------------------------------- numpy


class PaeNumpy:
    """The PAE encoder in numpy, equal to the torch model within float rounding (≤ 1e-5; the phase
    compared on the circle, where 0.999999 and 0.000001 are neighbours).

    ``encode(window)``: one window (J, W) in rad → dict of ``phase``, ``freq``, ``amp``, ``offset``, each
    (M,) float64. The convolutions compute in ``dtype`` (float32 default, as the weights), the FFT
    stage in float64 (M·W values; its power sums are where float32 loses most). Each convolution is one matrix
    product over an im2col matrix: the padded input, time-major (W+K−1, C), viewed as (W, K, C) with
    strides (row, row, item) and flattened to (W, K·C); the torch weight (O, C, K) becomes (K·C, O).
    """

    def __init__(self, cfg: PaeConfig, arrays: Mapping[str, np.ndarray], dtype=np.float32):
        if np.dtype(dtype) not in (np.float32, np.float64):
            raise ParameterError(f"PaeNumpy computes in float32 or float64, not {np.dtype(dtype)}")
        check_arrays(cfg, arrays, "PAE")
        self.config, self.dtype = cfg, np.dtype(dtype)
        a = {k: np.asarray(v, dtype=self.dtype) for k, v in arrays.items()}
        W, K = cfg.window, cfg.kernel
        self._mean, self._inv_std = a["mean"], (1.0 / a["std"]).astype(self.dtype)
        self._w1 = np.ascontiguousarray(a["enc1.weight"].transpose(2, 1, 0).reshape(-1, cfg.hidden))
        self._b1 = a["enc1.bias"]
        self._w2 = np.ascontiguousarray(a["enc2.weight"].transpose(2, 1, 0).reshape(-1, cfg.n_phases))
        self._b2 = a["enc2.bias"]
        self._wp, self._bp = np.ascontiguousarray(a["phase_weight"]), a["phase_bias"]
        self._fk = np.arange(1, W // 2 + 1) * (cfg.rate_hz / W)
        self._pad = K // 2

    def _conv(self, x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
        """'Same' Conv1d of time-major x (W, C) → (W, O)."""
        W, C = x.shape
        K = self.config.kernel
        buf = np.zeros((W + K - 1, C), dtype=self.dtype)
        buf[self._pad:self._pad + W] = x
        buf[:self._pad] = x[0]  # replicate padding, as the torch model's
        buf[self._pad + W:] = x[-1]
        s0, s1 = buf.strides
        cols = np.lib.stride_tricks.as_strided(buf, (W, K, C), (s0, s0, s1)).reshape(W, K * C)
        y = cols @ w
        y += b
        return y

    def encode(self, window) -> dict[str, np.ndarray]:
        cfg = self.config
        x = np.asarray(window, dtype=self.dtype)
        if x.shape != (cfg.n_joints, cfg.window):
            raise PhaseError(f"PAE window has shape {x.shape}, the model takes ({cfg.n_joints}, {cfg.window}) "
                             "(joints × frames)")
        if not np.isfinite(x).all():
            j, k = np.argwhere(~np.isfinite(x))[0]
            raise PhaseError(f"PAE window holds a non-finite value ({x[j, k]}) at joint {j}, frame {k}")
        h = self._conv((x.T - self._mean) * self._inv_std, self._w1, self._b1)
        neg = np.minimum(h, 0)
        np.expm1(neg, out=neg)
        np.maximum(h, 0, out=h)
        h += neg                                            # ELU
        z = self._conv(h, self._w2, self._b2)               # (W, M)
        c = np.fft.rfft(z.astype(np.float64), axis=0)       # the power sums lose most in float32
        p = c[1:].real ** 2 + c[1:].imag ** 2
        total = p.sum(axis=0)
        freq = (self._fk @ p) / (total + EPS)
        amp = 2.0 * np.sqrt(total + EPS) / cfg.window
        offset = c[0].real / cfg.window
        s = np.matmul(z.T[:, None, :], self._wp)[:, 0] + self._bp        # (M, 2)
        phase = np.mod(np.arctan2(s[:, 1], s[:, 0], dtype=np.float64) / TWO_PI, 1.0)
        return {"phase": phase, "freq": freq, "amp": amp, "offset": offset}


# --------------------------------------------------------------------------------------- weights file


def read_pae(path: str | Path, expect_joints: int | Sequence[str] | None = None
             ) -> tuple[PaeConfig, dict[str, np.ndarray], dict[str, Any]]:
    """(config, float32 arrays, metadata) of a file written by `save_pae`. ``expect_joints``: a joint
    count, or the joint names in order (the file must then store the same names). Every problem is a
    one-line PhaseError naming the file: missing, not an npz, corrupt, no or bad metadata, another
    model or schema, a bad config, a missing or misshapen array, non-finite values, other joints."""
    path = Path(path)
    data = read_npz(path, "PAE weights", PhaseError)
    doc = read_meta(data, path, PhaseError, "PAE weights file", detail=str, not_text="is not a JSON object",
                    ident=("model", MODEL_ID, "model id {got!r} is not {want!r}; not a PAE weights file"),
                    version=("schema", SCHEMA, "PAE schema {got!r} is not supported (felis reads {want})"))
    del data[META_KEY]
    try:
        cfg = PaeConfig.from_json(doc.get("config"))
    except ParameterError as e:
        raise PhaseError(f"{path}: bad config: {e}") from None
    if expect_joints is not None:
        _check_joints(path, cfg, expect_joints)
    check_arrays(cfg, data, str(path))
    return cfg, {k: data[k].astype(np.float32) for k in cfg.shapes()}, doc


def _check_joints(path: Path, cfg: PaeConfig, expect: int | Sequence[str]) -> None:
    if isinstance(expect, int | np.integer):
        if cfg.n_joints != expect:
            raise PhaseError(f"{path}: PAE takes {cfg.n_joints} joints, expected {int(expect)}")
        return
    names = [str(n) for n in expect]
    if cfg.n_joints != len(names):
        raise PhaseError(f"{path}: PAE takes {cfg.n_joints} joints, expected {len(names)} ({', '.join(names)})")
    if cfg.joints is not None and list(cfg.joints) != names:
        i = next(i for i, (a, b) in enumerate(zip(cfg.joints, names, strict=True)) if a != b)
        raise PhaseError(f"{path}: PAE joint {i} is {cfg.joints[i]!r}, expected {names[i]!r}")



def load_pae_numpy(path: str | Path, expect_joints: int | Sequence[str] | None = None,
                   dtype=np.float32) -> tuple[PaeNumpy, dict[str, Any]]:
    """(`PaeNumpy`, metadata) from a file written by `save_pae`, without importing torch."""
    cfg, arrays, doc = read_pae(path, expect_joints)
    return PaeNumpy(cfg, arrays, dtype), doc
