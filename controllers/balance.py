"""XCoM balance monitor (seed 004 §1.3, after Hof): is the robot about to fall?

Per tick, from the HAL state, in a world-aligned frame (z up):

* **CoM x and velocity v.** In simulation exactly (`State.truth`), v taken relative to the stance
  feet (their mean velocity over the last tick is subtracted: a strong push slides the feet, and the
  body does not tip over feet that move with it). On hardware from the joint angles
  and the IMU's orientation through the body model (`felis.bodymodel`: link masses of the
  description, geometry of the model), the CoM taken relative to the feet on the ground, and v by
  differencing that relative position over one tick (the stance feet do not move, so this is the
  CoM's velocity over the ground; no gyro and no integration drift).
* **Base of support (BoS).** ``support="feet"`` (default): the convex hull of every foot's ground
  projection. A knee-less leg leaves the ground only because the body tips, and its foot comes back
  down where it is when the body turns back; a tip-over turns about the edge of the feet that stay down,
  and ξ leaves this hull over that same edge. ``support="down"``: the hull of the feet in contact (touch
  sensors where fitted, and any foot within `FOOT_DOWN_M` of the lowest: a push jolts contacts off for
  a tick). While a gait runs, the feet it has lifted count where they will land: carried along with the
  body, p + v·t_touchdown.
* **Extrapolated CoM** ξ = x + v/ω0 with ω0 = √(g/l), l the CoM's height above the stance feet (eq. 1).
* **Margin of stability** b: the signed distance from ξ to the BoS edge, positive inside; for a
  two-foot line or one foot (no area) it is minus the distance to that line or point.
* **CoP** from the feet's normal forces where known (simulation): p = Σ f_i p_i / Σ f_i.
* **Classification** (the orderings of seed 004 §1.3 along the direction of motion u = v/|v|):
  ``standing`` (balanced, |v| < `STILL_MS`); ``moving`` (CoM < XCoM < CoP < BoS: the CoP can still
  stop the motion); ``unbalanced`` (CoM < CoP < XCoM < BoS: the CoP cannot, the feet can);
  ``falling`` (XCoM outside the BoS); ``unknown`` (a non-finite state or no orientation: never
  "balanced" on bad data).
* **Alarm with hysteresis**: raised after the margin has stayed below −`on_m` for `on_ticks` ticks
  (standing), or, while a gait runs, for `gait_ticks` ticks over which it still fell by ≥ `diverge_ms`
  (after a push ξ sits outside on a plateau until a swinging foot lands; in a fall it runs away, for
  the LIP ḃ = ω0·b); raised at once when the lowest point other than the feet is within `clear_m` of
  the ground (a collapse: the rear sags onto the floor with ξ on the BoS edge; `Truth.low`, or the body
  model's collision points); cleared after the margin has stayed above `off_m` for `off_ticks` ticks
  with the body clear of the ground.
  The alarm predicts a fall.
* **Warning**: the margin is below `warn_m` (ξ within that distance of the edge, or beyond it). This is
  when a protective reaction should start: reacting at the warning instead of the alarm saves about
  twice as many falls (docs/balance.md), and a needless crouch costs nothing.

The gait gate: ``monitor.gait`` is a callable t → gait (any object with ``stepping`` and ``swing``,
e.g. `felis.controllers.stepping.Gait`) or None. The stepping controller feeds it from its own clock;
the learned phase estimator (`felis.learning.phase.estimator`) can feed it instead. With the BoS of the
feet down, two feet down during a trot make the BoS the line between them and ξ is off it all the time:
without the gate every step would raise an alarm; with it the swinging feet are part of the BoS. With
every foot in the BoS the gate is what keeps a pushed trot quiet: the alarm needs `gait_ticks`
diverging ticks (above) instead of `on_ticks`.

Cost: about 20 µs per tick with the simulator's truth, about 50 µs when estimating from the body model
(``bench/balance_monitor.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from felis.bodymodel import BodyModel
from felis.errors import ParameterError
from felis.hal import Command, State
from felis.rotations import G

FOOT_DOWN_M = 0.03  # feet within this height of the lowest count as down
STILL_MS = 0.05  # CoM speed (m/s) below which a balanced robot is "standing"
MIN_LEG_M = 0.02  # l is clamped to at least this (a robot lying down)
CLASSES = ("unknown", "standing", "moving", "unbalanced", "falling")
SUPPORTS = ("feet", "down")  # the BoS: the hull of every foot, or of the feet down only
CLEAR_M = 0.004  # m: a lowest point other than the feet this close to the ground raises the alarm


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull of 2-D points (Andrew's monotone chain); collinear points dropped."""
    pts = [tuple(p) for p in np.asarray(points, dtype=float).reshape(-1, 2).tolist()]
    return np.array(_hull(pts), dtype=float).reshape(-1, 2)


