"""Breeding of the landing evolution (seed 000 §5): the next generation from a ranked population —
elites, children by tournament, crossover and mutation, and random immigrants in place of the worst —
and the ranking of a generation's marks by eq. 10 or 11. The draw order from the one generator is
fixed: training is deterministic and resumes bit-identically.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from felis.learning.landing.config import TrainConfig
from felis.learning.landing.nets import (
    crossover,
    crossover_simple,
    eliminate_and_immigrate,
    mutate,
    mutate_simple,
    random_simple,
    random_unit,
    rank_complex,
    rank_simple,
)


def _tournament(kept: Sequence[int], pos: np.ndarray, size: int, rng: np.random.Generator) -> int:
    """The best (lowest rank position) of ``size`` survivors drawn uniformly with replacement."""
    picks = [kept[int(rng.integers(len(kept)))] for _ in range(size)]
    return min(picks, key=lambda i: pos[i])


def next_generation(pop: Sequence[Any], order: np.ndarray, score_: np.ndarray, cfg: TrainConfig,
                    rng: np.random.Generator, make_random: Callable[[np.random.Generator], Any],
                    cross: Callable[[Any, Any, np.random.Generator], Any],
                    mut: Callable[[Any, np.random.Generator], Any]) -> list[Any]:
    """Elites (best first) + children + immigrants (module doc); the size stays len(pop)."""
    n = len(pop)
    pos = np.empty(n, dtype=int)
    pos[order] = np.arange(n)
    elites = [pop[i] for i in order[:cfg.n_elite]]
    rest = eliminate_and_immigrate(list(range(n)), score_, cfg.elimination_frac, rng, make_random)
    kept = list(rest[:n - cfg.n_eliminate])  # survivors' indices, then the immigrants
    immigrants = rest[n - cfg.n_eliminate:]
    children = []
    for _ in range(n - len(elites) - len(immigrants)):
        a = _tournament(kept, pos, cfg.tournament, rng)
        if rng.random() < cfg.p_crossover:
            b = _tournament(kept, pos, cfg.tournament, rng)
            if pos[b] < pos[a]:
                a, b = b, a
            child = cross(pop[a], pop[b], rng)
        else:
            child = pop[a]
        children.append(mut(child, rng))
    return elites + children + list(immigrants)


def _mutation_kw(cfg: TrainConfig) -> dict:
    return {"p_weight": cfg.p_weight, "sigma": cfg.sigma, "p_structure": cfg.p_structure,
            "max_hidden": cfg.max_hidden}


def breed_simple(pop, order, score_, cfg, rng):
    kw = _mutation_kw(cfg)
    return next_generation(pop, order, score_, cfg, rng, lambda r: random_simple(r, cfg.max_hidden),
                           crossover_simple, lambda b, r: mutate_simple(b, r, **kw))


def breed_compose(pop, order, score_, cfg, rng):
    kw = _mutation_kw(cfg)
    return next_generation(pop, order, score_, cfg, rng, lambda r: random_unit("compose", r, cfg.max_hidden),
                           crossover, lambda u, r: mutate(u, r, **kw))


def rank_marks(marks: np.ndarray, use_similarity: bool) -> tuple[np.ndarray, np.ndarray]:
    """`rank_simple` (N, 3+) or `rank_complex` (N, K, 3+) on (f, D, S); by f alone (D = S = 0) when
    ``use_similarity`` is False."""
    m = np.array(marks[..., :3], dtype=float)
    if not use_similarity:
        m[..., 1:] = 0.0
    return rank_simple(m) if m.ndim == 2 else rank_complex(m)
