"""A cap policy's inference side (issue 21): K closed-loop simple behaviours of the paper's nets, each for the starts
whose up axis lies nearest its centre, mirrored for the other half of the sphere; what `felis.controllers` runs.

`CapPolicy` dispatches a batch of cats (`felis.controllers.landing.LandingBatch`), `CapRule` one cat
(`felis.controllers.landing.LandingController`): at release each cat takes the behaviour whose centre (a unit up axis
with u_y ≥ 0) is nearest the up axis u its IMU reports (roll r, pitch p: u = (−sin p, cos p sin r, cos p cos r),
`felis.learning.landing.library.up_axis`) and keeps it; for u_y < 0 it runs the behaviour on its mirror image
(`mirror_inputs`, `mirror_velocities`), as the library's shelves are mirrored.

**Shifted** (a file whose ``settings`` name ``shift_from_m`` h₁ beside its ``height_m`` H): behaviours made for
drops from h₁, run from H as if released from h₁ later. Each cat holds its joints for s = √(2H/g) − √(2h₁/g),
rounded to whole ticks, then runs its behaviour with the time since release less s and its height input lowered by
(H − h₁) − ½g(t² − (t − s)²), the difference of the two free falls, until that reaches 0 at the touchdown. Without
angular momentum a falling cat's attitude does not depend on its speed, so it turns as it would from h₁; only the
impact is harder. The shift is the file's, for drops from H (a policy by height, `felis.learning.landing.by_height`,
gives it the drops nearest H). The 1 m behaviours run so land 47 and 37 of `random:100` from 3 m, where run as they
are they land 1 and 1 (`bench/landing_caps_height.py`).

**Files** (``bench/landing_caps.py --out`` writes them; `load_caps` reads them): JSON with ``"format":
"felis-landing-caps"``, the build's ``settings`` (``hidden``: the behaviours' hidden neurons per unit, ``height_m``:
the drop height they were evolved for) and ``caps``, one per centre: its ``centre`` and ``genome`` (`genome`'s
order: each unit's W1 then W2, spine, tail, legs). ``--policy caps`` names the shipped file, `SHIPPED_CAPS` (built
for 1 m). How the behaviours are made (imitated from the library, then evolved): `felis.learning.landing.caps`.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.library import up_axis
from felis.learning.landing.motion import DT  # the control tick (s)
from felis.learning.landing.policy import DROP_HEIGHT_M, KINDS, MAX_SPEED, PARTS, GeneUnit, SimpleBehaviour
from felis.rotations import G

FORMAT = "felis-landing-caps"
SHIPPED_CAPS = Path(__file__).parents[1] / "weights" / "landing_caps48-1m.json"  # ``--policy caps``

# Mirror images (left ↔ right; the library's `mirror_motion` for a closed loop): every joint axis is the same on both
# sides, so a mirrored state has the yaw joints' and the legs' rolls negated, left and right legs swapped, and the
# body's roll negated. IT: spine pitch, yaw, tail pitch, yaw, roll, pitch, height, then fl, fr, hl, hr (pitch,
# roll); velocities: spine, tail, then fl, fr, hl, hr (pitch, roll).
_IT_FROM = np.array([0, 1, 2, 3, 4, 5, 6, 9, 10, 7, 8, 13, 14, 11, 12])
_IT_SIGN = np.array([1, -1, 1, -1, -1, 1, 1, 1, -1, 1, -1, 1, -1, 1, -1], dtype=float)
_V_FROM = np.array([0, 1, 2, 3, 6, 7, 4, 5, 10, 11, 8, 9])
_V_SIGN = np.array([1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1], dtype=float)


def mirror_inputs(it: np.ndarray) -> np.ndarray:
    """IT (B, 15) of the mirror image of the cats with IT ``it`` (an involution)."""
    return np.asarray(it)[:, _IT_FROM] * _IT_SIGN


def mirror_velocities(v: np.ndarray) -> np.ndarray:
    """Joint velocities (B, 12) of the mirror image of velocities ``v`` (an involution)."""
    return np.asarray(v)[:, _V_FROM] * _V_SIGN


def nearest_centre(centres: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Index of the centre (K, 3; u_y ≥ 0) nearest each up axis ``u`` (B, 3), mirrored first where u_y < 0."""
    u = np.where((u[:, 1] < 0)[:, None], u * np.array([1.0, -1.0, 1.0]), u)
    return np.argmax(u @ np.asarray(centres).T, axis=1)


