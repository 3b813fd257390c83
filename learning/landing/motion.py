"""An open-loop whole-body landing motion (issue 21): the family the per-drop optimum searches
(`felis.learning.landing.optimum`), as a landing policy (`MotionRule`) that the landing controller runs on MuJoCo
and on servos alike. Numpy only: an inference module, which controllers may import.

**Motion family** (`motion_table`). A closed loop through `N_WAYPOINTS` waypoints of 8 angles each —
spine (pitch, yaw), tail (pitch, yaw), front legs (pitch, roll), hind legs (pitch, roll); the two legs of a
pair move together (`BODY_JOINTS`), leg angles within ±1.5 rad, spine and tail within ±1 rad — run again and
again from the release pose at the servos' top speed (each leg of the loop as many whole ticks as its
fastest joint needs), then, ``return_s`` before the predicted touchdown √(2h/g), every joint heads straight
to the touchdown posture at full speed: spine and tail straight, each leg pair at a searched pitch, shared
roll and splay (within ±0.6 rad; all 0 is the release pose, legs down). Loops of the spine, of the legs
(out across the roll axis, back along it) and of both turn the cat in the air without angular momentum
(docs/landing.md, "What limits it"); the family reaches the zero-gravity figures that the issue quotes.
As in every landing run, `felis.controllers.landing.LandingBatch` integrates the motion's velocities and
holds the spine straight below 0.5 m, and the safety layer caps each step.

**Files** (`load_motion`): a motion for one drop is a JSON object ``{"kind": "whole-body", "motion_x": [55
numbers in −1…1], "height_m", "steps"}`` (`MotionRule.as_dict`), optionally with the ``drop`` it was searched for
(``{roll_deg, pitch_deg, yaw_deg, height_m}``) and how it was made; ``felis run landing --policy FILE.json``
runs it. It is open loop: tuned for that drop and that height, it is no skill for any other.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.rotations import G

DT = 0.01
N_WAYPOINTS = 6
BODY_JOINTS = (0, 1, 2, 3, 4, 5, 4, 5, 6, 7, 6, 7)  # 12 joints from the 8 angles of a waypoint
LIMITS = np.array((1.0, 1.0, 1.0, 1.0, 1.5, 1.5, 1.5, 1.5))  # rad
RETURN_MIN_S, RETURN_MAX_S = 0.05, 0.35
POSTURE_LIMIT = 0.6  # rad: the touchdown posture's leg angles
N_POSTURE = 6  # front pitch, front roll (common), front splay, hind pitch, hind roll, hind splay
DIMS = N_WAYPOINTS * 8 + 1 + N_POSTURE


def decode(x: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """x ∈ [−1, 1]^55 → (waypoints (6, 8) in rad, return time in s, touchdown posture (12,) in rad).

    The posture moves the legs only: per pair, pitch, a roll both legs share and a splay (left + s, right − s)."""
    x = np.clip(np.asarray(x, dtype=float), -1.0, 1.0)
    n = N_WAYPOINTS * 8
    w = x[:n].reshape(N_WAYPOINTS, 8) * LIMITS
    r = RETURN_MIN_S + (x[n] + 1.0) * 0.5 * (RETURN_MAX_S - RETURN_MIN_S)
    fp, fr, fs, hp, hr, hs = np.round(x[n + 1:n + 1 + N_POSTURE] * POSTURE_LIMIT, 3)
    posture = np.array([0, 0, 0, 0, fp, fr + fs, fp, fr - fs, hp, hr + hs, hp, hr - hs], dtype=float)
    return w, float(r), posture


def _ticks(d: np.ndarray, speed: float | np.ndarray) -> int:
    """Whole ticks for the joints to move by ``d`` at ``speed`` (one number, or one per joint)."""
    if np.ndim(speed) == 0:
        return math.ceil(float(np.abs(d).max()) / (speed * DT) - 1e-9)
    return math.ceil(float((np.abs(d) / speed).max()) / DT - 1e-9)


def motion_table(x: np.ndarray, height_m: float, speed: float | np.ndarray, n_ticks: int) -> np.ndarray:
    """Joint velocities (n_ticks, 12) in rad/s of the motion ``x`` (module doc) for a drop from ``height_m``,
    joints at ``speed`` rad/s (one number, or one per joint: `felis.learning.landing.designs.joint_speeds`);
    tick k's row is the velocity the controller integrates at t = k·DT."""
    w, return_s, posture = decode(x)
    w = np.round(w, 3)[:, BODY_JOINTS]
    back_at = max(1, int(round((math.sqrt(2.0 * height_m / G) - return_s) / DT)))
    path, prev, i, stalled = [np.zeros(12)], np.zeros(12), 0, 0
    while len(path) <= back_at and stalled <= N_WAYPOINTS:  # the loop, again and again
        p = w[i % N_WAYPOINTS]
        i += 1
        d = p - prev
        ticks = _ticks(d, speed)
        if ticks <= 0:
            stalled += 1  # every waypoint where the last one was: hold
            continue
        stalled = 0
        path += [prev + d * (s / ticks) for s in range(1, ticks + 1)]
        prev = p
    path = path[:back_at + 1]
    path += [path[-1]] * (back_at + 1 - len(path))
    p = path[-1]  # then straight to the touchdown posture
    d = posture - p
    ticks = max(1, _ticks(d, speed))
    path += [p + d * (s / ticks) for s in range(1, ticks + 1)]
    path += [posture] * max(0, n_ticks - len(path))
    v = np.zeros((n_ticks, 12))
    v[1:] = np.diff(np.array(path[:n_ticks]), axis=0) / DT
    return v


