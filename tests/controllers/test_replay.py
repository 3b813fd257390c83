"""The replay's two library parts: `ReplayController` (the approach, then the logged commands at loop time ×
speed) run by the real loop on MuJoCo, and `position_error` (per-joint RMS and max against a reference run)."""

from __future__ import annotations

import numpy as np
import pytest

from felis.controllers.pose import min_jerk
from felis.controllers.replay import APPROACH_FRACTION, APPROACH_MIN_S, Commands, ReplayController, approach_time
from felis.errors import ParameterError
from felis.hal import State
from felis.logs.compare import position_error
from felis.loop import run_loop
from felis.sim import MujocoRobot
from felis.spec import load_spec


@pytest.fixture(scope="module")
def arm():
    return load_spec("arm")


def logged(n: int = 5) -> Commands:
    """A log's commands: 0.02 s ticks from t = 0.1 s, joint j follows 0.3·sin(2π·0.5·t + j) (gripper small)."""
    t = 0.1 + 0.02 * np.arange(60)
    q = 0.3 * np.sin(np.pi * t[:, None] + np.arange(n))
    q[:, -1] *= 0.03
    return Commands(t, q)


def state(t: float, q) -> State:
    q = np.asarray(q, dtype=float)
    return State(t=t, q=q, dq=np.zeros_like(q))


def test_commands_keep_finite_increasing_rows():
    t = np.array([0.0, 0.01, 0.01, 0.03, np.nan, 0.05, 0.04])
    q = np.arange(14.0).reshape(7, 2)
    q[3, 1] = np.nan
    c = Commands.from_arrays(t, q)
    assert c.t.tolist() == [0.0, 0.01, 0.05] and c.q[:, 0].tolist() == [0.0, 2.0, 10.0]
    assert c.at(0.03).tolist() == pytest.approx([6.0, 7.0])  # linear between 0.01 and 0.05
    assert c.at(-1.0).tolist() == [0.0, 1.0] and c.at(9.0).tolist() == [10.0, 11.0]  # held at the ends
    with pytest.raises(ParameterError, match="no usable commands"):
        Commands.from_arrays(np.array([0.0]), np.array([[np.nan, 1.0]]))


def test_approach_time_keeps_the_peak_speed(arm):
    q0 = np.zeros(arm.n)
    assert approach_time(arm, q0, q0) == APPROACH_MIN_S
    q1 = np.array([0.0, -1.5, 0.4, 0.7, 0.01])
    T = approach_time(arm, q0, q1)
    s = np.linspace(0, 1, 20001)
    w = np.array([min_jerk(x) for x in s])
    speed = np.abs(np.gradient(w, s * T))[:, None] * np.abs(q1 - q0)  # rad/s (m/s) along the profile
    peak = speed.max(axis=0)
    limit = APPROACH_FRACTION * arm.max_velocity
    assert (peak <= limit * (1 + 1e-6)).all()
    assert peak[1] == pytest.approx(limit[1], rel=1e-3)  # joint2's move sets the time
    assert T > APPROACH_MIN_S


def test_approach_then_log_at_speed(arm):
    c = logged()
    ctl = ReplayController(c, t_from=0.3, t_to=1.1, speed=2.0, approach_s=0.8)
    assert ctl.duration == pytest.approx(0.8 + 0.8 / 2)
    q0 = np.array([0.5, -0.2, 0.1, 0.0, 0.02])
    ctl.reset(arm, state(5.0, q0))
    assert ctl(state(5.0, q0)).q == pytest.approx(q0)  # starts where the robot is
    mid = ctl(state(5.4, q0)).q
    assert mid == pytest.approx(q0 + 0.5 * (c.at(0.3) - q0))  # min-jerk: half way at half time
    assert ctl(state(5.8, q0)).q == pytest.approx(c.at(0.3))  # the first pose when the approach ends
    assert ctl(state(6.0, q0)).q == pytest.approx(c.at(0.3 + 2 * 0.2))  # log time 0.7 s at 0.2 s × speed 2
    assert ctl(state(9.0, q0)).q == pytest.approx(c.at(1.1))  # held at --to
    assert np.isnan(ctl.log_time(0.5)) and ctl.log_time(1.0) == pytest.approx(0.7)
    assert ctl.log_time(1.2) == pytest.approx(1.1) and np.isnan(ctl.log_time(1.21))  # past --to: not compared
    with pytest.raises(ParameterError):
        ReplayController(c, t_from=1.0, t_to=1.0)
    with pytest.raises(ParameterError):
        ReplayController(c, t_from=0.2, t_to=1.0, speed=0.0)


def test_replay_through_the_loop_reproduces_a_run(arm):
    """A run in MuJoCo replayed in MuJoCo from the same start: the same commands, the same motion."""
    c = logged()
    with MujocoRobot(arm) as robot:
        start = robot.read().q
        ref = ReplayController(c, t_from=c.t[0], t_to=c.t[-1], approach_s=0.5)
        trace_t, trace_q = [], []
        run_loop(robot, ref, duration=ref.duration, rate_hz=50, monitors=[lambda s, cmd: (trace_t.append(s.t),
                                                                                         trace_q.append(s.q))])
    with MujocoRobot(arm) as robot:
        assert robot.read().q == pytest.approx(start)
        again = ReplayController(c, t_from=c.t[0], t_to=c.t[-1], approach_s=0.5)
        t2, q2 = [], []
        report = run_loop(robot, again, duration=again.duration, rate_hz=50,
                          monitors=[lambda s, cmd: (t2.append(s.t), q2.append(s.q))])
    assert report.ok and report.safety["step_clamps"] == 0
    tau_ref = ref.log_time(np.array(trace_t) - ref.t0)
    tau = again.log_time(np.array(t2) - again.t0)
    same = position_error(tau_ref[np.isfinite(tau_ref)], np.array(trace_q)[np.isfinite(tau_ref)], tau,
                          np.array(q2), list(arm.names))
    assert same.samples >= 55 and np.nanmax(same.max) < 1e-9  # MuJoCo is deterministic
    moved = np.ptp(np.array(q2)[:, :4], axis=0)
    assert (moved > 0.1).all()  # the arm followed the log (0.3 rad sines)


def test_position_error_rms_and_max():
    ref_t = np.linspace(0.0, 2.0, 201)
    ref_q = np.stack([np.sin(ref_t), np.cos(ref_t)], -1)
    tau = np.concatenate([[np.nan, np.nan], np.linspace(0.0, 2.0, 101), [2.5]])  # approach, window, past the end
    q = np.stack([np.sin(np.nan_to_num(tau)) + 0.01, np.cos(np.nan_to_num(tau))], -1)
    q[10, 1] += 0.2  # one bad tick on joint b
    c = position_error(ref_t, ref_q, tau, q, ["a", "b"], ["revolute", "prismatic"])
    assert c.samples == 101 and c.span == (0.0, 2.0)
    assert c.rms[0] == pytest.approx(0.01, rel=1e-6) and c.max[0] == pytest.approx(0.01, rel=1e-6)
    assert c.max[1] == pytest.approx(0.2, abs=1e-4) and c.rms[1] == pytest.approx(0.2 / np.sqrt(101), rel=1e-2)
    d = c.as_dict()
    assert d["joints"]["b"]["unit"] == "m" and d["joints"]["a"]["rms"] == pytest.approx(0.01)
    ref_q[:, 1] = np.nan  # a joint the reference never measured: no figure rather than a wrong one
    c = position_error(ref_t, ref_q, tau, q, ["a", "b"])
    assert np.isnan(c.rms[1]) and c.as_dict()["joints"]["b"]["rms"] is None
