"""Teleoperation: a leader arm's joints drive a follower's (`TeleopController`), or keys jog it (`JogController`).

Leader → follower mapping (`JointMap`, from ``--map`` text by `parse_map`, resolved against both descriptions by
`resolve_map`): per mapped follower joint f fed by leader joint l::

    q_f = scale · q_l + offset          (scale 1, offset 0 unless given)

where q_l is the leader's calibrated joint position (its description's direction, zero and transmission, and a
calibration file if given: the same units as the follower's joint, rad or m). Follower joints nothing maps hold
the position they had when the run began. Default mapping: every joint name the two descriptions share; with no
name in common, the first joints in order.

Engaging: the leader and the follower rarely start in the same pose, so for the first ``ramp`` seconds the target
blends from the follower's start pose to the leader's with a minimum-jerk weight w(s) = 10s³ − 15s⁴ + 6s⁵,
``q = q0 + w(t/ramp)·(q_mapped(t) − q0)``; after it the follower follows the leader directly (the safety layer
still clamps every target to the soft limits and to the maximum step per tick).

The leader is read through a callable (``source() -> q_leader``) that the command wires to the hardware, so the
controller imports no driver and runs unchanged on either follower backend. A read that fails raises from the
source; the loop then holds the last command (`felis.loop`).

Keyboard jogging (`JogController`): digits select a follower joint, ``x``/``y``/``z`` a tool-point axis, ``+``/``-``
(or the arrow keys) move the selection by one step; ``o``/``c`` open and close the gripper; ``q`` or Esc ends
the run. Tool-space steps go through the learned IK pipeline (`felis.learning.ik.solver`, seed 001), streamed
one frame per 10 ms of run time as `felis.controllers.arm_track` does.

`tracking_lag` measures how well a follower tracked: the lag τ* that best aligns its positions with the
leader's targets and the RMS error left after removing it.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from felis import armkin
from felis.controllers.pose import min_jerk
from felis.errors import ParameterError
from felis.hal import Command, State
from felis.spec import RobotSpec

RAMP_S = 1.0  # s: minimum-jerk blend from the follower's pose to the leader's when teleoperation starts
FRAME = 0.01  # s: the IK pipeline's frame period (100 Hz)
MAX_LAG_S = 0.5  # the longest lag `tracking_lag` looks for
MIN_SAMPLES = 50  # ticks after the ramp below which a run's lag is not reported (too few to mean anything)


# ---------------------------------------------------------------------------------------------- mapping
@dataclass(frozen=True)
class JointLink:
    """One mapped joint: ``follower = scale · leader + offset``."""

    leader: str
    follower: str
    scale: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class JointMap:
    """A mapping resolved against two descriptions: index arrays into the leader's and the follower's joints."""

    links: tuple[JointLink, ...]
    leader_idx: np.ndarray
    follower_idx: np.ndarray
    scale: np.ndarray
    offset: np.ndarray

    def apply(self, q_leader: np.ndarray, q_hold: np.ndarray) -> np.ndarray:
        """The follower's targets: ``q_hold`` with the mapped joints replaced by ``scale·q_l + offset``."""
        q = np.array(q_hold, dtype=float, copy=True)
        q[self.follower_idx] = self.scale * np.asarray(q_leader, dtype=float)[self.leader_idx] + self.offset
        return q

    def describe(self) -> str:
        return ", ".join(_link_text(k) for k in self.links)


def _link_text(k: JointLink) -> str:
    text = f"{k.leader}→{k.follower}"
    if k.scale != 1.0:
        text += f"×{k.scale:g}"
    if k.offset != 0.0:
        text += f"{k.offset:+g}"
    return text


_UNSIGNED = r"(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_LINK = re.compile(rf"^\s*(\w+)\s*=\s*(\w+)\s*(?:\*\s*([-+]?{_UNSIGNED}))?\s*(?:([-+])\s*({_UNSIGNED}))?\s*$")


