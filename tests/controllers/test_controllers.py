"""The pose controller: one object runs on both robots; interpolation and pose resolution."""

import numpy as np
import pytest

from felis.controllers import CONTROLLERS, PoseController, make_controller
from felis.controllers.pose import min_jerk
from felis.errors import ParameterError
from felis.hal import State
from felis.loop import run_loop
from felis.sim import MujocoRobot
from felis.spec import load_spec


def test_same_controller_object_runs_on_cat_and_arm():
    controller = PoseController("stand", duration=0.5)
    for name, tol in (("cat", 0.1), ("arm", 0.08)):
        spec = load_spec(name)
        with MujocoRobot(spec) as robot:
            report = run_loop(robot, controller, duration=1.5)
            assert report.ok and report.ticks == 150
            assert controller.spec is spec
            err = np.abs(report.final_state.q - spec.pose("stand"))
            assert err.max() < tol, f"{name}: {dict(zip(spec.names, err.round(3), strict=True))}"


def test_min_jerk_profile():
    assert min_jerk(0) == 0 and min_jerk(1) == 1 and min_jerk(0.5) == pytest.approx(0.5)
    assert min_jerk(-1) == 0 and min_jerk(2) == 1
    s = np.linspace(0, 1, 101)
    w = np.array([min_jerk(x) for x in s])
    assert np.all(np.diff(w) >= 0)
    assert np.gradient(w, s)[[0, -1]] == pytest.approx([0, 0], abs=0.02)


def _state(spec, t, q=None):
    return State(t=t, q=np.zeros(spec.n) if q is None else q, dq=np.zeros(spec.n))


def test_interpolation_and_go_to():
    spec = load_spec("arm")
    c = PoseController({"joint2": 1.0}, duration=2.0)
    c.reset(spec, _state(spec, 10.0))
    assert c(_state(spec, 10.0)).q == pytest.approx(np.zeros(5))
    assert c(_state(spec, 11.0)).q[1] == pytest.approx(0.5)
    assert c(_state(spec, 13.0)).q == pytest.approx([0, 1, 0, 0, 0])
    c.go_to("sit", _state(spec, 13.0), duration=1.0)
    assert c(_state(spec, 13.0)).q == pytest.approx([0, 1, 0, 0, 0])
    assert c(_state(spec, 14.0)).q == pytest.approx(spec.pose("sit"))


def test_hold_keeps_the_present_pose():
    spec = load_spec("cat")
    q = np.linspace(-0.5, 0.5, 12)
    c = PoseController("hold")
    c.reset(spec, _state(spec, 0.0, q))
    assert c(_state(spec, 5.0)).q == pytest.approx(q)


@pytest.mark.parametrize("pose,match", [("dance", "no pose 'dance'"), ({"neck": 1.0}, "no joint 'neck'"),
                                        ({"joint1": float("nan")}, "not finite")])
def test_bad_poses(pose, match):
    spec = load_spec("arm")
    with pytest.raises(ParameterError, match=match):
        PoseController(pose).reset(spec, _state(spec, 0.0))


def test_registry():
    assert {"hold", "stand", "sit"} <= set(CONTROLLERS)
    assert make_controller("sit") is not make_controller("sit")
    with pytest.raises(ParameterError, match="unknown controller 'fly'"):
        make_controller("fly")
    with pytest.raises(ParameterError):
        PoseController("stand", duration=-1)