def genome(b: SimpleBehaviour) -> np.ndarray:
    """The behaviour's weights as one vector: each unit's W1 then W2, spine, tail, legs."""
    return np.concatenate([w.ravel() for p in PARTS for w in (getattr(b, p).W1, getattr(b, p).W2)])


def with_genome(b: SimpleBehaviour, g: np.ndarray) -> SimpleBehaviour:
    """``b`` with the weights of ``g`` (`genome`'s order); inputs, hidden sizes and scales kept."""
    size = sum(getattr(b, p).W1.size + getattr(b, p).W2.size for p in PARTS)
    if len(g) != size:
        raise ParameterError(f"caps: a genome of {len(g)} weights for a behaviour of {size}")
    units, i = [], 0
    for p in PARTS:
        u = getattr(b, p)
        n1, n2 = u.W1.size, u.W2.size
        units.append(GeneUnit(p, u.inputs, u.hidden, g[i:i + n1].reshape(u.W1.shape),
                              g[i + n1:i + n1 + n2].reshape(u.W2.shape), u.scale))
        i += n1 + n2
    return SimpleBehaviour(*units).check()


def shift_s(height_m: float, built_m: float) -> float:
    """s = √(2H/g) − √(2h₁/g) in whole control ticks, 0 where H ≤ h₁ (module doc, "Shifted")."""
    return round(max(0.0, math.sqrt(2 * max(height_m, 0.0) / G) - math.sqrt(2 * built_m / G)) / DT) * DT


