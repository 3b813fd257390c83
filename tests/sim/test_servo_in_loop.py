"""Servo-in-the-loop: the same controller run through the whole hardware path (DynamixelRobot →
dynamixel-sdk → pseudo-terminal → byte-level virtual servos → MuJoCo) and on MuJoCo directly ends
in the same place, within 2 ticks' worth of motion.

"2 ticks' worth of motion" for joint i is twice the largest per-tick change of q_i in the direct run
(plus one encoder tick for quantisation). The controller moves until the last tick (a 1 s min-jerk
move to ``sit`` in a 1 s run), so a lagging or mis-scaled bus path would show. The virtual bus runs
in its own process, paced by the wall clock like real servos; its physics starts when torque comes
on, as the direct run's does.
"""

from __future__ import annotations

import numpy as np
import pytest

from felis.controllers import PoseController
from felis.servos import RAD_PER_TICK
from felis.spec import load_spec

RATE, DURATION = 50.0, 1.0


class _Record:
    def __init__(self):
        self.q: list[np.ndarray] = []

    def __call__(self, state, command):
        self.q.append(state.q.copy())


@pytest.mark.parametrize("robot", ["cat", "arm"])
def test_bus_run_ends_within_two_ticks_of_the_direct_run(robot, sim_robot, virtual_bus, dxl_robot, run):
    spec = load_spec(robot)
    direct, through = _Record(), _Record()
    rep_d = run(sim_robot(robot), PoseController("sit", duration=DURATION), DURATION, rate=RATE, monitors=[direct],
                log=False).report
    hw = dxl_robot(virtual_bus(robot, sim=True, process=True))  # felis.testing: closed, then stopped, at the end
    rep_b = run(hw, PoseController("sit", duration=DURATION), DURATION, rate=RATE, monitors=[through],
                log=False).report
    assert rep_d.ok and rep_b.ok and rep_b.stale_ticks == 0 and rep_b.ticks == rep_d.ticks
    qd, qb = rep_d.final_state.q, rep_b.final_state.q
    steps = np.abs(np.diff(np.array(direct.q), axis=0)).max(axis=0)
    budget = 2.0 * steps + RAD_PER_TICK * np.array([j.m_per_rad for j in spec.joints])
    err = np.abs(qb - qd)
    moved = np.abs(qd - np.array(direct.q[0])) > 0.05
    assert moved.any(), "the controller should move some joints"
    print(f"\n{robot}: max |q_bus - q_direct| = {err.max():.4f} rad; max error/budget = {(err / budget).max():.2f}")
    assert np.all(err <= budget), {n: (round(e, 4), round(b, 4)) for n, e, b in zip(spec.names, err, budget,
                                                                                       strict=True) if e > b}


def test_gains_written_on_the_bus_reach_the_simulated_joint(virtual_bus, dxl_robot, run):
    """The firmware controller a servo's memory sets drives its MuJoCo joint (`MujocoBackend._sync_gains`):
    the arm's shoulder, loaded by gravity in ``stand``, sags with the integral gain written to 0 over the bus and
    comes back onto its goal when Position I is written again."""
    spec = load_spec("arm")
    i = spec.names.index("joint2")
    vb = virtual_bus("arm", sim=True)
    hw = dxl_robot(vb)
    bus, sid = hw.bus, spec.joints[i].servo_id
    robot = vb.bus.backend.robot
    hw.arm()
    run(hw, PoseController("stand", duration=0.5), 1.0, rate=RATE, log=False)
    assert robot._ctl[i].ki > 0  # the description's 800/100/100, written by DynamixelRobot

    def error_after(seconds: float) -> float:
        run(hw, PoseController("stand", duration=0.1), seconds, rate=RATE, log=False)
        return abs(float(hw.read().q[i] - goal[i]))

    goal = spec.poses["stand"].copy()
    bus.write(sid, "position_i_gain", 0, raw=True)
    sag = error_after(1.5)
    assert robot._ctl[i].ki == 0.0 and robot.model.actuator_gainprm[robot._acts[i].integral, 0] == 0.0
    bus.write(sid, "position_i_gain", 400, raw=True)
    held = error_after(3.0)
    print(f"\njoint2 under gravity: {sag / RAD_PER_TICK:.1f} ticks from its goal without I, "
          f"{held / RAD_PER_TICK:.1f} with")
    assert sag > 3 * RAD_PER_TICK and held < sag / 3


def test_a_lockstep_bus_steps_with_the_loop_and_its_clock_is_the_simulations(virtual_bus, dxl_robot, run):
    """``lockstep=True``: no thread steps the bus's simulation; the `Lockstep` robot's ``advance`` does, one tick at a
    time, and its states carry the simulated time. Nothing moves while the host waits, and nothing before torque
    first comes on (the operator still holds the robot)."""
    import time

    from felis.errors import ParameterError
    from felis.sim.servo_in_loop import Lockstep

    vb = virtual_bus("arm", sim=True, lockstep=True)
    hw = dxl_robot(vb)
    backend = vb.bus.backend
    robot = Lockstep(hw, backend)
    robot.advance(0.02)
    assert backend.sim_t == 0.0 and robot.read().t == 0.0  # held: no time passes
    q0 = backend.robot.read().q.copy()
    rep = run(robot, PoseController("sit", duration=0.5), 0.5, rate=RATE, log=False).report
    assert rep.ok and rep.ticks == 25 and rep.final_state.t == pytest.approx(24 / RATE, abs=1e-9)
    assert backend.sim_t == pytest.approx(25 / RATE, abs=1e-9)  # whole ticks, whatever the host's lag
    q = backend.robot.read().q.copy()
    assert np.abs(q - q0).max() > 0.05  # it moved toward sit
    time.sleep(0.2)  # the wall clock moves; the simulation does not
    assert np.array_equal(backend.robot.read().q, q) and backend.sim_t == pytest.approx(25 / RATE, abs=1e-9)
    with pytest.raises(ParameterError, match="lockstep bus"):
        Lockstep(hw, virtual_bus("arm", sim=True).bus.backend)
    with pytest.raises(ParameterError, match="needs sim=True"):
        virtual_bus("arm", lockstep=True)
