"""Landing policies made of parts (issue 21): each cat takes one part at release and keeps it. What
`felis.learning.landing.by_height` (a part by the height sensed) and `felis.learning.landing.by_attitude` (a part by
the attitude, a vote) share. Numpy only: an inference module.

A subclass says which part each cat takes from its inputs IT at its first tick (t < half a tick, the release), by
``choose(it (B, 15)) -> (B,)``; `Latched` runs a batch, `LatchedRule` one cat.
"""

from __future__ import annotations

import numpy as np

from felis.learning.landing.motion import DT  # the control tick (s)


class Latched:
    """A `felis.controllers.landing.LandingBatch` policy over ``policies`` (each a behaviour's ``velocities_many`` or
    ``(IT, t, rows)``): cat b takes ``policies[choose(IT_b)]`` at its first tick and keeps it; each part sees only its
    own cats' rows. One instance per batch run."""

    def __init__(self, policies):
        self.policies = list(policies)
        self.choice: dict[int, int] = {}  # row → part

    def choose(self, it: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def __call__(self, it: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
        new = [i for i, r in enumerate(rows) if t[i] < DT / 2 or int(r) not in self.choice]
        if new:
            for i, k in zip(new, self.choose(it[new]), strict=True):
                self.choice[int(rows[i])] = int(k)
        pick = np.array([self.choice[int(r)] for r in rows], dtype=int)
        v = np.zeros((len(it), 12))
        for k in np.unique(pick):
            g = np.flatnonzero(pick == k)
            p = self.policies[k]
            f = getattr(p, "velocities_many", None)
            v[g] = f(it[g]) if callable(f) else p(it[g], t[g], rows[g])
        return v


class LatchedRule:
    """`Latched` for one cat, a `felis.controllers.landing.LandingController` policy ``(it (15,), t) -> (12,)`` over
    ``rules`` (``(it, t)`` callables): at its first call it takes ``rules[choose(it)]`` and keeps it."""

    def __init__(self, rules):
        self.rules = list(rules)
        self.part: int | None = None

    def choose(self, it: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def __call__(self, it: np.ndarray, t: float) -> np.ndarray:
        it = np.asarray(it, dtype=float)
        if self.part is None or float(t) < DT / 2:
            self.part = int(self.choose(it.reshape(1, -1))[0])
        return self.rules[self.part](it, t)
