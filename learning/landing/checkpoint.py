"""The state of a landing evolution run (`TrainState`: stage, populations, frozen behaviours, the
generator, the curves) and its checkpoint file: ``<workdir>/checkpoint.npz``, no pickle, replaced
atomically after every generation; the generator's state is stored as JSON so a resumed run is
bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from felis.errors import CheckpointError, PolicyError
from felis.files import MAX_ARRAY_BYTES, check_readable, write_atomic
from felis.learning.landing.policy import PARTS, GeneUnit, SimpleBehaviour

CHECKPOINT = "checkpoint.npz"
CHECKPOINT_FORMAT = "felis-landing-checkpoint"
CHECKPOINT_VERSION = 2
META_KEY = "__meta__"


@dataclass
class TrainState:
    stage: str  # "simple", "complex", "one" (one-net), "general" or "done"
    generation: int  # generations done in this stage
    simple: list[list[SimpleBehaviour]]  # per orientation: the population to evaluate next (elites first);
    # in the "one" and "general" stages a single population
    frozen: list[SimpleBehaviour] | None  # the complex stage's simple behaviours
    compose: list[GeneUnit] | None  # the compose population to evaluate next (elites first)
    rng: np.random.Generator
    history: dict



def _pack_unit(prefix: str, u: GeneUnit, arrays: dict[str, np.ndarray]) -> None:
    arrays[f"{prefix}/inputs"] = np.array(u.inputs, dtype=np.int64)
    arrays[f"{prefix}/W1"] = u.W1
    arrays[f"{prefix}/W2"] = u.W2
    arrays[f"{prefix}/scale"] = np.array(u.scale)


def _unpack_unit(prefix: str, kind: str, data: dict[str, np.ndarray]) -> GeneUnit:
    try:
        w1 = data[f"{prefix}/W1"]
        u = GeneUnit(kind, tuple(int(i) for i in data[f"{prefix}/inputs"]), int(w1.shape[0]) if w1.ndim == 2 else 0,
                     w1, data[f"{prefix}/W2"], float(data[f"{prefix}/scale"]))
        return u.check()
    except KeyError as e:
        raise CheckpointError(f"checkpoint lacks array {e.args[0]!r}") from None
    except (PolicyError, ValueError, TypeError) as e:
        raise CheckpointError(f"checkpoint unit {prefix!r} is corrupt: {e}") from None


def _pack_simple(prefix: str, b: SimpleBehaviour, arrays: dict[str, np.ndarray]) -> None:
    for p in PARTS:
        _pack_unit(f"{prefix}/{p}", getattr(b, p), arrays)


def _unpack_simple(prefix: str, data: dict[str, np.ndarray]) -> SimpleBehaviour:
    return SimpleBehaviour(*(_unpack_unit(f"{prefix}/{p}", p, data) for p in PARTS))


def save_checkpoint(path: Path, state: TrainState, run_id: dict) -> None:
    """Write ``state`` (module doc) atomically to ``path``."""
    arrays: dict[str, np.ndarray] = {}
    for k, pop in enumerate(state.simple):
        for i, b in enumerate(pop):
            _pack_simple(f"simple/{k}/{i}", b, arrays)
    for k, b in enumerate(state.frozen or ()):
        _pack_simple(f"frozen/{k}", b, arrays)
    for i, u in enumerate(state.compose or ()):
        _pack_unit(f"compose/{i}", u, arrays)
    doc = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **run_id, "stage": state.stage,
           "generation": state.generation, "n_simple": [len(p) for p in state.simple],
           "n_frozen": len(state.frozen or ()), "n_compose": len(state.compose or ()),
           "rng": state.rng.bit_generator.state, "history": state.history}
    arrays[META_KEY] = np.array(json.dumps(doc, allow_nan=False))
    write_atomic(path, lambda f: np.savez(f, **arrays), "training checkpoint", CheckpointError)


def _difference(saved: dict, now: dict) -> str | None:
    for key in sorted(set(saved) | set(now)):
        if saved.get(key) != now.get(key):
            return f"{key}={saved.get(key)!r} there, {now.get(key)!r} here"
    return None


def load_checkpoint(path: Path, run_id: dict) -> TrainState:
    """The state in ``path``; `CheckpointError` (one line) if it is corrupt or from another run."""
    check_readable(path, "checkpoint", CheckpointError, MAX_ARRAY_BYTES)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - any unreadable file is one line for the operator
        raise CheckpointError(f"{path}: unreadable training checkpoint ({type(e).__name__}); delete it or "
                              "start afresh without resume") from None
    try:
        doc = json.loads(str(data[META_KEY]))
    except (KeyError, ValueError):
        raise CheckpointError(f"{path}: not a landing training checkpoint (no metadata)") from None
    if doc.get("format") != CHECKPOINT_FORMAT or doc.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: not a landing training checkpoint of version {CHECKPOINT_VERSION}")
    for key in run_id:
        diff = _difference(doc.get(key) or {}, run_id[key]) if isinstance(run_id[key], dict) else (
            None if doc.get(key) == run_id[key] else f"{doc.get(key)!r} there, {run_id[key]!r} here")
        if diff:
            raise CheckpointError(f"{path}: written by a run with other {key} ({diff}); use the same "
                                  "settings to resume, or start afresh without resume")
    try:
        simple = [[_unpack_simple(f"simple/{k}/{i}", data) for i in range(n)] for k, n in enumerate(doc["n_simple"])]
        frozen = [_unpack_simple(f"frozen/{k}", data) for k in range(doc["n_frozen"])] or None
        compose = [_unpack_unit(f"compose/{i}", "compose", data) for i in range(doc["n_compose"])] or None
        rng = np.random.default_rng()
        rng.bit_generator.state = doc["rng"]
        return TrainState(doc["stage"], int(doc["generation"]), simple, frozen, compose, rng, doc["history"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: corrupt training checkpoint ({type(e).__name__}: {e})") from None
