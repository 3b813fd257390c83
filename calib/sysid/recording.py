"""Recording for system identification: the excitation run on a HAL `Robot` (`record`), kept as a
`Recording` in an ``.npz`` file.

`record` drives any HAL `Robot` (a `DynamixelRobot` over a real or virtual bus, or a `MujocoRobot`)
at ``rate_hz``: per tick it writes the target and reads the state. Each recording says on which time base
its write and read times are (``timebase``):

* ``"emulator"``: the servos run on a simulated clock the recorder advances (``clock=``, a `StepClock` driving
  a virtual bus's servos): the write and the read of tick k happen at exactly the emulator's time t_k, and
  the clock then moves on by 1/rate. No host timing enters the recording: a loaded machine only makes it
  slower (`felis.calib.sysid.clock`).
* ``"simulation"``: a non-realtime robot (`MujocoRobot`): the simulated times k/rate.
* ``"host"``: a realtime robot on the wall clock: ``time.perf_counter`` before and after each call, seconds
  since the start; the replay adds a latency (fitted, starting at `LATENCY_S`).

``setup`` says what the servos drive: ``"robot"`` (the robot's MuJoCo model: links, gravity; the robot hung
on a stand for a floating base) or ``"bench"`` (bare horns, nothing attached: the servos on a bench, or a
virtual bus's standalone servos).

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

from felis.calib.sysid.clock import StepClock
from felis.calib.sysid.excitation import Excitation, plan
from felis.calib.sysid.model import check_joints
from felis.errors import FelisError, SysidError
from felis.files import MAX_ARRAY_BYTES, check_readable, prepare_parent
from felis.hal import Command, Lifecycle, Robot
from felis.loop import servo_stop
from felis.spec import RobotSpec

RECORDING_SCHEMA = 1
LATENCY_S = 0.0005  # starting command → effect delay for a host-timed recording, beyond the write's own duration
TIMEBASES = ("host", "simulation", "emulator")
CLOCK_RETRIES = 5  # on the emulator's clock: reads of a tick whose reply was lost, before the clock moves on
SETUPS = ("robot", "bench")
_EXCITATION = Excitation()  # the default test signal (frozen: one instance serves every call)


@dataclass
class Recording:
    """What `record` measured. Times are seconds since the start; arrays are ticks × joints in spec order.

    ``t_write``/``t_read``: (ticks, 2) times before and after each write/read, on ``timebase`` (module doc;
    equal pairs where the time base stands still during a tick); ``q_cmd``: what
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
    timebase: str = ""  # module doc; "" (older files): "host" if realtime else "simulation"
    setup: str = "robot"

    def __post_init__(self):
        if not self.timebase:
            self.timebase = "host" if self.realtime else "simulation"
        if self.timebase not in TIMEBASES:
            raise SysidError(f"unknown time base {self.timebase!r}; expected one of {', '.join(TIMEBASES)}")
        if self.setup not in SETUPS:
            raise SysidError(f"unknown setup {self.setup!r}; expected one of {', '.join(SETUPS)}")

    @property
    def latency_s(self) -> float:
        """Starting command delay for the replay: `LATENCY_S` on the host's clock, 0 on a simulated one."""
        return LATENCY_S if self.timebase == "host" else 0.0

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
                            fixed_base=bool(data["fixed_base"]), backend=str(data.get("backend", "")),
                            timebase=str(data.get("timebase", "")), setup=str(data.get("setup", "robot")), **kw)
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
           progress: Callable[[float], None] | None = None, max_invalid: float = 0.05,
           clock: StepClock | None = None, setup: str = "robot") -> Recording:
    """Run the excitation for ``joints`` on ``robot`` (connected or armed) and record it.

    Only the HAL `Robot` protocol is used. With ``clock`` (the `StepClock` the robot's virtual servos run on)
    each tick is written and read at the clock's time, which then moves on by 1/rate: the emulator's time base
    (module doc), no pacing. Otherwise a realtime robot is paced by the wall clock (``time.perf_counter``) and
    a simulation is stepped by ``advance``. The robot is armed if it is only connected, and left armed at the
    hold pose. ``fixed_base`` records that a floating-base robot hung on a stand (the replay then holds its
    base), ``setup`` what the servos drive (module doc). ``progress(fraction)`` is called now and then. A read
    that fails (`felis.errors.CommError`) or leaves a joint stale marks its tick invalid; more than
    ``max_invalid`` of them is a `SysidError`.
    """
    spec = robot.spec
    joints = check_joints(spec, joints)
    if not 1.0 <= rate_hz <= 1000.0:
        raise SysidError(f"rate must be within 1…1000 Hz, got {rate_hz:g}")
    if setup not in SETUPS:
        raise SysidError(f"unknown setup {setup!r}; expected one of {', '.join(SETUPS)}")
    realtime = bool(getattr(robot, "realtime", False))
    timebase = "emulator" if clock is not None else "host" if realtime else "simulation"
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
    wall = time.perf_counter
    t0 = clock() if clock is not None else wall()
    last = first

    def read_checked():
        nonlocal last
        try:
            s = robot.read()
            ok = not (s.faults is not None and s.faults.stale is not None and bool(s.faults.stale.any()))
            last = s
        except FelisError:
            s, ok = last, False
        stop = servo_stop(spec, s.faults, True)
        if stop is not None:  # a servo that cannot follow: the recording is worthless, and so is going on
            raise SysidError(f"recording stopped: {stop[1]}")
        return s, ok

    for k in range(n):
        if clock is not None:  # the emulator's time stands still within the tick
            t = clock() - t0
            sent = robot.write(Command(q=p.q[k]))
            s, valid[k] = read_checked()
            for _ in range(CLOCK_RETRIES):  # a lost reply (a loaded host): ask again before time moves on, so
                if valid[k]:  # that everything sent in this tick is handled at t_k (the servos answer in order)
                    break
                s, valid[k] = read_checked()
            t_write[k] = t_read[k] = t
            clock.advance(dt)
        elif realtime:
            wait = t0 + k * dt - wall()
            if wait > 0:
                time.sleep(wait)
            a = wall() - t0
            sent = robot.write(Command(q=p.q[k]))
            b = wall() - t0
            s, valid[k] = read_checked()
            t_write[k] = (a, b)
            t_read[k] = (b, wall() - t0)  # the read starts when the write returns
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
                     valid=valid, active=p.active, kind=p.kind, backend=backend, timebase=timebase, setup=setup)
