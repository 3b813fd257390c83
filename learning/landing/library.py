"""A library of whole-body landing motions (issue 21): the per-drop optimum of many start attitudes, and at
release the motion that lands most often near the attitude the IMU reports. Numpy only at run time (an
inference module, which controllers may import); `build_library` (the search) needs the simulation.

**Why it works.** A dropped cat starts at rest, so what it does next depends on its drop height and on where
"up" points in its body frame, u = Rᵀ e_z = (−sin p, cos p sin r, cos p cos r) for R = Rz(yaw)·Ry(pitch)·Rx(roll),
and not on the yaw (the floor is the same every way). The cat is left–right symmetric: a start with
u = (u_x, −u_y, u_z) is the mirror image of one with u, and the mirror image of a motion lands it
(`mirror_motion`: spine and tail yaw, leg roll and the touchdown posture's shared roll change sign; checked
on every shipped entry). So a shelf of motions searched for attitudes with u_y ≥ 0 covers the sphere.

**What the policy senses**: the IMU's roll and pitch at release (in the nets' inputs IT) and the drop height,
which the operator gives (as the free-fall height estimate on hardware already needs; without it, the waist
height at release picks the nearer shelf). Then it runs open loop: the chosen motion's velocity table
(`felis.learning.landing.motion.motion_table`), timed for the drop's fall.

**Which motion** (`Shelf.choose`). The optimum's motions are tuned to their drop and often at the edge: a
motion searched for an attitude 10° away lands only about half the time (seed-0 optimum at 3 m, measured). So
each shelf also holds probes, a denser Fibonacci grid of attitudes, and which motions (entries and their mirror
images, within `EVAL_RADIUS_DEG`) land each probe. For an attitude u the policy takes the candidate c that
maximises Σₚ wₚ·[c lands p] over the probes within `RADIUS_DEG`, wₚ = exp(−½(∠(u, p)/`SIGMA_DEG`)²), ties to the
nearest entry; where no nearby probe is landed by anything, the nearest entry that landed its own drop (else the
nearest entry). An attitude with u_y < 0 is mirrored first and its choice mirrored back. A shelf whose probes are
denser than the library's (``felis train landing-library --add-probes``) may vote with its own, narrower σ.

**File** (`load_library`, JSON): ``{"format": FORMAT, "version": 1, "made_by", ["added", "extended_by",
"probes_added", "rebuilt", "joined", "rechecked", "extended", "filled",] "radius_deg", "sigma_deg", "shelves":
[{"height_m", ["sigma_deg",] "entries": [{"up", "drop", "landed", "motion_x"}], "probes": [{"up", "lands"}]}]}``;
``lands`` lists candidate ids, 2·entry + (1 if mirrored). Made by ``felis train landing-library``.

**Votes file** (the same format and version): the votes of another library file taken again on another cat or
physics step (`bench/landing_revote.py`), which candidates land each probe there; its motions and probes are that
library's. ``{"format", "version", "votes_of": {"file", "sha256"}, "revoted", "shelves": [{"height_m", "lands":
[[ids], …]}]}``: ``file`` is the library's path relative to the votes file's folder, ``sha256`` its bytes' (a
library rebuilt since is refused), one ``lands`` list per probe of the shelf of that height; a shelf it does not
list keeps the library's vote. `load_library` reads either kind; `votes_dict` writes one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.motion import DIMS, DT, N_WAYPOINTS, motion_table
from felis.rotations import G

FORMAT = "felis-landing-library"
VERSION = 1
DEFAULT_LIBRARY = Path(__file__).parents[1] / "weights" / "landing_library.json"
RADIUS_DEG = 15.0  # probes that vote for a candidate
SIGMA_DEG = 3.0  # their weight's fall-off: chosen on random:100 seeds 2 and 3 (docs/landing.md; was 6°)
EVAL_RADIUS_DEG = 30.0  # a candidate is tried on the probes this close to its own attitude
_MIRROR_WAYPOINT = np.array([1, -1, 1, -1, 1, -1, 1, -1], dtype=float)  # spine/tail yaw, leg roll change sign


def up_axis(roll: float | np.ndarray, pitch: float | np.ndarray) -> np.ndarray:
    """The world's up axis in the body frame, u = Rᵀ e_z, from roll and pitch (rad; R = Rz·Ry·Rx): (…, 3)."""
    r, p = np.asarray(roll, dtype=float), np.asarray(pitch, dtype=float)
    return np.stack([-np.sin(p), np.cos(p) * np.sin(r), np.cos(p) * np.cos(r)], axis=-1)


