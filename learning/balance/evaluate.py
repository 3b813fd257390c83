"""Push experiments on the simulated cat: one push per episode, the monitor's verdicts against ground
truth, protective reactions, and demonstrations for the strategy selector (seed 004).

An episode: the cat starts at rest in its ``stand`` pose; the base controller holds the stance
(phase ``stand``) or trots in place (phase ``step``); `felis.sim.pushes.Pusher` applies the push at
``t_s``; the run lasts until ``t_s + FALL_WINDOW_S``. The base runs inside a
`felis.controllers.reactions.ReactiveController` with a `BalanceMonitor`, so the alarm time, the
strategy and the selector's features come from the very controller that reacts.

Metrics over a set of pushes (`summarise`):

* recall: falls whose alarm came at or before the fall / falls;
* false_alarm_rate: pushes that did not end in a fall but raised an alarm / pushes without a fall;
* median_lead_s: median of (fall time − alarm time) over detected falls;
* fall_rate: falls / pushes.

With a reaction active, a push the reaction saved raised an alarm and did not fall: it counts as a
false alarm. The monitor's detection figures are therefore taken with ``reaction="none"``.

Demonstrations (`demonstrate`): every push that calls for a reaction is re-run with each strategy; the
outcome score is 1 + (time left in the window at the fall)/window for a fall (an early fall is worse),
else the peak tilt / 60° (< 1). Lower is better.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from felis.controllers.balance import BalanceMonitor
from felis.controllers.pose import PoseController
from felis.controllers.reactions import FEATURES, REACTIONS, ReactiveController
from felis.learning.common.evaluator import run_jobs, worker_count
from felis.loop import run_loop
from felis.scenarios.push import FALL_WINDOW_S, Push
from felis.scenarios.verdicts import FALL_TILT_DEG
from felis.sim.pushes import FallDetector, Pusher, ThreadedPushTest
from felis.spec import load_spec


@dataclass
class PushOutcome:
    push: Push
    reaction: str
    fell: bool
    fall_t: float | None
    why: str
    alarm: bool
    alarm_t: float | None
    strategy: str | None
    max_tilt_deg: float
    react_t: float | None = None
    features: np.ndarray | None = None
    margins: np.ndarray | None = field(default=None, repr=False)  # (ticks, 3): t, margin, alarm

    @property
    def detected(self) -> bool:
        return self.fell and self.alarm_t is not None and self.alarm_t <= self.fall_t + 1e-9

    @property
    def lead_s(self) -> float | None:
        return self.fall_t - self.alarm_t if self.detected else None

    @property
    def score(self) -> float:
        """Outcome for the demonstrations: lower is better (module doc)."""
        if self.fell:
            return 1.0 + max(0.0, self.push.t_s + FALL_WINDOW_S - self.fall_t) / FALL_WINDOW_S
        return min(self.max_tilt_deg / FALL_TILT_DEG, 0.999)

    def as_dict(self) -> dict:
        r = lambda v: None if v is None else round(float(v), 4)  # noqa: E731
        return {**self.push.as_dict(), "fell": self.fell, "fall_t_s": r(self.fall_t), "why": self.why or None,
                "alarm": self.alarm, "alarm_t_s": r(self.alarm_t), "lead_s": r(self.lead_s),
                "strategy": self.strategy, "max_tilt_deg": r(self.max_tilt_deg)}


class _Trace:
    """Loop monitor keeping (t, margin, alarm) of the reactive controller's assessments."""

    def __init__(self, controller: ReactiveController):
        self.controller, self.rows = controller, []

    def __call__(self, state, command) -> None:
        a = self.controller.assessment
        if a is not None:
            self.rows.append((a.t, a.margin, float(a.alarm)))


def _base(phase: str):
    """The controller that runs before and after the push: holding the stance, or trotting in place."""
    if phase == "step":
        from felis.controllers.stepping import SteppingController

        return SteppingController()
    return PoseController("stand", duration=0.2)