def parse_map(text: str) -> tuple[JointLink, ...]:
    """``"leader_joint=follower_joint[*scale][+offset], …"`` → links (``--map``).

    ``j1=joint1`` maps one to one; ``j4=joint4*-1+0.2`` mirrors and shifts (follower = −1·leader + 0.2).
    """
    links = []
    for part in text.split(","):
        if not part.strip():
            raise ParameterError(f"--map {text!r}: an empty entry; use leader_joint=follower_joint[*scale+offset],…")
        m = _LINK.match(part)
        if m is None:
            raise ParameterError(f"--map: cannot read {part.strip()!r}; use leader_joint=follower_joint[*scale+offset] "
                                 "(e.g. j4=joint4*-1+0.2)")
        leader, follower, scale, sign, offset = m.groups()
        s = 1.0 if scale is None else float(scale)
        o = 0.0 if offset is None else float(sign + offset)
        if not (math.isfinite(s) and math.isfinite(o)) or s == 0.0:
            raise ParameterError(f"--map {part.strip()!r}: the scale must be finite and non-zero, the offset finite")
        links.append(JointLink(leader, follower, s, o))
    return tuple(links)


def resolve_map(links: tuple[JointLink, ...] | None, leader: RobotSpec, follower: RobotSpec) -> JointMap:
    """Check ``links`` against both descriptions (None: the default mapping, module doc) and index them.

    Raises ParameterError naming a joint the leader or the follower lacks, or a follower joint mapped twice.
    """
    if links is None:
        shared = [n for n in leader.names if n in follower.names]
        if shared:
            links = tuple(JointLink(n, n) for n in shared)
        else:
            links = tuple(JointLink(a, b) for a, b in zip(leader.names, follower.names, strict=False))
    if not links:
        raise ParameterError(f"no joint of the leader {leader.name!r} maps onto the follower {follower.name!r}: give "
                             "--map leader_joint=follower_joint,…")
    for k in links:
        if k.leader not in leader.names:
            raise ParameterError(f"the leader {leader.name!r} has no joint {k.leader!r} (its joints: "
                                 f"{', '.join(leader.names)}); fix --map or --leader-robot")
        if k.follower not in follower.names:
            raise ParameterError(f"the follower {follower.name!r} has no joint {k.follower!r} (its joints: "
                                 f"{', '.join(follower.names)}); fix --map or --robot")
    targets = [k.follower for k in links]
    twice = sorted({t for t in targets if targets.count(t) > 1})
    if twice:
        raise ParameterError(f"--map drives the follower's {twice[0]!r} from more than one leader joint")
    return JointMap(links=tuple(links), leader_idx=np.array([leader.index(k.leader) for k in links], dtype=int),
                    follower_idx=np.array([follower.index(k.follower) for k in links], dtype=int),
                    scale=np.array([k.scale for k in links]), offset=np.array([k.offset for k in links]))


# ---------------------------------------------------------------------------------------------- tracking
@dataclass(frozen=True)
class Lag:
    """`tracking_lag`'s result: the lag (s), the RMS error after removing it and with none (per joint and
    over the joints used for the fit), in the joints' units (rad, m)."""

    lag_s: float
    rms: float
    rms_raw: float
    rms_joint: np.ndarray
    samples: int


def tracking_lag(t: np.ndarray, target: np.ndarray, follower: np.ndarray, *, max_lag: float = MAX_LAG_S,
                 resolution: float = 0.001, fit: np.ndarray | None = None) -> Lag:
    """The lag that best aligns a follower with its target, and the error left.

    ``t`` (N,) s, ``target`` and ``follower`` (N, k) positions at those times. For τ on a grid (``resolution``)
    over 0 … ``max_lag``::

        e_τ(t) = follower(t) − target(t − τ)          (target linearly interpolated)
        τ* = argmin_τ RMS(e_τ)                          over the samples with t − τ ≥ t_0

    RMS over the columns ``fit`` (a bool mask; default all). Raises ParameterError with fewer than 10 samples.
    """
    t = np.asarray(t, dtype=float)
    ref = np.asarray(target, dtype=float).reshape(len(t), -1)
    fol = np.asarray(follower, dtype=float).reshape(len(t), -1)
    if len(t) < 10:
        raise ParameterError(f"tracking_lag needs at least 10 samples, got {len(t)}")
    cols = np.ones(ref.shape[1], dtype=bool) if fit is None else np.asarray(fit, dtype=bool)
    span = float(t[-1] - t[0])
    lags = np.arange(0.0, min(max_lag, 0.5 * span) + resolution / 2, resolution)
    best = (math.inf, 0.0, None)
    for tau in lags:
        keep = t - tau >= t[0]
        shifted = np.column_stack([np.interp(t[keep] - tau, t, ref[:, c]) for c in range(ref.shape[1])])
        err = fol[keep] - shifted
        rms = float(np.sqrt(np.mean(err[:, cols] ** 2)))
        if rms < best[0]:
            best = (rms, float(tau), np.sqrt(np.mean(err ** 2, axis=0)))
    raw = float(np.sqrt(np.mean((fol - ref)[:, cols] ** 2)))
    return Lag(lag_s=best[1], rms=best[0], rms_raw=raw, rms_joint=best[2], samples=len(t))


