"""The stepping controller: the cat trots in place on MuJoCo without falling or wandering off."""

from dataclasses import dataclass

import mujoco
import numpy as np
import pytest

from felis.controllers.stepping import Gait, SteppingController
from felis.errors import ParameterError
from felis.hal import State
from felis.loop import run_loop
from felis.sim import MujocoRobot
from felis.spec import load_spec

TORSO = ("upper_body", "lower_body", "head", "tail")
PAIR_A = np.array([True, False, False, True])  # fl + hr


@dataclass
class Trace:
    """Per tick: time, upper-body xy (m), tilt (deg), waist height (m), foot contacts, torso on the
    floor, and the controller's gait mask and ramp level."""

    t: np.ndarray
    xy: np.ndarray
    tilt_deg: np.ndarray
    height: np.ndarray
    contacts: np.ndarray
    torso_hit: np.ndarray
    swing: np.ndarray
    amplitude: np.ndarray

    @property
    def drift(self) -> float:
        return float(np.hypot(*(self.xy - self.xy[0]).T).max())

    @property
    def after_ramp(self) -> np.ndarray:
        return self.amplitude >= 1.0

    def one_diagonal_down(self) -> float:
        c = self.contacts[self.after_ramp]
        return float(((c == PAIR_A).all(1) | (c == ~PAIR_A).all(1)).mean())

    def swing_agrees(self) -> float:
        """Fraction of ticks on which no foot the gait has lifted touches the floor."""
        m = self.after_ramp
        return float((~(self.swing[m] & self.contacts[m]).any(1)).mean())


def simulate(controller, duration: float) -> Trace:
    spec = load_spec("cat")
    rows = []
    with MujocoRobot(spec) as robot:
        m, d, root = robot.model, robot.data, robot.root_body
        floor = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor")
        torso = {robot.body_id(name) for name in TORSO}

        def monitor(state, command):
            hit = any(floor in (c.geom1, c.geom2) and
                      ({m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]} & torso) for c in d.contact[:d.ncon])
            g = controller.gait(state.t)
            rows.append((state.t, *d.xpos[root][:2], np.degrees(np.arccos(np.clip(d.xmat[root][8], -1, 1))),
                         state.height, *state.contacts, hit, *g.swing, g.amplitude))

        report = run_loop(robot, controller, duration=duration, rate_hz=100, clock="sim", monitors=[monitor])
        assert report.ok, report.stopped
    a = np.array(rows, dtype=float)
    return Trace(t=a[:, 0], xy=a[:, 1:3], tilt_deg=a[:, 3], height=a[:, 4], contacts=a[:, 5:9] > 0.5,
                 torso_hit=a[:, 9] > 0.5, swing=a[:, 10:14] > 0.5, amplitude=a[:, 14])


@pytest.fixture(scope="module")
def trot_2hz() -> Trace:
    return simulate(SteppingController(frequency_hz=2.0), duration=6.0)


def assert_upright(tr: Trace):
    assert tr.tilt_deg.max() < 20.0, f"tilted {tr.tilt_deg.max():.1f}°"
    assert tr.height.min() > 0.07, f"waist down to {tr.height.min():.3f} m"
    assert not tr.torso_hit.any(), f"torso touched the floor at t = {tr.t[tr.torso_hit][0]:.2f} s"


def test_trots_in_place_for_6s_without_falling(trot_2hz):
    assert_upright(trot_2hz)
    assert trot_2hz.drift < 0.05, f"drifted {trot_2hz.drift * 100:.1f} cm"


def test_diagonal_pairs_alternate_and_match_the_gait(trot_2hz):
    tr = trot_2hz
    assert tr.after_ramp.sum() > 400
    assert tr.one_diagonal_down() >= 0.30
    assert tr.swing_agrees() >= 0.80
    # each diagonal really carries the body on its own, in turn, several times
    c = tr.contacts[tr.after_ramp]
    for pair in (PAIR_A, ~PAIR_A):
        alone = (c == pair).all(1).astype(int)
        assert np.count_nonzero(np.diff(alone) == 1) >= 8


@pytest.mark.parametrize("frequency", [1.5, 2.5])
def test_other_frequencies_do_not_fall(frequency):
    tr = simulate(SteppingController(frequency_hz=frequency), duration=4.0)
    assert_upright(tr)
    assert tr.drift < 0.05, f"drifted {tr.drift * 100:.1f} cm"
    assert tr.one_diagonal_down() >= 0.30 and tr.swing_agrees() >= 0.80