def drop_up(d) -> np.ndarray:
    """`up_axis` of a `felis.scenarios.drop.Drop` (its yaw plays no part)."""
    return up_axis(math.radians(d.roll_deg), math.radians(d.pitch_deg))


def mirror_up(u: np.ndarray) -> np.ndarray:
    """The mirror image (y → −y) of up axes (…, 3)."""
    return np.asarray(u, dtype=float) * np.array([1.0, -1.0, 1.0])


def mirror_motion(x: np.ndarray) -> np.ndarray:
    """The mirror image (left ↔ right) of motions x (…, 55) of `felis.learning.landing.motion` (module doc).

    Every joint axis of the cat is the same on both sides (``sim/models/cat.xml``), and the legs of a pair move
    together: mirroring flips the sign of the yaw joints (spine, tail) and of the legs' roll in every waypoint, and
    the pairs' shared roll of the touchdown posture; pitches, the return time and the splay stay."""
    x = np.array(x, dtype=float)
    n = N_WAYPOINTS * 8
    x[..., :n] = (x[..., :n].reshape(*x.shape[:-1], N_WAYPOINTS, 8) * _MIRROR_WAYPOINT).reshape(*x.shape[:-1], n)
    x[..., n + 2] *= -1.0  # front pair's shared roll
    x[..., n + 5] *= -1.0  # hind pair's (the posture: front pitch, roll, splay, hind pitch, roll, splay)
    return x


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (deg) between unit vectors a (…, 3) and b (M, 3): (…, M)."""
    return np.degrees(np.arccos(np.clip(np.asarray(a) @ np.asarray(b).T, -1.0, 1.0)))


def _half(u: np.ndarray) -> tuple[np.ndarray, bool]:
    """(the unit up axis ``u`` in the half the shelves hold, u_y ≥ 0; whether it was mirrored there)."""
    u = np.asarray(u, dtype=float)
    u = u / np.linalg.norm(u)
    return (mirror_up(u), True) if u[1] < 0 else (u, False)


@dataclass
class Shelf:
    """The motions for one drop height (module doc): ``up`` (E, 3) the entries' attitudes (u_y ≥ 0), ``x``
    (E, 55) their motions, ``landed`` (E,) whether each landed its own drop, ``probe_up`` (P, 3) and ``lands``
    (P, 2E) bool: candidate c (2·entry + mirrored) lands probe p."""

    height_m: float
    up: np.ndarray
    x: np.ndarray
    landed: np.ndarray
    probe_up: np.ndarray
    lands: np.ndarray
    drops: list | None = None  # the entries' drops (dicts), for the record
    sigma_deg: float | None = None  # this shelf's vote width (its probes' spacing); None: the library's

    def candidates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(up (2E, 3), x (2E, 55), landed (2E,)): each entry, then its mirror image, interleaved."""
        up = np.stack([self.up, mirror_up(self.up)], axis=1).reshape(-1, 3)
        x = np.stack([self.x, mirror_motion(self.x)], axis=1).reshape(-1, DIMS)
        return up, x, np.repeat(self.landed, 2)

    def choose(self, u: np.ndarray, radius_deg: float = RADIUS_DEG, sigma_deg: float = SIGMA_DEG,
               exclude: int | None = None) -> tuple[np.ndarray, int]:
        """(the motion x (55,), the candidate id chosen) for the up axis ``u`` (3,) (module doc). ``exclude``: a
        probe left out of the vote (cross-validation)."""
        u, flip = _half(u)
        cand_up, cand_x, cand_landed = self.candidates()
        near = angles_deg(u, cand_up)
        c = -1
        if len(self.probe_up):
            a = angles_deg(u, self.probe_up)
            voters = np.flatnonzero(a <= radius_deg)
            if exclude is not None:
                voters = voters[voters != exclude]
            if voters.size:
                w = np.exp(-0.5 * (a[voters] / sigma_deg) ** 2)
                score = w @ self.lands[voters]
                if score.max() > 0:  # ties relative to the best: far probes' weights can be far below 1e-12
                    best = np.flatnonzero(score >= score.max() * (1.0 - 1e-9))
                    c = int(best[np.argmin(near[best])])
        if c < 0:
            pool = np.flatnonzero(cand_landed) if cand_landed.any() else np.arange(len(cand_up))
            c = int(pool[np.argmin(near[pool])])
        x = cand_x[c]
        if flip:
            x, c = mirror_motion(x), c ^ 1
        return x, c

    def near(self, u: np.ndarray, radius_deg: float = EVAL_RADIUS_DEG, vote_radius_deg: float = RADIUS_DEG,
             sigma_deg: float = SIGMA_DEG) -> np.ndarray:
        """Motions (K, 55) to start a search for the attitude ``u`` from (the warm-started per-drop optimum,
        `felis.learning.landing.optimum`): `choose`'s motion first, then every candidate within ``radius_deg``
        of ``u``, nearest first; each in ``u``'s frame (mirrored for u_y < 0, as `choose` does)."""
        u, flip = _half(u)
        cand_up, cand_x, _ = self.candidates()
        c = self.choose(u, vote_radius_deg, sigma_deg)[1]
        a = angles_deg(u, cand_up)
        within = np.flatnonzero(a <= radius_deg)
        within = within[np.argsort(a[within], kind="stable")]
        xs = cand_x[np.concatenate([[c], within[within != c]])]
        return mirror_motion(xs) if flip else xs


