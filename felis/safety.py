"""Safety layer between controller and robot, and the watchdog.

Per tick, on the controller's command (`SafetyLayer.filter`):

1. Non-finite targets (NaN, ±inf) anywhere in ``q``, ``dq_max`` or ``stiffness`` (or a stiffness of the wrong
   shape): the whole command is replaced by the last good one (held), and ``nonfinite_held`` counts it.
2. Soft limits: ``q`` is clamped to ``[lower + margin, upper - margin]`` of the description.
3. Maximum step: ``|q - q_last_sent| <= max_step`` with ``max_step = fraction · v_max · dt`` per joint
   (v_max from the description, by default the servo's no-load speed), so no target can jump; at
   start-up ``q_last_sent`` is the present position, which is what makes arming jump-free. Given the
   robot's time of each command (``filter(command, t)``: the loop passes ``state.t``), the bound is a speed,
   not a step: a tick that comes ``e`` s after the last command sent (a late tick on a wall clock, a
   stalled host) may move its targets by ``fraction · v_max · e``, with ``e`` at most
   ``SafetyConfig.max_late_ticks`` ticks, as far as the servo itself could have moved meanwhile. A fixed
   step would leave a late tick's targets behind the controller's path, and a path timed against a falling
   body (the landing motions, on servos whose host is loaded) then lands on its back. On a simulation's
   exact ticks ``e = dt`` and the bound is the step, bit for bit.
4. Stiffness (`felis.hal.Command.stiffness`) is clamped to ``[MIN_STIFFNESS, 1]``: a controller may soften a
   joint, never stiffen it past its description nor make it limp.

`Watchdog` counts consecutive failed reads and consecutive loop overruns; past their tolerance it
trips, and the loop disarms the robot (torque off) and stops.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from felis.hal import MIN_STIFFNESS, Command
from felis.spec import RobotSpec

_sum = np.add.reduce
_any = np.logical_or.reduce


@dataclass(frozen=True)
class SafetyConfig:
    """Tunables of the safety layer and watchdog (defaults suit both robots)."""

    soft_margin: float = 0.0  # rad (m) kept inside each joint's range
    max_speed_fraction: float = 1.0  # max step per tick as a fraction of v_max·dt
    read_fail_tolerance: int = 3  # consecutive failed reads tolerated; one more trips
    overrun_tolerance: int = 10  # consecutive overruns tolerated (wall clock only)
    max_late_ticks: float = 10.0  # a late command may catch up at most this many ticks' max step (module doc, 3)
    stop_on_hardware_error: bool = True  # a servo reporting a hardware error (e.g. overload) ends the run
    imu_timeout_s: float = 0.3  # an IMU quiet this long stops a controller that needs one (an event at once)

    def __post_init__(self):
        if self.soft_margin < 0 or not 0 < self.max_speed_fraction <= 10:
            raise ValueError("soft_margin must be ≥ 0 and max_speed_fraction in (0, 10]")
        if self.read_fail_tolerance < 0 or self.overrun_tolerance < 0 or not self.imu_timeout_s >= 0:
            raise ValueError("watchdog tolerances must be ≥ 0")
        if not 1.0 <= self.max_late_ticks <= 100.0:
            raise ValueError("max_late_ticks must be within 1…100 ticks")


@dataclass
class SafetyCounters:
    limit_clamps: int = 0  # ticks on which some target was clamped to the soft limits
    step_clamps: int = 0  # ticks on which some target was rate-limited
    nonfinite_held: int = 0  # ticks on which a non-finite command was replaced by the last good one

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class SafetyLayer:
    """Filters commands: non-finite → hold, soft limits, maximum step per tick."""

    def __init__(self, spec: RobotSpec, dt: float, config: SafetyConfig | None = None):
        self.config = config or SafetyConfig()
        margin = self.config.soft_margin
        self.lower = spec.lower + margin
        self.upper = spec.upper - margin
        if np.any(self.lower > self.upper):
            raise ValueError(f"soft_margin {margin} leaves no range for some joint of {spec.name}")
        self.dt = float(dt)
        self.max_step = self.config.max_speed_fraction * spec.max_velocity * dt
        self.counters = SafetyCounters()
        self.events: list[tuple[str, dict]] = []  # this tick's events, for the log
        self._last: Command | None = None
        self._t_sent: float | None = None  # the robot's time of the last command sent (module doc, 3)
        self._t_filtered: float | None = None

    def reset(self, q_present: np.ndarray, t: float | None = None) -> None:
        """Start from the present position (read at the robot's time ``t``): the first targets may move at most
        one step from it (or, given times, as far as ``v_max`` allows since ``t``)."""
        q0 = np.clip(np.asarray(q_present, dtype=float), self.lower, self.upper)
        self._last = Command(q=q0)
        self._t_sent = self._t_filtered = None if t is None else float(t)

    def step(self, t: float | None) -> np.ndarray:
        """The largest target change per joint for a command at the robot's time ``t`` (module doc, 3)."""
        if t is None or self._t_sent is None:
            return self.max_step
        late = (float(t) - self._t_sent) / self.dt
        if not late > 1.0 + 1e-6:  # on time (a simulation's tick, whatever its rounding), or a clock gone back
            return self.max_step
        return self.max_step * min(late, self.config.max_late_ticks)

    @property
    def last(self) -> Command:
        if self._last is None:
            raise RuntimeError("SafetyLayer.reset() must be called with the present position first")
        return self._last

    def filter(self, command: Command, t: float | None = None) -> Command:
        """The command made safe (module doc); ``t``: the robot's time of the state it answers (`felis.hal.State.t`),
        which lets a late tick catch up (3); None: one tick since the last command."""
        last = self.last
        self.events = []
        self._t_filtered = None if t is None else float(t)
        q = command.q if isinstance(command.q, np.ndarray) else np.asarray(command.q, dtype=float)
        dq_max = command.dq_max
        if dq_max is not None:
            dq_max = np.asarray(dq_max, dtype=float)
        stiffness = command.stiffness
        if stiffness is not None:
            stiffness = np.asarray(stiffness, dtype=float)
        # a sum is finite iff every term is (ufunc reduce: no Python-level wrapper on the hot path)
        if (q.shape != last.q.shape or not math.isfinite(_sum(q))
                or (dq_max is not None and not math.isfinite(_sum(dq_max)))
                or (stiffness is not None and (stiffness.shape != q.shape or not math.isfinite(_sum(stiffness))))):
            self.counters.nonfinite_held += 1
            bad = np.flatnonzero(~np.isfinite(q)).tolist() if q.shape == last.q.shape else []
            self.events.append(("nonfinite_held", {"joints": bad, "shape": list(q.shape)}))
            return last
        # one clamp to [max(lower, last − step), min(upper, last + step)]; attribute it only when it bites
        step = self.step(t)
        lo = np.maximum(self.lower, last.q - step)
        hi = np.minimum(self.upper, last.q + step)
        out = np.minimum(np.maximum(q, lo), hi)
        if _any(out != q):
            beyond = (q < self.lower) | (q > self.upper)
            if _any(beyond):
                self.counters.limit_clamps += 1
                self.events.append(("limit_clamp", {"joints": np.flatnonzero(beyond).tolist()}))
            in_range = np.minimum(np.maximum(q, self.lower), self.upper)
            if _any(out != in_range):
                self.counters.step_clamps += 1
        if stiffness is not None:  # compliance only: never stiffer than described, never limp
            stiffness = np.minimum(np.maximum(stiffness, MIN_STIFFNESS), 1.0)
        return Command(q=out, dq_max=dq_max, torque=command.torque, stiffness=stiffness)

    def filter_many(self, q: np.ndarray, last: np.ndarray) -> np.ndarray:
        """`filter` for a batch of robots at once (`felis.sim.batch`): ``q`` and ``last`` (the targets each
        robot sent last) are (B, n); a row with a non-finite target holds its last row. No counters."""
        q = np.asarray(q, dtype=float)
        lo = np.maximum(self.lower, last - self.max_step)
        hi = np.minimum(self.upper, last + self.max_step)
        out = np.minimum(np.maximum(q, lo), hi)
        bad = ~np.isfinite(q).all(axis=1)
        if bad.any():
            out[bad] = last[bad]
        return out

    def sent(self, command: Command) -> None:
        """Record what the robot actually sent: the reference for the next step limit and hold. Its time is the
        last `filter`'s ``t`` (a tick that held, its read failed, keeps the time of the target it repeats)."""
        self._last = command
        if self._t_filtered is not None:
            self._t_sent = self._t_filtered


@dataclass
class Watchdog:
    """Trips after too many consecutive read failures or (wall clock) loop overruns."""

    read_fail_tolerance: int = 3
    overrun_tolerance: int = 10
    read_failures: int = 0  # total
    overruns: int = 0  # total
    tripped: str | None = None
    _fail_run: int = field(default=0, repr=False)
    _overrun_run: int = field(default=0, repr=False)

    def read_ok(self) -> None:
        self._fail_run = 0

    def read_failed(self, error: Exception) -> bool:
        self.read_failures += 1
        self._fail_run += 1
        if self._fail_run > self.read_fail_tolerance and not self.tripped:
            self.tripped = f"{self._fail_run} consecutive read failures (last: {error})"
        return self.tripped is not None

    def tick(self, overrun: bool, enforce: bool) -> bool:
        if overrun:
            self.overruns += 1
            self._overrun_run += 1
        else:
            self._overrun_run = 0
        if enforce and self._overrun_run > self.overrun_tolerance and not self.tripped:
            self.tripped = f"{self._overrun_run} consecutive loop overruns"
        return self.tripped is not None
