r"""Motion samples for the landing nets: hand-written spine rules, tuned per training orientation.

Source: seed 000 (``000_d27ba58563dbcb8e.txt``) §6.4 (task) and §6.5 (motion samples); summary in
``shared/reference/methods.md``, "Evolved landing nets". The paper fixes the tail and the legs and writes
a spine rule Vs1 = f1(t), Vs2 = f2(t) per training orientation ("the waist moves close to a circle"),
adjusted by hand until the cat roughly rights itself; the features of those motions are the samples the
evolved nets imitate (eq. 7–8). Here the rules are data (`SpineRule`: piecewise-constant spine
velocities) and the hand adjustment is a small search (`tune_rule`), seeded with the paper's circle.

**Task** (§6.4): dropped at rest with the lowest point `TRAIN_HEIGHT_M` = 3 m up, 1/100 s control steps
(`DT`), `STEPS` = 200 of them (2 s: 0.78 s of fall, then the landing), through
`felis.controllers.landing.LandingController` (velocities integrated into targets; spine held straight
once the waist is below 0.5 m, §6.2).

**Orientations** (`TRAINING_ORIENTATIONS`, (roll, pitch, yaw) degrees, R = Rz(yaw)·Ry(pitch)·Rx(roll)).
The paper draws its 7 starting poses as arrows in its Fig. 4 and lists no angles, so this is our choice:
upside-down-ish starts spread over the lower half of the sphere of up-axes::

    1  (180,   0, 0)   on its back
    2  (135,   0, 0)   on its back, rolled 45° towards its right side
    3  (-135,  0, 0)   on its back, rolled 45° towards its left side
    4  (90,    0, 0)   on its right side
    5  (-90,   0, 0)   on its left side
    6  (180,  45, 0)   on its back, nose 45° down
    7  (180, -45, 0)   on its back, nose 45° up

(yaw only turns the heading, which does not matter to a fall, so it is 0.)

**Rule** (`SpineRule`): segments (t_end, Vs1, Vs2); from the end of the previous segment (0 for the
first) until t_end the spine pitch and yaw move at (Vs1, Vs2) rad/s, after the last segment they hold;
tail and legs get 0 (held at the release pose, all joints 0). The search builds rules from a path of
`N_WAYPOINTS` spine angle waypoints (pitch, yaw) within ±`WAYPOINT_LIMIT` rad (`rule_from_waypoints`):
each leg of the path is one segment, as many whole ticks long as the faster-moving joint needs at
`MAX_SPEED` (the XL330's no-load speed), so the integrated targets reach each waypoint exactly.

**Objective** (`rule_score`, higher is better, range −4…4)::

    J = 2·ū_air + u_end + [landed]

ū_air: the mean of the upper and lower body's up-axis z (cos of the tilt from vertical) at the first
step with the waist below 500 mm, where the spine rule hands over to the landing rule: how far the cat
turned face-down in the air, the paper's criterion (§6.6, Figs. 8 and 10). u_end: the upper body's
up-axis z at the end of the 200 steps (on its feet or not, after bounces). [landed]: 1 if the drop meets
`felis.scenarios.verdicts.landed` (feet only for 0.5 s after touchdown, tilt ≤ 30°, waist above half standing).

**Search** (`tune_rule`): cross-entropy method over the 2·`N_WAYPOINTS` waypoint angles: `POPULATION`
rules per generation drawn from a diagonal Gaussian (clipped to the limits), the best `ELITES` refit
the mean and spread; generation 0 also holds the hand-written seeds, circles (diamonds, at full speed)
of the spine in both directions. ``budget`` rollouts in all (default `BUDGET`); the best rule seen wins.

**Regenerate** (deterministic per seed; 6 min 50 s wall, 8 CPU-minutes, on 2 shared cores), one line
(split here at the backslash)::

    python -c "from felis.learning.landing.samples import make_samples; \
    make_samples('learning/weights/landing_samples.json')"

It writes ``landing_samples.json`` (format, the command, the objective, per orientation the rule, its
waypoints, score and outcome) and ``landing_samples.npz`` beside it (same stem: ``vectors`` (7, T, J, 3)
from `felis.learning.landing.features.MotionRecorder`, ``heights_mm`` (7, T), ``up_z`` (7, T)).

**Results** (seed 0, budget 720 rollouts per orientation). start tilt: the up-axis' angle from vertical
at release; ū_air and its ≈tilt (acos ū_air): how far the cat has turned when the waist passes 500 mm,
0.07 s before touchdown; tilt +0.5 s: the `landed` rule's tilt, 0.5 s after touchdown; u_end: up-axis z
after 2 s; non-foot contact: the first body other than a foot on the floor within the 0.5 s::

    ==  ===============  =====  ======  =====  ======  =====  =====  ===========  ======
    #   orientation      start  ū_air   ≈tilt  J       tilt   u_end  non-foot     landed
                         tilt°          air°           +0.5s°        contact
    ==  ===============  =====  ======  =====  ======  =====  =====  ===========  ======
    1   (180, 0, 0)        180   -0.50    120    0.01      2   1.00  upper_body   no
    2   (135, 0, 0)        135   -0.25    104    0.51      3   1.00  tail         no
    3   (-135, 0, 0)       135   -0.12     97    0.76      6   1.00  lower_body   no
    4   (90, 0, 0)          90    0.79     38    2.58     15   1.00  upper_body   no
    5   (-90, 0, 0)         90    0.88     28    1.52    116  -0.24  fl_leg       no
    6   (180, 45, 0)       135   -0.25    105    0.49      2   1.00  head         no
    7   (180, -45, 0)      135   -0.59    126   -0.18      7   1.00  tail         no
    ==  ===============  =====  ======  =====  ======  =====  =====  ===========  ======

No rule lands by the `landed` rule, and only from the sides (4, 5) does the cat come near face-down in
the air: the spine alone turns the body by 9–62° before touchdown (geometric phase of a bent, twisting
body with no angular momentum; legs held straight, weak XL330 servos lagging their targets by up to
0.7 rad at full speed). The body then strikes the floor first and six of seven rules leave the cat
on its feet (tilt ≤ 15° after 0.5 s, up-axis z 1.00 after 2 s) by rolling over on the bounce; rule 5
turns furthest in the air but ends on its side. That is "roughly rights itself" (§6.5) in this model:
the samples are motions to imitate, not landings to copy. The mirror pairs (2, 3) and (4, 5) differ
only by the search's draws (the model is left–right symmetric).
"""

