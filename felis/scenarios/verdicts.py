"""The verdicts on a drop (did it land?) and on a push (did it fall?), as pure functions of recorded truth.

The truth is recorded from the simulator at the physics rate (`felis.sim.landing.LandingRecorder`,
`felis.sim.pushes.FallDetector`); the rules live here, apart from any backend, so every command that asks
"did it land?" — ``felis sim drop``, ``felis eval landing``, landing training — gets the same answer.

*Landed* (issue 5, in its words): only the feet touch the ground through touchdown and for
``WINDOW_S`` = 0.5 s after it (touchdown = the first contact of any robot geom with the floor), and
0.5 s after touchdown the upper body's up-axis is within ``TILT_DEG`` = 30° of vertical and the waist
(``State.height``, the ``waist`` site) is above half its standing height (the waist height of the cat at
rest in its ``stand`` pose on the floor, `felis.learning.landing.evaluate.standing_waist_height`).
`landed` is the rule on its four inputs; `landing_verdict` finds them in a `LandingTruth`.

*Fell* (a push test): any body other than the feet touches the ground, or the upper body tilts past
``FALL_TILT_DEG`` = 60°, within `felis.scenarios.push.FALL_WINDOW_S` of the push. `fall_reason` is the
rule on one instant; `fall_verdict` finds the first instant that meets it in a `FallTruth`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from felis.rotations import tilt_from_up

WINDOW_S = 0.5  # feet only from touchdown to touchdown + WINDOW_S; pose judged at its end
TILT_DEG = 30.0  # up-axis within this of vertical at touchdown + WINDOW_S
WAIST_FRACTION = 0.5  # waist above this fraction of its standing height at touchdown + WINDOW_S
FALL_TILT_DEG = 60.0  # a push test: the upper body tilted past this has fallen
_EPS_S = 1e-9  # time comparisons at the physics rate


# ------------------------------------------------------------------------------------------ landing
def landed(foot_only: bool, tilt_deg: float, waist_m: float, standing_waist_m: float) -> bool:
    """The landing rule (module doc): feet only through the window, and at its end tilt ≤ 30° and waist
    > half the standing waist height. NaN inputs never land."""
    return bool(foot_only) and tilt_deg <= TILT_DEG and waist_m > WAIST_FRACTION * standing_waist_m


@dataclass(frozen=True)
class LandingTruth:
    """What happened in a drop, one entry per physics step in time order (`felis.sim.landing.LandingRecorder`
    records from touchdown to touchdown + `WINDOW_S`; earlier or later steps may be given and change nothing).

    ``floor_body``: a body touching the floor at that step (an index into ``bodies``; −1: none);
    ``off_foot_body``: a body other than a foot touching the floor (−1: none, i.e. feet only or nothing).
    """

    t: np.ndarray  # s, simulation time after each step
    up_z: np.ndarray  # world z of the upper body's up-axis (R₂₂, the cosine of its tilt)
    waist_m: np.ndarray  # height of the waist site (m)
    floor_body: np.ndarray  # int
    off_foot_body: np.ndarray  # int
    bodies: tuple[str, ...]  # body names, by index
    standing_waist_m: float


@dataclass(frozen=True)
class LandingVerdict:
    """`landing_verdict`'s answer, with the figures it was taken on and why it failed."""

    landed: bool
    foot_only: bool  # only feet on the floor from touchdown to touchdown + WINDOW_S
    touchdown_t: float | None  # time of the first floor contact
    first_body: str | None  # a body that made it
    touch_body: str | None  # the first non-foot body on the floor within the window
    touch_t: float | None  # … when
    tilt_deg: float | None  # at touchdown + WINDOW_S (None: the run ended before)
    waist_m: float | None  # at touchdown + WINDOW_S
    standing_waist_m: float
    reasons: tuple[tuple[str, str], ...]  # why it did not land: (kind fit for counting, detail); () if it did

    @property
    def why(self) -> str:
        """The reasons' details in one line ("" when it landed)."""
        return "; ".join(detail for _, detail in self.reasons)


