"""How well the learned phase tracks the cat's gait, and what it does for the balance monitor (issue 8).

**Phase against the gait** (`phase_metrics`, on recordings with foot contacts and the gait clock, i.e.
simulated ones). A *steady segment* is a run of frames at one commanded frequency and lift; it is judged
from one window after its start (the window then holds that gait only) to its end. On each:

* true step frequency f* from foot-contact timing (`felis.learning.phase.data.contact_frequency`);
* phase rate: the slope of the gait channel's unwrapped phase (least squares, cycles/s) over the
  segment; its ratio r = rate/f* is compared with the nearest integer multiple n = max(1, round(r))
  (a channel may turn at twice the step frequency: both diagonals' steps look alike): error |r/n − 1|;
* frequency output: the median of the gait channel's frequency f_c over the segment, error |f_c/f* − 1|
  (and against the nearest multiple, as for the phase);
* standing: over the frames whose whole window stands, the gait channel's median amplitude, as a
  fraction of its median while stepping;
* continuity: the largest phase step between consecutive frames, |Δφ| on the circle minus the step the
  frequency predicts (f_c·Δt), in cycles, over the frames within one window of a gait change, against the
  same over steady frames: a continuous phase shows no jump at the changes. Only frames where the gait
  channel's amplitude is above the stepping threshold count: standing, A ≈ 0 and the phase is undefined.

**Gate** (`gate_comparison`): pushes on the simulated cat with three balance monitors watching the same
run: gated by the stepping controller's own clock (the reference), by the online phase estimator
(`felis.learning.phase.estimator.PhaseEstimator`), and without a gate. No reaction: the monitors only
watch, so all three see the same physics. Recall and false alarms per monitor, per phase of the push.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from felis.learning.common.evaluator import run_jobs, worker_count
from felis.learning.phase.data import GaitRecording, contact_frequency
from felis.learning.phase.estimator import PhaseEstimator, _window_all, phase_track
from felis.learning.phase.infer import PaeNumpy

MIN_SEGMENT_S = 2.0  # s of a steady segment after its first window, to be judged
GATES = ("clock", "phase", "none")


def _segments(rec: GaitRecording) -> list[tuple[int, int]]:
    """(start, stop) frame ranges of constant commanded frequency > 0 and lift."""
    key = np.where(rec.stepping, rec.frequency_hz * 1000 + rec.amplitude, -1.0)
    edges = np.flatnonzero(np.diff(key) != 0) + 1
    bounds = np.concatenate([[0], edges, [len(key)]])
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if key[a] >= 0]


def _circ(d: np.ndarray) -> np.ndarray:
    """Differences of phases in cycles, wrapped to [−½, ½)."""
    return (d + 0.5) % 1.0 - 0.5


def phase_metrics(pae: PaeNumpy, channel: int, recs: Sequence[GaitRecording], threshold: float = 0.0) -> dict:
    """The module doc's phase figures over ``recs`` (each at the model's rate, with contacts and clock);
    ``threshold``: the stepping amplitude (a phase is only defined, and judged for continuity, above it)."""
    W, rate = pae.config.window, pae.config.rate_hz
    segs, stand_amp, step_amp, jumps_change, jumps_steady = [], [], [], [], []
    for rec in recs:
        tr = phase_track(pae, rec.q)
        ph, f, a = tr["phase"][:, channel], tr["freq"][:, channel], tr["amp"][:, channel]
        step_all, stand_all = _window_all(rec.stepping, W), _window_all(~rec.stepping, W)
        step_amp.append(a[step_all])
        stand_amp.append(a[stand_all])
        # continuity: phase steps near gait changes vs elsewhere (all frames with a full window)
        d = np.abs(_circ(np.diff(ph)) - f[1:] / rate)
        change = np.zeros(len(rec.t), dtype=bool)
        key = np.where(rec.stepping, rec.frequency_hz * 1000 + rec.amplitude, -1.0)
        for e in np.flatnonzero(np.diff(key) != 0) + 1:
            change[max(0, e - W):e + W] = True
        ok = np.isfinite(d) & (a[1:] > threshold) & (a[:-1] > threshold)
        jumps_change.append(d[ok & change[1:]])
        jumps_steady.append(d[ok & ~change[1:]])
        for a0, b0 in _segments(rec):
            s = a0 + W
            if (b0 - s) / rate < MIN_SEGMENT_S:
                continue
            true_f = contact_frequency(rec, rec.t[s], rec.t[b0 - 1])
            if not math.isfinite(true_f):
                continue
            unwrapped = np.unwrap(2 * math.pi * ph[s:b0]) / (2 * math.pi)
            rate_c = float(np.polyfit(rec.t[s:b0], unwrapped, 1)[0])
            med_f = float(np.median(f[s:b0]))
            r = abs(rate_c) / true_f
            n = max(1, round(r))
            rf = med_f / true_f
            nf = max(1, round(rf))
            segs.append({"recording": rec.name, "t0_s": round(float(rec.t[s]), 2),
                         "t1_s": round(float(rec.t[b0 - 1]), 2), "commanded_hz": round(float(rec.frequency_hz[s]), 3),
                         "lift": round(float(rec.amplitude[s]), 3),
                         "contact_hz": round(true_f, 4), "phase_rate_hz": round(rate_c, 4), "phase_multiple": n,
                         "phase_error": round(abs(r / n - 1), 4), "frequency_hz": round(med_f, 4),
                         "frequency_error": round(abs(rf - 1), 4), "frequency_multiple": nf,
                         "frequency_error_multiple": round(abs(rf / nf - 1), 4)})
    step, stand = np.concatenate(step_amp), np.concatenate(stand_amp)
    jc, js = np.concatenate(jumps_change), np.concatenate(jumps_steady)
    worst = lambda key: max((s[key] for s in segs), default=math.nan)  # noqa: E731
    return {
        "segments": segs,
        "phase_error_max": worst("phase_error"),
        "frequency_error_max": worst("frequency_error"),
        "frequency_error_multiple_max": worst("frequency_error_multiple"),
        "frequency_error_median": float(np.median([s["frequency_error"] for s in segs])) if segs else math.nan,
        "amp_stepping_median": float(np.median(step)) if step.size else math.nan,
        "amp_standing_median": float(np.median(stand)) if stand.size else math.nan,
        "amp_standing_ratio": float(np.median(stand) / np.median(step)) if stand.size and step.size else math.nan,
        "phase_jump_at_changes_max": float(jc.max()) if jc.size else math.nan,
        "phase_jump_steady_max": float(js.max()) if js.size else math.nan,
        "phase_jump_steady_p99": float(np.percentile(js, 99)) if js.size else math.nan,
    }


# --------------------------------------------------------------------------------------- the gate
class _Watch:
    """Loop monitor: a balance monitor's first alarm time."""

    def __init__(self, monitor):
        self.monitor, self.alarm_t = monitor, None

    def reset(self, spec=None, state=None) -> None:
        self.monitor.reset(spec, state)
        self.alarm_t = None

    def __call__(self, state, command) -> None:
        if self.monitor.assess(state).alarm and self.alarm_t is None:
            self.alarm_t = state.t