# ---------------------------------------------------------------------------------------------- controllers
class _Record:
    """Targets and positions per tick, for the run's lag and error (grows by doubling)."""

    def __init__(self, k: int):
        self.n = 0
        self.t = np.empty(1024)
        self.target = np.empty((1024, k))
        self.q = np.empty((1024, k))

    def add(self, t: float, target: np.ndarray, q: np.ndarray) -> None:
        if self.n == len(self.t):
            self.t = np.resize(self.t, 2 * self.n)
            self.target = np.resize(self.target, (2 * self.n, self.target.shape[1]))
            self.q = np.resize(self.q, (2 * self.n, self.q.shape[1]))
        self.t[self.n], self.target[self.n], self.q[self.n] = t, target, q
        self.n += 1


class TeleopController:
    """The follower tracks the leader through ``mapping`` (module doc). ``source()`` returns the leader's joint
    positions (its description's order) or raises; ``ramp`` seconds of minimum-jerk engagement first."""

    name = "teleop"

    def __init__(self, mapping: JointMap, source: Callable[[], np.ndarray], ramp: float = RAMP_S):
        if not (math.isfinite(ramp) and 0 <= ramp <= 10):
            raise ParameterError(f"--ramp must be within 0…10 s, got {ramp}")
        self.mapping = mapping
        self.source = source
        self.ramp = float(ramp)
        self.leader_q: np.ndarray | None = None  # the last leader reading (for the log)

    def reset(self, spec: RobotSpec, state: State) -> None:
        self.spec = spec
        if self.mapping.follower_idx.max(initial=-1) >= spec.n:
            raise ParameterError(f"the joint mapping was resolved for another follower than {spec.name!r}")
        self.t0 = state.t
        self.q0 = np.asarray(state.q, dtype=float).copy()
        self.kinds = np.array([spec.joints[i].kind == "revolute" for i in self.mapping.follower_idx])
        self.record = _Record(len(self.mapping.follower_idx))
        self._target: np.ndarray | None = None

    def __call__(self, state: State) -> Command:
        if self._target is not None and state.t - self.t0 >= self.ramp:  # what the last command aimed at
            idx = self.mapping.follower_idx
            self.record.add(state.t, self._target[idx], np.asarray(state.q, dtype=float)[idx])
        q_leader = np.asarray(self.source(), dtype=float)
        self.leader_q = q_leader
        target = self.mapping.apply(q_leader, self.q0)
        s = (state.t - self.t0) / self.ramp if self.ramp > 0 else 1.0
        q = target if s >= 1.0 else self.q0 + min_jerk(s) * (target - self.q0)
        self._target = target
        return Command(q=q)

    def summary(self) -> dict:
        """The follower's lag behind the leader and its RMS error after removing it (after the ramp): the reading
        at tick k against the leader's target sent at tick k − 1 and before (`tracking_lag`)."""
        r = self.record
        out: dict = {"source": "leader", "mapping": self.mapping.describe(), "samples": r.n}
        if r.n < MIN_SAMPLES:
            return out
        # each row pairs the reading at tick k with the target sent at tick k − 1 (read at t_{k−1} = t_k − dt)
        t, target, q = r.t[:r.n], r.target[:r.n], r.q[:r.n]
        fit = self.kinds if self.kinds.any() else None
        lag = tracking_lag(t, target, q, fit=fit)
        dt = float(np.median(np.diff(r.t[:r.n])))
        out.update({"lag_ms": round((lag.lag_s + dt) * 1e3, 1), "rms_after_lag": lag.rms, "rms_raw": lag.rms_raw,
                    "rms_deg_after_lag": math.degrees(lag.rms) if fit is not None else None,
                    "rms_joint": {k.follower: float(v)
                                  for k, v in zip(self.mapping.links, lag.rms_joint, strict=True)}})
        return out


# keys (after `felis.cli.keys` turned escape sequences into names)
UP, DOWN = ("+", "=", "up", "right"), ("-", "_", "down", "left")
QUIT = ("q", "esc")
JOINT_STEP = 0.05  # rad per key press (≈ 2.9°)
TOOL_STEP = 0.005  # m per key press
GRIPPER_STEP = 0.002  # m (or rad) per key press