class PushSim:
    """A reusable simulated cat for push episodes (one compiled model, reset between pushes)."""

    def __init__(self, robot: str = "cat", monitor: dict | None = None):
        from felis.sim import MujocoRobot
        from felis.sim.bodymodel import load_body_model

        self.spec = load_spec(robot)
        self.body = load_body_model(self.spec)
        self.monitor_options = dict(monitor or {})  # BalanceMonitor's own defaults unless given
        self.robot = MujocoRobot(self.spec)
        self.robot.connect()

    def run(self, p: Push, reaction: str | Callable = "none", trace: bool = False, monitors=(), log=None
            ) -> PushOutcome:
        """One push episode (module doc); ``monitors``: extra loop monitors (e.g. a video recorder); ``log``: a
        `felis.logs.runlog.RunLog` of the run (``felis eval balance --live``), with ``/balance`` and ``/phase``."""
        from felis.sim.scenarios import set_pose

        robot = self.robot
        robot.reset()
        set_pose(robot, self.spec.pose("stand"))
        monitor = BalanceMonitor(self.body, **self.monitor_options)
        ctl = ReactiveController(_base(p.phase), monitor, reaction)
        fall = FallDetector(robot, tuple(self.spec.sensors.contacts))
        tr = _Trace(ctl) if trace else None
        monitors = [Pusher(robot, p), fall, *([tr] if tr is not None else []), *monitors, *_skills(log, ctl)]
        run_loop(robot, ctl, duration=p.t_s + FALL_WINDOW_S, monitors=monitors, keep_armed=True,
                 log=log).raise_if_interrupted()
        return _outcome(p, reaction, ctl, fall, tr)

    def monitor_defaults(self) -> dict:
        """The monitor's thresholds in use (its defaults, with this sim's overrides)."""
        m = BalanceMonitor(self.body, **self.monitor_options)
        return {"on_m": m.on_m, "warn_m": m.warn_m, "on_ticks": m.on_ticks, "gait_ticks": m.gait_ticks}

    def close(self) -> None:
        self.robot.close()


def _outcome(p: Push, reaction, ctl: ReactiveController, fall: FallDetector, tr: _Trace | None) -> PushOutcome:
    name = reaction if isinstance(reaction, str) else "selector"
    return PushOutcome(p, name, fall.t is not None, fall.t, fall.why, ctl.alarm_t is not None, ctl.alarm_t,
                       ctl.strategy, fall.max_tilt_deg, ctl.react_t, ctl.features,
                       np.array(tr.rows) if tr is not None else None)


def _skills(log, controller) -> list:
    """The log's ``/balance`` and ``/phase`` channels as a loop monitor (none without a log)."""
    from felis.logs.skills import skill_channels

    found = skill_channels(log, controller)
    return [] if found is None else [found]


def run_push_virtual(p: Push, reaction: str | Callable = "none", *, rate_hz: float = 50.0,
                     monitor: dict | None = None, trace: bool = False, log=None, lockstep: bool = False) -> PushOutcome:
    """One push through the whole hardware path: `DynamixelRobot` → dynamixel-sdk → pseudo-terminal →
    virtual servos backed by MuJoCo, the IMU through its UART-RVC emulator, on the wall clock. The
    monitor has no simulator truth here: it estimates the CoM from the servos' angles and the IMU
    (`felis.bodymodel`), as on the real cat. The push and the fall detector act on the bus's model. ``log``: a
    `felis.logs.runlog.RunLog` of the run (its scene from the body model: `felis.sim.scene.hardware_view`).
    ``lockstep``: the bus's simulation steps with the loop's ticks and the loop's clock is the simulation's
    (`felis.sim.servo_in_loop.Lockstep`): the times measured do not depend on how loaded the machine is."""
    from felis.drivers.dynamixel.robot import DynamixelRobot
    from felis.sim.bodymodel import load_body_model
    from felis.sim.servo_in_loop import Lockstep, virtual_bus

    spec = load_spec("cat")
    body = load_body_model(spec)
    with virtual_bus(spec, sim=True, lockstep=lockstep) as bus:
        test = ThreadedPushTest(bus.backend.robot, p, tuple(spec.sensors.contacts))
        with DynamixelRobot(spec, bus.port, imu_port=bus.imu_port) as hw:
            robot = Lockstep(hw, bus.backend) if lockstep else hw
            ctl = ReactiveController(_base(p.phase), BalanceMonitor(body, **(monitor or {})), reaction)
            tr = _Trace(ctl) if trace else None
            run_loop(robot, ctl, duration=p.t_s + FALL_WINDOW_S, rate_hz=rate_hz, clock="wall", log=log,
                     monitors=[test] + ([tr] if tr is not None else []) + _skills(log, ctl)).raise_if_interrupted()
    fall = test.detector
    fall.t = test.fall_t
    return _outcome(p, reaction, ctl, fall, tr)