class MotionLibrary:
    """Shelves of motions by drop height (module doc); ``choose(u, height)`` → the motion for that start."""

    def __init__(self, shelves: list[Shelf], radius_deg: float = RADIUS_DEG, sigma_deg: float = SIGMA_DEG,
                 meta: dict | None = None):
        if not shelves:
            raise ParameterError("motion library: no shelves")
        self.shelves = sorted(shelves, key=lambda s: s.height_m)
        self.radius_deg, self.sigma_deg = float(radius_deg), float(sigma_deg)
        self.meta = meta or {}

    @property
    def heights(self) -> list[float]:
        return [s.height_m for s in self.shelves]

    def shelf(self, height_m: float) -> Shelf:
        """The shelf of the nearest height (by the ratio: fall times scale with √h)."""
        h = max(float(height_m), 1e-3)
        return min(self.shelves, key=lambda s: abs(math.log(s.height_m / h)))

    def choose(self, u: np.ndarray, height_m: float) -> np.ndarray:
        s = self.shelf(height_m)
        return s.choose(u, self.radius_deg, s.sigma_deg or self.sigma_deg)[0]

    def near(self, u: np.ndarray, height_m: float, radius_deg: float = EVAL_RADIUS_DEG) -> np.ndarray:
        """`Shelf.near` on the shelf for ``height_m``, with this library's vote."""
        s = self.shelf(height_m)
        return s.near(u, radius_deg, self.radius_deg, s.sigma_deg or self.sigma_deg)

    def as_dict(self) -> dict:
        shelves = []
        for s in self.shelves:
            entries = [{"up": [round(float(v), 6) for v in s.up[i]],
                        **({"drop": s.drops[i]} if s.drops else {}),
                        "landed": bool(s.landed[i]), "motion_x": [float(v) for v in s.x[i]]}
                       for i in range(len(s.up))]
            probes = [{"up": [round(float(v), 6) for v in s.probe_up[p]],
                       "lands": [int(c) for c in np.flatnonzero(s.lands[p])]} for p in range(len(s.probe_up))]
            shelves.append({"height_m": s.height_m, **({} if s.sigma_deg is None else {"sigma_deg": s.sigma_deg}),
                            "entries": entries, "probes": probes})
        return {"format": FORMAT, "version": VERSION, **self.meta, "radius_deg": self.radius_deg,
                "sigma_deg": self.sigma_deg, "shelves": shelves}