class JogController:
    """Keyboard jogging (module doc). ``keys()`` returns the keys pressed since the last call (names: ``"1"``,
    ``"x"``, ``"+"``, ``"up"``, ``"esc"`` …); ``solver`` is the learned IK pipeline for tool-space steps (None:
    tool space refused). ``done`` turns True on ``q``/Esc."""

    name = "jog"

    def __init__(self, keys: Callable[[], list[str]], solver=None, *, joint_step: float = JOINT_STEP,
                 tool_step: float = TOOL_STEP, gripper_step: float = GRIPPER_STEP):
        for what, v, hi in (("joint step", joint_step, 0.5), ("tool step", tool_step, 0.05),
                            ("gripper step", gripper_step, 0.05)):
            if not (math.isfinite(v) and 0 < v <= hi):
                raise ParameterError(f"{what} must be within 0…{hi}, got {v}")
        self.keys, self.solver = keys, solver
        self.joint_step, self.tool_step, self.gripper_step = joint_step, tool_step, gripper_step
        self.done = False

    def reset(self, spec: RobotSpec, state: State) -> None:
        self.spec = spec
        self.q = np.asarray(state.q, dtype=float).copy()
        self.selected: int | str = 0  # a joint index, or a tool axis "x"/"y"/"z"
        self.arm = np.array([spec.index(j) for j in armkin.JOINTS]) if set(armkin.JOINTS) <= set(spec.names) else None
        self.gripper = spec.index("gripper") if "gripper" in spec.names else None
        self.tool: np.ndarray | None = None  # the tool-point target while jogging in tool space
        self.tool_start: np.ndarray | None = None  # where tool space was last entered
        self.t0 = state.t
        self.frames = 0
        self.presses = 0
        self.ignored = 0
        self.unreachable = 0
        self.done = False

    @property
    def mode(self) -> str:
        return "tool" if isinstance(self.selected, str) else "joint"

    def press(self, key: str) -> None:
        """Apply one key (module doc); keys with no meaning here are counted in ``ignored``."""
        self.presses += 1
        if key in QUIT:
            self.done = True
        elif key.isdigit() and 1 <= int(key) <= self.spec.n:
            self.selected, self.tool = int(key) - 1, None
        elif key in ("x", "y", "z") and self.arm is not None and self.solver is not None:
            if self.tool is None:  # enter tool space at the commanded pose's tool point
                self.tool = armkin.fk(self.q[self.arm])
                self.tool_start = self.tool.copy()
                self.solver.reset()
            self.selected = key
        elif key in UP or key in DOWN:
            sign = 1.0 if key in UP else -1.0
            if isinstance(self.selected, str):
                self.tool = self.tool + sign * self.tool_step * (np.arange(3) == "xyz".index(self.selected))
            else:
                j = self.spec.joints[self.selected]
                step = self.joint_step if j.kind == "revolute" else self.gripper_step
                self.q[self.selected] = min(max(self.q[self.selected] + sign * step, j.lower), j.upper)
        elif key in ("o", "c") and self.gripper is not None:
            j = self.spec.joints[self.gripper]
            sign = 1.0 if key == "o" else -1.0
            self.q[self.gripper] = min(max(self.q[self.gripper] + sign * self.gripper_step, j.lower), j.upper)
        else:
            self.ignored += 1

    def __call__(self, state: State) -> Command:
        for key in self.keys():
            self.press(key)
        if self.tool is not None:  # stream the IK one frame per 10 ms of run time
            due = int(np.floor((state.t - self.t0) / FRAME + 1e-9)) + 1
            if self.frames == 0 or due - self.frames > 10:  # entering tool space, or after a stall: no burst
                self.frames = due - 1
            while self.frames < due:
                step = self.solver.step(self.tool)
                self.frames += 1
                self.unreachable += not step.reachable
                self.q[self.arm] = step.q
        return Command(q=self.q.copy())

    def summary(self) -> dict:
        out = {"source": "keyboard", "presses": self.presses, "ignored": self.ignored, "mode": self.mode,
               "unreachable_frames": self.unreachable}
        if self.tool is not None:
            out["tool_target_m"] = [float(v) for v in self.tool]
            out["tool_start_m"] = [float(v) for v in self.tool_start]
        return out