def _hull(pts: list[tuple[float, float]]) -> list[tuple[float, float]]:
    pts = sorted(set(pts))
    if len(pts) <= 2:
        return pts

    def turn(o, a, b):  # > 0: a left turn
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for p in pts:
        while len(lower) >= 2 and turn(lower[-2], lower[-1], p) <= 1e-15:
            lower.pop()
        lower.append(p)
    upper: list = []
    for p in reversed(pts):
        while len(upper) >= 2 and turn(upper[-2], upper[-1], p) <= 1e-15:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def _segment_distance(px: float, py: float, ax: float, ay: float, bx: float, by: float) -> float:
    dx, dy = bx - ax, by - ay
    L2 = dx * dx + dy * dy
    t = 0.0 if L2 == 0 else min(1.0, max(0.0, ((px - ax) * dx + (py - ay) * dy) / L2))
    return math.hypot(px - ax - t * dx, py - ay - t * dy)


def margin(point, hull) -> float:
    """Signed distance from ``point`` to the boundary of the convex polygon ``hull`` (ccw), positive inside.

    A hull of 2 points (a line) or 1 point has no inside: the margin is minus the distance to it.
    An empty hull (nothing on the ground) gives −inf.
    """
    pts = [tuple(p) for p in np.asarray(hull, float).reshape(-1, 2).tolist()]
    return _margin(float(point[0]), float(point[1]), pts)


def _margin(px: float, py: float, hull: list[tuple[float, float]]) -> float:
    n = len(hull)
    if n == 0:
        return -math.inf
    if n == 1:
        return -math.hypot(px - hull[0][0], py - hull[0][1])
    if n == 2:
        return -_segment_distance(px, py, *hull[0], *hull[1])
    inside = True
    nearest = math.inf
    for i in range(n):
        ax, ay = hull[i]
        bx, by = hull[(i + 1) % n]
        if (bx - ax) * (py - ay) - (by - ay) * (px - ax) < 0:  # right of a ccw edge: outside
            inside = False
        d = _segment_distance(px, py, ax, ay, bx, by)
        if d < nearest:
            nearest = d
    return nearest if inside else -nearest


def xcom(x: np.ndarray, v: np.ndarray, leg: float, g: float = G) -> np.ndarray:
    """Extrapolated centre of mass ξ = x + v/ω0, ω0 = √(g/l) (seed 004 eq. 1), horizontal (2,)."""
    w0 = math.sqrt(g / max(leg, MIN_LEG_M))
    return np.asarray(x, dtype=float)[:2] + np.asarray(v, dtype=float)[:2] / w0


@dataclass(frozen=True)
class Assessment:
    """The monitor's verdict for one tick (positions in the world-aligned frame, m). Plain tuples, not
    arrays: building five small arrays per tick would cost more than the rest of the monitor."""

    t: float
    cls: str  # one of CLASSES
    alarm: bool
    margin: float  # m, NaN when unknown
    xi: tuple[float, float] | None
    com: tuple[float, float, float] | None
    com_vel: tuple[float, float, float] | None  # relative to the stance feet
    cop: tuple[float, float] | None
    support: list[tuple[float, float]] | None  # BoS hull, counter-clockwise
    omega0: float
    down: tuple[bool, ...] | None  # per foot: used for the BoS
    warning: bool = False  # margin below warn_m: time to react
    clearance: float = math.nan  # m: the lowest point other than the feet, above the ground

    @property
    def balanced(self) -> bool:
        return self.cls in ("standing", "moving")


