"""Tool-point trajectories of the arm (100 Hz, the arm's base frame): the `Trajectory` type, the builtin
tracking targets (``circle``, ``figure8``), and CSV files ``t,x,y,z``. Not learned: what `arm-track`
follows and what the learned IK (`felis.learning.ik`) is trained and evaluated on. Joint angles of a
builtin come from the demonstrator's posture rule (`felis.controllers.arm_posture.demo_joints`).
Units: metres, seconds, radians.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from felis.controllers.arm_posture import DT, demo_joints
from felis.errors import ParameterError, TrajectoryError
from felis.files import read_text, write_atomic

BUILTINS = ("circle", "figure8")


@dataclass
class Trajectory:
    """A tool-point trajectory at 100 Hz in the arm's base frame.

    t (n,) s; p (n, 3) m; q (n, 4) rad demonstrated joint angles or None; kind (``reach``, ``line``,
    ``circle``, ``pick_place``, ``spline``, ``file``, ``recorded``, a builtin's name); ident: its id in
    a corpus (−1 when not from one).
    """

    t: np.ndarray
    p: np.ndarray
    q: np.ndarray | None
    kind: str
    ident: int

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=float)
        self.p = np.asarray(self.p, dtype=float)
        n = len(self.t)
        if self.t.ndim != 1 or self.p.shape != (n, 3):
            raise TrajectoryError(f"trajectory {self.ident} ({self.kind}): t must be (n,) and p (n, 3), "
                                  f"got {self.t.shape} and {self.p.shape}")
        if self.q is not None:
            self.q = np.asarray(self.q, dtype=float)
            if self.q.shape != (n, 4):
                raise TrajectoryError(f"trajectory {self.ident} ({self.kind}): q must be ({n}, 4), got {self.q.shape}")

    def __len__(self) -> int:
        return len(self.t)


def ease_progress(t: np.ndarray, duration: float, ramp: float) -> np.ndarray:
    """Progress u(t) from 0 to 1 over ``duration`` at a speed that ramps up from rest over ``ramp`` s
    (smootherstep), holds, and ramps down to rest: u' ∝ s(t/ramp) + s((T − t)/ramp) − 1.

    Closed form with F(x) = ∫₀ˣ s = x⁶ − 3x⁵ + 5x⁴/2 (x ≤ 1), F(x) = x − 1/2 (x > 1), ramp τ ≤ T/2::

        u(t) = (τ F(t/τ) + τ F(T/τ) − τ F((T − t)/τ) − t) / (T − τ)

    u, u' and u'' are continuous and u'(0) = u''(0) = u'(T) = u''(T) = 0.
    """
    t = np.asarray(t, dtype=float)
    tau = min(ramp, duration / 2)

    def F(x):
        x = np.clip(x, 0.0, None)
        xi = np.minimum(x, 1.0)
        return np.where(x <= 1.0, xi**4 * (2.5 + xi * (-3.0 + xi)), x - 0.5)

    u = (tau * F(t / tau) + tau * F(duration / tau) - tau * F((duration - t) / tau) - t) / (duration - tau)
    return np.clip(u, 0.0, 1.0)


def frame_times(length: float) -> np.ndarray:
    return np.arange(int(round(length / DT)) + 1) * DT



def read_trajectory_csv(path: str | Path) -> Trajectory:
    """A tool-point trajectory from CSV: a header with columns ``t,x,y,z`` (any order, extra columns
    ignored), then one row per 100 Hz frame (t in s, x y z in m in the arm's base frame).

    TrajectoryError (``<file>:<line>: column <c>: …``) for: a missing file, a missing column, a value
    that is not a number or not finite, fewer than 2 rows, t not strictly increasing, or a step that
    is not 0.01 s ± 10%. Returns kind ``file``, ident −1, q None.
    """
    path = Path(path)
    text = read_text(path, "trajectory file", TrajectoryError, undecodable="{path}: not a text CSV file",
                     unreadable="{path}: cannot read trajectory file: {reason}")
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    if not header or not any(h.strip() for h in header):
        raise TrajectoryError(f"{path}:1: empty; expected a header line with columns t,x,y,z")
    names = [h.strip().lower() for h in header]
    cols = {}
    for c in ("t", "x", "y", "z"):
        if c not in names:
            raise TrajectoryError(f"{path}:1: missing column {c!r} (header: {','.join(names)}; needs t,x,y,z)")
        if names.count(c) > 1:
            raise TrajectoryError(f"{path}:1: column {c!r} appears {names.count(c)} times")
        cols[c] = names.index(c)
    rows, lines = [], []
    for row in reader:
        line = reader.line_num
        if not row or all(not f.strip() for f in row):
            continue
        if len(row) < len(names):
            raise TrajectoryError(f"{path}:{line}: {len(row)} fields, the header has {len(names)}")
        values = []
        for c, j in cols.items():
            try:
                v = float(row[j])
            except ValueError:
                raise TrajectoryError(f"{path}:{line}: column {c}: {row[j].strip()!r} is not a number") from None
            if not math.isfinite(v):
                raise TrajectoryError(f"{path}:{line}: column {c}: {row[j].strip()!r} is not finite")
            values.append(v)
        rows.append(values)
        lines.append(line)
    if len(rows) < 2:
        raise TrajectoryError(f"{path}: {len(rows)} data row(s); a trajectory needs at least 2")
    data = np.array(rows)
    t = data[:, 0]
    dt = np.diff(t)
    for k in range(len(dt)):
        if dt[k] <= 0:
            raise TrajectoryError(f"{path}:{lines[k + 1]}: column t: {t[k + 1]:g} s is not after {t[k]:g} s "
                                  f"(line {lines[k]}); time must increase strictly")
        if abs(dt[k] - DT) > 0.1 * DT:
            raise TrajectoryError(f"{path}:{lines[k + 1]}: column t: step {dt[k]:.6g} s from line {lines[k]}; "
                                  f"trajectories are sampled at 100 Hz (0.01 s ± 10%)")
    return Trajectory(t=t, p=data[:, 1:], q=None, kind="file", ident=-1)


def write_trajectory_csv(path: str | Path, traj: Trajectory) -> Path:
    """Write ``t,x,y,z`` (and ``q1…q4`` when the trajectory has angles), floats in shortest round-trip
    form, atomically."""
    path = Path(path)
    cols = [traj.t[:, None], traj.p] + ([traj.q] if traj.q is not None else [])
    data = np.concatenate(cols, axis=1)
    head = "t,x,y,z" + (",q1,q2,q3,q4" if traj.q is not None else "")
    body = "\n".join(",".join(repr(float(v)) for v in row) for row in data)
    return write_atomic(path, head + "\n" + body + "\n", "trajectory file", TrajectoryError)


# ---------------------------------------------------------------------------------------------
# builtin and recorded trajectories

CIRCLE_CENTRE = {"vertical": np.array([0.22, 0.0, 0.16]), "horizontal": np.array([0.22, 0.0, 0.10])}
CIRCLE_RADIUS, CIRCLE_PERIOD = 0.06, 4.0
FIGURE8_CENTRE = np.array([0.22, 0.0, 0.16])
FIGURE8_SIZE, FIGURE8_PERIOD = (0.12, 0.06), 6.0
RAMP = 1.0  # s: ease in from rest and out to rest


def builtin_trajectory(name: str, duration: float | None = None, *, plane: str = "vertical") -> Trajectory:
    """A builtin tracking target in front of the arm, eased in from rest and out to rest over 1 s.

    ``circle``: radius 6 cm, period 4 s, in the vertical plane facing the arm (x = 0.22 m, centre
    z = 0.16 m) or, with ``plane="horizontal"``, at z = 0.10 m; default 9 s (two laps). ``figure8``:
    a lemniscate of Gerono 12 cm wide (y) × 6 cm high (z) in the vertical plane x = 0.22 m,
    (y, z) = c + (0.06 sin θ, 0.03 sin 2θ), period 6 s, starting at its crossing; default 7 s (one lap).
    With θ = 2π/period · (T − 1 s) · `ease_progress`, a duration of k periods + 1 s closes the curve.
    Every frame is in the demonstration workspace; q is filled by `demo_joints`.
    """
    if name not in BUILTINS:
        raise ParameterError(f"unknown builtin trajectory {name!r}; builtins: {', '.join(BUILTINS)}")
    if name == "circle" and plane not in CIRCLE_CENTRE:
        raise ParameterError(f"circle plane must be 'vertical' or 'horizontal', got {plane!r}")
    period = CIRCLE_PERIOD if name == "circle" else FIGURE8_PERIOD
    if duration is None:
        duration = 2 * period + RAMP if name == "circle" else period + RAMP
    if not (math.isfinite(duration) and duration >= 2 * DT):
        raise ParameterError(f"trajectory duration must be at least {2 * DT} s, got {duration}")
    t = frame_times(duration)
    ramp = min(RAMP, duration / 2)
    theta = 2 * np.pi / period * (duration - ramp) * ease_progress(t, duration, ramp)
    if name == "circle":
        c = CIRCLE_CENTRE[plane]
        e1 = np.array([0.0, 1.0, 0.0])
        e2 = np.array([0.0, 0.0, 1.0]) if plane == "vertical" else np.array([1.0, 0.0, 0.0])
        # starts at the bottom (vertical) or the point nearest the base (horizontal), heading +y
        p = c + CIRCLE_RADIUS * (np.sin(theta)[:, None] * e1 - np.cos(theta)[:, None] * e2)
    else:
        w, h = FIGURE8_SIZE
        p = FIGURE8_CENTRE + np.stack([0 * theta, w / 2 * np.sin(theta), h / 2 * np.sin(2 * theta)], -1)
    return Trajectory(t=t, p=p, q=demo_joints(p), kind=name, ident=-1)
