"""The excitation of system identification: the test signal each joint is driven with (`plan`).

From the hold pose (q = 0 clipped into the limits), per joint under test, with
every other joint holding:

* small steps ±A_s, A_s = ``small`` · τ_max/kp (inside the linear range): kp, damping;
* saturating steps ±A_l, A_l = ``large`` · τ_max/kp (clipped to the limits less ``margin``): the
  actuator saturates, the speed approaches τ_max/damping: torque_limit;
* a linear chirp of amplitude A_s/2 from ``chirp_hz[0]`` to ``chirp_hz[1]``: inertia, armature;
* a settling hold before and after, so each segment starts at rest (the replay starts from the
  measured state there). One joint at a time keeps coupling through the links small.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from felis.calib.sysid.model import check_joints
from felis.errors import SysidError
from felis.servos import servo_model
from felis.sim.servo import servo_params
from felis.spec import RobotSpec

KINDS = {"ramp": 0, "hold": 1, "step": 2, "saturate": 3, "chirp": 4}
STEP_KINDS = (KINDS["step"], KINDS["saturate"])


@dataclass(frozen=True)
class Excitation:
    """Shape of the test signal per joint (module doc). Amplitudes are fractions of τ_max/kp, the error
    at which the datasheet servo saturates; times in seconds."""

    small: float = 0.3
    large: float = 2.5
    margin: float = 0.1  # fraction of the joint's range kept clear of each limit
    settle_s: float = 0.3
    step_s: float = 0.3
    large_step_s: float = 0.4
    chirp_s: float = 2.0
    chirp_hz: tuple[float, float] = (0.5, 8.0)
    ramp_speed: float = 0.5  # rad/s (m/s) to the hold pose at the start

    def duration(self, n_joints: int) -> float:
        """Seconds of excitation for ``n_joints`` joints (not counting the ramp)."""
        return n_joints * (2 * self.settle_s + 4 * self.step_s + 4 * self.large_step_s + self.chirp_s)


@dataclass
class Plan:
    """Targets per tick: ``q`` (ticks × joints), joint under test (index, -1 none) and segment kind."""

    q: np.ndarray
    active: np.ndarray
    kind: np.ndarray
    rate_hz: float

    @property
    def duration(self) -> float:
        return len(self.q) / self.rate_hz


def hold_pose(spec: RobotSpec) -> np.ndarray:
    """q = 0 clipped into the limits (the cat hangs with legs down, spine and tail straight)."""
    return np.clip(np.zeros(spec.n), spec.lower, spec.upper)


def amplitudes(spec: RobotSpec, name: str, exc: Excitation, hold: np.ndarray) -> tuple[float, float]:
    """(small, large) step amplitudes for joint ``name`` around ``hold`` (joint units)."""
    i = spec.index(name)
    j = spec.joints[i]
    p = servo_params(servo_model(j.servo), m_per_rad=j.m_per_rad)
    sat = p.torque_limit / p.kp
    room = min(hold[i] - j.lower, j.upper - hold[i]) - exc.margin * (j.upper - j.lower)
    if room <= 0:
        raise SysidError(f"{name}: hold pose {hold[i]:.3g} leaves no room inside its limits")
    return min(exc.small * sat, 0.5 * room), min(exc.large * sat, room)


def plan(spec: RobotSpec, joints: Sequence[str], rate_hz: float, start: np.ndarray | None = None,
         exc: Excitation = Excitation(), hold: np.ndarray | None = None) -> Plan:
    """The excitation for ``joints`` (one after the other), starting with a ramp from ``start``."""
    joints = check_joints(spec, joints)
    hold = hold_pose(spec) if hold is None else np.asarray(hold, float)
    dt = 1.0 / rate_hz
    qs: list[np.ndarray] = []
    act: list[int] = []
    kinds: list[int] = []

    def add(q: np.ndarray, seconds: float, joint: int, kind: str) -> None:
        n = max(1, int(round(seconds * rate_hz)))
        qs.append(np.repeat(q[None, :], n, axis=0) if q.ndim == 1 else q)
        act.extend([joint] * len(qs[-1]))
        kinds.extend([KINDS[kind]] * len(qs[-1]))

    if start is not None:
        start = np.asarray(start, float)
        span = float(np.max(np.abs(hold - start))) if start.size else 0.0
        n = max(1, int(round(max(0.5, span / exc.ramp_speed) * rate_hz)))
        s = np.linspace(0.0, 1.0, n)
        blend = s**3 * (10 - 15 * s + 6 * s**2)  # min-jerk
        add(start + blend[:, None] * (hold - start), 0, -1, "ramp")
    for name in joints:
        i = spec.index(name)
        small, large = amplitudes(spec, name, exc, hold)

        def at(v: float, i=i) -> np.ndarray:
            q = hold.copy()
            q[i] += v
            return q

        add(hold, exc.settle_s, i, "hold")
        for v in (small, 0.0, -small, 0.0):
            add(at(v), exc.step_s, i, "step")
        for v in (large, 0.0, -large, 0.0):
            add(at(v), exc.large_step_s, i, "saturate")
        n = int(round(exc.chirp_s * rate_hz))
        t = np.arange(n) * dt
        f0, f1 = exc.chirp_hz
        f1 = min(f1, 0.25 * rate_hz)
        phase = 2 * np.pi * (f0 * t + 0.5 * (f1 - f0) / exc.chirp_s * t**2)
        q = np.repeat(hold[None, :], n, axis=0)
        q[:, i] += 0.5 * small * np.sin(phase)
        add(q, 0, i, "chirp")
        add(hold, exc.settle_s, i, "hold")
    return Plan(q=np.concatenate(qs), active=np.array(act, dtype=np.int64), kind=np.array(kinds, dtype=np.int64),
                rate_hz=float(rate_hz))
