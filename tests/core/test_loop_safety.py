"""Control loop and safety layer on the real MuJoCo cat: clamps, non-finite hold, watchdog, timing."""

import time

import numpy as np
import pytest

from felis.controllers import PoseController
from felis.errors import CommError, LifecycleError, ParameterError
from felis.hal import Command, Faults, Lifecycle, State
from felis.loop import run_loop
from felis.safety import SafetyConfig, SafetyLayer
from felis.sim import MujocoRobot
from felis.spec import load_spec

CAT = load_spec("cat")


@pytest.fixture
def cat():
    with MujocoRobot(CAT) as robot:
        yield robot


class Scripted:
    """Controller returning a scripted target per tick (the last one repeats)."""

    name = "scripted"

    def __init__(self, targets):
        self.targets = targets
        self.k = 0

    def reset(self, spec, state):
        self.k = 0

    def __call__(self, state):
        q = self.targets[min(self.k, len(self.targets) - 1)]
        self.k += 1
        return Command(q=np.array(q, dtype=float))


class Recorder:
    def __init__(self):
        self.sent = []

    def __call__(self, state, command):
        self.sent.append(command.q.copy())


# ------------------------------------------------------------------------- safety layer alone
def test_soft_limits_and_max_step():
    layer = SafetyLayer(CAT, dt=0.01, config=SafetyConfig(soft_margin=0.1))
    layer.reset(np.zeros(12))
    far = np.full(12, 5.0)
    out = layer.filter(Command(q=far))
    step = CAT.max_velocity * 0.01
    assert out.q == pytest.approx(step)  # rate-limited from the present position
    assert layer.counters.limit_clamps == 1 and layer.counters.step_clamps == 1
    q = out.q
    for _ in range(500):
        layer.sent(Command(q=q))
        q = layer.filter(Command(q=far)).q
    assert q == pytest.approx(CAT.upper - 0.1)  # converges onto the soft limit, never past it


def test_a_late_tick_may_catch_up_as_far_as_the_servo_could_move():
    """Given the robot's time of each command, the max step is a speed (`felis.safety`, 3): a tick 3 ticks after the
    last command sent may move 3 steps, at most ``max_late_ticks`` steps; on time (rounding included) it is one step,
    and a tick that held (no `filter`) keeps the time of the target it repeats."""
    layer = SafetyLayer(CAT, dt=0.001, config=SafetyConfig(max_late_ticks=5))  # 1 kHz: 11 steps stay in range
    step = CAT.max_velocity * 0.001
    far = CAT.upper
    layer.reset(np.zeros(12), t=1.0)
    out = layer.filter(Command(q=far), t=1.001 + 1e-12)  # on time, a float's rounding late
    assert out.q == pytest.approx(step)
    layer.sent(out)
    out = layer.filter(Command(q=far), t=1.005)  # 4 ticks since the last command sent
    assert out.q == pytest.approx(5 * step)
    layer.sent(out)
    layer.sent(out)  # a held tick: its read failed, no filter
    out = layer.filter(Command(q=far), t=1.025)  # 20 ticks late: capped at 5
    assert out.q == pytest.approx(10 * step)
    layer.sent(out)
    assert layer.filter(Command(q=far), t=1.02).q == pytest.approx(11 * step)  # a clock gone back: one step
    assert layer.filter(Command(q=far)).q == pytest.approx(11 * step)  # no time: one step
    assert np.all(11 * step < CAT.upper)
    with pytest.raises(ValueError, match="max_late_ticks"):
        SafetyConfig(max_late_ticks=0.5)


def test_nonfinite_holds_last_good_and_counts():
    layer = SafetyLayer(CAT, dt=0.01)
    layer.reset(np.zeros(12))
    good = layer.filter(Command(q=np.full(12, 0.05)))
    layer.sent(good)
    for bad in (np.full(12, np.nan), np.r_[np.zeros(11), np.inf], np.zeros(5)):
        assert layer.filter(Command(q=bad)) is good
    bad_speed = Command(q=np.zeros(12), dq_max=np.full(12, np.nan))
    assert layer.filter(bad_speed) is good
    assert layer.counters.nonfinite_held == 4
    assert layer.events[0][0] == "nonfinite_held"