class CapPolicy:
    """Behaviours over caps (module doc): cat b takes, at its first tick, ``behaviours[k]`` with ``centres[k]``
    (up axes with u_y ≥ 0) the nearest its up axis, mirrored when u_y < 0, and keeps it. A `LandingBatch` policy
    (``(IT, t, rows) -> velocities``); one instance per batch run. ``shift`` (H, h₁): behaviours made for drops
    from h₁, run shifted from H (module doc); the choice is then made when a cat starts, s after its release."""

    def __init__(self, centres: np.ndarray, behaviours, shift: tuple[float, float] | None = None):
        self.centres = np.asarray(centres, dtype=float).reshape(-1, 3)
        self.behaviours = list(behaviours)
        if len(self.centres) != len(self.behaviours) or not self.behaviours:
            raise ParameterError(f"caps: {len(self.centres)} centres for {len(self.behaviours)} behaviours")
        if np.any(self.centres[:, 1] < -1e-9):
            raise ParameterError("caps: the centres lie in the half u_y ≥ 0 (the other half runs mirrored)")
        if shift is not None and not (len(shift) == 2 and all(isinstance(x, int | float) and math.isfinite(x)
                                                              and x > 0 for x in shift) and shift[0] >= shift[1]):
            raise ParameterError(f"caps: a shift is from a drop height to a lower one, both positive metres; got "
                                 f"{shift!r}")
        self.shift = None if shift is None else (float(shift[0]), float(shift[1]))
        self.choice: dict[int, tuple[int, bool]] = {}

    def choose(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(behaviour index (B,), mirrored (B,)) for up axes ``u`` (B, 3)."""
        return nearest_centre(self.centres, u), u[:, 1] < 0

    def __call__(self, it: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
        if self.shift is None:
            return self._run(it, t, rows)
        h, h1 = self.shift
        s = shift_s(h, h1)
        v = np.zeros((len(it), 12))
        on = t >= s - 1e-9
        if on.any():
            x, tt = it[on].copy(), t[on]
            x[:, 6] += np.minimum(0.0, 0.5 * G * (tt ** 2 - (tt - s) ** 2) - (h - h1)) / DROP_HEIGHT_M
            v[on] = self._run(x, tt - s, rows[on])
        return v

    def _run(self, it: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
        new = [i for i, r in enumerate(rows) if t[i] < DT / 2 or int(r) not in self.choice]
        if new:
            k, flip = self.choose(up_axis(it[new, 4] * np.pi, it[new, 5] * (np.pi / 2)))
            for i, kk, ff in zip(new, k, flip, strict=True):
                self.choice[int(rows[i])] = (int(kk), bool(ff))
        pick = np.array([self.choice[int(r)] for r in rows], dtype=int).reshape(-1, 2)
        v = np.zeros((len(it), 12))
        for k in np.unique(pick[:, 0]):
            for f in (0, 1):
                g = np.flatnonzero((pick[:, 0] == k) & (pick[:, 1] == f))
                if g.size:
                    x = mirror_inputs(it[g]) if f else it[g]
                    out = self.behaviours[k].velocities_many(x)
                    v[g] = mirror_velocities(out) if f else out
        return v


class CapRule:
    """A cap policy (`CapPolicy`) for one cat: a `felis.controllers.landing.LandingController` policy
    ``(it (15,), t) -> (12,)``. It picks its behaviour at its first call from the IMU's attitude then and keeps it,
    and computes what `CapPolicy` computes for that cat in a batch."""

    kind = "caps"

    def __init__(self, centres: np.ndarray, behaviours, shift: tuple[float, float] | None = None):
        self.batch = CapPolicy(centres, behaviours, shift)

    def __call__(self, it: np.ndarray, t: float) -> np.ndarray:
        return self.batch(np.asarray(it, dtype=float).reshape(1, -1), np.array([float(t)]), np.zeros(1, int))[0]


def template(hidden: int) -> SimpleBehaviour:
    """A simple behaviour of the shape a caps file's genomes fill: every input, ``hidden`` neurons per unit."""
    if not (isinstance(hidden, int) and hidden >= 1):
        raise ParameterError(f"caps: hidden must be a whole number ≥ 1, got {hidden!r}")
    return SimpleBehaviour(*[GeneUnit(p, tuple(range(KINDS[p].n_available)), hidden,
                                      np.zeros((hidden, KINDS[p].n_available + 1)),
                                      np.zeros((len(KINDS[p].outputs), hidden + 1)), MAX_SPEED) for p in PARTS])


def is_caps_file(path: str | Path) -> bool:
    """Whether ``path`` is a JSON file that says it is a cap policy (`json_format`)."""
    return json_format(path) == FORMAT


def json_format(path: str | Path) -> str | None:
    """The ``format`` a JSON file says it has, else None (an unreadable file has none: its reader then says why).
    Every ``.json`` policy name is asked this (a 3 MB motion library takes ~80 ms to parse), so the answer is kept
    per file and version (its size and modification time)."""
    try:
        st = Path(path).stat()
    except OSError:
        return None
    return _says(str(Path(path).resolve()), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=64)
def _says(path: str, size: int, mtime_ns: int) -> str | None:
    try:
        doc = json.loads(Path(path).read_bytes())
    except (OSError, ValueError):
        return None
    return doc.get("format") if isinstance(doc, dict) and isinstance(doc.get("format"), str) else None


def file_shift(d: dict) -> tuple[float, float] | None:
    """(H, h₁) of a caps file's dict whose behaviours run shifted (``settings.shift_from_m``), else None."""
    h1 = d["settings"].get("shift_from_m")
    return None if h1 is None else (d["settings"]["height_m"], h1)


def load_caps(path: str | Path) -> tuple[dict, np.ndarray, list[SimpleBehaviour]]:
    """(the file's dict, centres (K, 3), behaviours) of a caps file (module doc); `ParameterError`, one line naming
    the file, for anything else: not JSON, another format, a genome of the wrong size, a centre off the sphere or in
    the mirrored half, a non-finite weight."""
    p = Path(path)
    try:
        d = json.loads(p.read_text())
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} file")
        t = template(d["settings"]["hidden"])
        caps = d["caps"]
        if not isinstance(caps, list) or not caps:
            raise ValueError("it holds no behaviour")
        centres = np.array([c["centre"] for c in caps], dtype=float).reshape(-1, 3)
        if not np.all(np.isfinite(centres)) or np.any(np.abs(np.linalg.norm(centres, axis=1) - 1) > 1e-6):
            raise ValueError("a centre is not a unit vector")
        genomes = [np.array(c["genome"], dtype=float) for c in caps]
        if not all(np.all(np.isfinite(g)) for g in genomes):
            raise ValueError("a genome holds a weight that is not a finite number")
        behaviours = [with_genome(t, g) for g in genomes]
        CapPolicy(centres, behaviours, file_shift(d))
    except (OSError, ValueError, KeyError, TypeError, ParameterError) as e:
        raise ParameterError(f"caps: {p}: {str(e).removeprefix('caps: ')}") from None
    return d, centres, behaviours


def load_cap_rule(path: str | Path) -> CapRule:
    """`CapRule` of a caps file (`load_caps`'s errors)."""
    d, centres, behaviours = load_caps(path)
    return CapRule(centres, behaviours, file_shift(d))


def load_cap_policy(path: str | Path) -> CapPolicy:
    """`CapPolicy` (a batch's) of a caps file (`load_caps`'s errors)."""
    d, centres, behaviours = load_caps(path)
    return CapPolicy(centres, behaviours, file_shift(d))