def _numbers(v, shape: tuple, what: str) -> np.ndarray:
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(f"{what} must be numbers") from None
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ParameterError(f"{what} must be {shape[0] if shape else 1} finite numbers")
    return a


def library_from_dict(doc) -> MotionLibrary:
    """A `MotionLibrary` from its JSON form (module doc); a fault is one `ParameterError` line (without the file)."""
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ParameterError(f"not a landing motion library (format {FORMAT!r})")
    if doc.get("version") != VERSION:
        raise ParameterError(f"library version {doc.get('version')!r} is not supported (felis reads {VERSION})")
    rs = [doc.get(k, d) for k, d in (("radius_deg", RADIUS_DEG), ("sigma_deg", SIGMA_DEG))]
    if not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in rs):
        raise ParameterError("radius_deg and sigma_deg must be positive numbers")
    shelves = []
    if not isinstance(doc.get("shelves"), list) or not doc["shelves"]:
        raise ParameterError("'shelves' must be a non-empty list")
    for k, s in enumerate(doc["shelves"]):
        where = f"shelf {k}"
        if not isinstance(s, dict):
            raise ParameterError(f"{where} is not an object")
        h = s.get("height_m")
        if isinstance(h, bool) or not isinstance(h, int | float) or not (math.isfinite(h) and h > 0):
            raise ParameterError(f"{where}: height_m must be a positive number")
        entries, probes = s.get("entries"), s.get("probes", [])
        if not isinstance(entries, list) or not entries or not isinstance(probes, list):
            raise ParameterError(f"{where}: needs a non-empty 'entries' list and a 'probes' list")
        fast = _shelf_arrays(entries, probes)  # the whole shelf at once; None: find the fault item by item below
        if fast is not None:
            U, X, landed, drops, P, lands = fast
        else:
            U, X, landed, drops, P, lands = _shelf_items(entries, probes, where)
        if np.any(np.abs(np.linalg.norm(U, axis=1) - 1.0) > 1e-3):
            raise ParameterError(f"{where}: every 'up' must be a unit vector")
        sig = s.get("sigma_deg")
        if sig is not None and (isinstance(sig, bool) or not isinstance(sig, int | float)
                                or not (math.isfinite(sig) and sig > 0)):
            raise ParameterError(f"{where}: sigma_deg must be a positive number")
        shelves.append(Shelf(float(h), U, X, landed, P, lands, drops if all(d is not None for d in drops) else None,
                             None if sig is None else float(sig)))
    meta = {k: doc[k] for k in ("made_by", "design", "grid", "search", "added", "extended_by", "probes_added",
                                     "rebuilt", "joined", "rechecked", "extended", "filled", "revoted") if k in doc}
    return MotionLibrary(shelves, float(rs[0]), float(rs[1]), meta)


def _shelf_arrays(entries: list, probes: list):
    """A well-formed shelf's (up, x, landed, drops, probe_up, lands) in a few numpy calls (the shipped library's
    ~14 000 items: 0.1 s, where `_shelf_items` takes 0.3 s), or None when anything is off."""
    try:
        if not all(type(e) is dict for e in entries) or not all(type(p) is dict for p in probes):
            return None
        U = np.array([e.get("up") for e in entries], dtype=float)
        X = np.array([e.get("motion_x") for e in entries], dtype=float)
        P = np.array([p.get("up") for p in probes], dtype=float).reshape(-1, 3)
        ids = [p.get("lands", []) for p in probes]
        if not all(type(c) is list for c in ids):
            return None
        flat = [c for cs in ids for c in cs]
    except (TypeError, ValueError):
        return None
    n_cand = 2 * len(entries)
    if (U.shape != (len(entries), 3) or X.shape != (len(entries), DIMS) or P.shape != (len(probes), 3)
            or not (np.isfinite(U).all() and np.isfinite(X).all() and np.isfinite(P).all())
            or not set(map(type, flat)) <= {int} or (flat and not 0 <= min(flat) <= max(flat) < n_cand)):
        return None
    lands = np.zeros((len(probes), n_cand), dtype=bool)
    lands[np.repeat(np.arange(len(probes)), [len(c) for c in ids]), np.array(flat, dtype=np.int64)] = True
    landed = np.array([bool(e.get("landed", False)) for e in entries])
    return U, X, landed, [e.get("drop") for e in entries], P, lands


