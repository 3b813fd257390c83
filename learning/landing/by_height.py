"""Landing policies by drop height (issue 21): at release each cat takes the policy made for the height nearest the
height it senses then, and keeps it. What the default landing policy, ``caps+library``, is: at the cap policy's
height (1 m) and at the motion library's other shelves' (3 m) the shipped vote by attitude made for that height
(`felis.learning.landing.by_attitude`: the cap policy or the library from 1 m, the library or the 3 m cap policy from
3 m); without a vote for a height, the cap policy (`felis.learning.landing.cap_policy`) at its own height and the
library's shelves (`felis.learning.landing.library`) at the others. Numpy only: an inference module.

**Which height.** The height h a cat senses at release is its nets' height input (IT[6]·3 m,
`felis.learning.landing.policy.normalise_inputs`): measured in simulation, the operator's drop height on hardware
(`felis.controllers.landing.LandingController`'s free-fall prediction). Of the parts' heights h_k it takes
argmin_k |ln(h_k / h)|, the nearest by the ratio (fall times scale with √h), as the library picks its shelf. Between
1 m and 3 m the boundary is √3 ≈ 1.73 m.

**Why.** Measured on `random:100` seeds 0–7 (docs/landing.md, "Policies by attitude"): from 1 m the cap policy lands
85.9 on average and the library 73.1, the vote between them 92.5; from 3 m the library lands 85.5, behaviours evolved
for 3 m from the 1 m ones run shifted (`learning/weights/landing_caps48-3m.json`) 71.6, the vote 94.25.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.parts import Latched, LatchedRule
from felis.learning.landing.policy import DROP_HEIGHT_M

NAME = "caps+library"  # ``--policy caps+library``: the default where both parts are shipped


def nearest_height(heights: Sequence[float], h) -> np.ndarray:
    """Index of the height in ``heights`` nearest each sensed height ``h`` (B,) by the ratio, argmin |ln(h_k / h)|
    (a height at or below 0 counts as 1 mm)."""
    h = np.maximum(np.atleast_1d(np.asarray(h, dtype=float)), 1e-3)
    return np.argmin(np.abs(np.log(np.asarray(heights, dtype=float)[None, :] / h[:, None])), axis=1)


def _check(heights, parts) -> np.ndarray:
    heights = np.asarray(heights, dtype=float).reshape(-1)
    if len(heights) != len(parts) or not len(parts):
        raise ParameterError(f"landing: {len(heights)} heights for {len(parts)} policies")
    if not np.all(np.isfinite(heights) & (heights > 0)) or len(set(heights.tolist())) != len(heights):
        raise ParameterError(f"landing: by-height policies need distinct positive heights, got {heights.tolist()}")
    return heights


class ByHeight(Latched):
    """Batch policies by height (module doc): cat b takes, at its first tick, ``policies[k]`` with ``heights[k]`` the
    nearest the height it senses, and keeps it (`felis.learning.landing.parts.Latched`). Each part is a
    `felis.controllers.landing.LandingBatch` policy (a behaviour's ``velocities_many``, or ``(IT, t, rows)``) and sees
    the batch's rows; one instance per batch run."""

    def __init__(self, heights: Sequence[float], policies: Sequence):
        self.heights = _check(heights, policies)
        super().__init__(policies)

    def choose(self, it: np.ndarray) -> np.ndarray:
        return nearest_height(self.heights, it[:, 6] * DROP_HEIGHT_M)


class ByHeightRule(LatchedRule):
    """`ByHeight` for one cat, a `felis.controllers.landing.LandingController` policy ``(it (15,), t) -> (12,)``:
    at its first call it takes the rule (``(it, t)`` callables) of the height nearest the one it senses and keeps
    it."""

    kind = "by-height"

    def __init__(self, heights: Sequence[float], rules: Sequence):
        self.heights = _check(heights, rules)
        super().__init__(rules)

    def choose(self, it: np.ndarray) -> np.ndarray:
        return nearest_height(self.heights, it[:, 6] * DROP_HEIGHT_M)


def caps_library_heights(caps: str | Path, library) -> tuple[float, list[float]]:
    """(the cap policy's height, the library's other shelf heights) for ``caps+library`` from a caps file and a
    `felis.learning.landing.library.MotionLibrary`; one line if the library has no other height."""
    from felis.learning.landing.cap_policy import load_caps

    h = float(load_caps(caps)[0]["settings"]["height_m"])
    rest = [x for x in library.heights if x != h]
    if not rest:
        raise ParameterError(f"{NAME}: the library has no shelf at another height than the cap policy's {h:g} m")
    return h, rest


def _votes_by_height(votes) -> dict[float, Path]:
    """{height: vote file} of the vote files among ``votes`` that exist (`felis.learning.landing.by_attitude`)."""
    from felis.learning.landing.by_attitude import load_vote

    out: dict[float, Path] = {}
    for f in votes:
        if Path(f).is_file():
            out[float(load_vote(f)[0]["height_m"])] = Path(f)
    return out


def caps_library_rule(caps: str | Path, library, drop_height: float | None = None,
                      votes: Sequence[str | Path] | None = None) -> ByHeightRule:
    """``caps+library`` for one cat: at each height the vote of ``votes`` (the shipped ones by default) made for it
    (`felis.learning.landing.by_attitude.vote_rule`: the library or a cap policy by attitude), else
    `felis.learning.landing.cap_policy.CapRule` at the caps file's height and the library's
    `felis.learning.landing.library.LibraryRule` (timed for ``drop_height``) at each other shelf's."""
    from felis.learning.landing.by_attitude import SHIPPED_VOTES, vote_rule
    from felis.learning.landing.cap_policy import load_cap_rule
    from felis.learning.landing.library import LibraryRule

    h, rest = caps_library_heights(caps, library)
    by = _votes_by_height(SHIPPED_VOTES if votes is None else votes)
    plain = [load_cap_rule(caps), *[LibraryRule(library, drop_height) for _ in rest]]
    return ByHeightRule([h, *rest], [vote_rule(by[x], library, drop_height) if x in by else p
                                     for x, p in zip([h, *rest], plain, strict=True)])


def caps_library_batch(caps: str | Path, library, heights, n_ticks: int, speed,
                       votes: Sequence[str | Path] | None = None) -> ByHeight:
    """``caps+library`` for a batch whose drops are from ``heights`` (m, one per cat): at each height the vote made
    for it (as `caps_library_rule`), else `CapPolicy` at the caps file's height and one `LibraryBatch` (``n_ticks``,
    joint ``speed``; shared with the votes) at the library's other shelves' heights."""
    from felis.learning.landing.by_attitude import SHIPPED_VOTES, vote_batch
    from felis.learning.landing.cap_policy import load_cap_policy
    from felis.learning.landing.library import LibraryBatch

    h, rest = caps_library_heights(caps, library)
    by = _votes_by_height(SHIPPED_VOTES if votes is None else votes)
    lib = LibraryBatch(library, heights, n_ticks, speed)
    plain = [load_cap_policy(caps), *[lib] * len(rest)]
    return ByHeight([h, *rest], [vote_batch(by[x], library, heights, n_ticks, speed, lib) if x in by else p
                                 for x, p in zip([h, *rest], plain, strict=True)])
