"""The gait's phase, frequency and amplitude online, from the recent joint trajectory, through a trained
periodic autoencoder (`felis.learning.phase.pae`, seed 003; run in numpy by `felis.learning.phase.infer`);
it feeds the balance monitor's gait gate.

**Tracking** (`phase_track`). For every frame k ≥ W − 1 of a trajectory q (T, J) the window of the last
W frames (k − W + 1 … k) is encoded (`PaeNumpy.encode`): per channel c a phase φ_c at the window's centre,
a frequency f_c, an amplitude A_c and an offset. The phase *now* (at the window's last frame) is the
centre phase carried forward half a window, as FLD propagates it:

    φ_c(now) = φ_c + f_c · (W − 1) / (2 · rate)   (mod 1)

**The gait channel and the stepping threshold** (`calibrate`, stored in the weights' metadata). On the
training recordings, over the frames whose whole window is stepping: the *strong* channels have a median
amplitude of at least half the largest; among them, those whose median frequency is within 25 % of the
lowest are the fundamental (a trot's two diagonal steps look alike, so some channels turn at twice the
cycle frequency: harmonics sit at ≥ 2×), and the strongest of those is the gait channel. No labels: only
the model's own outputs and which frames step. The stepping threshold is the amplitude halfway
(geometrically) between that channel's median amplitude over the frames whose whole window is standing
and its 5th percentile while stepping. Geometric, because a standing window's amplitude is near zero.

**Online** (`PhaseEstimator`): a loop monitor keeping the last W frames of ``state.q``, resampled onto
the model's rate by linear interpolation when the loop runs at another rate (a 50 Hz bus loop), and a
gait source for `felis.controllers.balance.BalanceMonitor.gait`: ``estimator.gait(t)`` returns a
`PhaseGait` (``stepping`` when the gait channel's amplitude is above the threshold, ``phase``,
``frequency_hz``, ``amplitude``; ``swing`` None: which feet are lifted is not known, so every lifted foot
counts; ``touchdown_s`` 0) or None until the window has filled, after a non-finite read, or when the
joint trajectory stopped arriving. Cost: one encode per tick (about 150 µs for 12 joints × 100 frames).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from felis.errors import PhaseError
from felis.learning.phase.infer import PaeNumpy, load_pae_numpy

DEFAULT_WEIGHTS = Path(__file__).parents[1] / "weights" / "phase.npz"


@dataclass(frozen=True)
class PhaseGait:
    """What the estimator tells a balance monitor's gait gate (duck-typed like `controllers.stepping.Gait`)."""

    stepping: bool
    phase: float  # the gait channel's phase now, [0, 1)
    frequency_hz: float
    amplitude: float
    swing: None = None  # unknown: every lifted foot counts in the BoS
    touchdown_s: float = 0.0


def phase_track(pae: PaeNumpy, q: np.ndarray) -> dict[str, np.ndarray]:
    """Per frame (T,) × channel (M): ``phase`` (now, module doc), ``freq``, ``amp``, ``offset``; NaN for
    the first W − 1 frames (no full window yet). ``q`` (T, J) at the model's rate."""
    cfg = pae.config
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != cfg.n_joints:
        raise PhaseError(f"trajectory has shape {q.shape}, the phase model takes (frames, {cfg.n_joints})")
    T, W = len(q), cfg.window
    out = {k: np.full((T, cfg.n_phases), np.nan) for k in ("phase", "freq", "amp", "offset")}
    ahead = (W - 1) / (2.0 * cfg.rate_hz)
    for k in range(W - 1, T):
        e = pae.encode(q[k - W + 1:k + 1].T)
        for key in ("freq", "amp", "offset"):
            out[key][k] = e[key]
        out["phase"][k] = np.mod(e["phase"] + e["freq"] * ahead, 1.0)
    return out


def _window_all(flags: np.ndarray, window: int) -> np.ndarray:
    """Per frame: the last ``window`` frames all have the flag (False for the first window − 1 frames)."""
    c = np.concatenate([[0], np.cumsum(flags.astype(int))])
    out = np.zeros(len(flags), dtype=bool)
    out[window - 1:] = (c[window:] - c[:-window]) == window
    return out