def _shelf_items(entries: list, probes: list, where: str):
    """`_shelf_arrays`, item by item: the first fault is a `ParameterError` naming it."""
    up, x, landed, drops = [], [], [], []
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            raise ParameterError(f"{where}, entry {i} is not an object")
        up.append(_numbers(e.get("up"), (3,), f"{where}, entry {i}: up"))
        x.append(_numbers(e.get("motion_x"), (DIMS,), f"{where}, entry {i}: motion_x"))
        landed.append(bool(e.get("landed", False)))
        drops.append(e.get("drop"))
    n_cand = 2 * len(entries)
    lands = np.zeros((len(probes), n_cand), dtype=bool)
    pup = []
    for p, pr in enumerate(probes):
        if not isinstance(pr, dict):
            raise ParameterError(f"{where}, probe {p} is not an object")
        pup.append(_numbers(pr.get("up"), (3,), f"{where}, probe {p}: up"))
        ids = pr.get("lands", [])
        if not isinstance(ids, list) or not all(isinstance(c, int) and not isinstance(c, bool)
                                                and 0 <= c < n_cand for c in ids):
            raise ParameterError(f"{where}, probe {p}: lands must be candidate ids 0…{n_cand - 1}")
        lands[p, ids] = True
    return np.array(up), np.array(x), np.array(landed), drops, np.array(pup).reshape(-1, 3), lands


_LOADED: dict[tuple, MotionLibrary] = {}  # the last files read, by (path, mtime, size): a command reads one 2-3 times
_LOADED_KEEP = 2


def load_library(path: str | Path = DEFAULT_LIBRARY) -> MotionLibrary:
    """A library file (module doc); every fault is one line naming the file. A file this process has read, unchanged
    since (same modification time and size), is not parsed again (the shipped library: ~0.3 s); each call returns
    its own copy, so a caller that edits one changes nothing another sees."""
    from felis.files import read_json

    path = Path(path)
    try:
        st = path.stat()
        key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    except OSError:
        key = None  # read_json says why
    if key in _LOADED:
        return _copy(_LOADED[key])
    doc = read_json(path, "landing motion library", ParameterError, " (make one: felis train landing-library)")
    try:
        lib = _with_votes(doc, path) if isinstance(doc, dict) and "votes_of" in doc else library_from_dict(doc)
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from None
    if key is not None and "votes_of" not in lib.meta:  # a votes file is checked against its library every time
        while len(_LOADED) >= _LOADED_KEEP:
            _LOADED.pop(next(iter(_LOADED)))
        _LOADED[key] = _copy(lib)
    return lib