# ----------------------------------------------------------------------------------- parallel runs
_SIM: PushSim | None = None


def _init(monitor: dict | None, selector_path: str | None) -> None:
    """Per worker process: its own model, and the selector ("" = none needed, None = the shipped one)."""
    global _SIM, _SELECTOR
    _SIM = PushSim(monitor=monitor)
    _SELECTOR = _load_selector(selector_path) if selector_path != "" else None


_SELECTOR = None


def _load_selector(path: str | None):
    from felis.learning.balance.selector import load_selector

    return load_selector(path, feature_names=FEATURES)


def _one(args) -> PushOutcome:
    p, reaction, trace = args
    return _SIM.run(p, _SELECTOR if reaction == "selector" else reaction, trace)


def run_pushes(pushes: Sequence[Push], reaction: str = "none", *, selector: str | None = None,
               workers: int | None = None, monitor: dict | None = None, trace: bool = False,
               progress: Callable[[int], None] | None = None) -> list[PushOutcome]:
    """Run every push with ``reaction`` (a name of `REACTIONS` or ``"selector"`` with a selector file),
    in ``workers`` processes (default: every core). Results are in push order and identical whatever
    the number of workers (each episode is deterministic and independent)."""
    if reaction not in (*REACTIONS, "selector"):
        from felis.errors import ParameterError

        raise ParameterError(f"unknown reaction {reaction!r}; known: {', '.join(REACTIONS)}, selector")
    workers = worker_count(workers, len(pushes))
    jobs = [(p, reaction, trace) for p in pushes]
    if reaction == "selector":
        _load_selector(selector)  # a bad selector file fails here, once, as one line
    else:
        selector = ""
    return run_jobs(_one, jobs, workers, _init, (monitor, selector), progress=progress)


def summarise(outcomes: Sequence[PushOutcome]) -> dict:
    """recall, false_alarm_rate, median_lead_s, fall_rate (module doc) and counts."""
    falls = [o for o in outcomes if o.fell]
    safe = [o for o in outcomes if not o.fell]
    detected = [o for o in falls if o.detected]
    leads = [o.lead_s for o in detected]
    ratio = lambda a, b: round(len(a) / len(b), 4) if b else None  # noqa: E731
    return {
        "pushes": len(outcomes), "falls": len(falls),
        "recall": ratio(detected, falls),
        "false_alarm_rate": ratio([o for o in safe if o.alarm], safe),
        "median_lead_s": round(float(np.median(leads)), 4) if leads else None,
        "fall_rate": ratio(falls, outcomes),
    }


def demonstrate(pushes: Sequence[Push], workers: int | None = None, monitor: dict | None = None,
                progress: Callable[[int], None] | None = None):
    """Demonstrations for the selector: (features (n, m), scores (n, len(REACTIONS)), pushes used).

    Each push is first run with ``none``; the ones that call for a reaction (a warning or an alarm) are
    re-run with every strategy. The features are the state at that first reaction, the same in every
    run of a push (the runs are identical up to it).
    """
    base = run_pushes(pushes, "none", workers=workers, monitor=monitor, progress=progress)
    alarmed = [o for o in base if o.react_t is not None and o.features is not None
               and np.all(np.isfinite(o.features))]
    scores = np.zeros((len(alarmed), len(REACTIONS)))
    for k, name in enumerate(REACTIONS):
        res = [o for o in alarmed] if name == "none" else run_pushes([o.push for o in alarmed], name,
                                                                       workers=workers, monitor=monitor,
                                                                       progress=progress)
        scores[:, k] = [o.score for o in res]
    X = np.array([o.features for o in alarmed]).reshape(len(alarmed), len(FEATURES))
    return X, scores, [o.push for o in alarmed]
