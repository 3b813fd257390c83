"""The hardware abstraction layer: `State`, `Command`, the `Robot` protocol and its lifecycle.

Everything above ``felis.drivers`` sees robots only through these types, in SI units and radians,
with arrays in the joint order of the robot's `RobotSpec`. A controller is a function of `State`
(and time) returning a `Command`; it runs unchanged on a simulated and on a real robot.

Lifecycle::

    DISCONNECTED --connect()--> CONNECTED (read-only) --arm()--> ARMED --disarm()--> CONNECTED
          ^                          |                              |
          +--------close()-----------+------------close()-----------+     any failure -> ERROR

``arm()`` turns torque on with the goal set to the present position first (no jump at start-up).
Torque goes off on ``disarm()``, on ``close()`` and on any exception escaping a ``with robot:`` block.
"""

from __future__ import annotations

import enum
from dataclasses import MISSING, dataclass, field, fields
from typing import Protocol, runtime_checkable

import numpy as np

from felis.errors import LifecycleError
from felis.spec import RobotSpec


class _Factory:
    def __repr__(self) -> str:
        return "<factory>"


_FACTORY = _Factory()  # the default shown for a field with a default factory, as dataclasses show it


def _fast_init(cls):
    """Give a frozen dataclass an ``__init__`` that fills the instance's dict in one update.

    The generated one assigns each field through ``object.__setattr__`` (frozen classes refuse plain
    assignment), about 0.3 µs a field; a loop tick makes a `State`, an `Imu`, a `Truth` and three `Command`s,
    so that was ~10 µs of each tick. Same signature, defaults and default factories; the instances stay
    frozen (assignment still raises ``FrozenInstanceError``), compare, hash and print the same.
    """
    ns: dict = {"MISSING": _FACTORY}
    args, body = [], []
    for f in fields(cls):
        if f.default is not MISSING:
            ns[f"_d_{f.name}"] = f.default
            args.append(f"{f.name}=_d_{f.name}")
        elif f.default_factory is not MISSING:
            ns[f"_f_{f.name}"] = f.default_factory  # called when the argument is left out, as before
            args.append(f"{f.name}=MISSING")
            body.append(f"if {f.name} is MISSING: {f.name} = _f_{f.name}()")
        else:
            args.append(f.name)
    body.append("self.__dict__.update(" + ", ".join(f"{f.name}={f.name}" for f in fields(cls)) + ")")
    exec(f"def __init__(self, {', '.join(args)}):\n    " + "\n    ".join(body), ns)  # noqa: S102 - fixed text
    init = ns["__init__"]
    init.__qualname__ = f"{cls.__qualname__}.__init__"
    init.__doc__ = cls.__init__.__doc__
    cls.__init__ = init
    return cls


@_fast_init
@dataclass(frozen=True)
class Imu:
    """IMU reading in the world-aligned convention of MuJoCo sensors.

    quat: orientation of the IMU frame in the world, (w, x, y, z); gyro: body rates (rad/s) in the
    IMU frame; accel: specific force (m/s²) in the IMU frame (reads +9.81 on z when level and still).
    """

    quat: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray


@dataclass(frozen=True)
class Faults:
    """Per-joint hardware error bits (Dynamixel Hardware Error Status) and communication errors.

    ``Faults()`` is "no faults" for a robot of any size (``hardware`` empty, the masks None). Its arrays are
    not changed once reported: a backend whose faults change reports a new `Faults` (the loop checks an object
    it has seen once, `felis.loop.run_loop`)."""

    hardware: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))  # int per joint, 0 = healthy
    comm_errors: int = 0  # failed transactions since connect
    stale: np.ndarray | None = None  # bool per joint: value not refreshed this tick
    torque_off: np.ndarray | None = None  # bool per joint: torque read off while the host holds it on
    rebooted: np.ndarray | None = None  # bool per joint: the servo lost its RAM settings (power dip, reboot)
    watchdog: np.ndarray | None = None  # bool per joint: the servo's Bus Watchdog tripped (it ignores goals)

    @staticmethod
    def none(n: int) -> Faults:
        return Faults(hardware=np.zeros(n, dtype=np.int32))

    @property
    def any(self) -> bool:
        return bool(self.hardware.any()) or any(m is not None and bool(m.any()) for m in (
            self.stale, self.torque_off, self.rebooted, self.watchdog))


