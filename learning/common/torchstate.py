"""A torch model's weights as numpy arrays and back, for the gradient-trained nets (the IK nets, the PAE):
the weights files and checkpoints hold float32 arrays by state-dict key, never pickled tensors.

Also the lazily built torch class: a module whose torch ``nn.Module`` subclass is made on first access
(`lazy_attribute`), so importing it, or the numpy inference beside it, does not import torch.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import numpy as np


def torch_to_arrays(model) -> dict[str, np.ndarray]:
    """The model's state (parameters and normalisation buffers) as float32 numpy arrays, by state_dict key."""
    return {k: v.detach().cpu().numpy().astype(np.float32, copy=True) for k, v in model.state_dict().items()}


def model_with_arrays(build: Callable[[], object], keys: Iterable[str], arrays: Mapping[str, np.ndarray]):
    """``build()``'s model holding ``arrays[k]`` (as float32) for each state-dict key ``k`` in ``keys``; the
    caller has checked the arrays. The construction's random initial weights are drawn inside
    ``torch.random.fork_rng``, so the global RNG is as it was."""
    import torch  # heavy: only a torch model needs it

    with torch.random.fork_rng(devices=[]):
        model = build()
    model.load_state_dict({k: torch.as_tensor(np.asarray(arrays[k], dtype=np.float32)) for k in keys})
    return model


def lazy_attribute(module: str, name: str, build: Callable[[], object]) -> Callable[[str], object]:
    """A module-level ``__getattr__`` for ``module`` that returns ``build()`` for ``name`` (the torch class,
    made on first access) and raises the usual AttributeError for anything else."""

    def __getattr__(attr: str):
        if attr == name:
            return build()
        raise AttributeError(f"module {module!r} has no attribute {attr!r}")

    return __getattr__