@pytest.mark.parametrize("options", [{"lift": 0.0}, {"frequency_hz": 0.0}])
def test_standing_keeps_all_feet_down(options):
    controller = SteppingController(**options)
    tr = simulate(controller, duration=2.0)
    settled = tr.t > 0.5
    assert tr.contacts[settled].all()
    assert not tr.swing.any() and not tr.amplitude.any()
    assert not any(controller.gait(t).stepping for t in np.arange(0, 5, 0.01))
    assert tr.tilt_deg.max() < 5 and tr.drift < 0.005


@pytest.mark.parametrize("options, match", [
    ({"frequency_hz": -1.0}, "frequency"), ({"frequency_hz": 4.5}, "frequency"),
    ({"frequency_hz": float("nan")}, "finite"), ({"lift": -0.1}, "lift"), ({"lift": 1.5}, "lift"),
    ({"lift": float("inf")}, "finite"), ({"ramp_s": -1.0}, "ramp_s"), ({"start_s": -0.5}, "start_s"),
    ({"lift": "high"}, "finite"),
])
def test_bad_arguments(options, match):
    with pytest.raises(ParameterError, match=match) as err:
        SteppingController(**options)
    assert "\n" not in str(err.value)


def _state(spec, t):
    return State(t=t, q=spec.pose("stand"), dq=np.zeros(spec.n))


def test_gait_clock():
    spec = load_spec("cat")
    c = SteppingController(frequency_hz=2.0, ramp_s=1.0, start_s=1.0)
    c.reset(spec, _state(spec, 10.0))
    assert c.base_pose == pytest.approx(spec.pose("stand"))
    assert not c.gait(10.5).stepping and not c.gait(11.0).stepping  # starts at reset + start_s
    g = c.gait(11.5)
    assert isinstance(g, Gait) and g.stepping and g.amplitude == pytest.approx(0.5)
    assert g.frequency_hz == 2.0 and c.gait(13.0).amplitude == 1.0
    ts = np.arange(11.0, 14.0, 0.01)
    phases = np.array([c.gait(t).phase for t in ts])
    assert ((phases >= 0) & (phases < 1)).all()
    assert np.unwrap(phases * 2 * np.pi)[-1] / (2 * np.pi) == pytest.approx(2.0 * (ts[-1] - 11.0), abs=1e-6)
    assert list(c.gait(12.0 + 0.1 / 2.0).swing) == [True, False, False, True]  # φ = 0.1: fl + hr
    assert list(c.gait(12.0 + 0.6 / 2.0).swing) == [False, True, True, False]  # φ = 0.6: fr + hl
    assert not c.gait(12.0 + 0.45 / 2.0).swing.any()  # dwell: all feet down
    # the command stays the stand pose until the gait runs, then only leg joints move
    assert c(_state(spec, 10.9)).q == pytest.approx(spec.pose("stand"))
    moved = np.flatnonzero(np.abs(c(_state(spec, 12.05)).q - spec.pose("stand")) > 1e-9)
    assert {spec.names[i].split("_")[0] for i in moved} <= {"fl", "fr", "hl", "hr"}


def test_blends_from_the_present_pose_and_is_deterministic():
    spec = load_spec("cat")
    still = SteppingController(lift=0.0)
    still.reset(spec, State(t=0.0, q=spec.pose("sit"), dq=np.zeros(spec.n)))
    assert still(_state(spec, 0.0)).q == pytest.approx(spec.pose("sit"))
    assert still(_state(spec, 0.15)).q == pytest.approx((spec.pose("sit") + spec.pose("stand")) / 2)
    assert still(_state(spec, 0.3)).q == pytest.approx(spec.pose("stand"))
    assert still(_state(spec, 5.0)).q == pytest.approx(spec.pose("stand"))
    c = SteppingController()
    c.reset(spec, State(t=0.0, q=spec.pose("sit"), dq=np.zeros(spec.n)))
    a = [c(_state(spec, t)).q for t in np.arange(0, 3, 0.01)]
    c.reset(spec, State(t=0.0, q=spec.pose("sit"), dq=np.zeros(spec.n)))
    b = [c(_state(spec, t)).q for t in np.arange(0, 3, 0.01)]
    assert np.array_equal(a, b)
    with pytest.raises(RuntimeError):
        SteppingController()(_state(spec, 0.0))
