"""Arm tool-point tracking with the learned IK pipeline (`felis.learning.ik.solver`, seed 001).

The controller first moves the arm from where it is to the IK solution of the trajectory's first
point (minimum-jerk, ``lead_in`` seconds), holds it ``hold`` seconds (the servos' I terms take up gravity's
load meanwhile: with the arm's I = 100 that takes a few seconds), then streams the trajectory: for every 10 ms of
trajectory time it feeds the next target to the pipeline (MP → PE → mean filter → exact refinement) and
commands the refined joint angles. Targets are taken ``lead`` seconds ahead of the clock: a servo in
position mode follows a moving goal late by its velocity lag (`felis.servos.velocity_lag_s`, 45 ms for the
arm's XM430-W350 at P = 800), and a reading shows a command one tick later; by default the lead is the
slowest arm joint's lag plus one 10 ms frame, so the tool point, not the command, is on the target.
The pipeline's frame offsets are in 100 Hz frames, so at other loop rates the controller steps it once
per 10 ms of elapsed time (several steps per tick, or none).
The gripper holds its position. After the last point the arm holds the last pose.

It keeps what an operator wants to know after a run (`summary`): the commanded pose's position error
(the IK's own, ≈ 0 for reachable targets), the measured tool point's error against the target at the
same time (servo lag included), and unreachable or invalid targets.
"""

from __future__ import annotations

import numpy as np

from felis import armkin
from felis.controllers.pose import min_jerk
from felis.controllers.trajectories import BUILTINS, builtin_trajectory, read_trajectory_csv
from felis.errors import ParameterError
from felis.hal import Command, State
from felis.learning.ik.solver import IkSolver
from felis.servos import servo_model, velocity_lag_s
from felis.spec import RobotSpec

ARM_JOINTS = armkin.JOINTS
FRAME = 0.01  # s: the pipeline's frame period (100 Hz)
LEAD_IN = 1.5  # s: minimum-jerk move to the first point's solution
SETTLE = 0.5  # s: holding the last pose at the end of a run


def error_stats(err_m: np.ndarray) -> dict:
    """mean, median, p95, p99, max of position errors, in millimetres."""
    e = np.asarray(err_m, dtype=float) * 1e3
    if e.size == 0:
        return {k: None for k in ("mean_mm", "median_mm", "p95_mm", "p99_mm", "max_mm")}
    return {"mean_mm": float(e.mean()), "median_mm": float(np.median(e)), "p95_mm": float(np.percentile(e, 95)),
            "p99_mm": float(np.percentile(e, 99)), "max_mm": float(e.max())}


def run_time(trajectory, lead_in: float = LEAD_IN, hold: float = 0.0) -> float:
    """Seconds a run needs to follow ``trajectory``: the lead-in, the hold, the trajectory, and `SETTLE`."""
    return lead_in + hold + float(trajectory.t[-1] - trajectory.t[0]) + SETTLE


def trajectory_from(source):
    """A trajectory from a builtin name (``circle``, ``figure8``), a CSV file path (``t,x,y,z``), or an
    object with ``t`` and ``p`` (returned as is)."""
    if hasattr(source, "t") and hasattr(source, "p"):
        return source
    text = str(source)
    if text in BUILTINS:
        return builtin_trajectory(text)
    if not text.lower().endswith(".csv"):
        raise ParameterError(f"trajectory {text!r}: use {' or '.join(BUILTINS)}, or a CSV file (t,x,y,z) "
                             "ending in .csv")
    return read_trajectory_csv(text)