class MotionRule:
    """One motion of the family as a policy callable ``(it, t) -> (12,)`` (`felis.controllers.landing.
    LandingController`, `felis.learning.landing.samples.rollout`): the velocity table of ``x`` for a drop from
    ``height_m``, ``steps`` ticks long; data as ``{"kind": "whole-body", "motion_x", "height_m", "steps"}``."""

    kind = "whole-body"

    def __init__(self, x, height_m: float, steps: int, speed: float | None = None):
        from felis.learning.landing.policy import MAX_SPEED

        x = np.asarray(x, dtype=float)
        if x.shape != (DIMS,) or not np.all(np.isfinite(x)):
            raise ParameterError(f"whole-body motion: expected {DIMS} finite numbers, got shape {x.shape}")
        if not (math.isfinite(height_m) and height_m > 0) or int(steps) < 1:
            raise ParameterError("whole-body motion: needs a positive height_m and steps ≥ 1")
        self.x, self.height_m, self.steps = x, float(height_m), int(steps)
        self.table = motion_table(x, self.height_m, MAX_SPEED if speed is None else speed, self.steps)

    @property
    def duration(self) -> float:
        return self.steps * DT

    def __call__(self, it, t: float) -> np.ndarray:
        k = int(round(float(t) / DT))
        return self.table[k].copy() if 0 <= k < self.steps else np.zeros(12)

    def as_dict(self) -> dict:
        return {"kind": self.kind, "motion_x": [float(v) for v in self.x], "height_m": self.height_m,
                "steps": self.steps}

    @staticmethod
    def from_dict(d) -> MotionRule:
        if not isinstance(d, dict) or d.get("kind") != MotionRule.kind or not isinstance(d.get("motion_x"), list):
            raise ParameterError("whole-body motion: expected {kind: whole-body, motion_x: [...], height_m, steps}")
        h, n = d.get("height_m"), d.get("steps")
        if isinstance(h, bool) or not isinstance(h, int | float) or isinstance(n, bool) or not isinstance(n, int):
            raise ParameterError("whole-body motion: height_m must be a number and steps a whole number")
        try:
            x = np.array(d["motion_x"], dtype=float)
        except (TypeError, ValueError):
            raise ParameterError("whole-body motion: motion_x must be numbers") from None
        return MotionRule(x, float(h), n)


def load_motion(path: str | Path) -> tuple[MotionRule, dict | None]:
    """(the motion, the drop it was searched for or None) from a motion file (module doc); every fault is one
    line naming the file."""
    from felis.files import read_json

    path = Path(path)
    doc = read_json(path, "motion file", ParameterError,
                    " (make one: felis eval landing --policy optimum --drops FILE --motions DIR)")
    try:
        rule = MotionRule.from_dict(doc)
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from None
    drop = doc.get("drop")
    if drop is not None and not (isinstance(drop, dict) and all(isinstance(drop.get(k), int | float) and
                                                                 not isinstance(drop.get(k), bool)
                                                                 for k in ("roll_deg", "pitch_deg", "yaw_deg",
                                                                           "height_m"))):
        raise ParameterError(f"{path}: 'drop' must be {{roll_deg, pitch_deg, yaw_deg, height_m}} numbers")
    return rule, drop


def is_motion_file(path: str | Path) -> bool:
    """A landing policy file is a motion (JSON) rather than evolved nets (npz): by its suffix."""
    return Path(path).suffix.lower() == ".json"


def motion_doc(x, drop: dict, landed: bool, command: str, steps: int) -> dict:
    """A motion file's content (module doc) for the motion ``x`` searched for ``drop`` (``Drop.as_dict()``)."""
    rule = MotionRule(np.asarray(x, dtype=float), float(drop["height_m"]), steps)
    return {**rule.as_dict(), "motion_x": [float(v) for v in rule.x],  # every digit: the searched motion exactly
            "drop": dict(drop), "landed_when_searched": bool(landed), "made_by": command}