_SIM = None
_WEIGHTS: str | None = None


def _init(weights: str) -> None:
    global _SIM, _WEIGHTS
    from felis.learning.balance.evaluate import PushSim

    _SIM, _WEIGHTS = PushSim(), weights


def _one(p) -> dict:
    from felis.controllers.balance import BalanceMonitor

    est = PhaseEstimator(_WEIGHTS, joints=[j.name for j in _SIM.spec.joints])
    phase = _Watch(BalanceMonitor(_SIM.body, gait=est.gait))
    none = _Watch(BalanceMonitor(_SIM.body))
    o = _SIM.run(p, "none", monitors=[est, phase, none])  # the estimator updates before its monitor reads it
    return {**p.as_dict(), "fell": o.fell, "fall_t_s": o.fall_t,
            "alarm_t_s": {"clock": o.alarm_t, "phase": phase.alarm_t, "none": none.alarm_t}}


def gate_comparison(pushes, weights: str | Path, workers: int | None = None,
                    progress: Callable[[int], None] | None = None) -> dict:
    """Recall and false alarms of the three monitors (module doc) on the same runs, overall and by phase."""
    rows = run_jobs(_one, pushes, worker_count(workers, len(pushes)), _init, (str(weights),), progress=progress)
    out = {"pushes": len(rows)}
    for phase in ("all", "stand", "step"):
        sel = [r for r in rows if phase == "all" or r["phase"] == phase]
        out[phase] = {g: _detection(sel, g) for g in GATES}
        out[phase]["pushes"] = len(sel)
        out[phase]["falls"] = sum(r["fell"] for r in sel)
    out["rows"] = rows
    return out


def _detection(rows: Sequence[dict], gate: str) -> dict:
    falls = [r for r in rows if r["fell"]]
    safe = [r for r in rows if not r["fell"]]
    det = [r for r in falls if r["alarm_t_s"][gate] is not None and r["alarm_t_s"][gate] <= r["fall_t_s"] + 1e-9]
    fa = [r for r in safe if r["alarm_t_s"][gate] is not None]
    leads = [r["fall_t_s"] - r["alarm_t_s"][gate] for r in det]
    return {"recall": round(len(det) / len(falls), 4) if falls else None,
            "false_alarm_rate": round(len(fa) / len(safe), 4) if safe else None,
            "false_alarms": len(fa), "misses": len(falls) - len(det),
            "median_lead_s": round(float(np.median(leads)), 4) if leads else None}
