"""Evolution side of the landing controller's nets (seed 000, §5–6.4): random gene units, mutation and
crossover, elimination, fitness, ranking, and writing policy files. The nets themselves (inputs, gene
units, behaviours, reading a policy) are `felis.learning.landing.policy`, what the controller imports.

Source: ``seeds/000_d27ba58563dbcb8e.txt`` — §5 (gene units, crossover, elimination), §6.4 (eqs. 9–11).

**Ranking.** Simple behaviours: lexicographic (f, D, S), eq. 10, see `compare_simple`. Complex
behaviours: pairwise by eq. 11, see `rank_complex`. Fitness: eq. 9 (`fitness_eq9`) times an upright
test (`fitness`), since eq. 9 alone rewards a steady high waist whatever the body's orientation.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from felis.errors import ParameterError, PolicyError
from felis.files import META_KEY, write_atomic
from felis.learning.landing.policy import (
    FORMAT,
    IT_NAMES,
    JOINTS,
    PARTS,
    VERSION,
    ComplexBehaviour,
    GeneUnit,
    SimpleBehaviour,
    _kind,
)

MAX_HIDDEN = 8  # default bound on hidden neurons for random units (the paper gives none)
LANDING_HEIGHT_MM = 500.0  # eq. 9: T is the first step with Sh < 500 mm
UPRIGHT_COS = math.cos(math.radians(30.0))  # up-axis within 30° of vertical, as felis.scenarios.verdicts


def same_structure(a: GeneUnit, b: GeneUnit) -> bool:
    """Same kind (so the same O), same inputs I and the same hidden count h (§5)."""
    return a.kind == b.kind and a.inputs == b.inputs and a.hidden == b.hidden


# -------------------------------------------------------------------------------------- operators


def _init_weights(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """N(0, 1/cols): unit-variance pre-activations for inputs in [-1, 1]."""
    return rng.normal(0.0, 1.0 / math.sqrt(cols), size=(rows, cols))


def random_unit(kind: str, rng: np.random.Generator, max_hidden: int = MAX_HIDDEN) -> GeneUnit:
    """A random unit (§5: "the hidden count and the inputs are chosen at random when an individual is
    created"): |I| uniform in 1…n_available, I a uniform subset of that size, h uniform in 1…max_hidden,
    weights N(0, 1/fan_in) with fan_in counting the bias."""
    k = _kind(kind)
    if max_hidden < 1:
        raise ParameterError(f"max_hidden is {max_hidden}; needs at least 1")
    n_in = int(rng.integers(1, k.n_available + 1))
    inputs = tuple(sorted(int(i) for i in rng.choice(k.n_available, size=n_in, replace=False)))
    h = int(rng.integers(1, max_hidden + 1))
    w1 = _init_weights(rng, h, n_in + 1)
    w2 = _init_weights(rng, len(k.outputs), h + 1)
    return GeneUnit(kind, inputs, h, w1, w2, k.scale)


def random_simple(rng: np.random.Generator, max_hidden: int = MAX_HIDDEN) -> SimpleBehaviour:
    """A random simple behaviour: random spine, tail and legs units (in that order from ``rng``)."""
    return SimpleBehaviour(*(random_unit(p, rng, max_hidden) for p in PARTS))


def mutate(unit: GeneUnit, rng: np.random.Generator, p_weight: float = 0.1, sigma: float = 0.1,
           p_structure: float = 0.05, max_hidden: int = MAX_HIDDEN) -> GeneUnit:
    """A mutated copy of ``unit``.

    Structure first: with probability ``p_structure`` one change, uniform among those allowed — add an
    unused input (a new W1 column, N(0, σ)), remove an input (|I| ≥ 2; its W1 column goes), add a hidden
    neuron (h < max_hidden; a new W1 row and W2 column, N(0, σ)), remove a hidden neuron (h ≥ 2; its W1 row
    and W2 column go). Every other weight is kept. Then weights: each one, independently with probability
    ``p_weight``, gets + N(0, σ²).
    """
    k = _kind(unit.kind)
    if not (0 <= p_weight <= 1 and 0 <= p_structure <= 1 and sigma >= 0):
        raise ParameterError(f"mutation needs probabilities in [0, 1] and sigma ≥ 0, got p_weight={p_weight}, "
                             f"p_structure={p_structure}, sigma={sigma}")
    inputs, h = list(unit.inputs), unit.hidden
    w1, w2 = unit.W1.copy(), unit.W2.copy()
    if rng.random() < p_structure:
        ops = []
        if len(inputs) < k.n_available:
            ops.append("add_input")
        if len(inputs) > 1:
            ops.append("remove_input")
        if h < max_hidden:
            ops.append("add_hidden")
        if h > 1:
            ops.append("remove_hidden")
        op = ops[int(rng.integers(len(ops)))] if ops else None
        if op == "add_input":
            unused = [i for i in range(k.n_available) if i not in inputs]
            new = unused[int(rng.integers(len(unused)))]
            pos = int(np.searchsorted(inputs, new))
            inputs.insert(pos, new)
            w1 = np.insert(w1, pos, rng.normal(0.0, sigma, size=h), axis=1)
        elif op == "remove_input":
            pos = int(rng.integers(len(inputs)))
            del inputs[pos]
            w1 = np.delete(w1, pos, axis=1)
        elif op == "add_hidden":
            w1 = np.vstack((w1, rng.normal(0.0, sigma, size=(1, w1.shape[1]))))
            w2 = np.insert(w2, h, rng.normal(0.0, sigma, size=w2.shape[0]), axis=1)
            h += 1
        elif op == "remove_hidden":
            j = int(rng.integers(h))
            w1 = np.delete(w1, j, axis=0)
            w2 = np.delete(w2, j, axis=1)
            h -= 1
    if p_weight > 0 and sigma > 0:
        for w in (w1, w2):
            hit = rng.random(w.shape) < p_weight
            w[hit] += rng.normal(0.0, sigma, size=int(hit.sum()))
    return GeneUnit(unit.kind, tuple(inputs), h, w1, w2, unit.scale)


def crossover(a: GeneUnit, b: GeneUnit, rng: np.random.Generator) -> GeneUnit:
    """Child of ``a`` and ``b`` (§5). Same structure (`same_structure`): weights crossed per neuron — for
    each hidden neuron j a fair coin picks one parent, whose incoming row W1[j, :] and outgoing column
    W2[:, j] the child takes together; the output biases W2[:, h] (the outgoing column of the constant
    unit appended to the hidden layer) are taken whole from one parent by one more coin. Otherwise a copy
    of ``a``: callers pass the fitter parent first."""
    if not same_structure(a, b):
        return a.copy()
    h = a.hidden
    pick_b = rng.random(h + 1) < 0.5
    w1 = np.where(pick_b[:h, None], b.W1, a.W1)
    w2 = np.where(pick_b[None, :], b.W2, a.W2)
    return GeneUnit(a.kind, a.inputs, h, w1, w2, a.scale)


def mutate_simple(b: SimpleBehaviour, rng: np.random.Generator, **kw: Any) -> SimpleBehaviour:
    """`mutate` applied to each of spine, tail, legs (in that order)."""
    return SimpleBehaviour(*(mutate(getattr(b, p), rng, **kw) for p in PARTS))


def crossover_simple(a: SimpleBehaviour, b: SimpleBehaviour, rng: np.random.Generator) -> SimpleBehaviour:
    """`crossover` of each part (spine, tail, legs); ``a`` the fitter parent."""
    return SimpleBehaviour(*(crossover(getattr(a, p), getattr(b, p), rng) for p in PARTS))


T = TypeVar("T")


def eliminate_and_immigrate(population: Sequence[T], scores: Sequence[float] | np.ndarray, frac: float,
                            rng: np.random.Generator, make_random: Callable[[np.random.Generator], T]
                            ) -> list[T]:
    """Elimination (§5): drop the floor(frac · N) individuals with the lowest ``scores`` (higher is
    better; ties: the later one goes first) and append as many ``make_random(rng)`` immigrants. The
    survivors keep their order; the size stays N. For eq. 10/11 rankings pass their scores
    (`rank_simple`, `rank_complex`)."""
    n = len(population)
    s = np.asarray(scores, dtype=float)
    if s.shape != (n,):
        raise ParameterError(f"{s.size} scores for a population of {n}")
    if not 0 <= frac <= 1:
        raise ParameterError(f"elimination fraction {frac} is outside [0, 1]")
    if np.any(np.isnan(s)):
        raise ParameterError("scores hold NaN")
    n_drop = int(math.floor(frac * n + 1e-9))
    order = np.lexsort((-np.arange(n), s))  # ascending score; equal scores: later index first
    dropped = set(order[:n_drop].tolist())
    kept = [p for i, p in enumerate(population) if i not in dropped]
    return kept + [make_random(rng) for _ in range(n_drop)]


# ----------------------------------------------------------------------------------------- fitness


def fitness_eq9(heights_mm: Sequence[float] | np.ndarray) -> float:
    """Eq. 9: f = mean(H) / (var(H) + 1), H = {Sh(t) | t > T}, T the first step with Sh(t) < 500 mm;
    heights in mm, var the population variance (ddof 0).

    If Sh never falls below 500 mm, or only at the last step (H empty), f = 0: the lowest value f can
    take (heights ≥ 0), so a rollout that never came down ties with the other failures and the ranking
    (eq. 10) falls through to D and S."""
    h = np.asarray(heights_mm, dtype=float)
    if h.ndim != 1 or not np.all(np.isfinite(h)):
        raise ParameterError("heights must be a 1-D series of finite values (mm)")
    below = np.flatnonzero(h < LANDING_HEIGHT_MM)
    if below.size == 0 or below[0] + 1 >= h.size:
        return 0.0
    hh = h[below[0] + 1:]
    return float(hh.mean() / (hh.var() + 1.0))


def upright_factor(up_z: float, smooth: bool = False) -> float:
    """1 if the upper body's up-axis is within 30° of vertical (up_z ≥ cos 30°), else 0. ``smooth``: a
    linear ramp from 0 at 60° (up_z = 0.5) to 1 at 30°, so evolution sees partial progress."""
    if not math.isfinite(up_z):
        raise ParameterError(f"up-axis z component {up_z} is not finite")
    if not smooth:
        return 1.0 if up_z >= UPRIGHT_COS else 0.0
    lo = math.cos(math.radians(60.0))
    return min(1.0, max(0.0, (up_z - lo) / (UPRIGHT_COS - lo)))


def fitness(heights_mm: Sequence[float] | np.ndarray, up_z: float, smooth: bool = False) -> float:
    """f of eq. 9 × `upright_factor` of the upper body's up-axis z at the end of the rollout (issue 5): a
    steady landing on the side or back scores 0 (or, smooth, less)."""
    return fitness_eq9(heights_mm) * upright_factor(up_z, smooth)


def landing_score(air_up_z: float, clean_frac: float, tilt_deg: float | None, waist_ratio: float | None,
                  landed: bool) -> float:
    """Our fitness for the issue's `landed` rule (``fitness="landing"`` in training; not the paper's):

        F = (1 + ū_td)/2 + c + clip(cos θ / cos 30°, 0, 1) + clip(w / 0.5, 0, 1) + [landed]   ∈ [0, 5]

    ū_td (``air_up_z``): mean up-axis z of the upper and lower body at touchdown (air righting, −1 upside
    down … 1 upright); c (``clean_frac``): the share of the 0.5 s window after touchdown before a part other
    than a foot touched the floor (1: feet only); θ (``tilt_deg``): the upper body's tilt at touchdown +
    0.5 s; w (``waist_ratio``): the waist height then over its standing height. ``tilt_deg`` or
    ``waist_ratio`` None (no touchdown, or the run ended before the window did) scores 0 for those terms.
    Each term is partial credit towards one clause of the rule, so evolution sees progress long before the
    first landing; eq. 9 rewards a steady high waist, which a cat lying on its splayed legs also has."""
    vals = [air_up_z, clean_frac] + [v for v in (tilt_deg, waist_ratio) if v is not None]
    if not all(isinstance(v, int | float) and math.isfinite(v) for v in vals):
        raise ParameterError(f"landing score inputs must be finite numbers, got {vals}")
    f = 0.5 * (1.0 + min(1.0, max(-1.0, air_up_z))) + min(1.0, max(0.0, clean_frac))
    if tilt_deg is not None:
        f += min(1.0, max(0.0, math.cos(math.radians(tilt_deg)) / UPRIGHT_COS))
    if waist_ratio is not None:
        f += min(1.0, max(0.0, waist_ratio / 0.5))
    return f + (1.0 if landed else 0.0)


# ----------------------------------------------------------------------------------------- ranking

RTOL = 1e-3  # keys within this relative difference tie (eq. 10's "f1 = f2")
ATOL = 1e-9  # … or within this absolute difference (values near 0)


@dataclass(frozen=True)
class SimpleResult:
    """The three marks of one rollout (§6.4): f (eq. 9, higher better), D (eq. 7, DTW distance to the
    motion sample, lower better), S (eq. 8, transition-matrix distance, lower better)."""

    f: float
    D: float
    S: float


def _keys(results: Sequence[SimpleResult] | np.ndarray) -> np.ndarray:
    if isinstance(results, np.ndarray):
        k = np.asarray(results, dtype=float)
    else:
        k = np.array([(r.f, r.D, r.S) for r in results], dtype=float).reshape(-1, 3)
    if k.shape[-1] != 3:
        raise ParameterError(f"results need three marks (f, D, S) each, got shape {k.shape}")
    if not np.all(np.isfinite(k)):
        raise ParameterError("results hold non-finite marks")
    return k


def _beats(a: np.ndarray, b: np.ndarray, rtol: float, atol: float) -> np.ndarray:
    """Eq. 10 with tolerances, broadcast over leading axes: True where result a beats result b."""
    d = a - b
    tie = np.abs(d) <= atol + rtol * np.maximum(np.abs(a), np.abs(b))
    f, D, S = (d[..., i] for i in range(3))
    tf, tD, tS = (tie[..., i] for i in range(3))
    return (~tf & (f > 0)) | (tf & ~tD & (D < 0)) | (tf & tD & ~tS & (S < 0))


def compare_simple(a: SimpleResult, b: SimpleResult, rtol: float = RTOL, atol: float = ATOL) -> int:
    """Eq. 10, +1 if ``a`` beats ``b``, −1 if ``b`` beats ``a``, 0 if they tie.

    The rule: f decides unless the two f tie; then D (lower wins) unless they tie; then S (lower wins).
    Two values x, y of a key tie iff |x − y| ≤ atol + rtol · max(|x|, |y|). (Eq. 10 as printed reads
    "M1 < M2 ⇔ D1 < D2" as well as "⇔ f1 < f2"; D and S are distances, so we take smaller as better.)"""
    ka, kb = _keys([a]), _keys([b])
    if _beats(ka, kb, rtol, atol)[0]:
        return 1
    return -1 if _beats(kb, ka, rtol, atol)[0] else 0


def rank_simple(results: Sequence[SimpleResult] | np.ndarray, rtol: float = RTOL, atol: float = ATOL
                ) -> tuple[np.ndarray, np.ndarray]:
    """Rank simple behaviours by eq. 10: (order best first, score per individual, higher better).

    Ties within a tolerance make "beats" intransitive (a ≈ b, b ≈ c, a ≠ c), so no sort key exists in
    general; the score is the net win count, #beaten − #beaten-by over all pairs, which gives exactly the
    lexicographic order whenever eq. 10 is a strict weak order (and equal scores to ties). Equal scores
    keep index order. ``results``: `SimpleResult` list or an (N, 3) array of (f, D, S)."""
    k = _keys(results)
    win = _beats(k[:, None, :], k[None, :, :], rtol, atol)
    score = win.sum(axis=1) - win.sum(axis=0)
    return np.argsort(-score, kind="stable"), score.astype(float)


def rank_complex(results: np.ndarray | Sequence[Sequence[SimpleResult]], rtol: float = RTOL,
                 atol: float = ATOL) -> tuple[np.ndarray, np.ndarray]:
    """Rank complex behaviours by eq. 11: (order best first, score per individual, higher better).

    ``results[n][k]``: complex behaviour n's marks (f, D, S) on training orientation k — an (N, K, 3)
    array or nested `SimpleResult` lists. Eq. 11: N1 < N2 ⇔ bigger(N1, N2) < bigger(N2, N1), with
    bigger(N1, N2) the number of orientations k on which N1's behaviour beats N2's. Our reading:
    "fitness greater" compares by eq. 10 (the paper's fitness combines f with the similarities, §5), and
    the pairwise relation is turned into a rank like `rank_simple`: score = #complex behaviours n beats
    under eq. 11 − #that beat it; equal scores keep index order. (The other reading — count the
    orientations on which N beats the simple behaviour trained there — needs only those K results as a
    row N+1 of ``results``; its score then shows whether N beats them.)"""
    if isinstance(results, np.ndarray):
        k = np.asarray(results, dtype=float)
    else:
        k = np.array([[(r.f, r.D, r.S) for r in row] for row in results], dtype=float)
    if k.ndim != 3:
        raise ParameterError(f"complex results need shape (N, K, 3), got {k.shape}")
    k = _keys(k)
    big = _beats(k[:, None, :, :], k[None, :, :, :], rtol, atol).sum(axis=2)  # bigger(n, m)
    win = big > big.T
    score = win.sum(axis=1) - win.sum(axis=0)
    return np.argsort(-score, kind="stable"), score.astype(float)


# -------------------------------------------------------------------------------------- policy files


def _unit_arrays(prefix: str, u: GeneUnit, out: dict[str, np.ndarray], doc: dict[str, Any]) -> None:
    u.check()
    out[f"{prefix}/inputs"] = np.array(u.inputs, dtype=np.int64)
    out[f"{prefix}/W1"] = u.W1
    out[f"{prefix}/W2"] = u.W2
    doc[prefix] = {"kind": u.kind, "hidden": u.hidden, "scale": u.scale}


def save_policy(path: str | Path, behaviour: SimpleBehaviour | ComplexBehaviour,
                meta: Mapping[str, Any] | None = None) -> Path:
    """Write a behaviour to ``path`` (``.npz``, no pickle) atomically (`felis.files.write_atomic`).

    Arrays ``<unit>/inputs`` (int64), ``<unit>/W1``, ``<unit>/W2`` (float64) for units ``spine``, ``tail``,
    ``legs`` (simple) or ``b<k>/spine`` … and ``compose`` (complex); ``__meta__`` a JSON string
    ``{"format": "felis-landing-policy", "version": 1, "type": "simple"|"complex", "joints": [...],
    "it": [...], "behaviours": K, "units": {unit: {"kind", "hidden", "scale"}}, "meta": meta}``.
    The behaviour is checked first, so a bad one is never written."""
    path = Path(path)
    if path.suffix != ".npz":
        raise PolicyError(f"{path}: a policy file must end in .npz")
    behaviour.check()
    arrays: dict[str, np.ndarray] = {}
    units: dict[str, Any] = {}
    if isinstance(behaviour, SimpleBehaviour):
        kind, n_b, simples = "simple", 1, [("", behaviour)]
    elif isinstance(behaviour, ComplexBehaviour):
        kind, n_b = "complex", len(behaviour.behaviours)
        simples = [(f"b{i}/", b) for i, b in enumerate(behaviour.behaviours)]
        _unit_arrays("compose", behaviour.compose, arrays, units)
    else:
        raise ParameterError(f"cannot save a {type(behaviour).__name__} as a landing policy")
    for pre, b in simples:
        for p in PARTS:
            _unit_arrays(pre + p, getattr(b, p), arrays, units)
    doc = {"format": FORMAT, "version": VERSION, "type": kind, "joints": list(JOINTS), "it": list(IT_NAMES),
           "behaviours": n_b, "units": units, "meta": dict(meta or {})}
    try:
        text = json.dumps(doc, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ParameterError(f"policy metadata is not JSON-serialisable: {e}") from None
    arrays[META_KEY] = np.array(text)
    return write_atomic(path, lambda f: np.savez(f, **arrays), "landing policy", PolicyError)