def _tilt(up: float) -> float:
    return tilt_from_up(up) if math.isfinite(up) else math.nan


def landing_verdict(truth: LandingTruth) -> LandingVerdict:
    """The landing rule (module doc) applied to a recorded drop."""
    t = np.asarray(truth.t, dtype=float)
    standing = float(truth.standing_waist_m)
    on_floor = np.flatnonzero(np.asarray(truth.floor_body) >= 0)
    if on_floor.size == 0:
        return LandingVerdict(False, False, None, None, None, None, None, None, standing,
                              (("never touched down", "never touched down"),))
    i0 = int(on_floor[0])
    touchdown = float(t[i0])
    end = touchdown + WINDOW_S
    first_body = truth.bodies[int(truth.floor_body[i0])]
    after = np.arange(i0, len(t))
    bad = after[(np.asarray(truth.off_foot_body)[i0:] >= 0) & (t[i0:] <= end + _EPS_S)]
    touch_body = truth.bodies[int(truth.off_foot_body[bad[0]])] if bad.size else None
    touch_t = float(t[bad[0]]) if bad.size else None
    judged = after[t[i0:] >= end - _EPS_S]
    tilt = waist = None
    if judged.size:
        tilt, waist = _tilt(float(truth.up_z[judged[0]])), float(truth.waist_m[judged[0]])
    foot_only = touch_body is None
    reasons = []
    if touch_body is not None:
        reasons.append((f"{touch_body} touched the ground",
                        f"{touch_body} touched the ground {touch_t - touchdown:.3f} s after touchdown"))
    if tilt is None or waist is None:
        reasons.append(("run ended too early", f"run ended before {WINDOW_S:g} s after touchdown"))
    else:
        if not tilt <= TILT_DEG:
            reasons.append((f"tilt > {TILT_DEG:g}°", f"tilt {tilt:.0f}° after {WINDOW_S:g} s"))
        if not waist > WAIST_FRACTION * standing:
            reasons.append(("waist < half standing", f"waist {waist:.3f} m < half standing "
                            f"({WAIST_FRACTION * standing:.3f} m) after {WINDOW_S:g} s"))
    ok = tilt is not None and waist is not None and landed(foot_only, tilt, waist, standing)
    return LandingVerdict(ok, foot_only, touchdown, first_body, touch_body, touch_t, tilt, waist, standing,
                          tuple(reasons))


# --------------------------------------------------------------------------------------------- falls
def fall_reason(tilt_deg: float, off_foot_body: str | None) -> str:
    """The fall rule at one instant (module doc): '' while standing, else why it counts as fallen."""
    if off_foot_body is not None:
        return f"{off_foot_body} touched the ground"
    if tilt_deg > FALL_TILT_DEG:
        return f"upper body tilted {tilt_deg:.0f}°"
    return ""


@dataclass(frozen=True)
class FallTruth:
    """What happened after a push, one entry per check (time order): the upper body's tilt (degrees) and a
    body other than a foot on the floor (an index into ``bodies``; −1: none)."""

    t: np.ndarray
    tilt_deg: np.ndarray
    off_foot_body: np.ndarray
    bodies: tuple[str, ...]


@dataclass(frozen=True)
class FallVerdict:
    fell: bool
    t: float | None  # the first instant that met the rule
    why: str
    max_tilt_deg: float  # up to and including that instant (the whole record if it did not fall)


def fall_verdict(truth: FallTruth) -> FallVerdict:
    """`fall_reason` at each recorded instant; the first one that says fallen is the fall."""
    max_tilt = 0.0
    for i, (t, tilt) in enumerate(zip(truth.t, truth.tilt_deg, strict=True)):
        max_tilt = max(max_tilt, float(tilt))
        b = int(truth.off_foot_body[i])
        why = fall_reason(float(tilt), truth.bodies[b] if b >= 0 else None)
        if why:
            return FallVerdict(True, float(t), why, max_tilt)
    return FallVerdict(False, None, "", max_tilt)