def test_stiffness_is_clamped_to_compliance_and_a_bad_one_is_held():
    """`Command.stiffness`: within [MIN_STIFFNESS, 1] (soften, never stiffen past the description, never limp);
    non-finite or of the wrong shape holds the last good command, like a bad target."""
    from felis.hal import MIN_STIFFNESS

    layer = SafetyLayer(CAT, dt=0.01)
    layer.reset(np.zeros(12))
    out = layer.filter(Command(q=np.zeros(12), stiffness=np.r_[0.0, 2.0, 0.5, np.ones(9)]))
    assert out.stiffness[:3] == pytest.approx([MIN_STIFFNESS, 1.0, 0.5])
    layer.sent(out)
    for bad in (np.full(12, np.nan), np.ones(5)):
        assert layer.filter(Command(q=np.zeros(12), stiffness=bad)) is out
    assert layer.counters.nonfinite_held == 2
    assert layer.filter(Command(q=np.zeros(12))).stiffness is None  # None: every joint as described


def test_reset_clamps_present_into_soft_range():
    layer = SafetyLayer(CAT, dt=0.01, config=SafetyConfig(soft_margin=0.2))
    layer.reset(CAT.upper)
    assert layer.last.q == pytest.approx(CAT.upper - 0.2)


# ------------------------------------------------------------------------- in the loop
def test_loop_clamps_what_reaches_the_robot(cat):
    rec = Recorder()
    report = run_loop(cat, Scripted([np.full(12, 9.0)]), duration=0.5, monitors=[rec])
    sent = np.array(rec.sent)
    assert np.all(sent <= CAT.upper + 1e-12) and np.all(sent >= CAT.lower - 1e-12)
    assert np.all(np.abs(np.diff(sent, axis=0)) <= CAT.max_velocity * 0.01 + 1e-12)
    assert report.safety["limit_clamps"] == 50 and report.safety["step_clamps"] > 0
    assert sent[-1] == pytest.approx(CAT.upper)


def test_loop_nonfinite_command_holds_and_counts(cat):
    targets = [np.full(12, 0.02 * k) for k in range(10)]
    targets[4] = np.full(12, np.nan)
    targets[5] = np.r_[np.zeros(11), -np.inf]
    rec = Recorder()
    report = run_loop(cat, Scripted(targets), duration=0.1, monitors=[rec])
    assert report.ok and report.ticks == 10
    assert report.safety["nonfinite_held"] == 2
    assert np.array_equal(rec.sent[4], rec.sent[3]) and np.array_equal(rec.sent[5], rec.sent[3])
    assert np.all(np.isfinite(np.array(rec.sent)))


class FlakyCat(MujocoRobot):
    """The MuJoCo cat whose reads fail on chosen ticks (a bus losing replies)."""

    def __init__(self, fail_ticks):
        super().__init__(CAT)
        self.fail_ticks, self.reads = set(fail_ticks), 0

    def _read(self):
        self.reads += 1
        if self.reads in self.fail_ticks:
            raise CommError(f"no status packet from servo 5 (read {self.reads})")
        return super()._read()


def test_watchdog_tolerates_a_few_read_failures():
    with FlakyCat(fail_ticks=[10, 11, 12, 30]) as robot:
        report = run_loop(robot, PoseController("stand"), duration=0.5)
    assert report.ok and report.ticks == 50 and report.read_failures == 4


def test_watchdog_disarms_after_too_many_read_failures():
    robot = FlakyCat(fail_ticks=range(20, 40))
    with robot:
        report = run_loop(robot, PoseController("stand"), duration=1.0,
                          safety=SafetyConfig(read_fail_tolerance=3), keep_armed=True)
        assert not report.ok and report.stopped.startswith("watchdog: 4 consecutive read failures")
        assert "no status packet" in report.stopped
        assert robot.lifecycle is Lifecycle.CONNECTED  # disarmed despite keep_armed
        assert np.all(robot.model.actuator_gainprm[:, 0] == 0)  # torque off
        assert report.ticks < 25


def test_the_first_reads_are_tried_again_as_the_watchdog_would():
    robot = FlakyCat(fail_ticks=[1, 3, 4, 5])  # read 1 before arming, reads 3–5 once armed
    with robot:
        report = run_loop(robot, PoseController("stand"), duration=0.1)
    assert report.ok and report.ticks == 10 and robot.reads == 6 + 10


def test_failure_right_after_arming_leaves_torque_off():
    robot = FlakyCat(fail_ticks=[2, 3, 4, 5])  # read 1: before arming; reads 2–5: once armed, one too many
    with robot:
        with pytest.raises(CommError, match="read 5"):
            run_loop(robot, PoseController("stand"), duration=1.0, safety=SafetyConfig(read_fail_tolerance=3))
        assert robot.lifecycle is Lifecycle.CONNECTED
        assert np.all(robot.model.actuator_gainprm[:, 0] == 0)


