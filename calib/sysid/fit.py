"""The fit of system identification: the servo model's parameters, per joint, that make the replay match
the recording (`fit`), and the result (`FitResult`, `fit_summary`, the ``fit`` block of a parameter file).

`fit` finds, per joint, the parameters p of `PARAMS` (Position P, I, D Gain in control-table units, damping,
armature, friction, torque limit, latency; any of them can be held, ``fixed``) minimising

    J(p) = Σ_k (q_sim,k(p) − q_k)² + w² · Σ_k ((e_sim,k(p) − e_k) / kp₀)²

over the joint's recorded segment: ``q_sim``/``e_sim`` come from replaying the recorded commands in
MuJoCo through the firmware's controller (`Replay`), ``kp₀`` is the starting P term's stiffness, which turns a
torque error into the position error it would cause, and ``w`` is ``effort_weight``. Why the effort term: the
position response alone fixes only ratios (kp/I, damping/I: scaling every torque and the inertia together
changes nothing but the share of the known link inertia); the torque reading pins the scale, and it tells D
(velocity feedback inside the controller, clipped with it) from the back-EMF damping (outside it: still
there when the output saturates), and shows the integral's torque directly. With ``effort_weight=0`` the fit
uses positions only. The optimiser is `scipy.optimize.least_squares` (trust-region reflective) on x =
log(p / p₀) for `LOG` parameters and p / scale for the others (which may reach 0: an I or D of 0, no
friction, no latency), bounded by `BOUNDS`, starting at the description's gains, the datasheet and the
recording's latency; joints are fitted one after the other, twice when there are several, so each sees its
neighbours' fitted models (they couple through the links).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from felis.calib.sysid.excitation import STEP_KINDS
from felis.calib.sysid.model import (
    BOUNDS,
    LOG,
    PARAMS,
    assemble,
    check_joints,
    default_params,
    gains,
    scale,
    value,
    with_gains,
)
from felis.calib.sysid.recording import Recording
from felis.calib.sysid.replay import Replay
from felis.errors import SysidError
from felis.sim.servo import ServoParams
from felis.spec import RobotSpec


@dataclass
class JointFit:
    """Result for one joint: models (``pid`` set: P, I, D) and position RMS errors (rad, or m) of the replay."""

    joint: str
    default: ServoParams
    fitted: ServoParams
    rms_before: float  # all ticks of the segment, starting model
    rms_after: float
    step_rms_before: float  # step and saturating-step ticks only
    step_rms_after: float
    saturated: bool  # the fitted actuator reached its torque limit: torque_limit is identified
    latency_before: float = 0.0  # s
    latency_after: float = 0.0
    evaluations: int = 0
    seconds: float = 0.0

    @property
    def pid(self) -> tuple[float, float, float]:
        return self.fitted.pid

    @property
    def step_improvement(self) -> float:
        return self.step_rms_before / max(self.step_rms_after, 1e-12)

    def as_dict(self) -> dict:
        """JSON-ready (non-finite numbers become None)."""
        out = {"default": asdict(self.default), "fitted": asdict(self.fitted)}
        out["default"]["latency_s"], out["fitted"]["latency_s"] = self.latency_before, self.latency_after
        for d in (out["default"], out["fitted"]):
            d["pid"] = list(d["pid"])
        out.update({k: getattr(self, k) for k in ("rms_before", "rms_after", "step_rms_before", "step_rms_after",
                                                   "saturated", "evaluations", "seconds")})
        out["step_improvement"] = self.step_improvement
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in out.items()}


@dataclass
class FitResult:
    robot: str
    joints: dict[str, JointFit] = field(default_factory=dict)
    effort_weight: float = 1.0
    latency_s: float = 0.0  # the starting latency
    timebase: str = ""
    fixed: tuple[str, ...] = ()

    @property
    def params(self) -> dict[str, ServoParams]:
        return {n: f.fitted for n, f in self.joints.items()}

    def as_dict(self) -> dict:
        return {"robot": self.robot, "effort_weight": self.effort_weight, "latency_s": self.latency_s,
                "timebase": self.timebase, "fixed": list(self.fixed),
                "joints": {n: f.as_dict() for n, f in self.joints.items()}}


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else float("nan")


def fit(spec: RobotSpec, recording: Recording, joints: Sequence[str] | None = None, *,
        initial: Mapping[str, ServoParams] | None = None, effort_weight: float = 1.0,
        fixed_base: bool | None = None, latency_s: float | None = None, passes: int | None = None,
        fixed: Sequence[str] = (), max_evaluations: int = 200,
        progress: Callable[[str, int, int], None] | None = None) -> FitResult:
    """Fit the servo model of each of ``joints`` (default: those the recording excites) to the recording.

    Per joint, `scipy.optimize.least_squares` within ``BOUNDS`` (module doc) on the parameters of `PARAMS` not
    in ``fixed`` (those keep their starting value), replaying that joint's segment; the other joints are
    simulated with their latest estimate (``initial``, else the datasheet servo at the description's gains,
    until fitted). ``latency_s`` is the starting latency (default: the recording's, `Recording.latency_s`).
    ``passes`` (default 2 for several joints on a robot, else 1) repeats the round so that each joint is refitted with
    its neighbours' fitted values (they couple through the links). "Before" errors replay the starting model
    for every joint, "after" the fitted one. ``progress(joint, index, count)`` is called before each joint of
    each pass.
    """
    from scipy.optimize import least_squares  # here: scipy.optimize is slow to import and only the fit needs it

    if not math.isfinite(effort_weight) or effort_weight < 0:
        raise SysidError(f"effort weight must be a non-negative number, got {effort_weight}")
    unknown = sorted(set(fixed) - set(PARAMS))
    if unknown:
        raise SysidError(f"cannot hold {unknown[0]!r}: the parameters are {', '.join(PARAMS)}")
    free = tuple(k for k in PARAMS if k not in fixed)
    if not free:
        raise SysidError("every parameter is held: nothing to fit")
    names = recording.tested if joints is None else check_joints(spec, joints)
    segments = {name: recording.segment(name) for name in names}
    coupled = len(names) > 1 and recording.setup != "bench"  # bare horns do not couple
    passes = (2 if coupled else 1) if passes is None else int(passes)
    if passes < 1:
        raise SysidError(f"passes must be at least 1, got {passes}")
    defaults = default_params(spec)
    replay = Replay(spec, recording, None, fixed_base=fixed_base, latency_s=latency_s)
    lat0 = replay.latency_s
    result = FitResult(robot=spec.name, effort_weight=effort_weight, latency_s=lat0, timebase=recording.timebase,
                       fixed=tuple(k for k in PARAMS if k in fixed))
    use_effort = effort_weight > 0 and bool(np.all(np.isfinite(recording.effort)))

    def data(name: str):
        i, seg = spec.index(name), segments[name]
        k = np.arange(seg.start, seg.stop)
        ok = recording.valid[k].copy()
        ok[0] = False  # the initial state is the measurement itself
        return i, seg, k, ok, np.isin(recording.kind[k], STEP_KINDS) & ok

    before = {}
    for name in names:  # starting model everywhere
        i, seg, k, ok, steps = data(name)
        q = replay.run(seg)[0][:, i] - recording.q[k, i]
        before[name] = (_rms(q[ok]), _rms(q[steps]))
    current = {n: (initial or {}).get(n, defaults[n]) for n in spec.names}
    latency = dict.fromkeys(names, lat0)
    for n, p in current.items():
        replay.set(n, p)
    evals = dict.fromkeys(names, 0)
    seconds = dict.fromkeys(names, 0.0)
    for rnd in range(passes):
        for count, name in enumerate(names):
            if progress is not None:
                progress(name, rnd * len(names) + count, passes * len(names))
            t_start = time.perf_counter()
            joint = spec.joints[spec.index(name)]
            i, seg, k, ok, steps = data(name)
            q_meas, e_meas = recording.q[k, i], recording.effort[k, i]
            start = defaults[name]
            ref = np.array([value(joint, start, lat0, f) if f in LOG else scale(joint, start, f) for f in free])
            log = np.array([f in LOG for f in free])
            lo = np.array([math.log(BOUNDS[f][0]) if f in LOG else BOUNDS[f][0] for f in free])
            hi = np.array([math.log(BOUNDS[f][1]) if f in LOG else BOUNDS[f][1] for f in free])
            now = np.array([value(joint, current[name], latency[name], f) for f in free])
            x0 = np.where(log, np.log(np.maximum(now, 1e-300) / ref), now / ref)
            x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
            w = effort_weight / start.kp
            rscale = 1.0 / math.sqrt(max(1, int(ok.sum())))
            held = {f: value(joint, current[name], latency[name], f) for f in PARAMS if f not in free}

            def model_of(x: np.ndarray, joint=joint, ref=ref, log=log, held=held) -> tuple[ServoParams, float]:
                v = np.where(log, ref * np.exp(x), ref * x)
                return assemble(joint, defaults[joint.name], {**held, **dict(zip(free, v.tolist(), strict=True))})

            def residuals(x: np.ndarray, name=name, i=i, seg=seg, ok=ok, q_meas=q_meas, e_meas=e_meas, w=w,
                          rscale=rscale, model_of=model_of) -> np.ndarray:
                evals[name] += 1
                p, lat = model_of(x)
                replay.set(name, p)
                q, e = replay.run(seg, latency_s=lat)
                r = [(q[:, i] - q_meas)[ok]]
                if use_effort:
                    r.append(w * (e[:, i] - e_meas)[ok])
                # a diverged replay (parameters at the edge of BOUNDS) counts as a large error, not a crash
                return np.nan_to_num(np.concatenate(r), nan=10.0, posinf=10.0, neginf=-10.0) * rscale

            try:
                sol = least_squares(residuals, x0, bounds=(lo, hi), method="trf", x_scale=1.0, diff_step=1e-3,
                                    max_nfev=max_evaluations, xtol=1e-5, ftol=1e-8)
            except ValueError as e:
                raise SysidError(f"{name}: the fit failed: {e}") from None
            current[name], latency[name] = model_of(sol.x)
            replay.set(name, current[name])  # later joints see this one as fitted
            seconds[name] += time.perf_counter() - t_start
    for name in names:
        joint = spec.joints[spec.index(name)]
        i, seg, k, ok, steps = data(name)
        best = current[name]
        q_after = replay.run(seg, latency_s=latency[name])[0][:, i]
        r = q_after - recording.q[k, i]
        force = best.kp * (recording.q_cmd[k, i] - q_after)
        start = defaults[name]
        result.joints[name] = JointFit(
            joint=name, default=with_gains(joint, start, gains(joint, start)), fitted=best,
            rms_before=before[name][0], rms_after=_rms(r[ok]), step_rms_before=before[name][1],
            step_rms_after=_rms(r[steps]), saturated=bool(np.any(np.abs(force) >= best.torque_limit)),
            latency_before=lat0, latency_after=latency[name], evaluations=evals[name], seconds=seconds[name])
    return result


def fit_summary(result: FitResult) -> dict:
    """The ``fit`` block of a parameter file: errors before/after per joint, latencies, settings."""
    return {"effort_weight": result.effort_weight, "latency_s": result.latency_s, "timebase": result.timebase,
            "fixed": list(result.fixed),
            "joints": {n: {**{k: v for k, v in f.as_dict().items() if k not in ("default", "fitted")},
                           "latency_s": f.latency_after} for n, f in result.joints.items()}}