from __future__ import annotations

import json
import math
import os
import time
import zipfile
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from felis.errors import ParameterError
from felis.files import MAX_ARRAY_BYTES, check_readable, write_atomic
from felis.learning.common.evaluator import run_jobs
from felis.learning.landing.nets import LANDING_HEIGHT_MM
from felis.learning.landing.policy import JOINTS, MAX_SPEED

TRAINING_ORIENTATIONS: tuple[tuple[float, float, float], ...] = (
    (180.0, 0.0, 0.0),
    (135.0, 0.0, 0.0),
    (-135.0, 0.0, 0.0),
    (90.0, 0.0, 0.0),
    (-90.0, 0.0, 0.0),
    (180.0, 45.0, 0.0),
    (180.0, -45.0, 0.0),
)
TRAIN_HEIGHT_M = 3.0
STEPS = 200
DT = 0.01

N_WAYPOINTS = 6
WAYPOINT_LIMIT = 1.0  # rad, inside the spine's ±60° (1.047 rad)
POPULATION = 24
ELITES = 6
BUDGET = 720  # rollouts per orientation: 30 generations
INIT_SPREAD = 0.8  # rad, the first generation's standard deviation
MIN_SPREAD = 0.1  # rad, floor of the spread so the search keeps exploring

FORMAT = "felis-landing-samples"
VERSION = 1
DEFAULT_SAMPLES_PATH = Path(__file__).parents[1] / "weights" / "landing_samples.json"
COMMAND = ("python -c \"from felis.learning.landing.samples import make_samples; "
           "make_samples('learning/weights/landing_samples.json')\"")