class BalanceMonitor:
    """The XCoM monitor (module doc). Call ``assess(state)`` once per tick, or use it as a loop monitor.

    Args:
        body: the robot's `BodyModel` (foot radius, and the CoM estimate when the state has no truth).
        on_m / on_ticks / off_m / off_ticks: the alarm's hysteresis (m, ticks).
        gait_ticks / diverge_ms: while a gait runs, ticks below −on_m needed, with the margin falling by
            at least diverge_ms (m/s) over them (the gait gate).
        clear_m: a body part other than the feet this close to the ground (m) raises the alarm at once.
        support: "feet" (every foot) or "down" (the feet down) make the BoS (module doc).
        warn_m: the margin (m) below which the assessment carries a warning (time to react).
        gait: callable t → gait or None (the gait gate), replaceable at any time.
        use_truth: use `State.truth` when present (simulation); False forces the hardware estimate.
    """

    def __init__(self, body: BodyModel, *, on_m: float = 0.01, on_ticks: int = 1, gait_ticks: int = 3,
                 diverge_ms: float = 0.1, off_m: float = 0.01, off_ticks: int = 10, warn_m: float = 0.03,
                 clear_m: float = CLEAR_M, support: str = "feet",
                 gait: Callable[[float], object] | None = None, use_truth: bool = True):
        for name, v in (("on_m", on_m), ("off_m", off_m), ("diverge_ms", diverge_ms), ("clear_m", clear_m)):
            if not math.isfinite(v) or v < 0:
                raise ParameterError(f"balance monitor: {name} must be ≥ 0, got {v}")
        if min(on_ticks, gait_ticks, off_ticks) < 1:
            raise ParameterError("balance monitor: on_ticks, gait_ticks and off_ticks must be ≥ 1")
        if support not in SUPPORTS:
            raise ParameterError(f"balance monitor: support must be one of {', '.join(SUPPORTS)}, got {support!r}")
        self.diverge_ms, self.clear_m, self.support = float(diverge_ms), float(clear_m), support
        self.body = body
        if not math.isfinite(warn_m):
            raise ParameterError(f"balance monitor: warn_m must be finite, got {warn_m}")
        self.on_m, self.on_ticks, self.off_m, self.off_ticks = on_m, int(on_ticks), off_m, int(off_ticks)
        self.warn_m, self.gait_ticks = warn_m, int(gait_ticks)
        self.gait = gait
        self.use_truth = use_truth
        self.reset()

    def reset(self, spec=None, state: State | None = None) -> None:
        """Forget the alarm and the last tick (the loop calls this with its spec and first state)."""
        self.alarm = False
        self.last: Assessment | None = None
        self._below = self._above = 0
        self._run: list[tuple[float, float]] = []  # (t, margin) of the ticks below −on_m, latest last
        self._prev: tuple[float, list, list] | None = None  # t, com, feet of the last tick

    # ------------------------------------------------------------------ per tick
    def __call__(self, state: State, command: Command | None = None) -> None:
        self.assess(state)

    def assess(self, state: State) -> Assessment:
        try:
            a = self._assess(state)
        except (ValueError, ZeroDivisionError, FloatingPointError, np.linalg.LinAlgError):
            a = None
        if a is None:  # unknown: keep the alarm as it was, never claim balance
            a = Assessment(state.t, "unknown", self.alarm, math.nan, None, None, None, None, None, math.nan, None)
        self.last = a
        return a

    def _assess(self, state: State) -> Assessment | None:
        # plain Python floats below: for four feet they are several times faster than numpy calls
        gait = self.gait(state.t) if self.gait is not None else None
        stepping = bool(getattr(gait, "stepping", False))
        r = self.body.foot_radius
        truth = state.truth if self.use_truth else None
        if truth is not None:
            com, feet, vel = truth.com.tolist(), truth.feet.tolist(), truth.com_vel.tolist()
            touching = (state.contacts if state.contacts is not None else truth.foot_force > 0).tolist()
            force, low = truth.foot_force.tolist(), truth.low
        else:
            if state.imu is None:
                return None
            c, f, low = self.body.com_feet_low(state.q, state.imu.quat)
            com, feet, vel, force = c.tolist(), f.tolist(), None, None
            touching = state.contacts.tolist() if state.contacts is not None else [False] * len(feet)
        if not math.isfinite(sum(com) + sum(map(sum, feet)) + (sum(vel) if vel is not None else 0.0)):
            return None
        # a foot counts as down when touching, or within FOOT_DOWN_M of the ground (the lowest foot):
        # contacts flicker for a tick when a push jolts the body, and a foot that just unloaded still
        # bounds where the CoP can go
        zs = [p[2] for p in feet]
        ground = min(zs) - r
        down = [bool(t) or z - r - ground < FOOT_DOWN_M for t, z in zip(touching, zs, strict=True)]
        stance = touching if any(touching) else down
        dv = self._stance_velocity(state.t, com, feet, stance, feet_only=truth is not None)
        if truth is not None:  # the CoM's velocity relative to the stance feet
            vel = [vel[0] - dv[0], vel[1] - dv[1], vel[2] - dv[2]]
        else:  # d/dt (CoM − stance feet): already relative
            vel = dv
        use = [True] * len(feet) if self.support == "feet" else list(down)
        support = [(p[0], p[1]) for p in feet]
        if stepping:  # the swinging feet land where the body carries them: ahead by v·(time to touchdown)
            swing = getattr(gait, "swing", None)
            ahead = float(getattr(gait, "touchdown_s", 0.0))
            for i in range(len(feet)):
                if (swing is None or swing[i]) and not touching[i]:
                    use[i] = True
                    support[i] = (support[i][0] + vel[0] * ahead, support[i][1] + vel[1] * ahead)
        leg = max(com[2] - ground, MIN_LEG_M)
        w0 = math.sqrt(G / leg)
        xi = (com[0] + vel[0] / w0, com[1] + vel[1] / w0)
        hull = _hull([p for p, u in zip(support, use, strict=True) if u])
        b = _margin(xi[0], xi[1], hull)
        cop = None
        if force is not None:
            fs = [f if d else 0.0 for f, d in zip(force, down, strict=True)]
            total = sum(fs)
            if total > 0:
                cop = (sum(f * p[0] for f, p in zip(fs, feet, strict=True)) / total,
                       sum(f * p[1] for f, p in zip(fs, feet, strict=True)) / total)
        cls = self._classify(vel, xi, cop, b)
        clearance = low - ground  # NaN (no low points) compares False below
        self._hysteresis(state.t, b, stepping, clearance < self.clear_m)
        return Assessment(state.t, cls, self.alarm, b, xi, tuple(com), tuple(vel), cop, hull, w0, tuple(use),
                          b < self.warn_m, clearance)

    def _stance_velocity(self, t: float, com: list, feet: list, stance: list, feet_only: bool) -> list[float]:
        """With the simulator's truth: the stance feet's mean velocity over the last tick (they slide
        under a strong push). Estimating: d/dt (CoM − mean stance foot), the CoM's velocity over the
        ground. Both over the same two ticks and the same feet."""
        prev, self._prev = self._prev, (t, com, feet)
        if prev is None or t <= prev[0]:
            return [0.0, 0.0, 0.0]
        before = prev[2]
        mx = my = mz = 0.0
        k = 0
        for i, s in enumerate(stance):
            if s:
                p, q = feet[i], before[i]
                mx += p[0] - q[0]
                my += p[1] - q[1]
                mz += p[2] - q[2]
                k += 1
        if k == 0:  # no foot known down: all of them
            for p, q in zip(feet, before, strict=True):
                mx += p[0] - q[0]
                my += p[1] - q[1]
                mz += p[2] - q[2]
            k = len(feet)
        dt = t - prev[0]
        mx, my, mz = mx / k, my / k, mz / k
        if feet_only:
            return [mx / dt, my / dt, mz / dt]
        c0 = prev[1]
        return [(com[0] - c0[0] - mx) / dt, (com[1] - c0[1] - my) / dt, (com[2] - c0[2] - mz) / dt]

    @staticmethod
    def _classify(vel, xi, cop, b: float) -> str:
        if b < 0:
            return "falling"
        speed = math.hypot(vel[0], vel[1])
        if speed < STILL_MS:
            return "standing"
        if cop is None:
            return "moving"
        ahead = vel[0] * (xi[0] - cop[0]) + vel[1] * (xi[1] - cop[1])
        return "unbalanced" if ahead > 0 else "moving"  # XCoM beyond the CoP along the motion

    def _hysteresis(self, t: float, b: float, stepping: bool, grounded: bool) -> None:
        """Raise: `on_ticks` ticks below −on_m standing; while a gait runs, `gait_ticks` ticks and the
        margin still falling over them (by ≥ diverge_ms); at once when the body nears the ground.
        Clear: `off_ticks` ticks above off_m with the body off the ground (a robot lying on its side may
        have ξ inside its feet's hull)."""
        run = self._run
        if b < -self.on_m:
            self._above = 0
            run.append((t, b))
        else:
            run.clear()
            self._above = self._above + 1 if b > self.off_m and not grounded else 0  # down on the floor: held
        need = self.gait_ticks if stepping else self.on_ticks
        if len(run) > need:
            del run[:-need]
        if not self.alarm:
            if grounded:
                self.alarm = True
            elif len(run) >= need:
                (t0, b0), (t1, b1) = run[0], run[-1]
                self.alarm = not stepping or (t1 > t0 and (b1 - b0) < -self.diverge_ms * (t1 - t0))
        elif self._above >= self.off_ticks:
            self.alarm = False
