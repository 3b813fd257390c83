"""Protective reactions and the controller that runs them when the balance monitor raises its alarm.

`ReactiveController` wraps a base controller (stand, trot in place) and a `BalanceMonitor`. Each tick
the base computes its command and the monitor assesses the state; when a warning or the alarm rises
(the XCoM near or past the edge of the base of support), a strategy
is chosen (fixed, or by a selector from the features below) and its pose replaces the base command
at once (the loop's safety layer still rate-limits it). The reaction holds while the alarm lasts and
`hold_s` after the risk has passed, then blends back to the base over `blend_s` with the minimum-jerk weight. This is
the control flow of seed 004 §2.1 (normal motion → balance check → recovery → blend back), without
the human's 150–250 ms passive phase: a robot can react on the next tick.

Strategies (all relative to the description's ``stand`` pose, x forward, y left):

* ``none``: keep the base command (the baseline).
* ``brace``: widen the stance: leg rolls out to ±`BRACE_ROLL`, legs splayed fore and aft by
  `BRACE_PITCH`.
* ``crouch``: splay the straight legs fore and aft (front pitch −`CROUCH_PITCH`, hind +): the legs
  have no knees, so this is how the cat lowers its CoM, by L(1 − cos θ) (2.5 cm), raising ω0.
* ``step``: move the feet on the falling side toward ξ: with d̂ the direction from the BoS centre to
  ξ in the heading frame, each leg whose hip lies on that side (h·d̂ > 0) puts its foot δ = `STEP_M`·d̂
  away, pitch = −asin(δx/L), roll = asin(δy/L) (leg length L); the other legs splay by `STEP_PITCH`.

The constants were tuned on simulated pushes (docs/balance.md): lowering the CoM is what a cat with
weak, knee-less legs can do fastest, so each strategy lowers it some.

Selector features at the first warning (`FEATURES`), in the heading frame (the IMU's yaw removed): ξ
relative to the BoS centre, the CoM velocity, the margin, the body's roll, pitch and their rates, and the
gait's phase when a gait runs.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from felis.controllers.balance import Assessment, BalanceMonitor
from felis.controllers.pose import min_jerk
from felis.errors import ParameterError
from felis.hal import Command, Controller, State
from felis.rotations import quat_matrix
from felis.spec import RobotSpec

REACTIONS = ("none", "brace", "crouch", "step")
FEATURES = ("xi_fwd", "xi_left", "v_fwd", "v_left", "margin", "roll", "pitch", "roll_rate", "pitch_rate",
            "yaw_rate", "stepping", "phase_sin", "phase_cos")
LEGS = ("fl", "fr", "hl", "hr")
BRACE_ROLL = 0.8  # rad
BRACE_PITCH = 0.7  # rad
CROUCH_PITCH = 0.8  # rad
STEP_M = 0.06  # m, foot displacement toward ξ
STEP_PITCH = 0.6  # rad, the other legs' splay while stepping
LEG_M = 0.085  # hip to foot centre


def heading_frame(quat: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(2×2 world→heading rotation, roll, pitch) from the IMU quaternion."""
    R = quat_matrix(quat)
    yaw = math.atan2(R[1, 0], R[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    roll = math.atan2(R[2, 1], R[2, 2])
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    return np.array([[c, s], [-s, c]]), roll, pitch


def features(a: Assessment, state: State, gait=None) -> np.ndarray:
    """The selector's state vector s_t (seed 004 eq. 2) at an assessment (`FEATURES` order): ξ from the
    BoS centre and the CoM velocity in the heading frame, the margin, the body's roll, pitch and rates
    (IMU), and the gait's phase (sin, cos of 2πφ; zeros when standing)."""
    if a.xi is None or state.imu is None:
        return np.full(len(FEATURES), np.nan)
    H, roll, pitch = heading_frame(state.imu.quat)
    centre = np.mean(a.support, axis=0)
    xi = H @ (np.asarray(a.xi) - centre)
    v = H @ np.asarray(a.com_vel[:2])
    w = np.asarray(state.imu.gyro, dtype=float)
    stepping = bool(getattr(gait, "stepping", False))
    phase = 2 * math.pi * float(getattr(gait, "phase", 0.0))
    ps, pc = (math.sin(phase), math.cos(phase)) if stepping else (0.0, 0.0)
    return np.array([xi[0], xi[1], v[0], v[1], a.margin, roll, pitch, w[0], w[1], w[2], float(stepping), ps, pc])


def reaction_pose(name: str, spec: RobotSpec, a: Assessment | None, state: State) -> np.ndarray:
    """The target pose of strategy ``name`` (module doc) for the robot in ``state``."""
    q = spec.pose("stand").copy()
    if name == "none":
        return q
    idx = {leg: (spec.index(f"{leg}_pitch"), spec.index(f"{leg}_roll")) for leg in LEGS}
    splay = {leg: (-1.0 if leg[0] == "f" else 1.0) for leg in LEGS}  # pitch sign that moves a foot outward
    if name == "brace":
        for leg, (p, r) in idx.items():
            q[r] = BRACE_ROLL if leg[1] == "l" else -BRACE_ROLL
            q[p] = splay[leg] * BRACE_PITCH
    elif name == "crouch":
        for leg, (p, _) in idx.items():
            q[p] = splay[leg] * CROUCH_PITCH
    elif name == "step":
        d = np.zeros(2)
        if a is not None and a.xi is not None and state.imu is not None:
            H, _, _ = heading_frame(state.imu.quat)
            d = H @ (np.asarray(a.xi) - np.mean(a.support, axis=0))
        n = float(np.hypot(*d))
        if n > 1e-9:
            d = d / n
            s = min(STEP_M, 0.95 * LEG_M)
            for leg, (p, r) in idx.items():
                hip = np.array([1.0 if leg[0] == "f" else -1.0, 1.0 if leg[1] == "l" else -1.0])
                if hip @ d > 0:
                    q[p] = -math.asin(s * d[0] / LEG_M)
                    q[r] = math.asin(s * d[1] / LEG_M)
                else:
                    q[p] = splay[leg] * STEP_PITCH
    else:
        raise ParameterError(f"unknown reaction {name!r}; known: {', '.join(REACTIONS)}")
    return np.clip(q, spec.lower, spec.upper)


class ReactiveController:
    """A base controller guarded by a balance monitor and a protective reaction (module doc).

    Args:
        base: the controller that runs while balanced (stand, stepping…).
        monitor: the `BalanceMonitor`; its gait gate is fed from ``base.gait`` if the base has one
            and the gate is not already fed.
        reaction: a name of `REACTIONS`, or a callable features → name (a selector).
        hold_s / blend_s: how long the reaction is held after the alarm clears, then blended back.

    ``needs_imu``: the monitor's XCoM is in the world frame, from the IMU's attitude: a run without one
    is refused, and one whose IMU goes quiet stops (`felis.loop`).
    """

    needs_imu = True

    def __init__(self, base: Controller, monitor: BalanceMonitor,
                 reaction: str | Callable[[np.ndarray], str] = "none", hold_s: float = 1.0, blend_s: float = 0.4):
        if isinstance(reaction, str) and reaction not in REACTIONS:
            raise ParameterError(f"unknown reaction {reaction!r}; known: {', '.join(REACTIONS)}")
        self.base, self.monitor, self.reaction = base, monitor, reaction
        self.hold_s, self.blend_s = float(hold_s), float(blend_s)
        self.name = f"{getattr(base, 'name', 'base')}+balance"

    def reset(self, spec: RobotSpec, state: State) -> None:
        self.spec = spec
        self.base.reset(spec, state)
        self.monitor.reset()
        if self.monitor.gait is None and callable(getattr(self.base, "gait", None)):
            self.monitor.gait = self.base.gait
        self.alarm_t: float | None = None  # first alarm (a fall predicted)
        self.react_t: float | None = None  # first reaction (a warning or an alarm)
        self.strategy: str | None = None  # the first reaction's strategy
        self.features: np.ndarray | None = None  # the selector's features at the first reaction
        self.reactions = 0
        self._q: np.ndarray | None = None  # the active reaction's pose
        self._calm_t: float | None = None  # when the alarm last cleared during a reaction
        self.assessment: Assessment | None = None
        self._was_risk = False

    def _choose(self, a: Assessment, state: State) -> str:
        gait = self.monitor.gait(state.t) if self.monitor.gait is not None else None
        self.features = features(a, state, gait)
        if isinstance(self.reaction, str):
            return self.reaction
        if not np.all(np.isfinite(self.features)):
            return "none"
        return str(self.reaction(self.features))

    def __call__(self, state: State) -> Command:
        cmd = self.base(state)
        a = self.assessment = self.monitor.assess(state)
        if a.alarm and self.alarm_t is None:
            self.alarm_t = state.t
        risk = a.alarm or a.warning
        rising, self._was_risk = risk and not self._was_risk, risk
        if rising and self._q is None:
            self.reactions += 1
            features_now = self.features
            name = self._choose(a, state)
            if self.react_t is None:
                self.react_t, self.strategy = state.t, name
            else:
                self.features = features_now  # keep the first reaction's features
            self._q = None if name == "none" else reaction_pose(name, self.spec, a, state)
            self._calm_t = None
        if self._q is None:
            return cmd
        if risk or a.cls == "unknown":
            self._calm_t = None
            return Command(q=self._q.copy())
        if self._calm_t is None:
            self._calm_t = state.t
        w = min_jerk((state.t - self._calm_t - self.hold_s) / self.blend_s)
        q = self._q + w * (cmd.q - self._q)
        if w >= 1.0:
            self._q = None
        return cmd.replace(q=q)

    def summary(self) -> dict:
        return {"alarm_t": self.alarm_t, "react_t": self.react_t, "strategy": self.strategy,
                "reactions": self.reactions}