OBJECTIVE = ("J = 2*mean(up_z upper, up_z lower at the first step with waist < 500 mm) + up_z upper at "
             "the end + (1 if landed else 0)")
_EPS_T = 1e-6  # s: segment boundaries are compared to this (control times are sums of 0.01 s)
_N_JOINTS = len(JOINTS)


# ------------------------------------------------------------------------------------------ the rule
def _number(v: Any, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ParameterError(f"{what} must be a finite number, got {v!r}")
    return float(v)


@dataclass(frozen=True)
class SpineRule:
    """Vs1 = f1(t), Vs2 = f2(t) as data (module doc): ``segments`` = ((t_end, Vs1, Vs2), …), t_end in s,
    strictly increasing and > 0, velocities in rad/s within ±`MAX_SPEED`. Segment k covers
    [t_end(k−1), t_end(k)); after the last one the spine holds. Calling it gives the 12 joint velocities
    of `LandingController`'s policy: spine from the segment, tail and legs 0."""

    segments: tuple[tuple[float, float, float], ...]
    _ends: np.ndarray = field(init=False, repr=False, compare=False)
    _vel: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        try:
            segs = tuple(tuple(s) for s in self.segments)
        except TypeError:
            raise ParameterError("spine rule: segments must be a list of (t_end, vs1, vs2)") from None
        out, last = [], 0.0
        for i, s in enumerate(segs):
            if len(s) != 3:
                raise ParameterError(f"spine rule: segment {i} must be (t_end, vs1, vs2), got {len(s)} values")
            t, v1, v2 = (_number(x, f"spine rule: segment {i} {n}") for x, n in zip(s, ("t_end", "vs1", "vs2"),
                                                                                    strict=True))
            if not t > last:
                raise ParameterError(f"spine rule: segment {i} ends at {t:g} s, not after {last:g} s")
            if max(abs(v1), abs(v2)) > MAX_SPEED + 1e-9:
                raise ParameterError(f"spine rule: segment {i} velocity ({v1:g}, {v2:g}) rad/s exceeds the "
                                     f"servo's {MAX_SPEED:.2f} rad/s")
            out.append((t, v1, v2))
            last = t
        object.__setattr__(self, "segments", tuple(out))
        object.__setattr__(self, "_ends", np.array([s[0] for s in out]))
        object.__setattr__(self, "_vel", np.array([s[1:] for s in out]).reshape(-1, 2))

    @property
    def duration(self) -> float:
        return self.segments[-1][0] if self.segments else 0.0

    def spine(self, t: float) -> np.ndarray:
        """(Vs1, Vs2) at time t (s since release)."""
        k = int(np.searchsorted(self._ends, float(t) + _EPS_T, side="right"))
        return self._vel[k].copy() if k < len(self._ends) else np.zeros(2)

    def __call__(self, it: Any, t: float) -> np.ndarray:
        v = np.zeros(_N_JOINTS)
        v[:2] = self.spine(t)
        return v

    def as_dict(self) -> dict:
        return {"segments": [list(s) for s in self.segments]}

    @staticmethod
    def from_dict(d: Any) -> SpineRule:
        if not isinstance(d, dict) or "segments" not in d or not isinstance(d["segments"], list):
            raise ParameterError("spine rule: expected an object with a list 'segments' of [t_end, vs1, vs2]")
        if any(not isinstance(s, list) for s in d["segments"]):
            raise ParameterError("spine rule: each segment must be a list [t_end, vs1, vs2]")
        return SpineRule(tuple(tuple(s) for s in d["segments"]))


def rule_from_waypoints(waypoints: np.ndarray | Sequence[Sequence[float]], speed: float = MAX_SPEED,
                        dt: float = DT) -> SpineRule:
    """A rule moving the spine (pitch, yaw) from straight through ``waypoints`` (N, 2) rad in turn: each leg
    lasts the whole number of ticks the faster-moving joint needs at ``speed``, both joints at constant
    velocity, so the integrated targets land on each waypoint. Waypoints are rounded to 1 mrad first
    (readable data); a repeated waypoint adds no segment."""
    w = np.round(np.asarray(waypoints, dtype=float), 3)
    if w.ndim != 2 or w.shape[1] != 2 or not np.all(np.isfinite(w)):
        raise ParameterError(f"spine waypoints must be finite (N, 2) angles, got shape {w.shape}")
    segs, t, prev = [], 0, np.zeros(2)
    for p in w:
        d = p - prev
        ticks = math.ceil(float(np.abs(d).max()) / (speed * dt) - 1e-9)
        if ticks <= 0:
            continue
        t += ticks
        v = d / (ticks * dt)
        segs.append((round(t * dt, 6), float(v[0]), float(v[1])))
        prev = p
    return SpineRule(tuple(segs))


def circle_waypoints(sign: int, amplitude: float = WAYPOINT_LIMIT, n: int = N_WAYPOINTS) -> np.ndarray:
    """The paper's hand rule, the waist "close to a circle": bend (pitch) then go round a diamond in
    (pitch, yaw), ``sign`` +1 or −1 for the direction; ``n`` waypoints."""
    ring = [(amplitude, 0.0), (0.0, sign * amplitude), (-amplitude, 0.0), (0.0, -sign * amplitude)]
    return np.array([ring[i % 4] for i in range(n)])


# ------------------------------------------------------------------------------------------ rollout
@dataclass
class Rollout:
    """One drop under a policy: what the samples and the trainer need.

    ``vectors`` (T, J, 3): `MotionRecorder` segment vectors per tick; ``heights_mm`` (T,): waist height
    (eq. 9's Sh); ``up_z`` / ``lower_up_z`` (T,): up-axis z of the upper / lower body per tick;
    ``final_up_z``: the upper body's up-axis z after the last step; ``outcome``: the `LandingOutcome`.
    T = the rollout's ticks (`STEPS` by default; a run that diverged is padded with its last tick)."""

    orientation: tuple[float, float, float]
    height_m: float
    vectors: np.ndarray
    heights_mm: np.ndarray
    up_z: np.ndarray
    lower_up_z: np.ndarray
    final_up_z: float
    outcome: Any

    @property
    def landed(self) -> bool:
        return bool(self.outcome.landed)


def _orientation(o: Any) -> tuple[float, float, float]:
    try:
        vals = tuple(o)
    except TypeError:
        raise ParameterError(f"orientation must be (roll, pitch, yaw) degrees, got {o!r}") from None
    if len(vals) != 3:
        raise ParameterError(f"orientation must be (roll, pitch, yaw) degrees, got {len(vals)} values")
    return tuple(_number(v, f"orientation {n}") for v, n in zip(vals, ("roll", "pitch", "yaw"), strict=True))


def _pad(a: np.ndarray, n: int) -> np.ndarray:
    if len(a) >= n:
        return a[:n]
    if len(a) == 0:
        return np.zeros((n, *a.shape[1:]))
    return np.concatenate([a, np.repeat(a[-1:], n - len(a), axis=0)])


def rollout(sim: Any, orientation: Sequence[float], policy_callable: Any, height_m: float = TRAIN_HEIGHT_M,
            steps: int = STEPS) -> Rollout:
    """Drop the cat of ``sim`` (a `felis.learning.landing.evaluate.LandingSim`) from ``height_m`` in
    ``orientation`` (roll, pitch, yaw degrees) for ``steps`` ticks of `DT` under ``policy_callable``: a callable
    (it, t) → (12,) joint velocities (a `SpineRule`) or an object with ``velocities(it)`` (an evolved
    behaviour), or a ready `LandingController`. Deterministic for equal inputs."""
    from felis.controllers.landing import LandingController
    from felis.learning.landing.features import MotionRecorder
    from felis.scenarios.drop import Drop

    o = _orientation(orientation)
    h = _number(height_m, "drop height")
    policy = policy_callable
    controller = policy if isinstance(policy, LandingController) else LandingController(policy)
    robot = sim.robot
    recorder = MotionRecorder(robot.model)
    upper, lower = robot.root_body, robot.body_id("lower_body")
    heights: list[float] = []
    ups: list[tuple[float, float]] = []

    def monitor(state, command) -> None:
        d = robot.data
        recorder.record(d)
        heights.append(1000.0 * float(state.height))
        ups.append((float(d.xmat[upper, 8]), float(d.xmat[lower, 8])))

    out = sim.run(Drop(*o, h), controller, monitors=[monitor], duration=steps * DT)
    u = _pad(np.array(ups, dtype=float).reshape(-1, 2), steps)
    final = float(robot.data.xmat[upper, 8]) if out.why != "physics diverged" else float(u[-1, 0])
    return Rollout(o, h, _pad(recorder.vectors(), steps), _pad(np.array(heights, dtype=float), steps),
                   u[:, 0].copy(), u[:, 1].copy(), final, out)


def air_up_z(r: Rollout) -> float:
    """ū_air (module doc): mean up-axis z of upper and lower body at the first step with the waist below
    500 mm (the last step if it never gets there)."""
    below = np.flatnonzero(r.heights_mm < LANDING_HEIGHT_MM)
    i = int(below[0]) if below.size else len(r.heights_mm) - 1
    return 0.5 * float(r.up_z[i] + r.lower_up_z[i])


def rule_score(r: Rollout) -> float:
    """The tuning objective J = 2·ū_air + u_end + [landed] (module doc); −4…4, higher is better."""
    if not (np.isfinite(r.final_up_z) and np.all(np.isfinite(r.up_z))):
        return -math.inf
    return 2.0 * air_up_z(r) + r.final_up_z + (1.0 if r.landed else 0.0)


# ------------------------------------------------------------------------------------------ search
def _search(sim: Any, orientation: Sequence[float], rng: np.random.Generator, budget: int
            ) -> tuple[SpineRule, np.ndarray, float, Rollout]:
    if isinstance(budget, bool) or not isinstance(budget, int) or budget < 1:
        raise ParameterError(f"tuning budget must be a whole number of rollouts ≥ 1, got {budget!r}")
    dims = 2 * N_WAYPOINTS
    mean, spread = np.zeros(dims), np.full(dims, INIT_SPREAD)
    seeds = [circle_waypoints(+1).ravel(), circle_waypoints(-1).ravel()]
    best: tuple[float, np.ndarray, SpineRule, Rollout] | None = None
    used = 0
    while used < budget:
        n = min(POPULATION, budget - used)
        x = np.clip(mean + spread * rng.standard_normal((n, dims)), -WAYPOINT_LIMIT, WAYPOINT_LIMIT)
        if used == 0:
            for i, s in enumerate(seeds[:n]):
                x[i] = s
        elif best is not None:
            x[0] = best[1]  # the best so far competes again (its score is deterministic)
        scores = np.empty(n)
        for i in range(n):
            rule = rule_from_waypoints(x[i].reshape(-1, 2))
            r = rollout(sim, orientation, rule)
            scores[i] = rule_score(r)
            if best is None or scores[i] > best[0]:
                best = (float(scores[i]), np.round(x[i], 3), rule, r)
        used += n
        elite = x[np.argsort(-scores, kind="stable")[:min(ELITES, n)]]
        mean, spread = elite.mean(axis=0), np.maximum(elite.std(axis=0), MIN_SPREAD)
    assert best is not None
    return best[2], best[1].reshape(-1, 2), best[0], best[3]


def tune_rule(sim: Any, orientation: Sequence[float], rng: np.random.Generator, budget: int = BUDGET
              ) -> SpineRule:
    """The spine rule that rights the cat best from ``orientation`` by `rule_score`, found by the
    cross-entropy search of the module doc in ``budget`` rollouts; deterministic for a given ``rng`` state."""
    return _search(sim, orientation, rng, budget)[0]


# ------------------------------------------------------------------------------------------ samples
@dataclass
class Sample:
    """One motion sample (§6.5): the rule for one training orientation and the motion it makes (a spine
    rule, or a whole-body motion `felis.learning.landing.optimum.MotionRule`: `felis.learning.landing.wholebody`)."""

    orientation: tuple[float, float, float]
    height_m: float
    rule: Any
    vectors: np.ndarray  # (T, J, 3)
    heights_mm: np.ndarray  # (T,)
    final_up_z: float
    landed: bool
    up_z: np.ndarray | None = None  # (T,) upper body up-axis z per tick
    score: float | None = None  # rule_score
    air_up_z: float | None = None


def _tune_one(args) -> dict:
    index, orientation, seed, budget = args
    from felis.learning.landing.evaluate import LandingSim

    sim = LandingSim()
    try:
        t0 = time.perf_counter()
        rng = np.random.default_rng([seed, index])
        rule, waypoints, score, r = _search(sim, orientation, rng, budget)
        return {"index": index, "rule": rule, "waypoints": waypoints, "score": score, "rollout": r,
                "seconds": time.perf_counter() - t0}
    finally:
        sim.close()


def make_samples(out_json: str | Path, seed: int = 0, workers: int | None = None, budget: int = BUDGET,
                 progress: Callable[[str], None] | None = None) -> list[Sample]:
    """Tune one rule per `TRAINING_ORIENTATIONS` entry (a process pool over orientations, ``workers``
    processes, default every core), write the rules and outcomes to ``out_json`` and the arrays to the
    ``.npz`` beside it; results are identical whatever the worker count (each orientation has its own
    generator, seeded by (seed, index))."""
    out_json = Path(out_json)
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ParameterError(f"workers must be a whole number ≥ 1, got {workers!r}")
    jobs = [(i, o, int(seed), budget) for i, o in enumerate(TRAINING_ORIENTATIONS)]
    workers = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
    t0 = time.perf_counter()
    if workers == 1:
        results = [_tune_one(j) for j in jobs]
    else:
        results = run_jobs(_tune_one, jobs, workers, chunksize=1)
    results.sort(key=lambda r: r["index"])
    samples, entries = [], []
    for res in results:
        r: Rollout = res["rollout"]
        s = Sample(r.orientation, r.height_m, res["rule"], r.vectors, r.heights_mm, r.final_up_z, r.landed,
                   r.up_z, res["score"], air_up_z(r))
        samples.append(s)
        entries.append({
            "orientation": list(r.orientation), "height_m": r.height_m, "rule": s.rule.as_dict(),
            "waypoints_rad": res["waypoints"].tolist(), "score": res["score"], "air_up_z": s.air_up_z,
            "final_up_z": r.final_up_z, "final_tilt_deg": round(math.degrees(math.acos(max(-1.0, min(
                1.0, r.final_up_z)))), 2), "landed": r.landed, "outcome": r.outcome.as_dict(),
            "tuning_s": round(res["seconds"], 1)})
        if progress:
            progress(f"{r.orientation}: score {res['score']:.3f}, air up_z {s.air_up_z:.2f}, "
                     f"final up_z {r.final_up_z:.2f}, landed {r.landed}")
    npz = out_json.with_suffix(".npz")
    doc = {"format": FORMAT, "version": VERSION, "command": COMMAND, "source": "seed 000 §6.4-6.5",
           "seed": int(seed), "budget": budget, "train_height_m": TRAIN_HEIGHT_M, "steps": STEPS, "dt": DT,
           "objective": OBJECTIVE, "arrays": npz.name, "wall_s": round(time.perf_counter() - t0, 1),
           "samples": entries}
    arrays = {"vectors": np.stack([s.vectors for s in samples]),
              "heights_mm": np.stack([s.heights_mm for s in samples]),
              "up_z": np.stack([s.up_z for s in samples])}
    write_atomic(npz, lambda f: np.savez(f, **arrays), "landing samples", ParameterError)
    write_atomic(out_json, json.dumps(doc, indent=1) + "\n", "landing samples", ParameterError)
    return samples


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise ParameterError(f"{path}: no such landing samples arrays file (written beside the .json by "
                             "make_samples)")
    check_readable(path, "landing samples arrays file", ParameterError, MAX_ARRAY_BYTES)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except AttributeError:
        raise ParameterError(f"{path}: a single .npy array, not landing samples arrays (.npz)") from None
    except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        raise ParameterError(f"{path}: corrupt landing samples arrays ({type(e).__name__}: "
                             f"{' '.join(str(e).split())[:160]})") from None


def load_samples(path: str | Path) -> list[Sample]:
    """Read what `make_samples` wrote (the .json and the .npz beside it); one-line ParameterError naming the
    file on a missing, corrupt or mismatched file."""
    from felis.files import read_json

    path = Path(path)
    doc = read_json(path, "landing samples file", ParameterError, hint=f" (make it with: {COMMAND})")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ParameterError(f"{path}: not a landing samples file (format {FORMAT!r})")
    if doc.get("version") != VERSION:
        raise ParameterError(f"{path}: landing samples version {doc.get('version')!r}, this felis reads {VERSION}")
    entries = doc.get("samples")
    if not isinstance(entries, list) or not entries:
        raise ParameterError(f"{path}: 'samples' must be a non-empty list")
    if doc.get("steps") != STEPS or doc.get("dt") != DT:
        raise ParameterError(f"{path}: made for {doc.get('steps')!r} steps of {doc.get('dt')!r} s, "
                             f"expected {STEPS} of {DT}")
    arrays = _read_arrays(path.with_name(str(doc.get("arrays") or path.with_suffix(".npz").name)))
    n = len(entries)
    from felis.learning.landing.features import FEATURE_BODIES

    shapes = {"vectors": (n, STEPS, len(FEATURE_BODIES), 3), "heights_mm": (n, STEPS), "up_z": (n, STEPS)}
    for k, shape in shapes.items():
        a = arrays.get(k)
        if a is None:
            raise ParameterError(f"{path}: its arrays file lacks {k!r}")
        if a.shape != shape or not np.issubdtype(a.dtype, np.floating) or not np.all(np.isfinite(a)):
            raise ParameterError(f"{path}: arrays {k!r} have shape {a.shape} ({a.dtype}), expected finite {shape}:"
                                 " the .json and .npz do not match")
    out = []
    for i, e in enumerate(entries):
        where = f"{path}: sample {i}"
        if not isinstance(e, dict):
            raise ParameterError(f"{where}: expected an object")
        try:
            missing = [k for k in ("orientation", "height_m", "rule", "final_up_z", "landed") if k not in e]
            if missing:
                raise ParameterError(f"missing {', '.join(missing)}")
            o = _orientation(e["orientation"])
            h = _number(e["height_m"], "height_m")
            if not h > 0:
                raise ParameterError(f"height_m must be positive, got {h:g}")
            if isinstance(e["rule"], dict) and e["rule"].get("kind") == "whole-body":
                from felis.learning.landing.optimum import MotionRule

                rule = MotionRule.from_dict(e["rule"])
            else:
                rule = SpineRule.from_dict(e["rule"])
            fu = _number(e["final_up_z"], "final_up_z")
            if not isinstance(e["landed"], bool):
                raise ParameterError(f"landed must be true or false, got {e['landed']!r}")
            score = None if e.get("score") is None else _number(e["score"], "score")
            air = None if e.get("air_up_z") is None else _number(e["air_up_z"], "air_up_z")
        except ParameterError as err:
            raise ParameterError(f"{where}: {err}") from None
        out.append(Sample(o, h, rule, arrays["vectors"][i], arrays["heights_mm"][i], fu, e["landed"],
                          arrays["up_z"][i], score, air))
    return out


def nearest_rule(orientation: Sequence[float], path: str | Path | None = None) -> SpineRule:
    """The hand-written rule of the training orientation nearest to ``orientation`` (roll, pitch, yaw in
    degrees; nearest by the rotation angle between the two start orientations): the `rules` baseline."""
    from felis.rotations import euler_quat

    samples = load_samples(path or DEFAULT_SAMPLES_PATH)
    q = euler_quat(*orientation)
    dots = [abs(float(np.dot(q, euler_quat(*s.orientation)))) for s in samples]
    return samples[int(np.argmax(dots))].rule
