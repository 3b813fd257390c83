"""Stepping controller: the cat trots in place, diagonal pairs (fl+hr, fr+hl) lifting in turn.

Clock. After `reset` at t₀ the joints blend from the present pose into ``stand`` (minimum jerk over
``BLEND_S`` = 0.3 s); the gait starts at t_s = t₀ + max(start_s, BLEND_S) and ramps in linearly:

    φ(t) = f · (t − t_s) mod 1,      a(t) = clip((t − t_s) / ramp_s, 0, 1)
    pair A = fl+hr swings for φ ∈ [0, ½ − d),   pair B = fr+hl swings for φ ∈ [½, 1 − d),
    all four feet are commanded down for the dwell φ ∈ [½ − d, ½) and [1 − d, 1).

Legs are straight and have no knee, so a foot is lifted by tilting its leg: with s ∈ [0, 1] the
progress through the swing, p(s) a trapezoid (minimum-jerk rise over the first and last ``RISE`` of
the swing, flat between) and θ = a · lift · p(s), a swinging leg gets

    roll  = roll_stand ± θ            (outward: + for fl/hl, − for fr/hr; foot centre up L(1 − cos θ))
    pitch = asin(sin(pitch₀) cos(roll_stand) / cos(roll)) + BACKWARD · θ

where pitch₀ = pitch_stand + a · PITCH_TRIM for every leg, the asin term keeps the foot's x in the hip
frame while the leg rolls, and BACKWARD · θ swings the foot slightly backward in the air. The
command runs ``LEAD_S`` ahead of the gait clock, i.e. it uses φ(t + LEAD_S), so that with the servo lag
the feet leave the floor near the nominal swing start. `gait` reports the clock itself (no lead).
Standing (f = 0 or lift = 0): the stand pose exactly, ``gait().stepping`` False.

Schedule (`SteppingController.scheduled`): segments i = 0, 1, … of (duration Dᵢ, frequency fᵢ, lift ℓᵢ)
follow each other from t_s (Tᵢ = t_s + D₀ + … + Dᵢ₋₁); the last one holds for ever. A segment with
fᵢ = 0 or ℓᵢ = 0 stands; its clock keeps the last frequency cᵢ (cᵢ = fᵢ if fᵢ > 0 else cᵢ₋₁, c₋₁ = 0)
so that the legs finish their swings while the lift ramps down. The clock is the integral of the
piecewise-constant frequency, so the phase is continuous through every change:

    φ(t) = Φᵢ + cᵢ · (t − Tᵢ) mod 1,      Φ₀ = 0,   Φᵢ₊₁ = Φᵢ + cᵢ · Dᵢ
    w = min(1, (t − Tᵢ) / ramp_s),     a(t) = aᵢ + (a*ᵢ − aᵢ) · w,   ℓ(t) = ℓ⁰ᵢ + (ℓ*ᵢ − ℓ⁰ᵢ) · w

with targets a*ᵢ = 1, ℓ*ᵢ = ℓᵢ for a stepping segment and 0, 0 for a standing one, and start values
aᵢ, ℓ⁰ᵢ where the previous segment left them (0 at t_s). The swing angle is θ = ℓ(t) · p(s); the ramp
level a(t) scales PITCH_TRIM as before and is `Gait.amplitude`; ℓ(t) is `Gait.lift`. All of it is
computed in closed form from t, so ``gait(t)`` stays a pure function of time. A single segment gives
the same numbers, bit for bit, as the constant controller.

Tuning (MuJoCo cat, 100 Hz loop, XL330 servo model, a grid over these constants at 1.5/2/2.5 Hz):
lift 0.5 rad (foot centre ≈ 10 mm up, enough to clear the floor while the body rocks a few degrees).
The centre of mass stands 5 mm ahead of the middle of the feet, so the body topples onto the lifted
fore foot each step; PITCH_TRIM −0.065 rad moves the feet ≈ 6 mm forward under it (without it, and
without the dwell, the trot settles into a rocking cycle that walks 1–2 cm/s). The dwell d = 0.15
damps the rocking between the diagonals (with d = 0 the outcome jumps between a clean trot and a
wobbling walk with small parameter changes). RISE 0.3 is a brisk lift (the safety layer's speed limit
trims its peak at ≥ 2 Hz); LEAD_S 40 ms matches the servo lag; BACKWARD 0.12 cancels a residual forward
creep (0.6 → < 0.2 cm/s, an empirical correction). Each constant (and lift) moved alone by ±20 % still
passes the tests.
Measured in tests/controllers/test_stepping.py (6 s at 2 Hz, 4 s at 1.5 and 2.5 Hz; ratios after the ramp):
  1.5 Hz: one diagonal alone down 64 %, no swinging foot in contact 89 %, drift 1.6 cm, tilt ≤ 4.9°
  2.0 Hz: one diagonal alone down 79 %, no swinging foot in contact 91 %, drift 1.7 cm, tilt ≤ 4.3°
  2.5 Hz: one diagonal alone down 81 %, no swinging foot in contact 93 %, drift 2.6 cm, tilt ≤ 3.9°
Over 15 s the drift stays < 3 cm at all three. The commanded dwell is seldom four feet down: the body
rocks onto the landing pair while the other pair is still settling.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from felis.controllers.pose import min_jerk
from felis.errors import ParameterError
from felis.hal import Command, State
from felis.spec import RobotSpec

LEGS = ("fl", "fr", "hl", "hr")  # the order of the gait's masks and of spec.sensors.contacts
PAIR_A = np.array([True, False, False, True])  # fl + hr: the pair that swings first
OUTWARD = np.array([1.0, -1.0, 1.0, -1.0])  # roll sign that swings each foot away from the body
BLEND_S = 0.3  # s, present pose → stand
DWELL = 0.15  # cycle fraction with all feet commanded down after each swing
RISE = 0.3  # swing fraction spent lifting (and again putting down)
LEAD_S = 0.04  # s the command runs ahead of the gait clock (servo lag)
PITCH_TRIM = -0.065  # rad on every leg pitch while stepping (feet forward, under the centre of mass)
BACKWARD = 0.12  # backward foot swing in the air, as a fraction of the lift angle
MAX_FREQUENCY_HZ = 4.0
MAX_LIFT = 0.8  # rad


@dataclass(frozen=True)
class Gait:
    """The gait's clock at one time (what a balance monitor's gait gate reads)."""

    stepping: bool  # True while the periodic gait runs (amplitude > 0)
    phase: float  # in [0, 1); 0 = start of the fl+hr swing
    swing: np.ndarray  # bool[4] in (fl, fr, hl, hr) order: feet the gait has lifted now
    frequency_hz: float
    amplitude: float  # 0..1 current ramp level
    touchdown_s: float = 0.0  # time until the swinging feet land (0 when none swings)
    lift: float = 0.0  # rad: the swing's current lift angle (amplitude · lift for a constant gait)


class Segment(NamedTuple):
    """One part of a gait schedule: ``duration_s`` seconds at ``frequency_hz`` with ``lift`` rad
    (frequency 0 or lift 0: stand)."""

    duration_s: float
    frequency_hz: float
    lift: float

    @property
    def stands(self) -> bool:
        return self.frequency_hz == 0 or self.lift == 0


def _finite(label: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if not math.isfinite(v):
        raise ParameterError(f"stepping {label} must be a finite number, got {value!r}")
    return v


def check_segments(segments) -> tuple[Segment, ...]:
    """``segments`` as `Segment` tuples; ParameterError (one line, naming the segment) if it is empty, a
    segment is not (duration_s, frequency_hz, lift), a value is not finite, a duration is not > 0, or a
    frequency or lift is out of range."""
    try:
        items = list(segments)
    except TypeError:
        raise ParameterError(f"stepping schedule must be a sequence of (duration_s, frequency_hz, lift), "
                             f"got {segments!r}") from None
    if not items:
        raise ParameterError("stepping schedule is empty: give at least one (duration_s, frequency_hz, lift)")
    out = []
    for i, seg in enumerate(items):
        if isinstance(seg, str | bytes) or not isinstance(seg, Sequence) or len(seg) != 3:
            raise ParameterError(f"stepping schedule segment {i} must be (duration_s, frequency_hz, lift), "
                                 f"got {seg!r}")
        d, f, lift = (_finite(f"segment {i} {label}", v) for label, v in zip(Segment._fields, seg, strict=True))
        if d <= 0:
            raise ParameterError(f"stepping schedule segment {i}: duration_s must be > 0 s, got {d}")
        if not 0.0 <= f <= MAX_FREQUENCY_HZ:
            raise ParameterError(f"stepping schedule segment {i}: frequency must be within "
                                 f"0…{MAX_FREQUENCY_HZ:g} Hz, got {f}")
        if not 0.0 <= lift <= MAX_LIFT:
            raise ParameterError(f"stepping schedule segment {i}: lift must be within 0…{MAX_LIFT:g} rad, got {lift}")
        out.append(Segment(d, f, lift))
    return tuple(out)


class SteppingController:
    """Trot in place: diagonal pairs (fl+hr, fr+hl) alternately lift and put down around ``stand``.

    Args:
        frequency_hz: steps of each pair per second (0…4; 0 = stand still).
        lift: outward roll of a swinging leg, rad (0…0.8; 0 = stand still).
        ramp_s: seconds over which the lift grows from 0 to full.
        start_s: seconds after reset at which the gait starts (never before the 0.3 s blend to stand).

    `SteppingController.scheduled` builds one that changes frequency and lift over time (module doc).
    """

    name = "step-in-place"

    def __init__(self, frequency_hz: float = 2.0, lift: float = 0.5, ramp_s: float = 0.5, start_s: float = 0.0):
        frequency_hz, lift, ramp_s, start_s = (_finite(label, v) for label, v in (
            ("frequency_hz", frequency_hz), ("lift", lift), ("ramp_s", ramp_s), ("start_s", start_s)))
        if not 0.0 <= frequency_hz <= MAX_FREQUENCY_HZ:
            raise ParameterError(f"stepping frequency must be within 0…{MAX_FREQUENCY_HZ:g} Hz, got {frequency_hz}")
        if not 0.0 <= lift <= MAX_LIFT:
            raise ParameterError(f"stepping lift must be within 0…{MAX_LIFT:g} rad, got {lift}")
        if ramp_s < 0 or start_s < 0:
            raise ParameterError(f"stepping ramp_s and start_s must be ≥ 0 s, got {ramp_s} and {start_s}")
        self.frequency_hz, self.lift, self.ramp_s, self.start_s = frequency_hz, lift, ramp_s, start_s
        self.schedule: tuple[Segment, ...] | None = None  # None: the constant gait above
        self.base_pose: np.ndarray | None = None
        self._q0: np.ndarray | None = None
        self._t0 = 0.0

    @classmethod
    def scheduled(cls, segments: Sequence[tuple[float, float, float]], ramp_s: float = 0.5,
                  start_s: float = 0.0) -> SteppingController:
        """A controller that runs ``segments`` of (duration_s, frequency_hz, lift) one after the other
        (module doc: the phase integrates the frequency; the lift ramps to each segment's value over
        ``ramp_s``; a segment with frequency 0 or lift 0 stands; the last segment holds).

        ``frequency_hz`` and ``lift`` of the result are the schedule's largest values (for reports).
        """
        segs = check_segments(segments)
        c = cls(frequency_hz=max(s.frequency_hz for s in segs), lift=max(s.lift for s in segs), ramp_s=ramp_s,
                start_s=start_s)
        c.schedule = segs
        starts, clock, phase0, amp0, lift0 = [0.0], [], [0.0], [0.0], [0.0]
        f = 0.0
        for i, seg in enumerate(segs):
            f = seg.frequency_hz if seg.frequency_hz > 0 else f
            clock.append(f)
            a, lift = c._ramp(i, amp0[i], lift0[i], seg.duration_s)
            starts.append(starts[-1] + seg.duration_s)
            phase0.append((phase0[-1] + f * seg.duration_s) % 1.0)
            amp0.append(a)
            lift0.append(lift)
        c._table = (starts[:-1], clock, phase0[:-1], amp0[:-1], lift0[:-1])
        return c

    @property
    def end_s(self) -> float:
        """Seconds after `reset` at which the schedule's last segment ends (the gait start for a constant
        gait): how long to run to see the whole schedule."""
        return max(self.start_s, BLEND_S) + (sum(s.duration_s for s in self.schedule) if self.schedule else 0.0)

    def _ramp(self, i: int, amp0: float, lift0: float, dt: float) -> tuple[float, float]:
        """Ramp level and lift ``dt`` s into segment ``i`` that started from ``amp0``, ``lift0``."""
        seg = self.schedule[i]
        amp1, lift1 = (0.0, 0.0) if seg.stands else (1.0, seg.lift)
        w = min(1.0, dt / self.ramp_s) if self.ramp_s > 0 else 1.0
        return amp0 + (amp1 - amp0) * w, lift0 + (lift1 - lift0) * w

    def _scheduled_gait(self, t: float) -> tuple[float, float, float, float]:
        """(phase, clock frequency, ramp level, lift) at ``t`` from the schedule (closed form)."""
        starts, clock, phase0, amp0, lift0 = self._table
        tau = t - (self._t0 + max(self.start_s, BLEND_S))
        if tau < 0:
            return 0.0, clock[0], 0.0, 0.0
        i = bisect_right(starts, tau) - 1
        dt = tau - starts[i]
        amp, lift = self._ramp(i, amp0[i], lift0[i], dt)
        return (phase0[i] + clock[i] * dt) % 1.0, clock[i], amp, lift

    def reset(self, spec: RobotSpec, state: State) -> None:
        self.base_pose = spec.pose("stand")
        self._q0 = np.asarray(state.q, dtype=float).copy()
        self._t0 = float(state.t)
        self._pitch = np.array([spec.index(f"{leg}_pitch") for leg in LEGS])
        self._roll = np.array([spec.index(f"{leg}_roll") for leg in LEGS])

    def gait(self, t: float) -> Gait:
        """The gait at time ``t`` (before `reset`, the clock counts from t = 0); a pure function of ``t``."""
        if self.schedule is not None:
            phase, frequency, amp, lift = self._scheduled_gait(t)
            if not lift > 0:
                amp = 0.0
        else:
            frequency = self.frequency_hz
            t_start = self._t0 + max(self.start_s, BLEND_S)
            running = self.frequency_hz > 0 and t >= t_start
            phase = (self.frequency_hz * (t - t_start)) % 1.0 if running else 0.0
            amp = 0.0
            if running and self.lift > 0:
                amp = min(1.0, (t - t_start) / self.ramp_s) if self.ramp_s > 0 else 1.0
            lift = amp * self.lift
        swing = np.zeros(4, dtype=bool)
        touchdown = 0.0
        if amp > 0 and phase % 0.5 < 0.5 - DWELL:
            swing = PAIR_A.copy() if phase < 0.5 else ~PAIR_A
            touchdown = (0.5 - DWELL - phase % 0.5) / frequency
        return Gait(stepping=amp > 0, phase=float(phase), swing=swing, frequency_hz=frequency,
                    amplitude=float(amp), touchdown_s=float(touchdown), lift=float(lift) if amp > 0 else 0.0)

    @staticmethod
    def _profile(s: float) -> float:
        """Lift over the swing, s ∈ [0, 1]: up in the first RISE, held, down in the last RISE."""
        return min_jerk(min(s, 1.0 - s) / RISE)

    def __call__(self, state: State) -> Command:
        if self.base_pose is None:
            raise RuntimeError("SteppingController.reset() must run before the first tick")
        q = self._q0 + min_jerk((state.t - self._t0) / BLEND_S) * (self.base_pose - self._q0)
        g = self.gait(state.t + LEAD_S)
        if g.stepping:
            s = min((g.phase % 0.5) / (0.5 - DWELL), 1.0)
            theta = g.lift * self._profile(s) * g.swing
            roll0, pitch0 = q[self._roll], q[self._pitch] + g.amplitude * PITCH_TRIM
            roll = roll0 + OUTWARD * theta
            keep_x = np.arcsin(np.clip(np.sin(pitch0) * np.cos(roll0) / np.cos(roll), -1.0, 1.0))
            q[self._roll] = roll
            q[self._pitch] = keep_x + BACKWARD * theta
        return Command(q=q)