def test_watchdog_disarms_on_overruns_with_wall_clock(cat):
    class Slow(PoseController):
        def __call__(self, state):
            time.sleep(0.012)
            return super().__call__(state)

    report = run_loop(cat, Slow("hold"), duration=1.0, rate_hz=100, clock="wall",
                      safety=SafetyConfig(overrun_tolerance=5))
    assert report.stopped == "watchdog: 6 consecutive loop overruns"
    assert report.ticks == 6 and report.timing.overruns == 6
    assert cat.lifecycle is Lifecycle.CONNECTED


def test_wall_clock_paces_real_time(cat):
    report = run_loop(cat, PoseController("hold"), duration=0.3, rate_hz=50, clock="wall")
    assert report.ok and report.ticks == 15
    assert 0.28 <= report.wall_time_s <= 0.45
    assert report.timing.overruns == 0


def test_controller_exception_disarms_and_propagates(cat):
    class Broken(PoseController):
        def __call__(self, state):
            if state.t > 0.05:
                raise RuntimeError("controller bug")
            return super().__call__(state)

    with pytest.raises(RuntimeError, match="controller bug"):
        run_loop(cat, Broken("hold"), duration=1.0, keep_armed=True)
    assert cat.lifecycle is Lifecycle.CONNECTED
    assert np.all(cat.model.actuator_gainprm[:, 0] == 0)


def test_timing_report(cat):
    report = run_loop(cat, PoseController("stand"), duration=1.0)
    t = report.timing
    assert report.ticks == 100 and report.sim_time_s == pytest.approx(1.0)
    assert 0 < t.mean_ms <= t.p99_ms <= t.max_ms and t.period_ms == 10.0
    d = report.as_dict()
    assert d["ok"] and d["timing"]["overruns"] == t.overruns


@pytest.mark.parametrize("kw", [{"duration": 0}, {"duration": float("nan")}, {"duration": 1, "rate_hz": 0},
                                {"duration": 1, "clock": "lunar"}])
def test_bad_loop_parameters(cat, kw):
    with pytest.raises(ParameterError):
        run_loop(cat, PoseController("hold"), **kw)


def test_lifecycle_rules(cat):
    with pytest.raises(LifecycleError, match="cannot write while connected"):
        cat.write(Command(q=np.zeros(12)))
    cat.arm()
    with pytest.raises(LifecycleError, match="cannot arm while armed"):
        cat.arm()
    with pytest.raises(ValueError, match="3 positions"):
        cat.write(Command(q=np.zeros(3)))
    cat.close()
    assert cat.lifecycle is Lifecycle.DISCONNECTED
    with pytest.raises(LifecycleError):
        cat.read()


def test_arming_does_not_jump(cat):
    from felis.sim.scenarios import set_pose

    pose = CAT.pose("sit")
    set_pose(cat, pose)
    cat.arm()
    assert cat.data.ctrl == pytest.approx(cat.data.qpos[cat._qadr])  # goal = present


def test_exception_in_with_block_turns_torque_off():
    robot = MujocoRobot(CAT)
    with pytest.raises(KeyError):
        with robot:
            robot.arm()
            raise KeyError("operator code failed")
    assert robot.lifecycle is Lifecycle.DISCONNECTED


def test_logged_events_match_counters_through_read_failures(tmp_path):
    from felis.logs.reader import read_log
    from felis.logs.runlog import RunLog

    robot = FlakyCat(fail_ticks=[6, 7])
    with robot, RunLog(tmp_path / "r.mcap", CAT) as log:
        report = run_loop(robot, Scripted([np.full(12, 9.0)]), duration=0.2, log=log)
    data = read_log(tmp_path / "r.mcap")
    kinds = [e["kind"] for e in data.events]
    assert kinds.count("limit_clamp") == report.safety["limit_clamps"] == 18  # 20 ticks, 2 without a command
    assert kinds.count("read_failed") == report.read_failures == 2


class ThirdPartyCat(MujocoRobot):
    """The MuJoCo cat as a robot of another vendor would report it: a `State` without ``faults`` (the
    default, no faults) or with ``faults=None``, and the loop's log and servo-stop checks must cope."""

    def __init__(self, explicit_none: bool):
        super().__init__(CAT)
        self.explicit_none = explicit_none

    def _read(self):
        s = super()._read()
        fields = dict(t=s.t, q=s.q, dq=s.dq, effort=s.effort, imu=s.imu, contacts=s.contacts, height=s.height)
        return State(**fields, faults=None) if self.explicit_none else State(**fields)


