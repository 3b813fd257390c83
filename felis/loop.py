"""The fixed-rate control loop: read, compute, safety, write, monitors, log, advance.

``run_loop`` drives any `Robot` with any `Controller` at ``rate_hz``::

    for each tick k (t_k = t_0 + k·dt):
        state   = robot.read()              # CommError: hold the last command; watchdog counts
                                            # stale joints (no reply) count like a failed read
                                            # a hardware error (servo shutdown), torque gone off
                                            # (switched off, a servo rebooted) or a tripped Bus
                                            # Watchdog stops the run, naming the joints
        command = controller(state)
        command = safety.filter(command, t) # non-finite → hold, soft limits, max step (a speed: late ticks
                                            # catch up, `felis.safety`)
        sent    = robot.write(command)      # what the backend actually sent (after its clamping)
        monitors(state, sent); log
        robot.advance(dt)                   # simulation: step physics; hardware: returns
        clock == "wall": sleep until t_k+1; a tick that ends after its deadline is an overrun

Clocks: ``"sim"`` runs as fast as the backend steps (simulated time only); ``"wall"`` paces ticks
to real time (needed for hardware, optional for simulation, e.g. servo-in-the-loop or a viewer).
The watchdog (see `felis.safety`) disarms the robot past its tolerances; any exception from the
controller, a monitor or the backend disarms it too before propagating. Torque is left off at the end of
a run unless ``keep_armed`` is set. A fatal `CommError` (the port vanished) ends the run at once
(``stopped = "comm lost: …"``, also logged as a ``comm_lost`` event). An IMU that stops reporting mid-
run (``state.imu`` turns None) is an ``imu_lost`` event, and a stop (``"imu lost"``) after
``SafetyConfig.imu_timeout_s`` when the controller declares ``needs_imu = True``. A signal
(`felis.shutdown`) or Ctrl-C ends the run as ``"interrupted (SIGTERM)"`` and the like; torque goes off
on every way out. The reads before the first tick (the state the controller is reset with, before and
after arming) follow the watchdog's rule: a failed one is tried again up to ``read_fail_tolerance``
times, then raised (a bus under load can drop one group read).

The log also gets an ``armed`` event when the loop arms the robot and a ``stopped`` event (the reason, the
ticks) at the end, so a viewer's log panel shows where a run began and why it ended.

The report gives the control path's time per tick (read → write, excluding monitors, logging,
physics and sleep): mean, p99, max; the mean time of monitors + logging; and overruns: with the
wall clock, ticks that ended past their deadline; with the simulated clock, ticks whose control
path alone took longer than the period.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

from felis import shutdown
from felis.errors import CommError, ParameterError
from felis.hal import Command, Controller, Lifecycle, Robot, State
from felis.safety import SafetyConfig, SafetyLayer, Watchdog


class Monitor(Protocol):
    """Observes each tick (state read, command sent); must not command the robot."""

    def __call__(self, state: State, command: Command) -> None: ...


class RunLogLike(Protocol):
    def state(self, state: State) -> None: ...
    def command(self, t: float, command: Command) -> None: ...
    def event(self, t: float, kind: str, **detail) -> None: ...


@dataclass
class Timing:
    """Control-path time per tick (read → compute → safety → write), monitors and logging apart."""

    mean_ms: float
    p99_ms: float
    max_ms: float
    overruns: int
    period_ms: float
    monitors_mean_ms: float = 0.0  # monitors + logging per tick

    @staticmethod
    def from_samples(control_s: np.ndarray, extra_s: np.ndarray, overruns: int, dt: float) -> Timing:
        if control_s.size == 0:
            return Timing(0.0, 0.0, 0.0, overruns, dt * 1e3)
        ms = control_s * 1e3
        return Timing(float(ms.mean()), float(np.percentile(ms, 99)), float(ms.max()), overruns, dt * 1e3,
                      float(extra_s.mean() * 1e3))


@dataclass
class LoopReport:
    """What a run did; `ok` is False when the watchdog stopped it."""

    robot: str
    controller: str
    clock: str
    rate_hz: float
    ticks: int
    sim_time_s: float
    wall_time_s: float
    stopped: str  # "duration", "until", "interrupted (SIG…)", "watchdog: …", "hardware error: …", "torque lost: …",
    #               "bus watchdog: …", "comm lost: …", "imu lost: …"
    timing: Timing
    safety: dict[str, int]
    read_failures: int
    stale_ticks: int = 0  # ticks where some joint's reading was not refreshed (hardware)
    write_failures: int = 0
    final_state: State | None = field(default=None, repr=False)
    comm: dict[str, int] = field(default_factory=dict)  # the bus's counters (hardware): retries, timeouts, …
    torque_off_verified: bool | None = None  # hardware: torque read back as 0 at the end (None: not known)

    FAILURES = ("watchdog", "hardware error", "torque lost", "bus watchdog", "comm lost", "imu lost")

    @property
    def ok(self) -> bool:
        return not self.stopped.startswith(self.FAILURES)

    @property
    def interrupted(self) -> bool:
        return self.stopped.startswith("interrupted")

    def raise_if_interrupted(self) -> LoopReport:
        """Raise `felis.shutdown.Interrupted` again when a signal ended this run (torque is already off):
        for callers that run many episodes, so Ctrl-C or SIGTERM stops them all, not just the current one."""
        if self.interrupted:
            from felis.shutdown import Interrupted

            raise Interrupted(self.stopped[len("interrupted ("):-1] or "SIGINT")
        return self

    def as_dict(self) -> dict:
        return {
            "robot": self.robot, "controller": self.controller, "clock": self.clock,
            "rate_hz": self.rate_hz, "ticks": self.ticks, "sim_time_s": round(self.sim_time_s, 6),
            "wall_time_s": round(self.wall_time_s, 4), "stopped": self.stopped, "ok": self.ok,
            "timing": {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.timing.__dict__.items()},
            "safety": self.safety, "read_failures": self.read_failures, "stale_ticks": self.stale_ticks,
            "write_failures": self.write_failures, "comm": self.comm, "torque_off_verified": self.torque_off_verified,
        }


def run_loop(
    robot: Robot,
    controller: Controller,
    *,
    duration: float,
    rate_hz: float | None = None,
    clock: Literal["sim", "wall"] = "sim",
    safety: SafetyConfig | None = None,
    log: RunLogLike | None = None,
    monitors: Iterable[Monitor] = (),
    until: Callable[[State], bool] | None = None,
    keep_armed: bool = False,
) -> LoopReport:
    """Run ``controller`` on ``robot`` for ``duration`` seconds at ``rate_hz`` (default: the spec's).

    The robot must be connected; it is armed here if it is not already.
    """
    rate = float(rate_hz if rate_hz is not None else robot.spec.rate_hz)
    if not (np.isfinite(duration) and duration > 0):
        raise ParameterError(f"duration must be a positive number of seconds, got {duration}")
    if not (np.isfinite(rate) and 1.0 <= rate <= 2000.0):
        raise ParameterError(f"rate must be within 1…2000 Hz, got {rate}")
    if clock not in ("sim", "wall"):
        raise ParameterError(f"clock must be 'sim' or 'wall', got {clock!r}")
    if robot.realtime and clock != "wall":
        raise ParameterError(f"{robot.spec.name} is real hardware: it needs clock='wall'")
    cfg = safety or SafetyConfig()
    dt = 1.0 / rate
    n_ticks = int(round(duration * rate))
    monitors = list(monitors)
    layer = SafetyLayer(robot.spec, dt, cfg)
    dog = Watchdog(cfg.read_fail_tolerance, cfg.overrun_tolerance)
    control = np.zeros(n_ticks)  # read → write
    extra = np.zeros(n_ticks)  # monitors + log
    name = getattr(controller, "name", type(controller).__name__)
    log_timing = getattr(log, "timing", None)  # optional: the tick's control-path time (`felis.logs.runlog`)
    log_tick = getattr(log, "tick", None)  # optional: state, command and time in one call (`RunLog.tick`)

    wall0 = deadline = time.perf_counter()
    stopped = "duration"
    ticks = 0
    stale_ticks = write_failures = 0
    finished = False  # the loop ended by its own rules, not by an exception
    needs_imu = bool(getattr(controller, "needs_imu", False))
    imu_seen, imu_lost_at = False, None
    faults_ok = None  # the last Faults that servo_stop passed
    state = first_read(robot, cfg.read_fail_tolerance)
    try:
        if robot.lifecycle is not Lifecycle.ARMED:
            robot.arm()
            state = first_read(robot, cfg.read_fail_tolerance)
            if log is not None:
                log.event(state.t, "armed")
        controller.reset(robot.spec, state)
        layer.reset(state.q, state.t)
        for m in monitors:
            if hasattr(m, "reset"):
                m.reset(robot.spec, state)
        wall0 = deadline = time.perf_counter()
        signals_before = shutdown.count()
        for k in range(n_ticks):
            if shutdown.count() > signals_before:  # a signal whose Interrupted was lost in a finaliser
                raise shutdown.Interrupted(shutdown.received()[signals_before])
            t0 = time.perf_counter()
            try:
                state = robot.read()
                faults = state.faults
                stale = faults.stale if faults is not None else None
                if stale is not None and stale.any():  # some servos did not answer: their values are old
                    stale_ticks += 1
                    names = [robot.spec.names[i] for i in np.flatnonzero(stale)]
                    if dog.read_failed(CommError(f"stale: {', '.join(names)}")):
                        stopped = f"watchdog: {dog.tripped}"
                        break
                else:
                    dog.read_ok()
                if faults is not faults_ok:  # a backend that reports the same (frozen) Faults: checked once
                    halt = servo_stop(robot.spec, faults, cfg.stop_on_hardware_error)
                    if halt is not None:
                        kind, stopped = halt
                        if log is not None:
                            log.event(state.t, kind, detail=stopped)
                        break
                    faults_ok = faults
                if state.imu is not None:
                    if imu_lost_at is not None and log is not None:
                        log.event(state.t, "imu_back", after_s=round(state.t - imu_lost_at, 4))
                    imu_seen, imu_lost_at = True, None
                elif imu_seen:
                    if imu_lost_at is None:
                        imu_lost_at = state.t
                        if log is not None:
                            log.event(state.t, "imu_lost", detail="the IMU stopped reporting")
                    if needs_imu and state.t - imu_lost_at >= cfg.imu_timeout_s:
                        stopped = (f"imu lost: no IMU reading for {state.t - imu_lost_at:.2f} s and {name} needs "
                                   "one")
                        break
                command = layer.filter(controller(state), state.t)
            except CommError as e:
                if e.fatal:  # the port is gone: nothing to hold
                    stopped = f"comm lost: {e}"
                    break
                layer.events = []
                if log is not None:
                    log.event(state.t, "read_failed", error=str(e))
                if dog.read_failed(e):
                    stopped = f"watchdog: {dog.tripped}"
                    break
                command = layer.last  # hold
            try:
                sent = robot.write(command)
            except CommError as e:
                if e.fatal:
                    stopped = f"comm lost: {e}"
                    break
                write_failures += 1
                sent = command
            layer.sent(sent)
            t_ctrl = time.perf_counter()
            control_s = t_ctrl - t0
            for m in monitors:
                m(state, sent)
            if log_tick is not None:
                log_tick(state, sent, control_s)
            elif log is not None:
                log.state(state)
                log.command(state.t, sent)
                if log_timing is not None:
                    log_timing(state.t, control_s)
            if log is not None:
                for kind, detail in layer.events:
                    log.event(state.t, kind, **detail)
            control[k] = control_s
            extra[k] = time.perf_counter() - t_ctrl
            ticks = k + 1
            if until is not None and until(state):
                stopped = "until"
                break
            robot.advance(dt)
            now = time.perf_counter()
            if clock == "wall":
                deadline += dt
                overrun = now > deadline
                if overrun:
                    deadline = now  # re-anchor: no burst of catch-up ticks after a stall
                else:
                    time.sleep(deadline - now)
            else:  # simulated time: would the control path have kept up in real time?
                overrun = control_s > dt
            if dog.tick(overrun, enforce=clock == "wall"):
                stopped = f"watchdog: {dog.tripped}"
                break
        finished = True
    except KeyboardInterrupt as e:
        stopped = f"interrupted ({getattr(e, 'signame', 'SIGINT')})"
        if log is not None:
            log.event(state.t, "interrupted", signal=getattr(e, "signame", "SIGINT"))
    finally:
        if not (finished and keep_armed and stopped in ("duration", "until")):
            _disarm(robot)  # torque off: on exceptions, interrupts and watchdog trips, whatever keep_armed says
    verified = getattr(robot, "torque_off_verified", None)
    if log is not None:
        if stopped.startswith("watchdog"):
            log.event(state.t, "watchdog", reason=dog.tripped)
        elif stopped.startswith("comm lost"):
            log.event(state.t, "comm_lost", detail=stopped[len("comm lost: "):])
        if verified is not None:
            log.event(state.t, "torque_off", verified=bool(verified))
        log.event(state.t, "stopped", reason=stopped, ticks=ticks)
    return LoopReport(
        robot=robot.spec.name, controller=name, clock=clock, rate_hz=rate, ticks=ticks,
        sim_time_s=ticks * dt, wall_time_s=time.perf_counter() - wall0, stopped=stopped,
        timing=Timing.from_samples(control[:ticks], extra[:ticks], dog.overruns, dt), safety=layer.counters.as_dict(),
        read_failures=dog.read_failures, stale_ticks=stale_ticks, write_failures=write_failures, final_state=state,
        comm=_comm_counters(robot), torque_off_verified=verified,
    )


def _disarm(robot: Robot) -> None:
    """Torque off on the way out; a second signal while it is written does not cut it short."""
    try:
        robot.disarm()
    except KeyboardInterrupt:  # pragma: no cover - felis.shutdown raises only once; a plain SIGINT may not
        robot.disarm()
        raise


def servo_stop(spec, faults, stop_on_hardware_error: bool) -> tuple[str, str] | None:
    """(event kind, stopped text) when a servo can no longer follow: hardware error, torque gone,
    Bus Watchdog tripped; None otherwise."""
    if faults is None:
        return None
    if stop_on_hardware_error and faults.hardware.any():
        return "hardware_error", "hardware error: " + _hardware_summary(spec, faults.hardware)
    for mask, kind, text in ((faults.rebooted, "torque_lost", "torque lost: {} rebooted (power dip or brown-out?)"),
                             (faults.torque_off, "torque_lost",
                              "torque lost: {} switched off (by another program, or the servo's own shutdown)"),
                             (faults.watchdog, "bus_watchdog",
                              "bus watchdog: {} stopped (the host was silent longer than the Bus Watchdog time)")):
        if mask is not None and mask.any():
            names = ", ".join(f"{spec.joints[i].name} (ID {spec.joints[i].servo_id})" for i in np.flatnonzero(mask))
            return kind, text.format(names)
    return None


def _comm_counters(robot: Robot) -> dict[str, int]:
    """The bus's counters summed over servos (hardware backends), {} otherwise."""
    bus = getattr(robot, "bus", None)
    stats = getattr(bus, "stats", None)
    if not isinstance(stats, dict):
        return {}
    out = {"retries": 0, "timeouts": 0, "corrupt": 0, "status_errors": 0}
    for st in stats.values():
        for k in out:
            out[k] += int(getattr(st, k, 0))
    out["failed_transactions"] = int(getattr(bus, "failed_transactions", 0))
    return out


def first_read(robot: Robot, tolerance: int) -> State:
    """The state the controller starts from: the watchdog's rule before the first tick.

    A failed read (no reply, a corrupt packet) is tried again, up to ``tolerance`` more times, as the
    loop's watchdog tolerates that many in a row; a fatal one (the port is gone) or one failure too many
    is raised: a controller never starts from a state that was not read.
    """
    for attempt in range(tolerance + 1):
        try:
            return robot.read()
        except CommError as e:
            if e.fatal or attempt == tolerance:
                raise
    raise CommError("no state was read")  # tolerance < 0


def _hardware_summary(spec, bits: np.ndarray) -> str:
    from felis.servos import hardware_error_names

    parts = []
    for i in np.flatnonzero(bits):
        j = spec.joints[i]
        parts.append(f"{j.name} (ID {j.servo_id}) {'+'.join(hardware_error_names(int(bits[i])))}")
    return ", ".join(parts)
