"""The fit of system identification: the servo model's parameters, per joint, that make the replay match
the recording (`fit`), and the result (`FitResult`, `fit_summary`, the ``fit`` block of a parameter file).

`fit` finds, per joint, p = (kp, damping, armature, frictionloss, torque_limit) minimising

    J(p) = Σ_k (q_sim,k(p) − q_k)² + w² · Σ_k ((e_sim,k(p) − e_k) / kp₀)²

over the joint's recorded segment: ``q_sim``/``e_sim`` come from replaying the recorded commands in
MuJoCo (`simulate`), ``kp₀`` is the datasheet gain, which turns a torque error into the position error
it would cause, and ``w`` is ``effort_weight``. Why the effort term: the position response of a
linear servo depends only on kp/I and damping/I; scaling kp, damping, armature, torque limit and
friction together changes nothing but the share of the (known) link inertia and gravity, so from
positions alone the absolute scale rests on those. The torque reading pins it directly. With
``effort_weight=0`` the fit uses positions only (servos whose current reading is poor; on the
virtual bus a leg still came out within 3 %). The optimiser is `scipy.optimize.least_squares`
(trust-region reflective) on x = log(p / p₀), bounded to ``BOUNDS`` (factors of the datasheet
values), starting at the datasheet; joints are fitted one after the other, twice when there are
several, so each sees its neighbours' fitted models (they couple through the links).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from felis.calib.sysid.excitation import STEP_KINDS
from felis.calib.sysid.model import BOUNDS, PARAMS, check_joints, default_params
from felis.calib.sysid.recording import Recording
from felis.calib.sysid.replay import Replay
from felis.errors import SysidError
from felis.sim.servo import ServoParams
from felis.spec import RobotSpec


@dataclass
class JointFit:
    """Result for one joint: parameters and position RMS errors (rad, or m) of the replay."""

    joint: str
    default: ServoParams
    fitted: ServoParams
    rms_before: float  # all ticks of the segment, datasheet parameters
    rms_after: float
    step_rms_before: float  # step and saturating-step ticks only
    step_rms_after: float
    saturated: bool  # the fitted actuator reached its torque limit: torque_limit is identified
    evaluations: int = 0
    seconds: float = 0.0

    @property
    def step_improvement(self) -> float:
        return self.step_rms_before / max(self.step_rms_after, 1e-12)

    def as_dict(self) -> dict:
        """JSON-ready (non-finite numbers become None)."""
        out = {"default": asdict(self.default), "fitted": asdict(self.fitted)}
        out.update({k: getattr(self, k) for k in ("rms_before", "rms_after", "step_rms_before", "step_rms_after",
                                                   "saturated", "evaluations", "seconds")})
        out["step_improvement"] = self.step_improvement
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in out.items()}


@dataclass
class FitResult:
    robot: str
    joints: dict[str, JointFit] = field(default_factory=dict)
    effort_weight: float = 1.0
    latency_s: float = 0.0

    @property
    def params(self) -> dict[str, ServoParams]:
        return {n: f.fitted for n, f in self.joints.items()}

    def as_dict(self) -> dict:
        return {"robot": self.robot, "effort_weight": self.effort_weight, "latency_s": self.latency_s,
                "joints": {n: f.as_dict() for n, f in self.joints.items()}}


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else float("nan")


def fit(spec: RobotSpec, recording: Recording, joints: Sequence[str] | None = None, *,
        initial: Mapping[str, ServoParams] | None = None, effort_weight: float = 1.0,
        fixed_base: bool | None = None, latency_s: float | None = None, passes: int | None = None,
        max_evaluations: int = 200, progress: Callable[[str, int, int], None] | None = None) -> FitResult:
    """Fit the servo model of each of ``joints`` (default: those the recording excites) to the recording.

    Per joint, `scipy.optimize.least_squares` on log(p / p₀) within ``BOUNDS`` (module doc), replaying
    that joint's segment; the other joints are simulated with their latest estimate (``initial``, else
    the datasheet, until fitted). ``passes`` (default 2 for several joints, else 1) repeats the round
    so that each joint is refitted with its neighbours' fitted values (they couple through the links).
    "Before" errors replay the datasheet model for every joint, "after" the fitted one.
    ``progress(joint, index, count)`` is called before each joint of each pass.
    """
    from scipy.optimize import least_squares  # here: scipy.optimize is slow to import and only the fit needs it

    if not math.isfinite(effort_weight) or effort_weight < 0:
        raise SysidError(f"effort weight must be a non-negative number, got {effort_weight}")
    names = recording.tested if joints is None else check_joints(spec, joints)
    segments = {name: recording.segment(name) for name in names}
    passes = (2 if len(names) > 1 else 1) if passes is None else int(passes)
    if passes < 1:
        raise SysidError(f"passes must be at least 1, got {passes}")
    defaults = default_params(spec)
    replay = Replay(spec, recording, None, fixed_base=fixed_base, latency_s=latency_s)
    result = FitResult(robot=spec.name, effort_weight=effort_weight, latency_s=replay.latency_s)
    use_effort = effort_weight > 0 and bool(np.all(np.isfinite(recording.effort)))
    lo = np.log([BOUNDS[k][0] for k in PARAMS])
    hi = np.log([BOUNDS[k][1] for k in PARAMS])

    def data(name: str):
        i, seg = spec.index(name), segments[name]
        k = np.arange(seg.start, seg.stop)
        ok = recording.valid[k].copy()
        ok[0] = False  # the initial state is the measurement itself
        return i, seg, k, ok, np.isin(recording.kind[k], STEP_KINDS) & ok

    before = {}
    for name in names:  # datasheet model everywhere
        i, seg, k, ok, steps = data(name)
        q = replay.run(seg)[0][:, i] - recording.q[k, i]
        before[name] = (_rms(q[ok]), _rms(q[steps]))
    current = {n: (initial or {}).get(n, defaults[n]) for n in spec.names}
    for n, p in current.items():
        replay.set(n, p)
    evals = dict.fromkeys(names, 0)
    seconds = dict.fromkeys(names, 0.0)
    for rnd in range(passes):
        for count, name in enumerate(names):
            if progress is not None:
                progress(name, rnd * len(names) + count, passes * len(names))
            t_start = time.perf_counter()
            i, seg, k, ok, steps = data(name)
            q_meas, e_meas = recording.q[k, i], recording.effort[k, i]
            p0 = defaults[name]
            base = np.array([getattr(p0, f) for f in PARAMS])
            x0 = np.clip(np.log(np.array([getattr(current[name], f) for f in PARAMS]) / base), lo + 1e-9, hi - 1e-9)
            w = effort_weight / p0.kp
            scale = 1.0 / math.sqrt(max(1, int(ok.sum())))

            def params_of(x: np.ndarray, base=base) -> ServoParams:
                return ServoParams(**dict(zip(PARAMS, (base * np.exp(x)).tolist(), strict=True)))

            def residuals(x: np.ndarray, name=name, i=i, seg=seg, ok=ok, q_meas=q_meas, e_meas=e_meas, w=w,
                          scale=scale) -> np.ndarray:
                evals[name] += 1
                replay.set(name, params_of(x))
                q, e = replay.run(seg)
                r = [(q[:, i] - q_meas)[ok]]
                if use_effort:
                    r.append(w * (e[:, i] - e_meas)[ok])
                # a diverged replay (parameters at the edge of BOUNDS) counts as a large error, not a crash
                return np.nan_to_num(np.concatenate(r), nan=10.0, posinf=10.0, neginf=-10.0) * scale

            try:
                sol = least_squares(residuals, x0, bounds=(lo, hi), method="trf", x_scale=1.0, diff_step=0.02,
                                    max_nfev=max_evaluations, xtol=1e-4, ftol=1e-6)
            except ValueError as e:
                raise SysidError(f"{name}: the fit failed: {e}") from None
            current[name] = params_of(sol.x)
            replay.set(name, current[name])  # later joints see this one as fitted
            seconds[name] += time.perf_counter() - t_start
    for name in names:
        i, seg, k, ok, steps = data(name)
        best = current[name]
        q_after = replay.run(seg)[0][:, i]
        r = q_after - recording.q[k, i]
        force = best.kp * (recording.q_cmd[k, i] - q_after)
        result.joints[name] = JointFit(
            joint=name, default=defaults[name], fitted=best, rms_before=before[name][0], rms_after=_rms(r[ok]),
            step_rms_before=before[name][1], step_rms_after=_rms(r[steps]),
            saturated=bool(np.any(np.abs(force) >= best.torque_limit)), evaluations=evals[name],
            seconds=seconds[name])
    return result


def fit_summary(result: FitResult) -> dict:
    """The ``fit`` block of a parameter file: errors before/after per joint, settings."""
    return {"effort_weight": result.effort_weight, "latency_s": result.latency_s,
            "joints": {n: {k: v for k, v in f.as_dict().items() if k not in ("default", "fitted")}
                       for n, f in result.joints.items()}}
