"""Numpy inference of the arm's IK nets (seed 001 §3.1.1–3.1.2): the nets' inputs and outputs, their
shapes (`NetSpec`), the forward pass (`NumpyNet`) and reading the weights file (`load_weights`). No torch:
the IK pipeline (`felis.learning.ik.solver`) and so the controllers load the shipped weights cheaply;
the torch nets, training and saving are `felis.learning.ik.net` and `felis.learning.ik.train`.

**Inputs and outputs.** Inputs are v = (p − S) / REACH, the shoulder → tool vector over the limb length
(`normalise`); joint angles are encoded as (sin q, cos q) pairs (no wrap jumps, `encode_angles`) and
decoded by atan2 (`decode_angles`). The Motion Predictor sees frames `MP_IN` and predicts `MP_OUT`; the
Posture Estimator sees `PE_IN` and gives the poses of frames `PE_OUT` (offsets at 100 Hz).

The nets' architecture, LSTM cell and MLP sizing rule are described in `felis.learning.ik.net`. The
weights file is one ``.npz`` (no pickled objects) holding several nets under ``<name>/`` prefixes and a
JSON metadata string (`felis.learning.ik.net.save_weights`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from felis.armkin import REACH, SHOULDER
from felis.errors import ParameterError, WeightsError
from felis.files import META_KEY, check_float_arrays, dataclass_from_json, read_meta, read_npz

# --- network windows (frame offsets at 100 Hz; seed 001 §3.1.2)

MP_IN = (-10, -5, 0)
MP_OUT = (5, 10)
PE_IN = (-10, -5, 0, 5, 10)
PE_OUT = (0, 1, 2, 3, 4, 5)

MODEL_ID = "felis-ik"
SCHEMA = 1
KINDS = ("lstm", "mlp")
STAT_KEYS = ("x_mean", "x_std", "y_mean", "y_std")


@dataclass(frozen=True)
class NetSpec:
    """The shape of one IK net: what goes in, what comes out, and how big it is.

    ``kind`` "lstm" or "mlp"; ``k`` input frames of ``n_in`` values each; ``hidden`` units per LSTM
    layer (for the MLP, the LSTM size it is matched to, see the module docstring); ``layers`` LSTM
    (or MLP hidden) layers; ``n_out`` outputs; ``name`` the net's prefix in a weights file ("mp",
    "pe"). ``in_offsets`` (k frame offsets relative to the current frame i, e.g. (−10, −5, 0)) and
    ``out_offsets`` (the frames the outputs belong to, n_out divisible by their number) document the
    net's contract; they are stored in the weights file and checked by `load_weights` (``expect``).
    """

    kind: str
    k: int
    n_in: int = 3
    hidden: int = 64
    layers: int = 2
    n_out: int = 6
    name: str = "net"
    in_offsets: tuple[int, ...] = ()
    out_offsets: tuple[int, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "in_offsets", tuple(int(v) for v in self.in_offsets))
        object.__setattr__(self, "out_offsets", tuple(int(v) for v in self.out_offsets))
        if self.kind not in KINDS:
            raise ParameterError(f"net {self.name!r}: kind {self.kind!r} is not one of {', '.join(KINDS)}")
        for f in ("k", "n_in", "hidden", "layers", "n_out"):
            v = getattr(self, f)
            if not isinstance(v, int | np.integer) or isinstance(v, bool) or v < 1:
                raise ParameterError(f"net {self.name!r}: {f} must be a positive integer, got {v!r}")
            object.__setattr__(self, f, int(v))
        if not self.name or "/" in self.name or self.name in (META_KEY, "nets"):
            raise ParameterError(f"net name {self.name!r} must be non-empty, contain no '/' and not be 'nets'")
        if self.in_offsets and len(self.in_offsets) != self.k:
            raise ParameterError(f"net {self.name!r}: {len(self.in_offsets)} in_offsets for k = {self.k} frames")
        if self.out_offsets and self.n_out % len(self.out_offsets):
            raise ParameterError(f"net {self.name!r}: n_out = {self.n_out} is not a multiple of "
                                 f"{len(self.out_offsets)} out_offsets")

    @property
    def width(self) -> int:
        """Hidden width: ``hidden`` for the LSTM, the matched width w for the MLP (module docstring)."""
        return self.hidden if self.kind == "lstm" else mlp_width(self)

    @property
    def param_count(self) -> int:
        """Trainable parameters (weights and biases; not the normalisation statistics)."""
        return param_count(self)

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """Name → shape of every array of this net (the torch ``state_dict`` keys, buffers included)."""
        h, n_in, n_out = self.hidden, self.n_in, self.n_out
        out = {"x_mean": (n_in,), "x_std": (n_in,), "y_mean": (n_out,), "y_std": (n_out,)}
        if self.kind == "lstm":
            out.update({"inp.weight": (h, n_in), "inp.bias": (h,)})
            for i in range(self.layers):
                out.update({f"lstm.weight_ih_l{i}": (4 * h, h), f"lstm.weight_hh_l{i}": (4 * h, h),
                            f"lstm.bias_ih_l{i}": (4 * h,), f"lstm.bias_hh_l{i}": (4 * h,)})
            out.update({"out.weight": (n_out, h), "out.bias": (n_out,)})
        else:
            w, fan_in = mlp_width(self), self.k * n_in
            for i in range(self.layers):
                out.update({f"hid.{i}.weight": (w, fan_in), f"hid.{i}.bias": (w,)})
                fan_in = w
            out.update({"out.weight": (n_out, w), "out.bias": (n_out,)})
        return out

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["in_offsets"], d["out_offsets"] = list(self.in_offsets), list(self.out_offsets)
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> NetSpec:
        """Inverse of `to_json`; unknown or missing keys raise ParameterError."""
        return dataclass_from_json(cls, d, "net spec", ParameterError)


def lstm_params(spec: NetSpec) -> int:
    """P_lstm = (n_in·h + h) + L·(8h² + 8h) + (h·n_out + n_out) (torch keeps two bias vectors)."""
    h = spec.hidden
    return (spec.n_in * h + h) + spec.layers * (8 * h * h + 8 * h) + (h * spec.n_out + spec.n_out)


def _mlp_params(w: int, spec: NetSpec) -> int:
    return (spec.k * spec.n_in * w + w) + (spec.layers - 1) * (w * w + w) + (w * spec.n_out + spec.n_out)


def mlp_width(spec: NetSpec) -> int:
    """The widest w with P_mlp(w) ≤ P_lstm (module docstring); at least 1."""
    budget, a, b = lstm_params(spec), spec.layers - 1, spec.k * spec.n_in + spec.layers + spec.n_out
    c = spec.n_out - budget  # a·w² + b·w + c ≤ 0
    w = int(-c / b) if a == 0 else int((-b + math.sqrt(b * b - 4 * a * c)) / (2 * a))
    while w > 1 and _mlp_params(w, spec) > budget:
        w -= 1
    while _mlp_params(w + 1, spec) <= budget:
        w += 1
    return max(w, 1)


def param_count(net: NetSpec | Any) -> int:
    """Trainable parameters of a `NetSpec` (from its shapes) or of a torch module."""
    if isinstance(net, NetSpec):
        return sum(math.prod(s) for n, s in net.shapes().items() if n not in STAT_KEYS)
    return sum(p.numel() for p in net.parameters())



# --------------------------------------------------------------------------------------------- inputs


def normalise(p: np.ndarray) -> np.ndarray:
    """v = (p − S) / REACH (..., 3): the shoulder → tool vector over the limb length (seed 001 §3.1.1)."""
    return (np.asarray(p, dtype=float) - SHOULDER) / REACH


def encode_angles(q: np.ndarray) -> np.ndarray:
    """(..., 4) angles → (..., 8) as (sin q1, cos q1, sin q2, cos q2, …): continuous across ±π."""
    q = np.asarray(q, dtype=float)
    return np.stack([np.sin(q), np.cos(q)], axis=-1).reshape(q.shape[:-1] + (2 * q.shape[-1],))


def decode_angles(x: np.ndarray) -> np.ndarray:
    """(..., 8) (sin, cos) pairs → (..., 4) angles in [−π, π] by atan2(s, c) (scale-free, so a pair
    need not have norm 1)."""
    x = np.asarray(x, dtype=float)
    pairs = x.reshape(x.shape[:-1] + (x.shape[-1] // 2, 2))
    return np.arctan2(pairs[..., 0], pairs[..., 1])



# --------------------------------------------------------------------------------------------- arrays


def check_arrays(spec: NetSpec, arrays: Mapping[str, np.ndarray], where: str) -> None:
    """WeightsError (one line starting with ``where``) unless ``arrays`` holds every array of ``spec``
    with the right shape, a float dtype, finite values and positive standard deviations."""
    check_float_arrays(arrays, spec.shapes(), where, WeightsError, positive=("x_std", "y_std"))


# --------------------------------------------------------------------------------------------- numpy


class NumpyNet:
    """Numpy inference of one IK net, equal to the torch `SeqNet` within float rounding (≤ 1e-5).

    ``net(x)`` with x of shape (B, k, n_in) returns (B, n_out); with (k, n_in), (n_out,). Computation
    is in ``dtype``: float32 by default (the weights are float32, and float64 products are about 1.7×
    slower on the 1 MiB of a 128-unit, 2-layer net), or float64. Built for single queries: the
    input normalisation is folded into the first layer (W' = W / σ_x, b' = b − W' μ_x), the output
    one into the last (W' = σ_y W, b' = σ_y b + μ_y); the two LSTM bias vectors are summed; the
    gates are reordered to (i, f, o, g) and the i, f, o rows halved so that one tanh serves all four
    gates (σ(z) = ½ tanh(z / 2) + ½, exact since halving is exact); and each layer's input
    projection W_ih x_t is done for all k frames in one matrix product before the recurrence.
    """

    def __init__(self, spec: NetSpec, arrays: Mapping[str, np.ndarray], dtype=np.float32):
        if np.dtype(dtype) not in (np.float32, np.float64):
            raise ParameterError(f"NumpyNet computes in float32 or float64, not {np.dtype(dtype)}")
        check_arrays(spec, arrays, f"net {spec.name!r}")
        self.spec, self.dtype = spec, np.dtype(dtype)
        a = {k: np.asarray(v, dtype=np.float64) for k, v in arrays.items() if k in spec.shapes()}
        xm, xs, ym, ys = (a[k] for k in STAT_KEYS)
        first = "inp" if spec.kind == "lstm" else "hid.0"
        w0, b0 = a[f"{first}.weight"], a[f"{first}.bias"]
        if spec.kind == "lstm":
            w0 = w0 / xs                                   # (h, n_in)
        else:                                              # flattened frames: stats repeat per frame
            w0 = w0 / np.tile(xs, spec.k)
        b0 = b0 - w0 @ (xm if spec.kind == "lstm" else np.tile(xm, spec.k))
        cast = self.dtype.type
        self._w0, self._b0 = np.ascontiguousarray(w0.T, dtype=cast), b0.astype(cast)
        self._wo = np.ascontiguousarray((a["out.weight"] * ys[:, None]).T, dtype=cast)
        self._bo = (a["out.bias"] * ys + ym).astype(cast)
        h = spec.hidden
        if spec.kind == "lstm":
            order = np.r_[0:2 * h, 3 * h:4 * h, 2 * h:3 * h]     # torch (i, f, g, o) → (i, f, o, g)
            scale = np.r_[np.full(3 * h, 0.5), np.ones(h)][:, None]
            self._lstm = []
            for i in range(spec.layers):
                wih = a[f"lstm.weight_ih_l{i}"][order] * scale
                whh = a[f"lstm.weight_hh_l{i}"][order] * scale
                b = (a[f"lstm.bias_ih_l{i}"] + a[f"lstm.bias_hh_l{i}"])[order] * scale[:, 0]
                self._lstm.append((np.ascontiguousarray(wih.T, dtype=cast), np.ascontiguousarray(whh.T, dtype=cast),
                                   b.astype(cast)))
        else:
            self._hid = [(np.ascontiguousarray(a[f"hid.{i}.weight"].T, dtype=cast), a[f"hid.{i}.bias"].astype(cast))
                         for i in range(1, spec.layers)]

    def __call__(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=self.dtype)
        spec = self.spec
        if x.shape[-2:] != (spec.k, spec.n_in) or x.ndim not in (2, 3):
            raise ParameterError(f"IK net {spec.name!r} takes ({spec.k}, {spec.n_in}) or (B, {spec.k}, {spec.n_in}) "
                                 f"inputs, got shape {x.shape}")
        if spec.kind == "mlp":
            return self._mlp_forward(x.reshape(*x.shape[:-2], spec.k * spec.n_in))
        return self._lstm_forward(x if x.ndim == 2 else x.transpose(1, 0, 2))

    def _mlp_forward(self, x: np.ndarray) -> np.ndarray:
        z = x @ self._w0
        z += self._b0
        np.maximum(z, 0, out=z)
        for w, b in self._hid:
            z = z @ w
            z += b
            np.maximum(z, 0, out=z)
        y = z @ self._wo
        y += self._bo
        return y

    def _lstm_forward(self, x: np.ndarray) -> np.ndarray:
        """x time-major: (k, n_in) for one query (the state is then 1-D: fewest, cheapest numpy calls)
        or (k, B, n_in). Layer by layer: one product for the input projection of all k frames, then
        the recurrence; at t = 0 (h = c = 0) the recurrent product and the forget term are skipped.
        (A wavefront over the layers, one set of calls per wave, measured 1.5× slower: strided views.)
        """
        k, hd = self.spec.k, self.spec.hidden
        h3 = 3 * hd
        lead = x.shape[:-1]                                # (k,) or (k, B)
        seq = x.reshape(-1, x.shape[-1]) @ self._w0        # (k·B, h); 2-D products are faster than 3-D
        seq += self._b0
        np.maximum(seq, 0, out=seq)
        last = len(self._lstm) - 1
        h = seq
        for li, (wih, whh, b) in enumerate(self._lstm):
            g_in = (seq @ wih).reshape(*lead, 4 * hd)      # W_ih x_t + b for all frames at once
            g_in += b
            nxt = None if li == last else np.empty((*lead, hd), dtype=self.dtype)
            z = np.tanh(g_in[0])                           # t = 0
            s = z[..., :h3]
            s *= 0.5
            s += 0.5                                       # σ of i, f, o (their rows were halved)
            c = s[..., :hd] * z[..., h3:]
            h = np.tanh(c)
            h *= s[..., 2 * hd:h3]
            for t in range(1, k):
                if nxt is not None:
                    nxt[t - 1] = h
                z = h @ whh
                z += g_in[t]
                np.tanh(z, out=z)
                s = z[..., :h3]
                s *= 0.5
                s += 0.5
                c *= s[..., hd:2 * hd]
                c += s[..., :hd] * z[..., h3:]
                h = np.tanh(c)
                h *= s[..., 2 * hd:h3]
            if nxt is not None:
                nxt[k - 1] = h
                seq = nxt.reshape(-1, hd)
        y = h @ self._wo
        y += self._bo
        return y


# --------------------------------------------------------------------------------------- weights file


def load_arrays(path: str | Path, expect: Mapping[str, Any] | None = None
                ) -> tuple[dict[str, tuple[NetSpec, dict[str, np.ndarray]]], dict[str, Any]]:
    """Read a weights file as (name → (spec, float32 arrays), metadata): the inverse of `save_weights`
    (e.g. to re-save one net beside a newly trained one). Checks and errors as `load_weights`."""
    path = Path(path)
    data = read_npz(path, "weights", WeightsError)
    doc = read_meta(data, path, WeightsError, "IK weights file", detail=str,
                    ident=("model", MODEL_ID, "model id {got!r} is not {want!r}; not IK weights"),
                    version=("schema", SCHEMA, "weights schema {got!r} is not supported (felis reads schema {want})"))
    if not isinstance(doc.get("nets"), dict) or not doc["nets"]:
        raise WeightsError(f"{path}: metadata lists no nets")
    specs: dict[str, NetSpec] = {}
    for name, entry in doc["nets"].items():
        try:
            spec = NetSpec.from_json(entry["spec"])
        except (ParameterError, KeyError, TypeError, ValueError) as e:
            raise WeightsError(f"{path}: net {name!r} has an invalid spec: {e}") from None
        if spec.name != name:
            raise WeightsError(f"{path}: net {name!r} has spec name {spec.name!r}")
        specs[name] = spec
    _check_expect(path, specs, expect)
    nets = {}
    for name, spec in specs.items():
        prefix = f"{name}/"
        arrays = {k[len(prefix):]: v for k, v in data.items() if k.startswith(prefix)}
        check_arrays(spec, arrays, f"{path}: net {name!r}")
        nets[name] = (spec, {k: arrays[k].astype(np.float32) for k in spec.shapes()})
    return nets, doc


def load_weights(path: str | Path, expect: Mapping[str, Any] | None = None,
                 dtype=np.float32) -> tuple[dict[str, NumpyNet], dict[str, Any]]:
    """Read a weights file written by `save_weights`: (name → `NumpyNet`, metadata document).

    Every problem raises `WeightsError` with one line naming the file and what is wrong: missing file,
    not an npz / corrupt / truncated, no or bad metadata, another model id or schema, a missing array,
    a shape that does not match the stored spec, non-finite values, or a mismatch with ``expect``.

    ``expect``: ``"nets"`` → names of nets that must be present; any other key is a net name (which
    must be present) → None, a `NetSpec` whose interface must match (k, n_in, n_out, in_offsets,
    out_offsets; not the architecture), or a dict of `NetSpec` field → value, e.g.
    ``{"nets": ("mp", "pe"), "mp": {"k": 3, "in_offsets": (-10, -5, 0)}}``.
    """
    nets, doc = load_arrays(path, expect)
    return {name: NumpyNet(spec, arrays, dtype) for name, (spec, arrays) in nets.items()}, doc


def _check_expect(path: Path, specs: Mapping[str, NetSpec], expect: Mapping[str, Any] | None) -> None:
    if expect is None:
        return
    if not isinstance(expect, Mapping):
        raise ParameterError(f"expect must map net names (and 'nets') to expectations, not {type(expect).__name__}")
    names = expect.get("nets", ())
    if isinstance(names, str):
        names = (names,)
    required = [*names, *(n for n in expect if n != "nets")]
    missing = [n for n in required if n not in specs]
    if missing:
        raise WeightsError(f"{path}: holds nets {', '.join(map(repr, specs))}, not the expected "
                           f"{', '.join(map(repr, missing))}")
    for name, want in expect.items():
        if want is None or name == "nets":
            continue
        if isinstance(want, NetSpec):
            want = {f: getattr(want, f) for f in ("k", "n_in", "n_out", "in_offsets", "out_offsets")}
        for field, value in want.items():
            if not hasattr(specs[name], field):
                raise ParameterError(f"expected field {field!r} of net {name!r} is not a NetSpec field")
            have = getattr(specs[name], field)
            if isinstance(have, tuple):
                value = tuple(value)
            if have != value:
                raise WeightsError(f"{path}: net {name!r} has {field} {have!r}, expected {value!r}")
