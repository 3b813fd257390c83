"""The keyframe player (`felis.controllers.keyframes`): minimum-jerk moves through poses, as a pure function of time."""

from __future__ import annotations

import numpy as np
import pytest

from felis.controllers import make_controller
from felis.controllers.keyframes import KeyframeController, peak_speed
from felis.errors import ParameterError
from felis.hal import State
from felis.spec import load_spec


def _state(t: float, q: np.ndarray) -> State:
    return State(t=t, q=q, dq=np.zeros_like(q), effort=np.zeros_like(q))


def test_keyframes_are_reached_at_rest_in_order_then_held():
    spec = load_spec("arm")
    start = np.array([0.3, -0.2, 0.1, 0.0, 0.005])
    a, b = spec.pose("stand"), spec.pose("sit")
    ctl = make_controller("keyframes", poses=[("stand", a), ("sit", b)], durations=[1.0, 0.5])
    t0 = 10.0
    ctl.reset(spec, _state(t0, start))
    q = lambda t: ctl(_state(t0 + t, start)).q  # noqa: E731
    assert np.allclose(q(0.0), start) and np.allclose(q(1.0), a) and np.allclose(q(1.5), b)
    assert np.allclose(q(0.5), (start + a) / 2) and np.allclose(q(1.25), (a + b) / 2)  # w(½) = ½
    assert np.allclose(q(7.0), b)  # held after the last
    h = 1e-4
    for t in (0.0, 1.0, 1.5):  # at rest at each keyframe: zero velocity
        assert np.abs(q(t + h) - q(max(t - h, 0.0))).max() / (2 * h) < 1e-3
    ts = np.arange(0.0, 1.0, 1e-3)
    v = np.abs(np.diff([q(t) for t in ts], axis=0)).max(axis=0) / 1e-3
    assert np.allclose(v, peak_speed(a - start, 1.0), rtol=1e-3, atol=1e-9)  # 1.875 |Δq| / T
    assert ctl.summary()["keyframes"] == ["stand", "sit"]


@pytest.mark.parametrize("poses, durations, expect", [
    ([], [], "plays poses"),
    ([("a", np.zeros(5))], [1.0, 2.0], "1 keyframe(s) need 1 duration(s), got 2"),
    ([("a", np.zeros(5))], [0.0], "must be > 0 s"),
])
def test_bad_keyframes_are_refused(poses, durations, expect):
    with pytest.raises(ParameterError, match=expect.replace("(", r"\(").replace(")", r"\)")):
        KeyframeController(poses, durations)


def test_keyframes_of_another_robot_are_refused_at_reset():
    ctl = KeyframeController([("a", np.zeros(5))], [1.0])
    spec = load_spec("cat")
    with pytest.raises(ParameterError, match="all 12 joints of the cat"):
        ctl.reset(spec, _state(0.0, np.zeros(spec.n)))