def _sha256(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def _with_votes(doc: dict, path: Path) -> MotionLibrary:
    """The library a votes file (module doc) names, with its shelves' votes replaced; faults are one line."""
    if doc.get("format") != FORMAT or doc.get("version") != VERSION:
        raise ParameterError(f"not a landing votes file (format {FORMAT!r}, version {VERSION})")
    of = doc["votes_of"]
    if not isinstance(of, dict) or not isinstance(of.get("file"), str) or not isinstance(of.get("sha256"), str):
        raise ParameterError("'votes_of' must hold the library's 'file' and its 'sha256'")
    base = path.parent / of["file"]
    if not base.is_file():
        raise ParameterError(f"votes of {base}: no such library file")
    if _sha256(base) != of["sha256"]:
        raise ParameterError(f"votes of {base}, which has changed since (its sha256 differs): take the vote again "
                             "(bench/landing_revote.py)")
    lib = load_library(base)
    if "votes_of" in lib.meta:
        raise ParameterError(f"votes of {base}, itself a votes file: name the library")
    shelves = doc.get("shelves")
    if not isinstance(shelves, list) or not shelves:
        raise ParameterError("'shelves' must be a non-empty list")
    for k, s in enumerate(shelves):
        h = s.get("height_m") if isinstance(s, dict) else None
        shelf = next((x for x in lib.shelves if isinstance(h, int | float) and x.height_m == h), None)
        if shelf is None:
            raise ParameterError(f"shelf {k}: {base.name} has no shelf of height {h!r} m (it has "
                                 f"{', '.join(f'{x:g}' for x in lib.heights)})")
        lands, n_cand = s.get("lands"), 2 * len(shelf.up)
        if not isinstance(lands, list) or len(lands) != len(shelf.probe_up):
            raise ParameterError(f"shelf {k} ({h:g} m): 'lands' must be one list per probe "
                                 f"({len(shelf.probe_up)})")
        new = np.zeros_like(shelf.lands)
        for p, ids in enumerate(lands):
            if not isinstance(ids, list) or not all(type(c) is int and 0 <= c < n_cand for c in ids):
                raise ParameterError(f"shelf {k} ({h:g} m), probe {p}: lands must be candidate ids 0…{n_cand - 1}")
            new[p, ids] = True
        shelf.lands = new
    base_meta = {k: v for k, v in lib.meta.items() if k != "revoted"}  # the library's own vote is not this one
    lib.meta = {**base_meta, "votes_of": of, **({"revoted": doc["revoted"]} if "revoted" in doc else {})}
    return lib


def votes_dict(lib: MotionLibrary, base: str | Path, out: str | Path, heights, meta: dict | None = None) -> dict:
    """A votes file (module doc) for ``out``: ``lib``'s votes on its shelves of ``heights`` over the library file
    ``base`` (whose motions and probes ``lib`` must have)."""
    import os

    base, out = Path(base), Path(out)
    ref = load_library(base)
    shelves = []
    for h in heights:
        s, r = lib.shelf(h), ref.shelf(h)
        if s.height_m != r.height_m or s.up.shape != r.up.shape or s.probe_up.shape != r.probe_up.shape:
            raise ParameterError(f"the votes' {h:g} m shelf is not {base}'s")
        shelves.append({"height_m": s.height_m, "lands": [[int(c) for c in np.flatnonzero(row)] for row in s.lands]})
    return {"format": FORMAT, "version": VERSION, **(meta or {}),
            "votes_of": {"file": os.path.relpath(base.resolve(), out.resolve().parent), "sha256": _sha256(base)},
            "shelves": shelves}


def _copy(lib: MotionLibrary) -> MotionLibrary:
    """``lib`` with nothing shared: `copy.deepcopy`'s result in 27 ms against 72 ms for the shipped library (its
    entries' drops are flat records)."""
    import copy

    def record(d):
        if not isinstance(d, dict):
            return copy.deepcopy(d)
        return {k: v if isinstance(v, str | int | float | bool | None) else copy.deepcopy(v) for k, v in d.items()}

    return MotionLibrary([Shelf(s.height_m, s.up.copy(), s.x.copy(), s.landed.copy(), s.probe_up.copy(),
                                s.lands.copy(), None if s.drops is None else [record(d) for d in s.drops],
                                s.sigma_deg) for s in lib.shelves], lib.radius_deg, lib.sigma_deg,
                         copy.deepcopy(lib.meta))


def is_library_file(path: str | Path) -> bool:
    """Whether ``path`` is a JSON file that says it is a motion library (a motion file is the other kind of
    ``.json`` policy); an unreadable file is not (its reader then says why)."""
    import json

    try:
        with open(path, "rb") as f:
            doc = json.loads(f.read())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and doc.get("format") == FORMAT


# ------------------------------------------------------------------------------------------ as policies


class LibraryRule:
    """The library as a `felis.controllers.landing.LandingController` policy ``(it, t) -> (12,)``: at the first
    tick (t < half a tick: the release) it reads roll and pitch from IT and picks its motion (module doc); then
    it plays that motion. ``drop_height`` (m): the drop's, for the shelf and the timing; None: the waist height at
    release picks the shelf and the motion keeps that shelf's timing.

    It follows the motion's path, not its velocity samples: at time t it returns (p(t) − p(t′))/(t − t′), with p
    the motion's joint offsets from the release pose (the velocity table summed, linear between ticks) and t′ the
    last call, so the controller's integrated targets are p(t) whatever the ticks' jitter (servos on a wall clock:
    a tick 7 ms late once turned a landing of the demo's drop into a fall on the back after touchdown). On a
    simulation's exact ticks, one after the other, that is the table's row to rounding, and it returns the row
    itself, as `LibraryBatch` plays it: a sequential drop is then the batch's bit for bit."""

    kind = "library"

    def __init__(self, library: MotionLibrary, drop_height: float | None = None, steps: int | None = None,
                 speed: float | np.ndarray | None = None):
        from felis.learning.landing.policy import MAX_SPEED

        self.library, self.drop_height = library, drop_height
        self.speed = MAX_SPEED if speed is None else speed
        self.steps = steps
        self.table: np.ndarray | None = None
        self.x: np.ndarray | None = None

    def start(self, it: np.ndarray) -> None:
        from felis.learning.landing.policy import DROP_HEIGHT_M

        roll, pitch = float(it[4]) * math.pi, float(it[5]) * math.pi / 2
        waist = float(it[6]) * DROP_HEIGHT_M
        h = self.drop_height if self.drop_height is not None else self.library.shelf(waist).height_m
        self.x = self.library.choose(up_axis(roll, pitch), h)
        steps = self.steps or int(round((math.sqrt(2 * h / G) + 1.0) / DT)) + 1  # the fall and 1 s
        self.table = motion_table(self.x, h, self.speed, steps)
        self._path = np.cumsum(self.table, axis=0) * DT  # p at each tick (row 0 is 0: the release pose)
        self._t, self._p = 0.0, np.zeros(12)

    def path(self, t: float) -> np.ndarray:
        """p(t): the motion's joint offsets (rad) at t s after release, linear between ticks."""
        k = _tick(float(t))
        if k is not None:  # on a tick (a simulation's clock): the tick's row exactly
            return self._path[min(k, len(self._path) - 1)]
        s = max(0.0, float(t) / DT)
        i = min(int(s), len(self._path) - 1)
        j = min(i + 1, len(self._path) - 1)
        return self._path[i] + (s - i) * (self._path[j] - self._path[i])

    def __call__(self, it, t: float) -> np.ndarray:
        t = float(t)
        if self.table is None or t < DT / 2:
            self.start(np.asarray(it, dtype=float))
        p = self.path(t)
        dt = t - self._t
        k, k0 = _tick(t), _tick(self._t)
        if k is not None and k0 == k - 1 and k < len(self.table):  # the next exact tick: its row, as the batch
            v = self.table[k]
        else:
            v = (p - self._p) / dt if dt > 0 else np.zeros(12)
        self._t, self._p = t, p
        return v


def _tick(t: float) -> int | None:
    """The control tick ``t`` s after release is on (a simulation's clock), or None (off the tick grid)."""
    s = max(0.0, t / DT)
    k = round(s)
    return k if abs(s - k) < 1e-6 else None


class LibraryBatch:
    """The library as a `felis.controllers.landing.LandingBatch` policy ``(IT, t, rows) -> (G, 12)``: each row
    picks its motion at its first tick from its IT, for its drop's height ``heights[row]``."""

    def __init__(self, library: MotionLibrary, heights, n_ticks: int, speed: float | np.ndarray):
        self.library = library
        self.heights = np.asarray(heights, dtype=float)
        self.n_ticks, self.speed = int(n_ticks), speed
        self.tables: np.ndarray | None = None

    def __call__(self, it: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
        if self.tables is None:
            self.tables = np.zeros((len(self.heights), self.n_ticks, 12))
        first = rows[np.asarray(t) < DT / 2]
        if first.size:
            sel = np.isin(rows, first)
            up = up_axis(it[sel, 4] * math.pi, it[sel, 5] * math.pi / 2)
            for r, u in zip(rows[sel], up, strict=True):
                x = self.library.choose(u, self.heights[r])
                self.tables[r] = motion_table(x, self.heights[r], self.speed, self.n_ticks)
        k = np.clip(np.rint(np.asarray(t) / DT).astype(int), 0, self.n_ticks - 1)
        return self.tables[rows, k]
