"""Landing policies by attitude (issue 21): at release each cat takes, of a few whole policies, the one that landed
most of the training drops started near its attitude, and keeps it. What the default landing policy, ``caps+library``
(`felis.learning.landing.by_height`), runs at each height: from 1 m the cap policy or the motion library
(`learning/weights/landing_vote-1m.json`), from 3 m the library or the cap policy evolved for 3 m
(`learning/weights/landing_vote-3m.json`). Numpy only: an inference module.

**The vote.** A vote file holds, for N training drops (``random:N`` draws on seeds no evaluation uses), each drop's
unit up axis p_n at release and whether each of the K parts landed it, l_nk ∈ {0, 1}. A cat whose IMU reports the up
axis u (roll r, pitch p: u = (−sin p, cos p sin r, cos p cos r), `felis.learning.landing.library.up_axis`) takes

    k* = argmax_k Σ_n w_n l_nk,   w_n = exp(−½ (∠(u, p_n) / σ)²),

the part that landed most near u, weighed by a Gaussian of the angle (σ: the file's ``sigma_deg``, chosen by
leave-one-seed-out on the training seeds). Both u and the p_n are folded into the half u_y ≥ 0 first: a start and its
mirror image are the same start for every part (the library's shelves and the cap policies are mirrored). On a tie
(no training drop near u, or equal votes) the first part is taken: the file lists the fallback first. It is the
library's own rule for choosing a motion (a vote of which lands the probes near the attitude), one level up.

**Why.** The library and the cap policies fail on different starts. On `random:100` seeds 0–7 from 3 m the library
lands 85.5 on average and the 3 m cap policy 71.6, but one or the other lands 96.5; from 1 m the cap policy lands
85.9 and the library 73.1, one or the other 93.0. The votes, taken on 4 800 other drops, land what docs/landing.md
("Policies by attitude") measures.

**Files** (``bench/landing_vote.py --out`` writes them; `load_vote` reads them): JSON with ``"format":
"felis-landing-vote"``, ``height_m``, ``parts`` (policy names: ``library``, or a caps file's name in the vote file's
folder), ``sigma_deg``, ``probes`` (``up``: N unit vectors, ``landed``: N rows of K 0/1), and how it was made.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.library import up_axis
from felis.learning.landing.parts import Latched, LatchedRule

FORMAT = "felis-landing-vote"
_WEIGHTS = Path(__file__).parents[1] / "weights"
SHIPPED_VOTES = (_WEIGHTS / "landing_vote-1m.json", _WEIGHTS / "landing_vote-3m.json")  # the default's, by height


def fold(u: np.ndarray) -> np.ndarray:
    """Up axes (B, 3) mirrored into the half u_y ≥ 0."""
    u = np.array(u, dtype=float).reshape(-1, 3)
    u[:, 1] = np.abs(u[:, 1])
    return u


def vote(probes: np.ndarray, landed: np.ndarray, sigma_deg: float, u: np.ndarray) -> np.ndarray:
    """The part (B,) each up axis ``u`` (B, 3) takes (module doc): argmax_k Σ_n w_n l_nk over the probes' up axes
    (N, 3) and their landings (N, K), the first part on a tie."""
    cos = np.clip(fold(u) @ fold(probes).T, -1.0, 1.0)
    w = np.exp(-0.5 * (np.arccos(cos) / math.radians(sigma_deg)) ** 2)
    score = w @ np.asarray(landed, dtype=float)
    k = np.argmax(score, axis=1)
    k[score[np.arange(len(k)), k] <= score[:, 0] + 1e-12] = 0  # a tie: the first part
    return k


class Vote:
    """A vote (module doc) over K parts: probes' up axes (N, 3), their landings (N, K), σ in degrees."""

    def __init__(self, probes, landed, sigma_deg: float):
        self.probes = np.asarray(probes, dtype=float).reshape(-1, 3)
        self.landed = np.asarray(landed, dtype=float)
        if self.landed.ndim != 2 or len(self.landed) != len(self.probes) or self.landed.shape[1] < 2 \
                or not len(self.probes):
            raise ParameterError(f"landing vote: {len(self.probes)} probes with landings of shape "
                                 f"{self.landed.shape}; needs one row of at least 2 parts a probe")
        if not (np.all(np.isfinite(self.probes)) and np.all(np.abs(np.linalg.norm(self.probes, axis=1) - 1) < 1e-6)):
            raise ParameterError("landing vote: a probe's up axis is not a unit vector")
        if not np.all(np.isin(self.landed, (0.0, 1.0))):
            raise ParameterError("landing vote: a landing is not 0 or 1")
        if not (isinstance(sigma_deg, int | float) and math.isfinite(sigma_deg) and 0 < sigma_deg <= 90):
            raise ParameterError(f"landing vote: sigma_deg must be in (0, 90], got {sigma_deg!r}")
        self.sigma_deg = float(sigma_deg)

    @property
    def parts(self) -> int:
        return self.landed.shape[1]

    def choose(self, u: np.ndarray) -> np.ndarray:
        return vote(self.probes, self.landed, self.sigma_deg, u)

    def choose_it(self, it: np.ndarray) -> np.ndarray:
        """The part for each row of IT (B, 15), from its roll and pitch."""
        it = np.asarray(it, dtype=float).reshape(-1, it.shape[-1])
        return self.choose(up_axis(it[:, 4] * math.pi, it[:, 5] * (math.pi / 2)))