def calibrate(pae: PaeNumpy, trajectories: Sequence[np.ndarray], stepping: Sequence[np.ndarray]) -> dict:
    """The gait channel and the stepping threshold (module doc) from trajectories (T, J) and their
    per-frame stepping flags (T,)."""
    W = pae.config.window
    amps_step, amps_stand, freqs = [], [], []
    for q, s in zip(trajectories, stepping, strict=True):
        tr = phase_track(pae, q)
        s = np.asarray(s, dtype=bool)
        amps_step.append(tr["amp"][_window_all(s, W)])
        freqs.append(tr["freq"][_window_all(s, W)])
        amps_stand.append(tr["amp"][_window_all(~s, W)])
    step, stand = np.concatenate(amps_step), np.concatenate(amps_stand)
    if len(step) == 0 or len(stand) == 0:
        raise PhaseError("calibration needs whole windows of stepping and of standing")
    amp_med, f_med = np.median(step, axis=0), np.median(np.concatenate(freqs), axis=0)
    strong = amp_med >= 0.5 * amp_med.max()
    fundamental = strong & (f_med <= 1.25 * f_med[strong].min())
    channel = int(np.argmax(np.where(fundamental, amp_med, -np.inf)))
    lo, hi = float(np.median(stand[:, channel])), float(np.percentile(step[:, channel], 5))
    if not hi > lo:
        raise PhaseError(f"the gait channel's amplitude does not separate stepping ({hi:.3g}) from standing "
                         f"({lo:.3g})")
    return {"channel": channel, "stepping_amp": math.sqrt(max(lo, 1e-9) * hi),
            "amp_standing": lo, "amp_stepping_p5": hi, "amp_stepping_median": float(amp_med[channel]),
            "channel_amp_median": amp_med.round(4).tolist(), "channel_freq_median_hz": f_med.round(4).tolist()}


class PhaseEstimator:
    """Loop monitor and gait source (module doc). ``weights``: a file from ``felis train phase``."""

    def __init__(self, weights: str | Path | None = None, joints: Sequence[str] | None = None):
        path = Path(weights) if weights is not None else DEFAULT_WEIGHTS
        self.pae, meta = load_pae_numpy(path, expect_joints=list(joints) if joints is not None else None)
        cal = meta.get("phase_estimator")
        if not isinstance(cal, dict) or not {"channel", "stepping_amp"} <= set(cal):
            raise PhaseError(f"{path}: no phase-estimator calibration in the weights' metadata "
                             "(made by `felis train phase`)")
        self.path, self.channel, self.threshold = path, int(cal["channel"]), float(cal["stepping_amp"])
        if not 0 <= self.channel < self.pae.config.n_phases:
            raise PhaseError(f"{path}: gait channel {self.channel} outside the model's {self.pae.config.n_phases}")
        cfg = self.pae.config
        self.dt = 1.0 / cfg.rate_hz
        self._ahead = (cfg.window - 1) / (2.0 * cfg.rate_hz)
        self.reset()

    def reset(self, spec=None, state=None) -> None:
        """Forget the trajectory (the loop calls this with its spec and first state; a spec whose joints
        differ from the model's is refused)."""
        if spec is not None:
            names = self.pae.config.joints
            have = [j.name for j in spec.joints]
            if names is not None and list(names) != have:
                raise PhaseError(f"{self.path}: phase model joints {list(names)} differ from {spec.name}'s {have}")
        self._clear()
        self.errors = 0  # non-finite reads seen

    def _clear(self) -> None:
        cfg = self.pae.config
        self._buf = np.zeros((cfg.window, cfg.n_joints))  # ring of frames on the model's grid
        self._n = 0  # frames written
        self._t_next: float | None = None  # time of the next grid frame
        self._last: tuple[float, np.ndarray] | None = None
        self.current: PhaseGait | None = None

    def __call__(self, state, command=None) -> None:
        t, q = float(state.t), np.asarray(state.q, dtype=float)
        if not np.isfinite(q).all():  # a failed read: unknown until a full window of good frames
            self.errors += 1
            self._clear()
            return
        if self._last is None:
            self._push(q)
            self._t_next = t + self.dt
        else:
            t0, q0 = self._last
            if t - t0 > 0.2:  # a gap: the trajectory is not continuous
                self._clear()
                self._push(q)
                self._t_next = t + self.dt
            while self._t_next is not None and self._t_next <= t + 1e-9:
                a = (self._t_next - t0) / (t - t0) if t > t0 else 1.0
                self._push(q0 + a * (q - q0))
                self._t_next += self.dt
        self._last = (t, q)
        if self._n >= self.pae.config.window:
            self.current = self._estimate()

    def _push(self, q: np.ndarray) -> None:
        self._buf[self._n % len(self._buf)] = q
        self._n += 1

    def window(self) -> np.ndarray:
        """The last W frames, oldest first, (J, W)."""
        k = self._n % len(self._buf)
        return np.concatenate([self._buf[k:], self._buf[:k]]).T

    def _estimate(self) -> PhaseGait:
        e = self.pae.encode(self.window())
        c = self.channel
        f, a = float(e["freq"][c]), float(e["amp"][c])
        return PhaseGait(stepping=a > self.threshold, phase=float((e["phase"][c] + f * self._ahead) % 1.0),
                         frequency_hz=f, amplitude=a)

    def gait(self, t: float) -> PhaseGait | None:
        """The latest estimate (None: unknown; the monitor then applies its standing rules)."""
        if self.current is None or self._last is None or t - self._last[0] > 0.2:
            return None
        return self.current
