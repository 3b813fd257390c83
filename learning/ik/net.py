"""The deep IK networks: an LSTM (or a same-size MLP) over a few frames of normalised wrist targets,
in torch, and the weights file that ships it (its numpy inference is `felis.learning.ik.infer`).

Method (seed 001 §3.1.2, ``shared/reference/methods.md`` "Deep IK solver"): the input is a short
sequence of k frames, each the shoulder→tool vector divided by the limb length (n_in = 3 values);
every frame goes through a fully connected layer, a stacked LSTM runs over the frames, and a fully
connected layer maps the last step's hidden state to the outputs. The Motion Predictor (MP) outputs
future target vectors, the Posture Estimator (PE) joint angles as (sin, cos) pairs. The paper uses
FC in → 3 × 512 LSTM → FC out; the arm's nets are smaller (``hidden``, ``layers`` in `NetSpec`).

LSTM cell (PyTorch's gate order i, f, g, o), per layer and step t::

    z = W_ih x_t + b_ih + W_hh h_{t-1} + b_hh
    i, f, o = σ(z_i), σ(z_f), σ(z_o);   g = tanh(z_g)
    c_t = f ⊙ c_{t-1} + i ⊙ g;         h_t = o ⊙ tanh(c_t)

Normalisation: the net sees x̂ = (x − μ_x) / σ_x (per input channel, over all frames) and predicts
standardised targets ŷ; the output is y = ŷ ⊙ σ_y + μ_y. The four statistics are buffers of the
torch model and arrays of the weights file, so a loaded net needs nothing else.

MLP sizing rule (for comparing network types like the paper's Fig. 4.6, same parameter budget):
the MLP flattens the k frames (k·n_in inputs) and has ``layers`` hidden Linear+ReLU layers of one
width w, then a Linear output. w is the largest width whose parameter count does not exceed that of
the LSTM with the same ``hidden`` and ``layers``::

    P_lstm(h, L) = (n_in·h + h) + L·(8h² + 8h) + (h·n_out + n_out)
    P_mlp(w, L)  = (k·n_in·w + w) + (L − 1)·(w² + w) + (w·n_out + n_out)
    w = max{w ≥ 1 : P_mlp(w, L) ≤ P_lstm(h, L)}

(for L = 2 this is about 4h; for L = 1, P_lstm / (k·n_in + n_out + 1)).

Here: the torch nets (`SeqNet`) and writing the weights file. `NetSpec`, the numpy forward pass
(`NumpyNet`) and reading the weights are `felis.learning.ik.infer`, which needs no torch, so controllers
load the shipped weights cheaply. The weights file is one ``.npz`` (no pickled objects) holding several
nets under ``<name>/`` prefixes and a JSON metadata string (see `save_weights`).
"""


from __future__ import annotations

import functools
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from felis.errors import ParameterError, WeightsError
from felis.learning.common.torchstate import lazy_attribute, model_with_arrays
from felis.learning.common.weights import weights_target, write_weights
from felis.learning.ik.infer import MODEL_ID, SCHEMA, NetSpec, check_arrays, param_count

if TYPE_CHECKING:  # torch is imported lazily: inference with NumpyNet must not pay for it
    import torch

RESERVED_META = ("schema", "model", "nets")


# --------------------------------------------------------------------------------------------- torch


