"""The arm's learned IK pipeline (seed 001 §3.1): targets → MP → PE → mean filter → exact refinement.

For each control tick i with tool-point target T_i (m, base frame):

1. **Input.** v_i = (T_i − S) / L, the shoulder → tool vector over the limb length (§3.1.1), its
   norm clipped to 1 so that out-of-reach targets stay inside what the nets were trained on.
2. **Motion Predictor** (§3.1.2): (v_{i−10}, v_{i−5}, v_i) → (v̂_{i+5}, v̂_{i+10}).
3. **Posture Estimator** (§3.1.2): (v_{i−10}, v_{i−5}, v_i, v̂_{i+5}, v̂_{i+10}) → joint angles of
   frames i … i+5, as (sin, cos) pairs decoded by atan2 (no wrap jumps). Variants trained with
   fewer input frames (the ablation: 1 or 3) skip what they do not need.
4. **Mean filter** (§3.1.3, eq. 3.3): P = (1/N)(Σ_{j=i−5}^{i−1} P_j^sent + Σ_{j=i}^{i+5} P̂_j), the poses
   already sent and the predicted ones (N = 11 once five poses have been sent), averaged as angle
   differences to P̂_i so that joint1 may cross ±π.
5. **Pitch smoothing** (ours, not in the paper): the tool pitch φ = q2 + q3 + q4 is the redundant
   degree of freedom, the only thing the nets choose that refinement keeps. It passes a critically
   damped second-order low-pass at ``pitch_hz`` (default 5 Hz, ω = 2π·f):
   φ̇_i = φ̇_{i−1} + Δt (ω² (φ_in − φ_{i−1}) − 2ω φ̇_{i−1}),  φ_i = φ_{i−1} + Δt φ̇_i,
   whose state is read back from the last two poses sent (φ̇_{i−1} = (φ_{i−1} − φ_{i−2}) / Δt), so a
   batch of independent queries needs nothing else. The nets' outputs are continuous but not smooth
   to the third derivative: on the 40 held-out demonstrations the shipped nets' RMS joint jerk is
   5.9× the demonstrations' without this stage and 0.70× with it at 5 Hz, for a median pitch off the
   demonstrator's of 0.17° → 1.17° (p95 0.8° → 6.3°: the lag on fast pitch changes); 3 Hz gives
   0.48× and 2.0°, 8 Hz 1.31× and 0.72°. Without the mean filter (``use_filter=False``) the 5 Hz stage
   alone gives 0.94× and 0.67°: the filter's past poses add lag of their own. Position accuracy is
   untouched: step 6 is exact for any pitch.
6. **Refinement** (`armkin.refine`): the closed form with the smoothed pitch and the filtered pose's
   elbow branch (exact to machine precision), else the nearest feasible pitch, else the nearest
   reachable point by DLS within the joint limits, flagged unreachable.

A history of 11 targets is kept; at the start it is filled with the first target (a stream that
starts from rest). A non-finite target is not used: the previous one is held and the step says so.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from felis import armkin
from felis.errors import TrajectoryError, WeightsError
from felis.learning.ik.infer import MP_IN, MP_OUT, PE_OUT, decode_angles, load_weights, normalise

DEFAULT_WEIGHTS = Path(__file__).parents[1] / "weights" / "ik.npz"
HISTORY = 11  # targets i−10 … i
PAST = 5  # sent poses i−5 … i−1 in the mean filter
PITCH_HZ = 5.0  # cut-off of the pitch smoothing (0: off)
DT = 0.01  # s: one frame at 100 Hz


def mean_filter(past: np.ndarray | None, poses: np.ndarray, n_past: int = PAST) -> np.ndarray:
    """Eq. 3.3 of seed 001: the mean of the last ``n_past`` poses sent, ``past`` (B, P, 4), and the
    predicted ones, ``poses`` (B, 6, 4), averaged as angle differences to the predicted current pose
    ``poses[:, 0]`` (each wrapped to (−π, π]) so that a joint crossing ±π averages correctly."""
    ref = poses[:, 0]
    k = 0 if past is None else min(past.shape[1], n_past)
    stack = np.concatenate([past[:, past.shape[1] - k:], poses], axis=1) if k else poses
    return ref + np.angle(np.exp(1j * (stack - ref[:, None, :]))).mean(axis=1)


def smooth_pitch(q: np.ndarray, past: np.ndarray | None, hz: float = PITCH_HZ) -> np.ndarray:
    """Step 5 above: ``q`` (B, 4) with q4 changed so that its pitch is one step of the critically damped
    low-pass from the last two poses sent (``past`` (B, P ≥ 2, 4)); ``q`` unchanged without them."""
    if hz <= 0 or past is None or past.shape[1] < 2:
        return q
    w = 2 * np.pi * hz
    phi1, phi2 = armkin.pitch(past[:, -1]), armkin.pitch(past[:, -2])
    v = (phi1 - phi2) / DT
    v = v + DT * (w * w * (armkin.pitch(q) - phi1) - 2 * w * v)
    out = np.array(q, dtype=float, copy=True)
    out[:, 3] += phi1 + DT * v - armkin.pitch(q)
    return out


@dataclass
class IkStep:
    """One tick of the pipeline. ``q`` is what to command (refined, within the joint limits)."""

    q: np.ndarray
    q_net: np.ndarray  # the Posture Estimator's pose for frame i (the raw network)
    q_filtered: np.ndarray  # after the mean filter, before refinement
    target: np.ndarray  # the target used (the previous one when the given one was not finite)
    error: float  # |fk(q) − target| (m)
    exact: bool  # closed form with the network's own pitch and branch
    reachable: bool  # False: the target is outside the workspace; q is the nearest reachable point
    valid: bool  # False: the given target was not finite and the previous one was held


class IkSolver:
    """The streaming pipeline. ``nets`` holds ``"mp"`` and ``"pe"`` (`felis.learning.ik.infer.NumpyNet`),
    ``pe_in`` the Posture Estimator's input frame offsets (a subset of −10, −5, 0, 5, 10)."""

    def __init__(self, nets: dict, pe_in: tuple[int, ...], *, filter_past: int = PAST, use_filter: bool = True,
                 pitch_hz: float = PITCH_HZ):
        for name in ("mp", "pe"):
            if name not in nets:
                raise WeightsError(f"IK weights lack the {name!r} net")
        if not set(pe_in) <= {-10, -5, 0, 5, 10} or 0 not in pe_in:
            raise WeightsError(f"IK weights: Posture Estimator input offsets {pe_in} are not a subset of "
                               "(-10, -5, 0, 5, 10) holding 0")
        self.mp, self.pe = nets["mp"], nets["pe"]
        self.pe_in = tuple(int(o) for o in pe_in)
        self.filter_past = int(filter_past) if use_filter else 0
        self.use_filter = use_filter
        if not (np.isfinite(pitch_hz) and 0 <= pitch_hz <= 20):
            raise ValueError(f"pitch smoothing must be within 0…20 Hz (0: off), got {pitch_hz}")
        self.pitch_hz = float(pitch_hz)
        self.meta: dict = {}  # the weights file's metadata (corpus, configuration, history) when loaded
        self.reset()

    @classmethod
    def load(cls, path: str | Path | None = None, **kwargs) -> IkSolver:
        """The pipeline from a weights file (default: the shipped ``learning/weights/ik.npz``)."""
        nets, meta = load_weights(Path(path) if path is not None else DEFAULT_WEIGHTS, expect={"nets": ("mp", "pe")})
        solver = cls(nets, tuple(meta.get("pe_in", (-10, -5, 0, 5, 10))), **kwargs)
        solver.meta = meta
        return solver

    def reset(self) -> None:
        """Forget the target history and the poses sent (a new trajectory)."""
        self._hist: deque[np.ndarray] = deque(maxlen=HISTORY)
        self._past: deque[np.ndarray] = deque(maxlen=max(self.filter_past, 2))
        self._last_target: np.ndarray | None = None

    # ------------------------------------------------------------------ the vectorised core
    def _inputs(self, targets: np.ndarray) -> np.ndarray:
        v = normalise(targets)
        n = np.linalg.norm(v, axis=-1, keepdims=True)
        return v / np.maximum(n, 1.0)

    def predict(self, hist: np.ndarray, past: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The pipeline on a batch: ``hist`` (B, 11, 3) targets i−10 … i (m), ``past`` (B, P, 4) poses
        sent before (or None). Returns ``q``, ``q_net``, ``q_filtered``, ``poses`` (B, 6, 4),
        ``future`` (B, 2, 3) normalised, ``error``, ``exact``, ``reachable``."""
        hist = np.asarray(hist, dtype=float)
        v = self._inputs(hist)
        frames = {-10: v[:, 0], -5: v[:, 5], 0: v[:, 10]}
        future = None
        if any(o > 0 for o in self.pe_in):
            mp_x = np.stack([frames[o] for o in MP_IN], axis=1)
            future = np.asarray(self.mp(mp_x), dtype=float).reshape(len(v), len(MP_OUT), 3)
            frames.update({o: future[:, k] for k, o in enumerate(MP_OUT)})
        pe_x = np.stack([frames[o] for o in self.pe_in], axis=1)
        poses = decode_angles(np.asarray(self.pe(pe_x), dtype=float).reshape(len(v), len(PE_OUT), 8))
        q_net = poses[:, 0]
        q_filtered = mean_filter(past, poses, self.filter_past) if self.use_filter else q_net
        seed = smooth_pitch(q_filtered, past, self.pitch_hz)
        res = armkin.refine(hist[:, -1], seed)
        return {"q": res.q, "q_net": q_net, "q_filtered": q_filtered, "poses": poses, "future": future,
                "error": res.error, "exact": res.exact, "reachable": res.reachable}

    # ------------------------------------------------------------------ streaming
    def step(self, target) -> IkStep:
        """One tick: the next target (3,) in metres → the joint angles to command."""
        t = np.asarray(target, dtype=float).reshape(-1)
        valid = t.shape == (3,) and bool(np.all(np.isfinite(t)))
        if not valid:
            if self._last_target is None:
                raise TrajectoryError(f"the first IK target must be 3 finite numbers, got {target!r}")
            t = self._last_target
        self._last_target = t
        if not self._hist:
            self._hist.extend([t] * HISTORY)
        else:
            self._hist.append(t)
        past = np.array(self._past)[None] if self._past else None
        out = self.predict(np.array(self._hist)[None], past)
        q = out["q"][0]
        self._past.append(q)
        return IkStep(q=q, q_net=out["q_net"][0], q_filtered=out["q_filtered"][0], target=t,
                      error=float(out["error"][0]), exact=bool(out["exact"][0]),
                      reachable=bool(out["reachable"][0]), valid=valid)

    def run(self, targets: np.ndarray) -> dict[str, np.ndarray]:
        """A whole trajectory (n, 3), streamed from a reset; arrays of every step's fields."""
        self.reset()
        steps = [self.step(p) for p in np.asarray(targets, dtype=float)]
        return {k: np.array([getattr(s, k) for s in steps]) for k in IkStep.__dataclass_fields__}