@_fast_init
@dataclass(frozen=True)
class Truth:
    """What only a simulator knows exactly, in the world frame (z up, floor at z = 0).

    com / com_vel: the robot's centre of mass (m) and its velocity (m/s); feet: foot body centres
    (k, 3) and foot_force: their normal contact forces (N), both in ``RobotSpec.sensors.contacts``
    order; low: the height (m) of the robot's lowest point other than its feet (the lowest point of
    its collision geometry outside the foot bodies), NaN where unknown. Monitors use it where present
    and estimate the same quantities on hardware.
    """

    com: np.ndarray
    com_vel: np.ndarray
    feet: np.ndarray
    foot_force: np.ndarray
    low: float = float("nan")


@_fast_init
@dataclass(frozen=True)
class State:
    """What the robot reports at one tick.

    t: time (s) since connect; q: joint positions (rad; m for prismatic); dq: velocities;
    effort: joint torques (N·m) estimated from servo current, None where not reported;
    imu / contacts (bool per foot in `RobotSpec.sensors.contacts` order) / height (m, waist above
    ground): None when the robot has no such sensor or the backend cannot know it; faults: per-joint
    hardware and communication faults (`Faults`; a backend that reports none gets ``Faults()``, no
    faults); truth: exact CoM and feet from a simulator (`Truth`), None on hardware.
    """

    t: float
    q: np.ndarray
    dq: np.ndarray
    effort: np.ndarray | None = None
    imu: Imu | None = None
    contacts: np.ndarray | None = None
    height: float | None = None
    faults: Faults = field(default_factory=Faults)
    truth: Truth | None = None


@_fast_init
@dataclass(frozen=True)
class Command:
    """What a controller asks for.

    q: position targets (rad; m for prismatic); dq_max: optional per-joint speed limits (rad/s)
    applied by the backend (Dynamixel Profile Velocity; rate-limited goal in simulation);
    torque: optional bool mask, False = torque off for that joint (None = all on);
    stiffness: optional per-joint compliance, the fraction s ∈ [`MIN_STIFFNESS`, 1] of the joint's Position P
    gain (the description's) its servo runs with (None = 1, every joint as described): Dynamixel writes
    P·s to Position P Gain (RAM, one sync write when it changes), MuJoCo scales the position actuator's kp.
    Only P is scaled: I, D and feedforward stay, so a compliant joint still comes back to its goal.
    """

    q: np.ndarray
    dq_max: np.ndarray | None = None
    torque: np.ndarray | None = None
    stiffness: np.ndarray | None = None

    def replace(self, **changes) -> Command:
        values = {"q": self.q, "dq_max": self.dq_max, "torque": self.torque, "stiffness": self.stiffness}
        values.update(changes)
        return Command(**values)


MIN_STIFFNESS = 0.05  # `Command.stiffness`: the softest a joint may be asked to go (5 % of its P gain)


class Lifecycle(enum.Enum):
    DISCONNECTED = "disconnected"
    CONNECTED = "connected"
    ARMED = "armed"
    ERROR = "error"


@runtime_checkable
class Robot(Protocol):
    """A robot the control loop can drive: simulation or hardware.

    ``advance(dt)``: a simulation steps its physics by ``dt``; hardware (``realtime = True``) returns
    at once, because the loop's wall clock paces the ticks (one place owns timing, so overruns are
    measured the same way for every backend, and a simulation can also run in real time).
    ``write`` returns the command actually sent, after the backend's own clamping.
    """

    spec: RobotSpec
    realtime: bool  # True: advance() waits for wall-clock time (hardware)

    @property
    def lifecycle(self) -> Lifecycle: ...

    def connect(self) -> None: ...

    def arm(self) -> None: ...

    def disarm(self) -> None: ...

    def read(self) -> State: ...

    def write(self, command: Command) -> Command: ...

    def advance(self, dt: float) -> None: ...

    def close(self) -> None: ...