@functools.cache
def _seqnet_class():
    """The torch IK net class ``SeqNet`` (see its docstring); defined on first use to keep torch lazy."""
    import torch
    from torch import nn

    class SeqNet(nn.Module):
        """The torch IK net; arguments as in `NetSpec`, which its ``spec`` attribute holds.

        LSTM: per-frame Linear(n_in → hidden) + ReLU, ``nn.LSTM(hidden, hidden, layers, batch_first=True)``
        over the k frames, the last step's hidden state → Linear(hidden → n_out). MLP: the k frames
        flattened → ``layers`` × (Linear + ReLU) of the matched width (module docstring) → Linear(n_out).
        Buffers ``x_mean, x_std, y_mean, y_std`` hold the normalisation (`set_stats`); ``core`` maps
        standardised inputs to standardised outputs (what training fits), ``forward`` raw inputs to
        target units.
        """

        def __init__(self, kind: str, k: int, n_in: int = 3, hidden: int = 64, layers: int = 2,
                     n_out: int = 6, name: str = "net", in_offsets=(), out_offsets=()):
            super().__init__()
            self.spec = NetSpec(kind, k, n_in, hidden, layers, n_out, name, tuple(in_offsets), tuple(out_offsets))
            if kind == "lstm":
                self.inp = nn.Linear(n_in, hidden)
                self.lstm = nn.LSTM(hidden, hidden, layers, batch_first=True)
                self.out = nn.Linear(hidden, n_out)
            else:
                w, fan_in = self.spec.width, k * n_in
                self.hid = nn.ModuleList()
                for _ in range(layers):
                    self.hid.append(nn.Linear(fan_in, w))
                    fan_in = w
                self.out = nn.Linear(w, n_out)
            self.register_buffer("x_mean", torch.zeros(n_in))
            self.register_buffer("x_std", torch.ones(n_in))
            self.register_buffer("y_mean", torch.zeros(n_out))
            self.register_buffer("y_std", torch.ones(n_out))

        def set_stats(self, x_mean, x_std, y_mean, y_std) -> None:
            """Copy normalisation statistics in (array-likes of shapes (n_in,) and (n_out,))."""
            for buf, v in zip((self.x_mean, self.x_std, self.y_mean, self.y_std),
                              (x_mean, x_std, y_mean, y_std), strict=True):
                buf.copy_(torch.as_tensor(np.asarray(v), dtype=buf.dtype))

        def core(self, xs: torch.Tensor) -> torch.Tensor:
            """Standardised input (B, k, n_in) → standardised output (B, n_out): what training fits."""
            if self.spec.kind == "lstm":
                seq, _ = self.lstm(torch.relu(self.inp(xs)))
                return self.out(seq[:, -1])
            z = xs.reshape(xs.shape[0], -1)
            for layer in self.hid:
                z = torch.relu(layer(z))
            return self.out(z)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            """Raw input (B, k, n_in) → outputs in target units (B, n_out)."""
            return self.core((x - self.x_mean) / self.x_std) * self.y_std + self.y_mean

    return SeqNet


# ``SeqNet`` is built on first access, so importing this module does not import torch.
__getattr__ = lazy_attribute(__name__, "SeqNet", _seqnet_class)


def model_from_spec(spec: NetSpec):
    """A freshly initialised `SeqNet` for ``spec`` (uses torch's global RNG, like any nn.Module)."""
    return _seqnet_class()(spec.kind, spec.k, spec.n_in, spec.hidden, spec.layers, spec.n_out, spec.name,
                           spec.in_offsets, spec.out_offsets)


def arrays_to_torch(spec: NetSpec, arrays: Mapping[str, np.ndarray]):
    """A `SeqNet` for ``spec`` holding ``arrays`` (as from `torch_to_arrays`); WeightsError if they do not fit."""
    check_arrays(spec, arrays, f"net {spec.name!r}")
    return model_with_arrays(lambda: model_from_spec(spec), spec.shapes(), arrays)


# --------------------------------------------------------------------------------------- weights file


def save_weights(path: str | Path, nets: Mapping[str, tuple[NetSpec, Mapping[str, np.ndarray]]],
                 meta: Mapping[str, Any] | None = None) -> Path:
    """Write several nets to one ``.npz`` atomically (temporary file beside, then ``os.replace``).

    ``nets`` maps a name (the array prefix: "mp", "pe") to (spec, arrays); the spec's ``name`` must be
    that name. Arrays are stored float32 as ``<name>/<key>``; ``__meta__`` holds a JSON string::

        {"schema": 1, "model": "felis-ik", "nets": {name: {"spec": {...}, "params": P,
         "in_offsets": [...], "out_offsets": [...]}}, ...meta}

    where ``meta`` (JSON-serialisable; e.g. training results, data set description) may not use the
    keys "schema", "model", "nets". The arrays are checked first, so a bad net is never written.
    """
    path, meta = weights_target(path, meta, RESERVED_META, "weights", "weights", WeightsError)
    if not nets:
        raise ParameterError("no nets to save")
    arrays: dict[str, np.ndarray] = {}
    doc_nets = {}
    for name, (spec, state) in nets.items():
        if spec.name != name:
            raise ParameterError(f"net saved as {name!r} has spec name {spec.name!r}; they must agree")
        check_arrays(spec, state, f"net {name!r}")
        for key in spec.shapes():
            arrays[f"{name}/{key}"] = np.asarray(state[key], dtype=np.float32)
        doc_nets[name] = {"spec": spec.to_json(), "params": param_count(spec),
                          "in_offsets": list(spec.in_offsets), "out_offsets": list(spec.out_offsets)}
    doc = {"schema": SCHEMA, "model": MODEL_ID, "nets": doc_nets, **meta}
    return write_weights(path, arrays, doc, "weights", "IK weights", WeightsError)