@pytest.mark.parametrize("explicit_none", [False, True])
def test_a_robot_that_reports_no_faults_runs(explicit_none, tmp_path):
    from felis.logs.runlog import RunLog

    assert not State(t=0.0, q=np.zeros(2), dq=np.zeros(2)).faults.any
    with ThirdPartyCat(explicit_none) as robot, RunLog(tmp_path / "r.mcap", robot.spec) as log:
        report = run_loop(robot, PoseController("stand"), duration=0.3, log=log)
    assert report.ok and report.ticks == 30


class FaultingCat(MujocoRobot):
    """The MuJoCo cat reporting one unchanged `Faults` for some ticks (as the simulation does), then a new one
    with a servo's hardware error (as the Dynamixel backend does when its status changes)."""

    def __init__(self, after_ticks: int):
        super().__init__(CAT)
        self.after_ticks, self.reads = after_ticks, 0

    def _read(self):
        self.reads += 1
        if self.reads == self.after_ticks:
            hw = np.zeros(CAT.n, dtype=np.int32)
            hw[2] = 0x20  # overload
            self._faults = Faults(hardware=hw)
        return super()._read()


def test_a_new_faults_object_is_checked_though_the_last_one_passed():
    """The loop checks a `Faults` it has already seen once (the simulation reports the same object every tick);
    a backend whose faults change reports a new one, and that one stops the run."""
    with FaultingCat(after_ticks=20) as robot:
        report = run_loop(robot, PoseController("stand"), duration=0.5)
    assert report.stopped.startswith("hardware error") and CAT.joints[2].name in report.stopped
    assert report.ticks == 20 - 2 - 1  # two reads before the first tick (before and after arming)


def test_the_hot_dataclasses_stay_frozen_dataclasses():
    """`felis.hal` gives State, Imu, Truth and Command a faster ``__init__``: same signature, defaults, default
    factories, equality, hashing rules and frozenness as the one dataclasses writes."""
    import dataclasses
    import inspect

    from felis.hal import Imu, Truth

    for cls in (State, Command, Imu, Truth):
        params = inspect.signature(cls).parameters
        assert list(params) == [f.name for f in dataclasses.fields(cls)]
        for f in dataclasses.fields(cls):
            if f.default is not dataclasses.MISSING:
                assert params[f.name].default is f.default
    q = np.arange(3.0)
    s = State(0.5, q, q)
    assert s.effort is None and s.truth is None and not s.faults.any
    assert State(0.5, q, q).faults is not s.faults  # a new default Faults for each, as the factory gives
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.t = 1.0
    assert dataclasses.replace(s, t=2.0).t == 2.0 and dataclasses.replace(s, t=2.0).q is q
    c = Command(q=q)
    assert Command(q=(1.0, 2.0)) == Command(q=(1.0, 2.0)) != Command(q=(1.0, 3.0))
    assert hash(Command(q=(1.0, 2.0))) == hash(Command(q=(1.0, 2.0)))  # frozen and eq: hashable by value
    assert repr(c) == f"Command(q={q!r}, dq_max=None, torque=None, stiffness=None)"
    with pytest.raises(TypeError):
        Command()  # q is required
    with pytest.raises(TypeError):
        State(0.0, q, q, bogus=1)


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the ignored Interrupted
def test_a_signal_lost_in_a_finaliser_still_stops_the_run(cat):
    """Python ignores an exception raised in a finaliser: a Ctrl-C whose handler runs inside a ``__del__`` raises
    nothing. `felis.shutdown` counts it, and the loop stops at its next tick as interrupted, torque off."""
    import gc
    import os
    import signal

    from felis.shutdown import signals

    class Finaliser:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)  # the handler runs here, its Interrupted is ignored
            for _ in range(1000):
                pass

    def monitor(state, command):
        monitor.ticks += 1
        if monitor.ticks == 3:
            Finaliser()  # made and collected at once
            gc.collect()

    monitor.ticks = 0
    with signals():
        report = run_loop(cat, PoseController("hold"), duration=1.0, rate_hz=50.0, monitors=[monitor])
    assert report.stopped == "interrupted (SIGINT)" and report.ticks == 3
    assert cat.lifecycle is not Lifecycle.ARMED