class ArmTrackController:
    """Follows ``trajectory`` (``t`` (n,) s and ``p`` (n, 3) m in the arm's base frame) with ``solver``."""

    name = "arm-track"

    def __init__(self, trajectory, solver=None, lead_in: float = LEAD_IN, lead: float | None = None,
                 hold: float = 0.0):
        t = np.asarray(trajectory.t, dtype=float)
        p = np.asarray(trajectory.p, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or len(t) != len(p) or len(p) < 2:
            raise ParameterError("arm-track needs a trajectory of at least 2 points (t, x, y, z)")
        if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
            raise ParameterError("arm-track: trajectory times must be finite and increasing")
        if not (np.isfinite(lead_in) and lead_in >= 0):
            raise ParameterError(f"arm-track: lead-in must be ≥ 0 s, got {lead_in}")
        if solver is None:
            solver = IkSolver.load()
        self.t = t - t[0]
        self.p = p
        self.solver = solver
        if not (np.isfinite(hold) and hold >= 0):
            raise ParameterError(f"arm-track: hold must be ≥ 0 s, got {hold}")
        if lead is not None and not (np.isfinite(lead) and 0 <= lead <= 0.5):
            raise ParameterError(f"arm-track: lead must be within 0…0.5 s, got {lead}")
        self.lead_in = float(lead_in)
        self.hold = float(hold)
        self.lead = lead  # None: from the servos (`reset`)
        self.duration = self.lead_in + self.hold + float(self.t[-1])

    @property
    def markers(self) -> np.ndarray:
        """Points along the target path (every 50 ms) for renderers to draw."""
        return self.p[::5]

    def target_at(self, tau: float) -> np.ndarray:
        """The trajectory's point at time ``tau`` (s from its start), linearly interpolated, held at the ends."""
        return np.array([np.interp(tau, self.t, self.p[:, k]) for k in range(3)])

    def reset(self, spec: RobotSpec, state: State) -> None:
        missing = [j for j in ARM_JOINTS if j not in spec.names]
        if missing:
            raise ParameterError(f"arm-track drives the arm's joints {', '.join(ARM_JOINTS)}; robot {spec.name!r} "
                                 f"lacks {', '.join(missing)}")
        self.spec = spec
        self.idx = np.array([spec.index(j) for j in ARM_JOINTS])
        if self.lead is None:  # the slowest joint's velocity lag, plus the tick between a command and its reading
            joints = [spec.joints[i] for i in self.idx]
            self.lead = max(velocity_lag_s(servo_model(j.servo), j.pid[0]) for j in joints) + FRAME
        self.t0 = state.t
        self.q_start = np.asarray(state.q, dtype=float).copy()
        self.solver.reset()
        first = self.solver.step(self.p[0])
        self.solver.reset()
        self.q_first = self.q_start.copy()
        self.q_first[self.idx] = first.q
        self.q_cmd = self.q_start.copy()
        self.frames = 0
        self.cmd_err: list[float] = []
        self.track_err: list[float] = []
        self.unreachable = 0
        self.invalid = 0

    def __call__(self, state: State) -> Command:
        t = state.t - self.t0
        if t < self.lead_in:
            w = min_jerk(t / self.lead_in) if self.lead_in > 0 else 1.0
            return Command(q=self.q_start + w * (self.q_first - self.q_start))
        if t < self.lead_in + self.hold:  # at the first point while the servos' integrators take up the load
            return Command(q=self.q_first)
        tau = t - self.lead_in - self.hold
        q_meas = np.asarray(state.q, dtype=float)[self.idx]
        if self.frames > 0 and tau <= self.t[-1] + FRAME and np.all(np.isfinite(q_meas)):
            self.track_err.append(float(np.linalg.norm(armkin.fk(q_meas) - self.target_at(tau))))
        due = min(int(np.floor(tau / FRAME + 1e-9)) + 1, int(np.floor(self.t[-1] / FRAME + 1e-9)) + 1)
        while self.frames < due:
            step = self.solver.step(self.target_at(self.frames * FRAME + self.lead))
            self.frames += 1
            self.cmd_err.append(step.error)
            self.unreachable += not step.reachable
            self.invalid += not step.valid
            self.q_cmd = self.q_cmd.copy()
            self.q_cmd[self.idx] = step.q
        q = self.q_first.copy() if self.frames == 0 else self.q_cmd
        return Command(q=q)

    def summary(self) -> dict:
        """Frames streamed, IK error of the commands and measured tracking error (mm), flagged targets."""
        return {"frames": self.frames, "unreachable": self.unreachable, "invalid": self.invalid,
                "command_error": error_stats(np.array(self.cmd_err)),
                "tracking_error": error_stats(np.array(self.track_err))}
