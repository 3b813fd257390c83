"""System identification of the simulated servo model (`felis.sim.servo`) from step and chirp responses.

What is identified
------------------
Each servo-driven joint is simulated (`felis.sim.servo`) as a position actuator with gain ``kp`` whose
force saturates at ``±torque_limit``, plus joint ``damping`` (back-EMF), ``armature`` (reflected rotor
inertia) and ``frictionloss`` (dry gear friction), on the MuJoCo model's link inertia and gravity::

    (I_link(q) + armature)·q̈ = clip(kp·(u − q), ±torque_limit) − damping·q̇ − friction(q̇) + τ_gravity(q) + …

The servo reports position, velocity and the motor torque ``effort = clip(kp·(u − q)) − damping·q̇``
(from Present Current). `fit` finds, per joint, p = (kp, damping, armature, frictionloss,
torque_limit) minimising

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

Excitation (`plan`): from the hold pose (q = 0 clipped into the limits), per joint under test, with
every other joint holding:

* small steps ±A_s, A_s = ``small`` · τ_max/kp (inside the linear range): kp, damping;
* saturating steps ±A_l, A_l = ``large`` · τ_max/kp (clipped to the limits less ``margin``): the
  actuator saturates, the speed approaches τ_max/damping: torque_limit;
* a linear chirp of amplitude A_s/2 from ``chirp_hz[0]`` to ``chirp_hz[1]``: inertia, armature;
* a settling hold before and after, so each segment starts at rest (the replay starts from the
  measured state there). One joint at a time keeps coupling through the links small.

Timing (`record`, `simulate`)
-----------------------------
`record` drives any HAL `Robot` (a `DynamixelRobot` over a real or virtual bus, or a `MujocoRobot`)
at ``rate_hz``: per tick it writes the target and reads the state, timestamping each call
(``time.perf_counter`` before and after, seconds since the start) for a realtime robot; for a
simulation the times are the simulated ones (k/rate). A servo applies a goal when the packet
arrives and reports the latest state it has, so the replay (`simulate`) applies command k from
``t_write_end,k + latency_s`` and samples state k at ``t_read_start,k``, with a zero-order hold on the
commands in between, at the model timestep (1 ms) with sub-step timing: a command arriving inside a
step weights that step's control by the time it is in force, a read between two steps interpolates
them (so the error is smooth in the parameters and timing is not rounded). ``latency_s`` (default
``LATENCY_S`` for realtime recordings, 0 for simulation) covers the bus transfer and the servo's (or
the virtual bus's 1 kHz physics thread's) next update.

Recordings are saved as ``.npz`` (plain arrays, never pickle); parameter files by
`felis.sim.servo_file`. ``felis sysid`` (``felis/cli/sysid.py``) wires it all for an operator.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from felis.errors import FelisError, SysidError
from felis.files import MAX_ARRAY_BYTES, check_readable
from felis.hal import Command, Lifecycle, Robot
from felis.loop import servo_stop
from felis.servos import servo_model
from felis.sim.servo import ServoParams, servo_params
from felis.spec import RobotSpec

RECORDING_SCHEMA = 1
LATENCY_S = 0.0005  # command → effect delay for a realtime recording beyond the write's own duration
PARAMS = ("kp", "damping", "armature", "frictionloss", "torque_limit")  # the fitted vector, in this order
# search range of each parameter, as factors (low, high) of its datasheet value
BOUNDS = {"kp": (0.2, 5.0), "damping": (0.1, 10.0), "armature": (0.05, 20.0), "frictionloss": (0.01, 20.0),
          "torque_limit": (0.3, 3.0)}
KINDS = {"ramp": 0, "hold": 1, "step": 2, "saturate": 3, "chirp": 4}
STEP_KINDS = (KINDS["step"], KINDS["saturate"])


def default_params(spec: RobotSpec) -> dict[str, ServoParams]:
    """The datasheet servo model of every joint (what `MujocoRobot` uses without overrides)."""
    return {j.name: servo_params(servo_model(j.servo), m_per_rad=j.m_per_rad) for j in spec.joints}


def check_joints(spec: RobotSpec, joints: Sequence[str] | None) -> list[str]:
    """Joint names (all when None) checked against ``spec``; duplicates dropped, order kept."""
    if joints is None:
        return list(spec.names)
    out: list[str] = []
    for name in joints:
        if name not in spec.names:
            raise SysidError(f"{spec.name} has no joint {name!r}; joints: {', '.join(spec.names)}")
        if name not in out:
            out.append(name)
    if not out:
        raise SysidError("no joints to identify")
    return out


# ----------------------------------------------------------------------------------------- excitation
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


# ----------------------------------------------------------------------------------------- recording
@dataclass
class Recording:
    """What `record` measured. Times are seconds since the start; arrays are ticks × joints in spec order.

    ``t_write``/``t_read``: (ticks, 2) host times before and after each write/read; ``q_cmd``: what
    ``write`` returned (after the backend's clamping and quantisation); ``q``/``dq``/``effort``:
    the state read; ``valid``: the read succeeded for every joint; ``active``/``kind``: the plan.
    """

    robot: str
    joints: tuple[str, ...]
    rate_hz: float
    realtime: bool
    fixed_base: bool
    t_write: np.ndarray
    t_read: np.ndarray
    q_cmd: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    effort: np.ndarray
    valid: np.ndarray
    active: np.ndarray
    kind: np.ndarray
    backend: str = ""

    @property
    def latency_s(self) -> float:
        """Default command delay for the replay: `LATENCY_S` on a realtime robot, 0 in simulation."""
        return LATENCY_S if self.realtime else 0.0

    def segment(self, joint: str) -> slice:
        """Ticks during which ``joint`` was under test."""
        i = self.joints.index(joint)
        k = np.flatnonzero(self.active == i)
        if k.size == 0:
            raise SysidError(f"the recording has no excitation of {joint!r}; it covers "
                             f"{', '.join(self.tested) or 'no joint'}")
        return slice(int(k[0]), int(k[-1]) + 1)

    @property
    def tested(self) -> list[str]:
        return [self.joints[i] for i in dict.fromkeys(int(a) for a in self.active if a >= 0)]

    def save(self, path: str | os.PathLike) -> Path:
        """Write as ``.npz`` (no pickled objects); atomic."""
        path = Path(path)
        if path.suffix != ".npz":
            raise SysidError(f"{path}: a recording file must end in .npz")
        from felis.files import prepare_parent

        prepare_parent(path, "recording", SysidError)
        arrays = {k: np.asarray(v) for k, v in asdict(self).items()}
        arrays["joints"] = np.array(self.joints, dtype=str)
        arrays["schema"] = np.array(RECORDING_SCHEMA)
        tmp = path.with_name(f".{path.name}.tmp.npz")
        try:
            np.savez_compressed(tmp, **arrays)
            os.replace(tmp, path)
        except OSError as e:
            raise SysidError(f"cannot write recording {path}: {e.strerror or e}") from None
        return path

    @staticmethod
    def load(path: str | os.PathLike, spec: RobotSpec | None = None) -> Recording:
        """Read a recording written by `save`; checks it against ``spec`` when given."""
        path = Path(path)
        check_readable(path, "recording", SysidError, MAX_ARRAY_BYTES)
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except FileNotFoundError:
            raise SysidError(f"{path}: no such recording") from None
        except (OSError, ValueError) as e:
            raise SysidError(f"{path}: not a recording (.npz): {e}") from None
        if int(data.get("schema", -1)) != RECORDING_SCHEMA:
            raise SysidError(f"{path}: recording schema {data.get('schema')} is not supported")
        try:
            kw = {f: data[f] for f in ("t_write", "t_read", "q_cmd", "q", "dq", "effort", "valid", "active", "kind")}
            rec = Recording(robot=str(data["robot"]), joints=tuple(str(s) for s in data["joints"]),
                            rate_hz=float(data["rate_hz"]), realtime=bool(data["realtime"]),
                            fixed_base=bool(data["fixed_base"]), backend=str(data.get("backend", "")), **kw)
        except KeyError as e:
            raise SysidError(f"{path}: recording lacks {e.args[0]!r}") from None
        n, m = rec.q.shape if rec.q.ndim == 2 else (0, 0)
        shapes_ok = (m == len(rec.joints) and all(a.shape == (n, m) for a in (rec.q_cmd, rec.dq, rec.effort))
                     and all(a.shape == (n, 2) for a in (rec.t_write, rec.t_read))
                     and all(a.shape == (n,) for a in (rec.valid, rec.active, rec.kind)))
        if not shapes_ok or n == 0:
            raise SysidError(f"{path}: recording arrays have inconsistent shapes")
        if spec is not None:
            if rec.robot != spec.name or rec.joints != spec.names:
                raise SysidError(f"{path}: recording is of {rec.robot!r} with joints {', '.join(rec.joints)}, "
                                 f"not of {spec.name!r}")
        return rec


def record(robot: Robot, joints: Sequence[str] | None = None, *, rate_hz: float = 200.0,
           exc: Excitation = Excitation(), fixed_base: bool = True, backend: str = "",
           progress: Callable[[float], None] | None = None, max_invalid: float = 0.05) -> Recording:
    """Run the excitation for ``joints`` on ``robot`` (connected or armed) and record it.

    Only the HAL `Robot` protocol is used. A realtime robot is paced by the wall clock
    (``time.perf_counter``); otherwise ``advance`` steps the simulation. The robot is armed if it
    is only connected, and left armed at the hold pose. ``fixed_base`` records that a floating-base
    robot hung on a stand (the replay then holds its base). ``progress(fraction)`` is called now and
    then. A read that fails (`felis.errors.CommError`) or leaves a joint stale marks its tick invalid;
    more than ``max_invalid`` of them is a `SysidError`.
    """
    spec = robot.spec
    joints = check_joints(spec, joints)
    if not 1.0 <= rate_hz <= 1000.0:
        raise SysidError(f"rate must be within 1…1000 Hz, got {rate_hz:g}")
    realtime = bool(getattr(robot, "realtime", False))
    if robot.lifecycle is Lifecycle.DISCONNECTED:
        robot.connect()
    if robot.lifecycle is Lifecycle.CONNECTED:
        robot.arm()
    elif robot.lifecycle is not Lifecycle.ARMED:
        raise SysidError(f"{spec.name}: cannot record while {robot.lifecycle.value}")
    first = robot.read()
    p = plan(spec, joints, rate_hz, start=first.q, exc=exc)
    n, m = len(p.q), spec.n
    t_write, t_read = np.zeros((n, 2)), np.zeros((n, 2))
    q_cmd, q, dq, effort = (np.zeros((n, m)) for _ in range(4))
    valid = np.ones(n, dtype=bool)
    dt = 1.0 / rate_hz
    clock = time.perf_counter
    t0 = clock()
    last = first
    for k in range(n):
        if realtime:
            wait = t0 + k * dt - clock()
            if wait > 0:
                time.sleep(wait)
            a = clock() - t0
            sent = robot.write(Command(q=p.q[k]))
            b = clock() - t0
            try:
                s = robot.read()
                stale = s.faults is not None and s.faults.stale is not None and bool(s.faults.stale.any())
                valid[k] = not stale
                last = s
            except FelisError:
                s, valid[k] = last, False
            stop = servo_stop(spec, s.faults, True)
            if stop is not None:  # a servo that cannot follow: the recording is worthless, and so is going on
                raise SysidError(f"recording stopped: {stop[1]}")
            t_write[k] = (a, b)
            t_read[k] = (b, clock() - t0)  # the read starts when the write returns
        else:
            sent = robot.write(Command(q=p.q[k]))
            s = robot.read()
            t_write[k] = t_read[k] = k * dt
        q_cmd[k], q[k], dq[k] = sent.q, s.q, s.dq
        effort[k] = s.effort if s.effort is not None else np.nan
        robot.advance(dt)
        if progress is not None and k % 50 == 0:
            progress(k / n)
    if progress is not None:
        progress(1.0)
    bad = 1.0 - valid.mean()
    if bad > max_invalid:
        raise SysidError(f"{bad:.0%} of the reads failed or were stale (more than {max_invalid:.0%}); check the "
                         "bus (`felis monitor`) and record again")
    return Recording(robot=spec.name, joints=spec.names, rate_hz=float(rate_hz), realtime=realtime,
                     fixed_base=fixed_base, t_write=t_write, t_read=t_read, q_cmd=q_cmd, q=q, dq=dq, effort=effort,
                     valid=valid, active=p.active, kind=p.kind, backend=backend)


# ----------------------------------------------------------------------------------------- replay
class Replay:
    """The recorded commands replayed in MuJoCo for a segment of ticks, with settable servo parameters.

    One compiled model is reused across evaluations (`fit` calls `run` hundreds of times).
    """

    def __init__(self, spec: RobotSpec, recording: Recording, params: Mapping[str, ServoParams] | None = None,
                 fixed_base: bool | None = None, latency_s: float | None = None):
        import mujoco

        from felis.sim.robot import MujocoRobot

        if recording.robot != spec.name or tuple(recording.joints) != spec.names:
            raise SysidError(f"the recording is of {recording.robot!r}, not of {spec.name!r}")
        self._mj = mujoco
        self.spec, self.rec = spec, recording
        self.latency_s = recording.latency_s if latency_s is None else float(latency_s)
        fixed = recording.fixed_base if fixed_base is None else fixed_base
        sim = MujocoRobot(spec, quantize=False, fixed_base=fixed)
        sim.connect()
        sim.arm()  # torque on: gains in place
        self.model, self.data = sim.model, sim.data
        self._sim = sim  # keeps the model alive
        m = self.model
        O = mujoco.mjtObj
        jid = [mujoco.mj_name2id(m, O.mjOBJ_JOINT, n) for n in spec.names]
        self.act = np.array([mujoco.mj_name2id(m, O.mjOBJ_ACTUATOR, n) for n in spec.names])
        self.qadr = np.array([m.jnt_qposadr[j] for j in jid])
        self.dadr = np.array([m.jnt_dofadr[j] for j in jid])
        self.h = float(m.opt.timestep)
        self.params = default_params(spec)
        self.damping = np.zeros(spec.n)
        for name, p in self.params.items():
            self.set(name, p)
        for name, p in (params or {}).items():
            self.set(name, p)
        self._qpos0 = self.data.qpos.copy()
        self._schedules: dict[tuple, tuple] = {}

    def set(self, joint: str, p: ServoParams) -> None:
        i = self.spec.index(joint)
        m, a, dof = self.model, self.act[i], self.dadr[i]
        m.actuator_gainprm[a, 0] = p.kp
        m.actuator_biasprm[a, 1] = -p.kp
        m.actuator_forcerange[a] = (-p.torque_limit, p.torque_limit)
        m.dof_damping[dof] = p.damping
        m.dof_armature[dof] = p.armature
        m.dof_frictionloss[dof] = p.frictionloss
        self.damping[i] = p.damping
        self.params[joint] = p

    def _schedule(self, k0: int, k1: int, latency_s: float) -> tuple:
        """Boundary steps, the control for the step after each, and where the reads fall (cached)."""
        key = (k0, k1, latency_s)
        if key in self._schedules:
            return self._schedules[key]
        rec, h = self.rec, self.h
        origin = rec.t_read[k0, 0]
        # command k0+j (j ≥ 1) takes effect at c[j-1] (in steps); before c[0] the command of tick k0 holds
        c = np.maximum.accumulate(np.maximum((rec.t_write[k0 + 1:k1, 1] + latency_s - origin) / h, 0.0))
        r = np.maximum((rec.t_read[k0:k1, 0] - origin) / h, 0.0)
        r_lo = np.floor(r).astype(np.int64)
        c_lo = np.floor(c).astype(np.int64)
        bounds = np.unique(np.concatenate([[0], c_lo, c_lo + 1, r_lo, r_lo + 1]))
        cmds = rec.q_cmd[k0:k1]
        first = np.searchsorted(c, bounds, side="right")  # command in force at the boundary
        last = np.searchsorted(c, bounds + 1, side="left")  # ... and at the end of the step after it
        ctrl = cmds[first].copy()
        for b in np.flatnonzero(last > first):  # the command changes inside this step: time-weighted mean
            t0, acc = float(bounds[b]), np.zeros(cmds.shape[1])
            for j in range(first[b], last[b]):
                acc += (c[j] - t0) * cmds[j]
                t0 = c[j]
            ctrl[b] = acc + (bounds[b] + 1 - t0) * cmds[last[b]]
        lo = np.searchsorted(bounds, r_lo)
        needed = np.zeros(len(bounds), dtype=bool)
        needed[lo] = needed[lo + 1] = True
        out = (bounds, ctrl, needed, lo, (r - r_lo)[:, None])
        self._schedules[key] = out
        return out

    def run(self, ticks: slice, latency_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Replay ``ticks`` from the measured state at its first tick: (q, effort) at every read.

        Sub-step timing: a command that arrives inside a model step contributes to that step's control
        in proportion to the time it is in force (exact for the linear part of the actuator); a read
        between two steps is interpolated linearly.
        """
        mj, m, d, rec = self._mj, self.model, self.data, self.rec
        k0, k1 = ticks.start or 0, ticks.stop if ticks.stop is not None else len(rec.q)
        lat = self.latency_s if latency_s is None else float(latency_s)
        bounds, ctrl, needed, lo, frac = self._schedule(k0, k1, lat)
        mj.mj_resetData(m, d)
        d.qpos[:] = self._qpos0
        d.qpos[self.qadr] = rec.q[k0]
        d.qvel[self.dadr] = rec.dq[k0]
        d.ctrl[self.act] = rec.q_cmd[k0]
        mj.mj_forward(m, d)
        nb, n = len(bounds), self.spec.n
        qs, es = np.zeros((nb, n)), np.zeros((nb, n))
        act, qadr, dadr, damping = self.act, self.qadr, self.dadr, self.damping
        step = mj.mj_step
        cur = 0
        for b in range(nb):
            s = bounds[b]
            if s > cur:
                step(m, d, int(s - cur))
                cur = s
            if needed[b]:
                qs[b] = d.qpos[qadr]
                es[b] = d.actuator_force[act] - damping * d.qvel[dadr]
            d.ctrl[act] = ctrl[b]
        q = qs[lo] + frac * (qs[lo + 1] - qs[lo])
        e = es[lo] + frac * (es[lo + 1] - es[lo])
        return q, e


def simulate(spec: RobotSpec, recording: Recording, params: Mapping[str, ServoParams] | None = None, *,
             fixed_base: bool | None = None, ticks: slice | None = None,
             latency_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Replay ``recording``'s commands in MuJoCo with ``params`` (joint -> ServoParams; others datasheet).

    Zero-order hold on the commands at the recorded write times (+ latency), sampled at the recorded
    read times, at the model timestep; the replay starts from the measured state at the first tick
    of ``ticks`` (default: all). Returns (q, effort), ticks × joints.
    """
    return Replay(spec, recording, params, fixed_base=fixed_base, latency_s=latency_s).run(ticks or slice(None))


# ----------------------------------------------------------------------------------------- fit
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
    from scipy.optimize import least_squares

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


def with_params(params: Mapping[str, ServoParams], **factors: float) -> dict[str, ServoParams]:
    """Each of ``params`` with fields scaled, e.g. ``with_params(p, kp=1.4, damping=0.7)`` (tests, demos)."""
    return {n: replace(p, **{k: getattr(p, k) * f for k, f in factors.items()}) for n, p in params.items()}
