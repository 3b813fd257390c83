"""Recording for system identification: the excitation run on a HAL `Robot` (`record`), kept as a
`Recording` in an ``.npz`` file.

`record` drives any HAL `Robot` (a `DynamixelRobot` over a real or virtual bus, or a `MujocoRobot`)
at ``rate_hz``: per tick it writes the target and reads the state, timestamping each call
(``time.perf_counter`` before and after, seconds since the start) for a realtime robot; for a
simulation the times are the simulated ones (k/rate).

Recordings are saved as ``.npz`` (plain arrays, never pickle); parameter files by
`felis.sim.servo_file`. ``felis sysid`` (``felis/cli/sysid.py``) wires it all for an operator.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from felis.calib.sysid.excitation import Excitation, plan
from felis.calib.sysid.model import check_joints
from felis.errors import FelisError, SysidError
from felis.files import MAX_ARRAY_BYTES, check_readable, prepare_parent
from felis.hal import Command, Lifecycle, Robot
from felis.loop import servo_stop
from felis.spec import RobotSpec

RECORDING_SCHEMA = 1
LATENCY_S = 0.0005  # command → effect delay for a realtime recording beyond the write's own duration
_EXCITATION = Excitation()  # the default test signal (frozen: one instance serves every call)


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
           exc: Excitation = _EXCITATION, fixed_base: bool = True, backend: str = "",
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