class RobotBase:
    """Shared lifecycle bookkeeping for backends.

    Subclasses implement ``_connect``, ``_arm``, ``_disarm``, ``_read``, ``_write``, ``_advance``,
    ``_close``; this class checks the state machine, turns torque off on close and on exceptions
    in a ``with`` block, and moves to ERROR when a backend call fails.
    """

    realtime = False

    def __init__(self, spec: RobotSpec):
        self.spec = spec
        self._life = Lifecycle.DISCONNECTED
        self._q_shape = (spec.n,)  # what write() checks each command's positions against

    @property
    def lifecycle(self) -> Lifecycle:
        return self._life

    def _require(self, *allowed: Lifecycle, action: str) -> None:
        if self._life not in allowed:
            want = " or ".join(a.value for a in allowed)
            raise LifecycleError(f"{self.spec.name}: cannot {action} while {self._life.value} (needs {want})")

    def _guard(self, fn, *args):
        try:
            return fn(*args)
        except Exception:
            self._fail()
            raise

    def _fail(self) -> None:
        """A backend call failed: ERROR state, torque off."""
        self._life = Lifecycle.ERROR
        self._safe_disarm()

    def _safe_disarm(self) -> None:
        try:
            self._disarm()
        except Exception:  # torque-off is best effort once something already failed
            pass

    def connect(self) -> None:
        self._require(Lifecycle.DISCONNECTED, action="connect")
        self._guard(self._connect)
        self._life = Lifecycle.CONNECTED

    def arm(self) -> None:
        self._require(Lifecycle.CONNECTED, action="arm")
        self._guard(self._arm)
        self._life = Lifecycle.ARMED

    def disarm(self) -> None:
        if self._life in (Lifecycle.ARMED, Lifecycle.ERROR):
            self._disarm()
            if self._life is Lifecycle.ARMED:
                self._life = Lifecycle.CONNECTED

    def read(self) -> State:
        if self._life is not Lifecycle.ARMED:
            self._require(Lifecycle.CONNECTED, Lifecycle.ARMED, action="read")
        return self._read()

    def write(self, command: Command) -> Command:
        if self._life is not Lifecycle.ARMED:
            self._require(Lifecycle.ARMED, action="write")
        q = command.q
        if not (isinstance(q, np.ndarray) and q.dtype == np.float64):
            q = np.asarray(q, dtype=float)
            command = command.replace(q=q)
        if q.shape != self._q_shape:
            raise ValueError(f"{self.spec.name}: command has {q.size} positions, robot has {self.spec.n} joints")
        try:
            return self._write(command)
        except Exception:
            self._fail()
            raise

    def advance(self, dt: float) -> None:
        if self._life is not Lifecycle.ARMED:
            self._require(Lifecycle.CONNECTED, Lifecycle.ARMED, action="advance")
        try:
            self._advance(dt)
        except Exception:
            self._fail()
            raise

    def close(self) -> None:
        if self._life is Lifecycle.DISCONNECTED:
            return
        try:
            self._safe_disarm()
        finally:
            self._close()
            self._life = Lifecycle.DISCONNECTED

    def __enter__(self):
        if self._life is Lifecycle.DISCONNECTED:
            try:
                self.connect()
            except BaseException:  # a failed or interrupted connect releases the port, torque off
                try:
                    self._close()
                except Exception:  # noqa: BLE001 - already failing; the first error is the one to report
                    pass
                self._life = Lifecycle.DISCONNECTED
                raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # backend hooks -------------------------------------------------------------------------
    def _connect(self) -> None:
        raise NotImplementedError

    def _arm(self) -> None:
        raise NotImplementedError

    def _disarm(self) -> None:
        raise NotImplementedError

    def _read(self) -> State:
        raise NotImplementedError

    def _write(self, command: Command) -> Command:
        raise NotImplementedError

    def _advance(self, dt: float) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        pass




@runtime_checkable
class Controller(Protocol):
    """A controller: bound to a robot by ``reset``, then called once per tick.

    ``reset(spec, state)`` is called by the loop before the first tick with the robot's description
    and first state, so one controller object can run on any robot (and be re-used across runs).
    ``__call__(state) -> Command`` must be a pure function of its inputs and its own state; it never
    touches a backend.
    """

    def reset(self, spec: RobotSpec, state: State) -> None: ...

    def __call__(self, state: State) -> Command: ...