class ByAttitude(Latched):
    """Batch policies by attitude (module doc): cat b takes, at its first tick, ``policies[k]`` that ``vote`` picks
    for its up axis, and keeps it (`felis.learning.landing.parts.Latched`). Each part is a
    `felis.controllers.landing.LandingBatch` policy (a behaviour's ``velocities_many``, or ``(IT, t, rows)``) and sees
    the batch's rows; one instance per batch run."""

    def __init__(self, v: Vote, policies):
        self.vote = v
        super().__init__(policies)
        if len(self.policies) != v.parts:
            raise ParameterError(f"landing vote: {v.parts} parts voted on, {len(self.policies)} policies given")

    def choose(self, it: np.ndarray) -> np.ndarray:
        return self.vote.choose_it(it)


class ByAttitudeRule(LatchedRule):
    """`ByAttitude` for one cat, a `felis.controllers.landing.LandingController` policy ``(it (15,), t) -> (12,)``:
    at its first call it takes the rule (``(it, t)`` callables) the vote picks for its attitude and keeps it."""

    kind = "by-attitude"

    def __init__(self, v: Vote, rules):
        self.vote = v
        super().__init__(rules)
        if len(self.rules) != v.parts:
            raise ParameterError(f"landing vote: {v.parts} parts voted on, {len(self.rules)} rules given")

    def choose(self, it: np.ndarray) -> np.ndarray:
        return self.vote.choose_it(it)


def is_vote_file(path: str | Path) -> bool:
    """Whether ``path`` is a JSON file that says it is a vote (`felis.learning.landing.cap_policy.json_format`)."""
    from felis.learning.landing.cap_policy import json_format

    return json_format(path) == FORMAT


def load_vote(path: str | Path) -> tuple[dict, Vote, list[str]]:
    """(the file's dict, its `Vote`, its parts as policy names: ``library`` or a caps file's path) of a vote file
    (module doc); `ParameterError`, one line naming the file, for anything else (not JSON, another format, a part
    that is not ``library`` or a file beside it, probes or landings of the wrong shape, a σ out of range). Read once
    per file version (its size and modification time): the default reads its votes for every cat it makes."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError as e:
        raise ParameterError(f"landing vote: {p}: {e.strerror or e}") from None
    return _load_vote(str(p), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _load_vote(path: str, size: int, mtime_ns: int) -> tuple[dict, Vote, list[str]]:
    p = Path(path)
    try:
        d = json.loads(p.read_text())
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} file")
        h = d["height_m"]
        if not (isinstance(h, int | float) and math.isfinite(h) and h > 0):
            raise ValueError(f"height_m must be a positive number of metres, got {h!r}")
        parts = []
        for name in d["parts"]:
            if name == "library":
                parts.append(name)
                continue
            f = p.parent / str(name)
            if Path(name).name != name or not f.is_file():
                raise ValueError(f"part {name!r} is neither 'library' nor a file beside it")
            parts.append(str(f))
        v = Vote(np.array(d["probes"]["up"], dtype=float), np.array(d["probes"]["landed"], dtype=float),
                 d["sigma_deg"])
        if v.parts != len(parts):
            raise ValueError(f"{len(parts)} parts named, landings for {v.parts}")
    except (OSError, ValueError, KeyError, TypeError, ParameterError) as e:
        raise ParameterError(f"landing vote: {p}: {str(e).removeprefix('landing vote: ')}") from None
    return d, v, parts


def vote_rule(path: str | Path, library, drop_height: float | None = None) -> ByAttitudeRule:
    """The vote file's policy for one cat: its parts as `felis.learning.landing.library.LibraryRule` (timed for
    ``drop_height``) and `felis.learning.landing.cap_policy.CapRule`."""
    from felis.learning.landing.cap_policy import load_cap_rule
    from felis.learning.landing.library import LibraryRule

    _, v, names = load_vote(path)
    return ByAttitudeRule(v, [LibraryRule(library, drop_height) if n == "library" else load_cap_rule(n)
                              for n in names])


def vote_batch(path: str | Path, library, heights, n_ticks: int, speed, lib_batch=None) -> ByAttitude:
    """The vote file's policy for a batch whose drops are from ``heights`` (m, one per cat): its parts as one
    `felis.learning.landing.library.LibraryBatch` (``n_ticks``, joint ``speed``; or ``lib_batch``, shared) and
    `felis.learning.landing.cap_policy.CapPolicy`."""
    from felis.learning.landing.cap_policy import load_cap_policy
    from felis.learning.landing.library import LibraryBatch

    _, v, names = load_vote(path)
    lib = lib_batch if lib_batch is not None else LibraryBatch(library, heights, n_ticks, speed)
    return ByAttitude(v, [lib if n == "library" else load_cap_policy(n) for n in names])
