"""The landing controller: velocities integrated into targets, the spine rule, the height estimate, bad
policy output held; on MuJoCo with the landing judge."""

from __future__ import annotations

import numpy as np
import pytest

from felis.controllers.landing import LandingController
from felis.errors import ParameterError
from felis.hal import Imu, State
from felis.learning.landing_eval import LandingSim
from felis.learning.landing_nets import LANDING_HEIGHT_M
from felis.sim.drops import Drop
from felis.spec import load_spec

UP = Imu(np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([0, 0, 9.81]))


def _state(t, q, height=1.0):
    return State(t=t, q=np.asarray(q, float), dq=np.zeros(12), imu=UP, height=height)


def test_velocities_are_integrated_and_clipped():
    spec = load_spec("cat")
    v = np.zeros(12)
    v[spec.index("tail_pitch")] = 2.0
    v[spec.index("fl_roll")] = -100.0
    ctl = LandingController(lambda it, t: v)
    ctl.reset(spec, _state(0.0, np.zeros(12)))
    ctl(_state(0.0, np.zeros(12)))
    cmd = ctl(_state(0.01, np.zeros(12)))
    assert cmd.q[spec.index("tail_pitch")] == pytest.approx(0.02)
    for k in range(2, 100):
        cmd = ctl(_state(0.01 * k, np.zeros(12)))
    assert cmd.q[spec.index("fl_roll")] == pytest.approx(spec.lower[spec.index("fl_roll")])  # clipped at the limit


def test_spine_held_straight_near_the_ground_and_bad_output_held():
    spec = load_spec("cat")
    v = np.zeros(12)
    v[spec.index("spine_pitch")] = 5.0
    out = {"v": v}
    ctl = LandingController(lambda it, t: out["v"])
    ctl.reset(spec, _state(0.0, np.zeros(12)))
    cmd = ctl(_state(0.1, np.zeros(12), height=2.0))
    assert cmd.q[spec.index("spine_pitch")] == pytest.approx(0.5)
    cmd = ctl(_state(0.11, np.zeros(12), height=LANDING_HEIGHT_M - 0.01))
    assert cmd.q[spec.index("spine_pitch")] == 0.0  # the paper's landing rule
    out["v"] = np.full(12, np.nan)
    before = ctl(_state(0.12, np.zeros(12), height=2.0)).q
    after = ctl(_state(0.13, np.zeros(12), height=2.0)).q
    assert np.array_equal(before, after) and ctl.held == 2


def test_height_from_free_fall_when_not_measured():
    spec = load_spec("cat")
    ctl = LandingController(lambda it, t: np.zeros(12), drop_height=3.0)
    ctl.reset(spec, _state(1.0, np.zeros(12), height=None))
    assert ctl.height(_state(1.5, np.zeros(12), height=None)) == pytest.approx(3.0 - 0.5 * 9.81 * 0.25)
    assert ctl.height(_state(10.0, np.zeros(12), height=None)) == 0.0
    no_h = LandingController(lambda it, t: np.zeros(12))
    no_h.reset(spec, _state(0.0, np.zeros(12), height=None))
    with pytest.raises(ParameterError, match="drop height"):
        no_h(_state(0.01, np.zeros(12), height=None))


def test_bad_arguments():
    with pytest.raises(ParameterError, match="policy"):
        LandingController(42)
    with pytest.raises(ParameterError, match="drop height"):
        LandingController(lambda it, t: np.zeros(12), drop_height=-1)
    with pytest.raises(ParameterError, match="cat's joints"):
        LandingController(lambda it, t: np.zeros(12)).reset(load_spec("arm"), _state(0, np.zeros(5)))


def test_on_mujoco_upright_drop_lands_with_a_still_policy():
    sim = LandingSim()
    still = LandingController(lambda it, t: np.zeros(12))
    assert sim.run(Drop(0, 0, 0, 0.3), still).landed
    assert not sim.run(Drop(180, 0, 0, 1.0), still).landed
