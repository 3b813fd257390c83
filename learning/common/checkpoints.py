"""Training checkpoints for the torch trainers (`felis.learning.ik.train`, `felis.learning.phase.train`):
one ``.npz`` per run, written atomically after every epoch, that a resumed run continues from
bit-identically.

Arrays: ``model/<key>`` (the weights now), ``best/<key>`` (the best-validation weights so far),
``opt/<i>/<state>`` (Adam's per-parameter state), ``rng`` (the batch generator's state, bytes),
``history/<list>`` (per-epoch curves); and a JSON ``__meta__``: the checkpoint's kind and schema,
``epoch`` (epochs done), ``best_epoch``, ``best_val``, ``opt_state`` (the state names per parameter) and
the run's identity (config, model, data fingerprint), which a resume must match key by key.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import FelisError

META_KEY = "__meta__"


def difference(old: Any, new: Any) -> str:
    """A short description of what differs between two JSON values (first differing key)."""
    if isinstance(old, dict) and isinstance(new, dict):
        for k in sorted(set(old) | set(new)):
            if old.get(k) != new.get(k):
                return f"{k}: {old.get(k)!r} there, {new.get(k)!r} now"
    return f"{old!r} there, {new!r} now"


def save_checkpoint(path: Path, kind: tuple[str, int], run_id: Mapping[str, Any], epoch: int,
                    model_arrays: Mapping[str, np.ndarray], opt, gen, hist: Mapping[str, Any],
                    history_lists: Sequence[str], best: Mapping[str, Any], what: str,
                    error: type[FelisError]) -> None:
    """Write the checkpoint (module doc); ``kind`` = (checkpoint id, schema)."""
    from felis.files import write_atomic

    arrays: dict[str, np.ndarray] = {f"model/{k}": v for k, v in model_arrays.items()}
    arrays.update({f"best/{k}": v.detach().cpu().numpy().copy() for k, v in best.items()})
    state = opt.state_dict()["state"]
    for i, st in state.items():
        for name, v in st.items():
            arrays[f"opt/{i}/{name}"] = v.detach().cpu().numpy().copy()
    arrays["rng"] = gen.get_state().numpy().copy()
    for name in history_lists:
        arrays[f"history/{name}"] = np.asarray(hist[name], dtype=np.float64)
    meta = {"model": kind[0], "schema": kind[1], "epoch": epoch, "best_epoch": hist["best_epoch"],
            "best_val": hist["best_val"], "opt_state": {str(i): sorted(st) for i, st in state.items()}, **run_id}
    arrays[META_KEY] = np.array(json.dumps(meta))
    write_atomic(path, lambda f: np.savez(f, **arrays), what, error)


def load_checkpoint(path: Path, kind: tuple[str, int], run_id: Mapping[str, Any], run_keys: Sequence[tuple[str, str]],
                    check: Callable[[Mapping[str, np.ndarray], str], None], model, opt, gen,
                    new_history: Callable[[], dict], history_lists: Sequence[str], what: str,
                    error: type[FelisError]):
    """Restore ``model``, ``opt`` and ``gen`` from ``path``; returns (epochs done, history, best weights).

    ``run_keys``: (meta key, what it is) that must equal ``run_id``'s; ``check(arrays, where)`` refuses
    weights of another shape. Every refusal is one line of ``error``: a corrupt file, another kind of
    checkpoint, another run, a history, optimiser or generator state that does not fit.
    """
    import torch

    from felis.files import read_npz

    data = read_npz(path, what, error)
    try:
        meta = json.loads(str(data[META_KEY]))
    except (KeyError, ValueError):
        raise error(f"{path}: no readable {META_KEY!r} metadata: is no {what}") from None
    if not isinstance(meta, dict) or meta.get("model") != kind[0] or meta.get("schema") != kind[1]:
        got = (meta.get("model"), meta.get("schema")) if isinstance(meta, dict) else None
        raise error(f"{path}: is no {what} (kind and schema {got!r})")
    for key, label in run_keys:
        if meta.get(key) != run_id[key]:
            raise error(f"{path}: checkpoint was made with another {label} ({difference(meta.get(key), run_id[key])}); "
                        "start without resuming or use the same settings")
    try:
        model_arrays = {k[6:]: v for k, v in data.items() if k.startswith("model/")}
        best_arrays = {k[5:]: v for k, v in data.items() if k.startswith("best/")}
        check(model_arrays, f"{path}: checkpoint model")
        check(best_arrays, f"{path}: checkpoint best weights")
        epoch = int(meta["epoch"])
        hist = new_history()
        for n in history_lists:
            hist[n] = data[f"history/{n}"].astype(float).tolist()
        hist["best_epoch"], hist["best_val"] = int(meta["best_epoch"]), float(meta["best_val"])
        if epoch < 1 or not all(len(hist[n]) == epoch for n in history_lists):
            raise error(f"{path}: checkpoint history does not match its epoch {epoch}")
        opt_state = {int(i): {n: torch.from_numpy(np.array(data[f"opt/{i}/{n}"])) for n in names}
                     for i, names in meta["opt_state"].items()}
        rng = data["rng"]
    except KeyError as e:
        raise error(f"{path}: checkpoint lacks {e.args[0]!r}") from None
    except (TypeError, ValueError, AttributeError) as e:
        raise error(f"{path}: corrupt checkpoint metadata ({e})") from None
    if rng.dtype != np.uint8 or rng.ndim != 1:
        raise error(f"{path}: checkpoint generator state is not a byte array")
    model.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in model_arrays.items()})
    try:
        opt.load_state_dict({"state": opt_state, "param_groups": opt.state_dict()["param_groups"]})
        gen.set_state(torch.from_numpy(np.array(rng)))
    except (RuntimeError, ValueError, KeyError) as e:
        raise error(f"{path}: checkpoint optimiser or generator state does not fit: {e}") from None
    for i, p in enumerate(model.parameters()):
        st = opt.state.get(p, {})
        for n in ("exp_avg", "exp_avg_sq"):
            if n not in st or st[n].shape != p.shape or not bool(torch.isfinite(st[n]).all()):
                raise error(f"{path}: checkpoint optimiser state {i}/{n} is missing, misshapen or non-finite")
    return epoch, hist, {k: torch.from_numpy(np.array(v)) for k, v in best_arrays.items()}
